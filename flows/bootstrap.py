"""``bootstrap`` flow: the run's data, the canonical initialisation (iteration 0), then one refinement subflow per
iteration, with metrics, report and dashboard artifacts after each.

Reads like the data flow of ``DESIGN.md``::

    collection + test split ── toy_collection ─▶ <run>/collection, <run>/test shards
    iteration 0 (camera sampling around the rest-pose mesh instead of infer/fit/plan):
    rest-pose rig           ── plan ───────────▶ iter-00/plan      render jobs (canonical, or random poses)
    iteration i >= 1 (predictor Φ_{i-1}):
    collection              ── infer(Φ_{i-1}) ─▶ iter-ii/infer     predicted dual point maps and clouds
    predictions + rig       ── fit ────────────▶ iter-ii/fit       θ, global similarity, camera, losses, status
    fits                    ── plan views ─────▶ iter-ii/plan      render jobs (estimated + augmented views)
    every iteration:
    render jobs + rig       ── render ─────────▶ iter-ii/render    training shards (RGB, mask, P/Q/occupancy)
    training shards         ── features ───────▶ iter-ii/features  feature shards
    training shards         ── train ──────────▶ iter-ii/train     Φ_i (predictor.pt)
    test split              ── infer(Φ_i) ─────▶ iter-ii/test_infer
    test predictions + GT   ── evaluate ───────▶ iter-ii/evaluate, metrics.parquet, report.html, artifacts

Every task is cached (inputs + stage config + stage code version + output location): rerunning with the same run
name after a crash recomputes only what is missing. Local run:
``python flows/bootstrap.py --category toy --preset tiny``.
"""
from __future__ import annotations

import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a script or loaded by path (deployments): make the project root importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import dataclasses
from typing import Any

from prefect import flow
from prefect.logging import get_run_logger

from bat3r_core import shards
from bat3r_core.config_utils import to_mapping
from bat3r_core.runs import prune_shards, write_manifest
from flows._artifacts import publish_iteration_artifacts
from flows._fanout import StageResult, artifact_key, run_stage
from flows._runners import make_task_runner
from flows._settings import Ablations, RunSettings, resolve_run
from flows.evaluate import evaluate
from flows.toy_collection import prepare_split
from tasks._cache import for_run
from tasks.evaluate import evaluate_shard, pseudo_label_quality
from tasks.features import extract_features_shard
from tasks.fit import fit_shard
from tasks.plan import plan_sampled_jobs, plan_views_shard
from tasks.predict import infer_shard
from tasks.raw_images import raw_image_shard
from tasks.render import render_shard
from tasks.train import train_model

__all__ = ["bootstrap", "canonical_initialisation", "refinement_iteration", "STAGE_MODULES"]

STAGE_MODULES = {
    "collection": "bat3r_core.predictor.collection", "toy_collection": "bat3r_core.datasets",
    "plan": "bat3r_core.datasets", "render": "bat3r_core.render.runner",
    "features": "bat3r_core.predictor.features", "train": "bat3r_core.predictor.train",
    "infer": "bat3r_core.predictor.infer", "fit": "bat3r_core.fitting.fit", "plan_views": "bat3r_core.fitting.augment",
    "raw_images": "bat3r_core.datasets",
    "evaluate": "bat3r_core.evaluation", "report": "bat3r_core.report",
}
"""The bat3r_core module each stage runs; their code versions go into ``manifest.json`` and the cache keys."""

def _ablations(**switches: bool) -> Ablations:
    return Ablations(**switches)


