"""Batched fitting of the rigged canonical mesh to predicted dual point clouds (the paper's mesh fitting).

Per instance (one image): nearest-vertex correspondences and inliers (:mod:`.correspondences`), FPS to control
points under the surface metric (:mod:`.sampling`), a robust Kabsch–Umeyama similarity from the assigned rest
vertices to the predicted posed points, then Adam over the excess rotations θ, log bone scales and the global
similarity (axis-angle delta ω on the initial rotation, ``R = R(ω) @ R0``; translation; log scale), with the
paper's learning rates and schedule (θ's and the bone scales' learning rates halved every 100 steps, θ wrapped to
|θ_j| ≤ π after every step, as in the reference). The objective is weighted as the reference weights it
(:mod:`.losses`: mean data term, absolute volume change, proxy terms normalised to the full mesh), plus, when
``config.weight_silhouette > 0``, the mesh's projection against the image's mask (:mod:`.silhouette`; not in the
paper). Instances are
independent: every loss is per instance and summed over the batch, and Adam is elementwise, so a batch gives the
same numbers as fitting its instances one at a time (random choices are seeded by ``config.seed`` and the sample
id, not the batch position).

Vertices: the file rig may split vertices at UV seams or not share them at all (unindexed exports). Everything
that needs the surface runs on the **fitting mesh** (``FittingAsset.fitting_rig``): the welded rig
(:func:`bat3r_core.topology.weld_rig`; ``FittingAsset.welded_rig``, ``FittingAsset.welding``), refined by midpoint
subdivision while its median edge is longer than ``config.densify_max_edge_fraction`` of the asset's length (a
low-poly asset's nearest vertices are too far from the surface points for the data term; its first Vw vertices
are the welded ones). Correspondences, geodesics, control points, the initial similarity and camera recovery read
the fitting mesh; the regulariser mesh (edge, volume, repulsion) is the welded mesh or its decimated proxy. What
:func:`fit_batch` returns is on the file rig's own vertices (``posed_vertices (B, V, 3)``, the file rig skinned
with its own weights).

Frames: predicted posed points are camera-frame points relative to the object depth (docs/CONVENTIONS.md), so the
fitted global similarity maps the canonical frame into that frame. The world of the fitted scene is the canonical
frame (the mesh posed by θ with unit bone scales); the camera rotation is the global rotation and its translation
is recovered from layer-0 pixels (:mod:`.camera`).
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass, field

import numpy as np
import torch

from bat3r_core.metrics import rms_chamfer, umeyama
from bat3r_core.rig import Rig
from bat3r_core.skinning import RigTensors, axis_angle_to_matrix, forward_kinematics
from bat3r_core.stopping import raise_if_stop_requested
from bat3r_core.topology import Welding, subdivide_rig, weld_rig

from .camera import CameraEstimate, recover_camera
from .config import FittingConfig
from .correspondences import VertexIndex, reassign_vertices
from .geodesics import (DenseGeodesics, LandmarkGeodesics, SubsetGeodesics, load_or_compute_geodesic_block,
                        load_or_compute_landmark_geodesics)
from .losses import (MeshRegularisers, RegulariserMesh, angle_term, data_term, find_repulsion_pairs,
                     regulariser_mesh, scale_term, wrap_axis_angle)
from .sampling import farthest_point_sampling
from .silhouette import (SilhouetteBatch, SilhouetteTarget, mesh_sample, nearest_projections, silhouette_target,
                         silhouette_terms)

__all__ = ["FittingAsset", "PointCloudInstance", "FitResult", "fit_batch", "densify", "median_edge_length",
           "LOSS_NAMES", "STATUS_TOO_FEW", "STATUS_BAD_INPUT"]

LOSS_NAMES = ("data", "angle", "edge", "volume", "repulsion", "scale", "silhouette", "total")
STATUS_TOO_FEW = "too_few_points"
STATUS_BAD_INPUT = "bad_input"
_INIT_IRLS_ITERATIONS = 3
_INIT_ANISOTROPIC_ITERATIONS = 50
_MAX_DENSIFY_LEVELS = 6


def median_edge_length(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Median length (metres) of the unique edges of a mesh: ``vertices`` (V, 3) metres, ``faces`` (F, 3) int;
    0 for a mesh without faces."""
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0:
        return 0.0
    e = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1), axis=0)
    v = np.asarray(vertices, dtype=np.float64)
    return float(np.median(np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1)))


