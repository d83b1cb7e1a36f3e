"""Pose clusters, splits, camera histograms, angle fits and pseudo-label summaries."""
from __future__ import annotations

import math

import numpy as np
import pyarrow as pa
import pytest
from scipy.spatial.transform import Rotation

from bat3r_core import analysis as A


def _blob_features(n_per: int = 60, k: int = 10, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """k well-separated blobs of [f_ang, f_sq, f_dist]; blob b has f_dist ≈ 1 + b (so it should become id b)."""
    rng = np.random.default_rng(seed)
    centers = np.stack([rng.uniform(0.1, 1.0, k), rng.uniform(0.1, 1.0, k), 1.0 + np.arange(k)], 1)
    truth = np.repeat(np.arange(k), n_per)
    feats = centers[truth] + rng.normal(0, [0.005, 0.005, 0.02], size=(len(truth), 3))
    perm = rng.permutation(len(truth))
    return feats[perm], truth[perm]


def test_standardize_zero_mean_unit_variance_and_reuse():
    f = np.random.default_rng(1).normal([1, 2, 3], [0.1, 5, 2], size=(200, 3))
    z, mean, std = A.standardize(f)
    np.testing.assert_allclose(z.mean(0), 0, atol=1e-12)
    np.testing.assert_allclose(z.std(0), 1, atol=1e-12)
    z2, _, _ = A.standardize(f[:10], mean, std)
    np.testing.assert_allclose(z2, z[:10])
    with pytest.raises(ValueError, match=r"features must have shape \(N, 3\)"):
        A.standardize(np.zeros((5, 2)))


def test_clusters_recover_separated_blobs_with_ids_ordered_by_f_dist():
    feats, truth = _blob_features()
    cl = A.cluster_poses(feats, k=10, seed=0)
    assert cl.k == 10 and cl.labels.shape == (600,)
    # well-separated blobs: the partition is exact, and ids follow increasing f_dist (blob b → id b)
    np.testing.assert_array_equal(cl.labels, truth)
    means = [feats[cl.labels == c, 2].mean() for c in range(10)]
    assert np.all(np.diff(means) > 0)
    np.testing.assert_allclose(cl.proportions(), np.full(10, 0.1))
    # nearest-centre assignment reproduces the fitted labels
    np.testing.assert_array_equal(A.assign_clusters(cl, feats), cl.labels)


def test_clustering_is_reproducible_by_seed():
    feats = np.random.default_rng(2).gamma(2.0, 1.0, size=(400, 3))  # no obvious clusters: seed matters
    a = A.cluster_poses(feats, seed=3)
    b = A.cluster_poses(feats, seed=3)
    np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_array_equal(a.centers, b.centers)
    with pytest.raises(ValueError, match="at least k=10 rows"):
        A.cluster_poses(feats[:5])


def _skewed_clusters(n: int = 5000, seed: int = 4) -> np.ndarray:
    # proportions like the paper's table (26 %, 16 %, ... 2.6 %)
    p = np.array([9.1, 26.4, 3.1, 3.2, 13.3, 2.6, 5.6, 12.6, 16.0, 8.1])
    return np.random.default_rng(seed).choice(10, size=n, p=p / p.sum())


def test_stratified_split_proportions_within_one_percent():
    c = _skewed_clusters()
    overall = np.bincount(c, minlength=10) / len(c)
    s = A.stratified_split(c, n_test=1000, n_train=800, seed=5)
    assert len(s.test) == 1000 and len(s.train) == 800
    assert len(np.intersect1d(s.train, s.test)) == 0
    for part in (s.test, s.train):
        share = np.bincount(c[part], minlength=10) / len(part)
        assert np.abs(share - overall).max() <= 0.01
    everything = A.stratified_split(c, n_test=1000, seed=5)
    assert len(everything.train) == 4000  # default: all the rest
    assert len(np.union1d(everything.train, everything.test)) == 5000


def test_stratified_split_reproducible_by_seed():
    c = _skewed_clusters()
    a = A.stratified_split(c, 500, 1000, seed=6)
    b = A.stratified_split(c, 500, 1000, seed=6)
    d = A.stratified_split(c, 500, 1000, seed=7)
    np.testing.assert_array_equal(a.test, b.test)
    np.testing.assert_array_equal(a.train, b.train)
    assert not np.array_equal(a.test, d.test)
    with pytest.raises(ValueError, match=r"n_test must be in \[1, 4999\]"):
        A.stratified_split(c, 5000)
    with pytest.raises(ValueError, match="cluster_ids must be a 1-D array of non-negative integers"):
        A.stratified_split(np.array([0.5, 1.0]), 1)


def test_alternative_split_drops_clusters_and_refills_to_base_size():
    c = _skewed_clusters()
    s = A.stratified_split(c, n_test=1000, n_train=1500, seed=8)
    excluded = [0, 2, 3, 5, 6, 9]
    alt = A.alternative_split(c, s.train, excluded, exclude_indices=s.test, seed=9)
    assert len(alt) == len(s.train) == len(np.unique(alt))
    assert not np.isin(c[alt], excluded).any()
    assert len(np.intersect1d(alt, s.test)) == 0
    kept = s.train[~np.isin(c[s.train], excluded)]
    assert np.isin(kept, alt).all()  # every allowed base sample is retained
    np.testing.assert_array_equal(alt, A.alternative_split(c, s.train, excluded, exclude_indices=s.test, seed=9))
    with pytest.raises(ValueError, match="needs .* more samples from the allowed clusters"):
        A.alternative_split(c, np.arange(4900), list(range(9)))


def test_camera_histograms_match_a_counting_loop():
    rng = np.random.default_rng(10)
    az = rng.uniform(-200, 200, 500)  # some beyond ±180: wrapped
    el = rng.standard_t(2, 500) * 8
    ro = rng.standard_t(2, 500) * 5
    h = A.camera_histograms(az, el, ro)
    ref = np.zeros((36, 36), int)
    outside = 0
    for a, e, r in zip(az, el, ro):
        a = (a + 180) % 360 - 180
        ia, ie = int((a + 180) // 10), int((e + 90) // 5)
        if not (-90 <= e <= 90 and -90 <= r <= 90):
            outside += 1
        if 0 <= ie < 36 or e == 90:
            ref[min(ie, 35), min(ia, 35)] += 1
    np.testing.assert_array_equal(h.az_el, ref)
    assert h.n == 500 and h.n_outside == outside
    assert h.az_roll.sum() == np.sum(np.abs(ro) <= 90)
    np.testing.assert_allclose(A.CameraHistograms.log_counts(np.array([0, 9, 99])), [0, 1, 2])
    per = A.camera_histograms_by_cluster(az, el, ro, np.arange(500) % 3)
    assert sorted(per) == [0, 1, 2]
    np.testing.assert_array_equal(sum(p.az_el for p in per.values()), h.az_el)


def test_angle_fits_prefer_student_t_for_heavy_tails():
    rng = np.random.default_rng(11)
    el = 2.0 + 5.0 * rng.standard_t(1.8, 3000)
    ro = 4.0 * rng.standard_t(1.5, 3000)
    fits = A.fit_camera_angles(el, ro)
    for name in ("elevation", "roll"):
        assert fits[name].loglik_t > fits[name].loglik_normal
    grid = np.linspace(-400, 400, 80001)
    pdf_t, pdf_n = A.angle_fit_densities(fits["elevation"], grid)
    step = grid[1] - grid[0]
    assert pdf_n.sum() * step == pytest.approx(1.0, abs=1e-3)
    assert pdf_t.sum() * step == pytest.approx(1.0, abs=0.02)  # heavy tails beyond ±400° are missing
    assert fits["elevation"].student_t[1] == pytest.approx(2.0, abs=0.5)


def test_pose_errors_against_loop_reference():
    rng = np.random.default_rng(12)
    n, j, v = 4, 5, 30
    gt_j, gt_v = rng.normal(size=(n, j, 3)), rng.normal(size=(n, v, 3))
    gt_r = rng.normal(0, 0.4, size=(n, j, 3))
    fit_j = gt_j + [0.01, 0.0, 0.0]                      # exactly 1 cm off
    fit_v = gt_v + rng.normal(0, 0.02, size=gt_v.shape)
    extra = Rotation.from_rotvec(np.array([0.0, 0.0, np.deg2rad(7.0)]))
    fit_r = (Rotation.from_rotvec(gt_r.reshape(-1, 3)) * extra).as_rotvec().reshape(n, j, 3)
    e = A.pose_errors(fit_j, gt_j, fit_v, gt_v, fit_r, gt_r)
    np.testing.assert_allclose(e.joint_err_cm, 1.0, atol=1e-10)
    ref_v = [np.mean([np.linalg.norm(fit_v[i, k] - gt_v[i, k]) for k in range(v)]) * 100 for i in range(n)]
    np.testing.assert_allclose(e.vertex_err_cm, ref_v, rtol=1e-12)
    np.testing.assert_allclose(e.angle_err_deg, 7.0, atol=1e-6)
    with pytest.raises(ValueError, match="fitted and ground-truth verts must both have shape"):
        A.pose_errors(fit_j, gt_j, fit_v[:, :3], gt_v, fit_r, gt_r)


def test_bone_direction_error_against_loop_reference():
    """Per bone (parent -> child joint) the angle between the fitted and the true vector, averaged over the bones
    that have a length; bones that are points (a joint on its parent) are left out."""
    rng = np.random.default_rng(4)
    parents = np.array([-1, 0, 1, 1, 3, 4])
    rest = rng.normal(size=(6, 3))
    rest[5] = rest[4]  # a zero-length bone: no direction
    gt, fit = rng.normal(size=(3, 6, 3)), rng.normal(size=(3, 6, 3))
    out = A.bone_direction_error_deg(fit, gt, parents, rest)
    for i in range(3):
        angles = []
        for j in (1, 2, 3, 4):
            a, b = fit[i, j] - fit[i, parents[j]], gt[i, j] - gt[i, parents[j]]
            angles.append(math.degrees(math.acos(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b))))
        assert out[i] == pytest.approx(np.mean(angles), rel=1e-9)
    assert np.allclose(A.bone_direction_error_deg(gt, gt, parents, rest), 0.0, atol=1e-5)
    # the same bones shifted and scaled: no direction changes
    assert np.allclose(A.bone_direction_error_deg(2.0 * gt + 1.0, gt, parents, rest), 0.0, atol=1e-5)


def test_summarize_pseudo_labels_counts_and_means():
    rows = pa.table({
        "sample_id": ["a", "b", "c", "d", "e"],
        "status": ["ok", "ok", "filtered", "filtered", "failed"],
        "reason": ["", "", "loss_total above 0.2", "loss_total above 0.2", "no points"],
        "loss_total": [0.1, 0.3, 0.5, 0.6, None],
        "loss_data": [0.05, 0.1, 0.2, 0.3, None],
        "joint_err_cm": [2.0, 4.0, 9.0, 9.0, None],
        "bone_err_deg": [10.0, 20.0, 40.0, 40.0, None],
    })
    s = A.summarize_pseudo_labels(rows)
    assert (s.n, s.n_ok) == (5, 2)
    assert s.status_counts == {"ok": 2, "filtered": 2, "failed": 1}
    assert s.reason_counts == {"loss_total above 0.2": 2, "no points": 1}
    np.testing.assert_allclose(s.losses["loss_total"], [0.1, 0.3])
    assert set(s.losses) == {"loss_total", "loss_data"}
    assert s.mean_joint_err_cm == pytest.approx(3.0)
    assert math.isnan(s.mean_vertex_err_cm)
    assert s.mean_bone_err_deg == pytest.approx(15.0)  # the ok rows only
    empty = A.summarize_pseudo_labels([])
    assert (empty.n, empty.n_ok) == (0, 0)
