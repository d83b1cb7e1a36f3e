"""Ground-truth dual point maps by ray casting, dual point clouds, and their float16 storage.

For every pixel of a ``W x H`` image a ray from the camera centre through the pixel centre
``(u, v) = (j + 0.5, i + 0.5)`` is intersected with the posed mesh (open3d's Embree ``RaycastingScene``, all hits
per ray). The ``K`` nearest distinct hits, front to back, give:

* ``P (H, W, K, 3)`` posed points, camera frame (OpenCV), metres;
* ``Q (H, W, K, 3)`` canonical points (rest-pose frame), the same barycentric combination of the canonical
  vertices of the hit triangle;
* ``occupancy (H, W, K)`` bool; ``mask = occupancy[..., 0]``; unoccupied entries of P and Q are 0;
* ``object_depth``: camera-frame ``z`` of the centre of the posed mesh's axis-aligned bounding box taken in the
  camera frame.

Hits on one ray closer than ``1e-6 * depth`` to the previous hit are the same surface crossing reported twice
(a ray through a shared edge or vertex) and are merged. Degenerate faces (repeated indices or zero area) are
skipped. A camera that sees nothing gives all-empty maps with ``status = "empty"``.

Storage: :func:`encode_float16` stores P relative to the object depth (``P - (0, 0, object_depth)``, the
predictor's regression target) and Q as they are, both float16. float16 has a spacing of ``2**-10`` m (0.98 mm)
on ``[1, 2)`` m, so coordinates below 2 m in magnitude round-trip within 0.49 mm each (< 0.85 mm in 3D); absolute
camera-frame P at 4-8 m would have a 3.9 mm spacing, which is why P is stored relative. The encoder refuses
points beyond 2 m (use float32 for such large objects). Measured on the 2.4 m toy with cameras 3-8 m away: at most
0.68 mm in 3D (absolute camera-frame P in float16 would lose 3.9 mm).
"""
from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from bat3r_core.cameras import PinholeCamera

STATUS_OK = "ok"
STATUS_EMPTY = "empty"
DUPLICATE_HIT_RTOL = 1e-6
"""Hits on one ray whose depths differ by less than this times the depth are merged (edge/vertex double hits)."""
FLOAT16_MAX_ABS_M = 2.0
"""Largest coordinate magnitude (metres) that :func:`encode_float16` accepts: below it float16 keeps < 0.49 mm."""


@dataclass(frozen=True, eq=False)
class DualPointMaps:
    """Dual point maps of one sample; see the module docstring for frames and units.

    Attributes:
        P: (H, W, K, 3) float32, camera frame, metres. Q: (H, W, K, 3) float32, canonical frame, metres.
        occupancy: (H, W, K) bool. object_depth: float, metres.
        status: ``"ok"`` or ``"empty"``; reason: human-readable, ``""`` when ok.
    """

    P: np.ndarray
    Q: np.ndarray
    occupancy: np.ndarray
    object_depth: float
    status: str = STATUS_OK
    reason: str = ""

    @property
    def mask(self) -> np.ndarray:
        """(H, W) bool foreground mask: layer-0 occupancy."""
        return self.occupancy[..., 0]


@dataclass(frozen=True, eq=False)
class DualPointMapBatch:
    """Stacked dual point maps of ``N`` samples.

    Attributes:
        P, Q: (N, H, W, K, 3) float32. occupancy: (N, H, W, K) bool. object_depth: (N,) float32.
        status, reason: one str per sample.
    """

    P: np.ndarray
    Q: np.ndarray
    occupancy: np.ndarray
    object_depth: np.ndarray
    status: list[str]
    reason: list[str]

    @property
    def mask(self) -> np.ndarray:
        """(N, H, W) bool."""
        return self.occupancy[..., 0]


