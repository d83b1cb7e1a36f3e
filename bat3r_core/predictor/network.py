"""The dual point map network: a (two-stage) UNet from image features to K-layer dual point maps.

Per pixel and layer k the network predicts the canonical point Q (rest-pose frame, metres), the posed point P
(camera frame relative to the object depth, i.e. ``P - (0, 0, object_depth)``, metres), an occupancy logit and
two confidence logits ``c`` (one for Q, one for P) whose confidence is ``C = 1 + exp(c)``.

Two-stage mode (reference): stage 1 sees the features and the mask and predicts the visible canonical map
(layer-0 Q and its confidence); stage 2 sees the features, the mask and stage 1's canonical map and predicts
everything else. Both stages are trained jointly (the gradient flows through the conditioning).
"""
from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn as nn

from bat3r_core.predictor.config import CHANNELS_PER_LAYER, ModelConfig


class PointMapPrediction(NamedTuple):
    """Raw network output for B images of H x W pixels and K layers (float32 unless autocast).

    canonical_points: (B, H, W, K, 3) metres, canonical (rest-pose) frame.
    posed_points: (B, H, W, K, 3) metres, camera frame with the object depth subtracted from z.
    occupancy_logits: (B, H, W, K); occupancy probability is ``sigmoid``.
    canonical_confidence_logits: (B, H, W, K); ``C_Q = 1 + exp(.)``.
    posed_confidence_logits: (B, H, W, K); ``C_P = 1 + exp(.)``.
    """

    canonical_points: torch.Tensor
    posed_points: torch.Tensor
    occupancy_logits: torch.Tensor
    canonical_confidence_logits: torch.Tensor
    posed_confidence_logits: torch.Tensor


def _groups(channels: int) -> int:
    for g in (8, 4, 2):
        if channels % g == 0:
            return g
    return 1


class _ConvBlock(nn.Module):
    """Two 3x3 convolutions, each followed by GroupNorm and SiLU."""

    def __init__(self, c_in: int, c_out: int) -> None:
        super().__init__()
        self.body = nn.Sequential(
            nn.Conv2d(c_in, c_out, 3, padding=1), nn.GroupNorm(_groups(c_out), c_out), nn.SiLU(),
            nn.Conv2d(c_out, c_out, 3, padding=1), nn.GroupNorm(_groups(c_out), c_out), nn.SiLU())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.body(x)


class UNet(nn.Module):
    """Plain UNet: strided-conv down-sampling, transposed-conv up-sampling, skip concatenation.

    Only deterministic-capable ops (no interpolation), so ``torch.use_deterministic_algorithms`` works on CUDA too.
    x: (B, c_in, H, W) -> (B, c_out, H, W); H and W must be divisible by ``2 ** depth``.
    """

    def __init__(self, c_in: int, c_out: int, base_channels: int, depth: int) -> None:
        super().__init__()
        widths = [base_channels * 2 ** min(i, 3) for i in range(depth + 1)]
        self.inc = _ConvBlock(c_in, widths[0])
        self.downs = nn.ModuleList(
            nn.Sequential(nn.Conv2d(widths[i], widths[i], 3, stride=2, padding=1), _ConvBlock(widths[i], widths[i + 1]))
            for i in range(depth))
        self.ups = nn.ModuleList(nn.ConvTranspose2d(widths[i + 1], widths[i], 2, stride=2) for i in range(depth))
        self.merges = nn.ModuleList(_ConvBlock(2 * widths[i], widths[i]) for i in range(depth))
        self.head = nn.Conv2d(widths[0], c_out, 1)
        self.depth = depth

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skips = [self.inc(x)]
        for down in self.downs:
            skips.append(down(skips[-1]))
        y = skips.pop()
        for i in reversed(range(self.depth)):
            y = self.merges[i](torch.cat([skips[i], self.ups[i](y)], dim=1))
        return self.head(y)


def _pixel_grid(batch: int, size: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """(B, 2, size, size): pixel-centre coordinates (u, v) scaled to [-1, 1] across the image."""
    c = (torch.arange(size, device=device, dtype=torch.float32) + 0.5) * (2.0 / size) - 1.0
    v, u = torch.meshgrid(c, c, indexing="ij")
    return torch.stack([u, v]).to(dtype).expand(batch, 2, size, size)


class DualPointMapNet(nn.Module):
    """Image features + foreground mask -> ``PointMapPrediction`` (see the module docstring)."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        if not isinstance(config, ModelConfig):
            raise TypeError(f"config: expected ModelConfig, got {type(config).__name__}")
        self.config = config
        # + the mask channel, + 2 pixel-coordinate channels (posed x, y depend on the absolute pixel position,
        # which a translation-equivariant UNet over rgb cannot otherwise see)
        k, c = config.layers, config.in_channels + 1 + (2 if config.pixel_coordinates else 0)
        if config.two_stage:
            self.stage1 = UNet(c, 4, config.base_channels, config.depth)  # layer-0 Q xyz + its confidence
            self.stage2 = UNet(c + 3, CHANNELS_PER_LAYER * k - 4, config.base_channels, config.depth)
        else:
            self.stage1 = UNet(c, CHANNELS_PER_LAYER * k, config.base_channels, config.depth)
            self.stage2 = None

    def forward(self, features: torch.Tensor, mask: torch.Tensor) -> PointMapPrediction:
        """features: (B, C, H, W) float; mask: (B, H, W) bool or float in [0, 1]."""
        cfg = self.config
        r = cfg.resolution
        if features.ndim != 4 or features.shape[1:] != (cfg.in_channels, r, r):
            raise ValueError(f"features: expected shape (B, {cfg.in_channels}, {r}, {r}), got {tuple(features.shape)}")
        if mask.shape != (features.shape[0], r, r):
            raise ValueError(f"mask: expected shape ({features.shape[0]}, {r}, {r}), got {tuple(mask.shape)}")
        x = [features, mask.to(features.dtype)[:, None]]
        if cfg.pixel_coordinates:
            x.append(_pixel_grid(features.shape[0], r, features.dtype, features.device))
        x = torch.cat(x, dim=1)
        if self.stage2 is None:
            out = self.stage1(x)
        else:
            first = self.stage1(x)  # (B, 4, H, W): layer-0 canonical xyz, canonical confidence logit
            rest = self.stage2(torch.cat([x, first[:, :3]], dim=1))  # (B, 9K - 4, H, W)
            # layer 0 = [Q0 (stage 1), P0 + occupancy (stage 2), c_Q0 (stage 1), c_P0 (stage 2)], then layers 1..K-1
            out = torch.cat([first[:, :3], rest[:, :4], first[:, 3:4], rest[:, 4:5], rest[:, 5:]], dim=1)
        b, _, h, w = out.shape
        out = out.view(b, cfg.layers, CHANNELS_PER_LAYER, h, w).permute(0, 3, 4, 1, 2)  # (B, H, W, K, 9)
        return PointMapPrediction(
            canonical_points=out[..., 0:3],
            posed_points=out[..., 3:6],
            occupancy_logits=out[..., 6],
            canonical_confidence_logits=out[..., 7],
            posed_confidence_logits=out[..., 8],
        )


def confidence(logits: torch.Tensor) -> torch.Tensor:
    """Confidence ``C = 1 + exp(c)`` (>= 1) from confidence logits ``c`` of any shape."""
    return 1.0 + torch.exp(logits)


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


__all__ = ["PointMapPrediction", "UNet", "DualPointMapNet", "confidence", "count_parameters"]
