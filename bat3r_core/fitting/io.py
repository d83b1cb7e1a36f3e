"""File formats of the fitting stage: the predicted points npz (input) and fit shards (output).

Points npz (``allow_pickle=False``; B instances, N_b points each, concatenated in instance order):

* ``offsets`` (B + 1,) int64: instance ``b`` owns rows ``offsets[b]:offsets[b + 1]`` of the point arrays.
* ``posed_points`` (ΣN, 3) float32: predicted posed points, metres, camera frame **relative to the object depth**
  (``P − (0, 0, object_depth)``, docs/CONVENTIONS.md).
* ``canonical_points`` (ΣN, 3) float32: predicted canonical points, metres, canonical frame.
* ``confidence`` (ΣN,) float32, optional: ``C = 1 + exp(c)``.
* ``pixels`` (ΣN, 2) float32: pixel ``(u, v)`` of each point. ``layers`` (ΣN,) int: layer (0 = front).
* ``intrinsics`` (B, 3, 3) float32: pixels of the image the pixels refer to. ``image_size`` (B, 2) int32 (W, H).
* ``sample_id`` (B,) unicode strings.
* ``masks`` (B, H, W) bool, optional: each image's mask (the silhouette term, ``FittingConfig.weight_silhouette``;
  without it the term uses the layer-0 pixels). Every instance's ``image_size`` must then be (W, H).

Fit shards (:mod:`bat3r_core.shards`): one Parquet row per instance with the columns of :data:`FIT_COLUMNS`, and
an npz with ``posed_vertices (B, V, 3) float32`` (the unscaled articulated mesh after the global similarity, in
the prediction frame; NaN for unfitted rows).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from bat3r_core.cameras import PinholeCamera
from bat3r_core.metrics import to_cm
from bat3r_core.shards import ShardPaths, write_shard

from .config import FittingConfig
from .fit import LOSS_NAMES, FitResult, FittingAsset, PointCloudInstance

__all__ = ["write_points_npz", "read_points_npz", "fit_rows", "write_fit_shard", "camera_from_row", "FIT_COLUMNS",
           "load_asset_rig", "fit_points_file"]

FIT_COLUMNS = (
    "sample_id", "status", "reason", "excess_rotations", "bone_scales", "global_scale", "global_rotation",
    "global_translation", "fx", "fy", "cx", "cy", "width", "height", "camera_rotation", "camera_translation",
    "camera_inlier_ratio", "camera_reprojection_px", *(f"loss_{n}" for n in LOSS_NAMES), "residual_chamfer_cm",
    "inlier_ratio", "mean_confidence", "num_points", "num_inliers", "num_control_points")
"""Columns of a fit shard row (list columns hold row-major flattened arrays)."""


def write_points_npz(path: str | os.PathLike, instances: list[PointCloudInstance]) -> Path:
    """Write instances in the points npz format (every instance needs pixels, layers, intrinsics and image size;
    confidence must be given for all instances or none)."""
    if not instances:
        raise ValueError("instances must not be empty")
    with_conf = [i.confidence is not None for i in instances]
    if any(with_conf) and not all(with_conf):
        raise ValueError("confidence must be given for all instances or for none")
    for i in instances:
        if i.pixels is None or i.layers is None or i.intrinsics is None or i.image_size is None:
            raise ValueError(f"instance {i.sample_id!r}: pixels, layers, intrinsics and image_size are required")
    counts = [len(np.asarray(i.posed_points)) for i in instances]
    arrays = {
        "offsets": np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        "posed_points": np.concatenate([np.asarray(i.posed_points, np.float32).reshape(-1, 3) for i in instances]),
        "canonical_points": np.concatenate([np.asarray(i.canonical_points, np.float32).reshape(-1, 3)
                                            for i in instances]),
        "pixels": np.concatenate([np.asarray(i.pixels, np.float32).reshape(-1, 2) for i in instances]),
        "layers": np.concatenate([np.asarray(i.layers, np.int64).reshape(-1) for i in instances]),
        "intrinsics": np.stack([np.asarray(i.intrinsics, np.float32) for i in instances]),
        "image_size": np.array([i.image_size for i in instances], dtype=np.int32),
        "sample_id": np.array([str(i.sample_id) for i in instances]),
    }
    if all(with_conf):
        arrays["confidence"] = np.concatenate([np.asarray(i.confidence, np.float32).reshape(-1) for i in instances])
    with_mask = [i.mask is not None for i in instances]
    if any(with_mask) and not all(with_mask):
        raise ValueError("mask must be given for all instances or for none")
    if all(with_mask):
        shapes = {np.asarray(i.mask).shape for i in instances}
        if len(shapes) != 1:
            raise ValueError(f"masks must all have one shape (H, W), got {sorted(shapes)}")
        arrays["masks"] = np.stack([np.asarray(i.mask, dtype=bool) for i in instances])
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)
    os.replace(tmp, path)
    return path


_REQUIRED = ("offsets", "posed_points", "canonical_points", "pixels", "layers", "intrinsics", "image_size",
             "sample_id")


def read_points_npz(path: str | os.PathLike) -> list[PointCloudInstance]:
    """Read a points npz (see the module docstring); ``ValueError`` naming the file and array when malformed."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"points file {path} does not exist")
    with np.load(path, allow_pickle=False) as z:
        missing = [k for k in _REQUIRED if k not in z.files]
        if missing:
            raise ValueError(f"{path}: missing array(s) {missing}; a points npz needs {list(_REQUIRED)}")
        a = {k: z[k] for k in z.files}
    off = a["offsets"].astype(np.int64)
    b = len(a["sample_id"])
    total = len(a["posed_points"])
    if off.shape != (b + 1,) or off[0] != 0 or off[-1] != total or (np.diff(off) < 0).any():
        raise ValueError(f"{path}: offsets must be ({b + 1},) non-decreasing from 0 to {total}, got {off.tolist()[:8]}")
    shapes = {"posed_points": (total, 3), "canonical_points": (total, 3), "pixels": (total, 2), "layers": (total,),
              "intrinsics": (b, 3, 3), "image_size": (b, 2)}
    if "confidence" in a:
        shapes["confidence"] = (total,)
    if "masks" in a:
        if a["masks"].ndim != 3 or a["masks"].dtype != bool:
            raise ValueError(f"{path}: array 'masks' must be (B, H, W) bool, got {a['masks'].shape} "
                             f"{a['masks'].dtype}")
        h, w = a["masks"].shape[1:]
        shapes["masks"] = (b, h, w)
        if b and not (a["image_size"] == [w, h]).all():
            raise ValueError(f"{path}: array 'masks' is {h}x{w} (H x W) but 'image_size' holds other sizes; "
                             "every image_size must be (W, H) of the masks")
    for k, shape in shapes.items():
        if a[k].shape != shape:
            raise ValueError(f"{path}: array '{k}' must have shape {shape}, got {a[k].shape}")
    out = []
    for i in range(b):
        s = slice(off[i], off[i + 1])
        out.append(PointCloudInstance(
            sample_id=str(a["sample_id"][i]), posed_points=a["posed_points"][s].astype(np.float64),
            canonical_points=a["canonical_points"][s].astype(np.float64),
            confidence=a["confidence"][s].astype(np.float64) if "confidence" in a else None,
            pixels=a["pixels"][s].astype(np.float64), layers=a["layers"][s].astype(np.int64),
            intrinsics=a["intrinsics"][i].astype(np.float64),
            image_size=(int(a["image_size"][i, 0]), int(a["image_size"][i, 1])),
            mask=a["masks"][i] if "masks" in a else None))
    return out


