"""The extractor interface and registry, and the ``rgb`` extractor (the masked crop itself)."""
from __future__ import annotations

import abc

import numpy as np

from bat3r_core.predictor.data import rgb_features
from bat3r_core.predictor.features.config import FeatureConfig, _code_version


# ------------------------------------------------------------------------------------------------------- registry
class FeatureExtractor(abc.ABC):
    """Interface of a feature extractor. Subclasses set ``name`` and ``cacheable`` and implement the methods."""

    name: str = ""
    cacheable: bool = False

    @abc.abstractmethod
    def channels(self, cfg: FeatureConfig) -> int:
        """Number of output channels C."""

    @abc.abstractmethod
    def identity(self, cfg: FeatureConfig) -> dict:
        """JSON-able description of everything the output depends on besides the images (hashed for caches)."""

    def prepare(self, rgb: np.ndarray, mask: np.ndarray, cfg: FeatureConfig) -> dict:
        """Make ready to compute (e.g. fit or load a PCA, possibly on these samples); returns extra identity."""
        return {}

    @abc.abstractmethod
    def compute_grid(self, rgb: np.ndarray, mask: np.ndarray, cfg: FeatureConfig) -> np.ndarray:
        """Features of one batch: rgb (B, R, R, 3) uint8, mask (B, R, R) bool → (B, C, h, w) float32."""


_EXTRACTORS: dict[str, FeatureExtractor] = {}


def register_extractor(extractor: FeatureExtractor, replace: bool = False) -> None:
    """Make ``extractor`` available under ``extractor.name``."""
    if not isinstance(extractor, FeatureExtractor):
        raise TypeError(f"extractor must be a FeatureExtractor, got {type(extractor).__name__}")
    if extractor.name in _EXTRACTORS and not replace:
        raise ValueError(f"a feature extractor named {extractor.name!r} is already registered")
    _EXTRACTORS[extractor.name] = extractor


def get_extractor(name: str) -> FeatureExtractor:
    if name not in _EXTRACTORS:
        raise ValueError(f"unknown feature extractor {name!r}; registered: {sorted(_EXTRACTORS)}")
    return _EXTRACTORS[name]


def available_extractors() -> list[str]:
    return sorted(_EXTRACTORS)


# ------------------------------------------------------------------------------------------------------------ rgb
class RGBExtractor(FeatureExtractor):
    """The masked crop itself: (B, 3, R, R) float32 in [0, 1], background 0."""

    name = "rgb"
    cacheable = False

    def channels(self, cfg: FeatureConfig) -> int:
        return 3

    def identity(self, cfg: FeatureConfig) -> dict:
        return {"extractor": self.name, "version": _code_version()}

    def compute_grid(self, rgb: np.ndarray, mask: np.ndarray, cfg: FeatureConfig) -> np.ndarray:
        return rgb_features(rgb, mask)
