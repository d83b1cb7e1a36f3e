"""Metric tests against slow, obviously-correct references (brute-force nearest neighbours, known transforms)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bat3r_core import metrics as M


def _brute_chamfer(x: np.ndarray, y: np.ndarray) -> float:
    """O(N·M) reference: every pairwise distance, row/column minima, RMS of both directions."""
    d2 = np.array([[float(np.sum((a - b) ** 2)) for b in y] for a in x])
    return float(np.sqrt(0.5 * (d2.min(axis=1).mean() + d2.min(axis=0).mean())))


def _animal(n: int, seed: int) -> np.ndarray:
    """A horse-like, front/back asymmetric point cloud (metres, +Y up, +Z forward): body, head, legs."""
    rng = np.random.default_rng(seed)
    parts = []
    body = rng.normal(size=(n // 2, 3))
    body /= np.linalg.norm(body, axis=1, keepdims=True)
    parts.append(body * [0.35, 0.35, 1.0] + [0, 1.2, 0])
    head = rng.normal(size=(n // 6, 3)) * [0.1, 0.12, 0.2] + [0, 1.7, 1.25]
    parts.append(head)
    rest = n - n // 2 - n // 6
    for k, (lx, lz) in enumerate([(-0.2, 0.7), (0.2, 0.7), (-0.2, -0.7), (0.2, -0.7)]):
        per_leg = rest // 4 + (rest % 4 if k == 3 else 0)
        h = rng.uniform(0.0, 1.0, per_leg)
        parts.append(np.stack([lx + rng.normal(0, 0.04, per_leg), h, lz + rng.normal(0, 0.04, per_leg)], 1))
    return np.concatenate(parts)


def _random_rotation(seed: int) -> np.ndarray:
    return Rotation.random(random_state=seed).as_matrix()


# ---------------------------------------------------------------- Chamfer

def test_chamfer_matches_brute_force_and_is_symmetric():
    rng = np.random.default_rng(0)
    x, y = rng.normal(size=(70, 3)), rng.normal(size=(45, 3)) + 0.3
    ref = _brute_chamfer(x, y)
    assert M.rms_chamfer(x, y) == pytest.approx(ref, rel=1e-12)
    assert M.rms_chamfer(y, x) == pytest.approx(ref, rel=1e-12)


def test_chamfer_identical_clouds_is_zero():
    x = _animal(300, 1)
    assert M.rms_chamfer(x, x) == 0.0
    assert M.rms_chamfer(x, x[::-1].copy()) == 0.0


def test_chamfer_units_known_offset():
    # points 1 m apart, shifted by 3 cm: every nearest distance is exactly 3 cm in both directions
    x = np.array([[0.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0]])
    y = x + [0, 0, 0.03]
    assert M.rms_chamfer(x, y) == pytest.approx(0.03, abs=1e-12)
    assert M.rms_chamfer_cm(x, y) == pytest.approx(3.0, abs=1e-10)
    assert M.to_cm(0.0123) == pytest.approx(1.23)
    np.testing.assert_allclose(M.to_cm(np.array([0.5, 2.0])), [50.0, 200.0])


def test_chamfer_rejects_bad_shapes():
    with pytest.raises(ValueError, match=r"x must have shape \(N, 3\), got \(4, 2\)"):
        M.rms_chamfer(np.zeros((4, 2)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="y must have at least 1 point"):
        M.rms_chamfer(np.zeros((4, 3)), np.zeros((0, 3)))
    with pytest.raises(ValueError, match="x contains non-finite"):
        M.rms_chamfer(np.full((2, 3), np.nan), np.zeros((4, 3)))


# ---------------------------------------------------------------- Umeyama / Kabsch

def test_umeyama_recovers_known_similarity():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(50, 3))
    rot, s, t = _random_rotation(3), 0.37, np.array([0.5, -2.0, 7.0])
    sim = M.umeyama(src, s * src @ rot.T + t)
    assert sim.scale == pytest.approx(s, rel=1e-10)
    np.testing.assert_allclose(sim.rotation, rot, atol=1e-10)
    np.testing.assert_allclose(sim.translation, t, atol=1e-10)
    np.testing.assert_allclose(sim.apply(src), s * src @ rot.T + t, atol=1e-10)


def test_kabsch_keeps_unit_scale_and_recovers_rigid_motion():
    rng = np.random.default_rng(4)
    src = rng.normal(size=(30, 3))
    rot, t = _random_rotation(5), np.array([1.0, 2.0, 3.0])
    sim = M.kabsch(src, src @ rot.T + t)
    assert sim.scale == 1.0
    np.testing.assert_allclose(sim.rotation, rot, atol=1e-10)
    np.testing.assert_allclose(sim.translation, t, atol=1e-10)
    # a scaled target: Kabsch still returns a proper rotation with unit scale, Umeyama finds the scale
    assert M.kabsch(src, 2 * src).scale == 1.0
    assert M.umeyama(src, 2 * src).scale == pytest.approx(2.0)


def test_umeyama_never_returns_a_reflection():
    rng = np.random.default_rng(6)
    src = rng.normal(size=(40, 3))
    mirrored = src * [-1.0, 1.0, 1.0]
    sim = M.umeyama(src, mirrored)
    assert np.linalg.det(sim.rotation) == pytest.approx(1.0)
    np.testing.assert_allclose(sim.rotation.T @ sim.rotation, np.eye(3), atol=1e-12)


def test_weighted_umeyama_equals_duplicated_points():
    rng = np.random.default_rng(7)
    src, tgt = rng.normal(size=(12, 3)), rng.normal(size=(12, 3))
    w = rng.integers(1, 4, size=12)
    a = M.umeyama(src, tgt, weights=w.astype(float))
    b = M.umeyama(np.repeat(src, w, axis=0), np.repeat(tgt, w, axis=0))
    assert a.scale == pytest.approx(b.scale, rel=1e-10)
    np.testing.assert_allclose(a.rotation, b.rotation, atol=1e-10)
    np.testing.assert_allclose(a.translation, b.translation, atol=1e-10)


def test_umeyama_input_checks():
    with pytest.raises(ValueError, match="same shape"):
        M.umeyama(np.zeros((5, 3)), np.zeros((6, 3)))
    with pytest.raises(ValueError, match=r"weights must have shape \(5,\)"):
        M.umeyama(np.eye(5, 3), np.eye(5, 3), weights=np.ones(4))
    with pytest.raises(ValueError, match="source points coincide"):
        M.umeyama(np.zeros((5, 3)), np.eye(5, 3))


# ---------------------------------------------------------------- alignments

def test_full_alignment_recovers_similarity_to_zero_chamfer():
    gt = _animal(600, 8)
    rot = M.rotation_about_axis((0, 1, 0), 25.0) @ M.rotation_about_axis((1, 0, 0), 10.0)
    s, t = 0.6, np.array([0.3, -0.2, 4.0])
    pred = s * gt @ rot.T + t  # the prediction is a similarity copy of the truth
    res = M.full_alignment(pred, gt)
    assert res.rms_cd < 1e-6
    assert res.similarity.scale == pytest.approx(1 / s, rel=1e-5)
    np.testing.assert_allclose(res.similarity.rotation, rot.T, atol=1e-5)
    # the reported distance is the brute-force Chamfer of the returned transform
    assert res.rms_cd == pytest.approx(_brute_chamfer(res.similarity.apply(pred), gt), abs=1e-12)


def test_full_alignment_handles_the_180_degree_ambiguity():
    gt = _animal(600, 9)
    pred = gt @ M.rotation_about_axis((0, 1, 0), 172.0).T + [0.1, 0.0, -0.2]
    only_zero = M.full_alignment(pred, gt, start_angles_deg=(0.0,))
    both = M.full_alignment(pred, gt)
    assert only_zero.rms_cd > 0.05  # a backwards local minimum from the 0° start ...
    assert both.rms_cd < 1e-6       # ... that the 180° start escapes
    assert both.start_angle_deg == 180.0
    assert both.rms_cd == pytest.approx(_brute_chamfer(both.similarity.apply(pred), gt), abs=1e-12)


def test_full_alignment_uses_the_given_up_axis():
    gt_canonical = _animal(600, 10)
    q = _random_rotation(11)  # ground truth observed in some camera frame; world up is q @ +Y there
    gt = gt_canonical @ q.T
    up = q @ np.array([0.0, 1.0, 0.0])
    pred = gt @ M.rotation_about_axis(up, 175.0).T * 1.3
    assert M.full_alignment(pred, gt, up=up).rms_cd < 1e-6
    assert M.full_alignment(pred, gt, up=up, start_angles_deg=(0.0,)).rms_cd > 0.05


def test_full_alignment_with_noise_matches_brute_force_and_beats_the_start():
    rng = np.random.default_rng(12)
    gt = _animal(400, 12)
    pred = (gt + rng.normal(0, 0.01, size=gt.shape)) @ M.rotation_about_axis((0, 1, 0), 15).T
    res = M.full_alignment(pred, gt)
    assert res.rms_cd == pytest.approx(_brute_chamfer(res.similarity.apply(pred), gt), abs=1e-12)
    assert res.rms_cd < 0.03
    no_iterations = M.full_alignment(pred, gt, iterations=0)
    assert res.rms_cd < no_iterations.rms_cd


def test_model_view_alignment_recovers_scale_and_translation_only():
    gt = _animal(500, 13)
    s, t = 1.7, np.array([0.0, 0.1, 2.5])
    pred = (gt - t) / s
    res = M.model_view_alignment(pred, gt)
    assert res.rms_cd < 1e-9
    assert res.similarity.scale == pytest.approx(s, rel=1e-9)
    np.testing.assert_allclose(res.similarity.translation, t, atol=1e-9)
    np.testing.assert_array_equal(res.similarity.rotation, np.eye(3))
    # a rotated prediction is not undone: model-view is penalised, full alignment is not
    rotated = pred @ M.rotation_about_axis((0, 1, 0), 30.0).T
    mv = M.model_view_alignment(rotated, gt)
    assert mv.rms_cd > 0.05
    assert M.full_alignment(rotated, gt).rms_cd < 1e-6
    assert mv.rms_cd == pytest.approx(_brute_chamfer(mv.similarity.apply(rotated), gt), abs=1e-12)


def test_model_view_iterations_improve_on_the_closed_form_start():
    rng = np.random.default_rng(14)
    gt = _animal(400, 14)
    # a partial view (only the front half): centroid matching alone is biased, the iterations correct it
    pred = gt[gt[:, 2] > 0] + rng.normal(0, 0.005, size=(int((gt[:, 2] > 0).sum()), 3))
    start = M.model_view_alignment(pred, gt, iterations=0)
    refined = M.model_view_alignment(pred, gt, iterations=10)
    assert refined.rms_cd < start.rms_cd
    assert refined.iterations >= 1


def test_alignment_input_checks():
    gt = _animal(100, 15)
    with pytest.raises(ValueError, match="pred_points must have at least 3 point"):
        M.full_alignment(gt[:2], gt)
    with pytest.raises(ValueError, match="iterations must be a non-negative integer"):
        M.model_view_alignment(gt, gt, iterations=-1)
    with pytest.raises(ValueError, match="axis must be a finite, non-zero vector"):
        M.full_alignment(gt, gt, up=(0, 0, 0))
    with pytest.raises(ValueError, match="must not collapse"):
        M.full_alignment(np.ones((5, 3)), gt)


# ---------------------------------------------------------------- rotation error

@pytest.mark.parametrize("angle", [0.0, 1e-4, 3.5, 37.0, 90.0, 179.0, 180.0])
def test_rotation_error_known_angles(angle):
    r_gt = _random_rotation(16)
    axis = np.array([0.3, -0.5, 0.8])
    r_pred = r_gt @ M.rotation_about_axis(axis, angle)
    assert M.rotation_error_deg(r_pred, r_gt) == pytest.approx(angle, abs=1e-6)
    assert M.rotation_error_deg(r_gt, r_pred) == pytest.approx(angle, abs=1e-6)


def test_rotation_error_batched_matches_arccos_reference():
    a = Rotation.random(20, random_state=17).as_matrix()
    b = Rotation.random(20, random_state=18).as_matrix()
    ref = [np.degrees(np.arccos(np.clip((np.trace(x.T @ y) - 1) / 2, -1, 1))) for x, y in zip(a, b)]
    np.testing.assert_allclose(M.rotation_error_deg(a, b), ref, atol=1e-6)


def test_rotation_error_rejects_non_rotations():
    with pytest.raises(ValueError, match="r_pred must hold proper rotation matrices"):
        M.rotation_error_deg(2 * np.eye(3), np.eye(3))
    with pytest.raises(ValueError, match="r_gt must hold proper rotation matrices"):
        M.rotation_error_deg(np.eye(3), np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match=r"r_gt must have shape \(\.\.\., 3, 3\)"):
        M.rotation_error_deg(np.eye(3), np.eye(2))


# ---------------------------------------------------------------- per sample

def test_evaluate_sample_units_and_fields():
    rng = np.random.default_rng(19)
    gt = _animal(400, 19)
    q = _random_rotation(20)
    gt_cam = gt @ q.T + [0, 0, 5.0]
    pred_cam = gt_cam[::2] + rng.normal(0, 0.01, size=(200, 3))
    r_pred = q @ M.rotation_about_axis((0, 0, 1), 4.0)
    out = M.evaluate_sample(pred_cam, gt_cam, up=q @ [0, 1, 0], pred_rotation=r_pred, gt_rotation=q)
    full = M.full_alignment(pred_cam, gt_cam, up=q @ [0, 1, 0])
    assert out.cd_cm == pytest.approx(100 * _brute_chamfer(full.similarity.apply(pred_cam), gt_cam), rel=1e-9)
    mv = M.model_view_alignment(pred_cam, gt_cam)
    assert out.mv_cd_cm == pytest.approx(100 * _brute_chamfer(mv.similarity.apply(pred_cam), gt_cam), rel=1e-9)
    assert 0.5 < out.cd_cm < 8.0  # 1 cm noise per axis + half the points
    assert out.mv_cd_cm >= out.cd_cm - 1e-9
    assert out.rot_err_deg == pytest.approx(4.0, abs=1e-9)
    assert (out.n_pred, out.n_gt) == (200, 400)
    assert set(out.as_dict()) >= {"cd_cm", "mv_cd_cm", "rot_err_deg"}
    no_cam = M.evaluate_sample(pred_cam, gt_cam, up=q @ [0, 1, 0])
    assert np.isnan(no_cam.rot_err_deg)
    with pytest.raises(ValueError, match="must be given together"):
        M.evaluate_sample(pred_cam, gt_cam, pred_rotation=q)
