"""Body frame, spherical camera coordinates, view types, viewpoint sampling/framing and the camera-prior fit."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats
from scipy.spatial.transform import Rotation

from bat3r_core.cameras import PinholeCamera
from bat3r_core.config_utils import ConfigError, from_mapping
from bat3r_core.toy import TOY_BODY_FRAME, TOY_JOINTS, build_toy_rig
from bat3r_core.viewpoints import (REFERENCE_STUDENT_T, AngleFit, AnglePrior, BodyFrame, CameraPriorConfig,
                                   SphericalCoords, ViewTypePrior,
                                   body_frame, camera_from_spherical, fit_angle_distribution, frame_camera,
                                   identity_frame, pose_from_spherical, sample_angles, sample_viewpoints,
                                   spherical_from_camera, spherical_from_poses, view_type)


@pytest.fixture(scope="module")
def toy():
    return build_toy_rig()


def _toy_frame(joints):
    i = TOY_JOINTS.index
    return body_frame(joints, i(TOY_BODY_FRAME["origin"]), tuple(map(i, TOY_BODY_FRAME["forward"])),
                      tuple(map(i, TOY_BODY_FRAME["horizontal"])))


def _random_frame(seed: int) -> BodyFrame:
    return BodyFrame(origin=np.random.default_rng(seed).normal(size=3),
                     rotation=Rotation.random(random_state=seed).as_matrix())


# ---------------------------------------------------------------------------------------------- body frame
def test_toy_rest_frame_is_the_canonical_frame_and_moves_with_the_body(toy):
    frame = _toy_frame(toy.rest_joint_positions)
    B = frame.rotation
    np.testing.assert_allclose(B.T @ B, np.eye(3), atol=1e-12)
    assert np.linalg.det(B) == pytest.approx(1.0)
    # left ~ +X, up ~ +Y, forward ~ +Z (the toy's spine rises by 1 cm over 30 cm)
    np.testing.assert_allclose(B, np.eye(3), atol=0.05)
    np.testing.assert_allclose(B[:, 2], [0, 0.01, 0.30] / np.linalg.norm([0, 0.01, 0.30]), atol=1e-12)
    Rg = Rotation.from_euler("xyz", [10, 70, -20], degrees=True).as_matrix()
    moved = _toy_frame(toy.rest_joint_positions @ Rg.T + [1.0, 2.0, 3.0])
    np.testing.assert_allclose(moved.rotation, Rg @ B, atol=1e-12)
    np.testing.assert_allclose(moved.origin, Rg @ frame.origin + [1.0, 2.0, 3.0], atol=1e-12)


def test_body_frame_keeps_forward_exact_and_orthogonalises_the_horizontal_pair():
    joints = np.array([[0, 0, 0], [0, 0, 1.0], [1.0, 0.3, 0.4], [-1.0, 0.1, 0.2]])
    frame = body_frame(joints, 0, (0, 1), (2, 3))
    np.testing.assert_allclose(frame.rotation[:, 2], [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(frame.rotation.T @ frame.rotation, np.eye(3), atol=1e-12)
    assert frame.rotation[1, 1] > 0.99  # up stays up although the hips are tilted
    with pytest.raises(ValueError, match=r"forward joint index must be an int in \[0, 4\), got 7"):
        body_frame(joints, 0, (0, 7), (2, 3))
    with pytest.raises(ValueError, match="parallel to the forward axis"):
        body_frame(joints, 0, (0, 1), (0, 1))
    with pytest.raises(ValueError, match=r"joints must have shape \(J, 3\), got \(4, 2\)"):
        body_frame(joints[:, :2], 0, (0, 1), (2, 3))


# ---------------------------------------------------------------------------------------------- spherical
def test_spherical_to_camera_round_trip():
    rng = np.random.default_rng(0)
    intr = PinholeCamera.from_fov(40, 32, 32)
    for seed in range(30):
        frame = _random_frame(seed)
        c = SphericalCoords(rng.uniform(-180, 180), rng.uniform(-85, 85), rng.uniform(-180, 180), rng.uniform(0.5, 9))
        cam = camera_from_spherical(frame, c, intr)
        back = spherical_from_camera(frame, cam)
        np.testing.assert_allclose([back.azimuth_deg, back.elevation_deg, back.roll_deg, back.radius],
                                   [c.azimuth_deg, c.elevation_deg, c.roll_deg, c.radius], atol=1e-8)
        # the camera looks at the origin: it projects onto the principal point
        np.testing.assert_allclose(cam.project(frame.origin)[0], [16, 16], atol=1e-8)
    Rs = np.stack([camera_from_spherical(identity_frame(), SphericalCoords(a, 10.0, -5.0, 4.0), intr).R
                   for a in (0.0, 90.0)])
    ts = np.stack([camera_from_spherical(identity_frame(), SphericalCoords(a, 10.0, -5.0, 4.0), intr).t
                   for a in (0.0, 90.0)])
    np.testing.assert_allclose(spherical_from_poses(identity_frame(), Rs, ts), [[0, 10, -5, 4], [90, 10, -5, 4]],
                               atol=1e-9)


def test_angle_semantics_front_left_above_and_roll():
    frame = identity_frame()  # left +X, up +Y, forward +Z
    intr = PinholeCamera.from_fov(40, 64, 64)
    front = camera_from_spherical(frame, SphericalCoords(0, 0, 0, 5), intr)
    np.testing.assert_allclose(front.center, [0, 0, 5], atol=1e-12)
    left = camera_from_spherical(frame, SphericalCoords(90, 0, 0, 5), intr)
    np.testing.assert_allclose(left.center, [5, 0, 0], atol=1e-12)  # on the animal's left side
    above = camera_from_spherical(frame, SphericalCoords(0, 30, 0, 2), intr)
    np.testing.assert_allclose(above.center, [0, 1, math.sqrt(3)], atol=1e-12)
    rear = camera_from_spherical(frame, SphericalCoords(180, 0, 0, 5), intr)
    np.testing.assert_allclose(rear.center, [0, 0, -5], atol=1e-12)
    # frontal view: the animal's left (+X) is on the image right; up is up
    uv = front.project(np.array([[0.5, 0, 0], [0, 0.5, 0]]))[0]
    assert uv[0, 0] > 32 and uv[1, 1] < 32
    # positive roll turns the image content clockwise: "up" moves to the right
    rolled = camera_from_spherical(frame, SphericalCoords(0, 0, 90, 5), intr)
    uv = rolled.project(np.array([0, 0.5, 0]))[0]
    assert uv[0] > 32 and abs(uv[1] - 32) < 1e-9


def test_pose_from_spherical_rejects_bad_coordinates():
    with pytest.raises(ValueError, match=r"coords.elevation_deg must be in \(-90, 90\), got 90"):
        pose_from_spherical(identity_frame(), SphericalCoords(0, 90, 0, 1))
    with pytest.raises(ValueError, match="coords.radius must be finite, got nan"):
        pose_from_spherical(identity_frame(), SphericalCoords(0, 0, 0, float("nan")))


@pytest.mark.parametrize("azimuth, expected", [
    (0, "front"), (-30, "front"), (29.999, "front"), (30, "left"), (149.999, "left"), (150, "rear"),
    (-30.001, "right"), (-150, "right"), (-150.001, "rear"), (180, "rear"), (-180, "rear"), (390, "left"),
    (-330, "left"), (90, "left"), (-90, "right"),
])
def test_view_type_bins(azimuth, expected):
    assert view_type(azimuth) == expected


def test_view_type_vectorised_agrees_with_scalar():
    az = np.linspace(-400, 400, 1601)
    np.testing.assert_array_equal(view_type(az), [view_type(float(a)) for a in az])
    with pytest.raises(ValueError, match=r"azimuth_deg must be finite; 1 value\(s\) are not"):
        view_type(np.array([0.0, np.nan]))


# ---------------------------------------------------------------------------------------------- prior
def test_default_prior_is_the_reference_table_and_loads_from_a_mapping():
    cfg = CameraPriorConfig()
    assert cfg.distribution == "student_t"
    assert cfg.per_view_type["front"].roll == AnglePrior(df=1.275, loc=-0.18, scale=4.85)
    assert cfg.per_view_type["rear"].elevation == AnglePrior(df=1.54, loc=-5.69, scale=4.86)
    assert cfg.per_view_type == REFERENCE_STUDENT_T
    loaded = from_mapping(CameraPriorConfig, {
        "distribution": "normal", "per_view_type": None,
        "elevation": {"loc": 2.0, "scale": 8.0}, "roll": {"loc": 0.0, "scale": 6.0}, "fov_deg": 35.0,
    }, "categories.toy.camera_prior")
    assert loaded.elevation == AnglePrior(loc=2.0, scale=8.0) and loaded.per_view_type is None
    # the error inside an Optional section names the nested key
    with pytest.raises(ConfigError, match=r"categories\.toy\.camera_prior\.per_view_type\.left\.roll: unknown key\(s\) "
                                          r"\['sigma'\]"):
        from_mapping(CameraPriorConfig, {"per_view_type": {"left": {"elevation": {"loc": 0.0, "scale": 1.0, "df": 2.0},
                                                                    "roll": {"loc": 0.0, "sigma": 1.0}}}},
                     "categories.toy.camera_prior")
    with pytest.raises(ConfigError, match=r"categories\.toy\.camera_prior\.roll: unknown key\(s\) \[.sigma.\]"):
        from_mapping(CameraPriorConfig, {"roll": {"loc": 0.0, "sigma": 1.0}}, "categories.toy.camera_prior")
    with pytest.raises(ValueError, match=r"per_view_type.front.elevation: distribution 'normal' takes no df"):
        CameraPriorConfig(distribution="normal")
    with pytest.raises(ValueError, match="elevation and roll are required unless per_view_type covers all"):
        CameraPriorConfig(per_view_type=None)
    with pytest.raises(ValueError, match=r"unknown view type\(s\) \['top'\]"):
        CameraPriorConfig(per_view_type={"top": REFERENCE_STUDENT_T["front"]})


def test_sampled_angles_follow_the_per_view_type_prior():
    narrow = {v: ViewTypePrior(elevation=AnglePrior(loc=loc, scale=0.01), roll=AnglePrior(loc=-loc, scale=0.01))
              for v, loc in (("front", 10.0), ("left", 20.0), ("right", 30.0), ("rear", 40.0))}
    cfg = CameraPriorConfig(distribution="normal", per_view_type=narrow)
    a = sample_angles(cfg, 3000, np.random.default_rng(1))
    expected = np.array([{"front": 10.0, "left": 20.0, "right": 30.0, "rear": 40.0}[t] for t in view_type(a[:, 0])])
    np.testing.assert_allclose(a[:, 1], expected, atol=0.1)
    np.testing.assert_allclose(a[:, 2], -expected, atol=0.1)
    assert stats.kstest((a[:, 0] + 180) / 360, "uniform").pvalue > 1e-3
    np.testing.assert_array_equal(a, sample_angles(cfg, 3000, np.random.default_rng(1)))  # seeded


def test_student_t_elevations_are_truncated_at_the_limit():
    cfg = CameraPriorConfig(max_abs_elevation_deg=30.0)
    a = sample_angles(cfg, 4000, np.random.default_rng(2))
    assert np.abs(a[:, 1]).max() < 30.0
    assert np.all((a[:, 2] >= -180) & (a[:, 2] < 180))
    # heavy tail: far more than a Normal with the same scale would give beyond 4 scales
    front = a[view_type(a[:, 0]) == "front", 2]
    assert np.mean(np.abs(front + 0.18) > 4 * 4.85) > 0.05


# ---------------------------------------------------------------------------------------------- framing
def _check_framing(vp, vertices):
    cam = vp.camera
    uv, z = cam.project(vertices)
    assert z.min() > 0
    lo, hi = uv.min(0), uv.max(0)
    size = np.array([cam.width, cam.height], float)
    gaps = np.stack([lo, size - hi]) / size  # (2 sides, 2 axes) relative gaps
    assert gaps.min() >= vp.margin - 1e-9  # every vertex inside with at least the margin
    tight = np.argmin(gaps.min(0))
    np.testing.assert_allclose(gaps[:, tight], vp.margin, atol=1e-9)  # tight axis: exactly the margin, centred
    np.testing.assert_allclose(gaps[0], gaps[1], atol=1e-9)  # the box is centred on both axes


def test_sampled_viewpoints_frame_the_toy_with_the_drawn_margin(toy):
    frame = _toy_frame(toy.rest_joint_positions)
    vps = sample_viewpoints(toy.rest_vertices, frame, 24, CameraPriorConfig(), 160, 120, np.random.default_rng(3))
    margins = [vp.margin for vp in vps]
    assert 0.1 <= min(margins) and max(margins) <= 0.25 and np.ptp(margins) > 0.05
    for vp in vps:
        _check_framing(vp, toy.rest_vertices)
        back = spherical_from_camera(frame, vp.camera)
        np.testing.assert_allclose([back.azimuth_deg, back.elevation_deg, back.roll_deg, back.radius],
                                   [vp.coords.azimuth_deg, vp.coords.elevation_deg, vp.coords.roll_deg,
                                    vp.coords.radius], atol=1e-8)
        assert vp.view_type == view_type(vp.coords.azimuth_deg)
        assert 2.5 < vp.coords.radius < 10.0  # the 2.4 m toy at a 40 degree field of view
    again = sample_viewpoints(toy.rest_vertices, frame, 24, CameraPriorConfig(), 160, 120, np.random.default_rng(3))
    assert all(a.camera.allclose(b.camera, atol=0) for a, b in zip(vps, again))


def test_frame_camera_close_up_and_bad_inputs():
    verts = np.array([[-1, -0.2, -0.3], [1, 0.2, 0.3], [0.3, -0.5, 0.1], [0.0, 0.4, -0.2]])
    vp = frame_camera(verts, identity_frame(), 35.0, 20.0, 10.0, 90.0, 64, 48, 0.02)
    _check_framing(vp, verts)
    with pytest.raises(ValueError, match=r"margin must be in \[0, 0.5\), got 0.5"):
        frame_camera(verts, identity_frame(), 0, 0, 0, 40.0, 64, 48, 0.5)
    with pytest.raises(ValueError, match="vertices must be finite"):
        frame_camera(verts * np.nan, identity_frame(), 0, 0, 0, 40.0, 64, 48, 0.1)
    with pytest.raises(TypeError, match="rng must be a numpy.random.Generator, got int"):
        sample_viewpoints(verts, identity_frame(), 2, CameraPriorConfig(), 64, 48, 0)


# ---------------------------------------------------------------------------------------------- fitting
def test_student_t_fit_recovers_synthetic_parameters_within_10_percent():
    df, loc, scale = 1.75, 8.25, 5.49  # the reference front-view elevation
    x = stats.t.rvs(df, loc, scale, size=20000, random_state=np.random.default_rng(4))
    fit = fit_angle_distribution(x)
    assert isinstance(fit, AngleFit)
    np.testing.assert_allclose(fit.student_t, (df, loc, scale), rtol=0.1)
    small_loc = fit_angle_distribution(stats.t.rvs(2.3, 0.95, 6.93, size=20000, random_state=np.random.default_rng(6)))
    np.testing.assert_allclose(small_loc.student_t[::2], (2.3, 6.93), rtol=0.1)
    assert abs(small_loc.student_t[1] - 0.95) < 0.1 * 6.93  # a location near 0: judged against the scale
    assert fit.loglik_t > fit.loglik_normal + 100  # heavy tails: the t wins clearly
    assert fit.loglik_t == pytest.approx(stats.t.logpdf(x, *fit.student_t).sum())


def test_normal_fit_and_comparison_on_gaussian_samples():
    x = np.random.default_rng(5).normal(-5.7, 4.9, size=5000)
    fit = fit_angle_distribution(x)
    assert fit.normal[0] == pytest.approx(-5.7, abs=0.2) and fit.normal[1] == pytest.approx(4.9, rel=0.05)
    assert abs(fit.loglik_t - fit.loglik_normal) < 5  # nested models: no real gain on Gaussian data


@pytest.mark.parametrize("bad, match", [
    (np.array([1.0, np.nan, 2.0, 3.0]), r"samples_deg must be finite; 1 of 4 are not"),
    (np.zeros((3, 2)), r"samples_deg must have shape \(N,\) with N >= 3, got \(3, 2\)"),
    (np.ones(5), r"samples_deg are all equal"),
])
def test_fit_rejects_bad_samples(bad, match):
    with pytest.raises(ValueError, match=match):
        fit_angle_distribution(bad)
