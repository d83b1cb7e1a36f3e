"""Plan stage: render jobs. Iteration 0 samples cameras around the rest-pose mesh (``canonical``); the random-poses
baseline samples random poses (``random_pose``); later iterations plan the estimated and augmented views of each
fitted instance (``plan_views_shard``). Jobs are written as ``part-NNNNN.parquet`` job files, one per render
shard."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import pyarrow.parquet as pq

from bat3r_core import datasets, shards
from bat3r_core.config_utils import from_mapping
from bat3r_core.fitting.augment import AugmentConfig, plan_views_for_fits
from bat3r_core.render.jobs import write_jobs
from bat3r_core.rig_io import load_rig
from bat3r_core.viewpoints import CameraPriorConfig
from tasks._cache import shard_input_files, stage_task

__all__ = ["plan_sampled_jobs", "plan_views_shard"]

_BUILDERS = {"canonical": datasets.canonical_jobs, "random_pose": datasets.random_pose_jobs}


@stage_task("plan", inputs=lambda p: [Path(p["asset"])], output=lambda p: Path(p["out_dir"]))
def plan_sampled_jobs(asset: str, out_dir: str, config: Mapping[str, Any]) -> dict:
    """Sample render jobs around the rig of ``asset`` and write them to ``out_dir/part-NNNNN.parquet``.

    config: ``{"kind": "canonical" | "random_pose", "n", "seed", "resolution", "shard_size", "body_frame":
    {origin, forward, horizontal}, "prior": CameraPriorConfig mapping, "num_textures", "num_envmaps"}``
    (``bat3r_core.datasets.canonical_jobs`` / ``random_pose_jobs``; the job builders are pure, the task writes
    their output). Returns ``stage, files, content_hash, n_jobs, n_shards``.
    """
    kind = config["kind"]
    if kind not in _BUILDERS:
        raise ValueError(f"config.kind must be one of {sorted(_BUILDERS)}, got {kind!r}")
    shard_size = int(config["shard_size"])
    if shard_size < 1:
        raise ValueError(f"config.shard_size must be >= 1, got {shard_size}")
    prior = from_mapping(CameraPriorConfig, config["prior"], "prior")
    jobs = _BUILDERS[kind](load_rig(asset), int(config["n"]), int(config["seed"]), dict(config["body_frame"]),
                           prior, resolution=int(config["resolution"]), num_textures=int(config["num_textures"]),
                           num_envmaps=int(config["num_envmaps"]), prefix=kind)
    files = [write_jobs(jobs[s:s + shard_size], Path(out_dir) / f"{shards.shard_name(i)}.parquet")
             for i, s in enumerate(range(0, len(jobs), shard_size))]
    return {"stage": "plan", "files": [str(f) for f in files], "content_hash": shards.content_hash(files),
            "n_jobs": len(jobs), "n_shards": len(files)}


def _views_inputs(p: Mapping[str, Any]) -> list[Path]:
    files = [Path(p["asset"])] + shard_input_files(p["fit_dir"], p["index"])
    if p.get("filter_dir"):
        files.append(shards.shard_paths(p["filter_dir"], p["index"]).parquet)
    return files


@stage_task("plan_views", inputs=_views_inputs,
            output=lambda p: Path(p["out_dir"]) / f"{shards.shard_name(p['index'])}.parquet",
            task_run_name="plan-{index}")
def plan_views_shard(asset: str, fit_dir: str, index: int, out_dir: str, config: Mapping[str, Any],
                     filter_dir: str | None = None) -> dict:
    """Render jobs for the fitted rows of fit shard ``index`` of ``fit_dir``: the estimated view and 1–2 augmented
    views per fit (``bat3r_core.fitting.augment.plan_views_for_fits``; rows that are not ok or have no camera are
    skipped), written to ``out_dir/part-<index>.parquet``. config: ``{"augment": AugmentConfig mapping,
    "body_frame": {origin, forward, horizontal}, "seed": int}``; shard ``index`` draws with seed
    ``seed * 1_000_003 + index``. filter_dir: the pseudo-label filter's shards (``tasks.filter``); when given,
    only the fits it kept are planned (``bat3r_core.pseudo_labels.read_kept``), otherwise every ok fit.
    Returns ``stage, index, files, content_hash, n_jobs, n_fits, n_kept``."""
    augment = from_mapping(AugmentConfig, config["augment"], "augment")
    rows = pq.read_table(shards.shard_paths(fit_dir, index).parquet).to_pylist()
    if filter_dir:
        from bat3r_core.pseudo_labels import read_kept

        decided = read_kept(filter_dir, index, [r["sample_id"] for r in rows])
        rows = [r if d["kept"] else {**r, "status": d["status"], "reason": d["reason"]}
                for r, d in zip(rows, decided)]
    jobs = plan_views_for_fits(load_rig(asset), rows, dict(config["body_frame"]), augment,
                               seed=_shard_seed(int(config["seed"]), index))
    path = write_jobs(jobs, Path(out_dir) / f"{shards.shard_name(index)}.parquet")
    return {"stage": "plan_views", "index": index, "files": [str(path)], "content_hash": shards.content_hash([path]),
            "n_jobs": len(jobs), "n_fits": len(rows), "n_kept": sum(r["status"] == shards.STATUS_OK for r in rows)}


def _shard_seed(seed: int, index: int) -> int:
    """One seed per (run seed, shard index) for ``plan_views_for_fits`` (which seeds row k with ``[seed, k]``)."""
    return int(seed) * 1_000_003 + int(index)
