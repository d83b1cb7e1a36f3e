"""Loop variants against a recorded fidelity benchmark: does a changed setting make the loop beat its control?

``bench_fidelity.py`` measures one loop against its control and oracle from one Φ₀. A variant of the loop (a
fitting setting, a filter, an ablation) is a bootstrap run from the same Φ₀ (``--init-predictor``, same preset and
iterations), so it needs no new control: this script reads each variant run's test metrics (``metrics.parquet``,
split ``test``) and its pseudo-label check per iteration (``iter-NN/evaluate/pseudo_label_filter.json`` and
``pseudo_labels.parquet``: the fits' vertex error against the hidden truth, the filter's precision) and puts them
next to the benchmark's recorded arms (``benchmarks/results/<fidelity>.json``).

    python benchmarks/compare_loops.py --fidelity fidelity_fix --runs bench-fix-sil:silhouette_16 \\
        [--runs OTHER[:LABEL] ...] [--iteration I] --record-as fidelity_loop_silhouette

Figures: ``mcd_<label>_iter<i>``, ``rot_err_deg_<label>_iter<i>``, ``median_fit_vertex_err_cm_<label>_iter<i>``,
``filter_precision_<label>_iter<i>``, ``filter_base_rate_<label>_iter<i>``, ``fit_joint_angle_deg_<label>_iter<i>``
(how far the fits articulate the rig: mean excess rotation of the non-root joints),
``median_fit_mask_iou_<label>_iter<i>`` and ``median_fit_mask_iou_gain_<label>_iter<i>`` (how well the fits'
silhouettes explain the photos' masks, and how much better than the rest pose's; no truth needed) for every
variant, the benchmark's
``mcd_{loop,control,oracle}_iter<i>`` and ``rot_err_deg_…`` copied, ``gap_to_control_cm_<label>`` (the
variant's test mCD at the benchmark's last iteration, or at ``--iteration``, minus the control's: negative = the
variant beats the control) and ``gap_recovered_<label>`` (the share of the control → oracle gap it closes there).
A random-poses baseline trained on from the same Φ₀ (``--random-poses --init-predictor``, iterations 0) is one
training round from Φ₀: its figures count as iteration 1.

A variant run at another seed (``--seed s --set train.seed=s``) is measured against the control and oracle at the
same seed when its spec names a reference run, ``RUN:LABEL@wide-seed1``: the rounds ``bench_fidelity.py --seeds``
caches there (``mcd_{control,oracle}_<label>_iter<i>``; the gap figures then use them). With ``--seeds-mean`` the
runs are the seeds of one variant, and their mean is compared the way ``bench_fidelity`` compares seeds:
``mcd_matched_mean``, ``mcd_{control,oracle}_matched_mean``, ``headroom_matched_mean`` and
``gap_recovered_matched_mean`` (mean variant against the mean of each run's own control and oracle: the record's
seed-0 arms for a run without a reference).

With ``--truth`` each iteration's ok fits are also scored against the hidden poses by bone direction
(``median_fit_bone_err_deg_<label>_iter<i>``, ``pct_bones_better_than_rest_<label>_iter<i>``, next to
``median_rest_pose_bone_err_deg_<label>_iter<i>``; ``evaluation_truth.pseudo_label_errors``): whether the poses
the loop rendered bend the right bones the right way, which the vertex error of a near-rest fit does not say.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _results import RESULTS_DIR, record, record_name  # noqa: E402
from bench_fidelity import gap_recovered  # noqa: E402

from bat3r_core.poses import mean_joint_angle_deg  # noqa: E402
from bat3r_core.runs import RunLayout, read_manifest  # noqa: E402

ARMS = ("loop", "control", "oracle")


def _run_spec(text: str) -> tuple[str, str, str | None]:
    spec, _, reference = text.partition("@")
    name, _, label = spec.partition(":")
    label = label or name
    if not name or not all(c.isalnum() or c in "_-" for c in label) or ("@" in text and not reference):
        raise argparse.ArgumentTypeError(f"--runs: expected RUN[:LABEL][@REFERENCE_RUN] (label of letters, digits, "
                                         f"'_', '-'), got {text!r}")
    return name, label.replace("-", "_"), reference or None


def reference_figures(run_dir: Path, label: str) -> dict[str, float]:
    """A variant's seed-matched control and oracle: the rounds ``bench_fidelity.py --seeds`` caches under
    ``<reference run>/fidelity/{control,oracle}/round-NN/metrics.json`` (Φ₀ trained on with the variant's training
    seed and scored with its evaluation seeds), as ``mcd_{control,oracle}_<label>_iter<i>``. Without them a variant
    at another seed would be measured against seed 0's control, and the spread between seeds (a few tenths of a cm
    here) would read as the loop's gain or loss."""
    figures: dict[str, float] = {}
    for arm in ("control", "oracle"):
        for cached in sorted((run_dir / "fidelity" / arm).glob("round-*/metrics.json")):
            i = int(cached.parent.name.split("-")[1])
            row = json.loads(cached.read_text())
            figures[f"mcd_{arm}_{label}_iter{i}"] = round(float(row["mcd_cm"]), 3)
    if not any(k.startswith("mcd_control_") for k in figures):
        raise FileNotFoundError(f"{run_dir / 'fidelity' / 'control'}: no round-NN/metrics.json (run "
                                f"bench_fidelity.py --seeds for it, or name no @REFERENCE_RUN)")
    return figures


