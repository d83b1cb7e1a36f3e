"""Per-sample rows, aggregation, failure-rate tables and metrics.parquet upserts."""
from __future__ import annotations

import math

import numpy as np
import pyarrow.parquet as pq
import pytest

from bat3r_core import evaluation as E
from bat3r_core import evaluation_truth as T
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


def test_bone_direction_error_sees_swing_and_not_twist(toy_rig):
    """Twisting a forearm 90° about its own bone barely moves the surface, and no point map shows it, yet a per-joint
    rotation error counts it three times a 30° swing of the same joint; the bone direction error counts the swing
    (30° on each of the bones below the forearm, averaged over the rig's bones) and hardly the twist."""
    from bat3r_core.poses import sample_toy_natural_poses

    theta, _ = sample_toy_natural_poses(1, seed=7, families=("gallop",))
    j = toy_rig.joint_index("forearm.L")
    truth = theta[0].copy()
    truth[j] = 0.0
    (child,) = np.flatnonzero(toy_rig.parents == j)
    axis = toy_rig.rest_joint_positions[child] - toy_rig.rest_joint_positions[j]
    axis = toy_rig.rest_transforms[j, :3, :3].T @ (axis / np.linalg.norm(axis))  # the bone in the joint's frame
    perpendicular = np.cross(axis, [0.0, 0.0, 1.0])
    twist, swing = truth.copy(), truth.copy()
    twist[j] = axis * np.pi / 2
    swing[j] = perpendicular / np.linalg.norm(perpendicular) * np.radians(30.0)
    gt = {"s": {"excess_rotations": truth}}
    bone, angle = {}, {}
    for name, pose in (("truth", truth), ("twist", twist), ("swing", swing)):
        rows = [{"sample_id": "s", "status": "ok", "excess_rotations": pose.ravel().tolist()}]
        (errors,) = T.pseudo_label_errors(rows, gt, toy_rig)
        bone[name], angle[name] = errors["bone_err_deg"], errors["angle_err_deg"]
    below = len(toy_rig.descendants(j)) - 1  # bones whose direction the swing turns by 30° (2: cannon, hoof)
    bones = int((toy_rig.parents >= 0).sum())
    assert bone["truth"] < 1e-4
    # 30° on those bones averaged over all, plus the small turn of the whole body the alignment gives every bone
    # (measured 3.18° against 2.31°)
    assert 30.0 * below / bones < bone["swing"] < 1.5 * 30.0 * below / bones, (bone, below, bones)
    assert angle["twist"] > 2.5 * angle["swing"] and bone["twist"] < 0.4 * bone["swing"], (bone, angle)


def test_pseudo_label_errors_zero_for_the_true_pose_and_blind_to_global_placement(toy_rig, tmp_path):
    from bat3r_core.poses import sample_toy_natural_poses

    theta, _ = sample_toy_natural_poses(3, seed=404)
    gt = {f"s{i}": {"excess_rotations": theta[i]} for i in range(3)}
    fitted = theta.copy()
    fitted[:, 0] += [0.4, -1.0, 0.2]  # another root rotation = another global orientation: not a pose error
    fitted[2, toy_rig.joint_index("forearm.L")] += [0.6, 0.0, 0.0]  # a real pose error on sample 2
    rows = [{"sample_id": f"s{i}", "status": "ok", "excess_rotations": fitted[i].ravel().tolist()} for i in range(3)]
    rows.append({"sample_id": "s9", "status": "too_few_points", "excess_rotations": []})
    out = {r["sample_id"]: r for r in T.pseudo_label_errors(rows, gt, toy_rig)}
    assert set(out) == {"s0", "s1", "s2"}
    for s in ("s0", "s1"):
        assert out[s]["vertex_err_cm"] < 1e-6 and out[s]["joint_err_cm"] < 1e-6 and out[s]["angle_err_deg"] < 1e-6
        assert out[s]["bone_err_deg"] < 1e-4
    assert out["s2"]["vertex_err_cm"] > 0.3 and out["s2"]["angle_err_deg"] > 0.5 and out["s2"]["bone_err_deg"] > 0.5
    # the stage writer: the same rows in pseudo_labels.parquet, and their means as the task's summary
    from bat3r_core.shards import write_shard

    stored = [{**r, "reason": ""} for r in rows]
    write_shard(tmp_path / "fit", 0, stored[:3])
    write_shard(tmp_path / "fit", 1, stored[3:])
    path, summary = T.write_pseudo_label_errors(tmp_path / "fit", gt, toy_rig, tmp_path / "evaluate")
    table = pq.read_table(path).to_pylist()
    assert path.name == T.PSEUDO_LABEL_FILE and sorted(r["sample_id"] for r in table) == ["s0", "s1", "s2"]
    assert summary["n"] == 3
    assert summary["vertex_err_cm"] == pytest.approx(out["s2"]["vertex_err_cm"] / 3, rel=1e-9, abs=1e-9)


