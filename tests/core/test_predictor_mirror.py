"""Left-right mirroring of training samples (bat3r_core.predictor.mirror): a mirrored sample equals the exact labels
of the mirrored pose seen by the mirrored camera, ray-cast independently; asymmetric rigs are refused."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from bat3r_core.cameras import PinholeCamera, look_at
from bat3r_core.config_utils import ConfigError
from bat3r_core.pointmaps import dual_point_maps
from bat3r_core.poses import sample_toy_natural_poses
from bat3r_core.predictor.config import TrainConfig
from bat3r_core.predictor.mirror import (CanonicalMirror, canonical_mirror_for_rig, mirror_decisions, mirror_samples,
                                         symmetry_error)
from bat3r_core.rig import find_left_right_pairs
from bat3r_core.skinning import skin
from bat3r_core.toy import TOY_BODY_FRAME, build_toy_rig

RES = 48


@pytest.fixture(scope="module")
def toy():
    return build_toy_rig()


def _posed(rig, theta: np.ndarray) -> np.ndarray:
    return skin(rig.tensors(dtype=torch.float64), torch.as_tensor(theta, dtype=torch.float64)[None]).vertices[0].numpy()


def _mirrored_pose(rig, theta: np.ndarray) -> np.ndarray:
    """The pose whose skinned mesh is the x-reflection of ``theta``'s (toy: lateral axis x, rest frames aligned with
    the canonical axes): left and right joints swap, and R -> M R M for M = diag(-1, 1, 1), i.e. the axis-angle
    (a, b, c) -> (a, -b, -c)."""
    assert np.allclose(rig.rest_transforms[:, :3, :3], np.eye(3))
    partner = np.arange(rig.num_joints)
    for left, right in find_left_right_pairs(rig.joint_names, rig.rest_joint_positions):
        partner[left], partner[right] = right, left
    out = np.empty_like(theta)
    out[partner] = theta * np.array([1.0, -1.0, -1.0])
    return out


def _camera(rig, azimuth_deg: float) -> PinholeCamera:
    v = rig.rest_vertices
    centre = 0.5 * (v.min(0) + v.max(0))
    a = np.radians(azimuth_deg)
    eye = centre + 4.0 * np.array([np.sin(a), 0.25, np.cos(a)])
    R, t = look_at(eye, centre, np.array([0.0, 1.0, 0.0]))
    f = 0.5 * RES / np.tan(np.radians(20.0))
    return PinholeCamera(f, f, RES / 2, RES / 2, RES, RES, R, t)


def _batch(maps, object_depth: float | None = None):
    depth = maps.object_depth if object_depth is None else object_depth
    P = np.where(maps.occupancy[..., None], maps.P - np.array([0.0, 0.0, depth]), 0.0)
    Q = np.where(maps.occupancy[..., None], maps.Q, 0.0)
    features = torch.from_numpy(np.random.default_rng(0).random((1, 3, RES, RES)).astype(np.float32))
    occ = maps.occupancy[None].copy()
    return (features, torch.from_numpy(occ[..., 0].copy()), torch.from_numpy(Q[None].astype(np.float32)),
            torch.from_numpy(P[None].astype(np.float32)), torch.from_numpy(occ))


def test_the_toy_is_symmetric_about_its_body_frame_and_its_plane_is_x_equals_zero(toy):
    mirror = canonical_mirror_for_rig(toy, TOY_BODY_FRAME)
    assert abs(abs(mirror.normal[0]) - 1.0) < 1e-6
    assert abs(mirror.origin[0]) < 1e-6
    err = symmetry_error(toy.rest_vertices, toy.faces, mirror)
    assert np.median(err) < 1e-3 and np.percentile(err, 95) < 5e-3  # metres: on the surface (to its tessellation)
    np.testing.assert_allclose(mirror.reflect(mirror.reflect(toy.rest_vertices)), toy.rest_vertices, atol=1e-12)


def test_an_asymmetric_rest_mesh_is_refused_with_the_measured_asymmetry(toy):
    v = toy.rest_vertices.copy()
    v[v[:, 0] > 0] += np.array([0.0, 0.0, 0.08])  # the left half shifted 8 cm forwards
    lopsided = dataclasses.replace(toy, rest_vertices=v)
    with pytest.raises(ConfigError, match=r"categories\.lopsided.*symmetric.*cm"):
        canonical_mirror_for_rig(lopsided, TOY_BODY_FRAME, source="categories.lopsided")


SHARED = Path(__file__).resolve().parents[3] / "shared" / "assets"


@pytest.mark.skipif(not SHARED.is_dir(), reason=f"the shared third-party assets are not in {SHARED}")
@pytest.mark.parametrize("path, scale", [("fox/Fox.glb", 0.01), ("dog_puppy/scene.gltf", 1.0)], ids=["fox", "dog"])
def test_the_shared_third_party_rigs_pass_the_symmetry_check_about_their_proposed_body_frame(path, scale):
    """Users' rigs (the Khronos Fox in centimetres, the seam-split Sketchfab dog) with ``body_frame: auto``."""
    from bat3r_core.assets import propose_body_frame
    from bat3r_core.rig_io import load_rig

    rig = load_rig(SHARED / path, scale=scale)
    p = propose_body_frame(rig)
    mirror = canonical_mirror_for_rig(rig, {"origin": p.origin, "forward": p.forward, "horizontal": p.horizontal})
    assert abs(mirror.normal[0]) > 0.999  # their lateral axis is x, as the canonical convention says
    v = rig.rest_vertices
    assert np.percentile(symmetry_error(v, rig.faces, mirror), 95) < 1e-3 * np.linalg.norm(np.ptp(v, axis=0))


