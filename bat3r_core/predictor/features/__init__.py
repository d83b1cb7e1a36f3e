"""Image features for the predictor: pluggable extractors, a PCA for DINOv2 patch features, and caches.

Extractors turn masked object crops ``rgb (N, R, R, 3) uint8`` + ``mask (N, R, R) bool`` into feature maps
``(N, C, R, R) float32`` with the background zeroed:

* ``rgb``: the crop itself, channels first in ``[0, 1]`` (``C = 3``); nothing to fit or cache.
* ``dinov2``: patch tokens of a frozen ``transformers`` ``Dinov2Model`` (a local folder or a hub id), reduced by
  a PCA fitted on the foreground patch tokens of the category to ``C`` channels (reference 64) and upsampled
  bilinearly to ``R``.

An extractor computes a *grid* ``(N, C, h, w)`` (for ``dinov2`` the PCA-reduced patch grid, small) which is what
the cache stores; upsampling and masking happen on the way out. The cache is a folder of npz shards under
``<cache_dir>/<extractor>-<config hash>/``, each holding ``keys (n,) str`` (content hashes of the crop and mask)
and ``grids (n, C, h, w) float32``; the config hash covers everything the grid depends on (extractor, code
version, model weights, input size, channels and, for ``dinov2``, the PCA's content), so a changed setting
computes into a new folder and an unchanged one reuses earlier results.
"""
from __future__ import annotations

import os
import threading
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F

from bat3r_core.predictor.data import check_crops
from bat3r_core.predictor.features.cache import _cache, sample_keys
from bat3r_core.predictor.features.config import (_STATS, IMAGENET_MEAN, IMAGENET_STD, Dinov2Options, FeatureConfig,
                                                  FeatureStats, _hash_json, feature_stats, resolve_device)
from bat3r_core.predictor.features.dinov2 import Dinov2Extractor, load_dinov2
from bat3r_core.predictor.features.pca import FeaturePCA, fit_feature_pca, load_pca, save_pca
from bat3r_core.predictor.features.registry import (FeatureExtractor, RGBExtractor, available_extractors, get_extractor,
                                                    register_extractor)
from bat3r_core.shards import ShardPaths, list_shards, ok_mask, read_shard, write_shard

__all__ = ["IMAGENET_MEAN", "IMAGENET_STD", "Dinov2Options", "FeatureConfig", "FeatureStats", "feature_stats",
           "resolve_device", "FeatureExtractor", "register_extractor", "get_extractor", "available_extractors",
           "RGBExtractor", "FeaturePCA", "fit_feature_pca", "save_pca", "load_pca", "load_dinov2", "Dinov2Extractor",
           "sample_keys", "feature_config_hash", "extract_features", "extract_grids", "grid_features",
           "make_feature_fn", "fit_pca_from_shards", "fit_pca_once", "extract_feature_shard"]

register_extractor(RGBExtractor())
register_extractor(Dinov2Extractor())


# ----------------------------------------------------------------------------------------------------- public API
def feature_config_hash(name: str, rgb: np.ndarray, mask: np.ndarray, cfg: FeatureConfig) -> str:
    """Hash of everything the features of extractor ``name`` depend on besides the images; prepares the
    extractor (fits the ``dinov2`` PCA on these samples when none exists yet)."""
    ext = get_extractor(name)
    return _hash_json({**ext.identity(cfg), **ext.prepare(rgb, mask, cfg)})


