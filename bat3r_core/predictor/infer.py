"""Inference of the dual point map predictor: load a checkpoint, predict maps, write shards and point clouds.

Posed points are predicted relative to the (unknown) object depth: the camera-frame ``P - (0, 0, object_depth)``
of ``docs/CONVENTIONS.md``. Inference outputs them as they are (z offset 0); the fitting stage recovers the camera
translation (and with it the depth) from layer-0 pixel <-> posed-point correspondences.

Output of ``predict_collection`` for input shard ``part-NNNNN`` of a collection folder:
- ``part-NNNNN.npz``: per row (first axis in Parquet row order; zeros for rows that were not predicted)
  ``canonical_points (N, H, W, K, 3) float16``, ``posed_points (N, H, W, K, 3) float16`` (relative),
  ``occupancy (N, H, W, K) float16`` probabilities (0 outside the input mask), ``canonical_confidence`` and
  ``posed_confidence (N, H, W, K) float16`` (``C = 1 + exp(c)``, clipped to 60000), ``mask (N, H, W) bool``.
- ``part-NNNNN.clouds.npz``: the dual point clouds after the reference filters (see ``DualClouds``).
- ``part-NNNNN.parquet``: one row per input row: ``sample_id``, ``status``, ``reason``, ``n_points``,
  ``mask_pixels``, ``mean_canonical_confidence``, ``mean_posed_confidence``. Written last (shard complete).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from bat3r_core.pointmaps import dual_point_cloud
from bat3r_core.predictor.config import ModelConfig, TrainConfig
from bat3r_core.predictor.data import FeatureFn, rgb_features
from bat3r_core.predictor.network import DualPointMapNet
from bat3r_core.predictor.checkpoints import load_configs, read_state
from bat3r_core.shards import STATUS_OK, ShardPaths, atomic_write, list_shards, read_shard, shard_paths, write_shard

#: Reference inference filters.
MIN_OCCUPANCY = 0.5
MIN_CONFIDENCE = 2.0
_FLOAT16_CONFIDENCE_MAX = 6.0e4


class PredictorConfigs(NamedTuple):
    model: ModelConfig
    train: TrainConfig


def load_predictor(ckpt: str | os.PathLike, device: str | torch.device | None = None
                   ) -> tuple[DualPointMapNet, PredictorConfigs]:
    """Load ``predictor.pt`` (or a training ``checkpoint.pt``) -> (model in eval mode on ``device``, configs).

    ``device=None`` picks CUDA when available, else CPU."""
    state = read_state(ckpt, "ckpt")
    model_cfg, train_cfg = load_configs(state)
    model = DualPointMapNet(model_cfg)
    model.load_state_dict(state["model"])
    device = torch.device(device if device is not None else ("cuda" if torch.cuda.is_available() else "cpu"))
    return model.to(device).eval(), PredictorConfigs(model_cfg, train_cfg)


@dataclass(frozen=True, eq=False)
class PredictedMaps:
    """Predicted dual point maps of N images (numpy, float32).

    canonical_points: (N, H, W, K, 3) metres, canonical frame.
    posed_points: (N, H, W, K, 3) metres, camera frame relative to the unknown object depth (z offset 0).
    occupancy: (N, H, W, K) probabilities, 0 outside the input mask.
    canonical_confidence, posed_confidence: (N, H, W, K) ``C = 1 + exp(c)`` >= 1.
    """

    canonical_points: np.ndarray
    posed_points: np.ndarray
    occupancy: np.ndarray
    canonical_confidence: np.ndarray
    posed_confidence: np.ndarray


def predict_maps(model: DualPointMapNet, features: np.ndarray | torch.Tensor, mask: np.ndarray | torch.Tensor,
                 batch_size: int = 16) -> PredictedMaps:
    """Run the network on features (N, C, H, W) float and mask (N, H, W) bool, ``batch_size`` images at a time,
    on the model's device, without gradients."""
    features = torch.as_tensor(np.asarray(features, dtype=np.float32) if isinstance(features, np.ndarray)
                               else features).float()
    mask = torch.as_tensor(np.asarray(mask) if isinstance(mask, np.ndarray) else mask).bool()
    if features.ndim != 4 or mask.shape != (features.shape[0], *features.shape[2:]):
        raise ValueError(f"features/mask: expected (N, C, H, W) and (N, H, W), got {tuple(features.shape)} and "
                         f"{tuple(mask.shape)}")
    if batch_size < 1:
        raise ValueError(f"batch_size: expected >= 1, got {batch_size}")
    device = next(model.parameters()).device
    was_training = model.training
    model.eval()
    parts: list[list[np.ndarray]] = [[] for _ in range(5)]
    with torch.no_grad():
        for s in range(0, features.shape[0], batch_size):
            m = mask[s:s + batch_size].to(device)
            out = model(features[s:s + batch_size].to(device), m)
            occ = torch.sigmoid(out.occupancy_logits.float()) * m[..., None].float()
            values = (out.canonical_points.float(), out.posed_points.float(), occ,
                      1.0 + torch.exp(out.canonical_confidence_logits.float()),
                      1.0 + torch.exp(out.posed_confidence_logits.float()))
            for lst, v in zip(parts, values):
                lst.append(v.cpu().numpy())
    model.train(was_training)
    return PredictedMaps(*(np.concatenate(p) for p in parts))


