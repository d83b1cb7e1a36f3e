"""Left-right mirroring of training samples: twice the poses and views per render for a bilaterally symmetric rig.

Flipping a crop's columns shows the mirror image of the scene: the camera-frame posed points become
``(-x, y, z)`` (a camera whose principal point ``cx`` moves to ``W - cx``: the renders' ``cx = W / 2`` stays put),
and every pixel now shows the mirror animal — for a left-right symmetric rest mesh, the same animal in the mirrored
pose — whose canonical point is the reflection of the original one through the rig's sagittal plane (the plane
through the body frame's origin joint, normal to its left axis). The layers keep their front-to-back order and the
occupancy flips with the pixels. So a mirrored sample is an exact sample of a pose and view the renders may never
have drawn, as long as the rest mesh is symmetric: :func:`canonical_mirror_for_rig` measures that and refuses a rig
that is not.

Features are flipped with the pixels; that is exact for the ``rgb`` features and an approximation for DINOv2 grids
(which are close to, not exactly, flip-equivariant).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Mapping

import numpy as np

from bat3r_core.config_utils import ConfigError

if TYPE_CHECKING:
    import torch

__all__ = ["CanonicalMirror", "SYMMETRY_TOLERANCE", "canonical_mirror_for_rig", "mirror_decisions",
           "mirror_samples", "symmetry_error"]

SYMMETRY_TOLERANCE = 0.01
"""Largest accepted 95th percentile of the reflected rest vertices' distance to the rest surface, as a fraction of
the rest mesh's bounding-box diagonal (2.7 cm for a 2.7 m horse)."""


@dataclass(frozen=True)
class CanonicalMirror:
    """The sagittal plane of the canonical (rest-pose) frame: ``origin`` (3,) metres on it, ``normal`` (3,) unit."""

    origin: tuple[float, float, float]
    normal: tuple[float, float, float]

    def __post_init__(self) -> None:
        o, n = np.asarray(self.origin, np.float64), np.asarray(self.normal, np.float64)
        if o.shape != (3,) or n.shape != (3,) or not (np.isfinite(o).all() and np.isfinite(n).all()):
            raise ConfigError(f"CanonicalMirror: origin and normal must be 3 finite floats, got {self.origin}, "
                              f"{self.normal}")
        if abs(np.linalg.norm(n) - 1.0) > 1e-6:
            raise ConfigError(f"CanonicalMirror.normal: expected a unit vector, got norm {np.linalg.norm(n):.6g}")

    def reflect(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) canonical points → their reflections through the plane (float64)."""
        p = np.asarray(points, np.float64)
        o, n = np.asarray(self.origin), np.asarray(self.normal)
        return p - 2.0 * ((p - o) @ n)[..., None] * n


def symmetry_error(vertices: np.ndarray, faces: np.ndarray, mirror: CanonicalMirror) -> np.ndarray:
    """Distance (metres) of each reflected vertex to the mesh surface ``(vertices, faces)``: all ≈ 0 for a mesh that
    is left-right symmetric about ``mirror``'s plane, whatever its vertex layout."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(faces, np.uint32)))
    query = o3d.core.Tensor(mirror.reflect(vertices).astype(np.float32))
    return scene.compute_distance(query).numpy().astype(np.float64)


def canonical_mirror_for_rig(rig, body_frame: Mapping, tolerance: float = SYMMETRY_TOLERANCE,
                             source: str = "asset") -> CanonicalMirror:
    """The sagittal plane of ``rig``'s rest pose from the catalog's ``body_frame`` spec (origin joint; left axis from
    the horizontal pair, orthogonalised against the forward pair), checked: the 95th percentile of
    :func:`symmetry_error` must be at most ``tolerance`` × the rest mesh's bounding-box diagonal, else a
    ``ConfigError`` naming ``source`` and the measured asymmetry (mirrored samples of an asymmetric mesh would teach
    canonical points off its surface)."""
    from bat3r_core.datasets import rig_body_frame

    frame = rig_body_frame(rig, rig.rest_joint_positions, body_frame)
    mirror = CanonicalMirror(origin=tuple(float(v) for v in frame.origin),
                             normal=tuple(float(v) for v in frame.rotation[:, 0]))
    v = np.asarray(rig.rest_vertices, np.float64)
    diagonal = float(np.linalg.norm(v.max(0) - v.min(0)))
    p95 = float(np.percentile(symmetry_error(v, rig.faces, mirror), 95))
    if p95 > tolerance * diagonal:
        raise ConfigError(
            f"{source}: train.mirror_probability > 0 needs a rest mesh that is left-right symmetric about the body "
            f"frame's sagittal plane (origin joint {body_frame.get('origin')!r}, left axis from "
            f"{list(body_frame.get('horizontal', []))}); 95 % of its reflected vertices lie within {100 * p95:.2f} cm "
            f"of the surface, above the tolerance {100 * tolerance * diagonal:.2f} cm ({tolerance:g} of the "
            f"{diagonal:.2f} m diagonal). Set train.mirror_probability: 0 for this category, or fix body_frame.")
    return mirror


def mirror_decisions(seed: int, step: int, micro: int, n: int, probability: float) -> np.ndarray:
    """(n,) bool: which samples of micro-batch ``micro`` of optimiser step ``step`` are mirrored. A function of its
    arguments only, so a resumed run mirrors the same samples as an uninterrupted one."""
    if probability <= 0.0:
        return np.zeros(n, dtype=bool)
    return np.random.default_rng([int(seed), 0x6D6972, int(step), int(micro)]).random(n) < probability


def mirror_samples(features: torch.Tensor, mask: torch.Tensor, canonical: torch.Tensor, posed: torch.Tensor,
                   occupancy: torch.Tensor, which: np.ndarray, mirror: CanonicalMirror
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The batch with the samples ``which`` (B,) bool mirrored (module docstring); the others unchanged.

    features (B, C, H, W), mask (B, H, W), canonical / posed (B, H, W, K, 3) (posed relative to the object depth,
    zero where unoccupied), occupancy (B, H, W, K). Unoccupied entries stay zero. Returns new tensors.
    """
    import torch

    which = np.asarray(which, dtype=bool)
    if which.shape != (features.shape[0],):
        raise ValueError(f"which: expected ({features.shape[0]},) bool, got {which.shape}")
    if not which.any():
        return features, mask, canonical, posed, occupancy
    idx = torch.from_numpy(np.flatnonzero(which))
    features, mask, canonical, posed, occupancy = (t.clone() for t in (features, mask, canonical, posed, occupancy))
    features[idx] = torch.flip(features[idx], dims=[-1])
    mask[idx] = torch.flip(mask[idx], dims=[-1])
    occ = torch.flip(occupancy[idx], dims=[2])
    occupancy[idx] = occ
    p = torch.flip(posed[idx], dims=[2])
    posed[idx] = p * torch.tensor([-1.0, 1.0, 1.0], dtype=p.dtype)
    reflected = torch.from_numpy(mirror.reflect(torch.flip(canonical[idx], dims=[2]).cpu().numpy()))
    canonical[idx] = torch.where(occ[..., None], reflected.to(canonical), torch.zeros((), dtype=canonical.dtype))
    return features, mask, canonical, posed, occupancy
