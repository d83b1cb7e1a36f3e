"""Geodesic distances on a canonical mesh for fitting, in memory linear in the vertex count, cached per mesh.

**Graph.** Shortest paths (Dijkstra, ``scipy.sparse.csgraph.dijkstra``) on a graph over the mesh vertices.
``graph="edges"`` uses the mesh edges only (the shortest *edge path*; it over-estimates the surface geodesic
because paths zig-zag along edges). ``graph="edges_and_diagonals"`` (default) also links, across every interior
edge, the two vertices opposite it in its two triangles, weighted by their straight distance: paths may then cut
across pairs of triangles, which removes most of the zig-zag excess. Fitting runs on the *welded* mesh
(:mod:`bat3r_core.topology`): on a mesh split at UV seams the graph would be cut along every seam.

**Landmark geodesics** (:class:`LandmarkGeodesics`, what fitting's farthest point sampling reads): ``L``
landmarks chosen by farthest point sampling under the graph metric itself, one exact Dijkstra row from each,
``(L, V)`` float32. ``d(a, b)`` is estimated through the landmarks nearest to its two ends,
``min(d(a, l_a) + d(l_a, b), d(b, l_b) + d(l_b, a))`` — an upper bound of the graph distance, exact when ``a`` or
``b`` is a landmark, and exact everywhere when ``V <= L`` (every vertex is a landmark). Memory ``2 · L · V``
float32 (the rows and their transpose).

**Exact blocks** (:func:`load_or_compute_geodesic_block`, what the repulsion term reads): exact distances among a
bounded set of vertices (the regulariser proxy's), from Dijkstra rows of those vertices only, computed in chunks
(working memory ``chunk · V``), stored ``(S, S)``.

:func:`geodesic_distances` (all pairs, ``V × V``) is the quadratic reference the approximation is measured
against (tests, ``docs/fitting.md``); fitting never calls it. Both cached kinds are written atomically to
``<cache_dir>/geodesic-<kind>-<hash>.npz`` where the hash covers the vertex coordinates, the faces, the graph kind
and the method's parameters.

Every geodesic object here offers ``distances_from(source, targets)``, ``distance_rows(targets)`` (the same as a
function of the source, per-target lookups done once) and ``pair_distances(a, b)`` (metres, float64) and
``num_vertices``; farthest point sampling and the repulsion pairs take any of them.
"""
from __future__ import annotations

import dataclasses
import hashlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import dijkstra

from bat3r_core.shards import atomic_write

__all__ = ["mesh_hash", "geodesic_distances", "geodesic_rows", "DenseGeodesics", "LandmarkGeodesics",
           "SubsetGeodesics", "landmark_geodesics", "load_or_compute_landmark_geodesics",
           "load_or_compute_geodesic_block", "default_cache_dir", "DEFAULT_LANDMARKS"]

GraphKind = Literal["edges", "edges_and_diagonals"]
DEFAULT_LANDMARKS = 512
_LANDMARK_METHOD = "fps-from-vertex-0/v1"


def default_cache_dir() -> Path:
    """``$BAT3R_CACHE/geodesics`` or ``~/.cache/bat3r/geodesics``."""
    root = os.environ.get("BAT3R_CACHE") or os.path.join(os.path.expanduser("~"), ".cache", "bat3r")
    return Path(root) / "geodesics"


def _check_mesh(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise ValueError(f"vertices must have shape (V, 3) with V > 0, got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces must be an integer array of shape (F, 3), got {f.dtype} {f.shape}")
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError(f"faces index vertices outside [0, {len(v)}): range [{f.min()}, {f.max()}]")
    return v, f.astype(np.int64)


def _check_graph(graph: str) -> None:
    if graph not in ("edges", "edges_and_diagonals"):
        raise ValueError(f"graph must be 'edges' or 'edges_and_diagonals', got {graph!r}")


def mesh_hash(vertices: np.ndarray, faces: np.ndarray, graph: str = "edges_and_diagonals", params: str = "") -> str:
    """SHA-256 (16 hex chars) of the float64 vertices, int64 faces, the graph kind and ``params`` (the method's
    parameters as text)."""
    v, f = _check_mesh(vertices, faces)
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(v).tobytes())
    h.update(np.ascontiguousarray(f).tobytes())
    h.update(graph.encode())
    h.update(params.encode())
    return h.hexdigest()[:16]


