"""Reconstruction metrics: RMS Chamfer distance, similarity alignment, ICP and camera rotation error.

Everything here is pure numpy/scipy math on point sets in **metres**; the ``*_cm`` helpers report centimetres.

* **RMS bidirectional Chamfer distance** between point sets X (N, 3) and Y (M, 3):
  ``sqrt(0.5 * (mean_x d²(x, Y) + mean_y d²(y, X)))`` with ``d`` the Euclidean nearest-neighbour distance.
* **Full alignment** (``full_alignment``): ICP with scale. Each iteration takes the nearest-neighbour
  correspondences in both directions (every predicted point to its nearest ground-truth point and every
  ground-truth point to its nearest predicted point) and solves one weighted Umeyama similarity over both sets,
  each direction weighted ``0.5 / count`` so the least-squares objective is exactly the squared RMS Chamfer
  distance for fixed correspondences. 50 iterations, started twice, rotated 0° and 180° about the up axis of the
  ground-truth frame; the start with the lower final Chamfer distance is kept.
* **Model-view alignment** (``model_view_alignment``): scale and translation only (no rotation), so a wrong
  camera rotation is penalised. See its docstring for the exact procedure.
* **Camera rotation error** (``rotation_error_deg``): geodesic angle between two rotation matrices, degrees.
* **Mask IoU** (``mask_iou``): ``|A ∩ B| / |A ∪ B|`` of two boolean images (1.0 when both are empty).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree

__all__ = [
    "M_TO_CM",
    "Similarity",
    "AlignmentResult",
    "SampleMetrics",
    "to_cm",
    "rms_chamfer",
    "rms_chamfer_cm",
    "umeyama",
    "kabsch",
    "rotation_about_axis",
    "full_alignment",
    "model_view_alignment",
    "rotation_error_deg",
    "evaluate_sample",
    "mask_iou",
]

M_TO_CM = 100.0


@dataclass(frozen=True)
class Similarity:
    """``x_out = scale * rotation @ x + translation`` (metres in, metres out).

    scale: float > 0; rotation: (3, 3) proper rotation; translation: (3,) metres.
    """

    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    def apply(self, points: np.ndarray) -> np.ndarray:
        """points: (N, 3) → (N, 3) transformed points."""
        return self.scale * np.asarray(points, dtype=np.float64) @ self.rotation.T + self.translation

    @staticmethod
    def identity() -> "Similarity":
        return Similarity(1.0, np.eye(3), np.zeros(3))


@dataclass(frozen=True)
class AlignmentResult:
    """Outcome of an alignment of predicted points onto ground-truth points.

    similarity: the transform applied to the predicted points.
    rms_cd: RMS bidirectional Chamfer distance after alignment, metres.
    start_angle_deg: rotation about the up axis of the start that was kept (0 for model-view alignment).
    iterations: correspondence iterations actually run for the kept start (stops early once converged).
    """

    similarity: Similarity
    rms_cd: float
    start_angle_deg: float
    iterations: int

    @property
    def rms_cd_cm(self) -> float:
        return to_cm(self.rms_cd)


@dataclass(frozen=True)
class SampleMetrics:
    """Metrics of one test sample (see ``evaluate_sample``).

    cd_cm: RMS bidirectional Chamfer distance after full alignment (ICP with scale), centimetres.
    mv_cd_cm: the same after model-view alignment (scale + translation only), centimetres.
    rot_err_deg: geodesic camera rotation error in degrees; NaN when no rotations were given.
    icp_scale, icp_start_deg: scale and start angle (0 or 180) of the kept full alignment.
    mv_scale: scale of the model-view alignment.
    n_pred, n_gt: number of predicted and ground-truth points.
    """

    cd_cm: float
    mv_cd_cm: float
    rot_err_deg: float
    icp_scale: float
    icp_start_deg: float
    mv_scale: float
    n_pred: int
    n_gt: int

    def as_dict(self) -> dict[str, float | int]:
        return asdict(self)


def to_cm(metres):
    """Metres → centimetres (float or array)."""
    if np.ndim(metres) == 0:
        return float(metres) * M_TO_CM
    return np.asarray(metres, dtype=np.float64) * M_TO_CM


def _points(name: str, points, min_count: int = 1) -> np.ndarray:
    a = np.asarray(points, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {a.shape}")
    if a.shape[0] < min_count:
        raise ValueError(f"{name} must have at least {min_count} point(s), got {a.shape[0]}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains non-finite values")
    return a


def _chamfer_from_distances(d_xy: np.ndarray, d_yx: np.ndarray) -> float:
    return float(np.sqrt(0.5 * (np.mean(d_xy ** 2) + np.mean(d_yx ** 2))))


def rms_chamfer(x: np.ndarray, y: np.ndarray) -> float:
    """RMS bidirectional Chamfer distance ``sqrt(0.5 * (mean d²(X→Y) + mean d²(Y→X)))``.

    x: (N, 3), y: (M, 3), same frame and units (metres). Returns metres. Symmetric in x and y.
    """
    x = _points("x", x)
    y = _points("y", y)
    d_xy, _ = cKDTree(y).query(x)
    d_yx, _ = cKDTree(x).query(y)
    return _chamfer_from_distances(d_xy, d_yx)


def rms_chamfer_cm(x: np.ndarray, y: np.ndarray) -> float:
    """``rms_chamfer`` in centimetres (inputs in metres)."""
    return to_cm(rms_chamfer(x, y))


def umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool = True,
            weights: np.ndarray | None = None) -> Similarity:
    """Least-squares similarity (Umeyama 1991) mapping ``source`` onto ``target`` point for point.

    Minimises ``sum_i w_i ||target_i - (s R source_i + t)||²`` over a proper rotation R, translation t and (when
    ``with_scale``) a scale s > 0; otherwise s = 1 (the Kabsch solution).

    source, target: (N, 3) corresponding points, N ≥ 3, metres. weights: (N,) non-negative, not all zero
    (default uniform); only their ratios matter.
    """
    src = _points("source", source, 3)
    tgt = _points("target", target, 3)
    if src.shape != tgt.shape:
        raise ValueError(f"source and target must have the same shape, got {src.shape} and {tgt.shape}")
    if weights is None:
        w = np.full(len(src), 1.0 / len(src))
    else:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (len(src),):
            raise ValueError(f"weights must have shape ({len(src)},), got {w.shape}")
        if np.any(w < 0) or not np.isfinite(w).all() or w.sum() <= 0:
            raise ValueError("weights must be finite, non-negative and not all zero")
        w = w / w.sum()
    mu_s = w @ src
    mu_t = w @ tgt
    src_c = src - mu_s
    tgt_c = tgt - mu_t
    cov = (tgt_c * w[:, None]).T @ src_c  # (3, 3) = sum_i w_i tgt_c_i src_c_i^T
    u, d, vt = np.linalg.svd(cov)
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2] = -1.0  # reflection → flip the weakest axis so R is a proper rotation
    rotation = (u * sign) @ vt
    scale = 1.0
    if with_scale:
        var_s = float(w @ np.sum(src_c ** 2, axis=1))
        if var_s <= 1e-18:
            raise ValueError("source points coincide; the scale of a similarity is undefined")
        scale = float(np.sum(d * sign) / var_s)
    translation = mu_t - scale * rotation @ mu_s
    return Similarity(scale, rotation, translation)


def kabsch(source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None) -> Similarity:
    """Rigid (rotation + translation, scale 1) least-squares alignment: ``umeyama(..., with_scale=False)``."""
    return umeyama(source, target, with_scale=False, weights=weights)


def rotation_about_axis(axis: Sequence[float], angle_deg: float) -> np.ndarray:
    """(3, 3) rotation by ``angle_deg`` degrees about ``axis`` (3,) (right-hand rule; normalised here)."""
    a = np.asarray(axis, dtype=np.float64)
    if a.shape != (3,) or not np.isfinite(a).all() or np.linalg.norm(a) < 1e-12:
        raise ValueError(f"axis must be a finite, non-zero vector of shape (3,), got {np.asarray(axis).tolist()}")
    a = a / np.linalg.norm(a)
    th = np.deg2rad(angle_deg)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(th) * k + (1 - np.cos(th)) * k @ k


def _rms_radius(p: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((p - p.mean(0)) ** 2, axis=1))))


def _fit_scale_translation(src: np.ndarray, tgt: np.ndarray, w: np.ndarray) -> tuple[float, np.ndarray]:
    """Weighted least squares for ``tgt ≈ s * src + t`` (no rotation); w sums to 1."""
    mu_s = w @ src
    mu_t = w @ tgt
    src_c = src - mu_s
    denom = float(w @ np.sum(src_c ** 2, axis=1))
    scale = float(w @ np.sum(src_c * (tgt - mu_t), axis=1)) / denom if denom > 1e-18 else 1.0
    return scale, mu_t - scale * mu_s


def _correspondence_iterations(pred: np.ndarray, gt: np.ndarray, start: Similarity, iterations: int,
                               with_rotation: bool) -> tuple[Similarity, float, int]:
    """Bidirectional nearest-neighbour iterations from ``start``; returns the best transform seen, its RMS CD
    (metres) and the number of iterations run. Each step minimises the squared RMS Chamfer distance for the
    current correspondences, so the objective never increases except through ties; the best iterate is kept."""
    gt_tree = cKDTree(gt)
    weights = np.concatenate([np.full(len(pred), 0.5 / len(pred)), np.full(len(gt), 0.5 / len(gt))])
    current = start
    best, best_cd = start, np.inf
    steps = 0
    for step in range(iterations + 1):
        moved = current.apply(pred)
        d_pg, j = gt_tree.query(moved)          # predicted → nearest ground truth
        d_gp, i = cKDTree(moved).query(gt)      # ground truth → nearest predicted
        cd = _chamfer_from_distances(d_pg, d_gp)
        if cd < best_cd - 1e-15:
            best, best_cd = current, cd
        elif step > 0:
            break  # no further decrease: the correspondences are a fixed point
        if step == iterations:
            break
        src = np.concatenate([pred, pred[i]])
        tgt = np.concatenate([gt[j], gt])
        if with_rotation:
            current = umeyama(src, tgt, with_scale=True, weights=weights)
        else:
            scale, translation = _fit_scale_translation(src, tgt, weights)
            if scale <= 0:
                break
            current = Similarity(scale, np.eye(3), translation)
        steps = step + 1
    return best, best_cd, steps


def full_alignment(pred_points: np.ndarray, gt_points: np.ndarray, up: Sequence[float] = (0.0, 1.0, 0.0),
                   iterations: int = 50, start_angles_deg: Sequence[float] = (0.0, 180.0)) -> AlignmentResult:
    """Align predicted points onto ground truth with ICP with scale, from several starts about the up axis.

    Start k: rotation ``R_k`` by ``start_angles_deg[k]`` about ``up`` (a direction in the ground-truth frame),
    scale ``s_0 = rms_radius(gt) / rms_radius(pred)`` (RMS distance of the points to their centroid), and the
    translation that maps the predicted centroid onto the ground-truth centroid. Then ``iterations`` bidirectional
    Umeyama iterations (module docstring). The start with the lowest final RMS Chamfer distance is kept (ties:
    the earlier start).

    pred_points: (N, 3) metres, any frame; gt_points: (M, 3) metres, ground-truth frame.
    up: (3,) the up direction of the ground-truth frame: ``(0, 1, 0)`` in the canonical frame (+Y up); for
    camera-frame points pass the world up expressed in the camera, e.g. ``R_gt @ (0, 1, 0)``.
    """
    pred = _points("pred_points", pred_points, 3)
    gt = _points("gt_points", gt_points, 3)
    if not isinstance(iterations, (int, np.integer)) or iterations < 0:
        raise ValueError(f"iterations must be a non-negative integer, got {iterations!r}")
    if len(start_angles_deg) == 0:
        raise ValueError("start_angles_deg must name at least one start angle")
    r_pred, r_gt = _rms_radius(pred), _rms_radius(gt)
    if r_pred <= 1e-12 or r_gt <= 1e-12:
        raise ValueError("pred_points and gt_points must not collapse to a single point")
    s0 = r_gt / r_pred
    best: AlignmentResult | None = None
    for angle in start_angles_deg:
        rot = rotation_about_axis(up, float(angle))
        start = Similarity(s0, rot, gt.mean(0) - s0 * rot @ pred.mean(0))
        sim, cd, steps = _correspondence_iterations(pred, gt, start, iterations, with_rotation=True)
        if best is None or cd < best.rms_cd:
            best = AlignmentResult(sim, cd, float(angle), steps)
    return best


def model_view_alignment(pred_points: np.ndarray, gt_points: np.ndarray, iterations: int = 10) -> AlignmentResult:
    """Align predicted points onto ground truth with a scale and a translation only (rotation fixed to identity).

    Exactly: (1) closed form start: ``s_0 = rms_radius(gt) / rms_radius(pred)``, ``t_0 = mean(gt) - s_0 mean(pred)``
    (matches centroids and spreads); (2) up to ``iterations`` steps that take the bidirectional nearest-neighbour
    correspondences of the current transform and solve the weighted least squares ``gt ≈ s · pred + t`` in closed
    form (same weights as ICP, ``0.5 / count`` per direction); a step with ``s ≤ 0`` or no decrease stops early.
    The transform with the lowest RMS Chamfer distance seen (start included) is returned.

    pred_points: (N, 3) and gt_points: (M, 3), metres, the same (camera) frame.
    """
    pred = _points("pred_points", pred_points, 3)
    gt = _points("gt_points", gt_points, 3)
    if not isinstance(iterations, (int, np.integer)) or iterations < 0:
        raise ValueError(f"iterations must be a non-negative integer, got {iterations!r}")
    r_pred, r_gt = _rms_radius(pred), _rms_radius(gt)
    if r_pred <= 1e-12 or r_gt <= 1e-12:
        raise ValueError("pred_points and gt_points must not collapse to a single point")
    s0 = r_gt / r_pred
    start = Similarity(s0, np.eye(3), gt.mean(0) - s0 * pred.mean(0))
    sim, cd, steps = _correspondence_iterations(pred, gt, start, iterations, with_rotation=False)
    return AlignmentResult(sim, cd, 0.0, steps)


def _rotations(name: str, r) -> np.ndarray:
    a = np.asarray(r, dtype=np.float64)
    if a.ndim < 2 or a.shape[-2:] != (3, 3):
        raise ValueError(f"{name} must have shape (..., 3, 3), got {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name} contains non-finite values")
    err = np.abs(np.swapaxes(a, -1, -2) @ a - np.eye(3)).max() if a.size else 0.0
    if err > 1e-3 or (a.size and np.any(np.linalg.det(a) < 0)):
        raise ValueError(f"{name} must hold proper rotation matrices (R^T R = I, det +1); max |R^T R - I| = {err:.2e}")
    return a


def rotation_error_deg(r_pred: np.ndarray, r_gt: np.ndarray) -> np.ndarray | float:
    """Geodesic angle between rotations, degrees in [0, 180]: the angle of ``r_pred^T @ r_gt``.

    r_pred, r_gt: (..., 3, 3) world → camera rotations (broadcastable). Uses atan2 of the skew and symmetric parts,
    accurate near 0° and 180°. Returns a float for single matrices, else an array of the broadcast batch shape.
    """
    a = _rotations("r_pred", r_pred)
    b = _rotations("r_gt", r_gt)
    m = np.swapaxes(a, -1, -2) @ b
    skew = np.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1)
    sin = 0.5 * np.linalg.norm(skew, axis=-1)
    cos = 0.5 * (np.trace(m, axis1=-2, axis2=-1) - 1.0)
    ang = np.rad2deg(np.arctan2(sin, cos))
    return float(ang) if ang.ndim == 0 else ang


def evaluate_sample(pred_points: np.ndarray, gt_points: np.ndarray, *, up: Sequence[float] = (0.0, 1.0, 0.0),
                    pred_rotation: np.ndarray | None = None, gt_rotation: np.ndarray | None = None,
                    icp_iterations: int = 50, mv_iterations: int = 10) -> SampleMetrics:
    """All per-sample metrics of one prediction.

    pred_points: (N, 3) predicted posed points (occupied, confident entries of the point map), metres, camera frame.
    gt_points: (M, 3) points sampled on the ground-truth posed surface, metres, camera frame.
    up: (3,) world up in the camera frame (``gt_rotation @ (0, 1, 0)`` for a +Y-up world), for the ICP starts.
    pred_rotation, gt_rotation: (3, 3) world → camera rotations (predicted/fitted and true), or both None.
    Raises ValueError for fewer than 3 points or non-finite inputs (mark such samples failed upstream).
    """
    if (pred_rotation is None) != (gt_rotation is None):
        raise ValueError("pred_rotation and gt_rotation must be given together (or both None)")
    full = full_alignment(pred_points, gt_points, up=up, iterations=icp_iterations)
    mv = model_view_alignment(pred_points, gt_points, iterations=mv_iterations)
    rot = float("nan") if pred_rotation is None else rotation_error_deg(pred_rotation, gt_rotation)
    return SampleMetrics(
        cd_cm=full.rms_cd_cm, mv_cd_cm=mv.rms_cd_cm, rot_err_deg=float(rot),
        icp_scale=full.similarity.scale, icp_start_deg=full.start_angle_deg, mv_scale=mv.similarity.scale,
        n_pred=int(np.asarray(pred_points).shape[0]), n_gt=int(np.asarray(gt_points).shape[0]))


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean masks of the same shape (e.g. (H, W)); 1.0 when both are empty."""
    a, b = np.asarray(a, dtype=bool), np.asarray(b, dtype=bool)
    if a.shape != b.shape:
        raise ValueError(f"mask_iou: masks must have the same shape, got {a.shape} and {b.shape}")
    union = int(np.logical_or(a, b).sum())
    return 1.0 if union == 0 else float(np.logical_and(a, b).sum() / union)