def densify(rig: Rig, max_median_edge: float) -> tuple[Rig, int]:
    """Midpoint-subdivide ``rig`` (:func:`bat3r_core.topology.subdivide_rig`) until its median edge is at most
    ``max_median_edge`` metres (0: never), at most 6 levels. Returns (rig, levels applied); the input's vertices
    keep their indices."""
    if not max_median_edge >= 0:
        raise ValueError(f"max_median_edge must be >= 0 (metres), got {max_median_edge!r}")
    levels = 0
    while (max_median_edge > 0 and levels < _MAX_DENSIFY_LEVELS
           and median_edge_length(rig.rest_vertices, rig.faces) > max_median_edge):
        rig = subdivide_rig(rig)
        levels += 1
    return rig, levels


@dataclass(frozen=True, eq=False)
class FittingAsset:
    """Everything about one rigged canonical mesh that fitting precomputes once (see :meth:`prepare`).

    Attributes:
        rig: the file rig (V vertices; outputs are on its vertices). tensors: its skinning tensors on ``device``.
        welded_rig: the rig on its welded mesh (Vw vertices, :func:`bat3r_core.topology.weld_rig`).
        welding: the :class:`~bat3r_core.topology.Welding` (file vertex → welded vertex, representatives).
        fitting_rig: the mesh fitting runs on (Vf vertices): ``welded_rig`` after ``densify_levels`` levels of
            :func:`~bat3r_core.topology.subdivide_rig`; its vertices ``[0, Vw)`` are ``welded_rig``'s.
        densify_levels: subdivision levels applied (0: ``fitting_rig`` is ``welded_rig``).
        fitting_tensors: skinning tensors of ``fitting_rig`` on ``device``.
        reg_mesh: the mesh of the edge/volume/repulsion terms (the welded mesh, or a decimated proxy of it; its
            ``source_vertex`` are welded vertices, hence also fitting-mesh vertices).
        reg_tensors: skinning tensors of ``reg_mesh``. regularisers: its edge/volume constants.
        geodesics: :class:`~.geodesics.LandmarkGeodesics` over the fitting mesh (farthest point sampling).
        reg_geodesics: geodesics over the ``reg_mesh`` vertices (repulsion): an exact
            :class:`~.geodesics.DenseGeodesics` block when ``reg_mesh`` has at most
            ``config.geodesic_exact_max_vertices`` vertices, else the landmark estimates read through
            ``reg_mesh.source_vertex``.
        vertex_index: KD-tree over the fitting mesh's rest vertices.
        geodesic_threshold: repulsion geodesic threshold for this asset, metres.
        length: longest side of the rest mesh's bounding box, metres (the objective's unit, see
            ``FittingConfig.objective_reference_length``).
        left_right: (P, 2) int64 left/right joint pairs. device, dtype: of the tensors.
    """

    rig: Rig
    tensors: RigTensors
    welded_rig: Rig
    welding: Welding
    fitting_rig: Rig
    densify_levels: int
    fitting_tensors: RigTensors
    reg_mesh: RegulariserMesh
    reg_tensors: RigTensors
    regularisers: MeshRegularisers
    geodesics: LandmarkGeodesics
    reg_geodesics: DenseGeodesics | LandmarkGeodesics | SubsetGeodesics
    vertex_index: VertexIndex
    geodesic_threshold: float
    length: float
    left_right: torch.Tensor
    device: torch.device
    dtype: torch.dtype
    _samples: dict = field(default_factory=dict, repr=False)

    def silhouette_vertices(self, count: int, seed: int) -> np.ndarray:
        """The fitting-mesh vertices the silhouette term projects (:func:`.silhouette.mesh_sample`), computed once
        per (count, seed)."""
        key = (int(count), int(seed))
        if key not in self._samples:
            self._samples[key] = mesh_sample(self.fitting_rig.rest_vertices, count, seed)
        return self._samples[key]

    @staticmethod
    def prepare(rig: Rig, config: FittingConfig, cache_dir=None, device: str | torch.device = "cpu",
                dtype: torch.dtype = torch.float32) -> "FittingAsset":
        """Weld the rig (and refine a coarse mesh), then precompute (and cache in ``cache_dir``, see
        :mod:`.geodesics`) what fitting it needs: landmark geodesics, the regulariser mesh and its exact geodesic
        block, the KD-tree."""
        if not isinstance(rig, Rig):
            raise TypeError(f"rig must be a bat3r_core.rig.Rig, got {type(rig).__name__}")
        if not isinstance(config, FittingConfig):
            raise TypeError(f"config must be a FittingConfig, got {type(config).__name__}")
        device = torch.device(device)
        welded, welding = weld_rig(rig, relative_tolerance=config.weld_relative_tolerance)
        length = float(np.ptp(rig.rest_vertices, axis=0).max())
        fitting, levels = densify(welded, config.densify_max_edge_fraction * length)
        fv, ff = fitting.rest_vertices, fitting.faces
        geo = load_or_compute_landmark_geodesics(fv, ff, cache_dir, num_landmarks=config.geodesic_landmarks)
        pairs = np.asarray(rig.left_right_pairs, dtype=np.int64).reshape(-1, 2)
        reg_mesh = regulariser_mesh(welded.rest_vertices, welded.faces, welded.skin_weights,
                                    config.regulariser_max_vertices)
        src = reg_mesh.source_vertex  # welded vertices = the first Vw fitting-mesh vertices
        if len(src) <= config.geodesic_exact_max_vertices:
            reg_geo = load_or_compute_geodesic_block(fv, ff, src, cache_dir)
        elif not reg_mesh.is_proxy and levels == 0:
            reg_geo = geo
        else:
            reg_geo = SubsetGeodesics(geo, src)
        return FittingAsset(rig=rig, tensors=rig.tensors(dtype=dtype, device=device), welded_rig=welded,
                            welding=welding, fitting_rig=fitting, densify_levels=levels,
                            fitting_tensors=fitting.tensors(dtype=dtype, device=device), reg_mesh=reg_mesh,
                            reg_tensors=RigTensors.from_arrays(reg_mesh.rest_vertices, rig.parents,
                                                               rig.rest_transforms, reg_mesh.skin_weights,
                                                               dtype=dtype, device=device),
                            regularisers=MeshRegularisers.from_mesh(
                                reg_mesh.rest_vertices, reg_mesh.faces, reg_mesh.skin_weights, dtype=dtype,
                                device=device, full_mesh=((welded.rest_vertices, welded.faces, welded.skin_weights)
                                                          if reg_mesh.is_proxy else None)),
                            geodesics=geo, reg_geodesics=reg_geo, vertex_index=VertexIndex(fv),
                            geodesic_threshold=config.geodesic_threshold_for(length), length=length,
                            left_right=torch.as_tensor(pairs, device=device), device=device, dtype=dtype)