def _graph_pairs(v: np.ndarray, f: np.ndarray, graph: str) -> tuple[np.ndarray, np.ndarray]:
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])  # (3F, 2), one per face corner
    opposite = np.concatenate([f[:, 2], f[:, 0], f[:, 1]])  # (3F,) vertex opposite each face edge
    pairs = [np.sort(edges, axis=1)]
    if graph == "edges_and_diagonals":
        key = np.sort(edges, axis=1)
        order = np.lexsort((key[:, 1], key[:, 0]))
        key, opp = key[order], opposite[order]
        same = (key[1:] == key[:-1]).all(1)  # consecutive corners sharing an edge: its two triangles
        a, b = opp[:-1][same], opp[1:][same]
        ok = a != b
        pairs.append(np.sort(np.stack([a[ok], b[ok]], 1), axis=1))
    p = np.unique(np.concatenate(pairs), axis=0) if len(f) else np.zeros((0, 2), dtype=np.int64)
    p = p[p[:, 0] != p[:, 1]]
    return p[:, 0], p[:, 1]


def _adjacency(v: np.ndarray, f: np.ndarray, graph: str) -> csr_matrix:
    """Symmetric (V, V) sparse graph, metres (both directions stored, so Dijkstra runs with ``directed=True``)."""
    i, j = _graph_pairs(v, f, graph)
    w = np.linalg.norm(v[i] - v[j], axis=1)
    n = len(v)
    return coo_matrix((np.concatenate([w, w]), (np.concatenate([i, j]), np.concatenate([j, i]))),
                      shape=(n, n)).tocsr()


def geodesic_distances(vertices: np.ndarray, faces: np.ndarray, graph: GraphKind = "edges_and_diagonals",
                       chunk: int = 512) -> np.ndarray:
    """All-pairs geodesic distances on the mesh: the quadratic **reference** (tests, error measurements).

    Args:
        vertices: (V, 3) metres. faces: (F, 3) int.
        graph: ``"edges"`` or ``"edges_and_diagonals"`` (see the module docstring).
        chunk: sources per Dijkstra call (bounds the float64 working memory to ``chunk * V``).
    Returns:
        (V, V) float32, metres; ``inf`` between disconnected components.
    """
    _check_graph(graph)
    v, f = _check_mesh(vertices, faces)
    return geodesic_rows(v, f, np.arange(len(v)), graph=graph, chunk=chunk)


def geodesic_rows(vertices: np.ndarray, faces: np.ndarray, sources: np.ndarray, targets: np.ndarray | None = None,
                  graph: GraphKind = "edges_and_diagonals", chunk: int = 64) -> np.ndarray:
    """Exact geodesic distances from ``sources`` to ``targets`` (Dijkstra rows of the sources only).

    Args:
        vertices: (V, 3) metres. faces: (F, 3) int. sources: (S,) int vertex indices.
        targets: (T,) int vertex indices, or None for all V vertices.
        chunk: sources per Dijkstra call; the working memory is ``chunk * V`` float64.
    Returns:
        (S, T) float32 metres (``inf`` between disconnected components).
    """
    _check_graph(graph)
    v, f = _check_mesh(vertices, faces)
    src = _check_indices("sources", sources, len(v))
    tgt = None if targets is None else _check_indices("targets", targets, len(v))
    if isinstance(chunk, bool) or not isinstance(chunk, (int, np.integer)) or chunk < 1:
        raise ValueError(f"chunk must be an int >= 1, got {chunk!r}")
    adj = _adjacency(v, f, graph)
    out = np.empty((len(src), len(v) if tgt is None else len(tgt)), dtype=np.float32)
    for s in range(0, len(src), chunk):
        d = dijkstra(adj, directed=True, indices=src[s:s + chunk])
        out[s:s + chunk] = d if tgt is None else d[:, tgt]
    return out


