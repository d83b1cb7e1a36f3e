"""The silhouette term of the fitting objective (not in the paper; ``FittingConfig.weight_silhouette``).

The dual point maps tell the fit where the surface is only as well as Φ predicts it; the image's mask tells it
exactly which pixels the animal covers. This term compares the fitted mesh's projection with the mask:

* **outside**: every sampled mesh vertex must project into the mask; its cost is the distance (pixels) from its
  projection to the nearest mask pixel, read bilinearly from the distance transform of the mask's complement,
  less half a pixel;
* **coverage**: every mask pixel must be covered; its cost is the distance from its centre to the nearest projected
  vertex, less half a pixel (a seeded sample of at most ``silhouette_mask_samples`` pixels; the nearest vertices
  are searched every ``silhouette_refresh_steps`` steps).

Both are converted to metres at the object's depth, put through the data term's Huber (δ in the objective's unit,
``FittingConfig.objective_reference_length``) and averaged; the term is their sum, weighed against the (mean) data
term by ``weight_silhouette``. Occluded vertices count too: a mesh's silhouette is the projection of all of it.

The projection. Posed points are camera-frame points relative to the object depth, and their x, y need not be
measured from the intrinsics' principal point (docs/CONVENTIONS.md), so the projection is estimated from the
instance's own layer-0 points and pixels: with the focal length ``f`` of the intrinsics, the object depth ``d`` and
principal point ``c`` of ``u = f·x / (z + d) + c`` that best reproduce the pixels (a bounded search over ``d``
started from a weak-perspective fit, ``c`` in closed form, refitted without outlying points); without intrinsics a
weak perspective ``u = a·x + c``. ``a = f / d`` is the pixels per metre at the object's depth.

The mask is ``PointCloudInstance.mask`` — the image's mask, which the inference stage stores beside its predictions
— or, when an instance has none, the pixels of its layer-0 points.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from scipy.ndimage import distance_transform_edt

__all__ = ["MIN_PROJECTION_POINTS", "SilhouetteBatch", "SilhouetteTarget", "mesh_sample", "nearest_projections",
           "silhouette_target", "silhouette_terms"]

MIN_PROJECTION_POINTS = 8
"""Fewer layer-0 points than this (or a degenerate fit) leave an instance without a silhouette term."""

_INSIDE_TOLERANCE_PX = 0.5
_COVER_TOLERANCE_PX = 0.5
_TRIM_ROUNDS = 3


@dataclass(frozen=True, eq=False)
class SilhouetteTarget:
    """What the silhouette term of one instance needs.

    Attributes:
        outside_distance: (H, W) float32, distance (pixels) from each pixel centre outside the mask to the nearest
            mask pixel centre; 0 inside.
        mask_pixels: (M, 2) float64 pixel centres ``(u, v)`` of (a sample of) the mask's pixels.
        pixels_per_metre: ``a`` of the projection. principal: ``(cu, cv)`` pixels.
        focal: focal length in pixels (perspective projection) or None (weak perspective).
    """

    outside_distance: np.ndarray
    mask_pixels: np.ndarray
    pixels_per_metre: float
    principal: tuple[float, float]
    focal: float | None


def _mask_of(mask: np.ndarray | None, pixels: np.ndarray, front: np.ndarray,
             image_size: tuple[int, int] | None) -> np.ndarray | None:
    if mask is not None:
        return np.asarray(mask, dtype=bool)
    uv = pixels[front]
    if not len(uv):
        return None
    if image_size is not None:
        w, h = int(image_size[0]), int(image_size[1])
    else:
        w, h = int(np.floor(uv[:, 0].max())) + 1, int(np.floor(uv[:, 1].max())) + 1
    out = np.zeros((h, w), dtype=bool)
    col = np.clip(np.floor(uv[:, 0]).astype(np.int64), 0, w - 1)
    row = np.clip(np.floor(uv[:, 1]).astype(np.int64), 0, h - 1)
    out[row, col] = True
    return out


def _weak_perspective(x: np.ndarray, uv: np.ndarray) -> tuple[float, float, float]:
    """Least-squares ``(a, cu, cv)`` of ``u = a·x + cu``, ``v = a·y + cv``."""
    n = len(x)
    a_mat = np.zeros((2 * n, 3))
    a_mat[0::2, 0], a_mat[1::2, 0] = x[:, 0], x[:, 1]
    a_mat[0::2, 1], a_mat[1::2, 2] = 1.0, 1.0
    sol, *_ = np.linalg.lstsq(a_mat, uv.reshape(-1), rcond=None)
    return float(sol[0]), float(sol[1]), float(sol[2])


def _perspective_residual(depth: float, x: np.ndarray, uv: np.ndarray, focal: float
                          ) -> tuple[float, np.ndarray]:
    """Sum of squared pixel residuals of ``u = f·x / (z + depth) + c`` with the best principal point ``c``, and
    that point."""
    proj = focal * x[:, :2] / (x[:, 2:3] + depth)
    centre = (uv - proj).mean(0)
    return float(((proj + centre - uv) ** 2).sum()), centre


def _fit_projection(x: np.ndarray, uv: np.ndarray, focal: float | None) -> tuple[float, float, float] | None:
    """``(a, cu, cv)`` of the projection of posed points ``x`` (n, 3) to pixels ``uv`` (n, 2): weak perspective
    without a focal length; with one, the object depth ``d = f / a`` and principal point of the perspective
    projection that best fits (a bounded 1D search over d, the principal point in closed form), then
    again without the points whose residual exceeds three times the median (outlying predictions), 3 times."""
    from scipy.optimize import minimize_scalar

    if len(x) < MIN_PROJECTION_POINTS:
        return None
    a, cu, cv = _weak_perspective(x, uv)
    if not (np.isfinite(a) and a > 0):
        return None
    if focal is None or not focal > 0:
        return a, cu, cv
    keep = np.ones(len(x), dtype=bool)
    for _ in range(_TRIM_ROUNDS + 1):
        xs, us = x[keep], uv[keep]
        d0 = focal / a
        lo = max(0.1 * d0, float(-xs[:, 2].min()) + 0.05 * d0)
        hi = max(10.0 * d0, 2.0 * lo)
        best = minimize_scalar(lambda d, xs=xs, us=us: _perspective_residual(d, xs, us, focal)[0], bounds=(lo, hi),
                               method="bounded", options={"xatol": 1e-4 * d0})
        depth = float(best.x)
        _, centre = _perspective_residual(depth, xs, us, focal)
        a, cu, cv = focal / depth, float(centre[0]), float(centre[1])
        residual = np.linalg.norm(focal * x[:, :2] / np.maximum(x[:, 2:3] + depth, 1e-9) + centre - uv, axis=1)
        keep = residual <= 3.0 * max(float(np.median(residual)), 1e-6)
        if keep.sum() < MIN_PROJECTION_POINTS:
            break
    return a, cu, cv


def silhouette_target(posed_points: np.ndarray, pixels: np.ndarray | None, layers: np.ndarray | None,
                      usable: np.ndarray, mask: np.ndarray | None, intrinsics: np.ndarray | None,
                      image_size: tuple[int, int] | None, max_mask_pixels: int,
                      rng: np.random.Generator) -> SilhouetteTarget | None:
    """The silhouette target of one instance, or None when it cannot have one (no pixels, an empty mask, fewer than
    :data:`MIN_PROJECTION_POINTS` usable layer-0 points, or a projection with ``a <= 0``).

    posed_points (N, 3), pixels (N, 2), layers (N,) or None (all layer 0): the instance's points; usable (N,) bool:
    the points the projection may be fitted to (finite inliers). mask: (H, W) bool or None (the layer-0 pixels).
    """
    if pixels is None:
        return None
    pixels = np.asarray(pixels, dtype=np.float64)
    p = np.asarray(posed_points, dtype=np.float64)
    front = np.asarray(usable, dtype=bool) & np.isfinite(p).all(1) & np.isfinite(pixels).all(1)
    if layers is not None:
        front &= np.asarray(layers) == 0
    m = _mask_of(mask, pixels, front, image_size)
    if m is None or not m.any() or front.sum() < MIN_PROJECTION_POINTS:
        return None
    focal = None
    if intrinsics is not None and np.isfinite(np.asarray(intrinsics, dtype=np.float64)[0, 0]):
        focal = float(np.asarray(intrinsics, dtype=np.float64)[0, 0])
    projection = _fit_projection(p[front], pixels[front], focal)
    if projection is None:
        return None
    a, cu, cv = projection
    rows, cols = np.nonzero(m)
    centres = np.stack([cols + 0.5, rows + 0.5], axis=1).astype(np.float64)
    if len(centres) > max_mask_pixels:
        centres = centres[np.sort(rng.choice(len(centres), max_mask_pixels, replace=False))]
    return SilhouetteTarget(outside_distance=distance_transform_edt(~m).astype(np.float32), mask_pixels=centres,
                            pixels_per_metre=a, principal=(cu, cv), focal=focal)


def mesh_sample(vertices: np.ndarray, count: int, seed: int) -> np.ndarray:
    """``count`` vertex indices spread over a mesh by Euclidean farthest point sampling (all when it has fewer),
    starting from a seeded random vertex: the points whose projection the silhouette term checks."""
    v = np.asarray(vertices, dtype=np.float64)
    if count >= len(v):
        return np.arange(len(v), dtype=np.int64)
    chosen = np.empty(count, dtype=np.int64)
    chosen[0] = np.random.default_rng(seed).integers(len(v))
    dist = np.linalg.norm(v - v[chosen[0]], axis=1)
    for k in range(1, count):
        chosen[k] = int(np.argmax(dist))
        dist = np.minimum(dist, np.linalg.norm(v - v[chosen[k]], axis=1))
    return chosen


@dataclass(frozen=True, eq=False)
class SilhouetteBatch:
    """:class:`SilhouetteTarget` s of B instances as padded tensors (instances without a target have ``active``
    0 and contribute 0)."""

    outside_distance: torch.Tensor  # (B, 1, H, W)
    mask_pixels: torch.Tensor  # (B, M, 2)
    mask_valid: torch.Tensor  # (B, M)
    pixels_per_metre: torch.Tensor  # (B,)
    principal: torch.Tensor  # (B, 2)
    focal: torch.Tensor  # (B,) 0 = weak perspective
    active: torch.Tensor  # (B,)

    @staticmethod
    def stack(targets: list[SilhouetteTarget | None], dtype: torch.dtype, device: torch.device
              ) -> SilhouetteBatch:
        b = len(targets)
        present = [t for t in targets if t is not None]
        h = max((t.outside_distance.shape[0] for t in present), default=1)
        w = max((t.outside_distance.shape[1] for t in present), default=1)
        m = max((len(t.mask_pixels) for t in present), default=1)
        dist = np.zeros((b, 1, h, w), np.float32)
        pix, valid = np.zeros((b, m, 2)), np.zeros((b, m))
        a, principal, focal, active = np.ones(b), np.zeros((b, 2)), np.zeros(b), np.zeros(b)
        for i, t in enumerate(targets):
            if t is None:
                continue
            th, tw = t.outside_distance.shape
            # pixels beyond a smaller image read as far outside its mask
            dist[i, 0] = np.float32(h + w)
            dist[i, 0, :th, :tw] = t.outside_distance
            pix[i, :len(t.mask_pixels)], valid[i, :len(t.mask_pixels)] = t.mask_pixels, 1.0
            a[i], principal[i], focal[i], active[i] = t.pixels_per_metre, t.principal, t.focal or 0.0, 1.0
        to = {"dtype": dtype, "device": device}
        return SilhouetteBatch(*(torch.as_tensor(x, **to) for x in (dist, pix, valid, a, principal, focal, active)))


def _project(points: torch.Tensor, batch: SilhouetteBatch) -> torch.Tensor:
    """(B, S, 2) pixel positions of posed points (B, S, 3) under each instance's projection."""
    a = batch.pixels_per_metre[:, None]
    perspective = batch.focal > 0
    depth = torch.where(perspective, batch.focal / batch.pixels_per_metre, torch.ones_like(a[:, 0]))[:, None]
    # z + depth is kept at >= a tenth of the depth: a vertex swung behind the camera must not flip sign
    ratio = depth / (points[..., 2] + depth).clamp(min=0.1 * depth)
    ratio = torch.where(perspective[:, None], ratio, torch.ones_like(ratio))
    return a[..., None] * points[..., :2] * ratio[..., None] + batch.principal[:, None, :]


