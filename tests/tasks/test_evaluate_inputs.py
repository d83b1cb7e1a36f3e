"""The evaluate tasks' cache inputs: the metrics task reads the collection's mask-IoU shards too, so a new or changed
collection shard recomputes ``metrics.parquet``."""
from __future__ import annotations

from bat3r_core import shards
from bat3r_core.evaluation_masks import COLLECTION_ROWS_DIR
from tasks._cache import stage_cache_key
from tasks.evaluate import _collection_inputs, evaluation_inputs


def _row(sid: str, iou: float) -> dict:
    return {"sample_id": sid, "split": "collection", "iteration": 0, "status": "ok", "reason": "",
            "pred_mask_iou": iou, "mask_pixels": 10, "pred_pixels": 8, "fit_status": "no_fit",
            "fit_mask_iou": float("nan"), "fit_pixels": 0}


def test_metrics_inputs_include_the_collection_rows_and_their_content_changes_the_key(tmp_path):
    run = tmp_path / "run"
    shards.write_shard(run / "iter-00" / "evaluate", 0, [{"sample_id": "t0", "status": "ok", "reason": ""}])
    before = evaluation_inputs(str(run))
    assert [p.name for p in before] == ["part-00000.parquet"]
    coll = run / "iter-00" / "evaluate" / COLLECTION_ROWS_DIR
    shards.write_shard(coll, 0, [_row("c0", 0.5)])
    files = evaluation_inputs(str(run))
    assert files[:1] == before and files[1:] == [coll / "part-00000.parquet"]
    key = stage_cache_key("metrics", "v1", files, None, run / "metrics.parquet")
    shards.write_shard(coll, 0, [_row("c0", 0.6)])
    assert stage_cache_key("metrics", "v1", evaluation_inputs(str(run)), None, run / "metrics.parquet") != key


def test_collection_shard_inputs_name_the_fits_only_where_the_iteration_has_them(tmp_path):
    for folder in ("pred", "coll", "fit"):
        shards.write_shard(tmp_path / folder, 0, [{"sample_id": "c0", "status": "ok", "reason": ""}])
    p = {"predictions_dir": str(tmp_path / "pred"), "collection_dir": str(tmp_path / "coll"), "index": 0,
         "config": {"asset": str(tmp_path / "asset.glb"), "iteration": 1}}
    without = _collection_inputs({**p, "fit_dir": None})
    assert without[0].name == "asset.glb" and [f.parent.name for f in without[1:]] == ["pred", "coll"]
    with_fits = _collection_inputs({**p, "fit_dir": str(tmp_path / "fit")})
    assert with_fits[:len(without)] == without and [f.parent.name for f in with_fits[len(without):]] == ["fit"]
    assert _collection_inputs({**p, "fit_dir": str(tmp_path / "missing")}) == without