def _check_indices(name: str, idx, n: int) -> np.ndarray:
    a = np.asarray(idx)
    if a.ndim != 1 or (a.size and not np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"{name} must be a 1-D integer array of vertex indices, got {a.dtype} {a.shape}")
    a = a.astype(np.int64)
    if a.size and (a.min() < 0 or a.max() >= n):
        raise ValueError(f"{name} index vertices outside [0, {n}): range [{a.min()}, {a.max()}]")
    return a


class DenseGeodesics:
    """Geodesic distances given as a square matrix (exact blocks, small meshes, tests).

    Args:
        matrix: (V, V) metres, symmetric.
    """

    def __init__(self, matrix: np.ndarray):
        m = np.asarray(matrix)
        if m.ndim != 2 or m.shape[0] != m.shape[1]:
            raise ValueError(f"matrix must be a square (V, V) array, got {m.shape}")
        self.matrix = m

    @property
    def num_vertices(self) -> int:
        return int(self.matrix.shape[0])

    @property
    def nbytes(self) -> int:
        return int(self.matrix.nbytes)

    def distances_from(self, source: int, targets: np.ndarray) -> np.ndarray:
        """(N,) float64 metres from vertex ``source`` to each of ``targets`` (N,)."""
        return self.matrix[int(source), np.asarray(targets)].astype(np.float64)

    def pair_distances(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(P,) float64 metres between vertices ``a[k]`` and ``b[k]``."""
        return self.matrix[np.asarray(a), np.asarray(b)].astype(np.float64)

    def distance_rows(self, targets: np.ndarray):
        """A function ``source -> (N,) float64`` distances from ``source`` to ``targets`` (N,)."""
        t = np.asarray(targets, dtype=np.int64)
        return lambda source: self.matrix[int(source)].take(t).astype(np.float64)


@dataclass(frozen=True, eq=False)
class LandmarkGeodesics:
    """Geodesic distances through landmarks (see the module docstring); build with :func:`landmark_geodesics`.

    Attributes:
        landmarks: (L,) int64 landmark vertices, in farthest-point order (the first is vertex 0).
        rows: (L, V) float32 metres, exact graph distances from each landmark to every vertex.
        nearest: (V,) int64 index into ``landmarks`` of each vertex's nearest landmark.
        offset: (V,) float32 metres, distance of each vertex to that landmark (0 at landmarks).
        columns: (V, L) float32, ``rows`` transposed and contiguous (a vertex's distances to every landmark in
            one cache-friendly row; farthest point sampling reads one per step). Derived, not cached.
    """

    landmarks: np.ndarray
    rows: np.ndarray
    nearest: np.ndarray
    offset: np.ndarray
    columns: np.ndarray = dataclasses.field(init=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "columns", np.ascontiguousarray(self.rows.T))

    @property
    def num_vertices(self) -> int:
        return int(self.rows.shape[1])

    @property
    def num_landmarks(self) -> int:
        return int(self.rows.shape[0])

    @property
    def exact(self) -> bool:
        """Every vertex is a landmark (``V <= L``): every distance is exact."""
        return self.num_landmarks == self.num_vertices

    @property
    def nbytes(self) -> int:
        return int(self.landmarks.nbytes + self.rows.nbytes + self.columns.nbytes + self.nearest.nbytes
                   + self.offset.nbytes)

    def distances_from(self, source: int, targets: np.ndarray) -> np.ndarray:
        """(N,) float64 metres, estimated distances from vertex ``source`` to each of ``targets`` (N,)."""
        s = int(source)
        t = np.asarray(targets, dtype=np.int64)
        via_source = self.offset[s] + self.rows[self.nearest[s], t].astype(np.float64)
        via_target = self.offset[t].astype(np.float64) + self.rows[self.nearest[t], s]
        d = np.minimum(via_source, via_target)
        d[t == s] = 0.0
        return d

    def distance_rows(self, targets: np.ndarray):
        """A function ``source -> (N,) float64`` giving :meth:`distances_from` ``(source, targets)``, with the
        per-target lookups (nearest landmark, offset) done once: what farthest point sampling calls per step."""
        t = np.asarray(targets, dtype=np.int64)
        near_t, off_t = self.nearest[t], self.offset[t]

        def row(source: int) -> np.ndarray:
            s = int(source)
            via_source = self.rows[self.nearest[s]].take(t)
            via_source += self.offset[s]
            via_target = self.columns[s].take(near_t)
            via_target += off_t
            d = np.minimum(via_source, via_target).astype(np.float64)
            d[t == s] = 0.0
            return d

        return row

    def pair_distances(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(P,) float64 metres, estimated distances between vertices ``a[k]`` and ``b[k]``."""
        a = np.asarray(a, dtype=np.int64)
        b = np.asarray(b, dtype=np.int64)
        via_a = self.offset[a].astype(np.float64) + self.rows[self.nearest[a], b]
        via_b = self.offset[b].astype(np.float64) + self.rows[self.nearest[b], a]
        d = np.minimum(via_a, via_b)
        d[a == b] = 0.0
        return d


class SubsetGeodesics:
    """The geodesics of ``base`` read through a vertex map: vertex ``k`` of this object is vertex ``index[k]`` of
    ``base`` (e.g. regulariser-proxy vertices read through their nearest welded vertex).

    Args:
        base: any geodesic object of this module. index: (K,) int vertices of ``base``.
    """

    def __init__(self, base, index: np.ndarray):
        self.base = base
        self.index = _check_indices("index", index, base.num_vertices)

    @property
    def num_vertices(self) -> int:
        return int(len(self.index))

    def distances_from(self, source: int, targets: np.ndarray) -> np.ndarray:
        return self.base.distances_from(int(self.index[int(source)]), self.index[np.asarray(targets)])

    def pair_distances(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return self.base.pair_distances(self.index[np.asarray(a)], self.index[np.asarray(b)])

    def distance_rows(self, targets: np.ndarray):
        rows = self.base.distance_rows(self.index[np.asarray(targets)])
        return lambda source: rows(int(self.index[int(source)]))


def _check_landmarks(num_landmarks) -> int:
    if isinstance(num_landmarks, bool) or not isinstance(num_landmarks, (int, np.integer)) or num_landmarks < 1:
        raise ValueError(f"num_landmarks must be an int >= 1, got {num_landmarks!r}")
    return int(num_landmarks)


def landmark_geodesics(vertices: np.ndarray, faces: np.ndarray, num_landmarks: int = DEFAULT_LANDMARKS,
                       graph: GraphKind = "edges_and_diagonals") -> LandmarkGeodesics:
    """Landmark geodesics of a mesh: ``min(num_landmarks, V)`` landmarks by farthest point sampling under the
    graph metric, starting at vertex 0 (a vertex of a component no landmark reaches yet is infinitely far, so every
    component gets a landmark before any gets a second), one Dijkstra row per landmark.

    Args:
        vertices: (V, 3) metres (a welded mesh). faces: (F, 3) int. num_landmarks: L >= 1.
        graph: see the module docstring.
    Returns:
        :class:`LandmarkGeodesics`; memory ``2 · L · V`` float32 plus ``O(V)``.
    """
    _check_graph(graph)
    v, f = _check_mesh(vertices, faces)
    n = len(v)
    k_max = min(_check_landmarks(num_landmarks), n)
    adj = _adjacency(v, f, graph)
    rows = np.empty((k_max, n), dtype=np.float32)
    landmarks = np.empty(k_max, dtype=np.int64)
    best = np.full(n, np.inf)
    nearest = np.zeros(n, dtype=np.int64)
    current = 0
    for k in range(k_max):
        landmarks[k] = current
        row = dijkstra(adj, directed=True, indices=current)  # (V,) float64
        rows[k] = row
        closer = row < best
        best[closer] = row[closer]
        nearest[closer] = k
        current = int(np.argmax(best))
    return LandmarkGeodesics(landmarks=landmarks, rows=rows, nearest=nearest, offset=best.astype(np.float32))


def _cache_path(folder, kind: str, key: str) -> Path:
    return (Path(folder) if folder is not None else default_cache_dir()) / f"geodesic-{kind}-{key}.npz"


def _save_npz(path: Path, **arrays) -> None:
    def _save(tmp: str) -> None:
        with open(tmp, "wb") as fh:  # a file object: np.savez would append ".npz" to a bare name
            np.savez(fh, **arrays)

    atomic_write(path, _save)


def load_or_compute_landmark_geodesics(vertices: np.ndarray, faces: np.ndarray,
                                       cache_dir: str | os.PathLike | None = None,
                                       num_landmarks: int = DEFAULT_LANDMARKS,
                                       graph: GraphKind = "edges_and_diagonals") -> LandmarkGeodesics:
    """:func:`landmark_geodesics`, read from / written to ``cache_dir`` (default :func:`default_cache_dir`) as
    ``geodesic-landmarks-<hash>.npz`` (hash of the mesh, graph kind, landmark count and selection method). Written
    atomically (temporary name, then rename), so concurrent workers never read a partial file."""
    _check_graph(graph)
    n_l = _check_landmarks(num_landmarks)
    path = _cache_path(cache_dir, "landmarks", mesh_hash(vertices, faces, graph, f"{_LANDMARK_METHOD}/L={n_l}"))
    n = np.asarray(vertices).shape[0]
    if path.is_file():
        with np.load(path, allow_pickle=False) as z:
            got = LandmarkGeodesics(**{k: z[k] for k in ("landmarks", "rows", "nearest", "offset")})
        if got.rows.shape == (min(n_l, n), n) and got.nearest.shape == (n,):
            return got
    geo = landmark_geodesics(vertices, faces, n_l, graph)
    _save_npz(path, landmarks=geo.landmarks, rows=geo.rows, nearest=geo.nearest, offset=geo.offset)
    return geo


def load_or_compute_geodesic_block(vertices: np.ndarray, faces: np.ndarray, sources: np.ndarray,
                                   cache_dir: str | os.PathLike | None = None,
                                   graph: GraphKind = "edges_and_diagonals") -> DenseGeodesics:
    """Exact geodesics among ``sources`` (S,) vertices: a :class:`DenseGeodesics` over S "vertices" (entry
    ``[i, k]`` is the distance between ``sources[i]`` and ``sources[k]``), from Dijkstra rows of the distinct
    sources only (:func:`geodesic_rows`). Cached as ``geodesic-block-<hash>.npz`` (hash of the mesh, graph kind
    and the sources), written atomically. Memory ``S²`` float32 plus ``64 · V`` float64 while computing."""
    _check_graph(graph)
    v, f = _check_mesh(vertices, faces)
    src = _check_indices("sources", sources, len(v))
    digest = hashlib.sha256(np.ascontiguousarray(src).tobytes()).hexdigest()[:16]
    path = _cache_path(cache_dir, "block", mesh_hash(v, f, graph, f"block/{digest}"))
    if path.is_file():
        with np.load(path, allow_pickle=False) as z:
            d = z["geodesics"]
        if d.shape == (len(src), len(src)):
            return DenseGeodesics(d)
    uniq, inverse = np.unique(src, return_inverse=True)
    d = geodesic_rows(v, f, uniq, uniq, graph)[np.ix_(inverse, inverse)]
    _save_npz(path, geodesics=d)
    return DenseGeodesics(d)
