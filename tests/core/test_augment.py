"""Viewpoint augmentation: view-type routing, per-type camera sampling and render-job rows."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from bat3r_core.cameras import PinholeCamera
from bat3r_core.render.jobs import JOB_SCHEMA, job_to_dict, jobs_to_table
from bat3r_core.skinning import skin
from bat3r_core.toy import TOY_BODY_FRAME, build_toy_rig
from bat3r_core.viewpoints import (VIEW_TYPES, SphericalCoords, body_frame, identity_frame, pose_from_spherical,
                                   spherical_from_camera)
from bat3r_core.fitting.augment import (AZIMUTH_RANGES, VIEW_TRANSITIONS, AugmentConfig, base_view_type,
                                        plan_views, plan_views_for_fits, sample_extra_view_types)


@pytest.fixture(scope="module")
def toy_scene():
    rig = build_toy_rig()
    theta = np.zeros((1, rig.num_joints, 3))
    theta[0, rig.joint_index("neck.1")] = [0.5, 0.0, 0.0]
    out = skin(rig.tensors(dtype=torch.float64), torch.as_tensor(theta))
    idx = {n: i for i, n in enumerate(rig.joint_names)}
    frame = body_frame(out.joints[0].numpy(), idx[TOY_BODY_FRAME["origin"]],
                       tuple(idx[n] for n in TOY_BODY_FRAME["forward"]),
                       tuple(idx[n] for n in TOY_BODY_FRAME["horizontal"]))
    return rig, theta[0], out.vertices[0].numpy(), frame


def _camera(frame, azimuth, elevation=5.0, roll=0.0):
    R, t = pose_from_spherical(frame, SphericalCoords(azimuth, elevation, roll, 6.0))
    return PinholeCamera(150.0, 150.0, 64.0, 64.0, 128, 128, R, t)


def test_transition_table():
    assert VIEW_TRANSITIONS["front"] == {"front": 0.05, "rear": 0.15, "right": 0.40, "left": 0.40}
    for base, row in VIEW_TRANSITIONS.items():
        assert set(row) == set(VIEW_TYPES) and min(row.values()) > 0 and sum(row.values()) == pytest.approx(1)
        assert row[base] == min(row.values())  # repeating the base type is the least likely
    for lateral in ("left", "right"):
        assert VIEW_TRANSITIONS[lateral]["front"] > VIEW_TRANSITIONS[lateral]["left" if lateral == "right" else "right"]
    with pytest.raises(ValueError, match=r"transitions\['front'\] must give every view type a probability > 0"):
        AugmentConfig(transitions={**VIEW_TRANSITIONS, "front": {"front": 0.0, "rear": 0.2, "left": 0.4,
                                                                 "right": 0.4}})


def test_base_view_type_from_rotation_only():
    frame = identity_frame()
    for az, expected in ((0.0, "front"), (20.0, "front"), (90.0, "left"), (-60.0, "right"), (170.0, "rear"),
                         (-175.0, "rear")):
        cam = _camera(frame, az, elevation=15.0, roll=10.0)
        vtype, got = base_view_type(frame, cam.R)
        assert vtype == expected
        assert got == pytest.approx(az, abs=1e-6)


def test_number_and_types_of_extra_views_follow_the_tables():
    config = AugmentConfig()
    rng = np.random.default_rng(8080)
    n = 6000
    for base, p_two in (("left", 0.65), ("right", 0.65), ("front", 0.35), ("rear", 0.35)):
        draws = [sample_extra_view_types(base, config, rng) for _ in range(n)]
        counts = np.bincount([len(d) for d in draws], minlength=3)
        assert counts[0] == 0 and counts[1] + counts[2] == n
        assert counts[2] / n == pytest.approx(p_two, abs=0.025)
        types = [t for d in draws for t in d]
        for t in VIEW_TYPES:
            assert types.count(t) / len(types) == pytest.approx(VIEW_TRANSITIONS[base][t], abs=0.025)


def test_plan_views_jobs(toy_scene):
    rig, theta, verts, frame = toy_scene
    cam = _camera(frame, 95.0)  # a left lateral base view
    config = AugmentConfig(num_textures=4, num_envmaps=3)
    jobs = plan_views("img-7", theta, verts, frame, cam, config, np.random.default_rng(31))
    assert jobs[0].sample_id == "img-7-est" and jobs[0].view_kind == "estimated" and jobs[0].view_type == "left"
    # the estimated view: the recovered camera's direction, framed like every canonical render (optical axis through
    # the body origin, principal point where the framing centres the mesh), not the recovered intrinsics
    est = jobs[0].camera
    a, b = spherical_from_camera(frame, est), spherical_from_camera(frame, cam)
    assert (a.azimuth_deg, a.elevation_deg, a.roll_deg) == pytest.approx((b.azimuth_deg, b.elevation_deg,
                                                                           b.roll_deg), abs=1e-6)
    uv, _ = est.project(frame.origin[None])
    assert uv[0] == pytest.approx([est.cx, est.cy], abs=1e-6)
    box = est.project(verts)[0]
    assert (box.min(0) + box.max(0)) / 2 == pytest.approx([64.0, 64.0], abs=1e-6)  # centred by the principal point
    assert abs(est.cy - cam.cy) > 1.0  # the recovered camera (centred principal point) framed it elsewhere
    recovered = plan_views("img-7", theta, verts, frame, cam,
                           AugmentConfig(num_textures=4, num_envmaps=3, estimated_framing="recovered"),
                           np.random.default_rng(31))
    assert recovered[0].camera is cam
    with pytest.raises(ValueError, match="estimated_framing must be 'canonical' or 'recovered', got 'photo'"):
        AugmentConfig(estimated_framing="photo")
    aug = jobs[1:]
    assert 1 <= len(aug) <= 2 and all(j.view_kind == "augmented" and j.source_id == "img-7" for j in aug)
    for j in jobs:
        c = spherical_from_camera(frame, j.camera)
        if j.view_kind == "augmented":
            lo, hi = AZIMUTH_RANGES[j.view_type]
            assert lo <= (c.azimuth_deg if c.azimuth_deg >= lo else c.azimuth_deg + 360) < hi
        # the mesh is framed: every vertex inside the image with at least 10 % margin on the tight side
        uv, depth = j.camera.project(verts)
        assert np.all(depth > 0)
        gap = np.minimum(uv.min(0), [128, 128] - uv.max(0)) / 128
        assert gap.min() >= 0.1 - 1e-6 and gap.min() <= 0.25 + 1e-6
        assert j.problems(rig.num_joints) == []
        assert 0 <= j.texture_id < 4 and 0 <= j.envmap_id < 3
    rows = [job_to_dict(j) for j in jobs]
    assert list(rows[0]) == JOB_SCHEMA.names
    assert jobs_to_table(jobs).schema.equals(JOB_SCHEMA)
    again = plan_views("img-7", theta, verts, frame, cam, config, np.random.default_rng(31))
    assert [job_to_dict(j) for j in again] == rows
    with pytest.raises(TypeError, match="camera must be a PinholeCamera"):
        plan_views("x", theta, verts, frame, None, config, np.random.default_rng(0))


def test_augmented_view_type_balance_over_many_fits(toy_scene):
    """From lateral bases the augmentation mostly produces front/rear views, as the table says."""
    _, theta, verts, frame = toy_scene
    config = AugmentConfig(include_estimated=False, width=64, height=64)
    rng = np.random.default_rng(99)
    types = []
    for k in range(150):
        jobs = plan_views(f"s{k}", theta, verts, frame, _camera(frame, -90.0), config, rng)
        types += [j.view_type for j in jobs]
        assert all(j.camera.width == 64 for j in jobs)
    share = {t: types.count(t) / len(types) for t in VIEW_TYPES}
    assert share["front"] + share["rear"] > 0.65 and share["right"] < 0.12


def test_plan_views_for_fit_rows(toy_scene):
    rig, theta, _, frame = toy_scene
    cam = _camera(frame, 175.0)
    ok = {"sample_id": "a", "status": "ok", "excess_rotations": theta.reshape(-1).tolist(), "fx": cam.fx,
          "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "width": cam.width, "height": cam.height,
          "camera_rotation": cam.R.reshape(-1).tolist(), "camera_translation": cam.t.tolist()}
    failed = {**ok, "sample_id": "b", "status": "too_few_points"}
    no_cam = {**ok, "sample_id": "c", "camera_translation": [np.nan] * 3}
    jobs = plan_views_for_fits(rig, [ok, failed, no_cam], TOY_BODY_FRAME, AugmentConfig(), seed=5)
    assert {j.source_id for j in jobs} == {"a"} and jobs[0].view_type == "rear"
    assert len({j.sample_id for j in jobs}) == len(jobs)
    again = plan_views_for_fits(rig, [ok], TOY_BODY_FRAME, AugmentConfig(), seed=5)
    assert [job_to_dict(j) for j in again] == [job_to_dict(j) for j in jobs]
    with pytest.raises(ValueError, match="frame_joints names a joint the rig does not have"):
        plan_views_for_fits(rig, [ok], {"origin": "nope", "forward": ("a", "b"), "horizontal": ("c", "d")},
                            AugmentConfig(), seed=5)
