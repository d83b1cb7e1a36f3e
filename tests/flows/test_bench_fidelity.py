"""``make bench-fidelity`` cut down to tiny sizes: the ``bench`` preset through the bootstrap flow, the control and
oracle rounds from its Φ₀, one ablation from the same Φ₀ (``init_predictor``), the figures, the plot and a resumed
rerun that trains nothing again."""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from bat3r_core import evaluation, shards
from bat3r_core.runs import RunLayout, read_manifest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_fidelity as B  # noqa: E402

# the bench preset at tiny sizes: what CI can afford (the preset's own sizes are make bench-fidelity's)
BENCH_TINY = {"run.canonical_samples": 8, "run.collection_size": 8, "run.test_size": 4, "shard_size": 8,
              "train.steps": 4, "train.batch_size": 4, "train.warmup_steps": 1, "train.checkpoint_every": 2,
              "model.base_channels": 8, "fitting.steps": 20, "fitting.min_valid_points": 5,
              "fitting.inlier_distance": 1.0, "pseudo_label_filter.min_kept": 2}
ARGS = ["--preset", "bench", "--run-name", "bt", "--iterations", "1",
        *[f"--set={k}={json.dumps(v)}" for k, v in BENCH_TINY.items()]]



@pytest.fixture(scope="module")
def bench_run(prefect_harness, catalog, tmp_path_factory):
    out = tmp_path_factory.mktemp("fidelity")
    figures = B.main([*ARGS, "--ablations", "no_pseudo_label_filter", "--oracle-sizes", "12", "--seeds", "0", "1",
                      "--results-dir", str(out)])
    return figures, out


