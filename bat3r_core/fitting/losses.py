"""The terms of the fitting objective (Eq. 4 of the paper), batched over instances (torch, CPU or CUDA).

Every function returns one value per instance, shape ``(B,)``. Vertices are ``(B, V, 3)`` metres. Following the
paper, the edge, volume and repulsion terms are evaluated on the *unscaled* articulated mesh (bone scales at 1, no
global similarity: they are invariant to rigid motion, and the global scale would otherwise shrink the mesh to
cheat them); the data term on the scaled articulated mesh after the global similarity.

Speed: for rigs with more vertices than ``FittingConfig.regulariser_max_vertices`` the edge, volume and repulsion
terms run on a quadric-decimated proxy of the rest mesh (:func:`regulariser_mesh`) skinned with the weights of the
nearest rig vertices; the data term and the output always use the full mesh. Fitting passes the *welded* rest mesh
(:mod:`bat3r_core.topology`), so vertices split at UV seams neither cut the edge graph nor repel each other.

Weighting as the reference weights it. The paper's λ were tuned on the authors' reference code, so every term
is normalised the way that code normalises it (Adam is invariant to the overall scale of the loss, so only the
ratios between terms matter); the checks are in docs/fitting.md ("Weighting as the reference weights it") and
``tests/core/test_fitting_losses.py`` (``test_gradient_ratios_match_the_full_mesh_reference``):

* data: **mean** over a sample's valid control points of ``Huber_δ(‖p_i − v_j*(i)‖)`` (Eq. 3 prints a sum; the
  reference averages, and a sum made every regulariser ~200× weaker than tuned).
* angle: mean over optimised joints of ``‖θ_j‖²``.
* edge: mean over mesh edges of ``(|e|² − |e_rest|²)²`` (metres⁴) on the full mesh. On a decimated proxy, whose
  edges are longer and far less uniform (toy: the mean |e_rest|⁴ is 92× the full mesh's), the term is
  ``mean_full(|e_rest|⁴) · Σ_e (a_e / A) ((|e|² − |e_rest|²) / |e_rest|²)²`` with ``a_e`` a third of the area of
  the faces bordering proxy edge e and ``A`` the area: each edge contributes ``≈ 4 ε² |e_rest|⁴`` under a smooth
  strain ε, so the full mesh's mean is ``4 mean_full|e_rest|⁴`` times the surface average of ε², which the
  area-weighted relative form estimates on the proxy. (A single ratio of fourth moments was 0.24–3× off.)
* volume: mean over the full mesh's bones of the squared **absolute** change ``(vol_b − vol_b_rest)²`` (m⁶): each
  face is assigned to the bone dominating the summed skin weights of its three vertices; a bone's volume is the
  sum of the signed tetrahedra spanned by its faces and its faces' current vertex centroid. On a proxy the sum
  over the proxy's bones is divided by the full mesh's bone count (a bone whose faces all vanished in the
  decimation would otherwise change the mean's divisor).
* repulsion: sum over candidate pairs of ``relu(r² − d²)²`` (pairs far apart geodesically, close in space). Pairs
  in contact scale with the square of the vertex density, so on a proxy the sum is multiplied by
  ``repulsion_scale = (V_full / V_proxy)²`` (1 on the full mesh).

On the full welded mesh (``regulariser_max_vertices: 0``) every |∇_θ term| / |∇_θ data| equals the slow
full-mesh reference's to 1e-4. On the default proxy they do not, and no fixed normalisation makes them: measured
on a noisy toy cloud, edge 0.86×, volume 0.54×, repulsion 0.74× the reference's ratio; over random poses the
proxy/full ratio of the edge gradient varies 0.7–1.3× and of the volume gradient 0.6–1.8× (the proxy does not
resolve the skinning blend zones where these terms live; per-bone calibration did not help). With the paper's λ
the edge and volume gradients are ~0.1 % of the data term's at that pose.
* scale: mean over left/right pairs of ``(log s_L − log s_R)²`` plus mean over joints of ``(log s_j)²``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

__all__ = ["MeshRegularisers", "data_term", "angle_term", "edge_term", "volume_term", "repulsion_term",
           "scale_term", "find_repulsion_pairs", "huber", "RegulariserMesh", "regulariser_mesh", "wrap_axis_angle"]


def huber(x: torch.Tensor, delta: float) -> torch.Tensor:
    """Elementwise Huber of non-negative distances ``x``: ``x²/2`` below ``delta``, ``δ (x − δ/2)`` above."""
    return torch.where(x <= delta, 0.5 * x * x, delta * (x - 0.5 * delta))


def data_term(posed: torch.Tensor, targets: torch.Tensor, mask: torch.Tensor, delta: float) -> torch.Tensor:
    """Huber data term.

    Args:
        posed: (B, N, 3) articulated mesh vertices at the control points' assigned vertices, metres.
        targets: (B, N, 3) predicted posed points, same frame.
        mask: (B, N) bool/float, 1 for real control points, 0 for padding.
    Returns:
        (B,) mean over valid points of Huber(‖p − v‖) (0 for an instance without valid points).
    """
    d2 = ((posed - targets) ** 2).sum(-1)
    d = torch.sqrt(d2 + 1e-18)  # smooth at zero
    m = mask.to(posed.dtype)
    return (huber(d, delta) * m).sum(-1) / m.sum(-1).clamp(min=1.0)


def angle_term(excess_rotations: torch.Tensor, joint_mask: torch.Tensor | None = None) -> torch.Tensor:
    """(B,) mean over (masked) joints of ``‖θ_j‖²``.

    Args:
        excess_rotations: (B, J, 3) radians. joint_mask: (J,) 1 for optimised joints, or None for all.
    """
    sq = (excess_rotations ** 2).sum(-1)  # (B, J)
    if joint_mask is None:
        return sq.mean(-1)
    m = joint_mask.to(sq.dtype)
    return (sq * m).sum(-1) / m.sum().clamp(min=1.0)


def wrap_axis_angle(theta: torch.Tensor) -> torch.Tensor:
    """``(..., 3)`` axis-angle vectors wrapped to angles ``≤ π``, the same rotations: an angle ``α > π`` about
    the unit axis ``a`` becomes ``α − 2πk ∈ [−π, π)`` about ``a``; vectors with ``α ≤ π`` are returned unchanged."""
    n = theta.norm(dim=-1, keepdim=True)
    wrapped = torch.remainder(n + torch.pi, 2.0 * torch.pi) - torch.pi  # in [-π, π), the same rotation about a
    return torch.where(n > torch.pi, theta * (wrapped / n.clamp(min=torch.pi)), theta)


def scale_term(bone_scales: torch.Tensor, pairs: torch.Tensor) -> torch.Tensor:
    """(B,) bone-scale symmetry + deviation. ``bone_scales`` (B, J) > 0; ``pairs`` (P, 2) int (left, right)."""
    log_s = torch.log(bone_scales)
    dev = (log_s ** 2).mean(-1)
    if pairs.numel() == 0:
        return dev
    sym = ((log_s[:, pairs[:, 0]] - log_s[:, pairs[:, 1]]) ** 2).mean(-1)
    return sym + dev


def _vertex_major(vertices: torch.Tensor) -> torch.Tensor:
    """(B, V, 3) → (V, B*3); free when the tensor is a view of vertex-major (V, B, 3) memory, as in fitting."""
    return vertices.permute(1, 0, 2).reshape(vertices.shape[1], -1)


def _unique_edges(faces: np.ndarray, vertices: np.ndarray | None = None):
    """(E, 2) unique edges of ``faces``; with ``vertices``, also (E,) each edge's area share: a third of the area of
    each face it borders (the shares sum to the surface area)."""
    f = np.asarray(faces, dtype=np.int64)
    e, inverse = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1), axis=0,
                           return_inverse=True)
    if vertices is None:
        return e
    v = np.asarray(vertices, dtype=np.float64)
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    return e, np.bincount(inverse.ravel(), weights=np.tile(area / 3.0, 3), minlength=len(e))


def _dominant_bones(faces: np.ndarray, skin_weights: np.ndarray) -> np.ndarray:
    """(F,) joint with the largest summed skin weight over each face's corners."""
    return np.asarray(skin_weights, dtype=np.float64)[np.asarray(faces, dtype=np.int64)].sum(1).argmax(1)