@pytest.mark.parametrize("azimuth", [35.0, 160.0])
def test_a_mirrored_sample_equals_the_labels_of_the_mirrored_pose_through_the_mirrored_camera(toy, azimuth):
    thetas, families = sample_toy_natural_poses(12, seed=5)
    theta = thetas[families.index("turn")]  # spine and neck yawed to one side
    cam = _camera(toy, azimuth)
    maps = dual_point_maps(_posed(toy, theta), toy.rest_vertices, toy.faces, cam)
    # the mirror scene, built independently: reflected world (x -> -x, the toy's sagittal plane), mirrored pose,
    # camera x_cam' = D x_cam for D = diag(-1, 1, 1): R' = D R M, t' = D t
    D = np.diag([-1.0, 1.0, 1.0])
    cam_m = PinholeCamera(cam.fx, cam.fy, cam.cx, cam.cy, RES, RES, D @ cam.R @ D, D @ cam.t)
    truth = dual_point_maps(_posed(toy, _mirrored_pose(toy, theta)), toy.rest_vertices, toy.faces, cam_m)
    assert abs(truth.object_depth - maps.object_depth) < 5e-3

    mirror = canonical_mirror_for_rig(toy, TOY_BODY_FRAME)
    f, m, q, p, occ = mirror_samples(*_batch(maps), np.array([True]), mirror)
    _, _, q_truth, p_truth, occ_truth = _batch(truth, object_depth=maps.object_depth)  # same reference depth
    a, b = occ[0, ..., 0].numpy(), occ_truth[0, ..., 0].numpy()
    assert (a & b).sum() / (a | b).sum() > 0.97  # silhouettes: the tessellation is symmetric only to ~1 mm
    assert torch.equal(m[0], occ[0, ..., 0])
    both = occ[0].numpy() & occ_truth[0].numpy()
    p_err = np.linalg.norm(p[0].numpy()[both] - p_truth[0].numpy()[both], axis=-1)
    q_err = np.linalg.norm(q[0].numpy()[both] - q_truth[0].numpy()[both], axis=-1)
    assert np.median(p_err) < 3e-3 and np.median(q_err) < 3e-3  # metres
    # without the canonical reflection the labels are the other side's: tens of centimetres off
    q_flipped_only = torch.flip(_batch(maps)[2], dims=[2])[0].numpy()
    assert np.median(np.linalg.norm(q_flipped_only[both] - q_truth[0].numpy()[both], axis=-1)) > 0.05
    np.testing.assert_array_equal(f[0].numpy(), torch.flip(_batch(maps)[0], dims=[-1])[0].numpy())