def run_figures(run_dir: Path, label: str, truth: dict | None = None, rig=None) -> dict[str, float]:
    """Test metrics and pseudo-label checks of one bootstrap run folder, keyed by ``label``; with the collection's
    ``truth`` (``evaluation_truth.load_ground_truth``) and the run's ``rig``, the fits' bone direction errors."""
    import pyarrow.parquet as pq

    metrics = run_dir / "metrics.parquet"
    if not metrics.is_file():
        raise FileNotFoundError(f"{metrics}: no such file (is {run_dir.name} a finished bootstrap run?)")
    figures: dict[str, float] = {}
    shift = 1 if warm_started_baseline(run_dir) else 0
    for row in pq.read_table(metrics).to_pylist():
        if row.get("split") != "test" or row.get("mcd_cm") is None:
            continue
        i = int(row["iteration"]) + shift
        figures[f"mcd_{label}_iter{i}"] = round(float(row["mcd_cm"]), 3)
        figures[f"rot_err_deg_{label}_iter{i}"] = round(float(row["rot_err_deg"]), 1)
    if not figures:
        raise ValueError(f"{metrics}: no test-split rows with an mCD")
    for evaluate in sorted(run_dir.glob("iter-*/evaluate")):
        i = int(evaluate.parent.name.split("-")[1])
        check = evaluate / "pseudo_label_filter.json"
        if check.is_file():
            data = json.loads(check.read_text())
            for key in ("precision", "base_rate"):
                if data.get(key) is not None:
                    figures[f"filter_{key}_{label}_iter{i}"] = round(float(data[key]), 3)
        labels = evaluate / "pseudo_labels.parquet"
        if labels.is_file():
            err = np.array([e for e in pq.read_table(labels, columns=["vertex_err_cm"]).column(0).to_pylist()
                            if e is not None], dtype=np.float64)
            if len(err):
                figures[f"median_fit_vertex_err_cm_{label}_iter{i}"] = round(float(np.median(err)), 2)
    for filtered in sorted(run_dir.glob("iter-*/filter")):
        figures.update(mask_figures(filtered, label, int(filtered.parent.name.split("-")[1])))
    for fit in sorted(run_dir.glob("iter-*/fit")):
        i = int(fit.parent.name.split("-")[1])
        rows = ok_pose_rows(fit)  # read once: the joint angle and the bone errors both score these poses
        if rows:
            figures[f"fit_joint_angle_deg_{label}_iter{i}"] = round(
                mean_joint_angle_deg([r["excess_rotations"] for r in rows]), 1)
        if truth is not None and rig is not None:
            figures.update(bone_figures(rows, label, i, truth, rig))
    if shift:  # the random poses it trained on, in place of fits
        rows = ok_pose_rows(run_dir / "iter-00" / "plan")
        if rows:
            figures[f"fit_joint_angle_deg_{label}_iter1"] = round(
                mean_joint_angle_deg([r["excess_rotations"] for r in rows]), 1)
    return figures