def test_ground_truth_camera_sees_the_photo_through_the_crop():
    from bat3r_core.cameras import PinholeCamera, look_at
    from bat3r_core.predictor.collection import CropTransform

    R, t = look_at(np.array([2.0, 1.0, 3.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]))
    photo = PinholeCamera.from_fov(40.0, 120, 90, R=R, t=t, cx=57.0, cy=48.0)
    truth = {"K": photo.K, "camera_rotation": R, "camera_translation": t}
    crop = CropTransform(x0=10.0, y0=-5.0, size=80.0, resolution=64)
    cam = T.ground_truth_camera(truth, crop)
    points = np.random.default_rng(0).uniform(-0.5, 0.5, (50, 3))
    uv_crop, depth = cam.project(points)
    uv_photo, depth_photo = photo.project(points)
    np.testing.assert_allclose(uv_crop, crop.apply(uv_photo), atol=1e-9)
    np.testing.assert_allclose(depth, depth_photo)
    assert (cam.width, cam.height) == (64, 64)


# ------------------------------------------------------------------ mask IoUs without 3D ground truth


def test_mask_iou_and_predicted_mask_against_hand_computation():
    from bat3r_core.evaluation_masks import predicted_mask
    from bat3r_core.metrics import mask_iou

    a = np.zeros((8, 8), bool)
    a[0:4, 0:4] = True                      # 16 pixels
    b = np.zeros((8, 8), bool)
    b[2:6, 2:6] = True                      # 16 pixels, 4 shared: IoU 4 / 28
    assert mask_iou(a, b) == pytest.approx(4 / 28)
    assert mask_iou(a, a) == 1.0 and mask_iou(a, ~a) == 0.0
    assert mask_iou(np.zeros((3, 3), bool), np.zeros((3, 3), bool)) == 1.0
    with pytest.raises(ValueError, match="same shape"):
        mask_iou(a, b[:4])
    occ = np.zeros((8, 8, 2), np.float16)
    occ[..., 0][a] = 0.7
    occ[0, 0, 0] = 0.5                      # exactly 0.5 is not occupied (inference keeps > 0.5)
    occ[..., 1] = 0.9                       # deeper layers do not count
    pred = predicted_mask(occ)
    assert pred.sum() == 15 and not pred[0, 0]
    assert mask_iou(pred, b) == pytest.approx(4 / 27)


def _toy_view(toy_rig, scale=1.3):
    """A toy sample: pose, global similarity and camera, its ray-cast mask through the collection's crop, and the
    ground-truth fit row in the fit shards' convention (world = unscaled posed mesh, canonical frame)."""
    import torch

    from bat3r_core.cameras import PinholeCamera, look_at
    from bat3r_core.metrics import rotation_about_axis
    from bat3r_core.pointmaps import dual_point_maps
    from bat3r_core.poses import sample_toy_natural_poses
    from bat3r_core.predictor.collection import crop_to_square
    from bat3r_core.skinning import skin

    theta, _ = sample_toy_natural_poses(1, seed=7)
    theta = theta[0]
    r_g = rotation_about_axis(np.array([0.0, 1.0, 0.0]), 40.0)
    t_g = np.array([0.1, -0.05, 0.2])
    verts = skin(toy_rig.tensors(dtype=torch.float64), torch.as_tensor(theta)[None]).vertices[0].numpy()
    world = scale * verts @ r_g.T + t_g
    r_c, t_c = look_at(np.array([2.5, 3.0, 8.0]), world.mean(axis=0), np.array([0.0, 1.0, 0.0]))
    photo = PinholeCamera.from_fov(35.0, 640, 480, R=r_c, t=t_c)
    full = dual_point_maps(world, toy_rig.rest_vertices, toy_rig.faces, photo, num_layers=1).occupancy[..., 0]
    _, mask, crop = crop_to_square(np.zeros((480, 640, 3), np.uint8), full, 64)
    k = crop.intrinsics(photo.K)
    row = {"sample_id": "s0", "status": "ok", "reason": "", "excess_rotations": theta.ravel().tolist(),
           "fx": k[0, 0], "fy": k[1, 1], "cx": k[0, 2], "cy": k[1, 2], "width": 64, "height": 64,
           "camera_rotation": (r_c @ r_g).ravel().tolist(),
           "camera_translation": ((r_c @ t_g + t_c) / scale).tolist()}
    return mask, row


