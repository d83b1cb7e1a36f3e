"""Training of the dual point map predictor: AdamW, warm-up + cosine, checkpoints, exact resume, DDP.

One *step* is one optimiser update over ``grad_accum`` micro-batches of ``batch_size`` samples per process.
The data order of epoch e is ``ShardDataset.epoch_order(seed, e)``; with W processes every micro-batch takes the
next ``W * batch_size`` samples of that order and process r uses the r-th slice of ``batch_size`` (the remainder
of an epoch that does not fill a global micro-batch is dropped). The position in the order (epoch, offset) is
part of the checkpoint, so a resumed run reads exactly the samples the uninterrupted run would have.

Files written to ``out_dir`` (only by rank 0):
- ``checkpoint.pt``: model, optimiser, scheduler, grad scaler, step, data position, RNG states and both configs
  as plain dicts; rewritten atomically (temporary file + rename) every ``checkpoint_every`` steps and at the end.
- ``predictor.pt``: the trained model and configs only (what ``infer.load_predictor`` needs), at the end.
- ``train_log.jsonl``: one JSON object per ``log_every`` steps (steps after the last checkpoint of a killed run
  are logged again when the run resumes).

A new ``Trainer`` on an ``out_dir`` holding ``checkpoint.pt`` resumes from it. Distributed training uses the
``torchrun`` environment (``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``, ``MASTER_ADDR``, ``MASTER_PORT``): NCCL with
one GPU per process, gloo on CPU.
"""
from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import random
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel

from bat3r_core.config_utils import to_mapping
from bat3r_core.predictor.checkpoints import CHECKPOINT_FORMAT, read_state
from bat3r_core.predictor.config import ModelConfig, TrainConfig
from bat3r_core.predictor.data import FeatureFn, ShardDataset, TrainingBatch, TrainingTargets, hold_on_device
from bat3r_core.predictor.mirror import CanonicalMirror, mirror_decisions, mirror_samples
from bat3r_core.predictor.loss import dual_pointmap_loss, huber_delta
from bat3r_core.predictor.network import DualPointMapNet
from bat3r_core.shards import atomic_write
from bat3r_core.stopping import raise_if_stop_requested, stop_requested

CHECKPOINT_NAME = "checkpoint.pt"
PREDICTOR_NAME = "predictor.pt"
PROGRESS_INTERVAL_S = 30.0
"""Seconds between two progress reports of :class:`Trainer` (step rate, loss, ETA), whatever the step rate."""

_logger = logging.getLogger(__name__)


def progress_line(progress: dict[str, Any]) -> str:
    """``"step 1200/5000 (24%), 9.4 steps/s, loss -2.18, ETA 6.7 min"`` for a :class:`Trainer` progress report."""
    eta = progress["eta_s"]
    eta_text = f"{eta / 60:.1f} min" if eta >= 60 else f"{eta:.0f} s"
    return (f"step {progress['step']}/{progress['steps']} ({progress['fraction']:.0%}), "
            f"{progress['steps_per_s']:.1f} steps/s, loss {progress['loss']:.3g}, ETA {eta_text}")


def _log_progress(progress: dict[str, Any]) -> None:
    _logger.info("training %s", progress_line(progress))


class WarmupCosine:
    """LR factor: linear from 1/(warmup+1) up to 1 over ``warmup`` steps, then cosine down to 0 at ``total``.

    A callable object (not a lambda) so ``LambdaLR.state_dict`` stores it as plain data."""

    def __init__(self, warmup: int, total: int) -> None:
        self.warmup = int(warmup)
        self.total = int(total)

    def __call__(self, step: int) -> float:
        if step < self.warmup:
            return (step + 1) / (self.warmup + 1)
        span = max(self.total - self.warmup, 1)
        t = min((step - self.warmup) / span, 1.0)
        return 0.5 * (1.0 + math.cos(math.pi * t))


def _dist_env() -> tuple[int, int, int]:
    """(rank, world_size, local_rank) from the torchrun environment; (0, 1, 0) without it."""
    return (int(os.environ.get("RANK", "0")), int(os.environ.get("WORLD_SIZE", "1")),
            int(os.environ.get("LOCAL_RANK", "0")))


def _torch_save_atomic(obj: Any, path: Path) -> None:
    """``torch.save`` to ``path`` atomically, with bytes that depend on ``obj`` only. Saved to a path, torch names
    the archive's root folder after the file, here a random temporary name: the same weights would hash differently
    on every save, and a train stage that re-exports a finished model (its cache invalidated by a code change) would
    invalidate every stage downstream and retrain the next iteration from scratch. Through a file object the root
    is always ``archive``."""
    def write(tmp: str) -> None:
        with open(tmp, "wb") as f:
            torch.save(obj, f)

    atomic_write(path, write)