def test_samples_not_picked_are_untouched_and_unoccupied_entries_stay_zero(toy):
    mirror = canonical_mirror_for_rig(toy, TOY_BODY_FRAME)
    maps = dual_point_maps(_posed(toy, np.zeros((toy.num_joints, 3))), toy.rest_vertices, toy.faces, _camera(toy, 80))
    one = _batch(maps)
    two = tuple(torch.cat([t, t]) for t in one)
    f, m, q, p, occ = mirror_samples(*two, np.array([False, True]), mirror)
    for got, original in zip((f, m, q, p, occ), two):
        assert torch.equal(got[0], original[0])
    assert torch.equal(two[2], torch.cat([one[2], one[2]]))  # inputs are not modified in place
    assert float(q[1][~occ[1]].abs().max()) == 0.0 and float(p[1][~occ[1]].abs().max()) == 0.0
    with pytest.raises(ValueError, match="which"):
        mirror_samples(*two, np.array([True]), mirror)


def test_mirror_decisions_are_a_function_of_seed_step_and_micro_batch():
    a = mirror_decisions(3, 17, 0, 4096, 0.5)
    np.testing.assert_array_equal(a, mirror_decisions(3, 17, 0, 4096, 0.5))
    assert not np.array_equal(a, mirror_decisions(3, 18, 0, 4096, 0.5))
    assert abs(a.mean() - 0.5) < 0.03
    assert not mirror_decisions(3, 17, 0, 64, 0.0).any()
    with pytest.raises(ConfigError, match="mirror_probability"):
        TrainConfig(mirror_probability=1.5)
    with pytest.raises(ConfigError, match="unit"):
        CanonicalMirror(origin=(0.0, 0.0, 0.0), normal=(2.0, 0.0, 0.0))


# ------------------------------------------------------------------------------------------------ the trainer
def _trainer_inputs(tmp_path):
    from bat3r_core.predictor.config import ModelConfig
    from bat3r_core.predictor.synthetic import write_synthetic_shards

    folder = tmp_path / "shards"
    write_synthetic_shards(folder, 8, 16, shard_size=4, seed=2)
    model = ModelConfig(resolution=16, layers=4, in_channels=3, base_channels=8, depth=2, two_stage=False)
    train = TrainConfig(steps=6, batch_size=4, lr=3e-3, warmup_steps=1, checkpoint_every=2, seed=3,
                        shuffle_shards=1, log_every=1, mirror_probability=0.5)
    return folder, model, train, CanonicalMirror(origin=(0.0, 0.0, 0.0), normal=(1.0, 0.0, 0.0))


def test_training_with_mirroring_resumes_exactly_and_needs_the_mirror_plane(tmp_path):
    from bat3r_core.predictor.data import ShardDataset
    from bat3r_core.predictor.train import Trainer

    shards, model, train, mirror = _trainer_inputs(tmp_path)
    full = Trainer(ShardDataset(shards), model, train, tmp_path / "full", device="cpu", mirror=mirror)
    full.train()
    killed = Trainer(ShardDataset(shards), model, train, tmp_path / "killed", device="cpu", mirror=mirror)
    killed.train(until_step=3)  # checkpoint at step 2
    resumed = Trainer(ShardDataset(shards), model, train, tmp_path / "killed", device="cpu", mirror=mirror)
    assert resumed.step == 2
    resumed.train()
    ref, got = full.model.state_dict(), resumed.model.state_dict()
    assert all(torch.equal(ref[k], got[k]) for k in ref)  # the same samples were mirrored at every step
    plain = Trainer(ShardDataset(shards), model, dataclasses.replace(train, mirror_probability=0.0),
                    tmp_path / "plain", device="cpu")
    plain.train()
    assert not all(torch.equal(ref[k], plain.model.state_dict()[k]) for k in ref)  # mirroring changed training
    with pytest.raises(ValueError, match="mirror: train_config.mirror_probability = 0.5 needs"):
        Trainer(ShardDataset(shards), model, train, tmp_path / "none", device="cpu")