# ---------------------------------------------------------------------------------------------- inputs
def _vertices(name: str, v, expected_rows: int | None = None) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (V, 3), got {a.shape}")
    if expected_rows is not None and a.shape[0] != expected_rows:
        raise ValueError(f"{name} must have {expected_rows} rows (one per posed vertex), got {a.shape[0]}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name} must be finite; {int((~np.isfinite(a)).any(1).sum())} rows have nan/inf")
    return a


def _faces(faces, num_vertices: int) -> np.ndarray:
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"faces must have shape (F, 3), got {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        raise TypeError(f"faces must be an integer array, got dtype {f.dtype}")
    if f.size and (f.min() < 0 or f.max() >= num_vertices):
        raise ValueError(f"faces index vertices in [0, {num_vertices}), got range [{f.min()}, {f.max()}]")
    return f.astype(np.int64)


def nondegenerate_faces(vertices: np.ndarray, faces: np.ndarray, rel_area_tol: float = 1e-12) -> np.ndarray:
    """(F,) bool: faces with three distinct indices and area above ``rel_area_tol`` times the squared bounding-box
    diagonal of ``vertices`` (V, 3)."""
    f = np.asarray(faces)
    distinct = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    v = np.asarray(vertices, dtype=np.float64)
    twice_area = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    diag2 = float(np.sum((v.max(0) - v.min(0)) ** 2)) if len(v) else 0.0
    return distinct & (twice_area > 2.0 * rel_area_tol * diag2)


# ---------------------------------------------------------------------------------------------- one sample
def sorted_hits(posed_cam: np.ndarray, faces: np.ndarray, ray_dirs: np.ndarray, nthreads: int = 0
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """All distinct hits of rays from the origin, sorted by ray then depth.

    Args:
        posed_cam: (V, 3) vertices, metres, camera frame (rays start at the camera centre, the origin).
        faces: (F, 3) int, non-degenerate.
        ray_dirs: (R, 3) float32 directions with ``z = 1`` (so the ray parameter is the depth).
        nthreads: open3d threads (0 = all).
    Returns:
        ray_id (M,) int64, depth (M,) float64, face (M,) int64, barycentric uv (M, 2) float64 (weights
        ``(1 - u - v, u, v)`` of the face's vertices 0, 1, 2), rank (M,) int64 (0 = nearest hit of its ray).
    """
    import open3d as o3d  # imported here so that forked/spawned workers import it themselves

    scene = o3d.t.geometry.RaycastingScene(nthreads=nthreads)
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(posed_cam, dtype=np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)))
    rays = np.zeros((ray_dirs.shape[0], 6), dtype=np.float32)
    rays[:, 3:] = ray_dirs
    hits = scene.list_intersections(o3d.core.Tensor(rays), nthreads=nthreads)
    ray_id = hits["ray_ids"].numpy().astype(np.int64)
    depth = hits["t_hit"].numpy()
    order = np.lexsort((depth, ray_id))  # open3d groups hits by ray but leaves them unsorted within a ray
    ray_id, depth = ray_id[order], depth[order].astype(np.float64)
    face = hits["primitive_ids"].numpy()[order].astype(np.int64)
    uv = hits["primitive_uvs"].numpy()[order].astype(np.float64)
    n = ray_id.shape[0]
    same_ray = np.zeros(n, dtype=bool)
    same_ray[1:] = ray_id[1:] == ray_id[:-1]
    duplicate = same_ray.copy()
    duplicate[1:] &= (depth[1:] - depth[:-1]) <= DUPLICATE_HIT_RTOL * depth[1:]
    if duplicate.any():
        keep = ~duplicate
        ray_id, depth, face, uv = ray_id[keep], depth[keep], face[keep], uv[keep]
        n = ray_id.shape[0]
        same_ray = np.zeros(n, dtype=bool)
        same_ray[1:] = ray_id[1:] == ray_id[:-1]
    idx = np.arange(n)
    first = np.maximum.accumulate(np.where(same_ray, 0, idx)) if n else idx
    return ray_id, depth, face, uv, idx - first


