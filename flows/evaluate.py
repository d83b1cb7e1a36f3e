"""``evaluate`` flow: recompute a run's ``metrics.parquet`` from its ``iter-NN/evaluate`` shards, rebuild
``report.html`` and publish the metrics table artifact.

Local run: ``python flows/evaluate.py --category toy --run-name tiny``.
"""
from __future__ import annotations

import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a script or loaded by path (deployments): make the project root importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from typing import Any

from prefect import flow
from prefect.artifacts import create_table_artifact

from bat3r_core.catalog import load_catalog
from bat3r_core.runs import RunLayout
from flows._artifacts import METRIC_COLUMNS
from flows._fanout import artifact_key
from tasks._cache import for_run, record_is_intact, remember_record_digests
from tasks.evaluate import build_report, update_metrics

__all__ = ["evaluate"]


@flow(name="evaluate", flow_run_name="{category}-{run_name}-evaluate")
def evaluate(category: str = "toy", run_name: str = "tiny", storage_root: str | None = None,
             catalog: str | None = None) -> dict[str, Any]:
    """Metrics and report of run ``<storage root>/<category>/<run name>`` (storage root: ``storage_root``, else
    that of ``catalog``, default ``$BAT3R_CATALOG`` / ``./data_catalog.yaml``).
    Returns ``{"rows": metrics rows (NaN as None), "report": path of report.html}``."""
    root = Path(storage_root) if storage_root else load_catalog(catalog).storage()
    layout = RunLayout(root, category, run_name)
    if not layout.root.is_dir():
        raise FileNotFoundError(f"run folder {layout.root} does not exist")
    metrics = _run_cached(update_metrics, layout)
    report = _run_cached(build_report, layout)["report"]
    if metrics["rows"]:
        create_table_artifact(table=[{c: r.get(c) for c in METRIC_COLUMNS} for r in metrics["rows"]],
                              key=artifact_key(category, run_name, "metrics"),
                              description=f"metrics.parquet of {layout.root}")
    return {"rows": metrics["rows"], "report": report}


def _run_cached(stage_task: Any, layout: RunLayout) -> dict[str, Any]:
    """``stage_task(run folder, {})``, cached; recomputed when the cached record's file was deleted or changed
    since."""
    record = for_run(stage_task, layout)(str(layout.root), {})
    remember_record_digests(record)  # the writer's hashes: the intact check reads nothing
    if not record_is_intact(record):
        record = for_run(stage_task, layout, refresh_cache=True)(str(layout.root), {})
        remember_record_digests(record)
    return record


def main(argv: list[str] | None = None) -> int:
    import argparse

    from bat3r_core.cli import add_catalog_argument

    parser = argparse.ArgumentParser(description="Recompute a run's metrics and report.")
    parser.add_argument("--category", default="toy")
    parser.add_argument("--run-name", default="tiny")
    parser.add_argument("--storage-root", default=None, help="runs folder (default: the catalog's storage root)")
    add_catalog_argument(parser)
    args = parser.parse_args(argv)
    out = evaluate(args.category, args.run_name, args.storage_root,
                   None if args.catalog is None else str(Path(args.catalog).resolve()))
    print(f"report: {out['report']}")
    for row in out["rows"]:
        print(row)
    return 0


if __name__ == "__main__":
    sys.exit(main())
