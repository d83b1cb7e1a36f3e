"""Same-compute control for ``make demo``: does the bootstrap loop beat simply training Φ₀ longer?

Reads the finished demo run (``runs/toy/<run name>``, default ``demo``; the overrides its manifest records apply),
then continues Φ₀ on the canonical renders of iteration 0 for as many warm-started rounds as the loop has
iterations, each round with the run's training schedule — the same training compute as the loop's Φ_1 … Φ_n, but
on rest-pose renders only. Every round is evaluated on the same test split with the same metrics as the loop
(``bat3r_core.evaluation``), and ``benchmarks/results/<record-as>.json`` records both sequences side by side:
``mcd_loop_cm_iter<i>`` (from the run's ``metrics.parquet``) and ``mcd_control_cm_iter<i>``.

    python benchmarks/bench_demo_control.py [--run-name demo] [--record-as demo_control]

Takes about 3 minutes per iteration on 2 CPU cores.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _results import record  # noqa: E402

from bat3r_core import evaluation, shards  # noqa: E402
from bat3r_core.predictor.data import ShardDataset  # noqa: E402
from bat3r_core.predictor.features import make_feature_fn  # noqa: E402
from bat3r_core.predictor.infer import predict_collection  # noqa: E402
from bat3r_core.predictor.train import Trainer  # noqa: E402
from bat3r_core.rig_io import load_rig  # noqa: E402
from bat3r_core.runs import read_manifest  # noqa: E402
from flows._settings import Ablations, resolve_run  # noqa: E402


def _test_metrics(settings, predictor: Path, out: Path, iteration: int, seed: int) -> dict:
    """The test-split metrics row of ``predictor`` (``evaluation.aggregate``), computed as the loop's test_infer and
    evaluate stages compute them for ``iteration`` (same features, ground truth and sampling seed)."""
    predict_collection(predictor, settings.layout.run_stage_dir("test"), out / "test_infer",
                       feature_fn=make_feature_fn(settings.features), device="cpu")
    gt = evaluation.load_ground_truth(Path(settings.test_split["ground_truth"]) / "ground_truth.npz")
    rig = load_rig(settings.assets.asset)
    for i in shards.list_shards(out / "test_infer"):
        evaluation.evaluate_prediction_shard(out / "test_infer", i, gt, rig, settings.body_frame, "test", iteration,
                                             out / "evaluate", seed=seed)
    return evaluation.aggregate(shards.read_table(out / "evaluate"))[0]


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run-name", default="demo")
    p.add_argument("--preset", default="demo")
    p.add_argument("--record-as", default="demo_control", help="name of the results/<name>.json to write")
    args = p.parse_args(argv)
    layout = resolve_run("toy", args.preset, args.run_name, {}, Ablations()).layout
    if not layout.manifest.is_file():
        raise FileNotFoundError(f"{layout.manifest}: run `make demo` (or flows/demo.py --run-name {args.run_name}) "
                                "first")
    parameters = read_manifest(layout)["config"]["parameters"]  # the run's own settings and seed
    overrides, run_seed = parameters["overrides"], int(parameters["seed"])
    settings = resolve_run("toy", args.preset, args.run_name, overrides, Ablations())
    metrics_path = layout.metrics
    if not metrics_path.is_file():
        raise FileNotFoundError(f"{metrics_path}: the run has no metrics yet; finish it first")
    loop = {int(r["iteration"]): float(r["mcd_cm"]) for r in evaluation.read_metrics(layout.root).to_pylist()
            if r["split"] == "test"}
    iterations = max(loop)
    renders = layout.stage_dir(0, "render")
    previous = layout.stage_dir(0, "train") / "predictor.pt"
    figures: dict[str, float] = {"iterations": iterations, "mcd_loop_cm_iter0": round(loop[0], 3),
                                 "mcd_control_cm_iter0": round(loop[0], 3)}
    dataset = ShardDataset(renders, make_feature_fn(settings.features), cache_shards=settings.train.shuffle_shards)
    for it in range(1, iterations + 1):
        out = layout.root / "control" / f"round-{it:02d}"
        trainer = Trainer(dataset, settings.model, settings.train, out / "train", device="cpu", init_from=previous)
        previous = trainer.train()
        row = _test_metrics(settings, previous, out, it, seed=run_seed + it)  # the loop evaluates i with seed + i
        mcd, rot = row["mcd_cm"], row["rot_err_deg"]
        figures[f"mcd_loop_cm_iter{it}"] = round(loop[it], 3)
        figures[f"mcd_control_cm_iter{it}"] = round(mcd, 3)
        figures[f"rot_err_control_deg_iter{it}"] = round(rot, 1)
        print(f"iteration {it}: loop {loop[it]:.2f} cm, canonical-only control {mcd:.2f} cm (ΔR {rot:.1f}°)")
    figures["ratio_loop"] = round(loop[iterations] / loop[0], 3)
    figures["ratio_control"] = round(figures[f"mcd_control_cm_iter{iterations}"] / loop[0], 3)
    record(args.record_as, figures,
           notes=(f"toy, {args.preset} preset, run {args.run_name!r} (overrides {overrides}): the loop's test mCD "
                  f"per iteration next to Φ₀ trained on for the same number of warm-started rounds "
                  f"({settings.train.steps} steps each) on its canonical renders only; {os.cpu_count()} CPU cores"))
    return figures


if __name__ == "__main__":
    main()
