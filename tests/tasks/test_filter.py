"""The filter task's contract: fit shards + inference clouds in → one filter shard per fit shard out → a record
that ``runs.summarize_drops`` reads; plan views then plans only the kept fits; the cache key covers the fit
shards and the filter config; the precision check against a known truth."""
from __future__ import annotations

import json

import numpy as np
import pyarrow.parquet as pq

from bat3r_core import shards
from bat3r_core.predictor.infer import DualClouds, clouds_path, save_clouds
from bat3r_core.rig_io import save_rig_glb
from bat3r_core.runs import summarize_drops
from bat3r_core.toy import TOY_BODY_FRAME
from tasks._cache import stage_cache_key
from tasks.filter import PRECISION_FILE, _inputs, filter_precision_check, filter_pseudo_labels
from tests.flows.test_plan_views import _fit_rows


def _clouds(points):
    n = [len(p) for p in points]
    m = sum(n)
    cat = np.concatenate(points).astype(np.float32) if m else np.zeros((0, 3), np.float32)
    return DualClouds(offsets=np.concatenate([[0], np.cumsum(n)]).astype(np.int64), posed_points=cat,
                      canonical_points=cat, canonical_confidence=np.full(m, 2.0, np.float32),
                      posed_confidence=np.full(m, 2.0, np.float32), pixels=np.zeros((m, 2), np.float32),
                      layers=np.zeros(m, np.int8))


