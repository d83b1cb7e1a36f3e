"""Per-sample rows, aggregation, failure-rate tables and metrics.parquet upserts."""
from __future__ import annotations

import math

import numpy as np
import pyarrow.parquet as pq
import pytest

from bat3r_core import evaluation as E
from bat3r_core.metrics import SampleMetrics


def _metrics(cd: float, mv: float, rot: float = math.nan) -> SampleMetrics:
    return SampleMetrics(cd_cm=cd, mv_cd_cm=mv, rot_err_deg=rot, icp_scale=1.0, icp_start_deg=0.0, mv_scale=1.0,
                         n_pred=100, n_gt=200)


def _write_iteration(run, iteration, cds, mvs, rots, split="test", failed=0):
    rows = [E.sample_row(f"s{iteration}-{i}", split, iteration, _metrics(c, m, r), azimuth_deg=10.0 * i,
                         pose_features=(0.1, 0.01, 0.5 * i), cluster=i % 2)
            for i, (c, m, r) in enumerate(zip(cds, mvs, rots))]
    rows += [E.sample_row(f"f{iteration}-{i}", split, iteration, None, status="empty", reason="no confident points")
             for i in range(failed)]
    E.write_sample_rows(run / f"iter-{iteration:02d}" / "evaluate", 0, rows)


def test_aggregate_definitions_against_hand_computation(tmp_path):
    cds, mvs, rots = [1.0, 3.0, 8.0, 4.0], [2.0, 6.0, 9.0, 5.0], [1.0, math.nan, 3.0, 5.0]
    _write_iteration(tmp_path, 0, cds, mvs, rots, failed=2)
    rows = E.aggregate(E.read_sample_rows(tmp_path))
    assert len(rows) == 1
    r = rows[0]
    assert (r["iteration"], r["split"], r["n"], r["n_failed"]) == (0, "test", 4, 2)
    assert r["mcd_cm"] == pytest.approx(4.0)
    assert r["rms_cd_cm"] == pytest.approx(math.sqrt((1 + 9 + 64 + 16) / 4))
    assert r["pct_mcd_over_5cm"] == pytest.approx(25.0)
    assert r["mv_mcd_cm"] == pytest.approx(5.5)
    assert r["mv_rms_cd_cm"] == pytest.approx(math.sqrt((4 + 36 + 81 + 25) / 4))
    assert r["pct_mv_over_5cm"] == pytest.approx(50.0)  # 5.0 is not > 5
    assert r["rot_err_deg"] == pytest.approx(3.0)        # NaN rotation errors are skipped
    assert r["median_cd_cm"] == pytest.approx(3.5)


def test_evaluate_run_writes_and_upserts_metrics(tmp_path):
    _write_iteration(tmp_path, 0, [6.0, 7.0], [7.0, 8.0], [10.0, 12.0])
    _write_iteration(tmp_path, 1, [2.0, 3.0], [3.0, 4.0], [2.0, 4.0])
    path = E.evaluate_run(tmp_path)
    assert path == tmp_path / "metrics.parquet"
    t = pq.read_table(path)
    assert set(E.METRICS_SCHEMA.names) <= set(t.column_names)
    assert t.column("iteration").to_pylist() == [0, 1]
    assert t.column("mcd_cm").to_pylist() == pytest.approx([6.5, 2.5])
    # an upsert of one (iteration, split) replaces that row only and keeps extra columns
    row = dict(t.to_pylist()[1], mcd_cm=99.0, variant="full")
    E.upsert_metrics(tmp_path, [row])
    t2 = E.read_metrics(tmp_path)
    assert t2.num_rows == 2
    assert t2.column("mcd_cm").to_pylist() == pytest.approx([6.5, 99.0])
    assert t2.column("variant").to_pylist() == [None, "full"]
    # recomputing from the per-sample rows restores the true value; no temporary files are left behind
    E.evaluate_run(tmp_path)
    assert E.read_metrics(tmp_path).column("mcd_cm").to_pylist() == pytest.approx([6.5, 2.5])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["iter-00", "iter-01", "metrics.parquet"]
    with pytest.raises(ValueError, match=r"metrics row 0 lacks column\(s\) \['n'"):
        E.upsert_metrics(tmp_path, [{"iteration": 2, "split": "test"}])


def test_cluster_breakdown(tmp_path):
    _write_iteration(tmp_path, 0, [1.0, 2.0, 6.0, 8.0], [1.0, 2.0, 6.0, 8.0], [0.0] * 4)
    rows = E.cluster_breakdown(E.read_sample_rows(tmp_path))
    assert [(r["cluster"], r["n"]) for r in rows] == [(0, 2), (1, 2)]
    assert rows[0]["mcd_cm"] == pytest.approx(3.5)  # cds 1 and 6
    assert rows[1]["pct_mcd_over_5cm"] == pytest.approx(50.0)  # cds 2 and 8