@dataclass(frozen=True, eq=False)
class PointCloudInstance:
    """One image's predicted dual point cloud.

    Attributes:
        sample_id: identifier of the image.
        posed_points: (N, 3) metres, camera frame relative to the object depth (``P − (0, 0, object_depth)``).
        canonical_points: (N, 3) metres, canonical frame.
        confidence: (N,) ``C = 1 + exp(c)`` or None.
        pixels: (N, 2) pixel coordinates ``(u, v)`` of each point or None (no camera translation then).
        layers: (N,) int layer of each point (0 = front) or None (all treated as layer 0).
        intrinsics: (3, 3) pixels or None. image_size: (width, height) or None.
        mask: (H, W) bool, the image's mask in the pixel frame of ``pixels`` (``image_size`` when given), or None:
            the silhouette term (:mod:`.silhouette`) then uses the pixels of the layer-0 points.
    """

    sample_id: str
    posed_points: np.ndarray
    canonical_points: np.ndarray
    confidence: np.ndarray | None = None
    pixels: np.ndarray | None = None
    layers: np.ndarray | None = None
    intrinsics: np.ndarray | None = None
    image_size: tuple[int, int] | None = None
    mask: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class FitResult:
    """Fits of a batch of B instances (rows in input order). Unfitted rows hold NaN.

    Attributes:
        sample_id, status, reason: per instance (status ``"ok"``, ``"too_few_points"`` or ``"bad_input"``).
        excess_rotations: (B, J, 3) radians. bone_scales: (B, J) (discarded for the training target).
        global_scale: (B,), global_rotation: (B, 3, 3), global_translation: (B, 3) metres: canonical → prediction
            frame, ``x = s R v + t``.
        posed_vertices: (B, V, 3) float32, the unscaled articulated mesh (unit bone scales) after the global
            similarity, metres, prediction frame.
        losses: name → (B,) final value of each loss term (unweighted) and ``total`` (weighted, as optimised).
        residual_chamfer: (B,) RMS bidirectional Chamfer between the inlier predicted posed points and the
            fitted mesh's distinct vertex positions (the fitting mesh posed like ``posed_vertices``: one point per
            welded vertex, so seam copies do not count twice, plus the refinement's vertices), metres.
        inlier_ratio: (B,) inliers / points. mean_confidence: (B,) mean C of all points (NaN without confidence).
        num_points, num_inliers, num_control_points: (B,) int.
        cameras: per instance a :class:`~.camera.CameraEstimate` or None (unfitted / no pixels).
    """

    sample_id: list[str]
    status: list[str]
    reason: list[str]
    excess_rotations: np.ndarray
    bone_scales: np.ndarray
    global_scale: np.ndarray
    global_rotation: np.ndarray
    global_translation: np.ndarray
    posed_vertices: np.ndarray
    losses: dict[str, np.ndarray]
    residual_chamfer: np.ndarray
    inlier_ratio: np.ndarray
    mean_confidence: np.ndarray
    num_points: np.ndarray
    num_inliers: np.ndarray
    num_control_points: np.ndarray
    cameras: list[CameraEstimate | None] = field(default_factory=list)


