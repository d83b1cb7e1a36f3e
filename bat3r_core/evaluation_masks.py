"""Evaluation without 3D ground truth: mask IoU of the predictor and of the reprojected fits on the collection.

For real photo collections there are no 3D labels, only the foreground masks. Per iteration ``i`` and collection
image (at the model's crop and resolution, the masks the predictor saw):

* ``pred_mask_iou``: IoU of Φ_i's predicted layer-0 occupancy, thresholded like inference (probability
  ``> MIN_OCCUPANCY`` = 0.5), with the image's mask. The predictor's occupancy is 0 outside the input mask, so this
  IoU is the fraction of mask pixels Φ_i calls occupied (a missed part lowers it; nothing can be added outside).
* ``fit_mask_iou``: IoU of the fitted mesh's silhouette with the mask. The mesh is the rig posed by the fitted θ
  (unit bone scales, canonical frame: the world of the recovered camera, as view planning renders it), ray-cast
  through the fit's recovered camera (``bat3r_core.fitting.io.camera_from_row``, intrinsics and image size of the
  crop) with :func:`bat3r_core.pointmaps.dual_point_maps` (one layer): the silhouette is the pixels whose ray hits
  the mesh, the same ray casting as the training labels.

Which fits belong to iteration ``i``: the flow runs, in iteration ``i >= 1``, infer(Φ_{i-1}) → fit → … → train Φ_i,
then evaluates Φ_i. The fits of ``iter-ii/fit`` are therefore the pseudo-labels Φ_i was trained on (the same
convention as ``pseudo_labels.parquet``); ``pred_mask_iou`` is Φ_i's own prediction of the collection (an extra
inference of the collection by Φ_i, ``iter-ii/evaluate/collection_infer``). Iteration 0 has no fits:
``fit_mask_iou`` is null and ``n_fits`` 0 there.

Files: ``iter-NN/evaluate/collection/part-NNNNN.parquet``, one row per collection image (``COLLECTION_SCHEMA``);
:func:`aggregate_collection` turns them into the ``split == "collection"`` rows of ``metrics.parquet``
(``METRICS_SCHEMA`` columns, the Chamfer ones null, plus ``COLLECTION_METRIC_COLUMNS``).
"""
from __future__ import annotations

import math
import os
from typing import Any, Mapping, Sequence

import numpy as np
import pyarrow as pa

from bat3r_core import shards, stages
from bat3r_core.metrics import mask_iou

__all__ = ["COLLECTION_SPLIT", "COLLECTION_SCHEMA", "COLLECTION_METRIC_COLUMNS", "COLLECTION_ROWS_DIR",
           "COLLECTION_INFER_DIR", "read_masks", "predicted_mask", "fit_silhouette", "fit_silhouettes",
           "collection_rows", "evaluate_collection_shard", "read_collection_rows", "aggregate_collection"]

COLLECTION_SPLIT = "collection"
COLLECTION_ROWS_DIR = stages.stage(stages.EVALUATE_COLLECTION).folder.split("/")[-1]
"""Per-sample rows: ``iter-NN/evaluate/collection/``."""
COLLECTION_INFER_DIR = stages.stage(stages.COLLECTION_INFER).folder.split("/")[-1]
"""Φ_i's predictions of the collection: ``iter-NN/evaluate/collection_infer/``."""
MIN_OCCUPANCY = 0.5
"""Occupancy threshold, as in ``bat3r_core.predictor.infer.MIN_OCCUPANCY``."""

COLLECTION_SCHEMA = pa.schema([
    ("sample_id", pa.string()),
    ("split", pa.string()),            # "collection"
    ("iteration", pa.int64()),         # the iteration whose predictor (and pseudo-labels) were evaluated
    ("status", pa.string()),           # the prediction's status ("ok" or its code)
    ("reason", pa.string()),
    ("pred_mask_iou", pa.float64()),   # NaN unless status is ok
    ("mask_pixels", pa.int64()),
    ("pred_pixels", pa.int64()),       # layer-0 pixels with occupancy > 0.5
    ("fit_status", pa.string()),       # "ok", "no_fit" (none of this iteration), "no_camera" or the fit's status
    ("fit_mask_iou", pa.float64()),    # NaN unless fit_status is ok
    ("fit_pixels", pa.int64()),        # silhouette pixels of the reprojected fit
])

COLLECTION_METRIC_COLUMNS = ("pred_mask_iou", "fit_mask_iou", "n_fits")
"""Columns of the ``collection`` rows of ``metrics.parquet`` beyond ``METRICS_SCHEMA``: mean ``pred_mask_iou``
over the ok predictions (``n`` of them), mean ``fit_mask_iou`` over the evaluated fits, their count ``n_fits``."""