@dataclass(frozen=True, eq=False)
class DualClouds:
    """Filtered dual point clouds of N instances, concatenated; instance i owns rows ``offsets[i]:offsets[i+1]``.

    offsets: (N + 1,) int64, ``offsets[0] = 0``, ``offsets[-1] = M``.
    posed_points: (M, 3) float32 metres, camera frame relative to the object depth.
    canonical_points: (M, 3) float32 metres, canonical frame.
    canonical_confidence, posed_confidence: (M,) float32, ``C = 1 + exp(c)``.
    pixels: (M, 2) float32 pixel centres (u, v) in the model's crop (relate them to the original image with the
        collection's crop transform).
    layers: (M,) int8 layer index, 0 = front (visible).
    Rows of one instance are in (row, column, layer) order.
    """

    offsets: np.ndarray
    posed_points: np.ndarray
    canonical_points: np.ndarray
    canonical_confidence: np.ndarray
    posed_confidence: np.ndarray
    pixels: np.ndarray
    layers: np.ndarray

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def instance(self, i: int) -> dict[str, np.ndarray]:
        """The arrays of instance ``i`` (views, no copy)."""
        if not 0 <= i < len(self):
            raise IndexError(f"i: expected 0 <= i < {len(self)}, got {i}")
        s, e = int(self.offsets[i]), int(self.offsets[i + 1])
        return {k: getattr(self, k)[s:e] for k in _CLOUD_KEYS}


_CLOUD_KEYS = ("posed_points", "canonical_points", "canonical_confidence", "posed_confidence", "pixels", "layers")


