"""Predictor stages: a collection's images and masks → preprocessed collection shards (object-centred crops), and
inference of dual point maps on those shards."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Sequence

from bat3r_core import shards
from bat3r_core.predictor import collection, infer
from bat3r_core.predictor.features import make_feature_fn
from bat3r_core.runs import shard_record
from bat3r_core.specs import InferSpec, as_spec
from tasks._cache import shard_input_files, stage_task
from tasks._devices import gpu_slot

__all__ = ["ingest_collection_shard", "infer_shard"]


def _sample_files(samples: Sequence[Mapping[str, str]]) -> list[Path]:
    return [Path(s[k]) for s in samples for k in ("image_path", "mask_path") if s.get(k)]


@stage_task("collection", inputs=lambda p: _sample_files(p["samples"]), spec=collection.CollectionConfig,
            output=lambda p: Path(p["out_dir"]) / shards.shard_name(p["index"]), retries=2,
            task_run_name="collection-{index}")
def ingest_collection_shard(samples: list[dict], index: int, out_dir: str,
                            config: collection.CollectionConfig | Mapping[str, Any]) -> dict:
    """Crop and write ``samples`` (``{"sample_id", "image_path", "mask_path"}``; ``mask_path`` may be ``""``) as
    shard ``index`` of ``out_dir`` (``bat3r_core.predictor.collection.write_collection_shard``; unreadable files
    become rows with a non-ok status). config: a ``CollectionConfig`` (or its mapping). Returns the shard record."""
    cfg = as_spec(collection.CollectionConfig, config, "collection config")
    items = [collection.CollectionSample(s["sample_id"], Path(s["image_path"]),
                                         Path(s["mask_path"]) if s.get("mask_path") else None) for s in samples]
    paths = collection.write_collection_shard(items, out_dir, index, cfg)
    return shard_record("collection", index, paths)


@stage_task("infer", inputs=lambda p: [Path(p["predictor"])] + shard_input_files(p["collection_dir"], p["index"]),
            output=lambda p: Path(p["out_dir"]) / shards.shard_name(p["index"]), spec=InferSpec, retries=2,
            gpu=True, task_run_name="infer-{index}")
def infer_shard(predictor: str, collection_dir: str, index: int, out_dir: str,
                config: InferSpec | Mapping[str, Any]) -> dict:
    """Predict dual point maps for shard ``index`` of ``collection_dir`` with the checkpoint ``predictor``
    (``bat3r_core.predictor.infer.predict_shard``; the model is loaded onto the GPU this task holds).
    config: a ``bat3r_core.specs.InferSpec`` (or its mapping). Returns the shard record plus ``clouds`` (the
    ``part-NNNNN.clouds.npz`` written beside the shard)."""
    spec = as_spec(InferSpec, config, "infer config")
    with gpu_slot() as device:
        model, _ = infer.load_predictor(predictor, "cpu" if device is None else f"cuda:{device}")
        paths = infer.predict_shard(model, collection_dir, index, out_dir, make_feature_fn(spec.features),
                                    spec.batch_size)
    record = shard_record("infer", index, paths)
    record["clouds"] = str(infer.clouds_path(out_dir, index))
    return record
