"""Features stage: image features of one rendered (or collection) shard → one feature shard."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from bat3r_core.predictor import features
from bat3r_core.runs import shard_record
from bat3r_core.specs import as_spec
from tasks._cache import shard_input_files, stage_task

__all__ = ["extract_features_shard"]


@stage_task("features", inputs=lambda p: shard_input_files(p["input_dir"], p["index"]),
            output=lambda p: Path(p["out_dir"]) / f"part-{p['index']:05d}", spec=features.FeatureConfig, retries=2)
def extract_features_shard(input_dir: str, index: int, out_dir: str,
                           config: features.FeatureConfig | Mapping[str, Any]) -> dict:
    """Features (``bat3r_core.predictor.features.extract_feature_shard``) of shard ``index`` of ``input_dir``
    (npz ``rgb``/``mask``) into shard ``index`` of ``out_dir``. config: a ``FeatureConfig`` (or its mapping).
    For ``dinov2`` without a fitted PCA, the PCA is first fitted on all shards of ``input_dir``
    (``fit_pca_once``).
    Returns the shard record (``bat3r_core.runs.shard_record``)."""
    cfg = as_spec(features.FeatureConfig, config, "features config")
    if cfg.extractor == "dinov2":
        # the PCA is fitted once, on every shard of the stage's input folder (all rendered before the stage fans out),
        # not on whichever shard's task happens to start first: the same PCA whatever the order
        features.fit_pca_once([input_dir], cfg)
    paths = features.extract_feature_shard(input_dir, index, out_dir, cfg)
    return shard_record("features", index, paths)