def edge_term(vertices: torch.Tensor, edges: torch.Tensor, rest_sq_lengths: torch.Tensor,
              weights: torch.Tensor | None = None) -> torch.Tensor:
    """(B,) mean over edges of ``(|e|² − |e_rest|²)²``, or its weighted sum ``Σ_e w_e (|e|² − |e_rest|²)²``.

    Args:
        vertices: (B, V, 3) metres. edges: (E, 2) int vertex indices. rest_sq_lengths: (E,) m².
        weights: (E,) per-edge weights, or None for the plain mean.
    """
    b = vertices.shape[0]
    x = _vertex_major(vertices)  # row gathers of (V, B*3) are contiguous in both passes
    e = (x.index_select(0, edges[:, 0]) - x.index_select(0, edges[:, 1])).reshape(-1, b, 3)  # (E, B, 3)
    sq = ((e * e).sum(-1) - rest_sq_lengths[:, None]) ** 2  # (E, B)
    return sq.mean(0) if weights is None else weights @ sq


def _bone_volumes(vertices: torch.Tensor, faces: torch.Tensor, face_bone_onehot: torch.Tensor,
                  centroid_weights: torch.Tensor) -> torch.Tensor:
    """(B, K) signed volume of each bone's faces about the centroid of their corners.

    Args:
        vertices: (B, V, 3). faces: (F, 3).
        face_bone_onehot: (F, K) dense one-hot bone of each face (dense products beat scatter-adds on CPU).
        centroid_weights: (K, V) dense, row k averages the corners of bone k's faces.
    """
    b = vertices.shape[0]
    x = _vertex_major(vertices)  # (V, B*3)
    c = face_bone_onehot @ (centroid_weights @ x)  # (F, B*3) centroid of each face's bone
    r0, r1, r2 = ((x.index_select(0, faces[:, k]) - c).reshape(-1, b, 3) for k in range(3))
    tet = (r0 * torch.cross(r1, r2, dim=-1)).sum(-1) / 6.0  # (F, B)
    return (face_bone_onehot.T @ tet).T