def test_failure_rates_against_a_loop():
    rng = np.random.default_rng(0)
    az = rng.uniform(-180, 180, 300)
    fd = rng.uniform(0, 2, 300)
    cd = rng.uniform(0, 10, 300)
    fr = E.failure_rates(az, fd, cd, f_dist_edges=[0, 0.5, 1.0, 2.0])
    count = np.zeros((3, 12), int)
    fail = np.zeros((3, 12), int)
    for a, f, c in zip(az, fd, cd):
        i = 0 if f < 0.5 else (1 if f < 1.0 else 2)
        j = int((a + 180) // 30)
        count[i, j] += 1
        fail[i, j] += c > 5
    np.testing.assert_array_equal(fr.count, count)
    np.testing.assert_array_equal(fr.failures, fail)
    np.testing.assert_allclose(fr.rate, fail / count)
    q = E.failure_rates(az, fd, cd, n_f_dist_bins=4)
    assert q.count.sum() == 300 and len(q.f_dist_edges) == 5
    assert np.all(np.abs(q.count.sum(1) - 75) <= 1)  # quantile bins hold equal counts
    empty = E.failure_rates(az[:1], fd[:1], cd[:1], f_dist_edges=[0, 1, 2])
    assert np.isnan(empty.rate).sum() == 2 * 12 - 1
    with pytest.raises(ValueError, match="must be 1-D of equal length"):
        E.failure_rates(az, fd[:5], cd)


def test_sample_row_checks():
    with pytest.raises(ValueError, match="status 'ok' needs metrics"):
        E.sample_row("a", "test", 0, None)
    with pytest.raises(ValueError, match="status 'empty' needs a reason"):
        E.sample_row("a", "test", 0, None, status="empty")
    r = E.sample_row("a", "test", 3, None, status="empty", reason="no points")
    assert math.isnan(r["cd_cm"]) and r["cluster"] == -1 and list(r) == E.SAMPLE_SCHEMA.names


def test_evaluate_run_on_an_empty_run(tmp_path):
    assert E.read_sample_rows(tmp_path).num_rows == 0
    path = E.evaluate_run(tmp_path)
    assert pq.read_table(path).num_rows == 0
    with pytest.raises(FileNotFoundError, match="does not exist"):
        E.evaluate_run(tmp_path / "missing")


def test_pseudo_label_errors_zero_for_the_true_pose_and_blind_to_global_placement(toy_rig, tmp_path):
    from bat3r_core.poses import sample_toy_natural_poses

    theta, _ = sample_toy_natural_poses(3, seed=404)
    gt = {f"s{i}": {"excess_rotations": theta[i]} for i in range(3)}
    fitted = theta.copy()
    fitted[:, 0] += [0.4, -1.0, 0.2]  # another root rotation = another global orientation: not a pose error
    fitted[2, toy_rig.joint_index("forearm.L")] += [0.6, 0.0, 0.0]  # a real pose error on sample 2
    rows = [{"sample_id": f"s{i}", "status": "ok", "excess_rotations": fitted[i].ravel().tolist()} for i in range(3)]
    rows.append({"sample_id": "s9", "status": "too_few_points", "excess_rotations": []})
    out = {r["sample_id"]: r for r in E.pseudo_label_errors(rows, gt, toy_rig)}
    assert set(out) == {"s0", "s1", "s2"}
    for s in ("s0", "s1"):
        assert out[s]["vertex_err_cm"] < 1e-6 and out[s]["joint_err_cm"] < 1e-6 and out[s]["angle_err_deg"] < 1e-6
    assert out["s2"]["vertex_err_cm"] > 0.3 and out["s2"]["angle_err_deg"] > 0.5
    # the stage writer: the same rows in pseudo_labels.parquet, and their means as the task's summary
    from bat3r_core.shards import write_shard

    stored = [{**r, "reason": ""} for r in rows]
    write_shard(tmp_path / "fit", 0, stored[:3])
    write_shard(tmp_path / "fit", 1, stored[3:])
    path, summary = E.write_pseudo_label_errors(tmp_path / "fit", gt, toy_rig, tmp_path / "evaluate")
    table = pq.read_table(path).to_pylist()
    assert path.name == E.PSEUDO_LABEL_FILE and sorted(r["sample_id"] for r in table) == ["s0", "s1", "s2"]
    assert summary["n"] == 3
    assert summary["vertex_err_cm"] == pytest.approx(out["s2"]["vertex_err_cm"] / 3, rel=1e-9, abs=1e-9)


def test_ground_truth_camera_sees_the_photo_through_the_crop():
    from bat3r_core.cameras import PinholeCamera, look_at
    from bat3r_core.predictor.collection import CropTransform

    R, t = look_at(np.array([2.0, 1.0, 3.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]))
    photo = PinholeCamera.from_fov(40.0, 120, 90, R=R, t=t, cx=57.0, cy=48.0)
    truth = {"K": photo.K, "camera_rotation": R, "camera_translation": t}
    crop = CropTransform(x0=10.0, y0=-5.0, size=80.0, resolution=64)
    cam = E.ground_truth_camera(truth, crop)
    points = np.random.default_rng(0).uniform(-0.5, 0.5, (50, 3))
    uv_crop, depth = cam.project(points)
    uv_photo, depth_photo = photo.project(points)
    np.testing.assert_allclose(uv_crop, crop.apply(uv_photo), atol=1e-9)
    np.testing.assert_allclose(depth, depth_photo)
    assert (cam.width, cam.height) == (64, 64)