@dataclass
class _Prepared:
    index: int
    vertex: np.ndarray  # (n,) assigned fitting-mesh vertex per control point
    target: np.ndarray  # (n, 3) predicted posed points of the control points
    canonical: np.ndarray  # (n, 3) predicted canonical points of the control points
    inlier_posed: np.ndarray  # (m, 3) predicted posed points of all inliers
    silhouette: SilhouetteTarget | None  # None: no silhouette term for this instance


def _id_seed(sample_id: str) -> int:
    """A stable seed from a sample id, so an instance's random choices do not depend on its batch."""
    return zlib.crc32(str(sample_id).encode())


def _check_instance(inst: PointCloudInstance) -> str:
    p = np.asarray(inst.posed_points)
    q = np.asarray(inst.canonical_points)
    if p.ndim != 2 or p.shape[1] != 3:
        return f"posed_points must have shape (N, 3), got {p.shape}"
    if q.shape != p.shape:
        return f"canonical_points must have the shape of posed_points {p.shape}, got {q.shape}"
    n = p.shape[0]
    for name in ("confidence", "layers"):
        a = getattr(inst, name)
        if a is not None and np.asarray(a).shape != (n,):
            return f"{name} must have shape ({n},), got {np.asarray(a).shape}"
    if inst.pixels is not None and np.asarray(inst.pixels).shape != (n, 2):
        return f"pixels must have shape ({n}, 2), got {np.asarray(inst.pixels).shape}"
    if inst.intrinsics is not None and np.asarray(inst.intrinsics).shape != (3, 3):
        return f"intrinsics must have shape (3, 3), got {np.asarray(inst.intrinsics).shape}"
    if inst.mask is not None:
        m = np.asarray(inst.mask)
        expected = None if inst.image_size is None else (int(inst.image_size[1]), int(inst.image_size[0]))
        if m.ndim != 2 or (expected is not None and m.shape != expected):
            return (f"mask must have shape {expected or '(H, W)'} (image_size is (width, height)), "
                    f"got {m.shape}")
    return ""


def _prepare(asset: FittingAsset, inst: PointCloudInstance, config: FittingConfig, rng: np.random.Generator,
             index: int) -> tuple[_Prepared | None, str, str, dict]:
    err = _check_instance(inst)
    if err:
        return None, STATUS_BAD_INPUT, err, {"num_points": 0, "num_inliers": 0}
    p = np.asarray(inst.posed_points, dtype=np.float64)
    finite = np.isfinite(p).all(1)
    corr = asset.vertex_index.match(inst.canonical_points, inst.confidence, config.inlier_distance,
                                    config.min_confidence)
    inl = corr.inlier & finite
    info = {"num_points": int(len(p)), "num_inliers": int(inl.sum())}
    if inl.sum() < config.min_valid_points:
        return None, STATUS_TOO_FEW, (f"{int(inl.sum())} inlier points (of {len(p)}) < min_valid_points "
                                      f"{config.min_valid_points}"), info
    idx = np.flatnonzero(inl)
    pick = farthest_point_sampling(corr.distance[idx], corr.vertex[idx], asset.geodesics,
                                   config.num_control_points, rng)
    ctrl = idx[pick]
    sil = silhouette_target(p, inst.pixels, inst.layers, inl, inst.mask, inst.intrinsics, inst.image_size,
                            config.silhouette_mask_samples, rng)
    q = np.asarray(inst.canonical_points, dtype=np.float64)
    return (_Prepared(index=index, vertex=corr.vertex[ctrl], target=p[ctrl], canonical=q[ctrl], inlier_posed=p[idx],
                      silhouette=sil),
            "ok", "", info)


def _robust_similarity(source: np.ndarray, target: np.ndarray, delta: float, depth_weight: float = 1.0
                       ) -> tuple[float, np.ndarray, np.ndarray]:
    """Kabsch–Umeyama similarity source → target, re-weighted a few times with Huber weights.

    With ``depth_weight`` w < 1 the residual's z component counts w times (the data term's weighting): each round
    solves the isotropic problem for targets whose z is moved from the current fit's z by w² of the residual —
    the majorisation of the anisotropic least squares, so every round lowers it (w = 1: the plain targets)."""
    w2 = float(depth_weight) ** 2
    axis = np.array([1.0, 1.0, float(depth_weight)])
    sim = umeyama(source, target, with_scale=True)
    rounds = _INIT_IRLS_ITERATIONS if w2 == 1.0 else _INIT_ANISOTROPIC_ITERATIONS
    for _ in range(rounds):
        model = sim.apply(source)
        r = np.linalg.norm((model - target) * axis, axis=1)
        weights = np.where(r <= delta, 1.0, delta / np.maximum(r, 1e-12))
        goal = target
        if w2 != 1.0:
            goal = target.copy()
            goal[:, 2] = model[:, 2] + w2 * (target[:, 2] - model[:, 2])
        sim = umeyama(source, goal, with_scale=True, weights=weights)
    return sim.scale, sim.rotation, sim.translation