def test_reprojected_ground_truth_fit_matches_the_rendered_mask_and_a_wrong_camera_does_not(toy_rig):
    from bat3r_core.evaluation_masks import fit_silhouette
    from bat3r_core.metrics import mask_iou

    mask, row = _toy_view(toy_rig)
    assert 300 < mask.sum() < 0.9 * mask.size
    sil = fit_silhouette(toy_rig, row)
    assert sil.shape == (64, 64)
    assert mask_iou(sil, mask) > 0.97       # photo mask resampled to the crop (nearest) vs ray casting at the crop
    t = np.asarray(row["camera_translation"])
    shifted = {**row, "camera_translation": (t + [1.0, 0.0, 0.0]).tolist()}  # the body's length sideways
    assert mask_iou(fit_silhouette(toy_rig, shifted), mask) < 0.2
    flipped = {**row, "camera_rotation": (np.diag([-1.0, -1.0, 1.0]) @ np.reshape(row["camera_rotation"], (3, 3))
                                          ).ravel().tolist(),
               "camera_translation": (np.diag([-1.0, -1.0, 1.0]) @ t).tolist()}  # upside-down about the centre
    assert mask_iou(fit_silhouette(toy_rig, flipped), mask) < 0.5
    assert fit_silhouette(toy_rig, {**row, "status": "too_few_points"}) is None


