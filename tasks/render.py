"""Render stage: one shard of render jobs → one training shard (Blender in worker subprocesses, exact labels);
and generated image collections (any category's rig, the toy's included)."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from prefect.logging import get_run_logger

from bat3r_core import generated_collections, shards
from bat3r_core.render import runner
from bat3r_core.render.config import SceneAssets
from bat3r_core.render.jobs import read_jobs
from bat3r_core.runs import shard_record
from bat3r_core.specs import GeneratedCollectionSpec, RenderSpec, as_spec
from tasks._cache import stage_task
from tasks._devices import gpu_slot

__all__ = ["render_shard", "render_generated_collection", "asset_files"]


def asset_files(assets: SceneAssets | Mapping[str, Any]) -> list[Path]:
    """The files of a ``SceneAssets`` (or its mapping) that exist (procedural ``toy:`` textures have none)."""
    if isinstance(assets, SceneAssets):
        names = [assets.asset, *assets.textures, *assets.envmaps]
    else:
        names = [assets.get("asset", "")] + list(assets.get("textures", ())) + list(assets.get("envmaps", ()))
    return [Path(n) for n in names if n and Path(n).is_file()]


@stage_task("render", inputs=lambda p: [Path(p["jobs_file"])] + asset_files(
                as_spec(RenderSpec, p["config"], "render config").assets),
            output=lambda p: Path(p["out_dir"]) / shards.shard_name(p["index"]), spec=RenderSpec,
            retries=2, gpu=True, task_run_name="render-{index}")
def render_shard(jobs_file: str, index: int, out_dir: str, config: RenderSpec | Mapping[str, Any]) -> dict:
    """Render the jobs of ``jobs_file`` (a render-job Parquet file) as training shard ``index`` of ``out_dir``
    (``bat3r_core.render.runner.render_shard``). config: a ``bat3r_core.specs.RenderSpec`` (or its mapping). On
    a GPU machine the worker is pinned to a free device (one shard per GPU). Returns the shard record plus
    ``processes``, ``crashes`` and ``seconds``."""
    spec = as_spec(RenderSpec, config, "render config")
    cfg, assets = spec.render, spec.assets
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


def _collection_inputs(config: GeneratedCollectionSpec | Mapping[str, Any]) -> list[Path]:
    """The files a generated collection is rendered from (none for the embedded toy, which is built in code)."""
    spec = as_spec(GeneratedCollectionSpec, config, "generated_collection config")
    return asset_files({"asset": spec.asset or "", "textures": spec.textures or (), "envmaps": spec.envmaps or ()})


@stage_task("generated_collection", inputs=lambda p: _collection_inputs(p["config"]),
            output=lambda p: Path(p["out_dir"]), spec=GeneratedCollectionSpec, retries=1,
            task_run_name="generated-collection")
def render_generated_collection(out_dir: str, config: GeneratedCollectionSpec | Mapping[str, Any]) -> dict:
    """A generated image collection in ``out_dir`` (``images/``, ``masks/``) and its hidden ground truth in the
    spec's ``ground_truth_dir`` (default ``<out_dir>_ground_truth``) with
    ``bat3r_core.generated_collections.ensure_collection`` (reused when already there).

    config: a ``bat3r_core.specs.GeneratedCollectionSpec`` (or its mapping). Returns ``stage, images_dir,
    masks_dir, ground_truth_dir, n_images, reused, files, content_hash`` and the render counts of
    ``bat3r_core.generated_collections.collection_drops_record`` (``n_rows`` jobs, ``n_ok`` images kept,
    ``n_failed``, ``failed_samples``, ``status_counts``, ``status_examples``).
    """
    spec = as_spec(GeneratedCollectionSpec, config, "generated_collection config")
    col = generated_collections.ensure_collection(out_dir, spec.n, spec.seed, spec.resolution, spec.render,
                                                  ground_truth_dir=spec.ground_truth_dir,
                                                  **spec.collection_options())
    stamp = col.ground_truth_dir / "collection.json"
    counts = generated_collections.collection_drops_record(col)
    return {**{k: counts[k] for k in ("n_rows", "n_ok", "n_failed", "failed_samples", "status_counts",
                                      "status_examples")},
            "stage": "generated_collection", "images_dir": str(col.images_dir), "masks_dir": str(col.masks_dir),
            "ground_truth_dir": str(col.ground_truth_dir), "n_images": len(col.sample_ids), "reused": col.reused,
            "files": [str(stamp)], "content_hash": shards.content_hash([stamp])}