def _skinning_matrices(tensors: RigTensors, g: torch.Tensor) -> torch.Tensor:
    """(B, J, 12): the top 3x4 rows of ``G_j @ G_rest[j]^-1``, flattened."""
    m = (g @ tensors.inverse_rest_transforms)[:, :, :3, :]
    return m.reshape(g.shape[0], g.shape[1], 12)


def _skin_all(tensors: RigTensors, m: torch.Tensor, rest_h: torch.Tensor) -> torch.Tensor:
    """(B, V, 3) linear blend skinning of every vertex from skinning matrices ``m`` (B, J, 12).

    The result is a view of vertex-major (V, B, 3) memory, the layout the regularisers' sparse products want.
    """
    b, j, _ = m.shape
    # (V, J) @ (J, B*12): one GEMM blends all instances' matrices per vertex
    blended = (tensors.skin_weights @ m.permute(1, 0, 2).reshape(j, b * 12)).reshape(-1, b, 3, 4)
    return (blended * rest_h[:, None, None, :]).sum(-1).permute(1, 0, 2)


def _skin_subset(tensors: RigTensors, m: torch.Tensor, rest_h: torch.Tensor, vertex: torch.Tensor) -> torch.Tensor:
    """(B, N, 3) skinning of the vertices ``vertex`` (B, N) only."""
    w = tensors.skin_weights[vertex]  # (B, N, J)
    blended = torch.bmm(w, m).reshape(*vertex.shape, 3, 4)
    return torch.einsum("bnrc,bnc->bnr", blended, rest_h[vertex])


def _nan_result(instances, statuses, reasons, infos, j, v) -> dict:
    b = len(instances)
    return dict(excess_rotations=np.full((b, j, 3), np.nan), bone_scales=np.full((b, j), np.nan),
                global_scale=np.full(b, np.nan), global_rotation=np.full((b, 3, 3), np.nan),
                global_translation=np.full((b, 3), np.nan), posed_vertices=np.full((b, v, 3), np.nan, np.float32),
                losses={k: np.full(b, np.nan) for k in LOSS_NAMES}, residual_chamfer=np.full(b, np.nan),
                inlier_ratio=np.array([i["num_inliers"] / max(i["num_points"], 1) for i in infos], dtype=np.float64),
                num_points=np.array([i["num_points"] for i in infos], dtype=np.int64),
                num_inliers=np.array([i["num_inliers"] for i in infos], dtype=np.int64),
                num_control_points=np.zeros(b, dtype=np.int64))


def fit_batch(asset: FittingAsset, instances: list[PointCloudInstance], config: FittingConfig,
              fit_focal: bool = False) -> FitResult:
    """Fit the asset's rig to each instance's predicted dual point cloud.

    Args:
        asset: from :meth:`FittingAsset.prepare` (its device is used).
        instances: B point clouds (any sizes; control points are padded and masked).
        config: the fitting configuration (a preset).
        fit_focal: also search the focal length during camera recovery (see :func:`~.camera.recover_camera`).
    Returns:
        :class:`FitResult`; instances with too few inlier points are recorded with their status, not fitted.
    """
    if not isinstance(config, FittingConfig):
        raise TypeError(f"config must be a FittingConfig, got {type(config).__name__}")
    if not isinstance(instances, (list, tuple)) or not all(isinstance(i, PointCloudInstance) for i in instances):
        raise TypeError("instances must be a list of PointCloudInstance")
    rig = asset.rig
    num_j, num_v = rig.num_joints, rig.num_vertices
    statuses, reasons, infos, prepared = [], [], [], []
    for k, inst in enumerate(instances):
        rng = np.random.default_rng([config.seed, _id_seed(inst.sample_id)])
        prep, status, reason, info = _prepare(asset, inst, config, rng, k)
        statuses.append(status)
        reasons.append(reason)
        infos.append(info)
        if prep is not None:
            prepared.append(prep)
    out = _nan_result(instances, statuses, reasons, infos, num_j, num_v)
    conf = [np.asarray(i.confidence, dtype=np.float64) if i.confidence is not None else None for i in instances]
    out["mean_confidence"] = np.array([float(c.mean()) if c is not None and len(c) else np.nan for c in conf])
    cameras: list[CameraEstimate | None] = [None] * len(instances)
    if prepared:
        fitted = _optimise(asset, prepared, config)
        for slot, prep in enumerate(prepared):
            k = prep.index
            for key in ("excess_rotations", "bone_scales", "global_scale", "global_rotation", "global_translation",
                        "posed_vertices"):
                out[key][k] = fitted[key][slot]
            for name in LOSS_NAMES:
                out["losses"][name][k] = fitted["losses"][name][slot]
            out["num_control_points"][k] = len(prep.vertex)
            out["residual_chamfer"][k] = rms_chamfer(prep.inlier_posed, fitted["posed_fitting_vertices"][slot])
            cameras[k] = _camera_of(asset, instances[k], fitted["world_fitting_vertices"][slot],
                                    fitted["global_rotation"][slot], config, fit_focal,
                                    fitted["posed_fitting_vertices"][slot])
    return FitResult(sample_id=[str(i.sample_id) for i in instances], status=statuses, reason=reasons,
                     cameras=cameras, **out)


