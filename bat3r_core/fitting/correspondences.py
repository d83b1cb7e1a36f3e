"""Correspondences between predicted canonical points and canonical mesh vertices, and the inlier test.

Each predicted canonical point ``q_i`` is assigned its nearest canonical vertex ``j*(i) = argmin_j ‖q_i − v^c_j‖``
(a ``scipy.spatial.cKDTree`` over the rest vertices). The reference keeps a point only if that distance is below a
threshold and its confidence ``C`` is at least ``min_confidence``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["Correspondences", "VertexIndex", "nearest_vertices", "reassign_vertices"]


@dataclass(frozen=True, eq=False)
class Correspondences:
    """Nearest canonical vertex of each predicted point.

    Attributes:
        vertex: (N,) int64 index ``j*(i)`` of the nearest canonical vertex.
        distance: (N,) float64 ``‖q_i − v^c_j*(i)‖``, metres.
        inlier: (N,) bool, distance below the threshold and confidence high enough.
    """

    vertex: np.ndarray
    distance: np.ndarray
    inlier: np.ndarray


class VertexIndex:
    """A KD-tree over the canonical (rest) vertices, built once per asset and queried per image.

    Args:
        rest_vertices: (V, 3) metres, canonical frame.
    """

    def __init__(self, rest_vertices: np.ndarray):
        v = np.asarray(rest_vertices, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
            raise ValueError(f"rest_vertices must have shape (V, 3) with V > 0, got {v.shape}")
        self.rest_vertices = v
        self._tree = cKDTree(v)

    def match(self, canonical_points: np.ndarray, confidence: np.ndarray | None, max_distance: float,
              min_confidence: float) -> Correspondences:
        """Nearest vertices of ``canonical_points`` (N, 3) metres (canonical frame) and the inlier mask.

        Args:
            confidence: (N,) confidence ``C = 1 + exp(c)`` or None (every point passes the confidence test).
            max_distance: inlier distance threshold, metres (strict ``<``).
            min_confidence: inlier confidence threshold (``C >= min_confidence``).
        """
        q = np.asarray(canonical_points, dtype=np.float64)
        if q.ndim != 2 or q.shape[1] != 3:
            raise ValueError(f"canonical_points must have shape (N, 3), got {q.shape}")
        finite = np.isfinite(q).all(1)
        dist = np.full(len(q), np.inf)
        vert = np.zeros(len(q), dtype=np.int64)
        if finite.any():
            d, j = self._tree.query(q[finite])
            dist[finite], vert[finite] = d, j
        inlier = dist < max_distance
        if confidence is not None:
            c = np.asarray(confidence, dtype=np.float64)
            if c.shape != (len(q),):
                raise ValueError(f"confidence must have shape ({len(q)},), got {c.shape}")
            inlier &= c >= min_confidence
        return Correspondences(vertex=vert, distance=dist, inlier=inlier)


def nearest_vertices(rest_vertices: np.ndarray, canonical_points: np.ndarray, confidence: np.ndarray | None = None,
                     max_distance: float = np.inf, min_confidence: float = 2.0) -> Correspondences:
    """One-shot :meth:`VertexIndex.match` (builds the tree each call; use :class:`VertexIndex` for many images)."""
    return VertexIndex(rest_vertices).match(canonical_points, confidence, max_distance, min_confidence)


def reassign_vertices(posed_vertices: np.ndarray, rest_vertices: np.ndarray, posed_points: np.ndarray,
                      canonical_points: np.ndarray, canonical_weight: float,
                      axis_weights: np.ndarray | None = None) -> np.ndarray:
    """Re-assign each point the vertex nearest to it in the joint posed + canonical space.

    Vertex ``j`` costs ``‖W (x_j − p_i)‖² + β² ‖v^c_j − q_i‖²``, with ``x_j`` the vertex in the current fit
    (posed, prediction frame), ``v^c_j`` its rest position, ``p_i``/``q_i`` the point's predicted posed and canonical
    positions, ``W = diag(axis_weights)`` and ``β = canonical_weight``. Large β gives back the nearest canonical vertex
    (:meth:`VertexIndex.match`); β = 0 is the closest-point step of articulated ICP. In between, a point whose
    predicted label lies on the wrong limb moves to the limb its posed position lies on once the fit has brought
    that limb near it.

    Args:
        posed_vertices: (V, 3) the current fit's vertices, metres, prediction frame. rest_vertices: (V, 3) metres.
        posed_points, canonical_points: (N, 3) metres. canonical_weight: β >= 0.
        axis_weights: (3,) per-axis weights of the posed distance (None: isotropic).
    Returns:
        (N,) int64 vertex indices.
    """
    w = np.ones(3) if axis_weights is None else np.asarray(axis_weights, dtype=np.float64)
    beta = float(canonical_weight)
    if not beta >= 0:
        raise ValueError(f"canonical_weight must be >= 0, got {canonical_weight!r}")
    verts = np.concatenate([np.asarray(posed_vertices, dtype=np.float64) * w,
                            beta * np.asarray(rest_vertices, dtype=np.float64)], 1)
    points = np.concatenate([np.asarray(posed_points, dtype=np.float64) * w,
                             beta * np.asarray(canonical_points, dtype=np.float64)], 1)
    return cKDTree(verts).query(points)[1].astype(np.int64)
