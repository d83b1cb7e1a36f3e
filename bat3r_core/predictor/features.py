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

import abc
import functools
import hashlib
import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F

from bat3r_core.predictor.data import rgb_features
from bat3r_core.shards import ShardPaths, atomic_write, list_shards, ok_mask, read_shard, write_shard



@functools.lru_cache(maxsize=1)
def _code_version() -> str:
    """The version of the feature code in the feature cache's and the PCA's config hash: the same mechanism as the
    stages' cache keys (``bat3r_core.runs.stage_code_version`` of this module and what it imports), so an edit of
    the feature code computes into a new cache folder and fits a new PCA."""
    from bat3r_core.runs import stage_code_version

    return stage_code_version(__name__)

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


# --------------------------------------------------------------------------------------------------------- dinov2
_MODELS: dict[tuple[str, str, str], torch.nn.Module] = {}
_FOLDER_HASHES: dict[tuple, str] = {}
_MEMORY_PCAS: dict[str, FeaturePCA] = {}


def _model_identity(model: str) -> str:
    """A local folder is identified by the content of its config and weight files, a hub id by its name."""
    folder = Path(model)
    if not folder.is_dir():
        return model
    files = sorted(p for p in folder.iterdir()
                   if p.is_file() and (p.name == "config.json" or p.suffix in (".safetensors", ".bin")))
    if not files:
        raise ValueError(f"dinov2.model folder {folder} holds no config.json or weight files")
    sig = tuple((str(p.resolve()), p.stat().st_size, p.stat().st_mtime_ns) for p in files)
    if sig not in _FOLDER_HASHES:
        h = hashlib.sha256()
        for p in files:
            h.update(p.name.encode())
            with open(p, "rb") as f:
                for chunk in iter(lambda: f.read(1 << 22), b""):
                    h.update(chunk)
        _FOLDER_HASHES[sig] = "sha256:" + h.hexdigest()[:16]
    return _FOLDER_HASHES[sig]


def load_dinov2(model: str, device: str | torch.device = "cpu") -> torch.nn.Module:
    """A frozen ``Dinov2Model`` in eval mode on ``device`` (memoised per model and device).

    ``model`` is a local folder (loaded with ``local_files_only=True``) or a hub id.
    """
    from transformers import Dinov2Model

    device = torch.device(device)
    local = Path(model).is_dir()
    if not local and model.startswith(("/", "./", "../", "~")):
        raise ValueError(f"dinov2.model folder {model} does not exist; expected a folder written by "
                         f"save_pretrained or a hub id such as facebook/dinov2-small")
    source = str(Path(model).resolve()) if local else model
    key = (source, _model_identity(model), str(device))  # a folder whose weights changed is loaded again
    if key not in _MODELS:
        try:
            net = Dinov2Model.from_pretrained(source, local_files_only=local)
        except (OSError, ValueError) as e:
            raise ValueError(f"dinov2.model {model!r} could not be loaded: not a folder written by "
                             f"save_pretrained, and not a hub id available offline ({e})") from e
        net.eval().requires_grad_(False)
        _MODELS[key] = net.to(device)
    return _MODELS[key]


