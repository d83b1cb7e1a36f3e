"""Topology-aware farthest point sampling of control points under the paper's surface metric.

For predicted canonical points ``q_n`` with assigned vertices ``j*(n)`` the distance is the path from one point to
the mesh, along the surface, and off the mesh again:

    D(q_n, q_m) = ‖q_n − v_j*(n)‖ + d_geo(v_j*(n), v_j*(m)) + ‖v_j*(m) − q_m‖

Farthest point sampling starts at a random point (seeded) and repeatedly adds the point whose D to the selected set
is largest. Only geodesic distances from the selected vertices are read, so a step costs O(N). ``d_geo`` comes from
any geodesic object of :mod:`.geodesics` (fitting passes the welded mesh's
:class:`~.geodesics.LandmarkGeodesics`; tests pass a :class:`~.geodesics.DenseGeodesics` matrix).
"""
from __future__ import annotations

import numpy as np

__all__ = ["surface_distance", "farthest_point_sampling"]


def surface_distance(offsets: np.ndarray, vertices: np.ndarray, geodesics, n: int, m: int) -> float:
    """D(q_n, q_m) for points with ``offsets`` (N,) ``‖q − v_j*‖`` (metres) and assigned ``vertices`` (N,) int;
    ``geodesics`` a geodesic object (``pair_distances``). The slow, obvious form used by tests."""
    d = geodesics.pair_distances(np.array([vertices[n]]), np.array([vertices[m]]))[0]
    return float(offsets[n] + d + offsets[m])


def farthest_point_sampling(offsets: np.ndarray, vertices: np.ndarray, geodesics, num_samples: int,
                            rng: np.random.Generator) -> np.ndarray:
    """Indices of ``min(num_samples, N)`` control points chosen by FPS under D.

    Args:
        offsets: (N,) metres, distance of each predicted canonical point to its assigned vertex.
        vertices: (N,) int, the assigned canonical vertex ``j*(n)``.
        geodesics: geodesic distances between canonical vertices, metres: an object with
            ``distance_rows(targets)`` (:class:`~.geodesics.LandmarkGeodesics`,
            :class:`~.geodesics.DenseGeodesics`, ...).
        num_samples: number of control points wanted (>= 1).
        rng: start-point generator (the first point is uniform over the N points).
    Returns:
        (min(num_samples, N),) int64 indices into the N points, in selection order, distinct.
    """
    off = np.asarray(offsets, dtype=np.float64)
    vert = np.asarray(vertices, dtype=np.int64)
    if off.ndim != 1 or vert.shape != off.shape:
        raise ValueError(f"offsets and vertices must both have shape (N,), got {off.shape} and {vert.shape}")
    if isinstance(num_samples, bool) or not isinstance(num_samples, (int, np.integer)) or num_samples < 1:
        raise ValueError(f"num_samples must be an int >= 1, got {num_samples!r}")
    if not callable(getattr(geodesics, "distance_rows", None)):
        raise TypeError("geodesics must be a geodesic object with distance_rows(targets) (e.g. "
                        f"fitting.geodesics.LandmarkGeodesics or DenseGeodesics), got {type(geodesics).__name__}")
    n = len(off)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    k = min(int(num_samples), n)
    chosen = np.empty(k, dtype=np.int64)
    chosen[0] = int(rng.integers(n))
    geo_from = geodesics.distance_rows(vert)  # source vertex -> (N,) geodesic distances to every point's vertex
    best = np.full(n, np.inf)
    for s in range(1, k):
        c = chosen[s - 1]
        # (N,) D from the last chosen point to every point
        d = off[c] + geo_from(vert[c]) + off
        np.minimum(best, d, out=best)
        best[chosen[:s]] = -np.inf
        chosen[s] = int(np.argmax(best))
    return chosen
