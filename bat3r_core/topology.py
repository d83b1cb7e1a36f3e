"""Mesh topology of rigged assets: welding split vertices, and the operations that split or refine a rig.

Third-party rigged meshes rarely share vertices the way the surface does: exporters split a vertex wherever its
UVs or normals differ (a UV seam, a hard edge), and flat-shaded or unindexed exports give every triangle its own
three vertices. Anything that needs the surface's connectivity (geodesics, edge graphs, decimation, repulsion)
must run on the *welded* mesh, where vertices at the same position are one vertex.

* :func:`weld_vertices` / :func:`weld_rig` merge vertices closer than a tolerance (relative to the mesh extent)
  and keep the mapping (:class:`Welding`) between the file's vertices and the welded ones.
* :func:`split_rig` duplicates vertices along the borders of face groups (what a UV-chart export does) and
  :func:`subdivide_rig` refines a rig by midpoint subdivision with interpolated skin weights; they build the
  seam-split and high-resolution assets the fitting tests and benchmark use.

Units: metres (positions and tolerances), as everywhere in bat3r.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .rig import Rig

__all__ = ["Welding", "weld_vertices", "weld_rig", "split_rig", "subdivide_rig", "DEFAULT_RELATIVE_TOLERANCE"]

DEFAULT_RELATIVE_TOLERANCE = 1e-6
"""Default weld tolerance as a fraction of the mesh extent (the longest side of its bounding box)."""


@dataclass(frozen=True, eq=False)
class Welding:
    """The welded mesh of a file mesh and the mapping between their vertices.

    Attributes:
        welded_of: (V,) int64, the welded vertex of every file vertex.
        vertices: (Vw, 3) float64 metres, each welded vertex at the position of its representative (its file
            vertices are within the tolerance of each other; exact copies weld to bit-identical positions).
        faces: (Fw, 3) int64 the file's faces re-indexed to welded vertices; faces that became degenerate (two
            corners on one welded vertex) are dropped.
        face_source: (Fw,) int64 the file face each welded face comes from.
        representative: (Vw,) int64 one file vertex of every welded vertex (the lowest file index), so
            ``file_values[representative]`` reads a per-file-vertex array in welded order. Welded vertices are
            numbered in lexicographic order of their positions (x, then y, then z): the welded mesh depends on the
            surface only, not on how the file numbers or splits its vertices (a seam-split or unindexed export
            welds to the same arrays, and shares its geodesics cache entry, as the indexed mesh).
        tolerance: metres; file vertices closer than this (and chains of such pairs) were merged.
        num_file_faces: F, the number of faces of the file mesh.
    """

    welded_of: np.ndarray
    vertices: np.ndarray
    faces: np.ndarray
    face_source: np.ndarray
    representative: np.ndarray
    tolerance: float
    num_file_faces: int

    @property
    def num_file_vertices(self) -> int:
        return int(self.welded_of.shape[0])

    @property
    def num_vertices(self) -> int:
        """Vw, the number of welded vertices."""
        return int(self.vertices.shape[0])

    @property
    def multiplicity(self) -> np.ndarray:
        """(Vw,) int64, how many file vertices each welded vertex merges."""
        return np.bincount(self.welded_of, minlength=self.num_vertices).astype(np.int64)

    @property
    def merges_nothing(self) -> bool:
        """True when no vertices were merged and no face dropped (the file mesh was welded already; the welded
        numbering may still differ from the file's)."""
        return self.num_vertices == self.num_file_vertices and len(self.face_source) == self.num_file_faces


def _check_vertices_faces(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise ValueError(f"vertices must have shape (V, 3) with V > 0, got {v.shape}")
    if not np.isfinite(v).all():
        raise ValueError("vertices must be finite")
    if f.ndim != 2 or f.shape[1] != 3 or (f.size and not np.issubdtype(f.dtype, np.integer)):
        raise ValueError(f"faces must be an integer array of shape (F, 3), got {f.dtype} {f.shape}")
    f = f.astype(np.int64)
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError(f"faces index vertices outside [0, {len(v)}): range [{f.min()}, {f.max()}]")
    return v, f


def _tolerance(v: np.ndarray, relative_tolerance: float, tolerance: float | None) -> float:
    if tolerance is not None:
        if isinstance(tolerance, bool) or not np.isfinite(tolerance) or tolerance < 0:
            raise ValueError(f"tolerance must be a finite number >= 0 (metres) or None, got {tolerance!r}")
        return float(tolerance)
    if isinstance(relative_tolerance, bool) or not np.isfinite(relative_tolerance) or relative_tolerance < 0:
        raise ValueError(f"relative_tolerance must be a finite number >= 0, got {relative_tolerance!r}")
    return float(relative_tolerance) * float(np.ptp(v, axis=0).max())


def weld_vertices(vertices: np.ndarray, faces: np.ndarray, relative_tolerance: float = DEFAULT_RELATIVE_TOLERANCE,
                  tolerance: float | None = None) -> Welding:
    """Merge vertices that share a position.

    Two vertices are merged when they are at most the tolerance apart; merging is transitive (the welded vertices
    are the connected components of the "closer than the tolerance" graph). Vertices no face uses are kept.

    Args:
        vertices: (V, 3) metres. faces: (F, 3) int indices into ``vertices``.
        relative_tolerance: tolerance as a fraction of the mesh extent (longest bounding-box side), >= 0; 0 merges
            exact duplicates only.
        tolerance: absolute tolerance in metres, overriding ``relative_tolerance`` when given.
    Returns:
        :class:`Welding`.
    """
    v, f = _check_vertices_faces(vertices, faces)
    tol = _tolerance(v, relative_tolerance, tolerance)
    n = len(v)
    pairs = cKDTree(v).query_pairs(tol, output_type="ndarray")  # every pair at distance <= tol
    if len(pairs):
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        _, label = connected_components(graph, directed=False)
    else:
        label = np.arange(n)
    # representative: the lowest file vertex of each component; welded vertices are numbered in lexicographic
    # order of the representatives' positions, so the welded mesh does not depend on the file's vertex numbering
    first = np.full(label.max() + 1, n, dtype=np.int64)
    np.minimum.at(first, label, np.arange(n))
    order = np.lexsort((first, v[first, 2], v[first, 1], v[first, 0]))  # x first, then y, z
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    welded_of = rank[label].astype(np.int64)
    representative = first[order].astype(np.int64)
    welded = v[representative]
    wf = welded_of[f] if len(f) else np.zeros((0, 3), dtype=np.int64)
    keep = (wf[:, 0] != wf[:, 1]) & (wf[:, 1] != wf[:, 2]) & (wf[:, 2] != wf[:, 0])
    return Welding(welded_of=welded_of, vertices=welded, faces=np.ascontiguousarray(wf[keep]),
                   face_source=np.flatnonzero(keep).astype(np.int64), representative=representative, tolerance=tol,
                   num_file_faces=int(len(f)))


def weld_rig(rig: Rig, relative_tolerance: float = DEFAULT_RELATIVE_TOLERANCE,
             tolerance: float | None = None) -> tuple[Rig, Welding]:
    """The rig on its welded mesh (see :func:`weld_vertices`) and the welding.

    The welded rig keeps the skeleton (joints, parents, rest transforms, left/right pairs) and the name; its rest
    vertices and faces are the welding's; the skin weights of a welded vertex are the mean of its file vertices'
    weights, renormalised to sum to 1; it has no UVs (a welded vertex on a seam has several).

    Args:
        rig: the file rig. relative_tolerance, tolerance: as in :func:`weld_vertices`.
    Returns:
        (welded rig, :class:`Welding`).
    """
    if not isinstance(rig, Rig):
        raise TypeError(f"rig must be a bat3r_core.rig.Rig, got {type(rig).__name__}")
    welding = weld_vertices(rig.rest_vertices, rig.faces, relative_tolerance, tolerance)
    w = np.zeros((welding.num_vertices, rig.num_joints))
    np.add.at(w, welding.welded_of, rig.skin_weights)
    w /= w.sum(1, keepdims=True)
    welded = Rig(name=rig.name, rest_vertices=welding.vertices, faces=welding.faces, joint_names=rig.joint_names,
                 parents=rig.parents, rest_transforms=rig.rest_transforms, skin_weights=w, uvs=None,
                 left_right_pairs=rig.left_right_pairs)
    return welded, welding


def split_rig(rig: Rig, face_groups: np.ndarray) -> Rig:
    """Duplicate the vertices shared by faces of different groups (a UV-chart export, inverse of welding).

    Every vertex gets one copy per distinct group among the faces that use it (copies keep its position, skin
    weights and UVs); a vertex no face uses is kept once. Copies are numbered by (original vertex, group), so the
    copies of a vertex are consecutive. ``face_groups = np.arange(F)`` gives every face its own three vertices.

    Args:
        rig: the rig to split. face_groups: (F,) int group of every face.
    Returns:
        The split rig (same faces in the same order, re-indexed).
    """
    if not isinstance(rig, Rig):
        raise TypeError(f"rig must be a bat3r_core.rig.Rig, got {type(rig).__name__}")
    g = np.asarray(face_groups)
    if g.shape != (len(rig.faces),) or (g.size and not np.issubdtype(g.dtype, np.integer)):
        raise ValueError(f"face_groups must be an integer array of shape (F={len(rig.faces)},), got {g.dtype} "
                         f"{g.shape}")
    g = g.astype(np.int64)
    corner_vertex = rig.faces.reshape(-1)
    corner_group = np.repeat(g, 3) - (g.min() if g.size else 0)  # groups >= 0
    unused = np.setdiff1d(np.arange(rig.num_vertices), corner_vertex)
    span = int(corner_group.max()) + 2 if corner_group.size else 1
    key = np.concatenate([corner_vertex * span + corner_group + 1, unused * span])  # unused vertices: group slot 0
    uniq, inverse = np.unique(key, return_inverse=True)
    source = uniq // span
    faces = inverse[:len(corner_vertex)].reshape(-1, 3)
    return Rig(name=rig.name, rest_vertices=rig.rest_vertices[source], faces=faces, joint_names=rig.joint_names,
               parents=rig.parents, rest_transforms=rig.rest_transforms, skin_weights=rig.skin_weights[source],
               uvs=None if rig.uvs is None else rig.uvs[source], left_right_pairs=rig.left_right_pairs)


def subdivide_rig(rig: Rig) -> Rig:
    """One level of midpoint subdivision: every triangle becomes four, with a new vertex at the midpoint of every
    edge whose skin weights (and UVs) are the mean of the edge's two ends. The surface is unchanged at rest.

    The original vertices keep their indices; edge midpoints follow (V + E vertices, 4F faces, same winding).
    """
    if not isinstance(rig, Rig):
        raise TypeError(f"rig must be a bat3r_core.rig.Rig, got {type(rig).__name__}")
    f = rig.faces
    n = rig.num_vertices
    corner_edges = np.sort(np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], 1), axis=2)  # (F, 3, 2)
    edges, edge_of = np.unique(corner_edges.reshape(-1, 2), axis=0, return_inverse=True)
    mid = n + edge_of.reshape(-1, 3)  # (F, 3): midpoints of edges (a, b), (b, c), (c, a)
    a, b, c = f[:, 0], f[:, 1], f[:, 2]
    ab, bc, ca = mid[:, 0], mid[:, 1], mid[:, 2]
    faces = np.concatenate([np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1), np.stack([ca, bc, c], 1),
                            np.stack([ab, bc, ca], 1)])

    def extend(x: np.ndarray) -> np.ndarray:
        return np.concatenate([x, 0.5 * (x[edges[:, 0]] + x[edges[:, 1]])])

    w = extend(rig.skin_weights)
    return Rig(name=rig.name, rest_vertices=extend(rig.rest_vertices), faces=faces, joint_names=rig.joint_names,
               parents=rig.parents, rest_transforms=rig.rest_transforms, skin_weights=w / w.sum(1, keepdims=True),
               uvs=None if rig.uvs is None else extend(rig.uvs), left_right_pairs=rig.left_right_pairs)