def object_depth_of(posed_cam: np.ndarray) -> float:
    """Camera-frame z of the centre of the camera-frame axis-aligned bounding box of (V, 3) vertices."""
    return float(0.5 * (posed_cam[:, 2].min() + posed_cam[:, 2].max()))


def _candidate_pixels(posed_cam: np.ndarray, camera: PinholeCamera) -> np.ndarray:
    """Flat indices of the pixels whose centre lies in the projected bounding box of the vertices (V, 3),
    camera frame: no other ray can hit the mesh. All pixels when a vertex is not in front of the camera."""
    H, W = camera.height, camera.width
    z = posed_cam[:, 2]
    if z.min() <= 0:
        return np.arange(H * W)
    u = camera.fx * posed_cam[:, 0] / z + camera.cx
    v = camera.fy * posed_cam[:, 1] / z + camera.cy
    # pixel centre j + 0.5 inside [u_min, u_max], widened by 1e-3 px: open3d intersects float32 vertices, whose
    # rounding (~1e-7 relative) moves the projected box by far less than that
    tol = 1e-3
    j0 = max(int(np.ceil(u.min() - 0.5 - tol)), 0)
    j1 = min(int(np.floor(u.max() - 0.5 + tol)), W - 1)
    i0 = max(int(np.ceil(v.min() - 0.5 - tol)), 0)
    i1 = min(int(np.floor(v.max() - 0.5 + tol)), H - 1)
    if j1 < j0 or i1 < i0:
        return np.zeros(0, dtype=np.int64)
    rows, cols = np.meshgrid(np.arange(i0, i1 + 1), np.arange(j0, j1 + 1), indexing="ij")
    return (rows * W + cols).ravel()


@dataclass(frozen=True, eq=False)
class _SparseMaps:
    """The occupied entries of one sample's maps: what a worker process sends back (dense maps are ~90 % zeros)."""

    index: np.ndarray  # (M,) int64 flat index into (H * W * K)
    P: np.ndarray  # (M, 3) float32, camera frame
    Q: np.ndarray  # (M, 3) float32, canonical frame
    object_depth: float
    status: str = STATUS_OK
    reason: str = ""


def _check_layers_frame(num_layers, frame) -> None:
    if isinstance(num_layers, bool) or not isinstance(num_layers, (int, np.integer)) or num_layers < 1:
        raise ValueError(f"num_layers must be an int >= 1, got {num_layers!r}")
    if frame not in ("world", "camera"):
        raise ValueError(f"frame must be 'world' or 'camera', got {frame!r}")


def _sparse_maps(posed_vertices, canonical_vertices, faces, camera: PinholeCamera, num_layers: int, frame: str,
                 nthreads: int) -> _SparseMaps:
    if not isinstance(camera, PinholeCamera):
        raise TypeError(f"camera must be a PinholeCamera, got {type(camera).__name__}")
    _check_layers_frame(num_layers, frame)
    posed = _vertices("posed_vertices", posed_vertices)
    canon = _vertices("canonical_vertices", canonical_vertices, expected_rows=posed.shape[0])
    f = _faces(faces, posed.shape[0])
    posed_cam = camera.world_to_camera(posed) if frame == "world" else posed
    K = int(num_layers)
    depth0 = object_depth_of(posed_cam) if posed.shape[0] else 0.0
    empty = (np.zeros(0, np.int64), np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), depth0)

    f = f[nondegenerate_faces(posed_cam, f)] if f.shape[0] else f
    if f.shape[0] == 0:
        return _SparseMaps(*empty, STATUS_EMPTY, "the mesh has no non-degenerate faces")
    pixels = _candidate_pixels(posed_cam, camera)
    ray_id = np.zeros(0, np.int64)
    if pixels.size:
        dirs = camera.pixel_ray_directions().reshape(-1, 3)[pixels].astype(np.float32)
        ray_id, _, face, uv, rank = sorted_hits(posed_cam, f, dirs, nthreads)
    if ray_id.shape[0] == 0:
        return _SparseMaps(*empty, STATUS_EMPTY,
                           "no pixel ray hits the mesh (camera looking away or mesh outside the image)")
    keep = rank < K
    ray_id, face, uv, rank = pixels[ray_id[keep]], face[keep], uv[keep], rank[keep]
    w = np.empty((ray_id.shape[0], 3))
    w[:, 0] = 1.0 - uv[:, 0] - uv[:, 1]
    w[:, 1:] = uv
    tri = f[face]  # (M, 3) vertex indices
    # (M, 3 corners) weights x (M, 3 corners, 3 xyz) -> (M, 3)
    P = np.einsum("mc,mcx->mx", w, posed_cam[tri]).astype(np.float32)
    Q = np.einsum("mc,mcx->mx", w, canon[tri]).astype(np.float32)
    return _SparseMaps(ray_id * K + rank, P, Q, depth0)