def test_the_bench_preset_runs_every_arm_from_one_phi0(bench_run, catalog):
    figures, out = bench_run
    layout = RunLayout(catalog / "runs", "toy", "bt")
    test_rows = {int(r["iteration"]): r for r in evaluation.read_metrics(layout.root).to_pylist()
                 if r["split"] == "test"}
    assert figures["mcd_loop_iter0"] == round(test_rows[0]["mcd_cm"], 3)
    assert figures["mcd_loop_iter1"] == round(test_rows[1]["mcd_cm"], 3)
    # the control and oracle start from the loop's Φ₀ and are trained once more, each to a model of its own
    for arm in ("control", "oracle"):
        assert figures[f"mcd_{arm}_iter0"] == figures["mcd_loop_iter0"]
        assert (layout.root / "fidelity" / arm / "round-01" / "train" / "predictor.pt").is_file()
        assert math.isfinite(figures[f"mcd_{arm}_iter1"])
    assert figures["headroom_oracle_over_control"] == pytest.approx(
        figures["mcd_oracle_iter1"] / figures["mcd_control_iter1"], abs=2e-3)
    # the ablation is a run of its own that starts from the same Φ₀ and does not train one
    abl = RunLayout(catalog / "runs", "toy", "bt-no_pseudo_label_filter")
    manifest = read_manifest(abl)
    assert manifest["config"]["ablations"]["no_pseudo_label_filter"] is True
    assert manifest["config"]["parameters"]["init_predictor"] == str(
        (layout.stage_dir(0, "train") / "predictor.pt").resolve())
    assert not abl.stage_dir(0, "train").exists()
    # --no-pseudo-label-filter: no filter stage, and every ok fit is rendered from its estimated view
    assert not abl.stage_dir(1, "filter").exists() and not (abl.stage_dir(1, "evaluate") / "pseudo_label_filter.json"
                                                           ).exists()
    ok_fits = {r["sample_id"] for r in shards.read_table(abl.stage_dir(1, "fit")).to_pylist() if r["status"] == "ok"}
    jobs = shards.read_table(abl.stage_dir(1, "render")).to_pylist()
    assert ok_fits and {j["source_id"] for j in jobs if j["view_kind"] == "estimated"} == ok_fits
    # while the loop's own filter rendered a subset (the bench preset keeps the better half)
    kept = {r["sample_id"] for r in shards.read_table(layout.stage_dir(1, "filter")).to_pylist() if r.get("kept")}
    loop_jobs = shards.read_table(layout.stage_dir(1, "render")).to_pylist()
    assert kept and {j["source_id"] for j in loop_jobs if j["view_kind"] == "estimated"} == kept
    assert figures["mcd_no_pseudo_label_filter_iter0"] == figures["mcd_loop_iter0"]  # same Φ₀, same test split
    assert (abl.stage_dir(1, "train") / "predictor.pt").is_file()
    # the floors of the test split at the preset's 32 px crops: exact maps beat exact rest-pose maps, and neither is 0
    assert 1.0 < figures["floor_perfect_map_cm"] < figures["floor_rest_pose_map_cm"]
    assert figures["best_headroom"] == pytest.approx(
        figures["floor_perfect_map_cm"] / figures["floor_rest_pose_map_cm"], abs=2e-3)
    # the oracle and Φ₀ scored on the collection's own images (the oracle's training set), cached per predictor
    for name in ("oracle", "phi0"):
        assert 0.0 < figures[f"mcd_{name}_on_collection"] < 100.0
        cached = json.loads((layout.root / "fidelity" / "on_collection" / name / "metrics.json").read_text())
        assert cached["split"] == "collection" and cached["n"] + cached["n_failed"] == 8
    # how each predictor's test maps are off, against the exact maps: cached per predictor; the loop's last iteration
    # and the control's last round are different networks from Φ₀, so their figures are their own
    n_test = sum(r["status"] == "ok" for r in shards.read_table(layout.run_stage_dir("test")).to_pylist())
    for name in ("phi0", "control", "oracle", "loop"):
        assert 0.0 < figures[f"depth_err_median_cm_{name}"] <= figures[f"depth_err_rms_cm_{name}"] < 500.0
        assert 0.1 <= figures[f"depth_err_tail_share_{name}"] <= 1.0
        assert 0.0 <= figures[f"depth_reversed_pct_{name}"] <= 100.0 and figures[f"lateral_err_rms_cm_{name}"] > 0
        cached = json.loads((layout.root / "fidelity" / "map_errors" / f"{name}.json").read_text())
        assert cached["n_images"] == n_test > 0 and cached["depth_err_rms_cm"] == pytest.approx(
            figures[f"depth_err_rms_cm_{name}"], abs=1e-3)
    assert figures["depth_err_rms_cm_loop"] != figures["depth_err_rms_cm_phi0"]
    # --oracle-sizes 12: the oracle again from the same Φ₀ on a collection of 12 images, a run of its own
    sized = RunLayout(catalog / "runs", "toy", "bt-oracle-n12")
    assert read_manifest(sized)["config"]["parameters"]["init_predictor"] == str(
        (layout.stage_dir(0, "train") / "predictor.pt").resolve())
    assert shards.read_table(sized.run_stage_dir("collection")).num_rows == 12
    assert (sized.root / "fidelity" / "oracle" / "round-01" / "train" / "predictor.pt").is_file()
    assert figures["mcd_oracle_n12_iter0"] == figures["mcd_loop_iter0"]
    assert math.isfinite(figures["mcd_oracle_n12_iter1"])
    assert json.loads((sized.root / "fidelity" / "on_collection" / "oracle" / "metrics.json").read_text())["n"] > 0
    # --seeds 0 1: the loop, control and oracle again from the same Φ₀ with seed 1, a run of its own
    seeded = RunLayout(catalog / "runs", "toy", "bt-seed1")
    config = read_manifest(seeded)["config"]
    assert config["parameters"]["init_predictor"] == str((layout.stage_dir(0, "train") / "predictor.pt").resolve())
    assert config["parameters"]["seed"] == 1 and config["parameters"]["overrides"]["train.seed"] == 1
    for arm in ("control", "oracle"):
        assert (seeded.root / "fidelity" / arm / "round-01" / "train" / "predictor.pt").is_file()
    for arm in ("control", "oracle"):  # Φ₀ as the seeded run scores it (its evaluation samples with seed 1 + i)
        assert figures[f"mcd_{arm}_seed1_iter0"] == figures["mcd_loop_seed1_iter0"]
    for arm in ("loop", "control", "oracle"):
        pair = (figures[f"mcd_{arm}_iter1"], figures[f"mcd_{arm}_seed1_iter1"])
        assert figures[f"mcd_{arm}_seeds_mean"] == pytest.approx(sum(pair) / 2, abs=2e-3)
        assert figures[f"mcd_{arm}_seeds_sd"] == pytest.approx(abs(pair[0] - pair[1]) / math.sqrt(2), abs=2e-3)
    # the loop's own test predictions under 5 evaluation seeds; seed k = 0 is the loop's own score
    assert figures["mcd_loop_eval_seed0"] == figures["mcd_loop_iter1"]
    scores = [figures[f"mcd_loop_eval_seed{k}"] for k in range(B.EVAL_SEEDS)]
    assert len(set(scores)) > 1, "other surface samples, other scores"
    assert figures["mcd_loop_eval_seeds_range"] == pytest.approx(max(scores) - min(scores), abs=2e-3)
    assert figures["mcd_loop_eval_seeds_sd"] == pytest.approx(float(np.std(scores, ddof=1)), abs=2e-3)
    saved = json.loads((out / "fidelity.json").read_text())
    assert "scored with 5 evaluation seeds, the loop's own test predictions move by sd" in saved["notes"]
    assert "over 2 seeds from the same Φ₀" in saved["notes"]
    assert "with 12 collection images the oracle reaches" in saved["notes"]
    assert "perfect oracle over a perfect control" in saved["notes"]
    assert "on the collection images it was trained on" in saved["notes"]
    assert "per map entry, Φ₀'s relative depth is off by median" in saved["notes"]
    assert saved["mcd_loop_iter1"] == figures["mcd_loop_iter1"] and "headroom" in saved["notes"]
    assert (out / "fidelity.png").stat().st_size > 5000


