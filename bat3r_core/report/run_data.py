"""What the report reads from a run folder, loaded once per build (every piece optional: a missing or unreadable
input becomes a note, never an error)."""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import pyarrow as pa

from bat3r_core import analysis, evaluation, evaluation_masks, evaluation_truth, shards, stages
from bat3r_core.report.inputs import QUALITATIVE_FILE

FIT_STAGE = stages.stage(stages.FIT).folder


def _col(table: pa.Table, name: str) -> np.ndarray:
    if name not in table.column_names:
        return np.full(table.num_rows, np.nan)
    return np.array([np.nan if v is None else v for v in table.column(name).to_pylist()], dtype=np.float64)


def _main_split(splits: Sequence[str]) -> str | None:
    splits = sorted(set(splits))
    return "test" if "test" in splits else (splits[0] if splits else None)


def _iter_label(iteration: int) -> str:
    return "0 (canonical)" if iteration == 0 else str(iteration)


@dataclass
class _RunData:
    run_dir: Path
    manifest: dict
    metrics: pa.Table
    metrics_note: str
    samples: pa.Table
    fits: dict[int, pa.Table]
    qualitative: dict[int, Path]
    load_errors: list[str]


def _guarded(what: str, fn: Callable, default, errors: list[str]):
    """``fn()``, or ``default`` with a message appended to ``errors`` when reading an input fails."""
    try:
        return fn()
    except Exception as exc:  # an unreadable input is reported on the page, never fatal
        errors.append(f"{what}: {type(exc).__name__}: {exc}")
        return default


def _read_manifest(path: Path) -> dict:
    if not path.is_file():
        return {}
    loaded = json.loads(path.read_text(encoding="utf-8"))
    return loaded if isinstance(loaded, dict) else {}


def report_inputs(run_dir: str | os.PathLike) -> list[Path]:
    """Every file ``build_report`` may read in ``run_dir``, in a fixed order: ``manifest.json``,
    ``metrics.parquet`` and, per iteration folder, the Parquet files of the ``evaluate``, ``evaluate/collection``
    and ``fit`` shards, ``evaluate/pseudo_labels.parquet`` and ``evaluate/qualitative.npz`` (those that exist). The
    report task's cache key hashes them (``tasks.evaluate.build_report``); ``tests/core/test_report.py`` checks,
    by watching the files the report opens, that nothing it reads is missing here."""
    run_dir = Path(run_dir)
    files = [run_dir / "manifest.json", run_dir / evaluation.METRICS_FILE]
    for _, d in evaluation.iteration_dirs(run_dir):
        evaluate = d / evaluation.EVALUATE_STAGE
        for folder in (evaluate, evaluate / evaluation_masks.COLLECTION_ROWS_DIR, d / FIT_STAGE):
            files += [shards.shard_paths(folder, i).parquet for i in shards.list_shards(folder)]
        files += [evaluate / evaluation_truth.PSEUDO_LABEL_FILE, evaluate / QUALITATIVE_FILE]
    return [f for f in files if f.is_file()]


def _load(run_dir: Path) -> _RunData:
    errors: list[str] = []
    manifest = _guarded("manifest.json", lambda: _read_manifest(run_dir / "manifest.json"), {}, errors)
    samples = _guarded("per-sample evaluation rows", lambda: evaluation.read_sample_rows(run_dir),
                       evaluation.SAMPLE_SCHEMA.empty_table(), errors)
    metrics = _guarded("metrics.parquet", lambda: evaluation.read_metrics(run_dir),
                       evaluation.METRICS_SCHEMA.empty_table(), errors)
    note = ""
    if metrics.num_rows == 0 and samples.num_rows:
        metrics = _guarded("aggregation of the per-sample rows", lambda: pa.Table.from_pylist(
            evaluation.aggregate(samples), schema=evaluation.METRICS_SCHEMA), metrics, errors)
        if metrics.num_rows:
            note = "metrics.parquet not written yet: values computed from the per-sample rows."
    if evaluation_masks.COLLECTION_SPLIT not in metrics.column("split").to_pylist():
        extra = _guarded("collection mask rows", lambda: evaluation_masks.aggregate_collection(
            evaluation_masks.read_collection_rows(run_dir)), [], errors)
        if extra:
            merged = metrics.to_pylist() + extra
            keys = list(dict.fromkeys(k for r in merged for k in r))
            metrics = pa.table({k: pa.array([r.get(k) for r in merged]) for k in keys})
    fits, qual = {}, {}
    for it, d in evaluation.iteration_dirs(run_dir):
        t = _guarded(f"iteration {it} fit rows", lambda: shards.read_table(d / FIT_STAGE), None, errors)
        if t is not None and t.num_rows:
            errs = d / evaluation.EVALUATE_STAGE / evaluation_truth.PSEUDO_LABEL_FILE
            if errs.is_file():  # pose errors against the hidden ground truth (evaluation stage)
                t = _guarded(f"iteration {it} pseudo-label errors", lambda: join_pose_errors(t, errs), t, errors)
            fits[it] = t
        q = d / evaluation.EVALUATE_STAGE / QUALITATIVE_FILE
        if q.is_file():
            qual[it] = q
    return _RunData(run_dir, manifest, metrics, note, samples, fits, qual, errors)


def join_pose_errors(fits: pa.Table, path: Path) -> pa.Table:
    """Fit rows with the ``joint_err_cm, vertex_err_cm, angle_err_deg, bone_err_deg`` of ``pseudo_labels.parquet``
    (NaN where a fit has none, or the file predates the column)."""
    import pyarrow.parquet as pq

    errs = {r["sample_id"]: r for r in pq.read_table(path).to_pylist()}
    ids = fits.column("sample_id").to_pylist()
    for col in analysis.POSE_ERROR_COLUMNS:
        values = pa.array([errs.get(i, {}).get(col, math.nan) for i in ids], pa.float64())
        fits = fits.set_column(fits.column_names.index(col), col, values) if col in fits.column_names \
            else fits.append_column(col, values)
    return fits