def _scatter(s: _SparseMaps, P: np.ndarray, Q: np.ndarray, occ: np.ndarray) -> None:
    """Write a sample's occupied entries into its zero-initialised (H, W, K, 3) / (H, W, K) arrays."""
    P.reshape(-1, 3)[s.index] = s.P  # P, Q and occ are contiguous: reshape gives views
    Q.reshape(-1, 3)[s.index] = s.Q
    occ.reshape(-1)[s.index] = True


def dual_point_maps(posed_vertices: np.ndarray, canonical_vertices: np.ndarray, faces: np.ndarray,
                    camera: PinholeCamera, num_layers: int = 4, frame: str = "world", nthreads: int = 0
                    ) -> DualPointMaps:
    """Ground-truth dual point maps of one posed mesh seen by ``camera``.

    Args:
        posed_vertices: (V, 3) metres, in the world frame (``frame="world"``, transformed by the camera's
            extrinsics) or already in the camera frame (``frame="camera"``).
        canonical_vertices: (V, 3) metres, rest-pose frame, same vertex order.
        faces: (F, 3) int vertex indices; degenerate faces are skipped.
        camera: intrinsics and image size (``camera.width`` x ``camera.height``); extrinsics used for
            ``frame="world"``.
        num_layers: K, the number of nearest hits kept per pixel.
        nthreads: threads for open3d (0 = all; 1 inside process pools).
    Returns:
        DualPointMaps with P, Q (H, W, K, 3) float32, occupancy (H, W, K), object_depth, status and reason.
    """
    s = _sparse_maps(posed_vertices, canonical_vertices, faces, camera, num_layers, frame, nthreads)
    H, W, K = camera.height, camera.width, int(num_layers)
    P = np.zeros((H, W, K, 3), dtype=np.float32)
    Q = np.zeros((H, W, K, 3), dtype=np.float32)
    occ = np.zeros((H, W, K), dtype=bool)
    _scatter(s, P, Q, occ)
    return DualPointMaps(P, Q, occ, s.object_depth, s.status, s.reason)


# ---------------------------------------------------------------------------------------------- many samples
def _check_batch(posed_vertices, cameras) -> np.ndarray:
    posed = np.asarray(posed_vertices, dtype=np.float64)
    if posed.ndim != 3 or posed.shape[2] != 3:
        raise ValueError(f"posed_vertices must have shape (N, V, 3), got {posed.shape}")
    if len(cameras) != posed.shape[0]:
        raise ValueError(f"got {len(cameras)} cameras for {posed.shape[0]} posed meshes")
    for i, c in enumerate(cameras):
        if not isinstance(c, PinholeCamera):
            raise TypeError(f"cameras[{i}] must be a PinholeCamera, got {type(c).__name__}")
    sizes = {(c.width, c.height) for c in cameras}
    if len(sizes) > 1:
        raise ValueError(f"all cameras must share one image size, got {sorted(sizes)}")
    return posed