def read_masks(collection_dir: str | os.PathLike) -> dict[str, np.ndarray]:
    """Sample id → foreground mask ``(H, W) bool`` of every complete shard of ``collection_dir`` (a run's
    ``collection`` stage: the crops at the model's resolution)."""
    masks: dict[str, np.ndarray] = {}
    for i in shards.list_shards(collection_dir):
        masks.update(_shard_masks(collection_dir, i))
    return masks


def _shard_masks(collection_dir: str | os.PathLike, index: int) -> dict[str, np.ndarray]:
    """Sample id → mask of collection shard ``index``; a clear error naming the shard when it has no masks."""
    table, arrays = shards.read_shard(collection_dir, index)
    if "mask" not in arrays:
        raise ValueError(f"collection shard {index} of {collection_dir} has no 'mask' array")
    return {str(s): np.asarray(m, dtype=bool) for s, m in zip(table.column("sample_id").to_pylist(), arrays["mask"])}


def predicted_mask(occupancy: np.ndarray, threshold: float = MIN_OCCUPANCY) -> np.ndarray:
    """(H, W) bool layer-0 occupancy of a prediction: occupancy (H, W, K) or (H, W) probabilities ``> threshold``."""
    occ = np.asarray(occupancy, dtype=np.float32)
    if occ.ndim == 3:
        occ = occ[..., 0]
    if occ.ndim != 2:
        raise ValueError(f"occupancy must have shape (H, W, K) or (H, W), got {occ.shape}")
    return occ > threshold


def fit_silhouettes(rig, fit_rows: Sequence[Mapping[str, Any]]) -> list[np.ndarray | None]:
    """Silhouettes ``(height, width) bool`` of fitted meshes seen through their recovered cameras (module docstring);
    None for a row without a camera (not ok, or no recovered translation)."""
    import torch

    from bat3r_core.fitting.io import camera_from_row
    from bat3r_core.pointmaps import dual_point_maps
    from bat3r_core.skinning import skin

    cams = [camera_from_row(dict(r)) for r in fit_rows]
    use = [k for k, c in enumerate(cams) if c is not None]
    out: list[np.ndarray | None] = [None] * len(cams)
    if not use:
        return out
    j = rig.num_joints
    theta = np.stack([np.asarray(fit_rows[k]["excess_rotations"], np.float64).reshape(j, 3) for k in use])
    verts = skin(rig.tensors(dtype=torch.float64), torch.as_tensor(theta)).vertices.numpy()
    for n, k in enumerate(use):
        maps = dual_point_maps(verts[n], rig.rest_vertices, rig.faces, cams[k], num_layers=1, nthreads=1)
        out[k] = np.asarray(maps.occupancy[..., 0], dtype=bool)
    return out


def fit_silhouette(rig, fit_row: Mapping[str, Any]) -> np.ndarray | None:
    """:func:`fit_silhouettes` of one fit row."""
    return fit_silhouettes(rig, [fit_row])[0]


def collection_rows(iteration: int, predictions: Sequence[Mapping[str, Any]], occupancy: np.ndarray,
                    masks: Mapping[str, np.ndarray], fits: Sequence[Mapping[str, Any]] | None, rig=None
                    ) -> list[dict[str, Any]]:
    """Per-sample ``COLLECTION_SCHEMA`` rows of one shard of collection predictions.

    predictions: the prediction rows (``sample_id, status, reason``); occupancy: (N, H, W, K) their occupancy
    (prediction npz, same order). masks: sample id → (H, W) bool collection mask at the model's crop (the masks the
    predictor saw). fits: this iteration's fit rows (``bat3r_core.fitting.io.FIT_COLUMNS``) or None when the
    iteration has none; rig: the category's rig (needed with fits).
    """
    fit_by_id = {str(r["sample_id"]): r for r in fits or ()}
    fit_ids = [sid for sid in fit_by_id if fit_by_id[sid]["status"] == shards.STATUS_OK and sid in masks]
    sil = dict(zip(fit_ids, fit_silhouettes(rig, [fit_by_id[s] for s in fit_ids]))) if fit_ids else {}
    rows = []
    for i, p in enumerate(predictions):
        sid = str(p["sample_id"])
        mask = masks.get(sid)
        row = {"sample_id": sid, "split": COLLECTION_SPLIT, "iteration": int(iteration), "status": p["status"],
               "reason": p["reason"] or "", "pred_mask_iou": math.nan, "mask_pixels": 0, "pred_pixels": 0,
               "fit_status": "no_fit", "fit_mask_iou": math.nan, "fit_pixels": 0}
        if mask is None:
            row.update(status="no_mask", reason=f"sample {sid!r} is not in the collection shard")
            rows.append(row)
            continue
        mask = np.asarray(mask, dtype=bool)
        row["mask_pixels"] = int(mask.sum())
        if p["status"] == shards.STATUS_OK:
            pred = predicted_mask(occupancy[i])
            row.update(pred_mask_iou=mask_iou(pred, mask), pred_pixels=int(pred.sum()))
        fit = fit_by_id.get(sid)
        if fit is not None:
            if fit["status"] != shards.STATUS_OK:
                row["fit_status"] = str(fit["status"])
            elif sil.get(sid) is None:
                row["fit_status"] = "no_camera"
            elif sil[sid].shape != mask.shape:
                row["fit_status"] = "size_mismatch"
            else:
                row.update(fit_status=shards.STATUS_OK, fit_mask_iou=mask_iou(sil[sid], mask),
                           fit_pixels=int(sil[sid].sum()))
        rows.append(row)
    return rows