def test_collection_rows_aggregate_into_metrics_rows(toy_rig, tmp_path):
    from bat3r_core import evaluation_masks as M
    from bat3r_core.metrics import mask_iou
    from bat3r_core.shards import write_shard

    mask0, fit0 = _toy_view(toy_rig)
    mask1 = np.zeros((64, 64), bool)
    mask1[10:30, 10:40] = True                                   # 600 pixels
    mask2 = mask1.copy()
    occ = np.zeros((3, 64, 64, 2), np.float16)
    occ[0, ..., 0][mask0] = 0.9                                  # s0: the whole mask: IoU 1
    occ[1, 10:20, 10:40, 0] = 0.8                                # s1: half of it: IoU 300 / 600
    write_shard(tmp_path / "pred", 0, [{"sample_id": s, "status": st, "reason": rs} for s, st, rs in
                                       [("s0", "ok", ""), ("s1", "ok", ""), ("s2", "empty", "no foreground")]],
                arrays={"occupancy": occ})
    write_shard(tmp_path / "coll", 0, [{"sample_id": s, "status": "ok", "reason": ""} for s in ("s0", "s1", "s2")],
                arrays={"mask": np.stack([mask0, mask1, mask2])})
    fits = [fit0, {**fit0, "sample_id": "s1", "status": "too_few_points", "reason": "3 points"}]
    write_shard(tmp_path / "fit", 0, fits)
    M.evaluate_collection_shard(tmp_path / "pred", 0, tmp_path / "coll", tmp_path / "fit", toy_rig, 1,
                                tmp_path / "run" / "iter-01" / "evaluate" / M.COLLECTION_ROWS_DIR)
    # iteration 0: no fits of its own
    M.evaluate_collection_shard(tmp_path / "pred", 0, tmp_path / "coll", None, None, 0,
                                tmp_path / "run" / "iter-00" / "evaluate" / M.COLLECTION_ROWS_DIR)
    rows = {(r["iteration"], r["sample_id"]): r for r in M.read_collection_rows(tmp_path / "run").to_pylist()}
    assert len(rows) == 6
    assert rows[1, "s0"]["pred_mask_iou"] == pytest.approx(1.0)
    assert rows[1, "s1"]["pred_mask_iou"] == pytest.approx(0.5) and rows[1, "s1"]["pred_pixels"] == 300
    assert math.isnan(rows[1, "s2"]["pred_mask_iou"]) and rows[1, "s2"]["status"] == "empty"
    fit_iou = mask_iou(M.fit_silhouette(toy_rig, fit0), mask0)
    assert rows[1, "s0"]["fit_status"] == "ok" and rows[1, "s0"]["fit_mask_iou"] == pytest.approx(fit_iou)
    assert rows[1, "s1"]["fit_status"] == "too_few_points" and rows[1, "s2"]["fit_status"] == "no_fit"
    assert rows[0, "s0"]["fit_status"] == "no_fit"
    _write_iteration(tmp_path / "run", 1, [1.0, 3.0], [2.0, 4.0], [1.0, 2.0])
    E.evaluate_run(tmp_path / "run")
    table = pq.read_table(tmp_path / "run" / "metrics.parquet").to_pylist()
    by_key = {(r["iteration"], r["split"]): r for r in table}
    assert set(by_key) == {(0, "collection"), (1, "collection"), (1, "test")}
    c1, c0 = by_key[1, "collection"], by_key[0, "collection"]
    assert (c1["n"], c1["n_failed"], c1["n_fits"]) == (2, 1, 1)
    assert c1["pred_mask_iou"] == pytest.approx(0.75) and c1["fit_mask_iou"] == pytest.approx(fit_iou)
    assert c0["pred_mask_iou"] == pytest.approx(0.75) and c0["n_fits"] == 0 and c0["fit_mask_iou"] is None
    assert c1["mcd_cm"] is None                                  # no 3D ground truth on the collection
    assert by_key[1, "test"]["mcd_cm"] == pytest.approx(2.0) and by_key[1, "test"]["pred_mask_iou"] is None


# ------------------------------------------------------------------ what the test mCD can reach at a resolution


def _floor_sample(toy_rig, theta, resolution, seed):
    """Ground truth and a collection row of the toy in pose ``theta``, seen through a mask-fitted crop."""
    import torch

    from bat3r_core.cameras import PinholeCamera, look_at
    from bat3r_core.metrics import rotation_about_axis
    from bat3r_core.pointmaps import dual_point_maps
    from bat3r_core.predictor.collection import crop_box_for_mask
    from bat3r_core.skinning import skin

    r_g = rotation_about_axis(np.array([0.0, 1.0, 0.0]), 70.0 + seed)
    verts = skin(toy_rig.tensors(dtype=torch.float64), torch.as_tensor(theta)[None]).vertices[0].numpy()
    world = verts @ r_g.T + np.array([0.3, 0.0, -0.2])
    r_c, t_c = look_at(np.array([3.0, 1.5, 6.0]), world.mean(axis=0), np.array([0.0, 1.0, 0.0]))
    photo = PinholeCamera.from_fov(35.0, 256, 256, R=r_c, t=t_c)
    mask = dual_point_maps(world, toy_rig.rest_vertices, toy_rig.faces, photo, num_layers=1).occupancy[..., 0]
    x0, y0, size = crop_box_for_mask(mask)
    gt = {"K": photo.K, "camera_rotation": r_c, "camera_translation": t_c, "posed_vertices": world,
          "global_rotation": r_g}
    row = {"sample_id": f"s{seed}", "status": "ok", "crop_x0": x0, "crop_y0": y0, "crop_size": size,
           "resolution": resolution}
    return gt, row