def extract_features(name: str, rgb: np.ndarray, mask: np.ndarray, cfg: FeatureConfig = FeatureConfig()
                     ) -> np.ndarray:
    """Feature maps of masked object crops.

    Args:
        name: extractor name (``rgb``, ``dinov2`` or one registered with ``register_extractor``).
        rgb: (N, R, R, 3) uint8 crops, background 0. mask: (N, R, R) bool foreground.
        cfg: settings; with ``cfg.cache_dir`` cacheable extractors reuse grids computed before for the same
            crop, mask and config. For ``dinov2`` without a fitted PCA, the PCA is fitted on these samples.
    Returns:
        (N, C, R, R) float32 features, zero on the background.
    """
    rgb, mask = check_crops(rgb, mask)
    if len(rgb) == 0:
        return np.zeros((0, get_extractor(name).channels(cfg)) + rgb.shape[1:3], np.float32)
    return grid_features(extract_grids(name, rgb, mask, cfg), mask)


def extract_grids(name: str, rgb: np.ndarray, mask: np.ndarray, cfg: FeatureConfig = FeatureConfig()
                  ) -> np.ndarray:
    """The extractor's native feature grids (N, C, h, w) float32 of masked crops (``dinov2``: one cell per patch,
    after the PCA; ``rgb``: the crop itself): what :func:`extract_features` computes before
    :func:`grid_features` brings them to the crop's resolution, and what the features stage stores."""
    rgb, mask = check_crops(rgb, mask)
    ext = get_extractor(name)
    n = rgb.shape[0]
    if n == 0:
        raise ValueError("extract_grids: no crop given (rgb has 0 rows)")
    config_hash = feature_config_hash(name, rgb, mask, cfg)
    cache = _cache(Path(cfg.cache_dir) / f"{name}-{config_hash}") if ext.cacheable and cfg.cache_dir else None
    keys = sample_keys(rgb, mask) if cache else [""] * n
    found = cache.lookup(keys) if cache else {}
    missing = [i for i in range(n) if keys[i] not in found]
    _STATS.cache_hits += n - len(missing) if cache else 0
    _STATS.cache_misses += len(missing) if cache else 0
    computed: dict[int, np.ndarray] = {}
    for s in range(0, len(missing), cfg.batch_size):
        b = missing[s:s + cfg.batch_size]
        grid = np.asarray(ext.compute_grid(rgb[b], mask[b], cfg), dtype=np.float32)
        if cache:
            cache.store([keys[i] for i in b], grid)
        computed.update(zip(b, grid))
    return np.stack([computed[i] if i in computed else found[keys[i]] for i in range(n)]).astype(np.float32)


def grid_features(grids: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Feature grids (N, C, h, w) → the model's input features (N, C, H, W) float32: bilinear (pixel-centre
    aligned) to the resolution of ``mask`` (N, H, W), zero where it is False. Training (from the feature shards)
    and inference (from :func:`extract_features`) both go through it, so they see the same numbers."""
    return _to_resolution(np.asarray(grids, dtype=np.float32), np.asarray(mask, dtype=bool))


def _to_resolution(grids: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(N, C, h, w) → (N, C, H, W) bilinear (pixel-centre aligned), zero where ``mask`` (N, H, W) is False."""
    H, W = mask.shape[1:]
    out = torch.from_numpy(grids)
    if out.shape[-2:] != (H, W):
        out = F.interpolate(out, size=(H, W), mode="bilinear", align_corners=False)
    return (out.numpy() * mask[:, None]).astype(np.float32)


def make_feature_fn(cfg: FeatureConfig) -> Callable:
    """A ``feature_fn(rgb, mask) -> (N, C, H, W) float32`` for the trainer, using ``cfg.extractor``.

    Takes numpy arrays or torch tensors (rgb (N, H, W, 3) uint8, mask (N, H, W) bool) and returns the same kind
    (a tensor on the input's device for tensor input).
    """
    get_extractor(cfg.extractor)

    def feature_fn(rgb, mask):
        if isinstance(rgb, torch.Tensor):
            dev = rgb.device
            out = extract_features(cfg.extractor, rgb.detach().cpu().numpy(),
                                   torch.as_tensor(mask).detach().cpu().numpy(), cfg)
            return torch.from_numpy(out).to(dev)
        return extract_features(cfg.extractor, rgb, mask, cfg)

    return feature_fn