def mask_figures(filter_dir: Path, label: str, iteration: int) -> dict[str, float]:
    """Median ``mask_iou`` and ``mask_iou_gain`` of an iteration's fits (the filter's quality columns: the fitted
    mesh's silhouette through its recovered camera against the photo's mask, and that IoU minus the rest pose's
    through the same camera), over the fits that have them: how well the fits explain the photos, with no truth."""
    import pyarrow.parquet as pq

    figures: dict[str, float] = {}
    for column in ("mask_iou", "mask_iou_gain"):
        values = [v for part in sorted(filter_dir.glob("part-*.parquet")) if column in pq.read_schema(part).names
                  for v in pq.read_table(part, columns=[column]).column(0).to_pylist() if v is not None]
        values = np.array(values, dtype=np.float64)
        values = values[np.isfinite(values)]
        if len(values):
            figures[f"median_fit_{column}_{label}_iter{iteration}"] = round(float(np.median(values)), 3)
    return figures


def bone_figures(rows: list[dict], label: str, iteration: int, truth: dict, rig) -> dict[str, float]:
    """Median bone direction error (degrees) of an iteration's ok fits ``rows`` that have a true pose, of the rest
    pose for the same images, and the share of fits that beat the rest pose by it
    (``bench_fit_oracle.pose_quality``, the fit oracle's own comparison)."""
    from bench_fit_oracle import pose_quality

    rows = [r for r in rows if r.get("sample_id") in truth]
    if not rows:
        return {}
    q = pose_quality(rows, truth, rig)
    return {f"median_fit_bone_err_deg_{label}_iter{iteration}": round(q["median_bone_err_deg"], 2),
            f"median_rest_pose_bone_err_deg_{label}_iter{iteration}": round(q["median_rest_pose_bone_err_deg"], 2),
            f"pct_bones_better_than_rest_{label}_iter{iteration}": round(q["pct_bones_better_than_rest"], 1)}


def warm_started_baseline(run_dir: Path) -> bool:
    """Whether the run is the random-poses baseline trained on from a given Φ₀ (``--random-poses
    --init-predictor``, iterations 0): its iteration 0 is one training round from Φ₀, so its figures count as
    iteration 1, where the control's first round is."""
    config = read_manifest(RunLayout(run_dir.parents[1], run_dir.parent.name, run_dir.name)).get("config", {})
    parameters = config.get("parameters", {})
    return bool(config.get("ablations", {}).get("random_poses") and parameters.get("init_predictor")
                and parameters.get("iterations") == 0)


def ok_pose_rows(folder: Path) -> list[dict]:
    """The rows of an iteration's fits (or of a plan's render jobs, which have no status column) whose status is ok
    and that have a pose: ``excess_rotations``, with ``sample_id`` and ``status`` where the shards have them. Only
    those columns are read."""
    import pyarrow.parquet as pq

    rows = []
    for part in sorted(folder.glob("part-*.parquet")):
        columns = [c for c in ("sample_id", "status", "excess_rotations") if c in pq.read_schema(part).names]
        rows += [r for r in pq.read_table(part, columns=columns).to_pylist()
                 if r.get("status", "ok") == "ok" and r.get("excess_rotations") is not None]
    return rows