def maps_to_clouds(maps: PredictedMaps, min_occupancy: float = MIN_OCCUPANCY,
                   min_confidence: float = MIN_CONFIDENCE) -> DualClouds:
    """Reference filters: keep (pixel, layer) entries with occupancy > ``min_occupancy`` and both confidences
    ``C_Q, C_P >= min_confidence`` (uses ``pointmaps.dual_point_cloud`` per image)."""
    clouds, offsets = [], [0]
    for i in range(maps.occupancy.shape[0]):
        c_min = np.minimum(maps.canonical_confidence[i], maps.posed_confidence[i]).astype(np.float64)
        # dual_point_cloud takes the logit c of C = 1 + exp(c); both are monotone, so filtering min(C) is exact
        logit = np.log(np.maximum(c_min - 1.0, 1e-30))
        cloud = dual_point_cloud(maps.posed_points[i], maps.canonical_points[i], maps.occupancy[i], logit,
                                 min_occupancy=min_occupancy, min_confidence=min_confidence)
        rows = (cloud.pixels[:, 1] - 0.5).astype(np.int64)
        cols = (cloud.pixels[:, 0] - 0.5).astype(np.int64)
        clouds.append({"posed_points": cloud.posed_points, "canonical_points": cloud.canonical_points,
                       "canonical_confidence": maps.canonical_confidence[i][rows, cols, cloud.layers],
                       "posed_confidence": maps.posed_confidence[i][rows, cols, cloud.layers],
                       "pixels": cloud.pixels, "layers": cloud.layers.astype(np.int8)})
        offsets.append(offsets[-1] + len(cloud.layers))
    dtypes = {"posed_points": (np.float32, (0, 3)), "canonical_points": (np.float32, (0, 3)),
              "canonical_confidence": (np.float32, (0,)), "posed_confidence": (np.float32, (0,)),
              "pixels": (np.float32, (0, 2)), "layers": (np.int8, (0,))}
    merged = {k: (np.concatenate([c[k] for c in clouds]).astype(dt) if clouds else np.zeros(shape, dt))
              for k, (dt, shape) in dtypes.items()}
    return DualClouds(offsets=np.asarray(offsets, np.int64), **merged)


def save_clouds(path: str | os.PathLike, clouds: DualClouds) -> Path:
    """Write ``clouds`` to ``path`` (npz: ``offsets`` + the concatenated arrays) atomically."""
    arrays = {"offsets": clouds.offsets, **{k: getattr(clouds, k) for k in _CLOUD_KEYS}}

    def _write(tmp: str) -> None:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
    return atomic_write(path, _write)


def load_clouds(path: str | os.PathLike) -> DualClouds:
    """Read a clouds npz written by ``save_clouds``."""
    with np.load(path, allow_pickle=False) as z:
        missing = [k for k in ("offsets", *_CLOUD_KEYS) if k not in z.files]
        if missing:
            raise ValueError(f"path: {path} lacks arrays {missing}")
        return DualClouds(offsets=z["offsets"], **{k: z[k] for k in _CLOUD_KEYS})


def clouds_path(folder: str | os.PathLike, index: int) -> Path:
    """``part-NNNNN.clouds.npz`` of shard ``index`` in ``folder``."""
    return shard_paths(folder, index).npz.with_suffix(".clouds.npz")


