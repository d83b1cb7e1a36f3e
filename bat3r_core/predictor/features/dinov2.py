"""The ``dinov2`` extractor: a frozen ``transformers`` DINOv2, its patch tokens reduced by a PCA fitted on the
category's foreground tokens."""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from bat3r_core.predictor.features.config import (FeatureConfig, IMAGENET_MEAN, IMAGENET_STD, _STATS, _code_version,
                                                  _hash_json, resolve_device)
from bat3r_core.predictor.features.pca import FeaturePCA, fit_feature_pca, load_pca, save_pca
from bat3r_core.predictor.features.registry import FeatureExtractor

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
