"""Dashboard artifacts of an iteration: the metrics table and a markdown summary (progress bars: ``_fanout``)."""
from __future__ import annotations

import math
from typing import Any, Sequence

from prefect.artifacts import create_markdown_artifact, create_table_artifact

from bat3r_core.runs import DROP_WARN_FRACTION, RunLayout, SampleDrops
from flows._fanout import StageResult, artifact_key

__all__ = ["summary_markdown", "publish_iteration_artifacts", "METRIC_COLUMNS"]

METRIC_COLUMNS = ("iteration", "split", "n", "n_failed", "mcd_cm", "pct_mcd_over_5cm", "rot_err_deg", "rms_cd_cm",
                  "mv_rms_cd_cm", "pred_mask_iou", "fit_mask_iou", "n_fits")
"""Columns of the dashboard's metrics table: ``metrics.parquet``'s test-split metrics and the collection's mask IoUs
(``bat3r_core.evaluation_masks``; empty cells where a row has none)."""


def _fmt(v: Any) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "–"
    return f"{v:.3f}" if isinstance(v, float) else str(v)


def _stage_line(r: StageResult) -> str:
    n = r.summary.n_total
    ok_samples = sum(int(rec.get("n_ok", 0)) for rec in r.records)
    bad_samples = sum(int(rec.get("n_failed", 0)) for rec in r.records)
    parts = [f"**{r.stage}**: {n - len(r.summary.failures)} of {n} task(s) done ({r.cached} from cache"
             + (f", {r.recomputed} recomputed after their files changed" if r.recomputed else "") + ")"]
    if any("n_rows" in rec for rec in r.records):
        parts.append(f"{ok_samples} samples ok, {bad_samples} skipped")
    planned = [rec for rec in r.records if "n_jobs" in rec]
    if planned:
        n_jobs = sum(int(rec["n_jobs"]) for rec in planned)
        n_files = sum(int(rec.get("n_shards", len(rec.get("files", [])))) for rec in planned)
        fits = sum(int(rec.get("n_fits", 0)) for rec in planned)
        parts.append(f"{n_jobs} render jobs in {n_files} shard(s)" + (f" from {fits} fit rows" if fits else ""))
    for rec in r.records:
        if "steps" in rec:
            loss = rec.get("final_loss")
            parts.append(f"{rec['steps']} steps on {rec.get('n_samples', '?')} samples, final loss {_fmt(loss)}")
    return "; ".join(parts)


def _drops_section(drops: Sequence[SampleDrops]) -> list[str]:
    """The stages that dropped more than ``DROP_WARN_FRACTION`` of their samples: one line each (counts, top
    reasons, an example file) and its table."""
    heavy = [d for d in drops if d.exceeds(DROP_WARN_FRACTION)]
    if not heavy:
        return []
    lines = ["", f"## Dropped samples (stages that dropped more than {100 * DROP_WARN_FRACTION:g} %)", ""]
    for d in heavy:
        lines += [f"- {d.describe()}", "", d.markdown(heading=False), ""]
    return lines


def summary_markdown(layout: RunLayout, iteration: int, stages: Sequence[StageResult],
                     metrics_rows: Sequence[dict], notes: Sequence[str] = (),
                     data_drops: Sequence[SampleDrops] = (), stopped: str | None = None) -> str:
    """The markdown summary of one iteration: what each stage did (cache hits, failed shards with their reasons,
    skipped samples, stages that dropped more than ``DROP_WARN_FRACTION`` of their samples), the metrics rows of
    this iteration, and a link to ``report.html``.

    data_drops: the run data's stages (collection and test split preparation; iteration 0's summary lists them).
    stopped: the error that stopped the iteration, for the summary of an iteration that did not finish.
    """
    lines = [f"# {layout.category} / {layout.run_name}: iteration {iteration}", ""]
    if stopped:
        lines += ["**Stopped:** " + stopped.replace("\n", " "), ""]
    lines += [f"- run data: {d.describe()}" for d in data_drops]
    lines += [f"- {_stage_line(r)}" for r in stages]
    lines += _drops_section([*data_drops, *(r.drops for r in stages)])
    failures = [(r.stage, f) for r in stages for f in r.summary.failures]
    if failures:
        lines += ["", "## Failed shards (after retries)", ""]
        lines += [f"- {stage} `{f.label}`: {f.reason}" for stage, f in failures]
    skipped = [(r.stage, s) for r in stages for rec in r.records for s in rec.get("failed_samples", [])]
    if skipped:
        lines += ["", "## Skipped samples (first ones)", ""]
        lines += [f"- {stage} `{s[0]}`: {s[1]} ({s[2]})" for stage, s in skipped[:20]]
    rows = [r for r in metrics_rows if r.get("iteration") == iteration]
    if not rows:
        lines += ["", "No metrics for this iteration yet (no evaluation shards)."]
    else:
        lines += ["", "## Metrics", "", "| " + " | ".join(METRIC_COLUMNS) + " |",
                  "|" + "---|" * len(METRIC_COLUMNS)]
        lines += ["| " + " | ".join(_fmt(r.get(c)) for c in METRIC_COLUMNS) + " |" for r in rows]
    lines += [f"- {n}" for n in notes]
    lines += ["", f"Report: [{layout.report}]({layout.report.resolve().as_uri()})", ""]
    return "\n".join(lines)


def publish_iteration_artifacts(layout: RunLayout, iteration: int, stages: Sequence[StageResult],
                                metrics_rows: Sequence[dict], notes: Sequence[str] = (),
                                data_drops: Sequence[SampleDrops] = (), stopped: str | None = None) -> None:
    """Create the run's metrics table artifact (all iterations so far; none while ``metrics.parquet`` is empty) and
    this iteration's markdown summary (``summary_markdown``)."""
    if metrics_rows:
        create_table_artifact(table=[{c: r.get(c) for c in METRIC_COLUMNS} for r in metrics_rows],
                              key=artifact_key(layout.category, layout.run_name, "metrics"),
                              description=f"metrics.parquet of {layout.root}")
    create_markdown_artifact(markdown=summary_markdown(layout, iteration, stages, metrics_rows, notes, data_drops,
                                                       stopped),
                             key=artifact_key(layout.category, layout.run_name, f"iter-{iteration:02d}-summary"),
                             description=f"iteration {iteration} of {layout.run_name}")
