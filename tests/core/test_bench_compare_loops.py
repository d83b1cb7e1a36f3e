"""``benchmarks/compare_loops.py``: a loop variant's run figures next to a recorded fidelity benchmark."""
import json
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import compare_loops as C  # noqa: E402


def _fake_run(root: Path, name: str, mcd: list[float]) -> Path:
    run = root / "toy" / name
    run.mkdir(parents=True)
    rows = [{"iteration": i, "split": "test", "mcd_cm": m, "rot_err_deg": 20.0 + i} for i, m in enumerate(mcd)]
    rows.append({"iteration": 1, "split": "collection", "mcd_cm": None, "rot_err_deg": None})
    pq.write_table(pa.Table.from_pylist(rows), run / "metrics.parquet")
    ev = run / "iter-01" / "evaluate"
    ev.mkdir(parents=True)
    (ev / "pseudo_label_filter.json").write_text(json.dumps({"precision": 0.25, "base_rate": 0.125, "n": 8}))
    pq.write_table(pa.Table.from_pylist([{"sample_id": str(k), "vertex_err_cm": e}
                                         for k, e in enumerate([9.0, 11.0, 13.0, None])]),
                   ev / "pseudo_labels.parquet")
    filtered = run / "iter-01" / "filter"
    filtered.mkdir(parents=True)
    pq.write_table(pa.Table.from_pylist([{"sample_id": str(k), "mask_iou": m, "mask_iou_gain": g} for k, (m, g) in
                                         enumerate([(0.5, 0.1), (0.7, -0.1), (0.9, 0.3), (None, None)])]),
                   filtered / "part-00000.parquet")
    fit = run / "iter-01" / "fit"
    fit.mkdir(parents=True)
    theta = [[0.5, 0.0, 0.0] + [0.0, 0.1, 0.0] * 2, [0.0] * 3 + [0.3, 0.0, 0.4, 0.0, 0.0, 0.0], None]
    pq.write_table(pa.Table.from_pylist([{"status": st, "excess_rotations": t} for st, t in
                                         zip(["ok", "ok", "too_few_points"], theta)]), fit / "part-00000.parquet")
    return run


