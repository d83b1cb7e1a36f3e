"""The pseudo-label diagnosis of ``benchmarks/bench_fit_oracle.py``: ground truth read back at the predicted points,
map errors in centimetres, substitution, and the fit-vs-rest-pose comparison."""
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import bench_fit_oracle as B  # noqa: E402

from bat3r_core.cameras import PinholeCamera, look_at  # noqa: E402
from bat3r_core.fitting.fit import PointCloudInstance  # noqa: E402
from bat3r_core.pointmaps import dual_point_maps  # noqa: E402
from bat3r_core.poses import sample_toy_natural_poses  # noqa: E402
from bat3r_core.skinning import skin  # noqa: E402

RES = 32


@pytest.fixture(scope="module")
def scene(toy_rig):
    """A posed toy seen from an off-centre crop camera, with its true maps as a 'prediction'."""
    theta, _ = sample_toy_natural_poses(1, seed=7, families=("gallop",))
    verts = skin(toy_rig.tensors(dtype=torch.float64), torch.as_tensor(theta)).vertices[0].numpy()
    R, t = look_at(np.array([3.5, 0.6, 1.0]), verts.mean(0), np.array([0.0, 1.0, 0.0]))
    cam = PinholeCamera.from_fov(40.0, RES, RES, R=R, t=t)
    cam = PinholeCamera(fx=cam.fx, fy=cam.fy, cx=cam.cx - 2.0, cy=cam.cy + 1.5, width=RES, height=RES, R=R, t=t)
    gt = {"K": np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]]), "camera_rotation": R,
          "camera_translation": t, "posed_vertices": verts, "excess_rotations": theta[0]}
    maps = dual_point_maps(verts, toy_rig.rest_vertices, toy_rig.faces, cam, 4, "world", nthreads=1)
    v, u, k = np.nonzero(maps.occupancy)
    inst = PointCloudInstance(sample_id="s0", posed_points=maps.P[v, u, k] - [0.0, 0.0, maps.object_depth],
                              canonical_points=maps.Q[v, u, k].astype(np.float64),
                              pixels=np.stack([u + 0.5, v + 0.5], 1), layers=k, confidence=np.full(len(v), 5.0))
    return inst, gt


def test_truth_is_read_back_at_the_predicted_pixels_and_layers(scene, toy_rig):
    inst, gt = scene
    truth = B.truth_at_points(inst, gt, toy_rig, RES)
    assert truth.occupied.all()
    np.testing.assert_allclose(truth.P, inst.posed_points, atol=1e-5)
    np.testing.assert_allclose(truth.Q, inst.canonical_points, atol=1e-5)
    e = B.map_errors(inst, truth)
    assert e["q_rms_cm"] < 1e-3 and max(e["p_rms_x_cm"], e["p_rms_y_cm"], e["p_rms_z_cm"]) < 1e-3


def test_truth_through_the_collection_crop(toy_rig, scene):
    """The model sees a crop of the photo: the truth is ray-cast with the crop's intrinsics, not the photo's."""
    from bat3r_core.predictor.collection import CropTransform

    _, gt = scene
    crop = CropTransform(x0=-3.0, y0=2.0, size=36.0, resolution=RES)
    K = crop.intrinsics(gt["K"])
    cam = PinholeCamera(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], width=RES, height=RES,
                        R=gt["camera_rotation"], t=gt["camera_translation"])
    maps = dual_point_maps(gt["posed_vertices"], toy_rig.rest_vertices, toy_rig.faces, cam, 4, "world", nthreads=1)
    v, u, k = np.nonzero(maps.occupancy)
    inst = PointCloudInstance(sample_id="s0", posed_points=maps.P[v, u, k] - [0.0, 0.0, maps.object_depth],
                              canonical_points=maps.Q[v, u, k].astype(np.float64),
                              pixels=np.stack([u + 0.5, v + 0.5], 1), layers=k)
    truth = B.truth_at_points(inst, gt, toy_rig, RES, crop)
    assert truth.occupied.all() and B.map_errors(inst, truth)["q_rms_cm"] < 1e-3
    uncropped = B.truth_at_points(inst, gt, toy_rig, RES)  # the photo's intrinsics: misaligned
    assert uncropped.occupied.mean() < 0.95 or B.map_errors(inst, uncropped)["q_rms_cm"] > 2.0