def _flat(a) -> list[float]:
    return np.asarray(a, dtype=np.float64).reshape(-1).tolist()


def fit_rows(result: FitResult) -> list[dict]:
    """One row (dict with :data:`FIT_COLUMNS`) per instance of a :class:`FitResult`."""
    rows = []
    nan3, nan9 = [float("nan")] * 3, [float("nan")] * 9
    for k, sid in enumerate(result.sample_id):
        cam = result.cameras[k] if result.cameras else None
        K = cam.intrinsics if cam is not None else np.full((3, 3), np.nan)
        size = cam.image_size if cam is not None and cam.image_size is not None else (0, 0)
        row = {
            "sample_id": sid, "status": result.status[k], "reason": result.reason[k],
            "excess_rotations": _flat(result.excess_rotations[k]), "bone_scales": _flat(result.bone_scales[k]),
            "global_scale": float(result.global_scale[k]), "global_rotation": _flat(result.global_rotation[k]),
            "global_translation": _flat(result.global_translation[k]),
            "fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
            "width": int(size[0]), "height": int(size[1]),
            "camera_rotation": _flat(cam.rotation) if cam is not None else nan9,
            "camera_translation": _flat(cam.translation) if cam is not None else nan3,
            "camera_inlier_ratio": cam.inlier_ratio if cam is not None else float("nan"),
            "camera_reprojection_px": cam.reprojection_error_px if cam is not None else float("nan"),
        }
        for n in LOSS_NAMES:
            row[f"loss_{n}"] = float(result.losses[n][k])
        row.update({"residual_chamfer_cm": float(to_cm(float(result.residual_chamfer[k]))),
                    "inlier_ratio": float(result.inlier_ratio[k]),
                    "mean_confidence": float(result.mean_confidence[k]),
                    "num_points": int(result.num_points[k]), "num_inliers": int(result.num_inliers[k]),
                    "num_control_points": int(result.num_control_points[k])})
        rows.append(row)
    return rows


