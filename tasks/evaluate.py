"""Evaluate stage, run-level part: ``metrics.parquet`` from the per-sample evaluation shards, and ``report.html``."""
from __future__ import annotations

import math
from pathlib import Path

from bat3r_core import evaluation, evaluation_truth, report, shards
from bat3r_core.specs import CollectionEvaluationSpec, EvaluateSpec, TruthSpec, as_spec
from tasks._cache import shard_input_files, stage_task

__all__ = ["update_metrics", "build_report", "evaluation_inputs", "evaluate_shard", "pseudo_label_quality",
           "evaluate_collection_shard"]


def evaluation_inputs(run_dir: str) -> list[Path]:
    """Every file of the complete ``iter-NN/evaluate`` and ``iter-NN/evaluate/collection`` shards of a run, in
    iteration and shard order."""
    from bat3r_core.evaluation_masks import COLLECTION_ROWS_DIR

    out = []
    for _, it_dir in evaluation.iteration_dirs(run_dir):
        for stage in (it_dir / "evaluate", it_dir / "evaluate" / COLLECTION_ROWS_DIR):
            out += [f for i in shards.list_shards(stage) for f in shard_input_files(stage, i)]
    return out


def _metrics_file(run_dir: str) -> Path:
    return Path(run_dir) / "metrics.parquet"


@stage_task("metrics", inputs=lambda p: evaluation_inputs(p["run_dir"]),
            output=lambda p: _metrics_file(p["run_dir"]))
def update_metrics(run_dir: str, config: dict | None = None) -> dict:
    """Recompute ``run_dir/metrics.parquet`` from every ``iter-NN/evaluate`` shard
    (``bat3r_core.evaluation.evaluate_run``). Returns ``stage, files, content_hash, rows`` (the metrics rows,
    NaN as None)."""
    path = evaluation.evaluate_run(run_dir)
    rows = [{k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in r.items()}
            for r in evaluation.read_metrics(run_dir).to_pylist()]
    return {"stage": "metrics", "files": [str(path)], "content_hash": shards.content_hash([path]), "rows": rows}


@stage_task("report", inputs=lambda p: report.report_inputs(p["run_dir"]),
            output=lambda p: Path(p["run_dir"]) / report.REPORT_FILE, retries=1)
def build_report(run_dir: str, config: dict | None = None) -> dict:
    """Rebuild ``run_dir/report.html`` (``bat3r_core.report.build_report``), cached by every file it reads
    (``bat3r_core.report.report_inputs``): a run whose evaluation, fits and manifest did not change since keeps its
    report, and a cached rerun reads none of them for it. Returns ``stage, report, files, content_hash``."""
    path = report.build_report(run_dir)
    return {"stage": "report", "report": str(path), "files": [str(path)], "content_hash": shards.content_hash([path])}


def _shard_inputs(p: dict) -> list[Path]:
    from bat3r_core.predictor.infer import clouds_path

    spec = as_spec(EvaluateSpec, p["config"], "evaluate config")
    return [Path(spec.asset), Path(spec.ground_truth)] + \
        shard_input_files(p["predictions_dir"], p["index"]) + [clouds_path(p["predictions_dir"], p["index"])]


@stage_task("evaluate", inputs=_shard_inputs,
            output=lambda p: Path(p["out_dir"]) / shards.shard_name(p["index"]), spec=EvaluateSpec, retries=1,
            task_run_name="evaluate-{index}")
