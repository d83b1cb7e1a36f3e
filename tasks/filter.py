"""Filter stage: every fit shard of an iteration → one filter shard per fit shard (kept flag, status, reason and
quality columns per fit; ``bat3r_core.pseudo_labels``), which plan views reads; and, where the collection has a
hidden ground truth (toy), the filter's precision against it."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping

from bat3r_core import pseudo_labels, shards
from bat3r_core.specs import TruthSpec, as_spec
from tasks._cache import shard_input_files, stage_task

__all__ = ["filter_pseudo_labels", "filter_precision_check", "PRECISION_FILE"]

PRECISION_FILE = "pseudo_label_filter.json"
"""``iter-NN/evaluate/pseudo_label_filter.json``: the filter's precision / recall against the hidden truth."""


def _fit_files(fit_dir: str) -> list[Path]:
    return [f for i in shards.list_shards(fit_dir) for f in shard_input_files(fit_dir, i)]


def _inputs(p: Mapping[str, Any]) -> list[Path]:
    from bat3r_core.predictor.infer import clouds_path

    collection = p.get("collection_dir")
    return [Path(p["asset"])] + _fit_files(p["fit_dir"]) + \
        [clouds_path(p["predictions_dir"], i) for i in shards.list_shards(p["fit_dir"])] + \
        ([f for i in shards.list_shards(collection) for f in shard_input_files(collection, i)] if collection else [])


@stage_task("filter", inputs=_inputs, output=lambda p: Path(p["out_dir"]),
            spec=pseudo_labels.PseudoLabelFilterConfig)
def filter_pseudo_labels(asset: str, fit_dir: str, predictions_dir: str, out_dir: str,
                         config: pseudo_labels.PseudoLabelFilterConfig | Mapping[str, Any],
                         collection_dir: str | None = None) -> dict:
    """Quality columns of every fit of ``fit_dir`` (``pseudo_labels.quality_rows``; the canonical points come from
    the inference clouds of ``predictions_dir``, the masks of ``mask_iou`` / ``mask_iou_gain`` from the collection
    crops of ``collection_dir``; without it those columns are NaN), the filter (``pseudo_labels.filter_fits``; its
    quantile is over all the iteration's fits) and one filter shard per fit shard in ``out_dir``.

    config: a ``PseudoLabelFilterConfig`` (or its mapping). Returns ``stage, files, parquet, content_hash``,
    ``n_rows`` (ok fits: the candidates), ``n_ok`` (kept), ``status_counts`` / ``status_examples`` (the drops, as
    ``bat3r_core.runs.summarize_drops`` reads them), ``kept_fraction``, ``n_rescued``.
    """
    import pyarrow.parquet as pq

    from bat3r_core.predictor.infer import clouds_path, load_clouds
    from bat3r_core.rig_io import load_rig

    cfg = as_spec(pseudo_labels.PseudoLabelFilterConfig, config, "filter config")
    indices = shards.list_shards(fit_dir)
    if not indices:
        raise FileNotFoundError(f"{fit_dir}: no complete fit shard")
    rows, points, sizes = [], [], []
    for i in indices:
        fit_rows = pq.read_table(shards.shard_paths(fit_dir, i).parquet).to_pylist()
        clouds = load_clouds(clouds_path(predictions_dir, i))
        if len(clouds) != len(fit_rows):
            raise ValueError(f"{predictions_dir}: clouds of shard {i} hold {len(clouds)} instances, the fit shard "
                             f"{len(fit_rows)} rows")
        rows += fit_rows
        points += [clouds.instance(k)["canonical_points"] for k in range(len(fit_rows))]
        sizes.append(len(fit_rows))
    masks = None
    if collection_dir is not None:
        from bat3r_core.evaluation_masks import read_masks

        by_id = read_masks(collection_dir)
        masks = [by_id.get(str(r["sample_id"])) for r in rows]
    quality = pseudo_labels.quality_rows(rows, load_rig(asset), points, masks)
    decided = pseudo_labels.filter_fits(quality, cfg)
    paths = pseudo_labels.write_filter_shards(out_dir, indices, decided, sizes)
    files = [p.parquet for p in paths]
    counts = pseudo_labels.filter_counts(decided)
    examples: dict[str, list[str]] = {}
    for r in decided:
        if not r["kept"] and r["status"] != pseudo_labels.STATUS_NOT_FITTED:
            examples.setdefault(r["status"], [r["sample_id"], r["reason"]])
    return {"stage": "filter", "files": [str(f) for f in files], "parquet": str(files[0]),
            "content_hash": shards.content_hash(files), "n_rows": counts["n_fits"], "n_ok": counts["n_kept"],
            "status_counts": counts["drop_counts"], "status_examples": examples,
            "kept_fraction": counts["kept_fraction"], "n_rescued": counts["n_rescued"]}


def _check_inputs(p: Mapping[str, Any]) -> list[Path]:
    spec = as_spec(TruthSpec, p["config"], "filter_check config")
    return [Path(spec.asset), Path(spec.ground_truth), Path(p["errors_file"])] + \
        _fit_files(p["fit_dir"]) + _fit_files(p["filter_dir"])


@stage_task("filter_check", inputs=_check_inputs,
            output=lambda p: Path(p["out_dir"]) / PRECISION_FILE, spec=TruthSpec)
def filter_precision_check(fit_dir: str, filter_dir: str, errors_file: str, out_dir: str,
                           config: TruthSpec | Mapping[str, Any]) -> dict:
    """Precision / recall of the kept fits against the hidden truth (``pseudo_labels.filter_precision``): the
    pseudo-label errors ``errors_file`` (``bat3r_core.evaluation_truth.write_pseudo_label_errors``), the rest pose's
    errors (``pseudo_labels.rest_pose_errors``) and the filter shards of ``filter_dir`` →
    ``out_dir/pseudo_label_filter.json``. config: a ``bat3r_core.specs.TruthSpec`` (the rig and the collection's
    ``ground_truth.npz``). Returns ``stage, files, content_hash`` and the figures."""
    import pyarrow.parquet as pq

    from bat3r_core.evaluation_truth import load_ground_truth
    from bat3r_core.rig_io import load_rig

    spec = as_spec(TruthSpec, config, "filter_check config")
    errors = pq.read_table(errors_file).to_pylist()
    fits = shards.read_table(fit_dir).to_pylist()
    rest = pseudo_labels.rest_pose_errors(fits, load_ground_truth(spec.ground_truth), load_rig(spec.asset))
    figures = pseudo_labels.filter_precision(errors, rest, shards.read_table(filter_dir).to_pylist())
    path = shards.atomic_write_text(Path(out_dir) / PRECISION_FILE, json.dumps(figures, indent=1, sort_keys=True))
    return {"stage": "filter_check", "files": [str(path)], "content_hash": shards.content_hash([path]), **figures}
