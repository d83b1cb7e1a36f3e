"""Plan stage: render jobs. Iteration 0 samples cameras around the rest-pose mesh (``canonical``); the random-poses
baseline samples random poses (``random_pose``); later iterations plan the estimated and augmented views of each
fitted instance (``plan_views_shard``). Jobs are written as ``part-NNNNN.parquet`` job files, one per render
shard."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import pyarrow.parquet as pq

from bat3r_core import datasets, shards
from bat3r_core.fitting.augment import plan_views_for_fits
from bat3r_core.render.jobs import write_jobs
from bat3r_core.rig_io import load_rig
from bat3r_core.specs import PlanViewsSpec, SampledPlanSpec, as_spec
from tasks._cache import shard_input_files, stage_task

__all__ = ["plan_sampled_jobs", "plan_views_shard"]

_BUILDERS = {"canonical": datasets.canonical_jobs, "random_pose": datasets.random_pose_jobs}


@stage_task("plan", inputs=lambda p: [Path(p["asset"])], output=lambda p: Path(p["out_dir"]), spec=SampledPlanSpec)
def plan_sampled_jobs(asset: str, out_dir: str, config: SampledPlanSpec | Mapping[str, Any]) -> dict:
    """Sample render jobs around the rig of ``asset`` and write them to ``out_dir/part-NNNNN.parquet``.

    config: a ``bat3r_core.specs.SampledPlanSpec`` (or its mapping) — ``bat3r_core.datasets.canonical_jobs`` /
    ``random_pose_jobs``; the job builders are pure, the task writes their output. Returns ``stage, files,
    content_hash, n_jobs, n_shards``.
    """
    spec = as_spec(SampledPlanSpec, config, "plan config")
    shard_size = spec.shard_size
    extra = {"pose_config": spec.random_poses} if spec.kind == "random_pose" else {}
    jobs = _BUILDERS[spec.kind](load_rig(asset), spec.n, spec.seed, dict(spec.body_frame), spec.prior,
                                resolution=spec.resolution, num_textures=spec.num_textures,
                                num_envmaps=spec.num_envmaps, prefix=spec.kind, **extra)
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
            spec=PlanViewsSpec, task_run_name="plan-{index}")
def plan_views_shard(asset: str, fit_dir: str, index: int, out_dir: str, config: PlanViewsSpec | Mapping[str, Any],
                     filter_dir: str | None = None) -> dict:
    """Render jobs for the fitted rows of fit shard ``index`` of ``fit_dir``: the estimated view and 1–2 augmented
    views per fit (``bat3r_core.fitting.augment.plan_views_for_fits``; rows that are not ok or have no camera are
    skipped), written to ``out_dir/part-<index>.parquet``. config: a ``bat3r_core.specs.PlanViewsSpec`` (or its
    mapping); shard ``index`` draws with seed ``seed * 1_000_003 + index``. filter_dir: the pseudo-label
    filter's shards (``tasks.filter``); when given, only the fits it kept are planned
    (``bat3r_core.pseudo_labels.read_kept``), otherwise every ok fit.
    Returns ``stage, index, files, content_hash, n_jobs, n_fits, n_kept``."""
    spec = as_spec(PlanViewsSpec, config, "plan_views config")
    rows = pq.read_table(shards.shard_paths(fit_dir, index).parquet).to_pylist()
    if filter_dir:
        from bat3r_core.pseudo_labels import read_kept

        decided = read_kept(filter_dir, index, [r["sample_id"] for r in rows])
        rows = [r if d["kept"] else {**r, "status": d["status"], "reason": d["reason"]}
                for r, d in zip(rows, decided)]
    jobs = plan_views_for_fits(load_rig(asset), rows, dict(spec.body_frame), spec.augment,
                               seed=_shard_seed(spec.seed, index))
    path = write_jobs(jobs, Path(out_dir) / f"{shards.shard_name(index)}.parquet")
    return {"stage": "plan_views", "index": index, "files": [str(path)], "content_hash": shards.content_hash([path]),
            "n_jobs": len(jobs), "n_fits": len(rows), "n_kept": sum(r["status"] == shards.STATUS_OK for r in rows)}


def _shard_seed(seed: int, index: int) -> int:
    """One seed per (run seed, shard index) for ``plan_views_for_fits`` (which seeds row k with ``[seed, k]``)."""
    return int(seed) * 1_000_003 + int(index)
