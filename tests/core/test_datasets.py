"""Render-job builders (canonical set, random-poses baseline) and the toy image collection."""
from __future__ import annotations

import json
import time

import cv2
import numpy as np
import pytest

from bat3r_core.datasets import canonical_jobs, random_pose_jobs, toy_collection_jobs
from bat3r_core.generated_collections import TOY_TEST_SEED_OFFSET, make_toy_collection
from bat3r_core.poses import sample_random_poses
from bat3r_core.render.config import RenderConfig
from bat3r_core.render.jobs import job_to_dict, jobs_from_table, jobs_to_table
from bat3r_core.toy import TOY_BODY_FRAME, TOY_COATS
from bat3r_core.viewpoints import AnglePrior, CameraPriorConfig, spherical_from_camera, view_type


def _rows(jobs):
    return [job_to_dict(j) for j in jobs]


def _projected_inside(job, verts) -> float:
    """Fraction of vertices that project inside the image."""
    uv, z = job.camera.project(verts)
    inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= job.camera.width) & (uv[:, 1] >= 0) & \
        (uv[:, 1] <= job.camera.height)
    return float(inside.mean())


def test_canonical_jobs_are_seeded_and_follow_the_schema(toy_rig):
    a = canonical_jobs(toy_rig, 12, seed=3, body_frame_spec=TOY_BODY_FRAME, resolution=64, num_textures=4,
                       num_envmaps=2)
    b = canonical_jobs(toy_rig, 12, seed=3, body_frame_spec=TOY_BODY_FRAME, resolution=64, num_textures=4,
                       num_envmaps=2)
    c = canonical_jobs(toy_rig, 12, seed=4, body_frame_spec=TOY_BODY_FRAME, resolution=64, num_textures=4,
                       num_envmaps=2)
    assert _rows(a) == _rows(b)
    assert _rows(a) != _rows(c)
    back = jobs_from_table(jobs_to_table(a))
    assert _rows(back) == _rows(a)
    assert len({j.sample_id for j in a}) == 12
    for j in a:
        assert j.view_kind == "canonical" and not np.any(j.excess_rotations)
        assert 0 <= j.texture_id < 4 and 0 <= j.envmap_id < 2 and 0 <= j.envmap_rotation < 2 * np.pi
        assert (j.camera.width, j.camera.height) == (64, 64)
        assert _projected_inside(j, toy_rig.rest_vertices) == 1.0  # framed with a margin
        # the view type recorded is the camera's azimuth class in the body frame
        from bat3r_core.datasets import rig_body_frame

        frame = rig_body_frame(toy_rig, toy_rig.rest_joint_positions, TOY_BODY_FRAME)
        assert view_type(spherical_from_camera(frame, j.camera).azimuth_deg) == j.view_type
    assert {j.envmap_id for j in canonical_jobs(toy_rig, 5, 0, TOY_BODY_FRAME)} == {-1}  # no maps: procedural sky


def test_canonical_jobs_normal_prior_and_margins(toy_rig):
    prior = CameraPriorConfig(distribution="normal", per_view_type=None, elevation=AnglePrior(loc=10.0, scale=1.0),
                              roll=AnglePrior(loc=0.0, scale=0.5))
    jobs = canonical_jobs(toy_rig, 40, seed=1, body_frame_spec=TOY_BODY_FRAME, prior=prior, resolution=32)
    from bat3r_core.datasets import rig_body_frame

    frame = rig_body_frame(toy_rig, toy_rig.rest_joint_positions, TOY_BODY_FRAME)
    elev = np.array([spherical_from_camera(frame, j.camera).elevation_deg for j in jobs])
    assert abs(elev.mean() - 10.0) < 0.6 and elev.std() < 1.6
    with pytest.raises(ValueError, match="n must be an int >= 1, got 0"):
        canonical_jobs(toy_rig, 0, 0, TOY_BODY_FRAME)
    with pytest.raises(ValueError, match="body frame spec needs 'horizontal'"):
        canonical_jobs(toy_rig, 2, 0, {"origin": "spine.2", "forward": ("spine.1", "spine.2")})
    with pytest.raises(KeyError, match="no joint named 'pelvis'"):
        canonical_jobs(toy_rig, 2, 0, dict(TOY_BODY_FRAME, origin="pelvis"))