def _stage_configs(settings: RunSettings, seed: int) -> dict[str, Any]:
    kind = "random_pose" if settings.ablations.random_poses else "canonical"
    gt = (settings.test_split or {}).get("ground_truth")
    return {
        "plan": {"kind": kind, "n": settings.canonical_samples, "seed": seed, "resolution": settings.image_size,
                 "shard_size": settings.shard_size, "body_frame": settings.body_frame,
                 "prior": to_mapping(settings.camera_prior), "num_textures": settings.assets.num_textures,
                 "num_envmaps": len(settings.assets.envmaps)},
        "render": {"render": to_mapping(settings.render), "assets": to_mapping(settings.assets)},
        "features": to_mapping(settings.features),
        "train": {"model": to_mapping(settings.model), "train": to_mapping(settings.train),
                  "features": to_mapping(settings.features)},
        "infer": {"features": to_mapping(settings.features), "batch_size": 16},
        "fit": {"fitting": to_mapping(settings.fitting), "fov_deg": settings.camera_prior.fov_deg,
                "resolution": settings.image_size,
                "geodesic_cache": str(settings.layout.storage_root / "_cache" / "geodesics")},
        "plan_views": {"augment": {"camera_prior": to_mapping(settings.camera_prior),
                                   "width": settings.image_size, "height": settings.image_size,
                                   "num_textures": settings.assets.num_textures,
                                   "num_envmaps": len(settings.assets.envmaps),
                                   "augment": not settings.ablations.no_view_augmentation},
                       "body_frame": settings.body_frame, "seed": seed},
        "evaluate": None if not gt else {"asset": settings.assets.asset,
                                         "ground_truth": str(Path(gt) / "ground_truth.npz"),
                                         "body_frame": settings.body_frame, "split": "test", "seed": seed},
    }


def _progress(settings: RunSettings, iteration: int, stage: str) -> str:
    return artifact_key(settings.layout.category, settings.layout.run_name, f"iter-{iteration:02d}", stage)


@flow(name="canonical-initialisation", flow_run_name="{category}-{run_name}-iter-00")
def canonical_initialisation(category: str, preset: str, run_name: str, overrides: dict[str, Any],
                             ablations: dict[str, bool], seed: int, max_failed_fraction: float) -> dict[str, Any]:
    """Iteration 0: sample render jobs around the rest-pose mesh, render them, extract features, train Φ_0.
    Returns ``{"stages": {stage: [records]}, "states": {stage: [state names]}, "predictor": path, "metrics": rows}``."""
    settings = resolve_run(category, preset, run_name, overrides, ablations, max_failed_fraction=max_failed_fraction)
    layout, cfg, mff = settings.layout, _stage_configs(settings, seed), settings.max_failed_fraction

    plan = run_stage("plan", for_run(plan_sampled_jobs, layout),
                     [{"asset": settings.assets.asset, "out_dir": str(layout.stage_dir(0, "plan")),
                       "config": cfg["plan"]}],
                     progress_key=_progress(settings, 0, "plan"), max_failed_fraction=0.0)
    job_files = plan.records[0]["files"]
    keep = range(len(job_files))
    for stage in ("plan", "render", "features"):  # shards of an earlier, larger plan of this run
        prune_shards(layout.stage_dir(0, stage), keep)

    render = run_stage("render", for_run(render_shard, layout),
                       [{"jobs_file": f, "index": i, "out_dir": str(layout.stage_dir(0, "render")),
                         "config": cfg["render"]} for i, f in enumerate(job_files)],
                       progress_key=_progress(settings, 0, "render"), max_failed_fraction=mff)

    features = run_stage("features", for_run(extract_features_shard, layout),
                         [{"input_dir": str(layout.stage_dir(0, "render")), "index": r["index"],
                           "out_dir": str(layout.stage_dir(0, "features")), "config": cfg["features"]}
                          for r in render.records],
                         progress_key=_progress(settings, 0, "features"), max_failed_fraction=mff)

    train = run_stage("train", for_run(train_model, layout),
                      [{"shards_dir": str(layout.stage_dir(0, "render")), "out_dir": str(layout.stage_dir(0, "train")),
                        "config": cfg["train"]}],
                      progress_key=_progress(settings, 0, "train"), max_failed_fraction=0.0)

    stages: list[StageResult] = [plan, render, features, train]
    predictor = train.records[0]["predictor"]
    stages += _evaluate_test(settings, cfg, 0, predictor)
    return _finish_iteration(settings, category, run_name, 0, stages, predictor)


