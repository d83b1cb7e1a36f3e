"""Raw-image baseline stage: the collection's crops with pseudo-labels ray-cast from their fits (no rendering)."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from bat3r_core import raw_images, shards
from bat3r_core.rig_io import load_rig
from bat3r_core.runs import shard_record
from bat3r_core.specs import RawImagesSpec, as_spec
from tasks._cache import shard_input_files, stage_task

__all__ = ["raw_image_shard"]


@stage_task("raw_images", inputs=lambda p: [Path(p["asset"])] + shard_input_files(p["fit_dir"], p["index"])
            + shard_input_files(p["collection_dir"], p["index"]),
            output=lambda p: Path(p["out_dir"]) / shards.shard_name(p["index"]), spec=RawImagesSpec, retries=1,
            task_run_name="raw-images-{index}")
def raw_image_shard(asset: str, fit_dir: str, collection_dir: str, index: int, out_dir: str,
                    config: RawImagesSpec | Mapping[str, Any]) -> dict:
    """Training shard ``index`` of ``out_dir`` from collection shard ``index`` and fit shard ``index``
    (``bat3r_core.raw_images.raw_image_shard``). config: a ``bat3r_core.specs.RawImagesSpec`` (or its mapping).
    Returns the shard record."""
    spec = as_spec(RawImagesSpec, config, "raw_images config")
    paths = raw_images.raw_image_shard(load_rig(asset), fit_dir, collection_dir, index, out_dir, spec.layers)
    return shard_record("raw_images", index, paths)