def _assemble(parts: list[_SparseMaps], cameras: Sequence[PinholeCamera], num_layers: int) -> DualPointMapBatch:
    n = len(parts)
    H, W = (cameras[0].height, cameras[0].width) if n else (0, 0)
    K = int(num_layers)
    P = np.zeros((n, H, W, K, 3), dtype=np.float32)
    Q = np.zeros((n, H, W, K, 3), dtype=np.float32)
    occ = np.zeros((n, H, W, K), dtype=bool)
    for i, s in enumerate(parts):
        _scatter(s, P[i], Q[i], occ[i])
    return DualPointMapBatch(P, Q, occ, np.array([s.object_depth for s in parts], dtype=np.float32),
                             [s.status for s in parts], [s.reason for s in parts])


def _sparse_chunk(posed: np.ndarray, canonical_vertices, faces, cameras, num_layers, frame, nthreads
                  ) -> list[_SparseMaps]:
    return [_sparse_maps(posed[i], canonical_vertices, faces, cameras[i], num_layers, frame, nthreads)
            for i in range(posed.shape[0])]


def dual_point_maps_batch(posed_vertices: np.ndarray, canonical_vertices: np.ndarray, faces: np.ndarray,
                          cameras: Sequence[PinholeCamera], num_layers: int = 4, frame: str = "world",
                          nthreads: int = 0) -> DualPointMapBatch:
    """Dual point maps of ``N`` samples that share topology and image size.

    Args:
        posed_vertices: (N, V, 3) metres (world or camera frame, see :func:`dual_point_maps`).
        canonical_vertices: (V, 3) metres, rest-pose frame. faces: (F, 3) int.
        cameras: N cameras with the same width and height.
    Returns:
        DualPointMapBatch with (N, ...) arrays and per-sample status/reason.
    """
    posed = _check_batch(posed_vertices, cameras)
    _check_layers_frame(num_layers, frame)
    parts = _sparse_chunk(posed, canonical_vertices, faces, list(cameras), num_layers, frame, nthreads)
    return _assemble(parts, cameras, num_layers)


def dual_point_maps_parallel(posed_vertices: np.ndarray, canonical_vertices: np.ndarray, faces: np.ndarray,
                             cameras: Sequence[PinholeCamera], num_layers: int = 4, frame: str = "world",
                             workers: int = 2, chunk_size: int = 16, mp_context: str = "spawn"
                             ) -> DualPointMapBatch:
    """:func:`dual_point_maps_batch` split into chunks of ``chunk_size`` samples over a process pool.

    Workers run open3d single-threaded and send back only the occupied entries; this process assembles the dense
    arrays. ``mp_context`` is ``"spawn"`` (safe in any parent, e.g. one that imported bpy or torch; each worker
    pays the open3d import, ~1 s) or ``"fork"`` (faster start on Linux). ``workers <= 1`` runs in this process.
    Results are in input order and identical to :func:`dual_point_maps_batch`.
    """
    posed = _check_batch(posed_vertices, cameras)
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, (int, np.integer)) or chunk_size < 1:
        raise ValueError(f"chunk_size must be an int >= 1, got {chunk_size!r}")
    if workers <= 1 or posed.shape[0] <= chunk_size:
        return dual_point_maps_batch(posed, canonical_vertices, faces, cameras, num_layers, frame,
                                     nthreads=0 if workers <= 1 else int(workers))
    canon = np.asarray(canonical_vertices, dtype=np.float64)
    f = np.asarray(faces)
    cams = list(cameras)
    with cf.ProcessPoolExecutor(max_workers=int(workers), mp_context=mp.get_context(mp_context)) as pool:
        futures = [pool.submit(_sparse_chunk, posed[s:s + chunk_size], canon, f, cams[s:s + chunk_size],
                               num_layers, frame, 1) for s in range(0, posed.shape[0], chunk_size)]
        parts = [p for fu in futures for p in fu.result()]
    return _assemble(parts, cams, num_layers)


