"""Predictor inputs: a collection's images and masks → preprocessed collection shards (object-centred crops)."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Sequence

from bat3r_core import shards
from bat3r_core.config_utils import from_mapping
from bat3r_core.predictor import collection
from bat3r_core.runs import shard_record
from tasks._cache import stage_task

__all__ = ["ingest_collection_shard"]


def _sample_files(samples: Sequence[Mapping[str, str]]) -> list[Path]:
    return [Path(s[k]) for s in samples for k in ("image_path", "mask_path") if s.get(k)]


@stage_task("collection", "bat3r_core.predictor.collection", inputs=lambda p: _sample_files(p["samples"]),
            output=lambda p: Path(p["out_dir"]) / shards.shard_name(p["index"]), retries=2,
            task_run_name="collection-{index}")
def ingest_collection_shard(samples: list[dict], index: int, out_dir: str, config: Mapping[str, Any]) -> dict:
    """Crop and write ``samples`` (``{"sample_id", "image_path", "mask_path"}``; ``mask_path`` may be ``""``) as
    shard ``index`` of ``out_dir`` (``bat3r_core.predictor.collection.write_collection_shard``; unreadable files
    become rows with a non-ok status). config: a ``CollectionConfig`` mapping. Returns the shard record."""
    cfg = from_mapping(collection.CollectionConfig, config, "collection")
    items = [collection.CollectionSample(s["sample_id"], Path(s["image_path"]),
                                         Path(s["mask_path"]) if s.get("mask_path") else None) for s in samples]
    paths = collection.write_collection_shard(items, out_dir, index, cfg)
    return shard_record("collection", index, paths)