def evaluate_shard(predictions_dir: str, index: int, out_dir: str, config: EvaluateSpec | dict) -> dict:
    """Per-sample evaluation rows of the test predictions in shard ``index`` of ``predictions_dir``
    (``bat3r_core.evaluation_truth.evaluate_prediction_shard``) → shard ``index`` of ``out_dir``.
    config: a ``bat3r_core.specs.EvaluateSpec`` (or its mapping). Returns the shard record."""
    from bat3r_core.rig_io import load_rig
    from bat3r_core.runs import shard_record

    spec = as_spec(EvaluateSpec, config, "evaluate config")
    gt = evaluation_truth.load_ground_truth(spec.ground_truth)
    paths = evaluation_truth.evaluate_prediction_shard(
        predictions_dir, index, gt, load_rig(spec.asset), dict(spec.body_frame), spec.split, spec.iteration, out_dir,
        seed=spec.seed)
    return shard_record("evaluate", index, paths)


def _truth_inputs(p: dict) -> list[Path]:
    spec = as_spec(TruthSpec, p["config"], "pseudo_labels config")
    return [Path(spec.asset), Path(spec.ground_truth)] + \
        [f for i in shards.list_shards(p["fit_dir"]) for f in shard_input_files(p["fit_dir"], i)]


@stage_task("pseudo_labels", inputs=_truth_inputs, spec=TruthSpec,
            output=lambda p: Path(p["out_dir"]) / evaluation_truth.PSEUDO_LABEL_FILE, retries=1)
def pseudo_label_quality(fit_dir: str, out_dir: str, config: TruthSpec | dict) -> dict:
    """Fitted-pose vs hidden ground-truth pose errors of an iteration's collection fits
    (``bat3r_core.evaluation_truth.write_pseudo_label_errors``) → ``out_dir/pseudo_labels.parquet``.
    config: a ``bat3r_core.specs.TruthSpec`` (the rig and the collection's ``ground_truth.npz``). Returns
    ``stage, files, content_hash, n`` and the mean errors."""
    from bat3r_core.rig_io import load_rig

    spec = as_spec(TruthSpec, config, "pseudo_labels config")
    path, summary = evaluation_truth.write_pseudo_label_errors(
        fit_dir, evaluation_truth.load_ground_truth(spec.ground_truth), load_rig(spec.asset), out_dir)
    return {"stage": "pseudo_labels", "files": [str(path)], "content_hash": shards.content_hash([path]), **summary}


def _collection_inputs(p: dict) -> list[Path]:
    spec = as_spec(CollectionEvaluationSpec, p["config"], "evaluate_collection config")
    files = [Path(spec.asset)] + shard_input_files(p["predictions_dir"], p["index"]) \
        + shard_input_files(p["collection_dir"], p["index"])
    if p.get("fit_dir") and p["index"] in shards.list_shards(p["fit_dir"]):
        files += shard_input_files(p["fit_dir"], p["index"])
    return files


@stage_task("evaluate_collection", inputs=_collection_inputs,
            output=lambda p: Path(p["out_dir"]) / shards.shard_name(p["index"]), spec=CollectionEvaluationSpec,
            retries=1, task_run_name="evaluate-collection-{index}")
def evaluate_collection_shard(predictions_dir: str, index: int, collection_dir: str, fit_dir: str | None,
                              out_dir: str, config: CollectionEvaluationSpec | dict) -> dict:
    """Mask IoUs without 3D ground truth (``bat3r_core.evaluation_masks.evaluate_collection_shard``): Φ_i's
    predictions of collection shard ``index`` and this iteration's fits of it (``fit_dir``, None at iteration 0)
    against the collection masks → shard ``index`` of ``out_dir``. config: a
    ``bat3r_core.specs.CollectionEvaluationSpec`` (or its mapping). Returns the shard record."""
    from bat3r_core.evaluation_masks import evaluate_collection_shard as run
    from bat3r_core.rig_io import load_rig
    from bat3r_core.runs import shard_record

    spec = as_spec(CollectionEvaluationSpec, config, "evaluate_collection config")
    rig = load_rig(spec.asset) if fit_dir and index in shards.list_shards(fit_dir) else None
    paths = run(predictions_dir, index, collection_dir, fit_dir, rig, spec.iteration, out_dir)
    return shard_record("evaluate_collection", index, paths)