# ---------------------------------------------------------------------------------------------- point clouds
@dataclass(frozen=True, eq=False)
class DualPointCloud:
    """Corresponding posed and canonical points of one image, in (row, column, layer) order.

    Attributes:
        posed_points: (N, 3) float32, camera frame, metres (as given in P).
        canonical_points: (N, 3) float32, rest-pose frame, metres.
        pixels: (N, 2) float32 pixel centres ``(u, v)``.
        layers: (N,) int64 layer index (0 = front).
        occupancy: (N,) float32 occupancy (probability, or 1 for boolean maps).
        confidence: (N,) float32 confidence ``C = 1 + exp(c)``, or ``None`` when none was given.
    """

    posed_points: np.ndarray
    canonical_points: np.ndarray
    pixels: np.ndarray
    layers: np.ndarray
    occupancy: np.ndarray
    confidence: np.ndarray | None


def dual_point_cloud(P: np.ndarray, Q: np.ndarray, occupancy: np.ndarray, confidence: np.ndarray | None = None,
                     min_occupancy: float = 0.5, min_confidence: float = 2.0) -> DualPointCloud:
    """Dual point maps -> dual point cloud with the reference inference filters.

    Keeps entries with ``occupancy > min_occupancy`` and, when ``confidence`` is given,
    ``C = 1 + exp(c) >= min_confidence`` (reference: 0.5 and 2, i.e. ``c >= 0``).

    Args:
        P, Q: (H, W, K, 3) posed (camera frame) and canonical points, metres.
        occupancy: (H, W, K) bool (ground truth) or occupancy *probabilities* in [0, 1] (apply the sigmoid to
            the network's occupancy logit first).
        confidence: (H, W, K) the network's raw confidence output ``c`` (unbounded, a log-scale value; the
            confidence is ``C = 1 + exp(c)``), or ``None``.
    """
    P = np.asarray(P)
    Q = np.asarray(Q)
    if P.ndim != 4 or P.shape[-1] != 3:
        raise ValueError(f"P must have shape (H, W, K, 3), got {P.shape}")
    if Q.shape != P.shape:
        raise ValueError(f"Q must have the shape of P {P.shape}, got {Q.shape}")
    occ = np.asarray(occupancy)
    if occ.shape != P.shape[:3]:
        raise ValueError(f"occupancy must have shape {P.shape[:3]}, got {occ.shape}")
    occ = occ.astype(np.float32)
    if occ.size and (np.nanmin(occ) < 0 or np.nanmax(occ) > 1 or np.isnan(occ).any()):
        raise ValueError("occupancy must be bool or probabilities in [0, 1] (apply a sigmoid to logits first)")
    keep = occ > min_occupancy
    conf = None
    if confidence is not None:
        c = np.asarray(confidence, dtype=np.float64)
        if c.shape != P.shape[:3]:
            raise ValueError(f"confidence must have shape {P.shape[:3]}, got {c.shape}")
        with np.errstate(over="ignore"):
            conf = 1.0 + np.exp(c)
        keep &= conf >= min_confidence
    rows, cols, layers = np.nonzero(keep)
    pixels = np.stack([cols + 0.5, rows + 0.5], axis=1).astype(np.float32)
    return DualPointCloud(posed_points=P[keep].astype(np.float32), canonical_points=Q[keep].astype(np.float32),
                          pixels=pixels, layers=layers.astype(np.int64), occupancy=occ[keep],
                          confidence=None if conf is None else conf[keep].astype(np.float32))