def test_finished_reference_rounds_are_not_trained_again(bench_run, catalog):
    from flows._settings import resolve_run

    figures, _ = bench_run
    settings = resolve_run("toy", "bench", "bt", BENCH_TINY)  # what ARGS --set
    ckpt = settings.layout.root / "fidelity" / "control" / "round-01" / "train" / "predictor.pt"
    before = ckpt.stat().st_mtime_ns

    def no_data(out):
        raise AssertionError("a finished round asked for its training data")

    rows = B._reference_rounds(settings, "control", no_data, 1, 0)
    assert ckpt.stat().st_mtime_ns == before
    assert round(rows[1]["mcd_cm"], 3) == figures["mcd_control_iter1"]
    # so are the floors: a rerun reads fidelity/floors.json instead of ray-casting the test split again
    floors = settings.layout.root / "fidelity" / "floors.json"
    written = floors.stat().st_mtime_ns
    assert B.map_floors(settings)["best_headroom"] == figures["best_headroom"]
    assert floors.stat().st_mtime_ns == written
    # the training-set scores are cached too: a missing checkpoint is not even opened on a rerun
    again = B.training_fit(settings, {"oracle": settings.layout.root / "nope.pt"}, 1, 0)
    assert again == {"mcd_oracle_on_collection": figures["mcd_oracle_on_collection"]}
    with pytest.raises(ValueError, match="split: expected 'test' or 'collection', got 'train'"):
        B._test_metrics(settings, ckpt, settings.layout.root / "unused", 1, 0, split="train")
    # a run that never prepared its test split (a seed's reference run made before its loop) is named, not scored
    unprepared = resolve_run("toy", "bench", "bt-never-ran", BENCH_TINY)
    with pytest.raises(FileNotFoundError, match=r"bt-never-ran/test: no test shards to score .*'bt-never-ran'"):
        B._test_metrics(unprepared, ckpt, settings.layout.root / "unused", 1, 0)


