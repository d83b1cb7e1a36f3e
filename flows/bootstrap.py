"""``bootstrap`` flow: the run's data, the canonical initialisation (iteration 0), metrics, report and artifacts.

Reads like the data flow of ``DESIGN.md`` for iteration 0 (which replaces infer/fit/plan with camera sampling
around the rest-pose mesh)::

    collection + test split ── toy_collection ─▶ <run>/collection, <run>/test shards
    rest-pose rig           ── plan ───────────▶ iter-00/plan      render jobs (canonical, or random poses)
    render jobs + rig       ── render ─────────▶ iter-00/render    training shards (RGB, mask, P/Q/occupancy)
    training shards         ── features ───────▶ iter-00/features  feature shards
    training shards         ── train ──────────▶ iter-00/train     Φ_0 (predictor.pt)
    evaluate shards         ── evaluate ───────▶ metrics.parquet, report.html, dashboard artifacts

Every task is cached (inputs + stage config + stage code version + output location): rerunning with the same run
name after a crash recomputes only what is missing. Local run:
``python flows/bootstrap.py --category toy --preset tiny --iterations 0``.
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

from bat3r_core.config_utils import to_mapping
from bat3r_core.runs import prune_shards, write_manifest
from flows._artifacts import publish_iteration_artifacts
from flows._fanout import StageResult, artifact_key, run_stage
from flows._runners import make_task_runner
from flows._settings import Ablations, RunSettings, resolve_run
from flows.evaluate import evaluate
from flows.toy_collection import prepare_split
from tasks._cache import for_run
from tasks.features import extract_features_shard
from tasks.plan import plan_sampled_jobs
from tasks.render import render_shard
from tasks.train import train_model

__all__ = ["bootstrap", "canonical_initialisation", "STAGE_MODULES", "MISSING_FOR_ITERATIONS"]

STAGE_MODULES = {
    "collection": "bat3r_core.predictor.collection", "toy_collection": "bat3r_core.datasets",
    "plan": "bat3r_core.datasets", "render": "bat3r_core.render.runner",
    "features": "bat3r_core.predictor.features", "train": "bat3r_core.predictor.train",
    "evaluate": "bat3r_core.evaluation", "report": "bat3r_core.report",
}
"""The bat3r_core module each stage runs; their code versions go into ``manifest.json`` and the cache keys."""

MISSING_FOR_ITERATIONS = (
    "shard-level mesh fitting (iter-NN/fit from infer shards; bat3r_core.fitting has fit_batch only)",
    "view planning after fitting (iter-NN/plan render jobs from fits and viewpoint augmentation)",
    "per-sample evaluation of a test shard (iter-NN/evaluate rows from predictions and ground truth)",
)
"""bat3r_core functions the bootstrap iterations i >= 1 need and that do not exist yet."""


def _ablations(**switches: bool) -> Ablations:
    return Ablations(**switches)


def _stage_configs(settings: RunSettings, seed: int) -> dict[str, Any]:
    kind = "random_pose" if settings.ablations.random_poses else "canonical"
    return {
        "plan": {"kind": kind, "n": settings.canonical_samples, "seed": seed, "resolution": settings.image_size,
                 "shard_size": settings.shard_size, "body_frame": settings.body_frame,
                 "prior": to_mapping(settings.camera_prior), "num_textures": len(settings.assets.textures),
                 "num_envmaps": len(settings.assets.envmaps)},
        "render": {"render": to_mapping(settings.render), "assets": to_mapping(settings.assets)},
        "features": to_mapping(settings.features),
        "train": {"model": to_mapping(settings.model), "train": to_mapping(settings.train),
                  "features": to_mapping(settings.features)},
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
    metrics = evaluate(category, run_name, storage_root=str(layout.storage_root))
    publish_iteration_artifacts(layout, 0, stages, metrics["rows"],
                                notes=["Per-sample evaluation of the test split is not available yet."])
    return {"stages": {r.stage: list(r.records) for r in stages},
            "states": {r.stage: list(r.states) for r in stages},
            "predictor": train.records[0]["predictor"], "metrics": metrics["rows"]}


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
        iterations: bootstrap iterations after the canonical initialisation (default: the preset's). Only 0 runs
            today: iterations need the bat3r_core functions listed in ``MISSING_FOR_ITERATIONS``.
        run_name: the run folder ``<storage root>/<category>/<run name>`` (default: the preset name). Rerunning
            with the same name reuses every completed task.
        overrides: dotted settings, e.g. ``{"train.steps": 100, "run.canonical_samples": 64}``
            (``flows._settings``).
        gaussian_cameras ... raw_images: the paper's ablation switches (``flows._settings.Ablations``).
        task_runner: a preset of ``deploy/task_runners.yaml`` (``local``, ``dask``, ``dask-cuda``, ``slurm``) or
            the path of a YAML file with one runner config.
        max_failed_fraction: a stage continues while at most this fraction of its shards failed after retries.
        seed: seed of the sampled render jobs.

    Returns ``{"run_dir", "iterations": [iteration-0 result], "metrics": rows}``.
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
    if n_iter > 0:
        raise ValueError(f"iterations={n_iter}: bootstrap iterations after the canonical initialisation need "
                         f"bat3r_core functions that do not exist yet: {'; '.join(MISSING_FOR_ITERATIONS)}. "
                         "Run with iterations=0 (--iterations 0) for the canonical initialisation.")
    layout = settings.layout.create()
    write_manifest(layout, {**settings.to_mapping(), "parameters": {
        "iterations": n_iter, "task_runner": task_runner, "seed": seed, "overrides": overrides}}, STAGE_MODULES)
    logger.info("run folder %s", layout.root)

    runner = make_task_runner(task_runner)
    for split, spec in (("collection", settings.collection), ("test", settings.test_split)):
        if spec is not None:
            prepare_split(settings, split, spec)
    init = canonical_initialisation.with_options(task_runner=runner)(
        category, preset, run_name, overrides, dataclasses.asdict(settings.ablations), seed,
        settings.max_failed_fraction)
    return {"run_dir": str(layout.root), "iterations": [init], "metrics": init["metrics"]}


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