def test_random_pose_jobs_use_the_baseline_sampler(toy_rig):
    from bat3r_core.datasets import _skin

    jobs = random_pose_jobs(toy_rig, 6, seed=11, body_frame_spec=TOY_BODY_FRAME, resolution=48, num_textures=2)
    theta, _ = sample_random_poses(toy_rig, 6, 11)
    np.testing.assert_array_equal(np.stack([j.excess_rotations for j in jobs]), theta)
    assert _rows(jobs) == _rows(random_pose_jobs(toy_rig, 6, 11, TOY_BODY_FRAME, resolution=48, num_textures=2))
    verts, _ = _skin(toy_rig, theta)
    for j, v in zip(jobs, verts):
        assert j.view_kind == "random_pose" and j.envmap_id == -1
        assert _projected_inside(j, v) == 1.0  # each camera frames its own posed mesh


def test_toy_collection_jobs_have_upright_yaw_and_natural_poses():
    jobs, fams, verts = toy_collection_jobs(8, seed=2, resolution=32)
    assert len(jobs) == len(fams) == 8 and verts.shape[0] == 8
    for j, v in zip(jobs, verts):
        r = j.global_rotation
        np.testing.assert_allclose(r[:, 1], [0.0, 1.0, 0.0], atol=1e-12)  # a yaw keeps the up axis
        assert j.view_kind == "collection" and 0 <= j.texture_id < len(TOY_COATS)
        assert _projected_inside(j, v) == 1.0
    jobs2, _, _ = toy_collection_jobs(8, seed=2, resolution=32)
    assert _rows(jobs) == _rows(jobs2)