def test_references_only_trains_the_extra_seeds_control_and_oracle_and_no_loop(bench_run, catalog, tmp_path):
    """--references-only --seeds 0 1 2: seed 0's (the benchmark's own) and seed 1's cached rounds (the fixture's
    --seeds 0 1) are read back, not trained again; seed 2 gets a 0-iteration run (its test split, Φ₀ scored at seed 2)
    and its control and oracle rounds, no loop; nothing is recorded. compare_loops.py then measures a run at seed 2
    against them."""
    import compare_loops as C

    figures, _ = bench_run
    seed1 = RunLayout(catalog / "runs", "toy", "bt-seed1")
    ckpt = seed1.root / "fidelity" / "control" / "round-01" / "train" / "predictor.pt"
    before = ckpt.stat().st_mtime_ns
    refs = B.main([*ARGS, "--seeds", "0", "1", "2", "--references-only", "--results-dir", str(tmp_path)])
    assert ckpt.stat().st_mtime_ns == before
    for arm in ("control", "oracle"):
        assert refs[f"{arm}_seed1"][1]["mcd_cm"] == pytest.approx(figures[f"mcd_{arm}_seed1_iter1"], abs=1e-3)
        assert refs[f"{arm}_seed1"][0]["mcd_cm"] == pytest.approx(figures["mcd_loop_seed1_iter0"], abs=1e-3)
    seed2 = RunLayout(catalog / "runs", "toy", "bt-seed2")
    assert read_manifest(seed2)["config"]["parameters"]["iterations"] == 0
    assert not (seed2.root / "iter-01").exists()
    for arm in ("control", "oracle"):
        assert (seed2.root / "fidelity" / arm / "round-01" / "metrics.json").is_file()
        assert math.isfinite(refs[f"{arm}_seed2"][1]["mcd_cm"])
    assert not list(tmp_path.iterdir()), "--references-only records nothing"
    # a run at seed 2 measured against them: its own Φ₀ row stands in for a loop run here
    compared = C.main(["--fidelity", "fidelity", "--runs", "bt-seed2:s2@bt-seed2", "--category", "toy",
                       "--storage-root", str(catalog / "runs"), "--iteration", "1", "--record-as", "v",
                       "--results-dir", str(bench_run[1])])
    assert compared["mcd_control_s2_iter1"] == round(refs["control_seed2"][1]["mcd_cm"], 3)
    assert compared["mcd_oracle_s2_iter1"] == round(refs["oracle_seed2"][1]["mcd_cm"], 3)
    # seed 0's are the benchmark's own rounds, read back under the run itself: no bt-seed0 run is made
    for arm in ("control", "oracle"):
        assert refs[f"{arm}_seed0"][1]["mcd_cm"] == pytest.approx(figures[f"mcd_{arm}_iter1"], abs=1e-3)
        assert refs[f"{arm}_seed0"][0]["mcd_cm"] == pytest.approx(figures["mcd_loop_iter0"], abs=1e-3)
    assert not (catalog / "runs" / "toy" / "bt-seed0").exists()
    assert B.main([*ARGS, "--references-only", "--results-dir", str(tmp_path)]) == {
        k: v for k, v in refs.items() if k.endswith("_seed0")}


def test_references_only_retrains_seed0_under_a_name_of_its_own_and_reproduces_the_benchmark(bench_run, catalog,
                                                                                          tmp_path, capsys):
    """One round further than the benchmark went (--iterations 2), seed 0's references are not the run's: they are
    trained under bt-seed0, from the same Φ₀, seed and data, and round 1 there reproduces the benchmark's own round 1;
    the run's own fidelity/ gets no round 2, and the printed hint names each seed's reference run."""
    figures, _ = bench_run
    refs = B.main([*ARGS, "--iterations", "2", "--seeds", "0", "1", "--references-only",
                   "--results-dir", str(tmp_path)])
    own = RunLayout(catalog / "runs", "toy", "bt")
    seed0 = RunLayout(catalog / "runs", "toy", "bt-seed0")
    for arm in ("control", "oracle"):
        assert not (own.root / "fidelity" / arm / "round-02").exists()
        assert (seed0.root / "fidelity" / arm / "round-02" / "metrics.json").is_file()
        assert refs[f"{arm}_seed0"][1]["mcd_cm"] == pytest.approx(figures[f"mcd_{arm}_iter1"], abs=1e-3)
        assert refs[f"{arm}_seed0"][0]["mcd_cm"] == pytest.approx(figures["mcd_loop_iter0"], abs=1e-3)
        assert refs[f"{arm}_seed1"][1]["mcd_cm"] == pytest.approx(figures[f"mcd_{arm}_seed1_iter1"], abs=1e-3)
        assert math.isfinite(refs[f"{arm}_seed1"][2]["mcd_cm"])
    out = capsys.readouterr().out
    assert "seed 0: compare a loop variant run at seed 0 with compare_loops.py --runs RUN:LABEL@bt-seed0" in out
    assert "RUN:LABEL@bt-seed1" in out