def nearest_projections(points: torch.Tensor, batch: SilhouetteBatch) -> torch.Tensor:
    """(B, M) index of the projected point (of ``points`` (B, S, 3)) nearest to each mask pixel (no gradient): the
    coverage term's assignment, which :func:`silhouette_terms` can reuse for a few steps."""
    with torch.no_grad():
        return torch.cdist(batch.mask_pixels, _project(points, batch)).argmin(-1)


def silhouette_terms(points: torch.Tensor, batch: SilhouetteBatch, unit: float, delta: float,
                     nearest: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(outside, coverage), each (B,): the two halves of the silhouette term for posed mesh points (B, S, 3)
    (metres, the prediction frame), in the objective's unit ``unit`` (metres) with Huber ``delta``.

    nearest: the coverage's pixel → point assignment (:func:`nearest_projections`) or None to compute it now (the
    exact nearest point; a stale assignment measures each pixel to a point that was nearest a few steps ago)."""
    from .losses import huber

    uv = _project(points, batch)
    _, _, h, w = batch.outside_distance.shape
    size = torch.tensor([w, h], dtype=uv.dtype, device=uv.device)
    grid = (uv / size * 2.0 - 1.0)[:, :, None, :]  # align_corners=False: pixel centres at (i + 0.5) / size
    far = float(h + w)
    outside_px = F.grid_sample(batch.outside_distance, grid, mode="bilinear", padding_mode="border",
                               align_corners=False)[:, 0, :, 0]
    # beyond the image border the distance keeps growing with the distance to the border
    beyond = ((-uv).clamp(min=0) + (uv - size).clamp(min=0)).norm(dim=-1)
    outside_px = torch.minimum(outside_px + beyond, torch.full_like(outside_px, far))
    outside_px = (outside_px - _INSIDE_TOLERANCE_PX).clamp(min=0.0)
    metres = unit * batch.pixels_per_metre[:, None]
    outside = huber(outside_px / metres, delta).mean(-1)
    if nearest is None:  # the nearest projected vertex of each mask pixel; only its distance is differentiated
        with torch.no_grad():
            nearest = torch.cdist(batch.mask_pixels, uv).argmin(-1)  # (B, M)
    gap = batch.mask_pixels - torch.gather(uv, 1, nearest[..., None].expand(-1, -1, 2))
    cover_px = (torch.sqrt((gap * gap).sum(-1) + 1e-12) - _COVER_TOLERANCE_PX).clamp(min=0.0)  # (B, M)
    valid = batch.mask_valid
    coverage = (huber(cover_px / metres, delta) * valid).sum(-1) / valid.sum(-1).clamp(min=1.0)
    return outside * batch.active, coverage * batch.active