class Dinov2Extractor(FeatureExtractor):
    """Frozen DINOv2 patch tokens → PCA to C channels on the (input_size / patch)² grid."""

    name = "dinov2"
    cacheable = True

    def channels(self, cfg: FeatureConfig) -> int:
        return cfg.dinov2.channels

    def identity(self, cfg: FeatureConfig) -> dict:
        o = cfg.dinov2
        return {"extractor": self.name, "version": _code_version(), "model": _model_identity(o.model),
                "input_size": o.input_size, "channels": o.channels}

    def pca_path(self, cfg: FeatureConfig) -> Path | None:
        """Where the PCA of this config lives (None: memory only)."""
        if cfg.dinov2.pca_path:
            return Path(cfg.dinov2.pca_path)
        if cfg.cache_dir:
            return Path(cfg.cache_dir) / "pca" / f"dinov2-{_hash_json(self.identity(cfg))}.npz"
        return None

    def prepare(self, rgb: np.ndarray, mask: np.ndarray, cfg: FeatureConfig) -> dict:
        pca = self.pca(cfg)
        if pca is None:
            pca = self.fit_pca(rgb, mask, cfg)
        return {"pca": pca.content_hash}

    def pca(self, cfg: FeatureConfig) -> FeaturePCA | None:
        """The saved PCA of this config, or None when none was fitted yet."""
        config_hash = _hash_json(self.identity(cfg))
        path = self.pca_path(cfg)
        if path is None:
            return _MEMORY_PCAS.get(config_hash)
        if not path.is_file():
            return None
        pca = load_pca(path)
        if pca.config_hash != config_hash:
            raise ValueError(f"PCA file {path} was fitted for extractor config {pca.config_hash}, but the current "
                             f"config is {config_hash}; delete the file or set dinov2.pca_path elsewhere")
        return pca

    def fit_pca(self, rgb: np.ndarray, mask: np.ndarray, cfg: FeatureConfig) -> FeaturePCA:
        """Fit the PCA on the foreground patch tokens of (at most ``pca_max_images``) samples and save it."""
        o = cfg.dinov2
        n = min(len(rgb), o.pca_max_images)
        idx = np.linspace(0, len(rgb) - 1, n).round().astype(int) if n < len(rgb) else np.arange(len(rgb))
        chunks = []
        for s in range(0, len(idx), cfg.batch_size):
            b = idx[s:s + cfg.batch_size]
            tokens, fg = self._tokens(rgb[b], mask[b], cfg)
            chunks.append(tokens[fg])
        fg_tokens = np.concatenate(chunks, axis=0) if chunks else np.zeros((0, 1))
        if len(fg_tokens) > o.pca_max_tokens:
            keep = np.random.default_rng(o.seed).choice(len(fg_tokens), o.pca_max_tokens, replace=False)
            fg_tokens = fg_tokens[np.sort(keep)]
        config_hash = _hash_json(self.identity(cfg))
        pca = fit_feature_pca(fg_tokens, o.channels, config_hash, n_images=len(idx))
        _STATS.pca_fits += 1
        path = self.pca_path(cfg)
        if path is None:
            _MEMORY_PCAS[config_hash] = pca
        else:
            save_pca(path, pca)
        return pca

    def compute_grid(self, rgb: np.ndarray, mask: np.ndarray, cfg: FeatureConfig) -> np.ndarray:
        pca = self.pca(cfg)
        if pca is None:
            raise ValueError("the dinov2 PCA has not been fitted for this config; call prepare() or fit_pca()")
        tokens, _ = self._tokens(rgb, mask, cfg)  # (B, h, w, D)
        return pca.project(tokens).transpose(0, 3, 1, 2)

    def _tokens(self, rgb: np.ndarray, mask: np.ndarray, cfg: FeatureConfig) -> tuple[np.ndarray, np.ndarray]:
        """Patch tokens (B, h, w, D) float32 and foreground patches (B, h, w) bool (mask area >= 1/2)."""
        o = cfg.dinov2
        device = resolve_device(cfg.device)
        net = load_dinov2(o.model, device)
        patch = int(net.config.patch_size)
        if o.input_size % patch:
            raise ValueError(f"dinov2.input_size must be a multiple of the model's patch size {patch}, "
                             f"got {o.input_size}")
        g = o.input_size // patch
        with torch.inference_mode():
            x = torch.from_numpy(np.ascontiguousarray(rgb)).to(device).permute(0, 3, 1, 2).float() / 255.0
            if x.shape[-1] != o.input_size:
                x = F.interpolate(x, size=(o.input_size,) * 2, mode="bilinear", align_corners=False,
                                  antialias=x.shape[-1] > o.input_size)
            mean = torch.tensor(IMAGENET_MEAN, device=device).view(1, 3, 1, 1)
            std = torch.tensor(IMAGENET_STD, device=device).view(1, 3, 1, 1)
            hidden = net(pixel_values=(x - mean) / std).last_hidden_state  # (B, prefix + g*g, D)
            tokens = hidden[:, -g * g:, :].reshape(len(rgb), g, g, -1).float().cpu().numpy()
            m = torch.from_numpy(np.ascontiguousarray(mask)).float()[:, None]
            fg = (F.interpolate(m, size=(g, g), mode="area")[:, 0] >= 0.5).numpy()
        _STATS.model_batches += 1
        return tokens, fg