def test_variant_figures_sit_next_to_the_benchmark_arms(tmp_path):
    results = tmp_path / "results"
    results.mkdir()
    (results / "fid.json").write_text(json.dumps({
        "mcd_loop_iter2": 11.0, "mcd_control_iter1": 10.5, "mcd_control_iter2": 10.4, "mcd_oracle_iter2": 10.3,
        "rot_err_deg_control_iter2": 25.0, "mcd_phi0_on_collection": 10.8, "machine": "x"}))
    _fake_run(tmp_path / "runs", "good", [10.9, 10.6, 10.2])
    _fake_run(tmp_path / "runs", "bad", [10.9, 10.8, 10.7])
    truth = tmp_path / "ground_truth.npz"
    keys = ("global_scale", "global_rotation", "global_translation", "camera_rotation", "camera_translation", "K",
            "posed_vertices")
    np.savez(truth, sample_id=np.array(["a", "b"]), excess_rotations=np.array([[0.0] * 3 + [0.2, 0.0, 0.0],
                                                                               [1.0, 0.0, 0.0] + [0.0, 0.0, 0.4]]),
             **{k: np.zeros(2) for k in keys})
    figures = C.main(["--fidelity", "fid", "--runs", "good:sil", "--runs", "bad", "--truth", str(truth),
                      "--storage-root",
                      str(tmp_path / "runs"), "--record-as", "variants", "--results-dir", str(results)])
    assert figures["mcd_sil_iter2"] == 10.2 and figures["rot_err_deg_sil_iter1"] == 21.0
    assert figures["gap_to_control_cm_sil"] == pytest.approx(-0.2) and figures["gap_to_control_cm_bad"] == 0.3
    assert figures["filter_precision_sil_iter1"] == 0.25 and figures["filter_base_rate_bad_iter1"] == 0.125
    assert figures["median_fit_vertex_err_cm_sil_iter1"] == 11.0  # the unfitted row (None) is left out
    assert figures["median_fit_mask_iou_sil_iter1"] == 0.7 and figures["median_fit_mask_iou_gain_bad_iter1"] == 0.1
    # non-root joints of the ok fits: 0.1, 0.1, 0.5, 0 rad (the root's 0.5 rad and the unfitted row left out)
    assert figures["fit_joint_angle_deg_sil_iter1"] == round(float(np.degrees(0.7 / 4)), 1)
    assert figures["truth_joint_angle_deg"] == round(float(np.degrees(0.3)), 1)  # 0.2 and 0.4 rad, roots left out
    assert figures["mcd_control_iter2"] == 10.4 and "mcd_phi0_on_collection" not in figures
    saved = json.loads((results / "variants.json").read_text())
    assert "sil (good): iteration 2 test mCD 10.20 cm against the control's 10.40" in saved["notes"]
    assert "beats the control" in saved["notes"] and "behind the control" in saved["notes"]
    assert figures["gap_recovered_sil"] == pytest.approx(2.0)  # 0.2 cm past the control of a 0.1 cm gap

    # a one-iteration variant against the benchmark's iteration 1 (no oracle there: no share of the gap)
    _fake_run(tmp_path / "runs", "short", [10.9, 10.45])
    figures = C.main(["--fidelity", "fid", "--runs", "short", "--storage-root", str(tmp_path / "runs"),
                      "--iteration", "1", "--record-as", "variants", "--results-dir", str(results)])
    assert figures["gap_to_control_cm_short"] == pytest.approx(-0.05) and "gap_recovered_short" not in figures
    with pytest.raises(SystemExit, match="no control figure at iteration 3"):
        C.main(["--fidelity", "fid", "--runs", "short", "--storage-root", str(tmp_path / "runs"),
                "--iteration", "3", "--record-as", "variants", "--results-dir", str(results)])


def test_a_random_poses_arm_from_phi0_counts_as_one_round(tmp_path):
    results = tmp_path / "results"
    results.mkdir()
    (results / "fid.json").write_text(json.dumps({"mcd_control_iter1": 10.5, "mcd_oracle_iter1": 10.0}))
    for name, iterations, random_poses in (("rp", 0, True), ("rp-scratch", 0, False)):
        run = _fake_run(tmp_path / "runs", name, [10.2])
        (run / "iter-00" / "plan").mkdir(parents=True)
        pq.write_table(pa.Table.from_pylist([{"sample_id": "j0", "excess_rotations": [0.3, 0, 0, 0, 0.2, 0]}]),
                       run / "iter-00" / "plan" / "part-00000.parquet")
        (run / "manifest.json").write_text(json.dumps({"config": {
            "ablations": {"random_poses": random_poses},
            "parameters": {"iterations": iterations, "init_predictor": "/x/predictor.pt"}}}))
    figures = C.main(["--fidelity", "fid", "--runs", "rp", "--runs", "rp-scratch", "--storage-root",
                      str(tmp_path / "runs"), "--iteration", "1", "--record-as", "v", "--results-dir", str(results)])
    assert figures["mcd_rp_iter1"] == 10.2 and "mcd_rp_iter0" not in figures
    assert figures["fit_joint_angle_deg_rp_iter1"] == round(float(np.degrees(0.2)), 1)  # the random poses' joints
    assert figures["gap_to_control_cm_rp"] == pytest.approx(-0.3) and figures["gap_recovered_rp"] == pytest.approx(0.6)
    assert figures["mcd_rp_scratch_iter0"] == 10.2 and "gap_to_control_cm_rp_scratch" not in figures


