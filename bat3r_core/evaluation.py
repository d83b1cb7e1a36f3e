"""Per-sample evaluation rows, their aggregation, and the run's ``metrics.parquet``.

Files (run folder layout of ``DESIGN.md``):

* ``iter-NN/evaluate/part-NNNNN.parquet``: one row per test sample, columns ``SAMPLE_SCHEMA`` (build rows with
  ``sample_row``, write them with ``write_sample_rows``).
* ``metrics.parquet``: one row per ``(iteration, split)``, columns ``METRICS_SCHEMA``, upserted atomically by
  ``upsert_metrics``; ``evaluate_run`` recomputes it from the stored per-sample rows.

Aggregates over the rows with ``status == "ok"`` of one (iteration, split):

* ``n``: number of ok rows; ``n_failed``: rows with any other status (not included in the averages).
* ``mcd_cm``: mean over samples of the per-sample RMS Chamfer distance after full alignment (``cd_cm``).
* ``rms_cd_cm``: root mean square over samples of ``cd_cm``: ``sqrt(mean(cd_cm²))`` (≥ ``mcd_cm``).
* ``pct_mcd_over_5cm``: percentage (0–100) of samples with ``cd_cm > 5``.
* ``mv_mcd_cm``, ``mv_rms_cd_cm``, ``pct_mv_over_5cm``: the same for the model-view distance ``mv_cd_cm``.
* ``rot_err_deg``: mean camera rotation error over the samples where it is finite (NaN if none).
* ``median_cd_cm``, ``std_cd_cm``: median and population standard deviation of ``cd_cm``.
"""
from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from bat3r_core import shards, stages
from bat3r_core.metrics import SampleMetrics
from bat3r_core.shards import atomic_write

__all__ = [
    "SAMPLE_SCHEMA",
    "METRICS_SCHEMA",
    "FAILURE_THRESHOLD_CM",
    "FailureRates",
    "iteration_dirs",
    "sample_row",
    "write_sample_rows",
    "read_sample_rows",
    "aggregate",
    "cluster_breakdown",
    "failure_rates",
    "upsert_metrics",
    "read_metrics",
    "evaluate_run",
]

_MOVED = ("sample_surface", "load_ground_truth", "ground_truth_camera", "evaluate_prediction_shard",
          "PSEUDO_LABEL_FILE", "pseudo_label_errors", "write_pseudo_label_errors")