def _evaluate_test(settings: RunSettings, cfg: dict[str, Any], iteration: int, predictor: str) -> list[StageResult]:
    """Φ_iteration on the test split: inference shards, then per-sample evaluation rows (needs ground truth)."""
    layout, mff = settings.layout, settings.max_failed_fraction
    test_dir = layout.run_stage_dir("test")
    if cfg["evaluate"] is None or not shards.list_shards(test_dir):
        return []
    infer = run_stage("test_infer", for_run(infer_shard, layout),
                      [{"predictor": predictor, "collection_dir": str(test_dir), "index": i,
                        "out_dir": str(layout.stage_dir(iteration, "test_infer")), "config": cfg["infer"]}
                       for i in shards.list_shards(test_dir)],
                      progress_key=_progress(settings, iteration, "test_infer"), max_failed_fraction=mff)
    evaluate_cfg = {**cfg["evaluate"], "iteration": iteration}
    rows = run_stage("evaluate", for_run(evaluate_shard, layout),
                     [{"predictions_dir": str(layout.stage_dir(iteration, "test_infer")), "index": r["index"],
                       "out_dir": str(layout.stage_dir(iteration, "evaluate")), "config": evaluate_cfg}
                      for r in infer.records],
                     progress_key=_progress(settings, iteration, "evaluate"), max_failed_fraction=mff)
    return [infer, rows]


def _finish_iteration(settings: RunSettings, category: str, run_name: str, iteration: int,
                      stages: list[StageResult], predictor: str) -> dict[str, Any]:
    """metrics.parquet, report.html and the iteration's dashboard artifacts; the subflow's result."""
    layout = settings.layout
    metrics = evaluate(category, run_name, storage_root=str(layout.storage_root))
    notes = [] if any(r.stage == "evaluate" for r in stages) else \
        ["The test split has no ground truth: no per-sample evaluation."]
    publish_iteration_artifacts(layout, iteration, stages, metrics["rows"], notes=notes)
    return {"stages": {r.stage: list(r.records) for r in stages},
            "states": {r.stage: list(r.states) for r in stages},
            "predictor": predictor, "metrics": metrics["rows"]}


@flow(name="refinement-iteration", flow_run_name="{category}-{run_name}-iter-{iteration:02d}")
def refinement_iteration(category: str, preset: str, run_name: str, iteration: int, predictor: str,
                         overrides: dict[str, Any], ablations: dict[str, bool], seed: int,
                         max_failed_fraction: float) -> dict[str, Any]:
    """Iteration i >= 1: Φ_{i-1} predicts the collection, the rig is fitted to every prediction, the fitted poses are
    rendered from their estimated and augmented viewpoints, and Φ_i is trained on those renders alone (earlier
    iterations' data are discarded, as in the paper). Returns like :func:`canonical_initialisation`."""
    settings = resolve_run(category, preset, run_name, overrides, ablations, max_failed_fraction=max_failed_fraction)
    layout, cfg, mff = settings.layout, _stage_configs(settings, seed + iteration), settings.max_failed_fraction
    collection_dir = layout.run_stage_dir("collection")
    infer = run_stage("infer", for_run(infer_shard, layout),
                      [{"predictor": predictor, "collection_dir": str(collection_dir), "index": i,
                        "out_dir": str(layout.stage_dir(iteration, "infer")), "config": cfg["infer"]}
                       for i in shards.list_shards(collection_dir)],
                      progress_key=_progress(settings, iteration, "infer"), max_failed_fraction=mff)
    fit = run_stage("fit", for_run(fit_shard, layout),
                    [{"asset": settings.assets.asset, "predictions_dir": str(layout.stage_dir(iteration, "infer")),
                      "index": r["index"], "out_dir": str(layout.stage_dir(iteration, "fit")), "config": cfg["fit"]}
                     for r in infer.records],
                    progress_key=_progress(settings, iteration, "fit"), max_failed_fraction=mff)
    earlier = [infer, fit]
    collection_gt = settings.collection.get("ground_truth")
    if collection_gt and (Path(collection_gt) / "ground_truth.npz").is_file():  # pseudo-label quality (toy)
        earlier.append(run_stage("pseudo_labels", for_run(pseudo_label_quality, layout),
                                 [{"fit_dir": str(layout.stage_dir(iteration, "fit")),
                                   "out_dir": str(layout.stage_dir(iteration, "evaluate")),
                                   "config": {"asset": settings.assets.asset,
                                              "ground_truth": str(Path(collection_gt) / "ground_truth.npz")}}],
                                 progress_key=_progress(settings, iteration, "pseudo_labels"),
                                 max_failed_fraction=1.0))
    if settings.ablations.raw_images:  # the raw-image baseline: train on the photos with fitted pseudo-labels
        render = run_stage("render", for_run(raw_image_shard, layout),
                           [{"asset": settings.assets.asset, "fit_dir": str(layout.stage_dir(iteration, "fit")),
                             "collection_dir": str(collection_dir), "index": r["index"],
                             "out_dir": str(layout.stage_dir(iteration, "render")),
                             "config": {"layers": settings.layers}} for r in fit.records],
                           progress_key=_progress(settings, iteration, "render"), max_failed_fraction=mff)
        return _train_and_evaluate(settings, category, run_name, iteration, cfg, earlier, render, predictor)
    plan = run_stage("plan", for_run(plan_views_shard, layout),
                     [{"asset": settings.assets.asset, "fit_dir": str(layout.stage_dir(iteration, "fit")),
                       "index": r["index"], "out_dir": str(layout.stage_dir(iteration, "plan")),
                       "config": cfg["plan_views"]} for r in fit.records],
                     progress_key=_progress(settings, iteration, "plan"), max_failed_fraction=mff)
    job_files = [(r["index"], r["files"][0]) for r in plan.records if r["n_jobs"] > 0]
    for stage in ("render", "features"):  # shards of an earlier plan of this run that this plan does not have
        prune_shards(layout.stage_dir(iteration, stage), [i for i, _ in job_files])
    if not job_files:
        raise RuntimeError(f"iteration {iteration}: no fitted instance produced a render job (fits: "
                           f"{sum(r['n_ok'] for r in fit.records)} ok of {sum(r['n_rows'] for r in fit.records)}); "
                           f"see {layout.stage_dir(iteration, 'fit')}")
    render = run_stage("render", for_run(render_shard, layout),
                       [{"jobs_file": f, "index": i, "out_dir": str(layout.stage_dir(iteration, "render")),
                         "config": cfg["render"]} for i, f in job_files],
                       progress_key=_progress(settings, iteration, "render"), max_failed_fraction=mff)
    return _train_and_evaluate(settings, category, run_name, iteration, cfg, [*earlier, plan], render, predictor)


