"""Predictor throughput on CPU: training steps per second (tiny and demo presets) and inference images per second
(demo preset), on synthetic two-sphere samples at each preset's resolution.

A training step is one optimiser update of the preset (batch_size x grad_accum samples: forward, DualPM loss,
backward, AdamW), including reading the batch from a cached shard and computing the rgb features; the first steps
are warm-up and not timed. Inference is ``predict_maps`` (no gradients) in batches of 16.

Writes benchmarks/results/predictor.json (keys ``train_steps_per_s_tiny``, ``train_steps_per_s_demo``,
``infer_images_per_s_demo`` plus the samples per second behind them) and refreshes benchmarks/RESULTS.md.
"""
from __future__ import annotations

import dataclasses
import os
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _results import record  # noqa: E402

from bat3r_core.catalog import load_catalog  # noqa: E402
from bat3r_core.predictor.data import ShardDataset  # noqa: E402
from bat3r_core.predictor.infer import predict_maps  # noqa: E402
from bat3r_core.predictor.network import count_parameters  # noqa: E402
from bat3r_core.predictor.synthetic import write_synthetic_shards  # noqa: E402
from bat3r_core.predictor.train import Trainer  # noqa: E402

WARMUP_STEPS, TIMED_STEPS, INFER_IMAGES = 2, 8, 64


def preset_configs(name: str):
    """(ModelConfig, TrainConfig) of the data catalog's run preset ``name``."""
    catalog = load_catalog()
    return catalog.model_config(name), catalog.train_config(name)


def _train_rate(preset: str, root: Path) -> tuple[float, float, int]:
    model_cfg, train_cfg = preset_configs(preset)
    train_cfg = dataclasses.replace(train_cfg, steps=WARMUP_STEPS + TIMED_STEPS, checkpoint_every=10 ** 6,
                                    log_every=10 ** 6)
    shards = root / f"shards-{preset}"
    write_synthetic_shards(shards, 32, model_cfg.resolution, model_cfg.layers, shard_size=32)
    trainer = Trainer(ShardDataset(shards), model_cfg, train_cfg, root / f"out-{preset}", device="cpu")
    trainer.train(until_step=WARMUP_STEPS)
    t0 = time.perf_counter()
    trainer.train(until_step=WARMUP_STEPS + TIMED_STEPS)
    steps_per_s = TIMED_STEPS / (time.perf_counter() - t0)
    return steps_per_s, steps_per_s * train_cfg.batch_size * train_cfg.grad_accum, count_parameters(trainer.model)


def _infer_rate(preset: str, root: Path) -> float:
    model_cfg, train_cfg = preset_configs(preset)
    shards = root / f"shards-{preset}"
    ds = ShardDataset(shards)
    trainer = Trainer(ds, model_cfg, dataclasses.replace(train_cfg, steps=1), root / f"infer-{preset}", device="cpu")
    batch = ds.get_batch(list(range(len(ds))) * (INFER_IMAGES // len(ds)))
    predict_maps(trainer.model, batch.features[:16], batch.mask[:16])  # warm-up
    t0 = time.perf_counter()
    predict_maps(trainer.model, batch.features, batch.mask, batch_size=16)
    return len(batch.mask) / (time.perf_counter() - t0)


def main() -> dict:
    figures: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for preset in ("tiny", "demo"):
            steps, samples, params = _train_rate(preset, root)
            figures[f"train_steps_per_s_{preset}"] = round(steps, 3)
            figures[f"train_samples_per_s_{preset}"] = round(samples, 2)
            figures[f"parameters_{preset}"] = params
        figures["infer_images_per_s_demo"] = round(_infer_rate("demo", root), 2)
    shapes = []
    for preset in ("tiny", "demo"):
        m = preset_configs(preset)[0]
        shapes.append(f"{preset} {m.resolution}x{m.resolution} K={m.layers} {m.in_channels}-channel features, "
                      f"{'two-stage' if m.two_stage else 'one-stage'} UNet depth {m.depth} width {m.base_channels}")
    notes = (f"CPU, float32, torch {torch.__version__}, {torch.get_num_threads()} threads; synthetic samples at "
             f"each preset's resolution ({'; '.join(shapes)}); "
             f"1-minute load average at the end {os.getloadavg()[0]:.1f} (other jobs share the cores).")
    record("predictor", figures, notes)
    for k, v in figures.items():
        print(f"{k}: {v}")
    return figures


if __name__ == "__main__":
    main()