_MIN_FRONT_POINTS = 8
"""Below this many layer-0 inliers, camera recovery uses the inliers of every layer."""


def _camera_of(asset: FittingAsset, inst: PointCloudInstance, world_vertices: np.ndarray, rotation: np.ndarray,
               config: FittingConfig, fit_focal: bool, posed_vertices: np.ndarray | None = None
               ) -> CameraEstimate | None:
    """Camera of one fitted instance from its layer-0 pixels (None without pixels or intrinsics).

    ``world_vertices`` (Vf, 3): the fitting mesh posed by θ (unit bone scales, canonical frame), which the
    correspondences index; ``posed_vertices`` (Vf, 3): the same mesh in the prediction frame (the final fit). With
    ``correspondence_refresh_steps`` > 0 each pixel's point takes the vertex the fit itself would re-assign it
    (:func:`~.correspondences.reassign_vertices` in the final fit), so the camera reads the correspondences the fit
    ended with, not the predicted labels it corrected."""
    if inst.pixels is None or inst.intrinsics is None:
        return None
    layers = np.zeros(len(inst.pixels), dtype=np.int64) if inst.layers is None else np.asarray(inst.layers)
    corr = asset.vertex_index.match(inst.canonical_points, inst.confidence, config.inlier_distance,
                                    config.min_confidence)
    front = (layers == 0) & corr.inlier
    if front.sum() < _MIN_FRONT_POINTS:
        # every layer's point lies on its pixel's ray too: use them when the visible layer has too few inliers
        front = corr.inlier
    if front.sum() < 2:
        return None
    vertex = corr.vertex[front]
    if config.correspondence_refresh_steps and posed_vertices is not None:
        p = np.asarray(inst.posed_points, dtype=np.float64)[front]
        ok = np.isfinite(p).all(1)  # a point without a posed position keeps its predicted label
        vertex[ok] = reassign_vertices(posed_vertices, asset.fitting_rig.rest_vertices, p[ok],
                                       np.asarray(inst.canonical_points, dtype=np.float64)[front][ok],
                                       config.correspondence_canonical_weight,
                                       np.array([1.0, 1.0, config.data_depth_weight]))
    rotated = world_vertices[vertex] @ rotation.T  # (n, 3) fitted points, camera orientation
    seed = np.random.default_rng([config.seed, 7, _id_seed(inst.sample_id)])
    return recover_camera(rotation, rotated, np.asarray(inst.pixels, dtype=np.float64)[front],
                          np.asarray(inst.intrinsics, dtype=np.float64), rng=seed, fit_focal=fit_focal,
                          image_size=inst.image_size)