def _rng_state() -> dict[str, Any]:
    np_state = np.random.get_state()
    py_state = random.getstate()
    return {"torch": torch.get_rng_state(),
            "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
            "numpy_keys": torch.from_numpy(np_state[1].astype(np.int64)),
            "numpy_rest": [int(np_state[2]), int(np_state[3]), float(np_state[4])],
            "python": [py_state[0], list(py_state[1]), py_state[2]]}


def _set_rng_state(state: dict[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    if torch.cuda.is_available() and state["cuda"]:
        torch.cuda.set_rng_state_all(state["cuda"])
    pos, has_gauss, cached = state["numpy_rest"]
    np.random.set_state(("MT19937", state["numpy_keys"].numpy().astype(np.uint32), int(pos), int(has_gauss),
                         float(cached)))
    random.setstate((state["python"][0], tuple(state["python"][1]), state["python"][2]))


def seed_everything(seed: int) -> None:
    """Seed python, numpy and torch (CPU and CUDA) RNGs."""
    random.seed(seed)
    np.random.seed(seed % (2 ** 32))
    torch.manual_seed(seed)


class Trainer:
    """Trains a ``DualPointMapNet`` on a ``ShardDataset``; resumes from ``out_dir/checkpoint.pt`` if present.

    Args:
        dataset: training samples; its resolution, layers and feature channels must match ``model_config``.
        out_dir: where checkpoints, the final predictor and the log go.
        device: ``None`` picks ``cuda:LOCAL_RANK`` when CUDA is available, else CPU.
        init_from: a ``predictor.pt`` (or training ``checkpoint.pt``) whose weights initialise the model (warm
            start; optimiser, schedule and data order start fresh). Its model config must equal
            ``model_config``. Ignored when ``out_dir`` holds a checkpoint to resume (that run started from it).
        mirror: the rig's sagittal plane (``predictor.mirror.canonical_mirror_for_rig``); required when
            ``train_config.mirror_probability > 0``, which mirrors that fraction of the samples.
        progress: called on rank 0 every ``progress_interval_s`` seconds of training and after the last step
            with ``{"step", "steps", "fraction", "steps_per_s", "loss", "eta_s"}`` (rate over this call's steps;
            ``loss``: the last step's total); default: an INFO line on this module's logger
            (:func:`progress_line`). ``None`` reports nothing.
    """

    def __init__(self, dataset: ShardDataset, model_config: ModelConfig, train_config: TrainConfig,
                 out_dir: str | os.PathLike, device: str | torch.device | None = None,
                 init_from: str | os.PathLike | None = None, mirror: CanonicalMirror | None = None,
                 progress: Callable[[dict[str, Any]], None] | None = _log_progress,
                 progress_interval_s: float = PROGRESS_INTERVAL_S) -> None:
        self.progress, self.progress_interval_s = progress, float(progress_interval_s)
        if not isinstance(model_config, ModelConfig):
            raise TypeError(f"model_config: expected ModelConfig, got {type(model_config).__name__}")
        if not isinstance(train_config, TrainConfig):
            raise TypeError(f"train_config: expected TrainConfig, got {type(train_config).__name__}")
        got = (dataset.height, dataset.width, dataset.layers, dataset.channels)
        want = (model_config.resolution, model_config.resolution, model_config.layers, model_config.in_channels)
        if got != want:
            raise ValueError(f"dataset: expected (H, W, K, C) = {want} from the model config, got {got}")
        if train_config.mirror_probability > 0 and mirror is None:
            raise ValueError(f"mirror: train_config.mirror_probability = {train_config.mirror_probability} needs the "
                             "rig's sagittal plane (predictor.mirror.canonical_mirror_for_rig), got None")
        self.dataset, self.model_config, self.config, self.mirror = dataset, model_config, train_config, mirror
        self.out_dir = Path(out_dir)
        self.rank, self.world_size, local_rank = _dist_env()
        if device is None:
            device = f"cuda:{local_rank}" if torch.cuda.is_available() else "cpu"
        self.device = torch.device(device)
        if self.world_size > 1 and not dist.is_initialized():
            if self.device.type == "cuda":
                torch.cuda.set_device(self.device)
            dist.init_process_group("nccl" if self.device.type == "cuda" else "gloo",
                                    rank=self.rank, world_size=self.world_size)
        if len(dataset) < train_config.batch_size * self.world_size:
            raise ValueError(f"dataset: expected at least batch_size * world_size = "
                             f"{train_config.batch_size * self.world_size} samples, got {len(dataset)}")
        seed_everything(train_config.seed)
        self.model = DualPointMapNet(model_config).to(self.device)
        self.ddp = (DistributedDataParallel(self.model, device_ids=[self.device.index] if self.device.type == "cuda"
                                            else None) if self.world_size > 1 else None)
        self.optimizer = torch.optim.AdamW(self.model.parameters(), lr=train_config.lr,
                                           betas=tuple(train_config.betas), weight_decay=train_config.weight_decay)
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(
            self.optimizer, WarmupCosine(train_config.warmup_steps, train_config.steps))
        cuda = self.device.type == "cuda"
        self.amp_dtype = ({"bfloat16": torch.bfloat16, "float16": torch.float16}.get(train_config.amp_dtype)
                          if cuda else None)
        self.scaler = torch.amp.GradScaler("cuda", enabled=cuda and self.amp_dtype is torch.float16)
        self.step = 0
        self.epoch = 0
        self.position = 0
        self._order: tuple[int, np.ndarray] | None = None
        if (self.out_dir / CHECKPOINT_NAME).is_file():
            self.load_checkpoint(self.out_dir / CHECKPOINT_NAME)
        elif init_from is not None:
            self.load_weights(init_from)

    # ----------------------------------------------------------------------------------------------- data order
    def _next_indices(self) -> np.ndarray:
        b, w = self.config.batch_size, self.world_size
        if self.position + b * w > len(self.dataset):
            self.epoch += 1
            self.position = 0
        if self._order is None or self._order[0] != self.epoch:
            self._order = (self.epoch, self.dataset.epoch_order(self.config.seed, self.epoch,
                                                                self.config.shuffle_shards))
        start = self.position + self.rank * b
        self.position += b * w
        return self._order[1][start:start + b]

    # ------------------------------------------------------------------------------------------------- training
    def train(self, until_step: int | None = None) -> Path:
        """Run optimiser steps until ``until_step`` (default: ``config.steps``); returns the path of
        ``predictor.pt`` once the last step is done, else of ``checkpoint.pt`` (possibly not yet written)."""
        cfg = self.config
        target = cfg.steps if until_step is None else min(int(until_step), cfg.steps)
        previous = torch.are_deterministic_algorithms_enabled()
        torch.use_deterministic_algorithms(previous or cfg.deterministic)
        try:
            return self._train(target)
        finally:
            torch.use_deterministic_algorithms(previous)

    def _train(self, target: int) -> Path:
        cfg = self.config
        module = self.ddp if self.ddp is not None else self.model
        self.model.train()
        t0 = time.perf_counter()
        first_step, last_report = self.step, t0
        while self.step < target:
            if self.world_size == 1 and stop_requested():  # (DDP ranks are processes of their own: no request)
                self.save_checkpoint()
                raise_if_stop_requested(f"training in {self.out_dir} at step {self.step} of {cfg.steps} "
                                        "(checkpoint.pt written: a rerun resumes from this step)")
            delta = (huber_delta(self.step, cfg.steps, cfg.huber_delta_start, cfg.huber_delta_end)
                     if cfg.loss == "robust" else None)
            self.optimizer.zero_grad(set_to_none=True)
            sums: dict[str, float] = {}
            for micro in range(cfg.grad_accum):
                batch = self._mirrored(self.dataset.get_batch(self._next_indices()), micro)
                sync = self.ddp is None or micro == cfg.grad_accum - 1
                with (contextlib.nullcontext() if sync else self.ddp.no_sync()):
                    with torch.autocast(self.device.type, dtype=self.amp_dtype, enabled=self.amp_dtype is not None):
                        pred = module(batch.features.to(self.device), batch.mask.to(self.device))
                    t = batch.targets
                    terms = dual_pointmap_loss(pred, t.canonical_points.to(self.device),
                                               t.posed_points.to(self.device), t.occupancy.to(self.device),
                                               kind=cfg.loss, delta=delta, occupancy_weight=cfg.occupancy_weight)
                    self.scaler.scale(terms.total / cfg.grad_accum).backward()
                for name in ("total", "canonical", "posed", "occupancy"):
                    sums[name] = sums.get(name, 0.0) + float(getattr(terms, name).detach()) / cfg.grad_accum
            if cfg.grad_clip > 0:
                self.scaler.unscale_(self.optimizer)
                sums["grad_norm"] = float(torch.nn.utils.clip_grad_norm_(self.model.parameters(), cfg.grad_clip))
            self.scaler.step(self.optimizer)
            self.scaler.update()
            self.scheduler.step()
            self.step += 1
            if self.rank == 0 and (self.step % cfg.log_every == 0 or self.step == cfg.steps):
                self._log({"step": self.step, "lr": self.scheduler.get_last_lr()[0], "huber_delta": delta,
                           "seconds": time.perf_counter() - t0, **sums})
            now = time.perf_counter()
            if self.rank == 0 and self.progress is not None and (
                    now - last_report >= self.progress_interval_s or self.step == target):
                rate = (self.step - first_step) / max(now - t0, 1e-9)
                self.progress({"step": self.step, "steps": cfg.steps, "fraction": self.step / cfg.steps,
                               "steps_per_s": rate, "loss": sums["total"], "eta_s": (cfg.steps - self.step) / rate})
                last_report = now
            if self.step % cfg.checkpoint_every == 0 or self.step == cfg.steps:
                self.save_checkpoint()
        if self.step >= cfg.steps:
            if self.rank == 0:
                _torch_save_atomic(self._predictor_state(), self.out_dir / PREDICTOR_NAME)
            self._barrier()
            return self.out_dir / PREDICTOR_NAME
        return self.out_dir / CHECKPOINT_NAME

    def _mirrored(self, batch: TrainingBatch, micro: int) -> TrainingBatch:
        """``batch`` with the samples ``mirror_decisions`` picks for this step, micro-batch and rank mirrored."""
        p = self.config.mirror_probability
        if p <= 0:
            return batch
        which = mirror_decisions(self.config.seed, self.step, micro * self.world_size + self.rank,
                                 len(batch.features), p)
        t = batch.targets
        f, m, q, pp, occ = mirror_samples(batch.features, batch.mask, t.canonical_points, t.posed_points, t.occupancy,
                                          which, self.mirror)
        return TrainingBatch(f, m, TrainingTargets(q, pp, occ))

    def _log(self, record: dict[str, Any]) -> None:
        self.out_dir.mkdir(parents=True, exist_ok=True)
        with open(self.out_dir / "train_log.jsonl", "a") as f:
            f.write(json.dumps(record) + "\n")

    def _barrier(self) -> None:
        if self.world_size > 1 and dist.is_initialized():
            dist.barrier()

    # ---------------------------------------------------------------------------------------------- checkpoints
    def _predictor_state(self) -> dict[str, Any]:
        return {"format": CHECKPOINT_FORMAT, "model_config": to_mapping(self.model_config),
                "train_config": to_mapping(self.config), "model": self.model.state_dict(), "step": self.step}

    def save_checkpoint(self) -> Path:
        """Write ``checkpoint.pt`` atomically (rank 0 only; every rank waits for it)."""
        path = self.out_dir / CHECKPOINT_NAME
        if self.rank == 0:
            state = self._predictor_state()
            state.update({"optimizer": self.optimizer.state_dict(), "scheduler": self.scheduler.state_dict(),
                          "scaler": self.scaler.state_dict(), "epoch": self.epoch, "position": self.position,
                          "world_size": self.world_size, "n_samples": len(self.dataset), "rng": _rng_state()})
            _torch_save_atomic(state, path)
        self._barrier()
        return path

    def load_weights(self, path: str | os.PathLike) -> None:
        """Initialise the model with the weights of a predictor or checkpoint file (warm start)."""
        state = read_state(path, "init_from")
        if state["model_config"] != to_mapping(self.model_config):
            raise ValueError(f"init_from: {path} has model_config {state['model_config']}, this run needs "
                             f"{to_mapping(self.model_config)}")
        self.model.load_state_dict(state["model"])

    def load_checkpoint(self, path: str | os.PathLike) -> None:
        """Restore everything ``save_checkpoint`` wrote; the configs must match this trainer's."""
        state = read_state(path, "checkpoint")
        if "optimizer" not in state:
            raise ValueError(f"checkpoint: {path} is a predictor without optimiser state, not a training checkpoint")
        for name, mine in (("model_config", self.model_config), ("train_config", self.config)):
            if state[name] != to_mapping(mine):
                raise ValueError(f"checkpoint {path}: {name} differs from this run's: {state[name]} vs "
                                 f"{to_mapping(mine)}")
        if state["n_samples"] != len(self.dataset) or state["world_size"] != self.world_size:
            raise ValueError(f"checkpoint {path}: written for {state['n_samples']} samples on "
                             f"{state['world_size']} processes, resuming with {len(self.dataset)} on "
                             f"{self.world_size}")
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        self.scaler.load_state_dict(state["scaler"])
        self.step, self.epoch, self.position = int(state["step"]), int(state["epoch"]), int(state["position"])
        self._order = None
        _set_rng_state(state["rng"])


def train_predictor(shards_dir: str | os.PathLike, out_dir: str | os.PathLike, model_cfg: ModelConfig,
                    train_cfg: TrainConfig, feature_fn: FeatureFn | None = None,
                    init_from: str | os.PathLike | None = None, mirror: CanonicalMirror | None = None) -> Path:
    """Train (or resume training) on the training shards of ``shards_dir``; returns ``out_dir/predictor.pt``.
    ``init_from``: warm-start weights; ``mirror``: the rig's sagittal plane (see :class:`Trainer`)."""
    dataset = hold_on_device(ShardDataset(shards_dir, feature_fn, cache_shards=train_cfg.shuffle_shards), None,
                             train_cfg.mirror_probability)
    return Trainer(dataset, model_cfg, train_cfg, out_dir, init_from=init_from, mirror=mirror).train()
