"""Train stage: one predictor Φ_{i+1} on an iteration's training shards (resumes from its checkpoint)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable, Mapping

from bat3r_core import shards
from bat3r_core.predictor import train as training
from bat3r_core.predictor.data import MixedDataset, ShardDataset, hold_on_device, with_canonical_replay
from bat3r_core.predictor.features import make_feature_fn
from bat3r_core.specs import TrainSpec, as_spec
from tasks._cache import shard_input_files, stage_task
from tasks._devices import gpu_slot

__all__ = ["train_model", "training_inputs", "training_set"]


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
    folders = [p["shards_dir"], p.get("features_dir"), p.get("replay_dir"), p.get("replay_features_dir")]
    return [f for d in folders if d for f in training_inputs(d)] + ([Path(init)] if init else [])


def _dataset(shards_dir: str, features_dir: str | None, spec: TrainSpec) -> ShardDataset:
    source = {"features_dir": features_dir} if features_dir else {"feature_fn": make_feature_fn(spec.features)}
    return ShardDataset(shards_dir, cache_shards=spec.train.shuffle_shards, **source)


def training_set(shards_dir: str, spec: TrainSpec, device: str | None, features_dir: str | None = None,
                 replay_dir: str | None = None, replay_features_dir: str | None = None):
    """What ``train_model`` trains on: the shards of ``shards_dir``, each set held on ``device`` when it fits
    (``data.hold_on_device``), with iteration 0's canonical renders of ``replay_dir`` mixed in by the spec's
    ``train.canonical_replay`` (``data.with_canonical_replay``)."""
    train_cfg = spec.train

    def held(folder: str, features: str | None):
        return hold_on_device(_dataset(folder, features, spec), device, train_cfg.mirror_probability)

    replay = held(replay_dir, replay_features_dir) if replay_dir and train_cfg.canonical_replay > 0 else None
    return with_canonical_replay(held(shards_dir, features_dir), replay, train_cfg.canonical_replay)


@stage_task("train", inputs=_inputs, output=lambda p: Path(p["out_dir"]), spec=TrainSpec, retries=1, gpu=True)
def train_model(shards_dir: str, out_dir: str, config: TrainSpec | Mapping[str, Any],
                features_dir: str | None = None, replay_dir: str | None = None,
                replay_features_dir: str | None = None) -> dict:
    """Train the predictor on the training shards of ``shards_dir`` into ``out_dir`` (``predictor.pt``,
    ``checkpoint.pt``, ``train_log.jsonl``). A killed task resumes from ``checkpoint.pt`` on its retry or rerun.
    features_dir: the features stage's shards of ``shards_dir`` (part of the cache key), streamed as the model's
    input so no sample's features are computed again; None computes them per batch (the spec's ``features``).

    replay_dir, replay_features_dir: iteration 0's canonical renders and their features, mixed in when the spec's
    ``train.canonical_replay`` > 0 (:func:`training_set`; part of the cache key).

    config: a ``bat3r_core.specs.TrainSpec`` (or its mapping); its ``init_from``, for a warm start, is the
    ``predictor.pt`` whose weights initialise the model (part of the cache key).
    Adapted from ``bat3r_core.predictor.train.train_predictor`` (same two calls) to pass the GPU this task holds:
    ``train_predictor`` has no device argument. Returns ``stage, predictor, files, content_hash, steps,
    final_loss`` (the last logged total loss).
    """
    spec = as_spec(TrainSpec, config, "train config")
    folders = {"features_dir": features_dir, "replay_dir": replay_dir, "replay_features_dir": replay_features_dir}
    _discard_stale_checkpoint(Path(out_dir), shards.content_hash(_inputs({"shards_dir": shards_dir, "config": spec,
                                                                           **folders})))
    model_cfg, train_cfg = spec.model, spec.train
    with gpu_slot() as device:
        device = None if device is None else f"cuda:{device}"
        dataset = training_set(shards_dir, spec, device, **folders)  # the GPU's copy, when one fits
        path = training.Trainer(dataset, model_cfg, train_cfg, out_dir, device=device,
                                init_from=spec.init_from, mirror=spec.mirror,
                                progress=dashboard_progress(out_dir)).train()
    log = Path(out_dir) / "train_log.jsonl"
    lines = log.read_text().splitlines() if log.is_file() else []
    last = json.loads(lines[-1]) if lines else {}
    return {"stage": "train", "predictor": str(path), "files": [str(path)],
            "content_hash": shards.content_hash([path]), "steps": train_cfg.steps,
            "final_loss": last.get("total"), "n_samples": len(dataset),
            "n_replayed": dataset.takes[1] if isinstance(dataset, MixedDataset) else 0,
            "shards_without_features": list(getattr(dataset, "shards_without_features", []))}