def __getattr__(name: str):
    """The ground-truth evaluation moved to :mod:`bat3r_core.evaluation_truth`; its names still resolve here."""
    if name in _MOVED:
        from bat3r_core import evaluation_truth

        return getattr(evaluation_truth, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

FAILURE_THRESHOLD_CM = 5.0
METRICS_FILE = "metrics.parquet"
EVALUATE_STAGE = stages.stage(stages.EVALUATE).folder
"""The folder of an iteration the per-sample evaluation rows live in (the stage table's ``evaluate``)."""
_ITER_RE = re.compile(r"^iter-(\d+)$")

SAMPLE_SCHEMA = pa.schema([
    ("sample_id", pa.string()),
    ("split", pa.string()),           # e.g. "test", "train", "alt_test"
    ("iteration", pa.int64()),        # the iteration whose predictor was evaluated
    ("status", pa.string()),          # "ok" or a short code ("empty", "failed", ...)
    ("reason", pa.string()),          # human-readable, "" when ok
    ("cd_cm", pa.float64()),          # RMS Chamfer after full alignment (NaN unless ok)
    ("mv_cd_cm", pa.float64()),       # RMS Chamfer after model-view alignment
    ("rot_err_deg", pa.float64()),    # camera rotation error (NaN when unknown)
    ("icp_scale", pa.float64()),
    ("mv_scale", pa.float64()),
    ("n_pred_points", pa.int64()),
    ("azimuth_deg", pa.float64()),    # ground-truth camera, body-centric, degrees in [-180, 180)
    ("elevation_deg", pa.float64()),
    ("roll_deg", pa.float64()),
    ("f_ang", pa.float64()),          # ground-truth pose features (NaN when unknown)
    ("f_sq", pa.float64()),
    ("f_dist", pa.float64()),
    ("cluster", pa.int64()),          # pose cluster id, -1 when unknown
])

_AGG_FIELDS = [
    ("iteration", pa.int64()), ("split", pa.string()), ("n", pa.int64()), ("n_failed", pa.int64()),
    ("mcd_cm", pa.float64()), ("pct_mcd_over_5cm", pa.float64()), ("rot_err_deg", pa.float64()),
    ("rms_cd_cm", pa.float64()), ("mv_rms_cd_cm", pa.float64()), ("mv_mcd_cm", pa.float64()),
    ("pct_mv_over_5cm", pa.float64()), ("median_cd_cm", pa.float64()), ("std_cd_cm", pa.float64()),
]
METRICS_SCHEMA = pa.schema(_AGG_FIELDS)


def iteration_dirs(run_dir: str | os.PathLike) -> list[tuple[int, Path]]:
    """``[(iteration, run_dir/iter-NN), ...]`` for the iteration folders present, sorted by iteration."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        return []
    out = [(int(m.group(1)), p) for p in run_dir.iterdir() if p.is_dir() and (m := _ITER_RE.match(p.name))]
    return sorted(out)


def sample_row(sample_id: str, split: str, iteration: int, metrics: SampleMetrics | None, *,
               status: str = shards.STATUS_OK, reason: str = "", azimuth_deg: float = math.nan,
               elevation_deg: float = math.nan, roll_deg: float = math.nan,
               pose_features: Sequence[float] | None = None, cluster: int = -1) -> dict[str, Any]:
    """One per-sample evaluation row in ``SAMPLE_SCHEMA`` order.

    metrics: the sample's ``SampleMetrics`` (required when status is "ok"; None for failed samples, whose metric
    columns are NaN). azimuth/elevation/roll_deg: the ground-truth body-centric camera angles, degrees.
    pose_features: (3,) ground-truth ``[f_ang, f_sq, f_dist]`` or None. cluster: pose cluster id or -1.
    """
    if not isinstance(sample_id, str) or not sample_id:
        raise ValueError(f"sample_id must be a non-empty string, got {sample_id!r}")
    if status == shards.STATUS_OK and metrics is None:
        raise ValueError(f"sample {sample_id!r}: status 'ok' needs metrics")
    if status != shards.STATUS_OK and not reason:
        raise ValueError(f"sample {sample_id!r}: status {status!r} needs a reason")
    feats = [math.nan] * 3 if pose_features is None else [float(v) for v in pose_features]
    if len(feats) != 3:
        raise ValueError(f"pose_features must have 3 values [f_ang, f_sq, f_dist], got {len(feats)}")
    m = metrics
    nan = math.nan
    return {
        "sample_id": sample_id, "split": str(split), "iteration": int(iteration), "status": status,
        "reason": reason,
        "cd_cm": m.cd_cm if m else nan, "mv_cd_cm": m.mv_cd_cm if m else nan,
        "rot_err_deg": m.rot_err_deg if m else nan, "icp_scale": m.icp_scale if m else nan,
        "mv_scale": m.mv_scale if m else nan, "n_pred_points": m.n_pred if m else 0,
        "azimuth_deg": float(azimuth_deg), "elevation_deg": float(elevation_deg), "roll_deg": float(roll_deg),
        "f_ang": feats[0], "f_sq": feats[1], "f_dist": feats[2], "cluster": int(cluster),
    }


def _rows_table(rows: Sequence[Mapping[str, Any]], schema: pa.Schema) -> pa.Table:
    names = schema.names
    for i, r in enumerate(rows):
        missing = [k for k in names if k not in r]
        if missing:
            raise ValueError(f"row {i} lacks column(s) {missing}")
    return pa.table({k: pa.array([r[k] for r in rows], type=schema.field(k).type) for k in names}, schema=schema)


def write_sample_rows(stage_dir: str | os.PathLike, index: int, rows: Sequence[Mapping[str, Any]]
                      ) -> shards.ShardPaths:
    """Write per-sample rows (from ``sample_row``) as shard ``index`` of ``stage_dir`` (``iter-NN/evaluate``),
    atomically, with the column types of ``SAMPLE_SCHEMA``."""
    return shards.write_shard(stage_dir, index, _rows_table(list(rows), SAMPLE_SCHEMA))


def read_sample_rows(run_dir: str | os.PathLike) -> pa.Table:
    """All complete ``iter-*/evaluate`` shards of a run, concatenated (``SAMPLE_SCHEMA`` columns first; an empty
    table with that schema when there are none). Missing optional columns are filled with nulls."""
    tables = []
    for _, it_dir in iteration_dirs(run_dir):
        t = shards.read_table(it_dir / EVALUATE_STAGE)
        if t.num_rows:
            tables.append(_conform(t, SAMPLE_SCHEMA))
    if not tables:
        return SAMPLE_SCHEMA.empty_table()
    return pa.concat_tables(tables, promote_options="default")


def _conform(table: pa.Table, schema: pa.Schema) -> pa.Table:
    cols = {}
    for f in schema:
        if f.name in table.column_names:
            cols[f.name] = table.column(f.name).cast(f.type)
        else:
            cols[f.name] = pa.nulls(table.num_rows, f.type)
    for name in table.column_names:
        if name not in cols:
            cols[name] = table.column(name)
    return pa.table(cols)


def _col(table: pa.Table, name: str, dtype=np.float64) -> np.ndarray:
    values = table.column(name).to_pylist()
    if dtype is np.float64:
        return np.array([math.nan if v is None else v for v in values], dtype=np.float64)
    return np.asarray(values, dtype=dtype)


def _summary(cd: np.ndarray, mv: np.ndarray, rot: np.ndarray) -> dict[str, float]:
    nan = math.nan
    rot = rot[np.isfinite(rot)]
    have = len(cd) > 0
    return {
        "mcd_cm": float(cd.mean()) if have else nan,
        "pct_mcd_over_5cm": float(100.0 * np.mean(cd > FAILURE_THRESHOLD_CM)) if have else nan,
        "rot_err_deg": float(rot.mean()) if len(rot) else nan,
        "rms_cd_cm": float(np.sqrt(np.mean(cd ** 2))) if have else nan,
        "mv_rms_cd_cm": float(np.sqrt(np.mean(mv ** 2))) if have else nan,
        "mv_mcd_cm": float(mv.mean()) if have else nan,
        "pct_mv_over_5cm": float(100.0 * np.mean(mv > FAILURE_THRESHOLD_CM)) if have else nan,
        "median_cd_cm": float(np.median(cd)) if have else nan,
        "std_cd_cm": float(cd.std()) if have else nan,
    }


def _groups(table: pa.Table, keys: Sequence[str]) -> dict[tuple, np.ndarray]:
    cols = [table.column(k).to_pylist() for k in keys]
    groups: dict[tuple, list[int]] = {}
    for i, key in enumerate(zip(*cols)):
        groups.setdefault(key, []).append(i)
    return {k: np.asarray(v) for k, v in sorted(groups.items(), key=lambda kv: tuple(map(str, kv[0])))}


def _check_columns(table: pa.Table, needed: Iterable[str], what: str) -> None:
    missing = [c for c in needed if c not in table.column_names]
    if missing:
        raise ValueError(f"{what} needs column(s) {missing}; got {table.column_names}")


def aggregate(table: pa.Table) -> list[dict[str, Any]]:
    """One ``METRICS_SCHEMA`` row per (iteration, split) of per-sample rows (module docstring), sorted."""
    _check_columns(table, ["iteration", "split", "status", "cd_cm", "mv_cd_cm", "rot_err_deg"], "aggregate")
    out = []
    groups = _groups(table, ["iteration", "split"])
    for (iteration, split), idx in sorted(groups.items(), key=lambda kv: (kv[0][0], kv[0][1])):
        sub = table.take(idx)
        ok = shards.ok_mask(sub)
        cd, mv, rot = (_col(sub, c)[ok] for c in ("cd_cm", "mv_cd_cm", "rot_err_deg"))
        bad = ~(np.isfinite(cd) & np.isfinite(mv))
        if bad.any():
            raise ValueError(f"iteration {iteration} split {split!r}: {int(bad.sum())} ok row(s) have non-finite "
                             "cd_cm/mv_cd_cm; mark them with a non-ok status")
        out.append({"iteration": int(iteration), "split": split, "n": int(ok.sum()),
                    "n_failed": int((~ok).sum()), **_summary(cd, mv, rot)})
    return out


def cluster_breakdown(table: pa.Table) -> list[dict[str, Any]]:
    """Per (iteration, split, cluster) rows of the ok samples: ``n, mcd_cm, pct_mcd_over_5cm, mv_mcd_cm,
    rot_err_deg`` (and the other ``_summary`` fields). Rows with cluster -1 (unknown) are left out."""
    _check_columns(table, ["iteration", "split", "status", "cluster", "cd_cm", "mv_cd_cm", "rot_err_deg"],
                   "cluster_breakdown")
    ok = table.filter(pa.array(shards.ok_mask(table)))
    out = []
    for (iteration, split, cluster), idx in _groups(ok, ["iteration", "split", "cluster"]).items():
        if cluster is None or cluster < 0:
            continue
        sub = ok.take(idx)
        cd, mv, rot = (_col(sub, c) for c in ("cd_cm", "mv_cd_cm", "rot_err_deg"))
        out.append({"iteration": int(iteration), "split": split, "cluster": int(cluster), "n": len(idx),
                    **_summary(cd, mv, rot)})
    return sorted(out, key=lambda r: (r["iteration"], r["split"], r["cluster"]))


@dataclass(frozen=True)
class FailureRates:
    """Failure rate over azimuth × binned pose complexity.

    rate: (B_f, B_az) fraction in [0, 1] of samples with ``cd_cm > threshold_cm`` per cell (NaN for empty cells);
    row b covers ``f_dist_edges[b] ≤ f_dist < f_dist_edges[b + 1]`` (last row closed), column a covers
    ``azimuth_edges[a] ≤ azimuth < azimuth_edges[a + 1]`` in degrees, azimuth wrapped to [-180, 180).
    count, failures: (B_f, B_az) int sample and failure counts.
    """

    rate: np.ndarray
    count: np.ndarray
    failures: np.ndarray
    azimuth_edges: np.ndarray
    f_dist_edges: np.ndarray
    threshold_cm: float


def failure_rates(azimuth_deg: np.ndarray, f_dist: np.ndarray, cd_cm: np.ndarray, *,
                  threshold_cm: float = FAILURE_THRESHOLD_CM, azimuth_edges: np.ndarray | None = None,
                  f_dist_edges: np.ndarray | None = None, n_f_dist_bins: int = 4) -> FailureRates:
    """Fraction of samples whose ``cd_cm`` exceeds ``threshold_cm`` per (f_dist bin, azimuth bin).

    azimuth_deg, f_dist, cd_cm: (N,) per-sample ground-truth azimuth (degrees), aligned joint distance (metres),
    and RMS Chamfer (cm). Samples with a non-finite value are ignored. Default azimuth bins: 12 of 30° over
    [-180, 180). Default f_dist bins: ``n_f_dist_bins`` quantile bins of the given f_dist (equal counts).
    """
    az = np.asarray(azimuth_deg, dtype=np.float64)
    fd = np.asarray(f_dist, dtype=np.float64)
    cd = np.asarray(cd_cm, dtype=np.float64)
    if not (az.ndim == fd.ndim == cd.ndim == 1 and len(az) == len(fd) == len(cd)):
        raise ValueError(f"azimuth_deg, f_dist and cd_cm must be 1-D of equal length, got {az.shape}, "
                         f"{fd.shape}, {cd.shape}")
    keep = np.isfinite(az) & np.isfinite(fd) & np.isfinite(cd)
    az, fd, cd = (np.mod(az[keep] + 180.0, 360.0) - 180.0), fd[keep], cd[keep]
    az_edges = np.linspace(-180.0, 180.0, 13) if azimuth_edges is None else np.asarray(azimuth_edges, float)
    if f_dist_edges is None:
        if n_f_dist_bins < 1:
            raise ValueError(f"n_f_dist_bins must be >= 1, got {n_f_dist_bins}")
        if len(fd) == 0:
            fd_edges = np.linspace(0.0, 1.0, n_f_dist_bins + 1)
        else:
            fd_edges = np.unique(np.quantile(fd, np.linspace(0, 1, n_f_dist_bins + 1)))
            if len(fd_edges) < 2:
                fd_edges = np.array([fd_edges[0], fd_edges[0] + 1e-9])
    else:
        fd_edges = np.asarray(f_dist_edges, dtype=np.float64)
    for name, e in (("azimuth_edges", az_edges), ("f_dist_edges", fd_edges)):
        if e.ndim != 1 or len(e) < 2 or np.any(np.diff(e) <= 0):
            raise ValueError(f"{name} must be strictly increasing with at least 2 entries, got {e.tolist()}")
    count, _, _ = np.histogram2d(fd, az, bins=[fd_edges, az_edges])
    fails, _, _ = np.histogram2d(fd[cd > threshold_cm], az[cd > threshold_cm], bins=[fd_edges, az_edges])
    with np.errstate(invalid="ignore", divide="ignore"):
        rate = np.where(count > 0, fails / np.maximum(count, 1), np.nan)
    return FailureRates(rate, count.astype(np.int64), fails.astype(np.int64), az_edges, fd_edges, float(threshold_cm))


def read_metrics(run_dir: str | os.PathLike) -> pa.Table:
    """``run_dir/metrics.parquet`` (an empty ``METRICS_SCHEMA`` table when it does not exist yet)."""
    path = Path(run_dir) / METRICS_FILE
    if not path.is_file():
        return METRICS_SCHEMA.empty_table()
    return pq.read_table(path)


def upsert_metrics(run_dir: str | os.PathLike, rows: Sequence[Mapping[str, Any]]) -> Path:
    """Insert or replace rows of ``run_dir/metrics.parquet`` keyed by ``(iteration, split)``; atomic.

    rows: mappings with at least the ``METRICS_SCHEMA`` columns (e.g. from ``aggregate``); extra columns are kept
    (null in rows without them). The file stays sorted by (iteration, split).
    """
    rows = list(rows)
    for i, r in enumerate(rows):
        missing = [f.name for f in METRICS_SCHEMA if f.name not in r]
        if missing:
            raise ValueError(f"metrics row {i} lacks column(s) {missing}")
    existing = read_metrics(run_dir).to_pylist()
    new_keys = {(int(r["iteration"]), str(r["split"])) for r in rows}
    merged = [r for r in existing if (int(r["iteration"]), str(r["split"])) not in new_keys]
    merged += [dict(r) for r in rows]
    merged.sort(key=lambda r: (int(r["iteration"]), str(r["split"])))
    extra = sorted({k for r in merged for k in r} - set(METRICS_SCHEMA.names))
    cols = {f.name: pa.array([r.get(f.name) for r in merged], type=f.type) for f in METRICS_SCHEMA}
    for k in extra:
        cols[k] = pa.array([r.get(k) for r in merged])
    path = Path(run_dir) / METRICS_FILE
    atomic_write(path, lambda tmp: pq.write_table(pa.table(cols), tmp))
    return path


def evaluate_run(run_dir: str | os.PathLike) -> Path:
    """Recompute ``run_dir/metrics.parquet`` from every ``iter-NN/evaluate`` shard of a run.

    Rows of (iteration, split) pairs that have per-sample rows are replaced; other rows already in the file are
    kept. The ``collection`` rows (mask IoUs without 3D ground truth) come from the ``iter-NN/evaluate/collection``
    shards (``bat3r_core.evaluation_masks.aggregate_collection``). Returns the path of ``metrics.parquet``.
    Raises ``FileNotFoundError`` when ``run_dir`` is not a folder.
    """
    from bat3r_core.evaluation_masks import aggregate_collection, read_collection_rows

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"run folder {run_dir} does not exist")
    rows = aggregate(read_sample_rows(run_dir)) + aggregate_collection(read_collection_rows(run_dir))
    return upsert_metrics(run_dir, rows)
