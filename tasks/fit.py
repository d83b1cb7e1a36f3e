"""Fit stage: one inference shard → one fit shard (the rig articulated to each predicted dual point cloud)."""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Any, Mapping

from bat3r_core import shards
from bat3r_core.config_utils import from_mapping, to_mapping
from bat3r_core.fitting.config import FittingConfig
from bat3r_core.fitting.fit import FittingAsset
from bat3r_core.fitting.io import fit_prediction_shard
from bat3r_core.predictor.infer import clouds_path
from bat3r_core.rig_io import load_rig
from bat3r_core.runs import shard_record
from bat3r_core.specs import FitSpec, as_spec
from tasks._cache import shard_input_files, stage_task
from tasks._devices import gpu_slot

__all__ = ["fit_shard"]


@lru_cache(maxsize=2)
def _asset(asset: str, config_json: str, cache_dir: str | None, device: str) -> FittingAsset:
    """The prepared rig (geodesics, regulariser mesh) — shared by the fit tasks of one process."""
    import json

    config = from_mapping(FittingConfig, json.loads(config_json), "fitting")
    return FittingAsset.prepare(load_rig(asset), config, cache_dir=cache_dir, device=device)


def _inputs(p: Mapping[str, Any]) -> list[Path]:
    return [Path(p["asset"])] + shard_input_files(p["predictions_dir"], p["index"]) + \
        [clouds_path(p["predictions_dir"], p["index"])]


@stage_task("fit", inputs=_inputs, spec=FitSpec,
            output=lambda p: Path(p["out_dir"]) / shards.shard_name(p["index"]), retries=1, gpu=True,
            task_run_name="fit-{index}")
def fit_shard(asset: str, predictions_dir: str, index: int, out_dir: str, config: FitSpec | Mapping[str, Any]) -> dict:
    """Fit the rig of ``asset`` to every prediction of inference shard ``index`` of ``predictions_dir``
    (``bat3r_core.fitting.io.fit_prediction_shard``), writing fit shard ``index`` of ``out_dir``.

    config: a ``bat3r_core.specs.FitSpec`` (or its mapping); the predictions live in its crop camera.
    Returns the shard record.
    """
    import json

    spec = as_spec(FitSpec, config, "fit config")
    with gpu_slot() as device:
        dev = "cpu" if device is None else f"cuda:{device}"
        prepared = _asset(asset, json.dumps(to_mapping(spec.fitting), sort_keys=True), spec.geodesic_cache, dev)
        paths = fit_prediction_shard(prepared, predictions_dir, index, out_dir, spec.fitting, spec.camera.pinhole())
    return shard_record("fit", index, paths)