def fit_pca_from_shards(shard_dirs: list[str | os.PathLike], cfg: FeatureConfig, refit: bool = False
                        ) -> FeaturePCA:
    """Fit (or load, unless ``refit``) the ``dinov2`` PCA on the ok samples of collection or training shards
    (npz ``rgb``/``mask``), using at most ``cfg.dinov2.pca_max_images`` evenly spaced samples."""
    ext = get_extractor("dinov2")
    if not isinstance(ext, Dinov2Extractor):
        raise TypeError(f"the registered 'dinov2' extractor is a {type(ext).__name__}, not a Dinov2Extractor")
    if not refit:
        existing = ext.pca(cfg)
        if existing is not None:
            return existing
    rgbs, masks = [], []
    for d in shard_dirs:
        for index in list_shards(d):
            table, arrays = read_shard(d, index)
            ok = ok_mask(table)
            rgbs.append(arrays["rgb"][ok])
            masks.append(arrays["mask"][ok])
    if not rgbs or sum(len(r) for r in rgbs) == 0:
        raise ValueError(f"no ok samples in shard folders {[str(d) for d in shard_dirs]} to fit the PCA on")
    return ext.fit_pca(np.concatenate(rgbs), np.concatenate(masks), cfg)


_PCA_LOCK = threading.Lock()


def fit_pca_once(shard_dirs: list[str | os.PathLike], cfg: FeatureConfig) -> FeaturePCA:
    """:func:`fit_pca_from_shards` under a process-wide lock: concurrent callers (the tasks of one features stage)
    fit the ``dinov2`` PCA once and the others load it. A second process fitting at the same time computes the same
    PCA from the same shards (deterministic subset and seed) and writes it atomically."""
    with _PCA_LOCK:
        return fit_pca_from_shards(shard_dirs, cfg)


def extract_feature_shard(collection_shard_dir: str | os.PathLike, index: int, out_dir: str | os.PathLike,
                          cfg: FeatureConfig = FeatureConfig()) -> ShardPaths:
    """Features of one shard with npz ``rgb``/``mask`` (a collection or training shard) → shard ``index`` of
    ``out_dir``.

    Rows: ``sample_id, status, reason`` copied from the input, ``extractor``, ``feature_config`` (hash).
    npz: ``grid (N, C, h, w) float32``, the extractor's native grids (:func:`extract_grids`; zeros for rows that are
    not ok), and ``mask (N, R, R) bool``; :func:`grid_features` of the two is the model's input, exactly what
    :func:`extract_features` returns for the same crops. Storing grids keeps a DINOv2 shard small (16×16 cells
    per sample, not R×R pixels).
    """
    table, arrays = read_shard(collection_shard_dir, index)
    if "rgb" not in arrays or "mask" not in arrays:
        raise ValueError(f"shard {index} of {collection_shard_dir} has no 'rgb'/'mask' arrays; "
                         f"got {sorted(arrays)}")
    rgb, mask = check_crops(arrays["rgb"], arrays["mask"])
    ok = ok_mask(table)
    ext = get_extractor(cfg.extractor)
    config_hash = ""
    if ok.any():
        grids = extract_grids(cfg.extractor, rgb[ok], mask[ok], cfg)
        feats = np.zeros((len(rgb),) + grids.shape[1:], np.float32)
        feats[ok] = grids
        config_hash = feature_config_hash(cfg.extractor, rgb[ok], mask[ok], cfg)
    else:
        feats = np.zeros((len(rgb), ext.channels(cfg)) + rgb.shape[1:3], np.float32)
    rows = [{"sample_id": r["sample_id"], "status": r["status"], "reason": r["reason"],
             "extractor": cfg.extractor, "feature_config": config_hash}
            for r in table.select(["sample_id", "status", "reason"]).to_pylist()]
    return write_shard(out_dir, index, rows, {"grid": feats, "mask": mask})
