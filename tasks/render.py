"""Render stage: one shard of render jobs → one training shard (Blender in worker subprocesses, exact labels);
and generated image collections (any category's rig, the toy's included)."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from prefect.logging import get_run_logger

from bat3r_core import generated_collections, shards
from bat3r_core.config_utils import from_mapping
from bat3r_core.render import runner
from bat3r_core.render.config import RenderConfig, SceneAssets
from bat3r_core.render.jobs import read_jobs
from bat3r_core.runs import shard_record
from tasks._cache import stage_task
from tasks._devices import gpu_slot

__all__ = ["render_shard", "render_generated_collection", "asset_files"]


def asset_files(assets: Mapping[str, Any]) -> list[Path]:
    """The files of a ``SceneAssets`` mapping that exist (procedural ``toy:`` textures have none)."""
    names = [assets.get("asset", "")] + list(assets.get("textures", ())) + list(assets.get("envmaps", ()))
    return [Path(n) for n in names if n and Path(n).is_file()]


@stage_task("render", inputs=lambda p: [Path(p["jobs_file"])] + asset_files(p["config"]["assets"]),
            output=lambda p: Path(p["out_dir"]) / shards.shard_name(p["index"]),
            retries=2, gpu=True, task_run_name="render-{index}")
def render_shard(jobs_file: str, index: int, out_dir: str, config: Mapping[str, Any]) -> dict:
    """Render the jobs of ``jobs_file`` (a render-job Parquet file) as training shard ``index`` of ``out_dir``
    (``bat3r_core.render.runner.render_shard``). config: ``{"render": RenderConfig mapping, "assets":
    SceneAssets mapping}``. On a GPU machine the worker is pinned to a free device (one shard per GPU).
    Returns the shard record plus ``processes``, ``crashes`` and ``seconds``."""
    cfg = from_mapping(RenderConfig, config["render"], "render")
    assets = from_mapping(SceneAssets, config["assets"], "assets")
    jobs = read_jobs(jobs_file)
    logger = get_run_logger()

    def progress(p: Mapping[str, Any]) -> None:  # long shards show they advance in the task's log
        logger.info("rendered %d/%d images (%.1f images/s)", p["done"], p["total"], p["images_per_s"])

    with gpu_slot() as device:
        result = runner.render_shard(jobs, assets, out_dir, index, cfg,
                                     gpu_index=device if cfg.device != "CPU" else None, progress=progress)
    record = shard_record("render", index, shards.shard_paths(out_dir, index))
    record.update(processes=result.processes, crashes=result.crashes, seconds=round(result.seconds, 3))
    return record


def _collection_inputs(config: Mapping[str, Any]) -> list[Path]:
    """The files a generated collection is rendered from (none for the embedded toy, which is built in code)."""
    return asset_files({"asset": config.get("asset") or "", "textures": config.get("textures") or (),
                        "envmaps": config.get("envmaps") or ()})


@stage_task("generated_collection", inputs=lambda p: _collection_inputs(p["config"]),
            output=lambda p: Path(p["out_dir"]), retries=1, task_run_name="generated-collection")
def render_generated_collection(out_dir: str, config: Mapping[str, Any]) -> dict:
    """A generated image collection in ``out_dir`` (``images/``, ``masks/``) and its hidden ground truth in
    ``config["ground_truth_dir"]`` (default ``<out_dir>_ground_truth``) with
    ``bat3r_core.generated_collections.ensure_collection`` (reused when already there).

    config: ``{"n", "seed", "resolution", "render": RenderConfig mapping, "ground_truth_dir": path or None}`` plus,
    for any rig but the embedded toy, ``"asset"`` (the rigged GLB), ``"body_frame"``, ``"textures"`` (``[]``: the
    asset's own texture), ``"envmaps"``, ``"prefix"``; and ``"pose_sampler"`` (``random`` / ``toy_natural``).
    Returns ``stage, images_dir, masks_dir, ground_truth_dir, n_images, reused, files, content_hash`` and the
    render counts of ``bat3r_core.generated_collections.collection_drops_record`` (``n_rows`` jobs, ``n_ok`` images
    kept, ``n_failed``, ``failed_samples``, ``status_counts``, ``status_examples``).
    """
    cfg = from_mapping(RenderConfig, config["render"], "render")
    extra = {k: config[k] for k in ("asset", "body_frame", "envmaps", "pose_sampler", "prefix")
             if config.get(k) is not None}
    if config.get("textures") is not None:
        extra["textures"] = tuple(config["textures"])
    if "envmaps" in extra:
        extra["envmaps"] = tuple(extra["envmaps"])
    col = generated_collections.ensure_collection(out_dir, int(config["n"]), int(config["seed"]),
                                                  int(config["resolution"]), cfg,
                                                  ground_truth_dir=config.get("ground_truth_dir"), **extra)
    stamp = col.ground_truth_dir / "collection.json"
    counts = generated_collections.collection_drops_record(col)
    return {**{k: counts[k] for k in ("n_rows", "n_ok", "n_failed", "failed_samples", "status_counts",
                                      "status_examples")},
            "stage": "generated_collection", "images_dir": str(col.images_dir), "masks_dir": str(col.masks_dir),
            "ground_truth_dir": str(col.ground_truth_dir), "n_images": len(col.sample_ids), "reused": col.reused,
            "files": [str(stamp)], "content_hash": shards.content_hash([stamp])}
