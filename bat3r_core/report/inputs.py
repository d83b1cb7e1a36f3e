"""The report's on-disk inputs written by the evaluation stage: the qualitative samples of an iteration
(``iter-NN/evaluate/qualitative.npz``, :data:`QUALITATIVE_FILE`; format in ``bat3r_core.report``)."""
from __future__ import annotations

import io
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from bat3r_core.shards import atomic_write_bytes

__all__ = ["QUALITATIVE_FILE", "QualitativeInputs", "write_report_inputs", "read_report_inputs"]

QUALITATIVE_FILE = "qualitative.npz"


# ---------------------------------------------------------------------------------------------- report inputs

@dataclass(frozen=True)
class QualitativeInputs:
    """Contents of ``qualitative.npz`` (see the module docstring for shapes, units and frames)."""

    sample_id: np.ndarray
    image: np.ndarray
    intrinsics: np.ndarray
    pred_points: np.ndarray
    mask: np.ndarray | None = None
    fitted_verts: np.ndarray | None = None
    faces: np.ndarray | None = None
    cd_cm: np.ndarray | None = None


def write_report_inputs(stage_dir: str | os.PathLike, *, sample_ids: Sequence[str], images: np.ndarray,
                        intrinsics: np.ndarray, pred_points: Sequence[np.ndarray], masks: np.ndarray | None = None,
                        fitted_verts: np.ndarray | None = None, faces: np.ndarray | None = None,
                        cd_cm: Sequence[float] | None = None, max_points: int = 3000, seed: int = 0) -> Path:
    """Write ``stage_dir/qualitative.npz`` for the report's qualitative grid, atomically.

    sample_ids: S ids. images: (S, H, W, 3) uint8. intrinsics: (S, 3, 3) pixels of ``images``.
    pred_points: S arrays (P_s, 3), metres, camera frame with absolute depth; each is subsampled (seeded) to at most
    ``max_points`` and NaN-padded to a common length. masks: (S, H, W) bool. fitted_verts: (S, V, 3) metres, camera
    frame (NaN for samples without a fit), with faces (F, 3) int. cd_cm: (S,) per-sample RMS Chamfer (cm).
    """
    ids = [str(s) for s in sample_ids]
    s = len(ids)
    images = np.asarray(images)
    if images.ndim != 4 or images.shape[0] != s or images.shape[-1] != 3 or images.dtype != np.uint8:
        raise ValueError(f"images must be (S={s}, H, W, 3) uint8, got {images.shape} {images.dtype}")
    k = np.asarray(intrinsics, dtype=np.float32)
    if k.shape != (s, 3, 3):
        raise ValueError(f"intrinsics must have shape ({s}, 3, 3), got {k.shape}")
    if len(pred_points) != s:
        raise ValueError(f"pred_points must hold {s} arrays, got {len(pred_points)}")
    rng = np.random.default_rng(seed)
    clouds = []
    for i, p in enumerate(pred_points):
        p = np.asarray(p, dtype=np.float32)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"pred_points[{i}] must have shape (P, 3), got {p.shape}")
        if len(p) > max_points:
            p = p[np.sort(rng.choice(len(p), max_points, replace=False))]
        clouds.append(p)
    width = max([len(p) for p in clouds] + [1])
    padded = np.full((s, width, 3), np.nan, dtype=np.float32)
    for i, p in enumerate(clouds):
        padded[i, : len(p)] = p
    arrays = {"sample_id": np.asarray(ids, dtype=str), "image": images, "intrinsics": k, "pred_points": padded}
    if masks is not None:
        masks = np.asarray(masks, dtype=bool)
        if masks.shape != images.shape[:3]:
            raise ValueError(f"masks must have shape {images.shape[:3]}, got {masks.shape}")
        arrays["mask"] = masks
    if (fitted_verts is None) != (faces is None):
        raise ValueError("fitted_verts and faces must be given together")
    if fitted_verts is not None:
        fv = np.asarray(fitted_verts, dtype=np.float32)
        fc = np.asarray(faces)
        if fv.ndim != 3 or fv.shape[0] != s or fv.shape[2] != 3:
            raise ValueError(f"fitted_verts must have shape ({s}, V, 3), got {fv.shape}")
        if fc.ndim != 2 or fc.shape[1] != 3 or not np.issubdtype(fc.dtype, np.integer):
            raise ValueError(f"faces must be an (F, 3) integer array, got {fc.shape} {fc.dtype}")
        arrays["fitted_verts"], arrays["faces"] = fv, fc.astype(np.int32)
    if cd_cm is not None:
        cd = np.asarray(cd_cm, dtype=np.float32)
        if cd.shape != (s,):
            raise ValueError(f"cd_cm must have shape ({s},), got {cd.shape}")
        arrays["cd_cm"] = cd
    path = Path(stage_dir) / QUALITATIVE_FILE
    atomic_write_bytes(path, _npz_bytes(arrays))
    return path


def _npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def read_report_inputs(path: str | os.PathLike) -> QualitativeInputs:
    """Load a ``qualitative.npz`` written by ``write_report_inputs`` (``allow_pickle=False``)."""
    with np.load(path, allow_pickle=False) as z:
        missing = [k for k in ("sample_id", "image", "intrinsics", "pred_points") if k not in z.files]
        if missing:
            raise ValueError(f"{path} lacks array(s) {missing}")
        get = lambda k: z[k] if k in z.files else None  # noqa: E731
        return QualitativeInputs(z["sample_id"], z["image"], z["intrinsics"], z["pred_points"], get("mask"),
                                 get("fitted_verts"), get("faces"), get("cd_cm"))