def test_the_fits_bone_directions_against_the_hidden_poses(tmp_path, toy_rig):
    """With --truth and a run whose manifest names its asset, each iteration's ok fits are scored by bone direction
    against the true poses and next to the rest pose: an exact fit scores 0 and beats it, a rest-pose fit ties it
    (not counted as beating it)."""
    from bat3r_core.evaluation_truth import pseudo_label_errors
    from bat3r_core.poses import sample_toy_natural_poses
    from bat3r_core.rig_io import save_rig_glb

    results = tmp_path / "results"
    results.mkdir()
    (results / "fid.json").write_text(json.dumps({"mcd_control_iter1": 10.5, "mcd_oracle_iter1": 10.0}))
    asset = save_rig_glb(toy_rig, tmp_path / "toy.glb")
    run = _fake_run(tmp_path / "runs", "variant", [10.9, 10.4])
    (run / "manifest.json").write_text(json.dumps({"config": {"assets": {"asset": str(asset)}}}))
    theta, _ = sample_toy_natural_poses(2, seed=3, families=("gallop",))
    truth = tmp_path / "ground_truth.npz"
    keys = ("global_scale", "global_rotation", "global_translation", "camera_rotation", "camera_translation", "K",
            "posed_vertices")
    np.savez(truth, sample_id=np.array(["a", "b"]), excess_rotations=theta, **{k: np.zeros(2) for k in keys})
    rows = [{"sample_id": "a", "status": "ok", "excess_rotations": theta[0].ravel().tolist()},
            {"sample_id": "b", "status": "ok", "excess_rotations": np.zeros(theta[1].size).tolist()},
            {"sample_id": "c", "status": "too_few_points", "excess_rotations": None}]
    pq.write_table(pa.Table.from_pylist(rows), run / "iter-01" / "fit" / "part-00000.parquet")
    figures = C.main(["--fidelity", "fid", "--runs", "variant", "--truth", str(truth), "--storage-root",
                      str(tmp_path / "runs"), "--iteration", "1", "--record-as", "v", "--results-dir", str(results)])
    truth_rows = {"a": {"excess_rotations": theta[0]}, "b": {"excess_rotations": theta[1]}}
    rest_b = pseudo_label_errors(rows[1:2], truth_rows, toy_rig)[0]["bone_err_deg"]
    rest_a = pseudo_label_errors([{**rows[0], "excess_rotations": rows[1]["excess_rotations"]}], truth_rows,
                                 toy_rig)[0]["bone_err_deg"]
    assert rest_a > 5 and rest_b > 5
    assert figures["median_fit_bone_err_deg_variant_iter1"] == pytest.approx(round(rest_b / 2, 2), abs=0.006)
    assert figures["median_rest_pose_bone_err_deg_variant_iter1"] == pytest.approx(round((rest_a + rest_b) / 2, 2),
                                                                                abs=0.006)
    assert figures["pct_bones_better_than_rest_variant_iter1"] == 50.0


def test_a_missing_run_or_benchmark_is_named(tmp_path):
    results = tmp_path / "results"
    results.mkdir()
    with pytest.raises(SystemExit, match="nope.json does not exist"):
        C.main(["--fidelity", "nope", "--runs", "x", "--storage-root", str(tmp_path), "--record-as", "v",
                "--results-dir", str(results)])
    (results / "fid.json").write_text(json.dumps({"mcd_control_iter1": 10.0}))
    with pytest.raises(FileNotFoundError, match=r"never-ran/metrics.parquet: no such file"):
        C.main(["--fidelity", "fid", "--runs", "never-ran", "--storage-root", str(tmp_path), "--record-as", "v",
                "--results-dir", str(results)])


@pytest.mark.parametrize("runs, named", [
    (["a:x", "b:x"], "label 'x' is given to 2 runs"),
    (["a:x", "b"], None), (["a:x", "x"], "label 'x' is given to 2 runs"),  # a label defaults to the run's name
    (["control"], "label 'control' would mix"), (["a:loop"], "label 'loop' would mix"),
    (["a:control_s2@ref"], "label 'control_s2' would mix"), (["a:oracle-s2"], "label 'oracle_s2' would mix")])
