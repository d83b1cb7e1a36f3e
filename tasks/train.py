"""Train stage: one predictor Φ_{i+1} on an iteration's training shards (resumes from its checkpoint)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable, Mapping

from bat3r_core import shards
from bat3r_core.predictor import train as training
from bat3r_core.predictor.data import ShardDataset, hold_on_device
from bat3r_core.predictor.features import make_feature_fn
from bat3r_core.specs import TrainSpec, as_spec
from tasks._cache import shard_input_files, stage_task
from tasks._devices import gpu_slot

__all__ = ["train_model", "training_inputs"]


def training_inputs(shards_dir: str) -> list[Path]:
    """Every file of the complete shards of ``shards_dir``, in shard order."""
    return [f for i in shards.list_shards(shards_dir) for f in shard_input_files(shards_dir, i)]


def _discard_stale_checkpoint(out_dir: Path, inputs_hash: str) -> None:
    """Keep ``checkpoint.pt`` only when it was written for the same training shards (a killed task resumes);
    training data that changed since (e.g. an earlier stage recomputed) starts a fresh model."""
    stamp = out_dir / "inputs.json"
    previous = json.loads(stamp.read_text()).get("inputs_hash") if stamp.is_file() else None
    if previous != inputs_hash:
        for name in ("checkpoint.pt", "predictor.pt", "train_log.jsonl"):
            (out_dir / name).unlink(missing_ok=True)
        out_dir.mkdir(parents=True, exist_ok=True)
        shards.atomic_write_text(stamp, json.dumps({"inputs_hash": inputs_hash}))


def dashboard_progress(out_dir: str) -> Callable[[dict[str, Any]], None]:
    """A ``Trainer`` progress callback for a Prefect task run: an INFO line in the task's log and a progress
    artifact (percent done, step rate, loss, ETA) updated in place on the dashboard. A failure to publish the
    artifact is logged once and never stops training."""
    from prefect.artifacts import create_progress_artifact, update_progress_artifact
    from prefect.logging import get_run_logger

    logger, state = get_run_logger(), {"id": None, "failed": False}

    def report(progress: dict[str, Any]) -> None:
        line = training.progress_line(progress)
        logger.info("training %s", line)
        if state["failed"]:
            return
        description = f"training {out_dir}: {line}"
        try:
            if state["id"] is None:
                state["id"] = create_progress_artifact(progress=100.0 * progress["fraction"], description=description)
            else:
                update_progress_artifact(state["id"], progress=100.0 * progress["fraction"], description=description)
        except Exception as e:  # noqa: BLE001 - the dashboard is not worth a failed training run
            state["failed"] = True
            logger.warning("training progress artifact not published (%s: %s); the log lines continue",
                           type(e).__name__, e)

    return report


def _inputs(p: Mapping[str, Any]) -> list[Path]:
    init = as_spec(TrainSpec, p["config"], "train config").init_from
    features = p.get("features_dir")
    return training_inputs(p["shards_dir"]) + (training_inputs(features) if features else []) + \
        ([Path(init)] if init else [])


@stage_task("train", inputs=_inputs, output=lambda p: Path(p["out_dir"]), spec=TrainSpec, retries=1, gpu=True)
def train_model(shards_dir: str, out_dir: str, config: TrainSpec | Mapping[str, Any],
                features_dir: str | None = None) -> dict:
    """Train the predictor on the training shards of ``shards_dir`` into ``out_dir`` (``predictor.pt``,
    ``checkpoint.pt``, ``train_log.jsonl``). A killed task resumes from ``checkpoint.pt`` on its retry or rerun.
    features_dir: the features stage's shards of ``shards_dir`` (part of the cache key), streamed as the model's
    input so no sample's features are computed again; None computes them per batch (the spec's ``features``).

    config: a ``bat3r_core.specs.TrainSpec`` (or its mapping); its ``init_from``, for a warm start, is the
    ``predictor.pt`` whose weights initialise the model (part of the cache key).
    Adapted from ``bat3r_core.predictor.train.train_predictor`` (same two calls) to pass the GPU this task holds:
    ``train_predictor`` has no device argument. Returns ``stage, predictor, files, content_hash, steps,
    final_loss`` (the last logged total loss).
    """
    spec = as_spec(TrainSpec, config, "train config")
    _discard_stale_checkpoint(Path(out_dir), shards.content_hash(_inputs({"shards_dir": shards_dir, "config": spec,
                                                                           "features_dir": features_dir})))
    model_cfg, train_cfg = spec.model, spec.train
    source = {"features_dir": features_dir} if features_dir else {"feature_fn": make_feature_fn(spec.features)}
    dataset = ShardDataset(shards_dir, cache_shards=train_cfg.shuffle_shards, **source)
    with gpu_slot() as device:
        device = None if device is None else f"cuda:{device}"
        held = hold_on_device(dataset, device, train_cfg.mirror_probability)  # the GPU's copy, when one fits
        path = training.Trainer(held, model_cfg, train_cfg, out_dir, device=device,
                                init_from=spec.init_from, mirror=spec.mirror,
                                progress=dashboard_progress(out_dir)).train()
    log = Path(out_dir) / "train_log.jsonl"
    lines = log.read_text().splitlines() if log.is_file() else []
    last = json.loads(lines[-1]) if lines else {}
    return {"stage": "train", "predictor": str(path), "files": [str(path)],
            "content_hash": shards.content_hash([path]), "steps": train_cfg.steps,
            "final_loss": last.get("total"), "n_samples": len(dataset),
            "shards_without_features": list(getattr(dataset, "shards_without_features", []))}