def write_fit_shard(folder: str | os.PathLike, index: int, result: FitResult) -> ShardPaths:
    """Write a :class:`FitResult` as shard ``index`` of ``folder`` (Parquet rows + ``posed_vertices`` npz)."""
    return write_shard(folder, index, fit_rows(result),
                       arrays={"posed_vertices": np.asarray(result.posed_vertices, dtype=np.float32)})


def camera_from_row(row: dict) -> PinholeCamera | None:
    """The recovered camera of a fit row, or None when it has none (unfitted, or no pixels/intrinsics)."""
    vals = [row["fx"], row["fy"], row["cx"], row["cy"], *row["camera_rotation"], *row["camera_translation"]]
    if row["status"] != "ok" or not np.isfinite(vals).all() or row["width"] < 1 or row["height"] < 1:
        return None
    return PinholeCamera(row["fx"], row["fy"], row["cx"], row["cy"], int(row["width"]), int(row["height"]),
                         np.asarray(row["camera_rotation"]).reshape(3, 3), np.asarray(row["camera_translation"]))


def load_asset_rig(asset: str | os.PathLike):
    """The rig of ``asset``: the literal ``"toy"`` builds the embedded toy; otherwise a rigged mesh file
    (:func:`bat3r_core.rig_io.load_rig`)."""
    if str(asset) == "toy":
        from bat3r_core.toy import build_toy_rig

        return build_toy_rig()
    from bat3r_core.rig_io import load_rig

    return load_rig(asset)


def fit_points_file(asset_path: str | os.PathLike, points_npz: str | os.PathLike, preset: str | FittingConfig,
                    out_dir: str | os.PathLike, *, shard_size: int = 256, device: str = "cpu",
                    overrides: dict | None = None, cache_dir: str | os.PathLike | None = None,
                    fit_focal: bool = False) -> dict:
    """``bat3r fit``: fit the asset's rig to every instance of a points npz and write fit shards to ``out_dir``.

    Args:
        asset_path: rigged mesh file, or ``"toy"``.
        points_npz: predicted points (format in the module docstring).
        preset: ``"synthetic"`` or ``"real"`` (the data catalog's ``fitting_presets``), or a ready
            :class:`~.config.FittingConfig`; ``overrides`` change single fields (e.g. ``{"inlier_distance": 0.05}``).
        out_dir: stage folder; shards ``part-00000`` … of ``shard_size`` instances each (fitted as one batch).
        device: torch device of the optimisation (``"cpu"`` or ``"cuda"``).
        cache_dir: geodesics cache folder (default: :func:`~.geodesics.default_cache_dir`).
        fit_focal: also search the focal length in camera recovery.
    Returns:
        ``{"shards": [parquet paths], "num_instances": n, "num_ok": k}``.
    """
    from bat3r_core.config_utils import replace_path

    from bat3r_core.catalog import fitting_preset
    from .fit import fit_batch

    if isinstance(shard_size, bool) or not isinstance(shard_size, int) or shard_size < 1:
        raise ValueError(f"shard_size must be an int >= 1, got {shard_size!r}")
    if isinstance(preset, FittingConfig):
        config = preset
        for key, value in (overrides or {}).items():
            config = replace_path(config, key, value)
    else:
        config = fitting_preset(preset, overrides)
    instances = read_points_npz(points_npz)
    rig = load_asset_rig(asset_path)
    asset = FittingAsset.prepare(rig, config, cache_dir=cache_dir, device=device)
    shards, ok = [], 0
    for index, start in enumerate(range(0, len(instances), shard_size)):
        result = fit_batch(asset, instances[start:start + shard_size], config, fit_focal=fit_focal)
        ok += sum(s == "ok" for s in result.status)
        shards.append(str(write_fit_shard(out_dir, index, result).parquet))
    return {"shards": shards, "num_instances": len(instances), "num_ok": ok}