def _setup(tmp_path, toy_rig):
    asset = save_rig_glb(toy_rig, tmp_path / "toy.glb")
    base = _fit_rows(toy_rig)  # two ok fits of the rest pose with cameras, one failed fit
    rest = np.asarray(toy_rig.rest_vertices)
    fit_dir, infer_dir = tmp_path / "fit", tmp_path / "infer"
    shard_rows = {0: [], 1: []}
    for k, residual in enumerate((1.0, 4.0, 2.0, 8.0)):
        row = dict(base[k % 2], sample_id=f"s{k}", residual_chamfer_cm=residual, inlier_ratio=0.8)
        shard_rows[k // 2].append(row)
    shard_rows[1].append(dict(base[2], sample_id="s9", residual_chamfer_cm=float("nan"), inlier_ratio=0.0))
    for index, rows in shard_rows.items():
        shards.write_shard(fit_dir, index, rows)
        save_clouds(clouds_path(infer_dir, index), _clouds([rest[::5] for _ in rows]))
    return str(asset), str(fit_dir), str(infer_dir)


def test_filter_task_writes_one_filter_shard_per_fit_shard_and_a_drops_record(tmp_path, toy_rig):
    asset, fit_dir, infer_dir = _setup(tmp_path, toy_rig)
    out_dir = str(tmp_path / "filter")
    config = {"keep_quantile": 0.5, "min_kept": 1}
    rec = filter_pseudo_labels.fn(asset, fit_dir, infer_dir, out_dir, config)
    assert shards.list_shards(out_dir) == [0, 1]
    rows = shards.read_table(out_dir).to_pylist()
    assert [r["sample_id"] for r in rows] == ["s0", "s1", "s2", "s3", "s9"]
    assert [r["kept"] for r in rows] == [True, False, True, False, False]  # best 2 of 4 by residual Chamfer
    assert [r["status"] for r in rows] == ["ok", "filtered_quantile", "ok", "filtered_quantile", "not_fitted"]
    assert all(r["canonical_chamfer_cm"] < 1e-3 for r in rows[:4])  # the clouds lie on the rest mesh (float32)
    assert rec["n_rows"] == 4 and rec["n_ok"] == 2 and rec["kept_fraction"] == 0.5 and rec["n_rescued"] == 0
    assert rec["status_counts"] == {"filtered_quantile": 2} and rec["status_examples"]["filtered_quantile"][0] == "s1"
    assert rec["content_hash"] == shards.content_hash(rec["files"]) and len(rec["files"]) == 2
    drops = summarize_drops("filter", [rec], label="iteration 1 filter")
    assert drops.headline() == "iteration 1 filter: 2 of 4 fits dropped (50.0 %)"
    # plan views reads the filter shard: only kept fits get render jobs
    from bat3r_core.render.jobs import read_jobs
    from tasks.plan import plan_views_shard

    body = {"origin": TOY_BODY_FRAME["origin"], "forward": list(TOY_BODY_FRAME["forward"]),
            "horizontal": list(TOY_BODY_FRAME["horizontal"])}
    plan_cfg = {"augment": {"num_textures": 4}, "body_frame": body, "seed": 3}
    sources = set()
    for index in (0, 1):
        plan = plan_views_shard.fn(asset, fit_dir, index, str(tmp_path / "plan"), plan_cfg, filter_dir=out_dir)
        sources |= {j.source_id for j in read_jobs(plan["files"][0])}
        assert plan["n_kept"] == 1
    assert sources == {"s0", "s2"}
    unfiltered = plan_views_shard.fn(asset, fit_dir, 0, str(tmp_path / "plan-all"), plan_cfg)
    assert {j.source_id for j in read_jobs(unfiltered["files"][0])} == {"s0", "s1"} and unfiltered["n_kept"] == 2


def test_filter_cache_key_covers_the_fit_shards_and_the_filter_config(tmp_path, toy_rig):
    asset, fit_dir, infer_dir = _setup(tmp_path, toy_rig)
    p = {"asset": asset, "fit_dir": fit_dir, "predictions_dir": infer_dir, "out_dir": str(tmp_path / "filter"),
         "config": {"keep_quantile": 0.5}}

    def key(params):
        return stage_cache_key("filter", "v", _inputs(params), params["config"], params["out_dir"])

    k0 = key(p)
    assert key(dict(p)) == k0
    assert key({**p, "config": {"keep_quantile": 0.75}}) != k0
    rows = pq.read_table(shards.shard_paths(fit_dir, 1).parquet).to_pylist()
    shards.write_shard(fit_dir, 1, [dict(rows[0], residual_chamfer_cm=0.5)] + rows[1:])
    assert key(p) != k0


def test_filter_task_scores_fits_by_their_agreement_with_the_collection_masks(tmp_path, toy_rig):
    """With the collection crops, the filter computes mask_iou / mask_iou_gain per fit; ranking by mask_iou keeps the
    fits whose silhouette is the image's mask; the collection shards are part of the cache key."""
    from bat3r_core.evaluation_masks import fit_silhouette

    asset, fit_dir, infer_dir = _setup(tmp_path, toy_rig)
    fits = {r["sample_id"]: r for r in shards.read_table(fit_dir).to_pylist()}
    coll = tmp_path / "collection"
    for index, ids in ((0, ["s0", "s1"]), (1, ["s2", "s3", "s9"])):
        masks = []
        for sid in ids:
            own = fit_silhouette(toy_rig, fits[sid]) if fits[sid]["status"] == "ok" else None
            shape = (fits["s0"]["height"], fits["s0"]["width"])
            # s0 and s3: the fit's own silhouette; s1 and s2: the silhouette moved by a third of the image
            masks.append(np.zeros(shape, bool) if own is None else
                         own if sid in ("s0", "s3") else np.roll(own, shape[1] // 3, axis=1))
        shards.write_shard(coll, index, [{"sample_id": s, "status": "ok", "reason": ""} for s in ids],
                           {"mask": np.stack(masks)})
    out_dir = str(tmp_path / "filter")
    rec = filter_pseudo_labels.fn(asset, fit_dir, infer_dir, out_dir, {"score": "mask_iou", "keep_quantile": 0.5},
                                  collection_dir=str(coll))
    rows = {r["sample_id"]: r for r in shards.read_table(out_dir).to_pylist()}
    assert rows["s0"]["mask_iou"] == 1.0 and rows["s3"]["mask_iou"] == 1.0
    assert rows["s1"]["mask_iou"] < 0.6 and rows["s2"]["mask_iou"] < 0.6
    assert [s for s in sorted(rows) if rows[s]["kept"]] == ["s0", "s3"] and rec["n_ok"] == 2
    assert rows["s0"]["mask_iou_gain"] == 0.0  # fits of the rest pose: nothing to gain over it
    assert np.isnan(rows["s9"]["mask_iou"])
    p = {"asset": asset, "fit_dir": fit_dir, "predictions_dir": infer_dir, "out_dir": out_dir,
         "config": {"score": "mask_iou"}, "collection_dir": str(coll)}
    k0 = stage_cache_key("filter", "v", _inputs(p), p["config"], out_dir)
    assert stage_cache_key("filter", "v", _inputs({**p, "collection_dir": None}), p["config"], out_dir) != k0
    table, arrays = shards.read_shard(coll, 0)
    shards.write_shard(coll, 0, table, {"mask": ~arrays["mask"]})
    assert stage_cache_key("filter", "v", _inputs(p), p["config"], out_dir) != k0


def test_precision_check_task_against_the_truth(tmp_path, toy_rig):
    from bat3r_core.evaluation_truth import write_pseudo_label_errors
    from bat3r_core.poses import sample_toy_natural_poses

    asset, fit_dir, infer_dir = _setup(tmp_path, toy_rig)
    theta, _ = sample_toy_natural_poses(4, seed=3)
    # s0 and s2 were fitted with their true pose, s1 and s3 with the rest pose
    for index in (0, 1):
        rows = pq.read_table(shards.shard_paths(fit_dir, index).parquet).to_pylist()
        for r in rows:
            if r["sample_id"] in ("s0", "s2"):
                r["excess_rotations"] = theta[int(r["sample_id"][1])].ravel().tolist()
        shards.write_shard(fit_dir, index, rows)
    gt = {f"s{k}": {"excess_rotations": theta[k]} for k in range(4)}
    v = toy_rig.num_vertices
    np.savez(tmp_path / "ground_truth.npz", sample_id=np.array([f"s{k}" for k in range(4)]), excess_rotations=theta,
             global_scale=np.ones(4), global_rotation=np.tile(np.eye(3), (4, 1, 1)),
             global_translation=np.zeros((4, 3)), camera_rotation=np.tile(np.eye(3), (4, 1, 1)),
             camera_translation=np.zeros((4, 3)), K=np.tile(np.eye(3), (4, 1, 1)), posed_vertices=np.zeros((4, v, 3)))
    from bat3r_core.rig_io import load_rig

    # the rig as the tasks load it (the asset file), as the flow's pseudo-label task does
    errors, _ = write_pseudo_label_errors(fit_dir, gt, load_rig(asset), tmp_path / "evaluate")
    filter_dir = str(tmp_path / "filter")
    filter_pseudo_labels.fn(asset, fit_dir, infer_dir, filter_dir, {"keep_quantile": 0.5})

    rec = filter_precision_check.fn(fit_dir, filter_dir, str(errors), str(tmp_path / "evaluate"),
                                    {"asset": asset, "ground_truth": str(tmp_path / "ground_truth.npz")})
    assert rec["n"] == 4 and rec["n_good"] == 2 and rec["n_kept"] == 2 and rec["n_kept_good"] == 2
    assert rec["precision"] == 1.0 and rec["recall"] == 1.0 and rec["base_rate"] == 0.5
    stored = json.loads((tmp_path / "evaluate" / PRECISION_FILE).read_text())
    assert stored["precision"] == 1.0 and rec["content_hash"] == shards.content_hash(rec["files"])