def evaluate_collection_shard(predictions_dir: str | os.PathLike, index: int, collection_dir: str | os.PathLike,
                              fit_dir: str | os.PathLike | None, rig, iteration: int, out_dir: str | os.PathLike
                              ) -> shards.ShardPaths:
    """:func:`collection_rows` of prediction shard ``index`` of ``predictions_dir`` (``bat3r_core.predictor.infer``
    output: occupancy in its npz), the masks of collection shard ``index`` and the fits of fit shard ``index`` of
    ``fit_dir`` (None or a folder without that shard: no fits) → shard ``index`` of ``out_dir``."""
    table, arrays = shards.read_shard(predictions_dir, index)
    masks = _shard_masks(collection_dir, index)
    fits = None
    if fit_dir is not None and index in shards.list_shards(fit_dir):
        fits = shards.read_shard(fit_dir, index, with_arrays=False)[0].to_pylist()
    n = table.num_rows
    occupancy = arrays.get("occupancy", np.zeros((n, 1, 1, 1), np.float16))
    rows = collection_rows(iteration, table.to_pylist(), occupancy, masks, fits, rig)
    return shards.write_shard(out_dir, index, _table(rows))


def _table(rows: Sequence[Mapping[str, Any]]) -> pa.Table:
    return pa.table({f.name: pa.array([r[f.name] for r in rows], type=f.type) for f in COLLECTION_SCHEMA},
                    schema=COLLECTION_SCHEMA)


def read_collection_rows(run_dir: str | os.PathLike) -> pa.Table:
    """Every ``iter-NN/evaluate/collection`` shard of a run, concatenated (an empty ``COLLECTION_SCHEMA`` table
    when there are none)."""
    from bat3r_core.evaluation import EVALUATE_STAGE, iteration_dirs

    tables = [shards.read_table(d / EVALUATE_STAGE / COLLECTION_ROWS_DIR) for _, d in iteration_dirs(run_dir)]
    tables = [t.select(COLLECTION_SCHEMA.names).cast(COLLECTION_SCHEMA) for t in tables if t.num_rows]
    return pa.concat_tables(tables) if tables else COLLECTION_SCHEMA.empty_table()


def aggregate_collection(table: pa.Table) -> list[dict[str, Any]]:
    """One ``metrics.parquet`` row per iteration of collection rows: the ``METRICS_SCHEMA`` columns (``n`` ok
    predictions, ``n_failed`` others, the Chamfer metrics NaN: no 3D ground truth) and
    ``COLLECTION_METRIC_COLUMNS`` (means over the ok predictions and the ok fits). Values that do not apply (the
    Chamfer columns, a mean over no rows) are None: null in ``metrics.parquet``."""
    from bat3r_core.evaluation import METRICS_SCHEMA

    out = []
    rows = table.to_pylist()
    for iteration in sorted({int(r["iteration"]) for r in rows}):
        sub = [r for r in rows if int(r["iteration"]) == iteration]
        pred = [r["pred_mask_iou"] for r in sub if r["status"] == shards.STATUS_OK]
        fit = [r["fit_mask_iou"] for r in sub if r["fit_status"] == shards.STATUS_OK]
        row: dict[str, Any] = {f.name: None for f in METRICS_SCHEMA}
        row.update(iteration=iteration, split=COLLECTION_SPLIT, n=len(pred), n_failed=len(sub) - len(pred),
                   pred_mask_iou=float(np.mean(pred)) if pred else None,
                   fit_mask_iou=float(np.mean(fit)) if fit else None, n_fits=len(fit))
        out.append(row)
    return out

