"""Camera recovery after fitting: rotation from the global similarity, translation from pixels.

The predicted posed points are camera-frame points relative to the object depth, so the fitted global rotation
``R_g`` is the camera rotation (world = canonical frame of the articulated mesh) but the translation is not
observed. With the fitted points ``X_i = R_g x_i`` (the articulated mesh vertices matched to layer-0 pixels,
rotated into the camera orientation) and their pixels ``(u_i, v_i)``, the translation ``t`` satisfies, per point,

    fx (X + tx) − (u − cx)(Z + tz) = 0,   fy (Y + ty) − (v − cy)(Z + tz) = 0,

two equations linear in ``t``: two points fix it. RANSAC draws 2-point samples (100 iterations), scores the
reprojection error against a threshold (5 px), and the best hypothesis is refined on its inliers by least squares
(linear solve, then Gauss–Newton on the reprojection error). An optional focal search repeats this over a grid of
focal lengths and keeps the one with the lowest truncated squared reprojection error (MSAC cost
``mean(min(e², threshold²))``, which rewards both more inliers and smaller errors).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["CameraEstimate", "recover_translation", "recover_camera"]


@dataclass(frozen=True, eq=False)
class CameraEstimate:
    """A recovered camera (OpenCV, world → camera ``x_cam = R x + t``; world = the fitted mesh's canonical frame).

    Attributes:
        rotation: (3, 3). translation: (3,) metres. intrinsics: (3, 3) pixels (focal possibly re-estimated).
        inlier_ratio: fraction of layer-0 correspondences within the RANSAC threshold.
        reprojection_error_px: RMS reprojection error of the inliers, pixels.
        image_size: (width, height) or None.
    """

    rotation: np.ndarray
    translation: np.ndarray
    intrinsics: np.ndarray
    inlier_ratio: float
    reprojection_error_px: float
    image_size: tuple[int, int] | None = None


def _system(points: np.ndarray, pixels: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear equations ``A t = b`` (2 per point): A (N, 2, 3), b (N, 2)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    du, dv = pixels[:, 0] - cx, pixels[:, 1] - cy
    n = len(points)
    A = np.zeros((n, 2, 3))
    A[:, 0, 0], A[:, 0, 2] = fx, -du
    A[:, 1, 1], A[:, 1, 2] = fy, -dv
    b = np.stack([du * points[:, 2] - fx * points[:, 0], dv * points[:, 2] - fy * points[:, 1]], 1)
    return A, b


def _reprojection(points: np.ndarray, pixels: np.ndarray, K: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Reprojection errors (pixels) of ``points`` (N, 3) under translations ``t`` (H, 3) → (H, N)."""
    x = points[None] + t[:, None, :]  # (H, N, 3)
    z = x[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * x[..., 0] / z + K[0, 2]
        v = K[1, 1] * x[..., 1] / z + K[1, 2]
    err = np.hypot(u - pixels[None, :, 0], v - pixels[None, :, 1])
    return np.where(z > 0, err, np.inf)


def _refine(points: np.ndarray, pixels: np.ndarray, K: np.ndarray, t: np.ndarray, iterations: int = 10) -> np.ndarray:
    """Least squares on inliers: linear solve, then Gauss–Newton on the reprojection error."""
    A, b = _system(points, pixels, K)
    t = np.linalg.lstsq(A.reshape(-1, 3), b.reshape(-1), rcond=None)[0]
    fx, fy = K[0, 0], K[1, 1]
    for _ in range(iterations):
        x = points + t
        z = x[:, 2]
        if (z <= 0).any():
            break
        res = np.concatenate([fx * x[:, 0] / z + K[0, 2] - pixels[:, 0], fy * x[:, 1] / z + K[1, 2] - pixels[:, 1]])
        J = np.zeros((2 * len(points), 3))
        J[: len(points), 0] = fx / z
        J[: len(points), 2] = -fx * x[:, 0] / z ** 2
        J[len(points):, 1] = fy / z
        J[len(points):, 2] = -fy * x[:, 1] / z ** 2
        step = np.linalg.lstsq(J, -res, rcond=None)[0]
        t = t + step
        if np.linalg.norm(step) < 1e-10:
            break
    return t


def recover_translation(points: np.ndarray, pixels: np.ndarray, intrinsics: np.ndarray, rng: np.random.Generator,
                        iterations: int = 100, threshold_px: float = 5.0) -> tuple[np.ndarray, np.ndarray, float]:
    """2-point RANSAC for the camera translation.

    Args:
        points: (N, 3) metres, fitted points rotated into the camera orientation (``R x``), N >= 2.
        pixels: (N, 2) their pixel coordinates ``(u, v)``.
        intrinsics: (3, 3) pixels.
        rng: sample generator. iterations: RANSAC hypotheses. threshold_px: inlier reprojection threshold.
    Returns:
        translation (3,) metres, inlier mask (N,) bool, RMS reprojection error of the inliers (pixels).
    """
    X = np.asarray(points, dtype=np.float64)
    uv = np.asarray(pixels, dtype=np.float64)
    K = np.asarray(intrinsics, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or X.shape[0] < 2:
        raise ValueError(f"points must have shape (N, 3) with N >= 2, got {X.shape}")
    if uv.shape != (len(X), 2):
        raise ValueError(f"pixels must have shape ({len(X)}, 2), got {uv.shape}")
    if K.shape != (3, 3):
        raise ValueError(f"intrinsics must have shape (3, 3), got {K.shape}")
    A, b = _system(X, uv, K)
    pick = np.stack([rng.choice(len(X), size=2, replace=False) for _ in range(iterations)])  # (H, 2)
    Ah = A[pick].reshape(iterations, 4, 3)
    bh = b[pick].reshape(iterations, 4)
    # normal equations per hypothesis, (H, 3, 3) and (H, 3)
    ata = np.einsum("hki,hkj->hij", Ah, Ah) + 1e-12 * np.eye(3)
    atb = np.einsum("hki,hk->hi", Ah, bh)
    t_h = np.linalg.solve(ata, atb[..., None])[..., 0]
    err = _reprojection(X, uv, K, t_h)  # (H, N)
    inl = err < threshold_px
    count = inl.sum(1)
    score = np.where(inl, err, 0.0).sum(1)
    best = int(np.lexsort((score, -count))[0])
    mask = inl[best]
    if mask.sum() < 2:
        mask = np.ones(len(X), dtype=bool)
    t = _refine(X[mask], uv[mask], K, t_h[best])
    e = _reprojection(X, uv, K, t[None])[0]
    mask = e < threshold_px
    if mask.sum() >= 2:
        t = _refine(X[mask], uv[mask], K, t)
        e = _reprojection(X, uv, K, t[None])[0]
        mask = e < threshold_px
    rms = float(np.sqrt(np.mean(e[mask] ** 2))) if mask.any() else float("inf")
    return t, mask, rms


def recover_camera(rotation: np.ndarray, points: np.ndarray, pixels: np.ndarray, intrinsics: np.ndarray,
                   rng: np.random.Generator, fit_focal: bool = False,
                   focal_factors: np.ndarray = np.geomspace(0.5, 2.0, 15), iterations: int = 100,
                   threshold_px: float = 5.0, image_size: tuple[int, int] | None = None) -> CameraEstimate:
    """The camera of one fitted instance.

    Args:
        rotation: (3, 3) world → camera rotation (the fitted global rotation).
        points: (N, 3) ``rotation @ x`` for the fitted world points matched to layer-0 pixels, metres.
        pixels: (N, 2). intrinsics: (3, 3) of the image the pixels refer to.
        fit_focal: search the focal length over ``focal_factors`` times the given one (lowest MSAC cost),
            keeping the principal point.
    """
    K0 = np.asarray(intrinsics, dtype=np.float64)
    candidates = focal_factors if fit_focal else np.array([1.0])
    best = None
    for f in candidates:
        K = K0.copy()
        K[0, 0] *= f
        K[1, 1] *= f
        t, mask, rms = recover_translation(points, pixels, K, rng, iterations, threshold_px)
        err = _reprojection(np.asarray(points, dtype=np.float64), np.asarray(pixels, dtype=np.float64), K, t[None])[0]
        key = float(np.mean(np.minimum(err ** 2, threshold_px ** 2)))
        if best is None or key < best[0]:
            best = (key, K, t, mask, rms)
    _, K, t, mask, rms = best
    return CameraEstimate(rotation=np.asarray(rotation, dtype=np.float64), translation=t, intrinsics=K,
                          inlier_ratio=float(mask.mean()), reprojection_error_px=rms,
                          image_size=None if image_size is None else (int(image_size[0]), int(image_size[1])))
