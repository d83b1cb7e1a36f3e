"""Same-compute references for ``make demo``: does the bootstrap loop beat training Φ₀ longer, and how far is it
from perfect pseudo-labels?

Reads the finished demo run (``runs/toy/<run name>``, default ``demo``; the overrides its manifest records apply)
and continues Φ₀ for as many warm-started rounds as the loop has iterations, each round with the run's training
schedule — the same training compute as the loop's Φ_1 … Φ_n — on two fixed datasets:

* control: the canonical renders of iteration 0 (rest pose only): what the loop must beat;
* oracle: the collection's own images labelled with their hidden truth (true pose and camera, ray-cast through
  the collection's crop; ``bat3r_core.raw_images.raw_image_shard``): what perfect fits would give, on exactly the
  images the test split is drawn like — an upper reference for any pseudo-labelling at this compute.

Every round is evaluated on the same test split with the same metrics as the loop (``bat3r_core.evaluation``),
and ``benchmarks/results/<record-as>.json`` records the sequences side by side: ``mcd_loop_cm_iter<i>`` (from the
run's ``metrics.parquet``), ``mcd_control_cm_iter<i>`` and ``mcd_oracle_cm_iter<i>``.

    python benchmarks/bench_demo_control.py [--run-name demo] [--record-as demo_control] [--no-oracle]

Takes about 3 minutes per iteration and reference on 2 CPU cores.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

if __name__ == "__main__":  # before Prefect is imported: it reads its settings once, at import
    from bat3r_core.cli import local_server_environment

    local_server_environment()

from _results import record, record_name  # noqa: E402

from bat3r_core import evaluation, evaluation_truth, shards  # noqa: E402
from bat3r_core.datasets import raw_image_shard  # noqa: E402
from bat3r_core.predictor.collection import crop_transform_from_row  # noqa: E402
from bat3r_core.predictor.data import ShardDataset, hold_on_device  # noqa: E402
from bat3r_core.predictor.features import make_feature_fn  # noqa: E402
from bat3r_core.predictor.infer import predict_collection  # noqa: E402
from bat3r_core.predictor.train import Trainer  # noqa: E402
from bat3r_core.rig_io import load_rig  # noqa: E402
from flows._settings import recorded_run  # noqa: E402


def _test_metrics(settings, predictor: Path, out: Path, iteration: int, seed: int, split: str = "test") -> dict:
    """The test-split metrics row of ``predictor`` (``evaluation.aggregate``), computed as the loop's test_infer and
    evaluate stages compute them for ``iteration`` (same features, ground truth and sampling seed).
    ``split="collection"`` scores the collection's own images against their hidden truth the same way."""
    if split not in ("test", "collection"):
        raise ValueError(f"split: expected 'test' or 'collection', got {split!r}")
    truth = (settings.test_split if split == "test" else settings.collection).get("ground_truth")
    if not truth:
        raise ValueError(f"the {split} split of the run's category has no ground_truth folder in the catalog")
    evaluate_dir = out / ("evaluate" if split == "test" else f"evaluate_{split}")
    images = settings.layout.run_stage_dir(split)
    if not shards.list_shards(images):
        raise FileNotFoundError(f"{images}: no {split} shards to score (run the bootstrap flow for run "
                                f"{settings.layout.run_name!r} first, e.g. with --iterations 0, to prepare its "
                                f"{split} split)")
    predict_collection(predictor, images, out / f"{split}_infer",
                       feature_fn=make_feature_fn(settings.features), device="cpu")
    gt = evaluation_truth.load_ground_truth(Path(truth) / "ground_truth.npz")
    rig = load_rig(settings.assets.asset)
    for i in shards.list_shards(out / f"{split}_infer"):
        evaluation_truth.evaluate_prediction_shard(out / f"{split}_infer", i, gt, rig, settings.body_frame, split,
                                                   iteration, evaluate_dir, seed=seed)
    return evaluation.aggregate(shards.read_table(evaluate_dir))[0]


def true_fit_rows(collection_rows: list[dict], ground_truth: dict) -> list[dict]:
    """Fit rows (the fit stage's columns that ``raw_image_shard`` reads) carrying the hidden truth of each ok
    collection image that has one: its pose θ and the camera taking the skinned rig (no global similarity) to the
    pixels of the collection's crop (``evaluation_truth.ground_truth_camera``) — the ground truth's global similarity
    folded into the camera (the toy's global scale is 1)."""
    rows = []
    for row in collection_rows:
        gt = ground_truth.get(row["sample_id"])
        if row["status"] != shards.STATUS_OK or gt is None:
            continue
        if abs(float(gt["global_scale"]) - 1.0) > 1e-9:
            raise ValueError(f"{row['sample_id']}: global scale {float(gt['global_scale'])} cannot be folded into a "
                             "camera; the oracle needs unit-scale ground truth")
        cam = evaluation_truth.ground_truth_camera(gt, crop_transform_from_row(row))
        rg, tg = np.asarray(gt["global_rotation"], np.float64), np.asarray(gt["global_translation"], np.float64)
        rows.append({"sample_id": row["sample_id"], "status": shards.STATUS_OK, "reason": "",
                     "excess_rotations": np.asarray(gt["excess_rotations"], np.float64).ravel().tolist(),
                     "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "width": cam.width,
                     "height": cam.height, "camera_rotation": (cam.R @ rg).ravel().tolist(),
                     "camera_translation": (cam.R @ tg + cam.t).tolist()})
    return rows