@pytest.mark.blender
def test_toy_collection_on_disk_with_separate_ground_truth(tmp_path):
    cfg = RenderConfig(resolution=32, samples=2)
    out = tmp_path / "toy"
    t0 = time.perf_counter()
    coll = make_toy_collection(out, 4, seed=5, resolution=48, config=cfg)
    first = time.perf_counter() - t0
    assert not coll.reused and len(coll.sample_ids) == 4
    assert coll.ground_truth_dir == tmp_path / "toy_ground_truth"
    images = sorted(p.name for p in (out / "images").iterdir())
    masks = sorted(p.name for p in (out / "masks").iterdir())
    assert images == masks == sorted(f"{s}.png" for s in coll.sample_ids)
    # the collection folder holds images, masks and a stamp, nothing of the ground truth
    assert sorted(p.name for p in out.iterdir()) == ["collection.json", "images", "masks"]
    assert "theta" not in (out / "collection.json").read_text()
    with np.load(coll.ground_truth_dir / "ground_truth.npz", allow_pickle=False) as gt:
        assert list(gt["sample_id"]) == list(coll.sample_ids)
        assert gt["excess_rotations"].shape == (4, 27, 3) and gt["posed_vertices"].shape[0] == 4
        assert set(gt["pose_family"]) <= {"stand", "walk", "trot", "gallop", "graze", "rear", "lie", "turn"}
        for k, sid in enumerate(coll.sample_ids):
            img = cv2.imread(str(out / "images" / f"{sid}.png"))
            mask = cv2.imread(str(out / "masks" / f"{sid}.png"), cv2.IMREAD_GRAYSCALE) > 127
            assert img.shape == (48, 48, 3) and mask.sum() > 50
            # the hidden posed vertices project onto the mask
            K, R, t = gt["K"][k], gt["camera_rotation"][k], gt["camera_translation"][k]
            cam = gt["posed_vertices"][k] @ R.T + t
            uv = cam[:, :2] / cam[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
            cols, rows = np.clip(np.floor(uv).astype(int), 0, 47).T
            near = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0  # thin legs at 48 px
            assert near[rows, cols].mean() > 0.97
    # cached: same parameters reuse it, other parameters regenerate it
    t0 = time.perf_counter()
    again = make_toy_collection(out, 4, seed=5, resolution=48, config=cfg)
    assert again.reused and again.sample_ids == coll.sample_ids and time.perf_counter() - t0 < first / 3
    stamp = json.loads((coll.ground_truth_dir / "collection.json").read_text())
    assert stamp["params"]["seed"] == 5 and stamp["params"]["n"] == 4
    other = make_toy_collection(out, 3, seed=6, resolution=48, config=cfg)
    assert not other.reused and len(other.sample_ids) == 3
    assert len(list((out / "images").iterdir())) == 3
    with pytest.raises(ValueError, match="must be outside the collection folder"):
        make_toy_collection(out, 2, ground_truth_dir=out / "gt")
    assert TOY_TEST_SEED_OFFSET != 0


def _renamed(rig):
    """The toy with other joint names (``spine.2`` → ``Spine_2``, ``thigh.L`` → ``Thigh_L``): not the toy's rig."""
    import dataclasses

    names = tuple(n[0].upper() + n[1:].replace(".", "_") for n in rig.joint_names)
    return dataclasses.replace(rig, name="critter", joint_names=names)


CRITTER_FRAME = {"origin": "Spine_2", "forward": ("Spine_1", "Spine_2"), "horizontal": ("Thigh_L", "Thigh_R")}


def test_collection_jobs_pose_any_rig_with_random_poses(toy_rig):
    from bat3r_core.datasets import _skin, collection_jobs

    rig = _renamed(toy_rig)
    jobs, fams, verts = collection_jobs(rig, 6, seed=9, body_frame_spec=CRITTER_FRAME, resolution=32, num_textures=3,
                                        prefix="critter")
    theta, _ = sample_random_poses(rig, 6, 9)
    np.testing.assert_array_equal(np.stack([j.excess_rotations for j in jobs]), theta)  # the baseline sampler
    assert fams == ["random"] * 6 and [j.sample_id for j in jobs] == [f"critter-{i:05d}" for i in range(6)]
    assert {j.texture_id for j in jobs} <= {0, 1, 2} and {j.envmap_id for j in jobs} == {-1}
    for j, v in zip(jobs, verts):
        np.testing.assert_allclose(j.global_rotation[:, 1], [0.0, 1.0, 0.0], atol=1e-12)  # a yaw about +Y
        assert _projected_inside(j, v) == 1.0  # framed around its own posed mesh
    posed, _ = _skin(rig, theta, np.stack([j.global_rotation for j in jobs]))
    np.testing.assert_allclose(verts, posed)
    assert _rows(jobs) == _rows(collection_jobs(rig, 6, 9, CRITTER_FRAME, 32, num_textures=3, prefix="critter")[0])
    with pytest.raises(ValueError, match=r"pose_sampler 'toy_natural' poses the toy's 27 joints .* use pose_sampler "
                                         r"'random'"):
        collection_jobs(rig, 2, 0, CRITTER_FRAME, pose_sampler="toy_natural")
    with pytest.raises(KeyError, match="no joint named 'spine.2'"):
        collection_jobs(rig, 2, 0, TOY_BODY_FRAME)
    with pytest.raises(ValueError, match=r"pose_sampler must be one of \['random', 'toy_natural'\], got 'walk'"):
        collection_jobs(rig, 2, 0, CRITTER_FRAME, pose_sampler="walk")


def test_make_collection_needs_an_existing_asset_and_a_body_frame(tmp_path):
    from bat3r_core.generated_collections import make_collection

    with pytest.raises(FileNotFoundError, match=r"asset .*missing.glb does not exist"):
        make_collection(tmp_path / "c", 2, asset=tmp_path / "missing.glb", body_frame=CRITTER_FRAME)
    (tmp_path / "a.glb").write_bytes(b"glTF")
    with pytest.raises(ValueError, match=r"body_frame: a generated collection of a.glb needs the category's"):
        make_collection(tmp_path / "c", 2, asset=tmp_path / "a.glb")


def test_collection_jobs_draw_the_weighted_pose_families(toy_rig):
    from bat3r_core.datasets import collection_jobs

    jobs, fams, _ = collection_jobs(toy_rig, 40, 5, TOY_BODY_FRAME, 32, pose_sampler="toy_natural",
                                    families=("lie", "rear", "stand"), family_weights=(1.0, 1.0, 0.0))
    assert set(fams) == {"lie", "rear"} and len(jobs) == 40
    with pytest.raises(ValueError, match=r"family_weights: only pose_sampler 'toy_natural' has pose families"):
        collection_jobs(toy_rig, 2, 0, TOY_BODY_FRAME, 32, pose_sampler="random", family_weights=(1.0,))


def test_make_collection_checks_pose_families_before_rendering(tmp_path):
    from bat3r_core.generated_collections import make_collection

    with pytest.raises(ValueError, match=r"pose_families: unknown pose families \['dance'\]"):
        make_collection(tmp_path / "c", 2, pose_families={"dance": 1.0})
    with pytest.raises(ValueError, match=r"pose_families: only pose_sampler 'toy_natural' has pose families"):
        make_collection(tmp_path / "c", 2, pose_sampler="random", pose_families={"lie": 1.0})
    with pytest.raises(ValueError, match=r"pose_families: expected a non-empty mapping"):
        make_collection(tmp_path / "c", 2, pose_families={})
    assert not (tmp_path / "c").exists()  # nothing rendered, nothing deleted


@pytest.mark.blender
def test_a_collection_with_pose_families_is_rendered_from_them_and_cached_apart(tmp_path):
    from bat3r_core.generated_collections import make_collection

    cfg = RenderConfig(resolution=32, samples=1)
    wide = make_collection(tmp_path / "wide", 4, seed=5, resolution=32, config=cfg,
                           pose_families={"lie": 1.0, "rear": 1.0})
    with np.load(wide.ground_truth_dir / "ground_truth.npz", allow_pickle=False) as gt:
        assert set(gt["pose_family"]) <= {"lie", "rear"} and len(gt["sample_id"]) == 4
    stamp = json.loads((wide.ground_truth_dir / "collection.json").read_text())
    assert stamp["params"]["pose_families"] == {"lie": 1.0, "rear": 1.0}
    assert make_collection(tmp_path / "wide", 4, seed=5, resolution=32, config=cfg,
                           pose_families={"lie": 1.0, "rear": 1.0}).reused
    # other frequencies are another collection: rendered again, not the cached one
    other = make_collection(tmp_path / "wide", 4, seed=5, resolution=32, config=cfg,
                            pose_families={"lie": 1.0, "rear": 0.0})
    assert not other.reused
    with np.load(other.ground_truth_dir / "ground_truth.npz", allow_pickle=False) as gt:
        assert set(gt["pose_family"]) == {"lie"}


@pytest.mark.blender
def test_a_collection_that_cannot_be_posed_leaves_the_cached_one_in_place(tmp_path):
    from bat3r_core.generated_collections import make_collection

    cfg = RenderConfig(resolution=32, samples=1)
    first = make_collection(tmp_path / "c", 2, seed=1, resolution=32, config=cfg)
    before = sorted(p.name for p in first.images_dir.iterdir())
    with pytest.raises(ValueError, match=r"n must be an int >= 1, got 0"):
        make_collection(tmp_path / "c", 0, seed=1, resolution=32, config=cfg)
    assert sorted(p.name for p in first.images_dir.iterdir()) == before and len(before) == 2
    assert (first.ground_truth_dir / "ground_truth.npz").is_file()
    assert make_collection(tmp_path / "c", 2, seed=1, resolution=32, config=cfg).reused
