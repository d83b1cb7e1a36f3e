"""The PCA that reduces DINOv2 patch tokens to ``C`` channels: fit, save, load."""
from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bat3r_core.predictor.features.config import _save_npz


# ------------------------------------------------------------------------------------------------------------ PCA
@dataclass(frozen=True, eq=False)
class FeaturePCA:
    """A PCA of patch features: ``project(t) = ((t - mean) @ components.T) * scale``.

    Attributes:
        mean: (D,) float64. components: (C, D) float64, orthonormal rows, sign fixed so each row's largest
        entry is positive. explained_variance: (C,) float64 of the fitted tokens. scale: 1 / sqrt of the first
        explained variance, so the first channel has unit variance on the fitted foreground.
        config_hash: hash of the extractor config it was fitted for. n_images, n_tokens: size of the fit.
    """

    mean: np.ndarray
    components: np.ndarray
    explained_variance: np.ndarray
    scale: float
    config_hash: str
    n_images: int
    n_tokens: int

    def project(self, tokens: np.ndarray) -> np.ndarray:
        """tokens (..., D) → (..., C) float32."""
        t = np.asarray(tokens, dtype=np.float64)
        if t.shape[-1] != self.mean.shape[0]:
            raise ValueError(f"tokens must have last dimension {self.mean.shape[0]}, got {t.shape}")
        return (((t - self.mean) @ self.components.T) * self.scale).astype(np.float32)

    @property
    def content_hash(self) -> str:
        h = hashlib.sha256()
        for a in (self.mean, self.components, np.float64(self.scale)):
            h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
        return h.hexdigest()[:16]


def fit_feature_pca(tokens: np.ndarray, channels: int, config_hash: str = "", n_images: int = 0) -> FeaturePCA:
    """PCA of tokens (n, D) to ``channels`` components via SVD of the centred tokens (float64)."""
    x = np.asarray(tokens, dtype=np.float64)
    if x.ndim != 2:
        raise ValueError(f"tokens must have shape (n, D), got {x.shape}")
    n, d = x.shape
    if channels > d:
        raise ValueError(f"dinov2.channels={channels} exceeds the model's token dimension D={d}")
    if n <= channels:
        raise ValueError(f"the PCA needs more than channels={channels} foreground patch tokens, got {n}; "
                         f"fit it on more or larger masked samples")
    mean = x.mean(axis=0)
    _, s, vt = np.linalg.svd(x - mean, full_matrices=False)
    comps = vt[:channels]
    signs = np.sign(comps[np.arange(channels), np.abs(comps).argmax(axis=1)])
    comps = comps * signs[:, None]
    var = s[:channels] ** 2 / (n - 1)
    scale = 1.0 / np.sqrt(var[0]) if var[0] > 0 else 1.0
    return FeaturePCA(mean, comps, var, float(scale), config_hash, int(n_images), int(n))


def save_pca(path: str | os.PathLike, pca: FeaturePCA) -> None:
    """Write a PCA as npz (atomically)."""
    _save_npz(Path(path), {
        "mean": pca.mean, "components": pca.components, "explained_variance": pca.explained_variance,
        "scale": np.float64(pca.scale), "config_hash": np.array(pca.config_hash),
        "n_images": np.int64(pca.n_images), "n_tokens": np.int64(pca.n_tokens)})


def load_pca(path: str | os.PathLike) -> FeaturePCA:
    with np.load(path, allow_pickle=False) as z:
        return FeaturePCA(z["mean"], z["components"], z["explained_variance"], float(z["scale"]),
                          str(z["config_hash"]), int(z["n_images"]), int(z["n_tokens"]))
