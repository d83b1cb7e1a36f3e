"""The view-planning task over a fit shard: estimated + augmented render jobs per fitted row, cached on rerun."""
from __future__ import annotations

import numpy as np
from prefect import flow

from bat3r_core import datasets, shards
from bat3r_core.fitting.augment import AugmentConfig, plan_views_for_fits
from bat3r_core.render.jobs import read_jobs
from bat3r_core.rig_io import load_rig, save_rig_glb
from bat3r_core.runs import RunLayout
from bat3r_core.toy import TOY_BODY_FRAME
from flows._fanout import run_stage
from tasks._cache import for_run
from tasks.plan import _shard_seed, plan_views_shard


def _fit_rows(rig):
    """Fit-shard rows whose fitted camera and pose are known: canonical views of the rest pose, one failed fit."""
    rows = []
    for job in datasets.canonical_jobs(rig, 2, seed=5, body_frame_spec=TOY_BODY_FRAME, resolution=32):
        cam = job.camera
        rows.append({"sample_id": f"img-{job.sample_id}", "status": "ok", "reason": "",
                     "excess_rotations": np.zeros(rig.num_joints * 3).tolist(),
                     "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "width": cam.width,
                     "height": cam.height, "camera_rotation": cam.R.reshape(-1).tolist(),
                     "camera_translation": cam.t.reshape(-1).tolist()})
    failed = dict(rows[0], sample_id="img-bad", status="failed", reason="too few points")
    return rows + [failed]


def test_plan_views_task(prefect_harness, tmp_path, toy_rig):
    asset = save_rig_glb(toy_rig, tmp_path / "toy.glb")
    layout = RunLayout(tmp_path, "toy", "pv")
    rows = _fit_rows(toy_rig)
    shards.write_shard(layout.stage_dir(1, "fit"), 3, rows)
    body = {"origin": TOY_BODY_FRAME["origin"], "forward": list(TOY_BODY_FRAME["forward"]),
            "horizontal": list(TOY_BODY_FRAME["horizontal"])}
    config = {"augment": {"num_textures": 4}, "body_frame": body, "seed": 11}

    @flow
    def plan_flow():
        return run_stage("plan", for_run(plan_views_shard, layout),
                         [{"asset": str(asset), "fit_dir": str(layout.stage_dir(1, "fit")), "index": 3,
                           "out_dir": str(layout.stage_dir(1, "plan")), "config": config}],
                         progress_key="pv-plan", max_failed_fraction=0.0)

    (record,) = plan_flow().records
    jobs = read_jobs(record["files"][0])
    assert record["n_fits"] == 3 and record["n_jobs"] == len(jobs) and record["index"] == 3
    assert record["files"][0].endswith("iter-01/plan/part-00003.parquet")
    by_source: dict[str, list] = {}
    for j in jobs:
        by_source.setdefault(j.source_id, []).append(j)
    assert sorted(by_source) == ["img-canonical-000000", "img-canonical-000001"]  # the failed fit is skipped
    for source, group in by_source.items():
        assert 2 <= len(group) <= 3  # the estimated view and 1-2 augmented views
        (est,) = [j for j in group if j.view_kind == "estimated"]
        row = next(r for r in rows if r["sample_id"] == source)
        # the rows' cameras look at the body origin already (canonical views): the estimated view keeps that
        # orientation and the line of sight, and only its distance follows its own framing margin
        np.testing.assert_allclose(est.camera.R.reshape(-1), row["camera_rotation"], atol=1e-9)
        np.testing.assert_allclose(est.camera.t[:2], row["camera_translation"][:2], atol=1e-9)
        assert all(j.view_kind == "augmented" for j in group if j is not est)
    # the task is the library call with the shard's seed
    direct = plan_views_for_fits(load_rig(asset), rows, body, AugmentConfig(num_textures=4), seed=_shard_seed(11, 3))
    assert [j.sample_id for j in direct] == [j.sample_id for j in jobs]
    np.testing.assert_allclose([j.camera.R for j in direct], [j.camera.R for j in jobs])
    assert plan_flow().states == ("Cached",)