def _optimise(asset: FittingAsset, prepared: list[_Prepared], config: FittingConfig) -> dict:
    """Adam over θ, log bone scales and the global similarity for the fittable instances."""
    dev, dt = asset.device, asset.dtype
    tensors, reg, reg_tensors = asset.tensors, asset.regularisers, asset.reg_tensors
    fit_tensors = asset.fitting_tensors
    b, num_j = len(prepared), asset.rig.num_joints
    n_max = max(len(p.vertex) for p in prepared)
    vertex = np.zeros((b, n_max), dtype=np.int64)
    target = np.zeros((b, n_max, 3))
    mask = np.zeros((b, n_max))
    s0, r0, t0 = np.ones(b), np.tile(np.eye(3), (b, 1, 1)), np.zeros((b, 3))
    rest = asset.fitting_rig.rest_vertices
    for i, p in enumerate(prepared):
        n = len(p.vertex)
        vertex[i, :n], target[i, :n], mask[i, :n] = p.vertex, p.target, 1.0
        s0[i], r0[i], t0[i] = _robust_similarity(rest[p.vertex], p.target, config.huber_delta,
                                                  config.data_depth_weight)
    to = dict(dtype=dt, device=dev)
    vertex_t = torch.as_tensor(vertex, device=dev)
    target_t, mask_t = torch.as_tensor(target, **to), torch.as_tensor(mask, **to)
    r0_t, t0_t, logs0_t = torch.as_tensor(r0, **to), torch.as_tensor(t0, **to), torch.as_tensor(np.log(s0), **to)
    rest_h = torch.cat([tensors.rest_vertices, torch.ones(tensors.num_vertices, 1, **to)], 1)  # (V, 4) file rig
    fit_rest_h = torch.cat([fit_tensors.rest_vertices, torch.ones(fit_tensors.num_vertices, 1, **to)], 1)
    reg_rest_h = torch.cat([reg_tensors.rest_vertices, torch.ones(reg_tensors.num_vertices, 1, **to)], 1)

    theta = torch.zeros(b, num_j, 3, **to, requires_grad=True)
    log_bone = torch.zeros(b, num_j, **to, requires_grad=True)
    omega = torch.zeros(b, 3, **to, requires_grad=True)
    d_trans = torch.zeros(b, 3, **to, requires_grad=True)
    d_logs = torch.zeros(b, **to, requires_grad=True)
    groups = [{"params": [theta], "lr": config.lr_rotations},
              {"params": [omega, d_trans, d_logs], "lr": config.lr_global}]
    if config.enable_bone_scales:
        groups.append({"params": [log_bone], "lr": config.lr_bone_scales})
    opt = torch.optim.Adam(groups)
    joint_mask = torch.ones(num_j, **to)
    if not config.fit_root_rotation:
        joint_mask[torch.as_tensor(asset.rig.parents < 0, device=dev)] = 0.0
    lo, hi = (float(np.log(x)) for x in config.bone_scale_bounds)
    # the objective in units of the asset's length relative to the reference animal (config docstring)
    unit = asset.length / config.objective_reference_length if config.objective_reference_length > 0 else 1.0
    radius = config.repulsion_radius * unit
    pair_batch = torch.zeros(0, dtype=torch.long, device=dev)
    pairs = torch.zeros(0, 2, dtype=torch.long, device=dev)
    sil_batch = SilhouetteBatch.stack([p.silhouette for p in prepared], dt, dev)
    sil_vertex = torch.as_tensor(asset.silhouette_vertices(config.silhouette_vertices, config.seed),
                                 device=dev)[None].expand(b, -1)

    sil_nearest = None
    # the data residual's camera-depth component weighted by config.data_depth_weight (1: isotropic, the paper's;
    # multiplied before the division by the unit, so w = 1 gives the very bits of the unweighted term)
    axis_w = torch.as_tensor([1.0, 1.0, config.data_depth_weight], **to)

    def articulation():
        """The masked θ, the unscaled skinning matrices, the bone scales and the data term's skinning matrices
        (with the bone scales when they are optimised)."""
        th = theta * joint_mask[None, :, None]
        m_unscaled = _skinning_matrices(tensors, forward_kinematics(tensors, th))
        if config.enable_bone_scales:
            scales = torch.exp(log_bone)
            return th, m_unscaled, scales, _skinning_matrices(tensors, forward_kinematics(tensors, th, scales))
        return th, m_unscaled, torch.ones_like(log_bone), m_unscaled

    def similarity():
        """The global similarity (rotation, scale, translation) canonical → prediction frame."""
        return axis_angle_to_matrix(omega) @ r0_t, torch.exp(logs0_t + d_logs), t0_t + d_trans

    axis_np = np.array([1.0, 1.0, config.data_depth_weight])

    def reassign() -> None:
        """Re-assign every control point's vertex in the current fit (``correspondence_refresh_steps``)."""
        nonlocal vertex_t
        with torch.no_grad():
            _, _, _, m_data = articulation()
            rot, scale, trans = similarity()
            fit = scale[:, None, None] * _skin_all(fit_tensors, m_data, fit_rest_h) @ rot.transpose(1, 2)
            fit = (fit + trans[:, None, :]).cpu().numpy().astype(np.float64)
        for i, p in enumerate(prepared):
            vertex[i, :len(p.vertex)] = reassign_vertices(fit[i], rest, p.target, p.canonical,
                                                          config.correspondence_canonical_weight, axis_np)
        vertex_t = torch.as_tensor(vertex, device=dev)

    def evaluate(step: int, final: bool = False):
        nonlocal pair_batch, pairs, sil_nearest
        th, m_unscaled, scales, m_data = articulation()
        verts_u = _skin_all(reg_tensors, m_unscaled, reg_rest_h)  # (B, Vr, 3) unscaled articulated (proxy) mesh
        ctrl = _skin_subset(fit_tensors, m_data, fit_rest_h, vertex_t)  # (B, N, 3) control vertices, scaled mesh
        rot, scale, trans = similarity()
        posed_ctrl = scale[:, None, None] * ctrl @ rot.transpose(1, 2) + trans[:, None, :]
        if step % config.repulsion_refresh_steps == 0 and config.weight_repulsion > 0:
            vu = verts_u.detach().cpu().numpy().astype(np.float64)
            found = [find_repulsion_pairs(vu[i], asset.reg_geodesics, asset.geodesic_threshold, 2.0 * radius,
                                          config.repulsion_k) for i in range(b)]
            pair_batch = torch.as_tensor(np.concatenate([np.full(len(f), i) for i, f in enumerate(found)]),
                                         dtype=torch.long, device=dev)
            pairs = torch.as_tensor(np.concatenate(found), dtype=torch.long, device=dev).reshape(-1, 2)
        terms = {
            "data": data_term(posed_ctrl * axis_w / unit, target_t * axis_w / unit, mask_t, config.huber_delta),
            "angle": angle_term(th, joint_mask),
            "edge": reg.edge(verts_u) / unit ** 4,
            "volume": reg.volume(verts_u) / unit ** 6,
            "repulsion": reg.repulsion(verts_u, pair_batch, pairs, radius, b) / unit ** 4,
            "scale": scale_term(scales, asset.left_right),
        }
        if config.weight_silhouette > 0 or final:  # reported as a quality column even when not optimised
            sil = _skin_subset(fit_tensors, m_data, fit_rest_h, sil_vertex)
            sil = scale[:, None, None] * sil @ rot.transpose(1, 2) + trans[:, None, :]
            if final or step % config.silhouette_refresh_steps == 0:
                sil_nearest = nearest_projections(sil, sil_batch)
            outside, coverage = silhouette_terms(sil, sil_batch, unit, config.huber_delta, sil_nearest)
            terms["silhouette"] = outside + coverage
        else:
            terms["silhouette"] = torch.zeros(b, **to)
        warm = 1.0
        if config.warmup and config.warmup_steps > 0:
            warm = 1.0 + (config.warmup_factor - 1.0) * max(0.0, 1.0 - step / config.warmup_steps)
        total = (terms["data"] + warm * (config.weight_angle * terms["angle"] + config.weight_edge * terms["edge"]
                                         + config.weight_volume * terms["volume"])
                 + config.weight_repulsion * terms["repulsion"] + config.weight_scale * terms["scale"]
                 + config.weight_silhouette * terms["silhouette"])
        terms["total"] = total
        return terms, m_unscaled, rot, scale, trans, scales

    for step in range(config.steps):
        raise_if_stop_requested(f"fitting {len(prepared)} point clouds at step {step} of {config.steps}")
        halving = 0.5 ** (step // config.rotation_lr_halving_steps)
        opt.param_groups[0]["lr"] = config.lr_rotations * halving
        if config.enable_bone_scales:  # the reference halves the bone scales' learning rate with θ's
            opt.param_groups[2]["lr"] = config.lr_bone_scales * halving
        refresh = config.correspondence_refresh_steps
        if refresh and step and step % refresh == 0:
            reassign()
        opt.zero_grad(set_to_none=True)
        terms, *_ = evaluate(step)
        terms["total"].sum().backward()
        opt.step()
        with torch.no_grad():
            theta.copy_(wrap_axis_angle(theta))  # the same rotations with |θ_j| <= π, as the reference keeps them
            if config.enable_bone_scales:
                log_bone.clamp_(lo, hi)
    with torch.no_grad():
        terms, m_unscaled, rot, scale, trans, scales = evaluate(config.steps, final=True)
        terms["silhouette"] = torch.where(sil_batch.active > 0, terms["silhouette"],
                                          torch.full_like(terms["silhouette"], float("nan")))
        verts_u = _skin_all(tensors, m_unscaled, rest_h)  # the full file mesh, unit bone scales
        posed = scale[:, None, None] * verts_u @ rot.transpose(1, 2) + trans[:, None, :]
        fit_u = _skin_all(fit_tensors, m_unscaled, fit_rest_h)  # the fitting mesh, unit bone scales
        posed_fit = scale[:, None, None] * fit_u @ rot.transpose(1, 2) + trans[:, None, :]
        th = theta * joint_mask[None, :, None]
    cpu = lambda t: t.detach().cpu().numpy().astype(np.float64)  # noqa: E731
    return dict(excess_rotations=cpu(th), bone_scales=cpu(scales), global_scale=cpu(scale),
                global_rotation=cpu(rot), global_translation=cpu(trans),
                posed_vertices=posed.detach().cpu().numpy().astype(np.float32), world_fitting_vertices=cpu(fit_u),
                posed_fitting_vertices=cpu(posed_fit), losses={k: cpu(v) for k, v in terms.items()})
