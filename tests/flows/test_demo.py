"""``make demo``'s recorded figures and verdict (flows/demo.py), from metrics rows as metrics.parquet holds them."""
import json
import math

from flows.demo import demo_figures


def _row(iteration, mcd, rot):
    return {"iteration": iteration, "split": "test", "mcd_cm": mcd, "rot_err_deg": rot}


def test_figures_and_verdict_follow_the_ratio_of_last_to_canonical_mcd():
    figures, verdict = demo_figures([_row(0, 13.114, 40.74), _row(1, 12.41, 35.47), _row(2, 11.478, 25.33)], 13.204)
    assert verdict == "NOT met"
    assert figures == {"minutes": 13.2, "mcd_canonical_cm": 13.114, "mcd_last_cm": 11.478, "mcd_ratio": 0.875,
                       "iterations": 2, "mcd_iter1_cm": 12.41, "rot_err_canonical_deg": 40.7,
                       "rot_err_last_deg": 25.3}
    figures, verdict = demo_figures([_row(0, 12.0, 30.0), _row(1, 9.0, float("nan"))], 5.0)
    assert verdict == "met" and figures["mcd_ratio"] == 0.75  # the goal is <= 0.75: the boundary passes
    assert "rot_err_last_deg" not in figures and not any(math.isnan(v) for v in figures.values())


def test_only_a_demo_run_from_an_empty_folder_is_recorded():
    from flows.demo import record_refusal

    assert record_refusal("demo", no_record=False, resumed=False) is None
    assert "cached stages were reused" in record_refusal("demo", no_record=False, resumed=True)
    assert "only the demo preset" in record_refusal("tiny", no_record=False, resumed=False)
    assert record_refusal("demo", no_record=True, resumed=False) == "--no-record"


def test_control_verdict_points_at_the_same_compute_references(tmp_path):
    from flows.demo import control_verdict

    assert len(control_verdict(11.0, tmp_path)) == 2  # no recorded references: the caveat and where to look
    (tmp_path / "demo_control.json").write_text(json.dumps(
        {"iterations": 2, "mcd_control_cm_iter2": 10.15, "mcd_oracle_cm_iter2": 9.96}))
    (tmp_path / "fidelity.json").write_text(json.dumps(
        {"iterations": 2, "mcd_loop_iter2": 7.1, "mcd_control_iter2": 8.0, "mcd_oracle_iter2": 6.0}))
    lines = control_verdict(11.48, tmp_path)
    assert "control 10.15 cm, oracle (true labels) 9.96 cm; this run's loop 11.48 cm — at or behind" in lines[1]
    assert lines[2].endswith("loop 7.10, control 8.00, oracle 6.00 cm.")
    (tmp_path / "fidelity.json").write_text(json.dumps(
        {"iterations": 2, "mcd_loop_iter2": 7.1, "mcd_control_iter2": 8.0, "mcd_oracle_iter2": 6.0,
         "loop_gap_recovered": 0.45}))
    assert control_verdict(11.48, tmp_path)[2].endswith("loop 7.10, control 8.00, oracle 6.00 cm, 45% of the "
                                                        "control → oracle gap.")
    # a narrow gap (oracle / control above the 0.75) says so
    (tmp_path / "fidelity.json").write_text(json.dumps(
        {"iterations": 3, "mcd_loop_iter3": 10.30, "mcd_control_iter3": 10.97, "mcd_oracle_iter3": 10.21,
         "loop_gap_recovered": 0.89}))
    assert control_verdict(11.48, tmp_path)[2].endswith("89% of the control → oracle gap; but oracle / control is "
                                                        "0.931, short of the 0.75 that would make it the paper's "
                                                        "gain: even true labels gain little over the rest pose's at "
                                                        "that scale.")
    (tmp_path / "fidelity.json").write_text(json.dumps(
        {"iterations": 3, "mcd_loop_iter3": 10.30, "mcd_control_iter3": 10.97, "mcd_oracle_iter3": 10.21,
         "loop_gap_recovered": 0.89, "seeds": 2, "loop_gap_recovered_seeds_mean": 0.7}))
    assert "89% of the control → oracle gap (70% in the mean of 2 seeds); but" in control_verdict(11.48, tmp_path)[2]
    assert "ahead of the control" in control_verdict(9.0, tmp_path)[1]
    # references measured from another Φ₀ say so; from this run's Φ₀ they do not
    (tmp_path / "demo_control.json").write_text(json.dumps(
        {"iterations": 2, "mcd_control_cm_iter0": 13.11, "mcd_control_cm_iter2": 10.15}))
    other = control_verdict(12.04, tmp_path, canonical_mcd=12.92)
    assert "started from another Φ₀ (13.11 cm; this run's: 12.92 cm): make bench-demo" in other[2]
    assert not any("another Φ₀" in line for line in control_verdict(12.04, tmp_path, canonical_mcd=13.12))


def test_the_seeds_verdict_reads_the_demo_loops_seed_matched_record(tmp_path):
    from flows.demo import SEEDS_RECORD, control_verdict, seeds_verdict

    assert seeds_verdict(tmp_path) == []  # no record: no line
    record = {"mcd_matched_mean": 11.1, "mcd_control_matched_mean": 11.3, "mcd_oracle_matched_mean": 10.5,
              "gap_recovered_matched_mean": 0.25, "n_seeds_matched_mean": 3,
              "gap_to_control_cm_a": -0.1, "gap_to_control_cm_a_seed1": -0.3}  # two gap keys: the count is recorded
    (tmp_path / f"{SEEDS_RECORD}.json").write_text(json.dumps(record))
    (line,) = seeds_verdict(tmp_path)
    assert "Over 3 seeds at this preset" in line and f"RESULTS.md, {SEEDS_RECORD})" in line
    assert "loop 11.10, control 11.30, oracle 10.50 cm — ahead of the control, 25% of the control → oracle gap" in line
    assert line in control_verdict(11.0, tmp_path)
    behind = {**record, "mcd_matched_mean": 11.4, "gap_recovered_matched_mean": -0.125}
    (tmp_path / f"{SEEDS_RECORD}.json").write_text(json.dumps(behind))
    assert seeds_verdict(tmp_path)[0].endswith("loop 11.40, control 11.30, oracle 10.50 cm — at or behind the control.")
    (tmp_path / f"{SEEDS_RECORD}.json").write_text(json.dumps({"mcd_matched_mean": 11.4}))  # not a seeds-mean record
    assert seeds_verdict(tmp_path) == []