# ---------------------------------------------------------------------------------------------- storage
def storage_dtype(canonical_vertices: np.ndarray, max_scale: float = 1.0) -> type:
    """The on-disk dtype of P/Q for a rig: float16 when every canonical coordinate (and the posed extent about
    the object depth, at most the rig's extent times ``max_scale``) stays below :data:`FLOAT16_MAX_ABS_M`, where
    float16 keeps the round trip under 0.49 mm per coordinate; float32 otherwise (large animals, off-centre
    canonical frames). Decoding handles both."""
    v = np.asarray(canonical_vertices, dtype=np.float64)
    extent = float(np.linalg.norm(np.ptp(v, axis=0))) * max_scale
    fits = float(np.abs(v).max()) < 0.98 * FLOAT16_MAX_ABS_M and extent < 0.98 * FLOAT16_MAX_ABS_M * 2
    return np.float16 if fits else np.float32


def encode_float16(P: np.ndarray, Q: np.ndarray, occupancy: np.ndarray, object_depth: np.ndarray | float,
                   dtype: type = np.float16) -> tuple[np.ndarray, np.ndarray]:
    """Compact storage of dual point maps: P relative to the object depth, Q as is.

    Args:
        P, Q: (..., H, W, K, 3) metres; occupancy: (..., H, W, K) bool; object_depth: (...) metres.
        dtype: ``np.float16`` (default) or ``np.float32`` (see :func:`storage_dtype`).
    Returns:
        ``(P_rel, Q)`` of ``dtype`` with ``P_rel = P - (0, 0, object_depth)`` on occupied entries and 0 elsewhere.
    Raises:
        ValueError if ``dtype`` is float16 and an occupied coordinate of ``P_rel`` or ``Q`` reaches
        :data:`FLOAT16_MAX_ABS_M` (float16 would lose more than 0.49 mm there: store float32 instead).
    """
    if dtype not in (np.float16, np.float32):
        raise ValueError(f"dtype must be np.float16 or np.float32, got {dtype!r}")
    P = np.asarray(P, dtype=np.float64)
    Q = np.asarray(Q, dtype=np.float64)
    occ = np.asarray(occupancy, dtype=bool)
    if P.shape != Q.shape or P.shape[-1] != 3 or occ.shape != P.shape[:-1]:
        raise ValueError(f"P, Q must be (..., H, W, K, 3) and occupancy (..., H, W, K); got {P.shape}, {Q.shape}, "
                         f"{occ.shape}")
    d = np.asarray(object_depth, dtype=np.float64)
    if d.shape != P.shape[:-4]:
        raise ValueError(f"object_depth must have shape {P.shape[:-4]}, got {d.shape}")
    rel = P.copy()
    rel[..., 2] -= d[..., None, None, None]
    rel[~occ] = 0.0
    Qz = np.where(occ[..., None], Q, 0.0)
    if dtype is np.float32:
        return rel.astype(np.float32), Qz.astype(np.float32)
    for name, a in (("P - object_depth", rel), ("Q", Qz)):
        worst = float(np.abs(a).max()) if a.size else 0.0
        if worst >= FLOAT16_MAX_ABS_M:
            raise ValueError(f"{name} reaches {worst:.3f} m >= {FLOAT16_MAX_ABS_M} m: float16 would lose > 0.49 mm; "
                             "store float32 for this object")
    return rel.astype(np.float16), Qz.astype(np.float16)


def decode_float16(P16: np.ndarray, Q16: np.ndarray, occupancy: np.ndarray, object_depth: np.ndarray | float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`encode_float16`: float32 ``P`` (camera frame) and ``Q``; unoccupied entries are 0."""
    occ = np.asarray(occupancy, dtype=bool)
    P = np.asarray(P16, dtype=np.float32).copy()
    Q = np.asarray(Q16, dtype=np.float32).copy()
    d = np.asarray(object_depth, dtype=np.float32)
    if P.shape != Q.shape or occ.shape != P.shape[:-1] or d.shape != P.shape[:-4]:
        raise ValueError(f"shapes do not match: P16 {P.shape}, Q16 {Q.shape}, occupancy {occ.shape}, "
                         f"object_depth {d.shape}")
    P[..., 2] += d[..., None, None, None]
    P[~occ] = 0.0
    Q[~occ] = 0.0
    return P, Q
