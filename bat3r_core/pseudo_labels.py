"""Pseudo-label filtering: per-fit quality columns, the filter that keeps the fits worth rendering, and its check
against a hidden ground truth (toy).

Data flow (``DESIGN.md``): ``fits ── filter ──▶ kept fits``. The reference drops fits before rendering by
per-sample quality (Chamfer to the canonical and to the prediction, confidence, final fitting loss, joint
distance; thresholds not published). Here:

* :func:`quality_rows` — one row per fit with the columns of :data:`QUALITY_COLUMNS`: what the fit shard already
  holds (``residual_chamfer_cm``, ``inlier_ratio``, ``mean_confidence``, ``loss_data``, ``loss_total``,
  ``camera_reprojection_px``, ``camera_inlier_ratio``) plus two cheap ones computed here: ``canonical_chamfer_cm``
  (RMS distance of the prediction's canonical points to their nearest rest-mesh vertex, one-sided: a partial view
  covers part of the mesh) and ``pose_joint_dist_cm`` (``f_dist`` of :func:`bat3r_core.poses.pose_features`, in
  cm: the sum over joints of the distance between the Kabsch-aligned posed joints and the rest joints); and, given
  the images' masks, two that need no 3D truth (:func:`mask_agreement`): ``mask_iou``, the IoU of the fitted mesh's
  silhouette through its recovered camera with the mask, and ``mask_iou_gain``, that IoU minus the rest pose's seen
  through the same camera.
* :class:`PseudoLabelFilterConfig` and :func:`filter_fits` — thresholds per column, then the best
  ``keep_quantile`` of the ok fits by ``score``, then at least ``min_kept`` fits; every row gets a kept flag, a
  status (``ok`` or the drop status) and a reason.
* :func:`write_filter_shards` — one filter shard per fit shard (rows in the fit shard's order), what plan views
  reads.
* :func:`filter_precision` — precision / recall of the kept set against the truth: a fit is *good* when its
  vertex error (``bat3r_core.evaluation_truth.pseudo_label_errors``) is below the rest pose's (:func:`rest_pose_errors`).
* :func:`score_ranking` — per quality column, its rank correlation with the fit-minus-rest error and the precision
  of keeping its best quantile: which ``score`` to choose, measured on a collection with a hidden truth.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from bat3r_core import shards

__all__ = ["QUALITY_COLUMNS", "HIGHER_IS_BETTER", "FILTER_COLUMNS", "STATUS_NOT_FITTED", "STATUS_QUANTILE",
           "PseudoLabelFilterConfig", "quality_rows", "filter_fits", "write_filter_shards", "read_kept",
           "filter_counts", "rest_pose_errors", "filter_precision", "score_ranking", "mask_agreement"]

QUALITY_COLUMNS = ("residual_chamfer_cm", "inlier_ratio", "mean_confidence", "loss_data", "loss_total",
                   "camera_reprojection_px", "camera_inlier_ratio", "canonical_chamfer_cm", "pose_joint_dist_cm",
                   "mask_iou", "mask_iou_gain")
"""Per-fit quality columns a filter can threshold or rank by."""
HIGHER_IS_BETTER = frozenset({"inlier_ratio", "mean_confidence", "camera_inlier_ratio", "mask_iou", "mask_iou_gain"})
"""Quality columns where larger is better (the others: smaller is better)."""
FILTER_COLUMNS = ("sample_id", "kept", "status", "reason", "score", *QUALITY_COLUMNS)
"""Columns of a filter shard row."""
STATUS_NOT_FITTED = "not_fitted"
"""Filter status of a fit whose own status is not ok (not a candidate; not counted as a filter drop)."""
STATUS_QUANTILE = "filtered_quantile"
"""Filter status of an ok fit outside the best ``keep_quantile`` by score."""


def _threshold_status(column: str) -> str:
    return f"filtered_{column}"


@dataclass(frozen=True)
class PseudoLabelFilterConfig:
    """Which fits become pseudo-labels (the catalog's ``runs.<preset>.pseudo_label_filter``).

    Attributes:
        score: the quality column that ranks the fits (:data:`QUALITY_COLUMNS`; direction from
            :data:`HIGHER_IS_BETTER`).
        keep_quantile: keep at most ``ceil(keep_quantile * ok fits)`` of the threshold survivors, best score
            first; 1.0 keeps them all.
        min_kept: if fewer fits survive, the best-scoring dropped ok fits are kept back up to
            ``min(min_kept, ok fits)`` (so a small run never loses all its fits).
        maximum: ``{column: value}``: drop a fit whose column is above the value (or NaN).
        minimum: ``{column: value}``: drop a fit whose column is below the value (or NaN).
    """

    score: str = "residual_chamfer_cm"
    keep_quantile: float = 1.0
    min_kept: int = 1
    maximum: dict[str, float] = field(default_factory=dict)
    minimum: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.score not in QUALITY_COLUMNS:
            raise ValueError(f"score: expected one of {list(QUALITY_COLUMNS)}, got {self.score!r}")
        if not (isinstance(self.keep_quantile, (int, float)) and 0.0 < self.keep_quantile <= 1.0):
            raise ValueError(f"keep_quantile: must be in (0, 1], got {self.keep_quantile!r}")
        if isinstance(self.min_kept, bool) or not isinstance(self.min_kept, int) or self.min_kept < 0:
            raise ValueError(f"min_kept: must be an integer >= 0, got {self.min_kept!r}")
        for name in ("maximum", "minimum"):
            for column, value in getattr(self, name).items():
                if column not in QUALITY_COLUMNS:
                    raise ValueError(f"{name}.{column}: unknown quality column; expected one of "
                                     f"{list(QUALITY_COLUMNS)}")
                if not math.isfinite(float(value)):
                    raise ValueError(f"{name}.{column}: must be a finite number, got {value!r}")


def _float(v: Any) -> float:
    return float("nan") if v is None else float(v)


def quality_rows(fit_rows: Sequence[Mapping[str, Any]], rig, canonical_points: Sequence[np.ndarray | None],
                 masks: Sequence[np.ndarray | None] | None = None) -> list[dict[str, Any]]:
    """The quality columns (:data:`QUALITY_COLUMNS`) of every fit row, plus ``sample_id`` and ``fit_status``.

    Args:
        fit_rows: fit shard rows (``bat3r_core.fitting.io.FIT_COLUMNS``).
        rig: the category's rig (rest vertices and joints; skinning of the fitted θ).
        canonical_points: per row, the prediction's canonical points (metres, canonical frame) or None.
        masks: per row, the image's foreground mask ``(height, width)`` at the fit camera's image size (the crop the
            predictor saw), or None; without masks ``mask_iou`` and ``mask_iou_gain`` are NaN.
    Rows whose fit is not ok get NaN in the computed columns.
    """
    import torch
    from scipy.spatial import cKDTree

    from bat3r_core.metrics import to_cm
    from bat3r_core.poses import pose_features
    from bat3r_core.skinning import skin

    if len(canonical_points) != len(fit_rows):
        raise ValueError(f"canonical_points: expected {len(fit_rows)} entries (one per fit row), got "
                         f"{len(canonical_points)}")
    tree = cKDTree(np.asarray(rig.rest_vertices, dtype=np.float64))
    ok = [i for i, r in enumerate(fit_rows) if r["status"] == shards.STATUS_OK]
    pose = np.full(len(fit_rows), np.nan)
    if ok:
        j = rig.num_joints
        theta = np.stack([np.asarray(fit_rows[i]["excess_rotations"], np.float64).reshape(j, 3) for i in ok])
        tensors = rig.tensors(dtype=torch.float64)
        posed = skin(tensors, torch.as_tensor(theta)).joints.numpy()
        rest = skin(tensors, torch.zeros((1, j, 3), dtype=torch.float64)).joints.numpy()[0]
        pose[ok] = to_cm(pose_features(theta, posed, rest, exclude=np.asarray(rig.parents) < 0)[:, 2])
    out = []
    for i, r in enumerate(fit_rows):
        row = {"sample_id": r["sample_id"], "fit_status": r["status"]}
        row.update({c: _float(r.get(c)) for c in QUALITY_COLUMNS[:7]})
        pts = canonical_points[i]
        if r["status"] == shards.STATUS_OK and pts is not None and len(pts):
            d, _ = tree.query(np.asarray(pts, dtype=np.float64).reshape(-1, 3))
            row["canonical_chamfer_cm"] = float(to_cm(float(np.sqrt(np.mean(d ** 2)))))
        else:
            row["canonical_chamfer_cm"] = float("nan")
        row["pose_joint_dist_cm"] = float(pose[i])
        out.append(row)
    if masks is not None and len(masks) != len(fit_rows):
        raise ValueError(f"masks: expected {len(fit_rows)} entries (one per fit row), got {len(masks)}")
    for row, (iou, gain) in zip(out, mask_agreement(fit_rows, rig, masks or [None] * len(fit_rows))):
        row["mask_iou"], row["mask_iou_gain"] = iou, gain
    return out


def mask_agreement(fit_rows: Sequence[Mapping[str, Any]], rig, masks: Sequence[np.ndarray | None]
                   ) -> list[tuple[float, float]]:
    """Per fit row, ``(mask_iou, mask_iou_gain)``: the IoU of the fitted mesh's silhouette through its recovered
    camera (``bat3r_core.evaluation_masks.fit_silhouettes``) with the image's mask, and that IoU minus the IoU of the
    same fit with its articulation undone (every non-root joint's θ set to zero; root θ, global similarity and camera
    kept): how much better the fitted pose explains the mask than the rest pose seen the same way. Needs no 3D
    truth. NaN for a fit that is not ok, has no camera or no mask, or whose camera's image size differs from the
    mask's."""
    from bat3r_core.evaluation_masks import fit_silhouettes
    from bat3r_core.metrics import mask_iou

    nan = (float("nan"), float("nan"))
    use = [i for i, r in enumerate(fit_rows) if r["status"] == shards.STATUS_OK and masks[i] is not None]
    out = [nan] * len(fit_rows)
    if not use:
        return out
    roots = np.asarray(rig.parents) < 0
    unposed = []
    for i in use:
        theta = np.asarray(fit_rows[i]["excess_rotations"], np.float64).reshape(rig.num_joints, 3).copy()
        theta[~roots] = 0.0
        unposed.append({**fit_rows[i], "excess_rotations": theta.ravel().tolist()})
    fitted = fit_silhouettes(rig, [fit_rows[i] for i in use])
    rest = fit_silhouettes(rig, unposed)
    for i, a, b in zip(use, fitted, rest):
        mask = np.asarray(masks[i], dtype=bool)
        if a is None or b is None or a.shape != mask.shape:
            continue
        iou = mask_iou(a, mask)
        out[i] = (iou, iou - mask_iou(b, mask))
    return out


def _better_first(values: np.ndarray, higher: bool) -> np.ndarray:
    """Row order best first (stable; NaN last)."""
    key = np.where(np.isfinite(values), -values if higher else values, np.inf)
    return np.argsort(key, kind="stable")


def filter_fits(quality: Sequence[Mapping[str, Any]], config: PseudoLabelFilterConfig) -> list[dict[str, Any]]:
    """Decide which fits become pseudo-labels (see :class:`PseudoLabelFilterConfig`).

    quality: rows of :func:`quality_rows` (``sample_id``, ``fit_status`` and the quality columns).
    Returns one row per input row, in order, with :data:`FILTER_COLUMNS`: ``kept``; ``status`` ``ok`` for a kept
    fit, else :data:`STATUS_NOT_FITTED`, ``filtered_<column>`` (first threshold failed, in ``maximum`` then
    ``minimum`` order) or :data:`STATUS_QUANTILE`; ``reason`` says why (for a fit kept back by ``min_kept``, which
    drop it was spared); ``score`` the ranking column's value.
    """
    n = len(quality)
    score = np.array([_float(q.get(config.score)) for q in quality], dtype=np.float64)
    status = [STATUS_NOT_FITTED] * n
    reason = [f"fit {q['fit_status']}" for q in quality]
    candidates = [i for i, q in enumerate(quality) if q["fit_status"] == shards.STATUS_OK]
    survivors = []
    for i in candidates:
        q, failed = quality[i], None
        for column, limit in config.maximum.items():
            v = _float(q.get(column))
            if not v <= limit:
                failed = (column, f"{column} {v:.4g} > {limit:.4g}" if math.isfinite(v) else f"{column} is NaN")
                break
        if failed is None:
            for column, limit in config.minimum.items():
                v = _float(q.get(column))
                if not v >= limit:
                    failed = (column, f"{column} {v:.4g} < {limit:.4g}" if math.isfinite(v) else f"{column} is NaN")
                    break
        if failed is None:
            survivors.append(i)
        else:
            status[i], reason[i] = _threshold_status(failed[0]), failed[1]
    higher = config.score in HIGHER_IS_BETTER
    n_quantile = math.ceil(config.keep_quantile * len(candidates) - 1e-9)
    ranked = [survivors[k] for k in _better_first(score[survivors], higher)] if survivors else []
    kept = set(ranked[:n_quantile])
    for rank, i in enumerate(ranked):
        if i in kept:
            status[i], reason[i] = shards.STATUS_OK, ""
        else:
            status[i] = STATUS_QUANTILE
            reason[i] = (f"{config.score} {score[i]:.4g} ranks {rank + 1} of {len(ranked)}; the best "
                         f"{n_quantile} ({100 * config.keep_quantile:.0f} % of {len(candidates)} ok fits) are kept")
    target = min(config.min_kept, len(candidates))
    if len(kept) < target:
        dropped = [i for i in candidates if i not in kept]
        for k in _better_first(score[dropped], higher)[:target - len(kept)]:
            i = dropped[k]
            kept.add(i)
            reason[i] = f"kept by min_kept={config.min_kept} (was {status[i]}: {reason[i]})"
            status[i] = shards.STATUS_OK
    out = []
    for i, q in enumerate(quality):
        row = {"sample_id": q["sample_id"], "kept": i in kept, "status": status[i], "reason": reason[i],
               "score": float(score[i])}
        row.update({c: _float(q.get(c)) for c in QUALITY_COLUMNS})
        out.append(row)
    return out


def write_filter_shards(folder: str | os.PathLike, indices: Sequence[int], rows: Sequence[Mapping[str, Any]],
                        sizes: Sequence[int]) -> list[shards.ShardPaths]:
    """Write the filter rows of all fit shards as shards ``indices`` of ``folder`` (``sizes[k]`` rows each, in
    order) and delete any other shard there (left by an earlier, larger run)."""
    import pyarrow as pa

    if len(indices) != len(sizes) or sum(sizes) != len(rows):
        raise ValueError(f"sizes {list(sizes)} must match indices {list(indices)} and sum to {len(rows)} rows")
    schema = pa.schema([("sample_id", pa.string()), ("kept", pa.bool_()), ("status", pa.string()),
                        ("reason", pa.string()), ("score", pa.float64())]
                       + [(c, pa.float64()) for c in QUALITY_COLUMNS])
    out, start = [], 0
    for index, size in zip(indices, sizes):
        table = pa.Table.from_pylist([dict(r) for r in rows[start:start + size]], schema=schema)
        out.append(shards.write_shard(folder, int(index), table))
        start += size
    for i in set(shards.list_shards(folder)) - {int(i) for i in indices}:
        p = shards.shard_paths(folder, i)
        for f in (p.parquet, p.npz):
            f.unlink(missing_ok=True)
    return out


def read_kept(filter_dir: str | os.PathLike, index: int, sample_ids: Sequence[str]) -> list[dict[str, Any]]:
    """The filter rows of fit shard ``index`` (:func:`write_filter_shards`), checked to be for ``sample_ids`` (the
    fit shard's rows, in order); ``ValueError`` when the filter shard belongs to other fits."""
    import pyarrow.parquet as pq

    rows = pq.read_table(shards.shard_paths(filter_dir, index).parquet).to_pylist()
    ids = [r["sample_id"] for r in rows]
    if ids != list(sample_ids):
        raise ValueError(f"{filter_dir}: filter shard {index} is for samples {ids[:4]}…, not the fit shard's "
                         f"{list(sample_ids)[:4]}…; rerun the filter stage")
    return rows


def filter_counts(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """``n_fits`` (ok fits: the candidates), ``n_kept``, ``kept_fraction`` (None without candidates),
    ``n_rescued`` (kept by ``min_kept``) and ``drop_counts`` ({status: fits}) of filter rows."""
    candidates = [r for r in rows if r["status"] != STATUS_NOT_FITTED]
    kept = [r for r in candidates if r["kept"]]
    drops: dict[str, int] = {}
    for r in candidates:
        if not r["kept"]:
            drops[r["status"]] = drops.get(r["status"], 0) + 1
    return {"n_fits": len(candidates), "n_kept": len(kept),
            "kept_fraction": len(kept) / len(candidates) if candidates else None,
            "n_rescued": sum(r["reason"].startswith("kept by min_kept") for r in kept),
            "drop_counts": dict(sorted(drops.items(), key=lambda kv: (-kv[1], kv[0])))}


def rest_pose_errors(fit_rows: Sequence[Mapping[str, Any]], ground_truth: Mapping[str, Mapping], rig
                     ) -> list[dict[str, Any]]:
    """The errors of the rest pose against the truth, for the same fits as
    ``bat3r_core.evaluation_truth.pseudo_label_errors`` (which it calls with every θ set to zero): what a fit has to beat
    to be a useful pseudo-label."""
    from bat3r_core.evaluation_truth import pseudo_label_errors

    zero = [{**r, "excess_rotations": [0.0] * len(r["excess_rotations"])} for r in fit_rows]
    return pseudo_label_errors(zero, ground_truth, rig)


def filter_precision(error_rows: Sequence[Mapping[str, Any]], rest_rows: Sequence[Mapping[str, Any]],
                     filter_rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """How well the kept set picks the fits that beat the rest pose.

    error_rows: ``pseudo_label_errors`` rows (``sample_id, vertex_err_cm``) of the ok fits with ground truth;
    rest_rows: :func:`rest_pose_errors` of the same fits; filter_rows: the filter rows (``sample_id, kept``).
    A fit is *good* when ``vertex_err_cm`` < its rest pose's. Returns ``n`` (fits with truth), ``n_good``,
    ``n_kept``, ``n_kept_good``, ``precision`` (good share of the kept), ``recall`` (kept share of the good),
    ``base_rate`` (good share of all: the precision of keeping every fit); None where a denominator is 0.
    """
    rest = {r["sample_id"]: float(r["vertex_err_cm"]) for r in rest_rows}
    kept = {r["sample_id"]: bool(r["kept"]) for r in filter_rows}
    missing = sorted({r["sample_id"] for r in error_rows} - set(rest))
    if missing:
        raise ValueError(f"rest_rows lack samples {missing[:4]}")
    missing = sorted({r["sample_id"] for r in error_rows} - set(kept))
    if missing:
        raise ValueError(f"filter_rows lack samples {missing[:4]} (filter shard of other fits?)")
    good = {r["sample_id"] for r in error_rows if float(r["vertex_err_cm"]) < rest[r["sample_id"]]}
    kept_ids = {r["sample_id"] for r in error_rows if kept[r["sample_id"]]}
    n = len(error_rows)

    def ratio(a: int, b: int) -> float | None:
        return a / b if b else None

    return {"n": n, "n_good": len(good), "n_kept": len(kept_ids), "n_kept_good": len(good & kept_ids),
            "precision": ratio(len(good & kept_ids), len(kept_ids)), "recall": ratio(len(good & kept_ids), len(good)),
            "base_rate": ratio(len(good), n)}


def score_ranking(error_rows: Sequence[Mapping[str, Any]], rest_rows: Sequence[Mapping[str, Any]],
                  quality: Sequence[Mapping[str, Any]], columns: Sequence[str] = QUALITY_COLUMNS,
                  quantiles: Sequence[float] = (0.5, 0.25, 0.1)) -> dict[str, dict[str, Any]]:
    """How well each quality column would rank the fits, against the truth: which ``score`` a filter should use.

    error_rows, rest_rows: as in :func:`filter_precision`; quality: rows with ``sample_id`` and the columns (the
    filter shard rows hold them all). Only fits with an error, a rest error and a quality row take part.
    Per column: ``rho``, the Spearman rank correlation of the column with the fit's vertex error minus its rest
    pose's (> 0: larger values mean worse fits; NaN values rank last), and ``precision@q`` for each quantile, the
    share of fits beating the rest pose among the best ``ceil(q * n)`` by the column (direction from
    :data:`HIGHER_IS_BETTER`; NaN last, as the filter ranks). Also ``base_rate`` (share of all fits beating the
    rest pose) and ``n`` under the key ``"all"``."""
    from scipy.stats import spearmanr

    rest = {r["sample_id"]: float(r["vertex_err_cm"]) for r in rest_rows}
    by_id = {r["sample_id"]: r for r in quality}
    rows = [r for r in error_rows if r["sample_id"] in rest and r["sample_id"] in by_id]
    delta = np.array([float(r["vertex_err_cm"]) - rest[r["sample_id"]] for r in rows])
    good = delta < 0
    out: dict[str, dict[str, Any]] = {"all": {"n": len(rows), "base_rate": float(good.mean()) if rows else None}}
    for column in columns:
        values = np.array([_float(by_id[r["sample_id"]].get(column)) for r in rows], dtype=np.float64)
        higher = column in HIGHER_IS_BETTER
        order = _better_first(values, higher)
        worst = (np.nanmin(values) if higher else np.nanmax(values)) if np.isfinite(values).any() else 0.0
        entry: dict[str, Any] = {"rho": float(spearmanr(np.where(np.isfinite(values), values, worst), delta)[0])
                                 if len(rows) > 2 and np.ptp(delta) > 0 else float("nan")}
        for q in quantiles:
            k = max(1, math.ceil(q * len(rows))) if rows else 0
            entry[f"precision@{q:g}"] = float(good[order[:k]].mean()) if k else None
        out[column] = entry
    return out