def predict_shard(model: DualPointMapNet, collection_dir: str | os.PathLike, index: int, out_dir: str | os.PathLike,
                  feature_fn: FeatureFn | None = None, batch_size: int = 16) -> ShardPaths:
    """Predict shard ``index`` of ``collection_dir`` (npz ``rgb (N, H, W, 3) uint8`` and ``mask (N, H, W) bool`` at
    the model resolution; rows with status != ok are passed through) into ``out_dir`` (module docstring)."""
    cfg = model.config
    feature_fn = feature_fn or rgb_features
    table, arrays = read_shard(collection_dir, index)
    n = table.num_rows
    ids = table.column("sample_id").to_pylist()
    status = table.column("status").to_pylist()
    reason = table.column("reason").to_pylist()
    r, k = cfg.resolution, cfg.layers
    ok = np.array([s == STATUS_OK for s in status], bool)
    if n and ok.any():
        for key in ("rgb", "mask"):
            if key not in arrays:
                raise ValueError(f"collection_dir: shard {index} of {collection_dir} lacks the '{key}' array")
        if arrays["rgb"].shape[1:] != (r, r, 3) or arrays["mask"].shape[1:] != (r, r):
            raise ValueError(f"collection_dir: shard {index} holds {arrays['rgb'].shape[1:3]} images; the model "
                             f"expects {r}x{r} crops")
        mask_all = arrays["mask"].astype(bool)
        empty = ok & ~mask_all.reshape(n, -1).any(axis=1)
        for i in np.flatnonzero(empty):
            status[i], reason[i] = "empty", "the mask has no foreground pixel"
        ok &= ~empty
    out = {"canonical_points": np.zeros((n, r, r, k, 3), np.float16),
           "posed_points": np.zeros((n, r, r, k, 3), np.float16),
           "occupancy": np.zeros((n, r, r, k), np.float16),
           "canonical_confidence": np.zeros((n, r, r, k), np.float16),
           "posed_confidence": np.zeros((n, r, r, k), np.float16),
           "mask": np.zeros((n, r, r), bool)}
    sel = np.flatnonzero(ok)
    per_row_clouds: dict[int, dict[str, np.ndarray]] = {}
    if len(sel):
        mask = arrays["mask"][sel].astype(bool)
        features = np.asarray(feature_fn(arrays["rgb"][sel], mask), np.float32)
        maps = predict_maps(model, features, mask, batch_size)
        clouds = maps_to_clouds(maps)
        for j, i in enumerate(sel):
            per_row_clouds[int(i)] = clouds.instance(j)
        out["mask"][sel] = mask
        for key in ("canonical_points", "posed_points", "occupancy"):
            out[key][sel] = getattr(maps, key).astype(np.float16)
        for key in ("canonical_confidence", "posed_confidence"):
            out[key][sel] = np.minimum(getattr(maps, key), _FLOAT16_CONFIDENCE_MAX).astype(np.float16)
    rows, parts = [], []
    for i in range(n):
        c = per_row_clouds.get(i)
        parts.append(c)
        rows.append({"sample_id": ids[i], "status": status[i], "reason": reason[i],
                     "n_points": 0 if c is None else int(len(c["layers"])),
                     "mask_pixels": int(out["mask"][i].sum()),
                     "mean_canonical_confidence": float(c["canonical_confidence"].mean()) if c and len(c["layers"])
                     else 0.0,
                     "mean_posed_confidence": float(c["posed_confidence"].mean()) if c and len(c["layers"]) else 0.0})
    save_clouds(clouds_path(out_dir, index), _concat_clouds(parts))
    return write_shard(out_dir, index, rows, out if n else None)


def _concat_clouds(parts: list[dict[str, np.ndarray] | None]) -> DualClouds:
    """Per-row cloud dicts (``None`` = no points) -> ``DualClouds`` over all rows."""
    empty = {"posed_points": np.zeros((0, 3), np.float32), "canonical_points": np.zeros((0, 3), np.float32),
             "canonical_confidence": np.zeros(0, np.float32), "posed_confidence": np.zeros(0, np.float32),
             "pixels": np.zeros((0, 2), np.float32), "layers": np.zeros(0, np.int8)}
    parts = [p if p is not None else empty for p in parts]
    offsets = np.concatenate([[0], np.cumsum([len(p["layers"]) for p in parts])]).astype(np.int64)
    merged = {k: np.concatenate([empty[k]] + [p[k] for p in parts]).astype(empty[k].dtype) for k in _CLOUD_KEYS}
    return DualClouds(offsets=offsets, **merged)


def predict_collection(model_ckpt: str | os.PathLike, collection_dir: str | os.PathLike, out_dir: str | os.PathLike,
                       feature_fn: FeatureFn | None = None, batch_size: int = 16,
                       device: str | torch.device | None = None) -> list[ShardPaths]:
    """``bat3r predict --model CKPT --collection DIR --out DIR``: predict every complete shard of
    ``collection_dir`` that ``out_dir`` does not hold complete yet (a rerun resumes); returns all output shards."""
    model, _ = load_predictor(model_ckpt, device)
    written = []
    for index in list_shards(collection_dir):
        paths = shard_paths(out_dir, index)
        written.append(paths if paths.complete else predict_shard(model, collection_dir, index, out_dir,
                                                                  feature_fn, batch_size))
    return written