def main(argv: list[str] | None = None) -> dict[str, float]:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--fidelity", required=True, help="name of the benchmarks/results/<name>.json to compare with")
    p.add_argument("--runs", type=_run_spec, action="append", required=True, metavar="RUN[:LABEL][@REFERENCE_RUN]",
                   help="a bootstrap run of the same category started from the benchmark's Φ₀ (repeatable); "
                        "@REFERENCE_RUN: measure it against that run's cached seed-matched control and oracle "
                        "rounds (bench_fidelity.py --seeds: <run>-seed<s>) instead of the benchmark's seed-0 arms")
    p.add_argument("--category", default="toy")
    p.add_argument("--seeds-mean", action="store_true",
                   help="the runs are seeds of one variant: also compare their mean test mCD against the mean of "
                        "their controls and oracles (seed-matched where the run names a reference run)")
    p.add_argument("--iteration", type=int, default=None,
                   help="compare at this iteration (default: the benchmark's last; e.g. 1 for one-iteration variants)")
    p.add_argument("--storage-root", type=Path, default=None,
                   help="where runs live (default: the data catalog's storage root)")
    p.add_argument("--truth", type=Path, default=None, metavar="GROUND_TRUTH_NPZ",
                   help="the collection's hidden ground truth (a generated collection's ground_truth.npz): adds "
                        "truth_joint_angle_deg, how far the true poses articulate the rig, next to the fits', "
                        "and the fits' bone direction errors against it")
    p.add_argument("--record-as", type=record_name, required=True, help="name of the results/<name>.json to write")
    p.add_argument("--results-dir", type=Path, default=None,
                   help="write the json there and leave RESULTS.md alone (default: benchmarks/results)")
    args = p.parse_args(argv)
    labels = [label for _, label, _ in args.runs]
    for label in labels:  # a run's figures are keyed by its label: two runs, or a run and an arm, must not share keys
        if labels.count(label) > 1:
            p.error(f"--runs: label {label!r} is given to {labels.count(label)} runs; name them apart (RUN:LABEL)")
        if label in ARMS or label.startswith(("control_", "oracle_")):
            p.error(f"--runs: label {label!r} would mix its figures with the benchmark's arms or a run's "
                    f"references (mcd_{{control,oracle}}_<label>_iter<i>); choose one that is not 'loop', "
                    f"'control', 'oracle' and starts with neither 'control_' nor 'oracle_'")
    bench_file = (args.results_dir or RESULTS_DIR) / f"{args.fidelity}.json"
    if not bench_file.is_file() and args.results_dir is not None:
        bench_file = RESULTS_DIR / f"{args.fidelity}.json"
    if not bench_file.is_file():
        raise SystemExit(f"--fidelity: {bench_file} does not exist (a bench_fidelity.py --record-as name)")
    bench = json.loads(bench_file.read_text())
    figures = {k: v for k, v in bench.items()
               if isinstance(v, (int, float)) and k.startswith(tuple(f"{m}_{a}_iter" for m in ("mcd", "rot_err_deg")
                                                                     for a in ARMS))}
    last = max((int(k.rsplit("iter", 1)[1]) for k in figures if k.startswith("mcd_control_iter")), default=None)
    if last is None:
        raise SystemExit(f"--fidelity: {bench_file} has no control arm (mcd_control_iter<i>)")
    if args.iteration is not None:
        # past the record's last iteration only when every run brings its own (seed-matched) control and oracle
        if f"mcd_control_iter{args.iteration}" not in figures and any(ref is None for _, _, ref in args.runs):
            raise SystemExit(f"--iteration: {bench_file} has no control figure at iteration {args.iteration} "
                             f"(it has 0..{last}); runs measured there need their own references "
                             f"(RUN:LABEL@REFERENCE_RUN)")
        last = args.iteration
    if args.storage_root is None:
        from bat3r_core.catalog import load_catalog

        args.storage_root = load_catalog(None, validate_stages=False).storage()
    lines = []
    truth = rig = None
    if args.truth is not None:
        from bat3r_core.evaluation_truth import load_ground_truth
        from bat3r_core.rig_io import load_rig

        truth = load_ground_truth(args.truth)
        poses = [t["excess_rotations"] for t in truth.values()]
        figures["truth_joint_angle_deg"] = round(mean_joint_angle_deg(poses), 1)
        config = read_manifest(RunLayout(args.storage_root, args.category, args.runs[0][0])).get("config", {})
        asset = config.get("assets", {}).get("asset")
        if asset:
            rig = load_rig(asset)
        else:
            lines.append(f"no bone direction errors: run {args.runs[0][0]!r} records no asset in its manifest")
    matched = []  # (variant, control, oracle) at the last iteration, each against its own references
    for name, label, reference in args.runs:
        got = run_figures(Path(args.storage_root) / args.category / name, label, truth, rig)
        figures.update(got)
        control, oracle, which = figures.get(f"mcd_control_iter{last}"), figures.get(f"mcd_oracle_iter{last}"), ""
        if reference is not None:
            refs = reference_figures(Path(args.storage_root) / args.category / reference, label)
            figures.update(refs)
            if f"mcd_control_{label}_iter{last}" not in refs:
                raise SystemExit(f"--runs {name}@{reference}: the reference run has no control round {last}")
            control, oracle = refs[f"mcd_control_{label}_iter{last}"], refs.get(f"mcd_oracle_{label}_iter{last}")
            which = f" (seed-matched, {reference})"
        final = got.get(f"mcd_{label}_iter{last}")
        if final is not None:
            gap = round(final - control, 3)
            figures[f"gap_to_control_cm_{label}"] = gap
            recovered = float("nan") if oracle is None else gap_recovered(control, oracle, final)
            if np.isfinite(recovered):  # the share of the control -> oracle gap it closes (none: no gap)
                figures[f"gap_recovered_{label}"] = round(recovered, 3)
            if oracle is not None:
                matched.append((final, control, oracle))
            loop = figures.get(f"mcd_loop_iter{last}")  # the benchmark's own loop (none past its last iteration)
            lines.append(f"{label} ({name}): iteration {last} test mCD {final:.2f} cm against the control's "
                         f"{control:.2f}{which}" + ("" if loop is None else f" and the loop's {loop:.2f}") + ": "
                         + ("beats the control" if gap < 0 else "behind the control"))
        else:
            lines.append(f"{label} ({name}): no test mCD at iteration {last} yet")
    if args.seeds_mean:  # the runs are seeds of one variant: mean against mean control and oracle (bench_fidelity)
        if len(matched) < 2:
            raise SystemExit(f"--seeds-mean: needs two or more runs with a test mCD and an oracle at iteration {last}, "
                             f"got {len(matched)}")
        final, control, oracle = (float(np.mean(c)) for c in zip(*matched))
        figures.update(n_seeds_matched_mean=len(matched), mcd_matched_mean=round(final, 3),
                       mcd_control_matched_mean=round(control, 3), mcd_oracle_matched_mean=round(oracle, 3),
                       headroom_matched_mean=round(oracle / control, 3))
        recovered = gap_recovered(control, oracle, final)
        if np.isfinite(recovered):
            figures["gap_recovered_matched_mean"] = round(recovered, 3)
        lines.append(f"over the {len(matched)} seeds: mean mCD {final:.2f} cm against the control's "
                     f"{control:.2f} and the oracle's {oracle:.2f} (headroom {oracle / control:.3f}): "
                     f"{recovered:.0%} of the gap recovered")
    for line in lines:
        print(line)
    record(args.record_as, figures, notes=f"loop variants from {args.fidelity}'s Φ₀ against its arms. "
           + "; ".join(lines), results_dir=args.results_dir)
    return figures


if __name__ == "__main__":
    main()
