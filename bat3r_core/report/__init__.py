"""The run report: one self-contained ``report.html`` per run folder, rebuilt after every iteration.

``build_report(run_dir)`` reads (all optional; a missing piece shows a "not available yet" note in its section):

* ``manifest.json``: top-level scalar entries are listed in the summary.
* ``metrics.parquet``: ``bat3r_core.evaluation.METRICS_SCHEMA`` rows (computed from the per-sample rows when the
  file is missing).
* ``iter-NN/evaluate/part-*.parquet``: per-sample rows, ``bat3r_core.evaluation.SAMPLE_SCHEMA``.
* the ``split == "collection"`` rows of ``metrics.parquet`` (mask IoUs without 3D ground truth,
  ``bat3r_core.evaluation_masks``; computed from ``iter-NN/evaluate/collection`` when the file lacks them).
* ``iter-NN/fit/part-*.parquet``: fit rows with ``sample_id, status, reason``, final losses as ``loss_*`` float
  columns, optionally ``joint_err_cm, vertex_err_cm, angle_err_deg, bone_err_deg`` (pose errors where ground truth
  exists, see ``bat3r_core.analysis.pose_errors`` and ``bone_direction_error_deg``) and the estimated body-centric camera ``azimuth_deg, elevation_deg,
  roll_deg``.
* ``iter-NN/evaluate/qualitative.npz`` (``QUALITATIVE_FILE``, written by ``write_report_inputs``): S samples with
  ``sample_id (S,) str``, ``image (S, H, W, 3) uint8``, ``intrinsics (S, 3, 3) float32`` (pixels of ``image``),
  ``pred_points (S, P, 3) float32`` (metres, camera frame, absolute depth, NaN rows pad), optional
  ``mask (S, H, W) bool``, ``fitted_verts (S, V, 3) float32`` (metres, camera frame, all NaN for a sample without a
  fit) with ``faces (F, 3) int32``, and ``cd_cm (S,) float32``.

Sections (HTML ids, stable): ``SECTION_IDS``. Every figure is a matplotlib (Agg) PNG embedded as base64.

Modules: ``inputs`` (the qualitative samples the evaluation stage writes for the report), ``run_data`` (loading a
run folder once per build), ``sections`` (one function per section: figures and tables), ``markup`` (titles, HTML
pieces, CSS); this module assembles the page.
"""
from __future__ import annotations

import html
import os
from pathlib import Path

from bat3r_core.report.inputs import QUALITATIVE_FILE, QualitativeInputs, read_report_inputs, write_report_inputs
from bat3r_core.report.markup import _CSS, _TITLES, SECTION_IDS
from bat3r_core.report.run_data import FIT_STAGE, _load, join_pose_errors, report_inputs
from bat3r_core.report.sections import _SECTIONS
from bat3r_core.shards import atomic_write_bytes

__all__ = ["SECTION_IDS", "QUALITATIVE_FILE", "QualitativeInputs", "write_report_inputs", "read_report_inputs",
           "build_report", "report_inputs", "join_pose_errors", "FIT_STAGE", "REPORT_FILE"]

REPORT_FILE = "report.html"


def build_report(run_dir: str | os.PathLike) -> Path:
    """Write ``run_dir/report.html`` (self-contained, atomic) from whatever the run folder holds; return its path.

    Never fails because a piece is missing or unreadable: such a section shows a note instead (an unexpected error
    inside one section is shown in that section, with its message, and the other sections are still drawn).
    Raises ``FileNotFoundError`` only when ``run_dir`` is not a folder.
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"run folder {run_dir} does not exist")
    data = _load(run_dir)
    body = []
    for sid in SECTION_IDS:
        try:
            content = _SECTIONS[sid](data)
        except Exception as exc:  # one broken input must not take the whole report down
            content = f'<p class="error">This section could not be drawn: {html.escape(type(exc).__name__)}: ' \
                      f'{html.escape(str(exc))}</p>'
        body.append(f'<section id="{sid}"><h2>{html.escape(_TITLES[sid])}</h2>{content}</section>')
    title = " / ".join(str(data.manifest[k]) for k in ("category", "run_name") if k in data.manifest) \
        or run_dir.name
    nav = "".join(f'<a href="#{sid}">{html.escape(_TITLES[sid])}</a>' for sid in SECTION_IDS)
    page = (f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8"><title>bat3r report: '
            f'{html.escape(title)}</title><style>{_CSS}</style></head><body><header><h1>bat3r run report: '
            f'{html.escape(title)}</h1><p>{html.escape(str(run_dir))}</p></header><nav>{nav}</nav><main>'
            + "".join(body) + "</main></body></html>")
    path = run_dir / REPORT_FILE
    atomic_write_bytes(path, page.encode("utf-8"))
    return path