def _train_and_evaluate(settings: RunSettings, category: str, run_name: str, iteration: int, cfg: dict[str, Any],
                        earlier: list[StageResult], render: StageResult, previous: str) -> dict[str, Any]:
    """features → train Φ_iteration on the iteration's training shards (from Φ_{iteration-1}'s weights
    ``previous`` when ``train.warm_start``) → evaluate it on the test split."""
    layout, mff = settings.layout, settings.max_failed_fraction
    features = run_stage("features", for_run(extract_features_shard, layout),
                         [{"input_dir": str(layout.stage_dir(iteration, "render")), "index": r["index"],
                           "out_dir": str(layout.stage_dir(iteration, "features")), "config": cfg["features"]}
                          for r in render.records],
                         progress_key=_progress(settings, iteration, "features"), max_failed_fraction=mff)
    train = run_stage("train", for_run(train_model, layout),
                      [{"shards_dir": str(layout.stage_dir(iteration, "render")),
                        "out_dir": str(layout.stage_dir(iteration, "train")),
                        "config": {**cfg["train"], "init_from": previous if settings.train.warm_start else None}}],
                      progress_key=_progress(settings, iteration, "train"), max_failed_fraction=0.0)
    new_predictor = train.records[0]["predictor"]
    stages = [*earlier, render, features, train, *_evaluate_test(settings, cfg, iteration, new_predictor)]
    return _finish_iteration(settings, category, run_name, iteration, stages, new_predictor)


def _bootstrap_run_name() -> str:
    from prefect.runtime import flow_run

    p = flow_run.parameters
    return f"{p.get('category', 'toy')}-{p.get('run_name') or p.get('preset', 'tiny')}"