def test_the_fit_oracle_runs_on_the_bench_run(bench_run, catalog, tmp_path):
    """``make bench-fidelity``'s second step, ``bench_fit_oracle.py``, on the cut-down run: the predicted fits, the
    exact-maps fits and the error-scale sweep; scaling the errors to zero fits exactly the exact maps."""
    import bench_fit_oracle as FO

    figures = FO.main(["--category", "toy", "--run-name", "bt", "--versions", "predicted", "true_P_and_Q", "--error-scales", "0", "0.5",
                       "--results-dir", str(tmp_path)])
    assert figures["images"] == 8
    for version in ("predicted", "true_P_and_Q", "errors_x0", "errors_x0.5"):
        assert math.isfinite(figures[f"median_fit_vertex_err_cm_{version}"])
        assert 0.0 <= figures[f"pct_better_than_rest_{version}"] <= 100.0
        assert 0.0 <= figures[f"refit_filter_base_rate_{version}"] <= 1.0  # the run's filter on these fits
    for key in ("fit_vertex_err_cm", "median_fit_vertex_err_cm", "pct_better_than_rest", "refit_filter_base_rate"):
        assert figures[f"{key}_errors_x0"] == figures[f"{key}_true_P_and_Q"]
    written = json.loads((tmp_path / "fit_oracle.json").read_text())
    assert written["median_fit_vertex_err_cm_errors_x0.5"] == figures["median_fit_vertex_err_cm_errors_x0.5"]
    assert "errors scaled by 0, 0.5" in written["notes"] and "toy, bench preset, run 'bt'" in written["notes"]
    with pytest.raises(SystemExit):
        FO.main(["--run-name", "bt", "--error-scales", "-1", "--results-dir", str(tmp_path)])


def test_gap_recovered_and_ablation_ordering():
    assert B.gap_recovered(10.0, 6.0, 8.0) == pytest.approx(0.5)
    assert B.gap_recovered(10.0, 6.0, 11.0) == pytest.approx(-0.25)
    assert math.isnan(B.gap_recovered(10.0, 10.5, 9.0))  # no gap: the oracle is no better than the control
    assert B.ablation_ordering(5.0, 6.0, 7.0).startswith("holds")
    assert B.ablation_ordering(5.0, 7.0, 6.0).startswith("does not hold")
    # which pair is out of the paper's order
    assert B.ablation_ordering(5.0, 7.0, 6.0).endswith(
        "(no view augmentation (7.00) is not ahead of no fitting regularisation (6.00))")
    assert B.ablation_ordering(6.5, 6.0, 7.0).endswith("(the full loop (6.50) is not ahead of no view augmentation "
                                                       "(6.00))")
    assert B.ablation_ordering(5.0, None, 7.0).startswith("not measured")


def test_the_demo_verdict_holds_the_benchmark_to_its_headroom_goal():
    from flows.demo import BENCH_HEADROOM_GOAL

    assert BENCH_HEADROOM_GOAL == B.HEADROOM_GOAL


def test_a_missing_init_predictor_is_refused_before_anything_runs(prefect_harness, catalog, tmp_path):
    from flows.bootstrap import bootstrap

    with pytest.raises(FileNotFoundError, match="init_predictor: .*nope.pt is not a file"):
        bootstrap(category="toy", preset="tiny", run_name="noinit", init_predictor=str(tmp_path / "nope.pt"))
    assert not (catalog / "runs" / "toy" / "noinit" / "manifest.json").exists()


def test_training_publishes_its_progress_on_the_dashboard(bench_run):
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterType

    with get_client(sync_client=True) as client:
        artifacts = client.read_artifacts(artifact_filter=ArtifactFilter(type=ArtifactFilterType(any_=["progress"])))
    training = [a for a in artifacts if (a.description or "").startswith("training ")]
    assert training, "no training progress artifact"
    assert all(float(a.data) == 100.0 for a in training)  # every train task of the run finished
    assert any("iter-01/train" in a.description and "steps/s" in a.description for a in training)