def test_labels_that_would_share_figure_keys_are_refused(tmp_path, capsys, runs, named):
    """Every figure of a run is keyed by its label, the references' as mcd_{control,oracle}_<label>_iter<i>: two runs
    with one label, or a label that is an arm or starts like a reference key, would overwrite figures silently."""
    argv = ["--fidelity", "nope", "--storage-root", str(tmp_path), "--record-as", "v", "--results-dir", str(tmp_path)]
    for spec in runs:
        argv += ["--runs", spec]
    with pytest.raises(SystemExit) as raised:
        C.main(argv)
    if named is None:  # accepted labels get as far as the missing record
        assert "nope.json does not exist" in str(raised.value)
    else:
        assert raised.value.code == 2 and named in capsys.readouterr().err


def test_variants_at_other_seeds_meet_their_own_seeds_control_and_oracle(tmp_path):
    """RUN:LABEL@REFERENCE reads the reference run's cached fidelity rounds (what bench_fidelity --seeds writes) as
    that variant's control and oracle; with --seeds-mean the runs are also compared as a mean (mean variant against
    the mean of their own controls and oracles), as bench_fidelity compares seeds."""
    results = tmp_path / "results"
    results.mkdir()
    (results / "fid.json").write_text(json.dumps({"mcd_control_iter2": 10.4, "mcd_oracle_iter2": 10.0}))
    runs = tmp_path / "runs"
    _fake_run(runs, "v1", [11.0, 10.8, 10.5])
    _fake_run(runs, "v2", [11.0, 10.8, 10.9])
    for ref, (control, oracle) in (("ref1", (10.7, 10.1)), ("ref2", (10.5, 9.9))):
        for arm, last in (("control", control), ("oracle", oracle)):
            for i, m in ((1, last + 0.2), (2, last)):
                out = runs / "toy" / ref / "fidelity" / arm / f"round-{i:02d}"
                out.mkdir(parents=True)
                (out / "metrics.json").write_text(json.dumps({"mcd_cm": m, "rot_err_deg": 20.0}))
    figures = C.main(["--fidelity", "fid", "--runs", "v1:a@ref1", "--runs", "v2:b@ref2", "--storage-root", str(runs),
                      "--seeds-mean", "--record-as", "v", "--results-dir", str(results)])
    assert figures["mcd_control_a_iter2"] == 10.7 and figures["mcd_oracle_b_iter1"] == pytest.approx(10.1)
    # seed-matched gaps: a 10.5 vs control 10.7 / oracle 10.1 -> 1/3 recovered; b 10.9 vs 10.5 / 9.9 -> -2/3
    assert figures["gap_to_control_cm_a"] == pytest.approx(-0.2) and figures["gap_to_control_cm_b"] == 0.4
    assert figures["gap_recovered_a"] == pytest.approx(1 / 3, abs=1e-3)
    assert figures["gap_recovered_b"] == pytest.approx(-2 / 3, abs=1e-3)
    # means: variant 10.7, control 10.6, oracle 10.0 -> headroom 0.943, recovered -1/6
    assert figures["mcd_matched_mean"] == 10.7 and figures["mcd_control_matched_mean"] == 10.6
    assert figures["n_seeds_matched_mean"] == 2
    assert figures["headroom_matched_mean"] == round(10.0 / 10.6, 3)
    assert figures["gap_recovered_matched_mean"] == pytest.approx(-1 / 6, abs=1e-3)
    assert "(seed-matched, ref1)" in json.loads((results / "v.json").read_text())["notes"]
    # without the @ the record's seed-0 arms are that run's references (a: 10.5 against 10.4 / 10.0); means with b:
    # variant 10.7, control 10.45, oracle 9.95 -> -1/2; without --seeds-mean no mean is formed
    figures = C.main(["--fidelity", "fid", "--runs", "v1:a", "--runs", "v2:b@ref2", "--storage-root", str(runs),
                      "--seeds-mean", "--record-as", "v", "--results-dir", str(results)])
    assert figures["gap_recovered_a"] == pytest.approx(-0.25)
    assert figures["gap_recovered_matched_mean"] == pytest.approx(-0.5, abs=1e-3)
    figures = C.main(["--fidelity", "fid", "--runs", "v1:a", "--runs", "v2:b@ref2", "--storage-root", str(runs),
                      "--record-as", "v", "--results-dir", str(results)])
    assert "gap_recovered_matched_mean" not in figures
    with pytest.raises(SystemExit, match="--seeds-mean: needs two or more runs"):
        C.main(["--fidelity", "fid", "--runs", "v1:a@ref1", "--storage-root", str(runs), "--seeds-mean",
                "--record-as", "v", "--results-dir", str(results)])
    with pytest.raises(FileNotFoundError, match=r"nope/fidelity/control: no round-NN/metrics.json"):
        C.main(["--fidelity", "fid", "--runs", "v1:a@nope", "--storage-root", str(runs), "--record-as", "v",
                "--results-dir", str(results)])
    with pytest.raises(SystemExit):  # argparse: an empty reference
        C.main(["--fidelity", "fid", "--runs", "v1:a@", "--storage-root", str(runs), "--record-as", "v",
                "--results-dir", str(results)])