def test_map_errors_in_cm_per_axis_and_substitution(scene, toy_rig):
    inst, gt = scene
    truth = B.truth_at_points(inst, gt, toy_rig, RES)
    rng = np.random.default_rng(0)
    depth_noise = rng.normal(0.0, 0.2, len(inst.posed_points))
    bad = PointCloudInstance(**{**inst.__dict__, "canonical_points": inst.canonical_points + [0.1, 0.0, 0.0],
                                "posed_points": inst.posed_points + np.c_[0 * depth_noise, 0 * depth_noise,
                                                                          depth_noise] + [0.0, 0.0, 0.7]})
    e = B.map_errors(bad, truth)
    assert e["q_rms_cm"] == pytest.approx(10.0, abs=1e-3) and e["q_median_cm"] == pytest.approx(10.0, abs=1e-3)
    assert e["p_rms_x_cm"] < 1e-3 and e["p_rms_y_cm"] < 1e-3  # a translation is not an error
    assert e["p_rms_z_cm"] == pytest.approx(100 * depth_noise.std(), rel=1e-3)
    # a point off the true surface takes no part
    off = PointCloudInstance(**{**inst.__dict__, "layers": np.full(len(inst.layers), 3)})
    t_off = B.truth_at_points(off, gt, toy_rig, RES)
    assert 0 < t_off.occupied.sum() < len(inst.layers)
    s = B.substitute(off, t_off, true_p=False, true_q=True)
    assert len(s.canonical_points) == len(s.pixels) == len(s.confidence) == t_off.occupied.sum()
    fixed = B.substitute(bad, truth, true_p=True, true_q=True)
    np.testing.assert_allclose(fixed.canonical_points, inst.canonical_points, atol=1e-5)
    p = fixed.posed_points - fixed.posed_points.mean(0)
    np.testing.assert_allclose(p, inst.posed_points - inst.posed_points.mean(0), atol=1e-5)
    np.testing.assert_allclose(B.substitute(bad, truth, True, False).canonical_points, bad.canonical_points)


def test_pose_quality_against_the_rest_pose(scene, toy_rig):
    _, gt = scene
    theta = gt["excess_rotations"]
    wrong = theta.copy()
    wrong[toy_rig.joint_index("forearm.L")] += [1.5, 0.0, 0.0]
    rows = [{"sample_id": "s0", "status": "ok", "excess_rotations": theta.ravel().tolist()},
            {"sample_id": "s1", "status": "ok", "excess_rotations": (3 * wrong).ravel().tolist()},
            {"sample_id": "s2", "status": "too_few_points", "excess_rotations": []}]
    q = B.pose_quality(rows, {"s0": gt, "s1": gt, "s2": gt}, toy_rig)
    assert q["fitted"] == 2 and q["rest_pose_vertex_err_cm"] > 1.0
    assert q["pct_better_than_rest"] == 50.0  # the truth beats the rest pose, a wild pose does not
    # a fit a twentieth of the way from the rest pose to the truth beats the rest pose in vertex error, yet its bone
    # directions are hardly better than the rest pose's: the figure that shows how little it articulates
    near = [{"sample_id": "s3", "status": "ok", "excess_rotations": (0.05 * theta).ravel().tolist()}]
    q = B.pose_quality(rows[:1] + near, {"s0": gt, "s3": gt}, toy_rig)
    assert q["pct_better_than_rest"] == 100.0 and q["pct_bones_better_than_rest"] == 100.0
    fitted_errors, rest_errors = B.pose_errors(near, {"s3": gt}, toy_rig)
    fitted, rest = fitted_errors[0]["bone_err_deg"], rest_errors[0]["bone_err_deg"]
    assert 0.85 * rest < fitted < rest and rest > 5.0
    assert q["median_rest_pose_bone_err_deg"] == pytest.approx(rest)
    assert q["median_bone_err_deg"] == pytest.approx(0.5 * fitted, abs=1e-5)  # the median of ~0 and it