@flow(name="bootstrap", flow_run_name=_bootstrap_run_name)
def bootstrap(category: str = "toy", preset: str = "tiny", iterations: int | None = None,
              run_name: str | None = None, overrides: dict[str, Any] | None = None,
              gaussian_cameras: bool = False, no_fitting_regularisation: bool = False,
              no_view_augmentation: bool = False, random_poses: bool = False, raw_images: bool = False,
              task_runner: str = "local", max_failed_fraction: float = 0.1, seed: int = 0) -> dict[str, Any]:
    """The bootstrap loop of ``category`` at run preset ``preset`` (``tiny``, ``demo``, ``paper``).

    Args:
        iterations: bootstrap iterations after the canonical initialisation (default: the preset's).
        run_name: the run folder ``<storage root>/<category>/<run name>`` (default: the preset name). Rerunning
            with the same name reuses every completed task.
        overrides: dotted settings, e.g. ``{"train.steps": 100, "run.canonical_samples": 64}``
            (``flows._settings``).
        gaussian_cameras ... raw_images: the paper's ablation switches (``flows._settings.Ablations``).
        task_runner: a preset of ``deploy/task_runners.yaml`` (``local``, ``dask``, ``dask-cuda``, ``slurm``) or
            the path of a YAML file with one runner config.
        max_failed_fraction: a stage continues while at most this fraction of its shards failed after retries.
        seed: seed of the sampled render jobs.

    Returns ``{"run_dir", "iterations": [result of each iteration], "metrics": rows}``.
    """
    logger = get_run_logger()
    run_name = run_name or preset
    switches = dict(gaussian_cameras=gaussian_cameras, no_fitting_regularisation=no_fitting_regularisation,
                    no_view_augmentation=no_view_augmentation, random_poses=random_poses, raw_images=raw_images)
    overrides = dict(overrides or {})
    settings = resolve_run(category, preset, run_name, overrides, _ablations(**switches),
                           max_failed_fraction=max_failed_fraction)
    n_iter = settings.iterations if iterations is None else int(iterations)
    if n_iter < 0:
        raise ValueError(f"iterations must be >= 0, got {n_iter}")
    if random_poses and n_iter > 0:
        raise ValueError("random_poses is a baseline trained once on random poses: run it with iterations=0")
    layout = settings.layout.create()
    write_manifest(layout, {**settings.to_mapping(), "parameters": {
        "iterations": n_iter, "task_runner": task_runner, "seed": seed, "overrides": overrides}}, STAGE_MODULES)
    logger.info("run folder %s", layout.root)

    runner = make_task_runner(task_runner)
    for split, spec in (("collection", settings.collection), ("test", settings.test_split)):
        if spec is not None:
            prepare_split(settings, split, spec)
    ablation_dict = dataclasses.asdict(settings.ablations)
    results = [canonical_initialisation.with_options(task_runner=runner)(
        category, preset, run_name, overrides, ablation_dict, seed, settings.max_failed_fraction)]
    for iteration in range(1, n_iter + 1):
        logger.info("iteration %d of %d", iteration, n_iter)
        results.append(refinement_iteration.with_options(task_runner=runner)(
            category, preset, run_name, iteration, results[-1]["predictor"], overrides, ablation_dict, seed,
            settings.max_failed_fraction))
    return {"run_dir": str(layout.root), "iterations": results, "metrics": results[-1]["metrics"]}


def _parse(argv: list[str] | None = None):
    import argparse
    import json

    p = argparse.ArgumentParser(description="Run the bat3r bootstrap flow locally.")
    p.add_argument("--category", default="toy")
    p.add_argument("--preset", default="tiny")
    p.add_argument("--iterations", type=int, default=None)
    p.add_argument("--run-name", default=None)
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=JSON",
                   help="override a setting, e.g. --set train.steps=100 (value parsed as JSON, else a string)")
    for name in ("gaussian-cameras", "no-fitting-regularisation", "no-view-augmentation", "random-poses",
                 "raw-images"):
        p.add_argument(f"--{name}", action="store_true")
    p.add_argument("--task-runner", default="local")
    p.add_argument("--max-failed-fraction", type=float, default=0.1)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    overrides = {}
    for item in args.overrides:
        key, sep, value = item.partition("=")
        if not sep:
            p.error(f"--set expects KEY=VALUE, got {item!r}")
        try:
            overrides[key] = json.loads(value)
        except json.JSONDecodeError:
            overrides[key] = value
    return args, overrides


if __name__ == "__main__":
    args, overrides = _parse()
    result = bootstrap(category=args.category, preset=args.preset, iterations=args.iterations,
                       run_name=args.run_name, overrides=overrides, gaussian_cameras=args.gaussian_cameras,
                       no_fitting_regularisation=args.no_fitting_regularisation,
                       no_view_augmentation=args.no_view_augmentation, random_poses=args.random_poses,
                       raw_images=args.raw_images, task_runner=args.task_runner,
                       max_failed_fraction=args.max_failed_fraction, seed=args.seed)
    print(f"run folder: {result['run_dir']}")
    for row in result["metrics"]:
        print(row)