def test_map_floors_fall_with_resolution_and_only_the_rest_pose_pays_for_the_pose(toy_rig):
    from bat3r_core.poses import sample_toy_natural_poses

    theta, _ = sample_toy_natural_poses(4, seed=11)
    theta[0] = 0.0                                       # sample 0 is in the rest pose
    floors = {}
    for res in (32, 64):
        gts, rows = {}, []
        for i in range(4):
            gt, row = _floor_sample(toy_rig, theta[i], res, i)
            gts[row["sample_id"]] = gt
            rows.append(row)
        rows.append({"sample_id": "s9", "status": "too_few_points"})          # skipped
        rows.append({**rows[0], "sample_id": "unknown"})                     # no ground truth: skipped
        floors[res] = {r["sample_id"]: r for r in T.map_floor_rows(rows, gts, toy_rig, num_layers=4, seed=3)}
    for res, out in floors.items():
        assert set(out) == {"s0", "s1", "s2", "s3"}
        # the rest pose is its own best rest-pose prediction: both ideal maps are the same map
        assert out["s0"]["rest_pose_map_cd_cm"] == pytest.approx(out["s0"]["perfect_map_cd_cm"], abs=1e-3)
        for s in ("s1", "s2", "s3"):
            assert out[s]["rest_pose_map_cd_cm"] > out[s]["perfect_map_cd_cm"] + 0.5
        assert 100 < out["s1"]["n_points"] < res * res * 4
    # a finer map holds ~4x the points, so its perfect-prediction floor drops markedly; it is never 0 at 32 px
    for s in ("s0", "s1", "s2", "s3"):
        assert floors[64][s]["n_points"] > 3 * floors[32][s]["n_points"]
        assert floors[64][s]["perfect_map_cd_cm"] < 0.75 * floors[32][s]["perfect_map_cd_cm"]
        assert floors[32][s]["perfect_map_cd_cm"] > 2.0


# ------------------------------------------------------------------ how a prediction is off, not only how far


def _crafted_maps(rng, h=4, w=5, k=2, depth=5.0):
    """Exact camera-frame maps of a crafted scene: every pixel occupied in both layers, layer 1 behind layer 0."""
    p = rng.normal(size=(h, w, k, 3)) * 0.3
    p[..., 2] = depth + rng.uniform(-0.4, 0.4, size=(h, w, k))
    p[..., 1, 2] += 0.6
    q = rng.normal(size=(h, w, k, 3))
    return p, q, np.ones((h, w, k), bool)