def test_filter_figures_read_the_runs_precision_check(tmp_path):
    from bat3r_core.runs import RunLayout
    from tasks.filter import PRECISION_FILE

    layout = RunLayout(tmp_path, "toy", "r")
    assert B.filter_figures(layout, 1) == {}  # no filter (ablation) or no truth: nothing to report
    layout.stage_dir(1, "evaluate").mkdir(parents=True)
    (layout.stage_dir(1, "evaluate") / PRECISION_FILE).write_text(
        '{"base_rate": 0.0625, "n": 384, "n_good": 24, "n_kept": 192, "n_kept_good": 16, '
        '"precision": 0.08333333333333333, "recall": 0.6666666666666666}')
    assert B.filter_figures(layout, 1) == {"filter_precision": 0.083, "filter_recall": 0.667, "filter_base_rate": 0.062,
                                           "filter_n_kept": 192, "filter_n_kept_good": 16}


def test_fitting_changes_for_a_sweep():
    from bat3r_core.catalog import fitting_preset
    from bat3r_core.config_utils import ConfigError

    base = fitting_preset("synthetic")
    changed = B.changed_fitting(base, {"weight_angle": 1, "steps": 50})
    assert changed.weight_angle == 1.0 and isinstance(changed.weight_angle, float) and changed.steps == 50
    assert changed.weight_edge == base.weight_edge and base.weight_angle == 1.0e-5  # the run's own stay as they were
    with pytest.raises(ConfigError, match="weight_angel"):
        B.changed_fitting(base, {"weight_angel": 1.0})
    with pytest.raises(ConfigError, match="steps"):
        B.changed_fitting(base, {"steps": "many"})


def test_error_scales_interpolate_between_truth_and_prediction(scene, toy_rig):
    inst, gt = scene
    truth = B.truth_at_points(inst, gt, toy_rig, RES)
    rng = np.random.default_rng(1)
    n = len(inst.posed_points)
    bad = PointCloudInstance(**{**inst.__dict__, "canonical_points": inst.canonical_points + rng.normal(0, 0.1, (n, 3)),
                                "posed_points": inst.posed_points + rng.normal(0, 0.05, (n, 3)) + [0.0, 0.0, 0.7]})
    full = B.map_errors(bad, truth)
    for scale in (0.0, 0.25, 1.0):
        e = B.map_errors(B.scale_errors(bad, truth, scale), truth)
        for key in ("q_rms_cm", "p_rms_x_cm", "p_rms_y_cm", "p_rms_z_cm"):
            assert e[key] == pytest.approx(scale * full[key], rel=1e-6, abs=1e-6), (scale, key)
    one = B.scale_errors(bad, truth, 1.0)
    np.testing.assert_allclose(one.canonical_points, bad.canonical_points)
    np.testing.assert_allclose(one.posed_points, bad.posed_points, atol=1e-12)  # the prediction, centroid kept
    zero = B.scale_errors(bad, truth, 0.0)
    np.testing.assert_allclose(zero.canonical_points, B.substitute(bad, truth, True, True).canonical_points)
    assert B.error_scale_version(0.25) == "errors_x0.25" and B.error_scale_version(1.0) == "errors_x1"
    with pytest.raises(ValueError, match="error scale"):
        B.scale_errors(bad, truth, -0.5)


def test_the_runs_filter_scored_on_refits(scene, toy_rig):
    """``refit_filter_precision``: the filter ranks the fits by their own quality columns and is scored against
    the truth — here a truthful fit (beats the rest pose) and a wild one; keeping the better half by residual
    Chamfer keeps the truthful one."""
    from bat3r_core.pseudo_labels import PseudoLabelFilterConfig

    inst, gt = scene
    theta = gt["excess_rotations"]
    wild = theta.copy()
    wild[toy_rig.joint_index("forearm.L")] += [1.5, 0.0, 0.0]
    base = {"status": "ok", "inlier_ratio": 0.9}
    rows = [{**base, "sample_id": "s0", "excess_rotations": theta.ravel().tolist(), "residual_chamfer_cm": 1.0},
            {**base, "sample_id": "s1", "excess_rotations": (3 * wild).ravel().tolist(),
             "residual_chamfer_cm": 9.0}]
    config = PseudoLabelFilterConfig(score="residual_chamfer_cm", keep_quantile=0.5, min_kept=1)
    got = B.refit_filter_precision(rows, [inst, inst], {"s0": gt, "s1": gt}, toy_rig, config)
    assert (got["n"], got["n_good"], got["n_kept"], got["n_kept_good"]) == (2, 1, 1, 1)
    assert got["precision"] == 1.0 and got["base_rate"] == 0.5