def test_seed_figures_and_their_verdict_by_hand():
    arms = {"loop": {2: {"mcd_cm": 10.0}}, "control": {2: {"mcd_cm": 11.0}}, "oracle": {2: {"mcd_cm": 8.0}},
            "loop_seed3": {2: {"mcd_cm": 12.0}}, "control_seed3": {2: {"mcd_cm": 11.0}},
            "oracle_seed3": {2: {"mcd_cm": 8.0}}}
    assert B.seed_figures([0], arms, 2) == {} and B.seed_line({}) is None
    f = B.seed_figures([0, 3], arms, 2)
    assert f["seeds"] == 2 and f["mcd_loop_seeds_mean"] == 11.0 and f["mcd_loop_seeds_sd"] == pytest.approx(1.414, abs=1e-3)
    assert f["mcd_control_seeds_sd"] == 0.0 and f["loop_minus_control_seeds_mean"] == 0.0
    assert f["loop_minus_control_seeds_sd"] == pytest.approx(1.414, abs=1e-3) and f["loop_ahead_of_control_seeds"] == 1
    assert f["headroom_seeds_mean"] == pytest.approx(8.0 / 11.0, abs=1e-3) and f["loop_gap_recovered_seeds_mean"] == 0.0
    line = B.seed_line(f)
    assert line.startswith("over 2 seeds from the same Φ₀ (mean ± sd of the last iteration's test mCD, cm): loop "
                           "11.00 ± 1.41, control 11.00 ± 0.00, oracle 8.00 ± 0.00")
    assert "ahead in 1 of 2 seeds" in line and line.endswith("headroom of the means 0.727, share of the gap recovered 0%")
    lines = B.verdict_lines({"iterations": 2, "mcd_loop_iter2": 10.0, "mcd_control_iter2": 11.0,
                             "mcd_oracle_iter2": 8.0, **f})
    assert lines[-2] == line and lines[-1].startswith("paper's ablation ordering")
    # without headroom, the share over a gap of at least MIN_GAP_CM is given with its gap; under it, not at all
    wide = {**f, "mcd_control_seeds_mean": 10.97, "mcd_oracle_seeds_mean": 10.21, "headroom_seeds_mean": 0.931,
            "loop_gap_recovered_seeds_mean": 0.7}
    assert B.seed_line(wide).endswith("headroom of the means 0.931, share of the gap recovered 70% (of a gap of "
                                      "0.76 cm)")
    narrow = {**wide, "mcd_oracle_seeds_mean": 10.80, "headroom_seeds_mean": 0.985}
    assert B.seed_line(narrow).endswith("headroom of the means 0.985")
    with pytest.raises(SystemExit):
        B.main(["--seeds", "1", "2"])   # seed 0 (the benchmark's own arms) must be among them


def test_verdicts_follow_the_recorded_figures():
    figs = {"iterations": 2, "mcd_loop_iter2": 7.0, "mcd_control_iter2": 10.0, "mcd_oracle_iter2": 6.0}
    lines = B.verdict_lines(figs)
    assert "0.600 (goal <= 0.75: met" in lines[0] and "recovers 75% of" in lines[1] and "(goal >= 50%: met)" in lines[1]
    assert lines[2] == "paper's ablation ordering not measured (run with --ablations)"
    figs.update({"mcd_no_view_augmentation_iter2": 8.0, "mcd_no_fitting_regularisation_iter2": 9.0})
    assert B.verdict_lines(figs)[2].startswith("paper's ablation ordering holds")
    # no headroom: the share of a 0.03 cm gap is not reported as a figure of merit
    flat = B.verdict_lines({"iterations": 2, "mcd_loop_iter2": 11.07, "mcd_control_iter2": 10.40,
                            "mcd_oracle_iter2": 10.37})
    assert "NOT met" in flat[0] and "not meaningful" in flat[1] and "0.67 cm behind the control" in flat[1]
    # short of the headroom goal but a gap wider than the seed spread: the share is reported, with what it is not
    narrow = B.verdict_lines({"iterations": 3, "mcd_loop_iter3": 10.30, "mcd_control_iter3": 10.97,
                              "mcd_oracle_iter3": 10.21})
    assert "0.931 (goal <= 0.75: NOT met" in narrow[0]
    assert narrow[1].startswith("the loop (10.30 cm) recovers 88% of the control -> oracle gap (goal >= 50%: met), "
                                "of a gap of 0.76 cm, narrower than the headroom goal asks for")
    assert B.MIN_GAP_CM == 0.25 and "not meaningful" in B.verdict_lines(
        {"iterations": 1, "mcd_loop_iter1": 10.9, "mcd_control_iter1": 11.0, "mcd_oracle_iter1": 10.76})[1]
    floored = B.verdict_lines({**figs, "floor_perfect_map_cm": 5.73, "floor_rest_pose_map_cm": 8.14,
                               "best_headroom": 0.704})
    assert "exact point maps score 5.73 cm and exact rest-pose maps 8.14 cm" in floored[2]
    assert floored[2].endswith("headroom of 0.704") and floored[3].startswith("paper's ablation ordering holds")
    underfit = B.verdict_lines({**figs, "mcd_oracle_on_collection": 5.7, "mcd_phi0_on_collection": 6.5})
    assert underfit[2] == ("on the collection images it was trained on (true labels) the oracle scores 5.70 cm "
                           "(Φ₀: 6.50) against 6.00 on the test split: it under-fits even its training images, so "
                           "the network's capacity to learn at this compute, not the poses it is shown, sets the "
                           "test error")
    sized = B.verdict_lines({**figs, "mcd_oracle_n1536_iter2": 5.0, "mcd_oracle_n1536_on_collection": 4.5})
    assert sized[2] == ("with 1536 collection images the oracle reaches 5.00 cm (headroom 0.500; 4.50 cm on its "
                        "training images)")
    errors = {f"{k}_{name}": v for name in ("phi0", "oracle") for k, v in zip(
        B.MAP_ERROR_FIGURES, (9.8 if name == "phi0" else 8.0, 30.2, 0.74 if name == "phi0" else 0.6, 6.25, 8.4))}
    gross = B.verdict_lines({**figs, **errors, "crop_px": 32})
    assert gross[2] == ("per map entry, Φ₀'s relative depth is off by median 9.8 cm, RMS 30.2 cm, the worst 10 % of "
                        "entries carry 74% of the squared error, 6 % of images with their depth order reversed; the "
                        "oracle's by median 8.0 cm, RMS 30.2 cm, the worst 10 % of entries carry 60% of the squared "
                        "error, 6 % of images with their depth order reversed: gross depth errors on a few entries "
                        "and images (the animal's depth order misread from a 32 px image) dominate even the "
                        "oracle's error, and training on true poses does not remove them")
    errors["depth_err_tail_share_oracle"] = 0.3   # even errors: no conclusion drawn
    assert B.verdict_lines({**figs, **errors})[2].endswith("depth order reversed")
    fits = B.verdict_lines({**figs, "mcd_oracle_on_collection": 4.0})
    assert fits[2].endswith("4.00 cm against 6.00 on the test split: it fits its training images better than unseen "
                            "ones") and fits[3].startswith("paper's ablation ordering holds")
    shifted = B.verdict_lines({**figs, **errors, "lateral_bias_y_cm_phi0": -0.4, "lateral_bias_y_cm_oracle": -9.9})
    assert shifted[2].endswith("; the oracle's test maps are shifted 9.9 cm up on average (what training renders "
                               "whose x, y follow another principal point teach, docs/fitting.md)")
    assert "Φ₀'s test maps are shifted" not in shifted[2]
    spread = B.verdict_lines({**figs, "mcd_loop_eval_seed0": 7.0, "mcd_loop_eval_seed1": 7.04,
                              "mcd_loop_eval_seeds_sd": 0.028, "mcd_loop_eval_seeds_range": 0.04})
    assert spread[2] == ("scored with 2 evaluation seeds, the loop's own test predictions move by sd 0.028 cm (range "
                         "0.040): that much of any spread between runs is the evaluation's sampling, the rest is "
                         "training")