def test_past_the_records_last_iteration_only_with_seed_matched_references(tmp_path):
    """A record of two iterations cannot say where the control is at iteration 3, but a run whose reference run has
    cached round 3 can be measured there; a run without a reference at that iteration is refused by name."""
    results = tmp_path / "results"
    results.mkdir()
    (results / "fid.json").write_text(json.dumps({"mcd_control_iter2": 10.4, "mcd_oracle_iter2": 10.0,
                                                  "mcd_loop_iter2": 10.6}))
    runs = tmp_path / "runs"
    _fake_run(runs, "v1", [11.0, 10.8, 10.6, 10.5])
    _fake_run(runs, "v2", [11.0, 10.8, 10.9, 10.8])
    for ref, (control, oracle) in (("ref1", (10.7, 10.1)), ("ref2", (10.9, 10.3))):
        for arm, last in (("control", control), ("oracle", oracle)):
            for i in (1, 2, 3):
                out = runs / "toy" / ref / "fidelity" / arm / f"round-{i:02d}"
                out.mkdir(parents=True)
                (out / "metrics.json").write_text(json.dumps({"mcd_cm": last + 0.1 * (3 - i), "rot_err_deg": 20.0}))
    figures = C.main(["--fidelity", "fid", "--runs", "v1:a@ref1", "--runs", "v2:b@ref2", "--storage-root", str(runs),
                      "--iteration", "3", "--seeds-mean", "--record-as", "v", "--results-dir", str(results)])
    # a: 10.5 against 10.7 / 10.1 -> 1/3; b: 10.8 against 10.9 / 10.3 -> 1/6; means 10.65, 10.8, 10.2 -> 1/4
    assert figures["gap_recovered_a"] == pytest.approx(1 / 3, abs=1e-3)
    assert figures["gap_recovered_b"] == pytest.approx(1 / 6, abs=1e-3)
    assert figures["gap_recovered_matched_mean"] == pytest.approx(0.25, abs=1e-3)
    assert figures["headroom_matched_mean"] == round(10.2 / 10.8, 3)
    notes = json.loads((results / "v.json").read_text())["notes"]
    assert "a (v1): iteration 3 test mCD 10.50 cm against the control's 10.70 (seed-matched, ref1): beats" in notes
    assert "loop's" not in notes  # the record's loop has no iteration 3 to quote
    with pytest.raises(SystemExit, match=r"no control figure at iteration 3 .*RUN:LABEL@REFERENCE_RUN"):
        C.main(["--fidelity", "fid", "--runs", "v1:a@ref1", "--runs", "v2:b", "--storage-root", str(runs),
                "--iteration", "3", "--record-as", "v", "--results-dir", str(results)])
    with pytest.raises(SystemExit, match="the reference run has no control round 4"):
        C.main(["--fidelity", "fid", "--runs", "v1:a@ref1", "--storage-root", str(runs),
                "--iteration", "4", "--record-as", "v", "--results-dir", str(results)])