def test_ranking_figures_from_a_runs_fit_filter_and_error_files(tmp_path, scene, toy_rig):
    import pyarrow as pa
    import pyarrow.parquet as pq

    from bat3r_core import evaluation_truth, shards
    from bat3r_core.pseudo_labels import QUALITY_COLUMNS
    from bat3r_core.runs import RunLayout

    _, gt = scene
    theta = np.asarray(gt["excess_rotations"])
    wrong = theta.copy()
    wrong[toy_rig.joint_index("forearm.L")] += [1.5, 0.0, 0.0]
    layout = RunLayout(tmp_path, "toy", "r")
    assert B.ranking_figures(layout, 1, {"s0": gt, "s1": gt}, toy_rig) == {}  # no filter shards: nothing to rank
    fits = [{"sample_id": "s0", "status": "ok", "reason": "", "excess_rotations": theta.ravel().tolist()},
            {"sample_id": "s1", "status": "ok", "reason": "", "excess_rotations": (3 * wrong).ravel().tolist()}]
    shards.write_shard(layout.stage_dir(1, "fit"), 0, fits)
    # the good fit (s0) has the smaller residual but the smaller inlier ratio: residual ranks right, inliers wrong
    quality = [{"sample_id": s, "status": "ok", "reason": "", **{c: 1.0 for c in QUALITY_COLUMNS},
                "residual_chamfer_cm": r, "inlier_ratio": i} for s, r, i in (("s0", 1.0, 0.2), ("s1", 5.0, 0.9))]
    shards.write_shard(layout.stage_dir(1, "filter"), 0, quality)
    layout.stage_dir(1, "evaluate").mkdir(parents=True)
    errors = evaluation_truth.pseudo_label_errors(fits, {"s0": gt, "s1": gt}, toy_rig)
    pq.write_table(pa.Table.from_pylist(errors), layout.stage_dir(1, "evaluate") / evaluation_truth.PSEUDO_LABEL_FILE)
    figures = B.ranking_figures(layout, 1, {"s0": gt, "s1": gt}, toy_rig)
    assert figures["rank_base_rate"] == 0.5  # the true pose beats the rest pose, the wild one does not
    assert figures["rank_precision_q0.5_residual_chamfer_cm"] == 1.0
    assert figures["rank_precision_q0.5_inlier_ratio"] == 0.0
    assert np.isnan(figures["rank_rho_residual_chamfer_cm"])  # two fits: too few for a rank correlation


def test_refit_ranking_figures_match_the_runs_own_and_nan_is_left_out_of_the_record():
    """refit_ranking names its figures as ranking_figures does; a ρ over a constant column is NaN there and
    ``_finite`` leaves it out of what ``record`` gets."""
    fitted = [{"sample_id": s, "vertex_err_cm": e} for s, e in (("a", 1.0), ("b", 9.0), ("c", 2.0), ("d", 8.0))]
    rest = [{"sample_id": s, "vertex_err_cm": 5.0} for s in "abcd"]
    quality = [{"sample_id": s, "residual_chamfer_cm": r, "inlier_ratio": 0.5} for s, r in zip("abcd", (1, 4, 2, 3))]
    got = B.refit_ranking((fitted, rest), quality)
    assert got["rank_precision_q0.25_residual_chamfer_cm"] == 1.0   # the best quarter (a) beats the rest pose
    assert got["rank_rho_residual_chamfer_cm"] == pytest.approx(1.0)  # ranks 1, 4, 2, 3; deltas -4, 4, -3, 3 too
    assert np.isnan(got["rank_rho_inlier_ratio"])                    # constant column
    kept = B._finite(got)
    assert "rank_rho_inlier_ratio" not in kept and kept["rank_rho_residual_chamfer_cm"] == pytest.approx(1.0)


def test_a_bad_record_name_is_refused_before_the_work(capsys, tmp_path):
    """``--record-as`` becomes results/<name>.json: a name ``record`` would refuse after minutes of refitting
    (a dot, a slash) is refused when the arguments are parsed, naming the argument, before any run is read."""
    with pytest.raises(SystemExit) as exc:
        B.main(["--run-name", "no-such-run", "--record-as", "fit_oracle_depth_0.3", "--results-dir", str(tmp_path)])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--record-as" in err and "'fit_oracle_depth_0.3'" in err
    assert list(tmp_path.iterdir()) == []