def _oracle_dataset(settings, rig, out: Path) -> Path:
    """The collection's crops labelled with their hidden truth, as training shards under ``out/data``."""
    collection = settings.layout.run_stage_dir("collection")
    gt = evaluation_truth.load_ground_truth(Path(settings.collection["ground_truth"]) / "ground_truth.npz")
    for i in shards.list_shards(collection):
        rows, _ = shards.read_shard(collection, i, with_arrays=False)
        shards.write_shard(out / "true_fit", i, true_fit_rows(rows.to_pylist(), gt))
        raw_image_shard(rig, out / "true_fit", collection, i, out / "data", num_layers=settings.model.layers)
    return out / "data"


def _rounds(settings, data: Path, out: Path, iterations: int, run_seed: int) -> list[dict]:
    """Φ₀ trained on ``data`` for ``iterations`` warm-started rounds of the run's schedule; test metrics per round."""
    layout = settings.layout
    dataset = hold_on_device(ShardDataset(data, make_feature_fn(settings.features),
                                          cache_shards=settings.train.shuffle_shards), None,
                             settings.train.mirror_probability)  # on the GPU once for every round, when one fits
    previous = layout.stage_dir(0, "train") / "predictor.pt"
    rows = []
    for it in range(1, iterations + 1):
        o = out / f"round-{it:02d}"
        previous = Trainer(dataset, settings.model, settings.train, o / "train", init_from=previous,
                           mirror=settings.mirror).train()
        rows.append(_test_metrics(settings, previous, o, it, seed=run_seed + it))  # the loop evaluates i: seed + i
    return rows


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run-name", default="demo")
    p.add_argument("--record-as", type=record_name, default="demo_control", help="name of the results/<name>.json to write")
    p.add_argument("--no-oracle", action="store_true", help="skip the perfect-pseudo-label reference")
    args = p.parse_args(argv)
    settings, parameters = recorded_run("toy", args.run_name)  # the run's own settings and seed
    layout, overrides, run_seed = settings.layout, parameters["overrides"], int(parameters["seed"])
    if not layout.metrics.is_file():
        raise FileNotFoundError(f"{layout.metrics}: the run has no metrics yet; finish it first")
    loop = {int(r["iteration"]): float(r["mcd_cm"]) for r in evaluation.read_metrics(layout.root).to_pylist()
            if r["split"] == "test"}
    iterations = max(loop)
    references = {"control": lambda out: layout.stage_dir(0, "render")}
    if not args.no_oracle:
        references["oracle"] = lambda out: _oracle_dataset(settings, load_rig(settings.assets.asset), out)
    figures: dict[str, float] = {"iterations": iterations}
    for it in range(iterations + 1):
        figures[f"mcd_loop_cm_iter{it}"] = round(loop[it], 3)
    for name, data in references.items():
        out = layout.root / name
        figures[f"mcd_{name}_cm_iter0"] = round(loop[0], 3)
        for it, row in enumerate(_rounds(settings, data(out), out, iterations, run_seed), start=1):
            figures[f"mcd_{name}_cm_iter{it}"] = round(row["mcd_cm"], 3)
            figures[f"rot_err_{name}_deg_iter{it}"] = round(row["rot_err_deg"], 1)
            print(f"iteration {it}: loop {loop[it]:.2f} cm, {name} {row['mcd_cm']:.2f} cm "
                  f"(ΔR {row['rot_err_deg']:.1f}°)", flush=True)
    for name in ("loop", *references):
        figures[f"ratio_{name}"] = round(figures[f"mcd_{name}_cm_iter{iterations}"] / loop[0], 3)
    record(args.record_as, figures,
           notes=(f"toy, {settings.preset} preset, run {args.run_name!r} (overrides {overrides}): the loop's test mCD "
                  f"per iteration next to Φ₀ trained on for the same number of warm-started rounds "
                  f"({settings.train.steps} steps each) on its canonical renders only (control)"
                  + ("" if args.no_oracle else " and on the collection's images with their true labels (oracle)")
                  + f"; {os.cpu_count()} CPU cores"))
    return figures


if __name__ == "__main__":
    main()
