"""Feature settings (``FeatureConfig``, ``Dinov2Options``), the process-wide counters and small helpers."""
from __future__ import annotations

import functools
import hashlib
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from bat3r_core.shards import atomic_write


@functools.lru_cache(maxsize=1)
def _code_version() -> str:
    """The version of the feature code in the feature cache's and the PCA's config hash: the same mechanism as the
    stages' cache keys (``bat3r_core.runs.stage_code_version`` of the features package and what it imports), so
    an edit of the feature code computes into a new cache folder and fits a new PCA."""
    from bat3r_core.runs import stage_code_version

    return stage_code_version("bat3r_core.predictor.features")

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


# ---------------------------------------------------------------------------------------------------------- config
@dataclass(frozen=True)
class Dinov2Options:
    """Settings of the ``dinov2`` extractor.

    Attributes:
        model: a local folder written by ``save_pretrained`` (loaded with ``local_files_only``) or a hub id such
            as ``facebook/dinov2-small`` (needs hub access or a filled Hugging Face cache).
        input_size: side of the square image fed to the ViT, pixels; a multiple of the model's patch size
            (224 with patch 14 gives a 16 x 16 grid).
        channels: PCA output channels C (reference 64).
        pca_path: where the PCA npz lives; None: ``<cache_dir>/pca/dinov2-<config hash>.npz`` (in memory only
            when there is no cache_dir either).
        pca_max_images: at most this many images are used to fit the PCA.
        pca_max_tokens: at most this many foreground patch tokens (a seeded random subset) enter the fit.
        seed: seed of that subset.
    """

    model: str = "facebook/dinov2-small"
    input_size: int = 224
    channels: int = 64
    pca_path: str | None = None
    pca_max_images: int = 1000
    pca_max_tokens: int = 200_000
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("input_size", "channels", "pca_max_images", "pca_max_tokens"):
            if getattr(self, name) < 1:
                raise ValueError(f"dinov2.{name} must be >= 1, got {getattr(self, name)}")


@dataclass(frozen=True)
class FeatureConfig:
    """Feature extraction settings.

    Attributes:
        extractor: registered extractor name (``rgb``, ``dinov2``).
        batch_size: images per forward pass.
        device: ``auto`` (CUDA when available, else CPU), ``cpu``, ``cuda`` or ``cuda:N``.
        cache_dir: folder of the feature cache and the default PCA location; None disables the cache.
        dinov2: options of the ``dinov2`` extractor.
    """

    extractor: str = "rgb"
    batch_size: int = 16
    device: str = "auto"
    cache_dir: str | None = None
    dinov2: Dinov2Options = field(default_factory=Dinov2Options)

    def __post_init__(self) -> None:
        if self.batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {self.batch_size}")


@dataclass
class FeatureStats:
    """Counters of this process's feature work (for logs and tests)."""

    cache_hits: int = 0
    cache_misses: int = 0
    pca_fits: int = 0
    model_batches: int = 0


_STATS = FeatureStats()


def feature_stats() -> FeatureStats:
    """A copy of the process-wide counters."""
    return FeatureStats(**asdict(_STATS))


def resolve_device(device: str) -> torch.device:
    """``auto`` → CUDA when available else CPU; anything else must name a torch device."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        return torch.device(device)
    except RuntimeError as e:
        raise ValueError(f"device must be 'auto', 'cpu', 'cuda' or 'cuda:N', got {device!r}") from e


def _hash_json(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()[:16]


def _save_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Atomically write an (uncompressed) npz."""
    def _write(tmp: str) -> None:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
    atomic_write(path, _write)