def test_gpu_rounds_runs_the_documented_split_workflow_on_the_bench_run(bench_run, catalog, tmp_path):
    """pack → train (here on the CPU) → evaluate → the loop's pack from the run's own iteration-1 renders → train
    from the returned Φ₀ → evaluate → record: the commands README's "Training the benchmark's models on a GPU
    machine" runs across two machines."""
    import gpu_rounds as G
    import torch

    from bat3r_core.predictor.infer import load_predictor

    _, out = bench_run
    layout = RunLayout(catalog / "runs", "toy", "bt")
    p1, o1, p2, o2 = (tmp_path / n for n in ("p1", "o1", "p2", "o2"))
    G.main(["pack", "--run-name", "bt", "--out", str(p1)])
    plan = json.loads((p1 / "plan.json").read_text())
    canonical = shards.read_table(layout.stage_dir(0, "render")).num_rows
    assert plan["samples"] == {"canonical": canonical, "oracle": 8}
    G.main(["train", "--pack", str(p1), "--out", str(o1), "--work", str(tmp_path / "w1"), "--phi0-steps", "3",
            "--round-steps", "2"])
    G.main(["pack", "--run-name", "bt", "--loop-iteration", "1", "--out", str(p2)])
    loop_samples = sum(1 for r in shards.read_table(layout.stage_dir(1, "render")).to_pylist() if r["status"] == "ok")
    # the bench preset replays the canonical renders in each refinement iteration: the loop pack carries them too
    assert json.loads((p2 / "plan.json").read_text())["samples"] == {"loop1": loop_samples, "replay": canonical}
    G.main(["train", "--pack", str(p2), "--out", str(o2), "--work", str(tmp_path / "w2"), "--phi0",
            str(o1 / "phi0.pt"), "--round-steps", "2"])
    # every round starts from the float16 Φ₀ that came back, and takes the same steps
    t1, t2 = (json.loads((o / "timings.json").read_text()) for o in (o1, o2))
    assert set(t2) >= {"loop1"} and "replay" not in t2  # the replayed renders are no round of their own
    # the loop round trained on its renders mixed with as many canonical ones (train.canonical_replay = 1), as the
    # flow's iteration 1 did
    loop_state = torch.load(tmp_path / "w2" / "loop1" / "checkpoint.pt", map_location="cpu", weights_only=True)
    assert loop_state["n_samples"] == loop_samples + min(canonical, loop_samples)
    assert t1["phi0"]["steps"] == 3 and t1["control"]["steps"] == t1["oracle"]["steps"] == t2["loop1"]["steps"] == 2
    for o, name in ((o1, "phi0"), (o1, "oracle"), (o2, "loop1")):
        state = torch.load(o / f"{name}.pt", map_location="cpu", weights_only=True)
        assert {v.dtype for v in state["model"].values() if v.is_floating_point()} == {torch.float16}
        load_predictor(o / f"{name}.pt", "cpu")
    e1, e2 = tmp_path / "e1.json", tmp_path / "e2.json"
    G.main(["evaluate", "--run-name", "bt", "--predictors", str(o1), "--json", str(e1)])
    G.main(["evaluate", "--run-name", "bt", "--predictors", str(o2), "--names", "loop1", "--tag", "call2",
            "--json", str(e2)])
    figures = G._record(G.argparse.Namespace(
        category="toy", run_name="bt", loop_run="bt", evaluations=[str(e1), str(e2)], timings=[str(o1 / "timings.json"),
                                                                               str(o2 / "timings.json")],
        record_as="gpu_rounds_tiny", results_dir=out))
    rows = {**json.loads(e1.read_text()), **json.loads(e2.read_text())}
    assert figures["mcd_control_iter1"] == round(rows["control"]["mcd_cm"], 3)
    assert figures["mcd_loop_iter1"] == round(rows["loop1"]["mcd_cm"], 3)
    assert figures["mcd_oracle_iter0"] == figures["mcd_loop_iter0"] == round(rows["phi0"]["mcd_cm"], 3)
    assert figures["headroom"] == pytest.approx(figures["mcd_oracle_iter1"] / figures["mcd_control_iter1"], abs=2e-3)
    c, o, lp = (figures[f"mcd_{a}_iter1"] for a in ("control", "oracle", "loop"))
    if c > o:  # a gap to close: the loop's share of it
        assert figures["loop_gap_recovered"] == pytest.approx((c - lp) / (c - o), abs=2e-3)
    else:  # none (tiny models): no share is recorded, rather than a meaningless or infinite one
        assert "loop_gap_recovered" not in figures
    # the loop's fits against the truth and the run's own filter check are in the record
    ok_fits = sum(1 for r in shards.read_table(layout.stage_dir(1, "fit")).to_pylist() if r["status"] == "ok")
    assert figures["fit_fitted"] == ok_fits
    check = json.loads((layout.stage_dir(1, "evaluate") / "pseudo_label_filter.json").read_text())
    assert figures["filter_precision"] == round(check["precision"], 3)
    for arm in ("phi0", "control", "oracle", "loop"):
        assert f"depth_err_rms_cm_{arm}" in figures
    assert (out / "gpu_rounds_tiny.png").stat().st_size > 0
    recorded = json.loads((out / "gpu_rounds_tiny.json").read_text())
    assert recorded["round_steps"] == 2 and "headroom oracle/control" in recorded["notes"]
    # compare: predictors of evaluation files side by side, with the mean lateral shift of each
    side = G._compare(G.argparse.Namespace(category="toy", run_name="bt", evaluations=[str(e1)],
                                           record_as="gpu_rounds_cmp", notes="tiny", results_dir=out))
    assert side["mcd_oracle"] == round(rows["oracle"]["mcd_cm"], 3) and "lateral_bias_y_cm_control" in side
    assert json.loads((out / "gpu_rounds_cmp.json").read_text())["notes"] == "tiny"


def test_a_category_without_hidden_truth_is_refused(catalog, capsys):
    with pytest.raises(SystemExit):
        B.main(["--category", "horse", "--run-name", "nohorse"])
    err = capsys.readouterr().err
    assert "--category horse: the benchmark needs a generated collection" in err
    assert not (catalog / "runs" / "horse" / "nohorse").exists()