def test_map_errors_against_hand_computation():
    rng = np.random.default_rng(4)
    p, q, occ = _crafted_maps(rng)
    rel = p - np.array([0.0, 0.0, 5.0])            # what the network predicts: relative to the object depth
    exact = T.map_errors(rel, q, occ.astype(np.float32), p, q, occ, object_depth=5.0)
    assert np.abs(exact.depth).max() < 1e-12 and np.abs(exact.lateral).max() < 1e-12
    assert exact.depth_correlation == pytest.approx(1.0) and exact.occupancy_iou == 1.0

    off = rel.copy()
    off[..., 0] += 0.03                             # 3 cm to the side, 4 cm deeper, 12 cm off in Q everywhere
    off[..., 2] += 0.04
    prob = np.full(occ.shape, 0.9, np.float32)
    prob[0, 0, 0] = 0.2                             # one true entry missed
    truth_occ = occ.copy()
    truth_occ[3, 4, 1] = False                      # one predicted entry that the truth does not have
    m = T.map_errors(off, q + np.array([0.0, 0.12, 0.0]), prob, p, q, truth_occ, object_depth=5.0)
    n = occ.size - 2
    assert len(m.depth) == n
    np.testing.assert_allclose(m.depth, 0.04, atol=1e-9)
    np.testing.assert_allclose(m.lateral, 0.03, atol=1e-9)
    np.testing.assert_allclose(m.lateral_bias, [0.03, 0.0], atol=1e-9)   # the whole map shifted 3 cm sideways
    np.testing.assert_allclose(exact.lateral_bias, [0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(m.canonical, 0.12, atol=1e-9)
    assert m.occupancy_iou == pytest.approx(n / occ.size)
    assert m.depth_correlation == pytest.approx(1.0)   # a constant offset keeps the depth order

    # the same relative depths mirrored about their mean: the near flank predicted far
    mean_z = rel[..., 2].mean()
    flipped = rel.copy()
    flipped[..., 2] = 2 * mean_z - rel[..., 2]
    r = T.map_errors(flipped, q, occ.astype(np.float32), p, q, occ, object_depth=5.0)
    assert r.depth_correlation == pytest.approx(-1.0)
    np.testing.assert_allclose(r.depth, 2 * np.abs(rel[..., 2] - mean_z).ravel(), atol=1e-9)

    with pytest.raises(ValueError, match="share"):
        T.map_errors(rel[:, :4], q, occ, p, q, occ, object_depth=5.0)


def test_summarise_map_errors_tail_share_and_reversed_images_by_hand():
    def errors(depth_cm, corr):
        d = np.asarray(depth_cm, np.float64) / 100.0
        return T.MapErrors(depth=d, lateral=np.zeros_like(d), canonical=d * 2, depth_correlation=corr,
                           occupancy_iou=0.5)

    even = [errors([1.0] * 10, 0.9), errors([1.0] * 10, 0.8)]
    s = T.summarise_map_errors(even)
    assert s["depth_err_tail_share"] == pytest.approx(0.1)       # 2 of 20 entries carry 2 of 20 units
    assert s["depth_err_median_cm"] == pytest.approx(1.0) and s["depth_err_rms_cm"] == pytest.approx(1.0)
    assert s["depth_reversed_pct"] == 0.0 and s["n_images"] == 2

    gross = [errors([1.0] * 9 + [10.0], 0.7), errors([1.0] * 10, -0.4), errors([], math.nan)]
    s = T.summarise_map_errors(gross)
    # 20 entries: the worst 2 are 10 cm and 1 cm → (100 + 1) / (19 + 100)
    assert s["depth_err_tail_share"] == pytest.approx(101 / 119)
    assert s["depth_err_rms_cm"] == pytest.approx(math.sqrt(119 / 20))
    assert s["canonical_err_median_cm"] == pytest.approx(2.0)
    assert s["depth_reversed_pct"] == pytest.approx(50.0)           # of the 2 images with a correlation
    assert s["occupancy_iou"] == pytest.approx(0.5)
    assert s["lateral_bias_y_cm"] == 0.0 and s["lateral_bias_abs_cm"] == 0.0
    # one image shifted 6 cm up (camera y down: -6), one 2 cm sideways: the mean shift and the mean shift size
    shifted = [T.MapErrors(depth=np.zeros(3), lateral=np.full(3, 0.06), canonical=np.zeros(3), depth_correlation=1.0,
                           occupancy_iou=1.0, lateral_bias=np.array([0.0, -0.06])),
               T.MapErrors(depth=np.zeros(3), lateral=np.full(3, 0.02), canonical=np.zeros(3), depth_correlation=1.0,
                           occupancy_iou=1.0, lateral_bias=np.array([0.02, 0.0]))]
    s = T.summarise_map_errors(shifted)
    assert s["lateral_bias_x_cm"] == pytest.approx(1.0) and s["lateral_bias_y_cm"] == pytest.approx(-3.0)
    assert s["lateral_bias_abs_cm"] == pytest.approx(4.0)
    with pytest.raises(ValueError, match="tail"):
        T.summarise_map_errors(even, tail=1.5)
    with pytest.raises(ValueError, match="no image"):
        T.summarise_map_errors([])


def test_prediction_map_errors_of_exact_and_depth_reversed_predictions(toy_rig, tmp_path):
    """Inference shards holding the exact maps score 0 everywhere; the same maps with the depth order mirrored
    are all reversed, with the depth error the mirroring puts there; unpredicted or unknown samples are skipped."""
    from bat3r_core import shards
    from bat3r_core.pointmaps import dual_point_maps
    from bat3r_core.poses import sample_toy_natural_poses
    from bat3r_core.predictor.collection import crop_transform_from_row

    theta, _ = sample_toy_natural_poses(3, seed=5)
    gts, rows, exact, flipped = {}, [], [], []
    for i in range(3):
        gt, row = _floor_sample(toy_rig, theta[i], 32, i)
        gts[row["sample_id"]] = gt
        rows.append(row)
        cam = T.ground_truth_camera(gt, crop_transform_from_row(row))
        m = dual_point_maps(gt["posed_vertices"], toy_rig.rest_vertices, toy_rig.faces, cam, num_layers=2)
        rel = np.where(m.occupancy[..., None], m.P - np.array([0.0, 0.0, m.object_depth], np.float32), 0.0)
        exact.append((rel, np.where(m.occupancy[..., None], m.Q, 0.0), m.occupancy.astype(np.float32)))
        f = rel.copy()
        f[..., 2] = np.where(m.occupancy, -rel[..., 2], 0.0)
        flipped.append((f, exact[-1][1], exact[-1][2]))
    table = [{"sample_id": r["sample_id"], "status": "ok", "reason": ""} for r in rows]
    table.append({"sample_id": "nobody", "status": "ok", "reason": ""})           # no ground truth: skipped
    for name, maps in (("exact", exact), ("flipped", flipped)):
        maps = maps + [tuple(np.zeros_like(a) for a in maps[0])]
        shards.write_shard(tmp_path / name, 0, table, {
            "posed_points": np.stack([m[0] for m in maps]).astype(np.float16),
            "canonical_points": np.stack([m[1] for m in maps]).astype(np.float16),
            "occupancy": np.stack([m[2] for m in maps]).astype(np.float16)})
    s = T.summarise_map_errors(T.prediction_map_errors(tmp_path / "exact", rows, gts, toy_rig))
    assert s["n_images"] == 3 and s["occupancy_iou"] == 1.0 and s["depth_reversed_pct"] == 0.0
    assert s["depth_err_rms_cm"] < 0.2 and s["lateral_err_rms_cm"] < 0.2 and s["canonical_err_rms_cm"] < 0.2  # f16
    errs = T.prediction_map_errors(tmp_path / "flipped", rows, gts, toy_rig)
    assert T.summarise_map_errors(errs)["depth_reversed_pct"] == 100.0
    for (rel, _, occ), e in zip(exact, errs):
        np.testing.assert_allclose(e.depth, 2 * np.abs(rel[occ > 0.5][:, 2]), atol=2e-3)
    with pytest.raises(ValueError, match="predicted at 32 px"):
        T.prediction_map_errors(tmp_path / "exact", [{**rows[0], "resolution": 64}], gts, toy_rig)


def test_mask_agreement_of_the_true_pose_beats_its_rest_pose_and_the_rest_pose_gains_nothing(toy_rig):
    """pseudo_labels.mask_agreement: IoU of the fit's silhouette with the mask, and its gain over the same fit with
    the articulation undone, against hand-computed IoUs of the ray-cast silhouettes."""
    from bat3r_core import pseudo_labels as PL
    from bat3r_core.evaluation_masks import fit_silhouette
    from bat3r_core.metrics import mask_iou

    mask, row = _toy_view(toy_rig)
    j = toy_rig.num_joints
    theta = np.asarray(row["excess_rotations"]).reshape(j, 3).copy()
    theta[np.asarray(toy_rig.parents) >= 0] = 0.0
    rest = {**row, "sample_id": "rest", "excess_rotations": theta.ravel().tolist()}
    rest_iou = mask_iou(fit_silhouette(toy_rig, rest), mask)
    rows = [row, rest, {**row, "sample_id": "nomask"}, {**row, "sample_id": "bad", "status": "too_few_points"},
            {**row, "sample_id": "small", "width": 32, "height": 32}]
    got = PL.mask_agreement(rows, toy_rig, [mask, mask, None, mask, mask])
    assert got[0][0] == pytest.approx(mask_iou(fit_silhouette(toy_rig, row), mask)) and got[0][0] > 0.97
    assert got[0][1] == pytest.approx(got[0][0] - rest_iou) and got[0][1] > 0.03  # the pose explains the mask
    assert got[1] == (pytest.approx(rest_iou), pytest.approx(0.0, abs=1e-12))       # the rest pose gains nothing
    assert all(math.isnan(v) for k in (2, 3, 4) for v in got[k])                     # no mask, no fit, other size
    q = PL.quality_rows(rows[:2], toy_rig, [None, None], [mask, mask])
    assert q[0]["mask_iou"] == pytest.approx(got[0][0]) and q[1]["mask_iou_gain"] == pytest.approx(0.0, abs=1e-12)
    assert all(math.isnan(r["mask_iou"]) for r in PL.quality_rows(rows[:2], toy_rig, [None, None]))
    with pytest.raises(ValueError, match="one per fit row"):
        PL.quality_rows(rows[:2], toy_rig, [None, None], [mask])