def volume_term(vertices: torch.Tensor, faces: torch.Tensor, face_bone_onehot: torch.Tensor,
                centroid_weights: torch.Tensor, rest_volumes: torch.Tensor, num_bones: float | None = None
                ) -> torch.Tensor:
    """(B,) local-volume term: ``Σ_b (vol_b − vol_b_rest)² / num_bones`` (m⁶; see the module docstring).

    Args:
        vertices: (B, V, 3) metres. faces: (F, 3). face_bone_onehot: (F, K). centroid_weights: (K, V).
        rest_volumes: (K,) m³. num_bones: the divisor, the full mesh's bone count (None: K, a plain mean).
    """
    vol = _bone_volumes(vertices, faces, face_bone_onehot, centroid_weights)
    k = vol.shape[-1] if num_bones is None else num_bones
    return ((vol - rest_volumes) ** 2).sum(-1) / k


def find_repulsion_pairs(vertices: np.ndarray, geodesics, geodesic_threshold: float,
                         search_radius: float, k: int) -> np.ndarray:
    """Candidate repulsion pairs of one posed mesh.

    Pairs ``(i, j)``, ``i < j``, closer than ``search_radius`` in space and further apart than
    ``geodesic_threshold`` on the canonical surface; each vertex keeps at most its ``k`` nearest such partners.
    Geodesics are read for the spatially close pairs only.

    Args:
        vertices: (V, 3) metres (unscaled articulated mesh).
        geodesics: a geodesic object over the same V vertices with ``pair_distances(a, b)`` (metres; e.g.
            :class:`~.geodesics.DenseGeodesics`, :class:`~.geodesics.LandmarkGeodesics`).
    Returns:
        (P, 2) int64.
    """
    if not callable(getattr(geodesics, "pair_distances", None)):
        raise TypeError("geodesics must be a geodesic object with pair_distances(a, b) (e.g. "
                        f"fitting.geodesics.DenseGeodesics), got {type(geodesics).__name__}")
    if getattr(geodesics, "num_vertices", len(vertices)) != len(vertices):
        raise ValueError(f"geodesics cover {geodesics.num_vertices} vertices, vertices has {len(vertices)}")
    pairs = cKDTree(vertices).query_pairs(search_radius, output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    pairs = pairs[geodesics.pair_distances(pairs[:, 0], pairs[:, 1]) > geodesic_threshold]
    if len(pairs) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    d = np.linalg.norm(vertices[pairs[:, 0]] - vertices[pairs[:, 1]], axis=1)
    # keep, per vertex, its k nearest partners (pairs count for both ends)
    order = np.argsort(d, kind="stable")
    pairs = pairs[order]
    ends = np.concatenate([pairs[:, 0], pairs[:, 1]])
    pair_of = np.concatenate([np.arange(len(pairs))] * 2)
    o = np.argsort(ends, kind="stable")
    ends_sorted = ends[o]
    first = np.searchsorted(ends_sorted, ends_sorted, side="left")
    rank = np.arange(len(ends_sorted)) - first
    ok = np.zeros(len(pairs), dtype=bool)
    ok[pair_of[o][rank < k]] = True  # a pair survives if it is among the k nearest of either end
    return pairs[ok].astype(np.int64)


def repulsion_term(vertices: torch.Tensor, pair_batch: torch.Tensor, pairs: torch.Tensor, radius: float,
                   batch_size: int) -> torch.Tensor:
    """(B,) sum over candidate pairs of ``relu(r² − d²)²``.

    Args:
        vertices: (B, V, 3) metres. pair_batch: (P,) instance index of each pair. pairs: (P, 2) vertex indices.
    """
    out = torch.zeros(batch_size, dtype=vertices.dtype, device=vertices.device)
    if pairs.numel() == 0:
        return out
    b, v = vertices.shape[:2]
    x = _vertex_major(vertices).reshape(v * b, 3)  # row v * B + b holds vertex v of instance b
    d = x.index_select(0, pairs[:, 0] * b + pair_batch) - x.index_select(0, pairs[:, 1] * b + pair_batch)
    pen = torch.relu(radius * radius - (d * d).sum(-1)) ** 2
    return out.index_add(0, pair_batch, pen)


@dataclass(frozen=True)
class MeshRegularisers:
    """Per-asset constants of the edge and volume terms (build with :meth:`from_mesh`).

    Attributes:
        edges: (E, 2) int64 unique mesh edges. rest_sq_lengths: (E,) m².
        faces: (F, 3) int64. face_bone_onehot: (F, K) one-hot compacted bone of each face (the joint with the
            largest summed skin weight over its corners). centroid_weights: (K, V) averaging over each bone's corners.
        bone_of: (K,) int64 rig joint of each compacted bone. rest_volumes: (K,) m³.
        edge_weights: (E,) weights of :func:`edge_term`, None for the plain mean (the full mesh); on a proxy
            ``w_e = (a_e / A) · mean_full |e_rest|⁴ / |e_rest,e|⁴`` (module docstring).
        num_bones: divisor of the volume sum, the full mesh's bone count (K for the full mesh).
        repulsion_scale: multiplier of the repulsion sum, ``(V_full / V)²`` (1 for the full mesh).
    """

    edges: torch.Tensor
    rest_sq_lengths: torch.Tensor
    faces: torch.Tensor
    face_bone_onehot: torch.Tensor
    centroid_weights: torch.Tensor
    bone_of: torch.Tensor
    rest_volumes: torch.Tensor
    edge_weights: torch.Tensor | None = None
    num_bones: float = 1.0
    repulsion_scale: float = 1.0

    @staticmethod
    def from_mesh(rest_vertices: np.ndarray, faces: np.ndarray, skin_weights: np.ndarray,
                  dtype: torch.dtype = torch.float32, device: str | torch.device = "cpu",
                  full_mesh: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> "MeshRegularisers":
        """Constants from the rest mesh: ``rest_vertices`` (V, 3) m, ``faces`` (F, 3), ``skin_weights`` (V, J).

        ``full_mesh``: ``(vertices, faces, skin_weights)`` of the full mesh when this mesh is a decimated proxy of
        it: the edge, volume and repulsion terms are then normalised to act with the full mesh's magnitudes
        (module docstring). None: this is the full mesh."""
        v = np.array(rest_vertices, dtype=np.float64)
        f = np.array(faces, dtype=np.int64)
        w = np.asarray(skin_weights, dtype=np.float64)
        e, share = _unique_edges(f, v)
        rest_sq = ((v[e[:, 0]] - v[e[:, 1]]) ** 2).sum(1)
        dominant = _dominant_bones(f, w)
        bone_of, face_bone = np.unique(dominant, return_inverse=True)
        to = dict(dtype=dtype, device=device)
        edge_weights, num_bones, repulsion_scale = None, float(len(bone_of)), 1.0
        if full_mesh is not None:
            fv, ff, fw = (np.asarray(a) for a in full_mesh)
            fe = _unique_edges(ff)
            full_sq = ((fv[fe[:, 0]] - fv[fe[:, 1]]) ** 2).sum(1)
            # area-weighted mean of the squared relative change ((|e|² − |e_rest|²) / |e_rest|²)², in the full
            # mesh's units: times its mean |e_rest|⁴
            edge_weights = torch.as_tensor(share / share.sum() * np.mean(full_sq ** 2)
                                           / np.maximum(rest_sq, 1e-12) ** 2, **to)
            num_bones = float(len(np.unique(_dominant_bones(ff, fw))))
            repulsion_scale = float((len(fv) / len(v)) ** 2)
        nb = len(bone_of)
        ft = torch.as_tensor(f, device=device)
        onehot = np.zeros((len(f), nb))
        onehot[np.arange(len(f)), face_bone] = 1.0
        cw = np.zeros((nb, len(v)))
        np.add.at(cw, (np.repeat(face_bone, 3), f.reshape(-1)), 1.0)
        cw /= cw.sum(1, keepdims=True)
        fb, cw = torch.as_tensor(onehot, **to), torch.as_tensor(cw, **to)
        rest_vol = _bone_volumes(torch.as_tensor(v, **to)[None], ft, fb, cw)[0]
        return MeshRegularisers(edges=torch.as_tensor(e, device=device), rest_sq_lengths=torch.as_tensor(rest_sq, **to),
                                faces=ft, face_bone_onehot=fb, centroid_weights=cw,
                                bone_of=torch.as_tensor(bone_of, device=device), rest_volumes=rest_vol,
                                edge_weights=edge_weights, num_bones=num_bones, repulsion_scale=repulsion_scale)

    def edge(self, vertices: torch.Tensor) -> torch.Tensor:
        """(B,) :func:`edge_term` of (B, V, 3) vertices (weighted by ``edge_weights`` on a proxy)."""
        return edge_term(vertices, self.edges, self.rest_sq_lengths, self.edge_weights)

    def volume(self, vertices: torch.Tensor) -> torch.Tensor:
        """(B,) :func:`volume_term` of (B, V, 3) vertices over ``num_bones`` bones."""
        return volume_term(vertices, self.faces, self.face_bone_onehot, self.centroid_weights, self.rest_volumes,
                           self.num_bones)

    def repulsion(self, vertices: torch.Tensor, pair_batch: torch.Tensor, pairs: torch.Tensor, radius: float,
                  batch_size: int) -> torch.Tensor:
        """(B,) :func:`repulsion_term`, times ``repulsion_scale``."""
        return self.repulsion_scale * repulsion_term(vertices, pair_batch, pairs, radius, batch_size)


@dataclass(frozen=True, eq=False)
class RegulariserMesh:
    """The mesh the edge, volume and repulsion terms are evaluated on: the rig's own mesh, or a quadric-decimated
    proxy of it when the rig has more vertices than a budget (see :func:`regulariser_mesh`).

    Attributes:
        rest_vertices: (Vr, 3) metres, canonical frame. faces: (Fr, 3) int64. skin_weights: (Vr, J), each proxy
            vertex copies the weights of its nearest rig vertex. source_vertex: (Vr,) int64 nearest rig vertex
            (the identity for the full mesh); geodesics of the proxy are read through it.
        is_proxy: whether this is a decimated proxy.
    """

    rest_vertices: np.ndarray
    faces: np.ndarray
    skin_weights: np.ndarray
    source_vertex: np.ndarray
    is_proxy: bool


def regulariser_mesh(rest_vertices: np.ndarray, faces: np.ndarray, skin_weights: np.ndarray,
                     max_vertices: int) -> RegulariserMesh:
    """The full mesh if it has at most ``max_vertices`` vertices (or ``max_vertices == 0``), else a proxy made by
    open3d's quadric decimation to about ``max_vertices`` vertices (deterministic)."""
    v = np.asarray(rest_vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    w = np.asarray(skin_weights, dtype=np.float64)
    if max_vertices == 0 or len(v) <= max_vertices:
        return RegulariserMesh(v, f, w, np.arange(len(v)), False)
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v.copy()),
                                     o3d.utility.Vector3iVector(f.astype(np.int32)))
    target = int(len(f) * max_vertices / len(v))  # keep the face/vertex ratio of the original
    small = mesh.simplify_quadric_decimation(target_number_of_triangles=max(target, 4))
    small.remove_degenerate_triangles()
    small.remove_unreferenced_vertices()
    pv = np.asarray(small.vertices, dtype=np.float64)
    pf = np.asarray(small.triangles, dtype=np.int64)
    _, src = cKDTree(v).query(pv)
    return RegulariserMesh(pv, pf, w[src], src.astype(np.int64), True)