def instances_from_predictions(predictions_dir: str | os.PathLike, index: int, camera: PinholeCamera
                               ) -> tuple[list[PointCloudInstance], list[dict]]:
    """Point-cloud instances of inference shard ``index`` (``bat3r_core.predictor.infer`` output).

    Every row of the shard becomes an instance (rows whose prediction failed get no points, so fitting records
    them as unfitted). The confidence of a point is the smaller of its canonical and posed confidences; the mask
    is the input mask the shard stores (the silhouette term's).

    Args:
        camera: the nominal camera of the model's crops (intrinsics and image size; e.g.
            ``PinholeCamera.from_fov(prior.fov_deg, R, R)``, the field of view the training renders used).
    Returns:
        (instances, prediction rows) in shard row order.
    """
    from bat3r_core.predictor.infer import clouds_path, load_clouds
    from bat3r_core.shards import read_shard

    table, _ = read_shard(predictions_dir, index, with_arrays=False)
    rows = table.to_pylist()
    masks = _prediction_masks(predictions_dir, index, len(rows))
    clouds = load_clouds(clouds_path(predictions_dir, index))
    if len(clouds) != len(rows):
        raise ValueError(f"{predictions_dir}: shard {index} has {len(rows)} rows but its clouds hold {len(clouds)} "
                         "instances")
    if not isinstance(camera, PinholeCamera):
        raise TypeError(f"camera must be a PinholeCamera, got {type(camera).__name__}")
    k, size = np.asarray(camera.K, dtype=np.float64), (camera.width, camera.height)
    out = []
    for i, row in enumerate(rows):
        c = clouds.instance(i)
        ok = row["status"] == "ok"
        n = len(c["posed_points"]) if ok else 0
        conf = np.minimum(c["canonical_confidence"], c["posed_confidence"])[:n].astype(np.float64)
        out.append(PointCloudInstance(
            sample_id=row["sample_id"], posed_points=c["posed_points"][:n].astype(np.float64),
            canonical_points=c["canonical_points"][:n].astype(np.float64), confidence=conf,
            pixels=c["pixels"][:n].astype(np.float64), layers=c["layers"][:n].astype(np.int64), intrinsics=k,
            image_size=size, mask=None if masks is None else masks[i]))  # a wrong size: fitting names it
    return out, rows


def _prediction_masks(predictions_dir: str | os.PathLike, index: int, rows: int) -> np.ndarray | None:
    """The input masks ``(N, H, W) bool`` an inference shard stores beside its maps (None when it has none: a shard
    without arrays, or one written before the masks were kept)."""
    from bat3r_core.shards import shard_paths

    npz = shard_paths(predictions_dir, index).npz
    if not npz.is_file():
        return None
    with np.load(npz, allow_pickle=False) as z:
        if "mask" not in z.files:
            return None
        masks = z["mask"]
    if masks.ndim != 3 or len(masks) != rows:
        raise ValueError(f"{npz}: array 'mask' must be ({rows}, H, W), got {masks.shape}")
    return masks.astype(bool)


def fit_prediction_shard(asset: FittingAsset, predictions_dir: str | os.PathLike, index: int,
                         out_dir: str | os.PathLike, config: FittingConfig, camera: PinholeCamera,
                         fit_focal: bool = False) -> ShardPaths:
    """Fit the rig to every instance of inference shard ``index`` and write fit shard ``index`` of ``out_dir``.

    Rows whose prediction failed keep their prediction status and reason (prefixed ``prediction:``), so a bad
    image stays traceable through the stages.
    """
    from .fit import fit_batch

    instances, pred_rows = instances_from_predictions(predictions_dir, index, camera)
    result = fit_batch(asset, instances, config, fit_focal=fit_focal)
    rows = fit_rows(result)
    for row, pred in zip(rows, pred_rows):
        if pred["status"] != "ok":
            row["status"], row["reason"] = pred["status"], f"prediction: {pred['reason']}"
    return write_shard(out_dir, index, rows,
                       arrays={"posed_vertices": np.asarray(result.posed_vertices, dtype=np.float32)})