register_extractor(RGBExtractor())
register_extractor(Dinov2Extractor())


# ---------------------------------------------------------------------------------------------------------- cache
class _FeatureCache:
    """npz shards of (keys, grids) in one folder; an in-process index maps a key to its shard and row."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self._index: dict[str, tuple[Path, int]] = {}
        self._seen: set[str] = set()

    def _refresh(self) -> None:
        if not self.folder.is_dir():
            return
        for p in sorted(self.folder.glob("*.npz")):
            if p.name in self._seen:
                continue
            with np.load(p, allow_pickle=False) as z:
                keys = z["keys"]
            for row, k in enumerate(keys.tolist()):
                self._index.setdefault(k, (p, row))
            self._seen.add(p.name)

    def lookup(self, keys: list[str]) -> dict[str, np.ndarray]:
        self._refresh()
        by_file: dict[Path, list[tuple[str, int]]] = {}
        for k in keys:
            if k in self._index:
                p, row = self._index[k]
                by_file.setdefault(p, []).append((k, row))
        found = {}
        for p, items in by_file.items():
            with np.load(p, allow_pickle=False) as z:
                grids = z["grids"]
            for k, row in items:
                found[k] = grids[row]
        return found

    def store(self, keys: list[str], grids: np.ndarray) -> None:
        name = hashlib.sha256("".join(keys).encode()).hexdigest()[:16] + ".npz"
        _save_npz(self.folder / name, {"keys": np.array(keys), "grids": grids.astype(np.float32)})


_CACHES: dict[str, _FeatureCache] = {}


def _cache(folder: Path) -> _FeatureCache:
    key = str(folder.resolve())
    if key not in _CACHES:
        _CACHES[key] = _FeatureCache(folder)
    return _CACHES[key]


def sample_keys(rgb: np.ndarray, mask: np.ndarray) -> list[str]:
    """Content hash (hex, 32 chars) of each crop and its mask."""
    keys = []
    for i in range(len(rgb)):
        h = hashlib.sha256(str(rgb[i].shape).encode())
        h.update(np.ascontiguousarray(rgb[i]).tobytes())
        h.update(np.packbits(mask[i]).tobytes())
        keys.append(h.hexdigest()[:32])
    return keys


# ----------------------------------------------------------------------------------------------------- public API
def _check_inputs(rgb: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    rgb = np.asarray(rgb)
    mask = np.asarray(mask)
    if rgb.ndim != 4 or rgb.shape[-1] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be (N, R, R, 3) uint8, got {rgb.shape} {rgb.dtype}")
    if mask.shape != rgb.shape[:3]:
        raise ValueError(f"mask must have shape {rgb.shape[:3]} (rgb's first three axes), got {mask.shape}")
    if mask.dtype != bool:
        raise TypeError(f"mask must be bool, got {mask.dtype}")
    return rgb, mask


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
    rgb, mask = _check_inputs(rgb, mask)
    if len(rgb) == 0:
        return np.zeros((0, get_extractor(name).channels(cfg)) + rgb.shape[1:3], np.float32)
    return grid_features(extract_grids(name, rgb, mask, cfg), mask)


def extract_grids(name: str, rgb: np.ndarray, mask: np.ndarray, cfg: FeatureConfig = FeatureConfig()
                  ) -> np.ndarray:
    """The extractor's native feature grids (N, C, h, w) float32 of masked crops (``dinov2``: one cell per patch,
    after the PCA; ``rgb``: the crop itself): what :func:`extract_features` computes before
    :func:`grid_features` brings them to the crop's resolution, and what the features stage stores."""
    rgb, mask = _check_inputs(rgb, mask)
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
    rgb, mask = _check_inputs(arrays["rgb"], arrays["mask"])
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
