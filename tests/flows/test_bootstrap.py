"""The bootstrap flow end to end (canonical initialisation + 2 refinement iterations): real Blender, ray casting,
training and fitting at tiny sizes; the rerun hits the cache for every task; a SIGKILLed run resumes, reuses its
completed shards and produces the same metrics."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from prefect import flow

from bat3r_core import shards
from bat3r_core.runs import RunLayout, read_manifest

ROOT = Path(__file__).resolve().parents[2]
TINY = {"run.canonical_samples": 8, "run.collection_size": 4, "run.test_size": 4, "train.steps": 4,
        "shard_size": 4}
CLI_TINY = [f"--set={k}={v}" for k, v in TINY.items()]



@pytest.fixture(scope="module")
def first_run(prefect_harness, catalog):
    from flows.bootstrap import bootstrap

    t0 = time.perf_counter()
    result = bootstrap(category="toy", preset="tiny", iterations=2, run_name="t1", overrides=TINY)
    return result, time.perf_counter() - t0


def _hashes(folder: Path) -> dict[str, str]:
    return {p.name: shards.content_hash([p]) for p in sorted(folder.glob("part-*"))}


def test_canonical_initialisation_writes_the_run_folder(first_run, catalog):
    result, seconds = first_run
    layout = RunLayout(catalog / "runs", "toy", "t1")
    assert result["run_dir"] == str(layout.root)
    manifest = read_manifest(layout)
    assert manifest["config"]["canonical_samples"] == 8 and manifest["config"]["train"]["steps"] == 4
    assert set(manifest["stage_code_versions"]) >= {"plan", "render", "features", "train", "evaluate"}
    # tools analysing a finished run get back exactly the settings it ran with, from its manifest
    from flows._settings import recorded_run

    settings, parameters = recorded_run("toy", "t1")
    assert json.loads(json.dumps({**settings.to_mapping(), "parameters": parameters})) == manifest["config"]
    assert parameters["overrides"] == TINY and settings.train.steps == 4
    with pytest.raises(FileNotFoundError, match="no such run"):
        recorded_run("toy", "never-ran")
    assert layout.metrics.is_file() and layout.report.is_file()
    init = result["iterations"][0]
    assert init["states"]["render"] == ["Completed", "Completed"]
    table, arrays = shards.read_shard(layout.stage_dir(0, "render"), 1)
    ok = shards.ok_mask(table)
    assert table.num_rows == 4 and ok.sum() >= 3
    assert arrays["rgb"].shape == (4, 32, 32, 3) and arrays["P"].shape == (4, 32, 32, 4, 3)
    # real renders and labels: the object covers pixels, and the ray-cast occupancy agrees with the mask
    assert arrays["mask"][ok].sum() > 50
    layer0 = arrays["occupancy"][ok][..., 0]
    iou = (layer0 & arrays["mask"][ok]).sum() / (layer0 | arrays["mask"][ok]).sum()
    assert iou > 0.8
    assert Path(init["predictor"]).is_file()
    assert shards.list_shards(layout.stage_dir(0, "features")) == [0, 1]
    assert shards.list_shards(layout.run_stage_dir("collection")) == [0]
    assert shards.list_shards(layout.run_stage_dir("test")) == [0]


def test_refinement_iterations_fit_render_train_and_evaluate(first_run, catalog):
    result, _ = first_run
    layout = RunLayout(catalog / "runs", "toy", "t1")
    assert len(result["iterations"]) == 3
    for i in (1, 2):
        it = result["iterations"][i]
        assert set(it["states"]) == {"infer", "fit", "pseudo_labels", "filter", "filter_check", "plan_views", "render",
                                     "features", "train", "collection_infer", "evaluate_collection", "test_infer",
                                     "evaluate"}
        fits = shards.read_table(layout.stage_dir(i, "fit")).to_pylist()
        assert len(fits) == 4 and sum(r["status"] == "ok" for r in fits) >= 1
        jobs = shards.read_table(layout.stage_dir(i, "render")).to_pylist()
        ok_fits = {r["sample_id"] for r in fits if r["status"] == "ok"}
        # the tiny preset's filter: the best 75 % of the ok fits by residual Chamfer, never fewer than 4
        decided = shards.read_table(layout.stage_dir(i, "filter")).to_pylist()
        assert [r["sample_id"] for r in decided] == [r["sample_id"] for r in fits]
        kept = {r["sample_id"] for r in decided if r["kept"]}
        assert kept <= ok_fits and len(kept) == min(len(ok_fits), max(4, -(-3 * len(ok_fits) // 4)))
        (rec,) = it["stages"]["filter"]
        assert rec["n_rows"] == len(ok_fits) and rec["n_ok"] == len(kept)
        assert it["drops"]["filter"]["n_ok"] == len(kept)
        # every kept fit is rendered from its estimated view plus 1-2 augmented views
        assert {j["source_id"] for j in jobs} <= kept
        assert {j["view_kind"] for j in jobs} <= {"estimated", "augmented"}
        assert sum(j["view_kind"] == "estimated" for j in jobs) == len(kept)
        # the filter's precision against the toy's hidden truth
        (check,) = it["stages"]["filter_check"]
        stored = json.loads((layout.stage_dir(i, "evaluate") / "pseudo_label_filter.json").read_text())
        assert stored["n"] == len(ok_fits) and stored["n_kept"] == len(kept) and stored == \
            {k: check[k] for k in stored}
        assert Path(it["predictor"]).is_file() and it["predictor"] != result["iterations"][i - 1]["predictor"]
        # the tiny preset warm-starts: Φ_i was trained from Φ_{i-1}, whose file is part of the train inputs
        from tasks.train import training_inputs

        stamp = json.loads((layout.stage_dir(i, "train") / "inputs.json").read_text())["inputs_hash"]
        previous = Path(result["iterations"][i - 1]["predictor"])
        assert stamp == shards.content_hash(training_inputs(str(layout.stage_dir(i, "render")))
                                            + training_inputs(str(layout.stage_dir(i, "features"))) + [previous])
    rows = shards.read_table(layout.stage_dir(2, "evaluate")).to_pylist()
    assert len(rows) == 4 and all(r["iteration"] == 2 and r["split"] == "test" for r in rows)
    # pseudo-label quality against the toy collection's hidden ground truth, shown in the report
    errors = pq.read_table(layout.stage_dir(1, "evaluate") / "pseudo_labels.parquet").to_pylist()
    assert errors and all(r["vertex_err_cm"] > 0 for r in errors)
    from bat3r_core import analysis
    from bat3r_core.report import join_pose_errors

    joined = join_pose_errors(shards.read_table(layout.stage_dir(1, "fit")),
                               layout.stage_dir(1, "evaluate") / "pseudo_labels.parquet")
    assert np.isfinite(analysis.summarize_pseudo_labels(joined).mean_vertex_err_cm)
    metrics = pq.read_table(layout.metrics).to_pylist()
    test_rows = [r for r in metrics if r["split"] == "test"]
    assert sorted(r["iteration"] for r in test_rows) == [0, 1, 2]
    assert all(r["n"] + r["n_failed"] == 4 and r["mcd_cm"] > 0 for r in test_rows)
    # evaluation without 3D ground truth: Φ_i's and iteration i's fits' mask IoUs on the collection, per iteration
    collection = {r["iteration"]: r for r in metrics if r["split"] == "collection"}
    assert sorted(collection) == [0, 1, 2] and len(metrics) == 6
    for i, row in collection.items():
        per_image = shards.read_table(layout.stage_dir(i, "evaluate") / "collection").to_pylist()
        assert len(per_image) == 4 and row["n"] + row["n_failed"] == 4 and row["n"] >= 1
        assert np.isfinite(row["pred_mask_iou"]) and 0.0 <= row["pred_mask_iou"] <= 1.0
        assert row["mcd_cm"] is None
        if i == 0:  # the canonical iteration has no fits of its own
            assert row["n_fits"] == 0 and row["fit_mask_iou"] is None
            continue
        ok_fits = sum(r["status"] == "ok" for r in shards.read_table(layout.stage_dir(i, "fit")).to_pylist())
        assert 1 <= row["n_fits"] <= ok_fits
        assert np.isfinite(row["fit_mask_iou"]) and 0.0 < row["fit_mask_iou"] <= 1.0
        assert row["fit_mask_iou"] == pytest.approx(np.mean([r["fit_mask_iou"] for r in per_image
                                                             if r["fit_status"] == "ok"]))
    report = layout.report.read_text()
    assert '<section id="collection-masks">' in report and "Latest (collection, iteration 2)" in report


def test_rerun_hits_the_cache_for_every_task(first_run, catalog):
    from flows.bootstrap import bootstrap

    layout = RunLayout(catalog / "runs", "toy", "t1")
    before = {s: _hashes(layout.stage_dir(0, s)) for s in ("plan", "render", "features")}
    predictor = shards.content_hash([layout.stage_dir(0, "train") / "predictor.pt"])
    metrics = shards.content_hash([layout.metrics])
    shards.forget_file_digests()  # as a fresh process would start: nothing hashed yet
    again = bootstrap(category="toy", preset="tiny", iterations=2, run_name="t1", overrides=TINY)
    # every run file is read for its content hash at most once, though several tasks' cache keys and the
    # records' intact checks name it (hash once: shards.file_digest), and the shards that records name are not
    # read at all: their writer's digests come with the cached records (tasks._cache.remember_record_digests)
    reads = {Path(f): n for f, n in shards.file_digest_reads().items() if str(layout.root) in f}
    assert max(reads.values(), default=1) == 1, {f: n for f, n in reads.items() if n > 1}
    assert not any(f.parent.name in ("render", "features") for f in reads), sorted(reads)
    states = again["iterations"][0]["states"]
    assert states == {"plan": ["Cached"], "render": ["Cached", "Cached"], "features": ["Cached", "Cached"],
                      "train": ["Cached"], "collection_infer": ["Cached"], "evaluate_collection": ["Cached"],
                      "test_infer": ["Cached"], "evaluate": ["Cached"]}
    for it in again["iterations"][1:]:
        assert all(s == "Cached" for stage in it["states"].values() for s in stage), it["states"]
    assert shards.content_hash([layout.metrics]) == metrics
    assert {s: _hashes(layout.stage_dir(0, s)) for s in before} == before
    assert shards.content_hash([layout.stage_dir(0, "train") / "predictor.pt"]) == predictor


def test_inference_task_with_the_trained_predictor(first_run, catalog):
    from flows._fanout import run_stage
    from tasks._cache import for_run
    from tasks.predict import infer_shard

    layout = RunLayout(catalog / "runs", "toy", "t1")
    predictor = first_run[0]["iterations"][0]["predictor"]

    @flow
    def infer_flow():
        return run_stage("infer", for_run(infer_shard, layout),
                         [{"predictor": predictor, "collection_dir": str(layout.run_stage_dir("test")), "index": 0,
                           "out_dir": str(layout.stage_dir(1, "infer")),
                           "config": {"features": {"extractor": "rgb"}, "batch_size": 4}}],
                         progress_key="t1-infer", max_failed_fraction=0.0)

    result = infer_flow()
    (record,) = result.records
    table, arrays = shards.read_shard(layout.stage_dir(1, "infer"), 0)
    assert record["n_rows"] == table.num_rows == 4
    assert arrays["canonical_points"].shape == (4, 32, 32, 4, 3)
    assert Path(record["clouds"]).is_file()
    assert infer_flow().states == ("Cached",)


def _persisted_render_shards(layout: RunLayout) -> set[int]:
    """Render shards whose task has finished: its JSON result record (naming the shard) is in the result storage."""
    if not layout.results_dir.is_dir():
        return set()
    text = b"".join(p.read_bytes() for p in layout.results_dir.glob("render-*"))
    return {i for i in (0, 1) if f"iter-00/render/part-{i:05d}.parquet".encode() in text}


def test_killed_run_resumes_from_its_completed_shards(first_run, catalog, prefect_harness):
    from prefect.settings import PREFECT_API_URL

    layout = RunLayout(catalog / "runs", "toy", "k1")
    # the catalog reaches the flow through --catalog alone (the subprocess has no $BAT3R_CATALOG)
    env = {**{k: v for k, v in os.environ.items() if k != "BAT3R_CATALOG"},
           "PREFECT_API_URL": PREFECT_API_URL.value(), "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, str(ROOT / "flows" / "bootstrap.py"), "--catalog", str(catalog / "data_catalog.yaml"),
           "--iterations", "0", "--run-name", "k1", *CLI_TINY]
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    try:
        deadline = time.monotonic() + 240
        while 0 not in _persisted_render_shards(layout) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        assert 0 in _persisted_render_shards(layout), "render shard 0 never completed"
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the flow and its Blender workers, mid-iteration
        proc.wait()
    assert not (layout.stage_dir(0, "train") / "predictor.pt").exists()
    assert read_manifest(layout)["config"]["parameters"]["catalog"] == str(catalog / "data_catalog.yaml")
    completed = _persisted_render_shards(layout)  # task finished: shard written and its record persisted
    kept = {p.name: (p.stat().st_mtime_ns, shards.content_hash([p]))
            for i in completed for p in layout.stage_dir(0, "render").glob(f"part-{i:05d}.*")}

    from flows.bootstrap import bootstrap

    resumed = bootstrap(category="toy", preset="tiny", iterations=0, run_name="k1", overrides=TINY)
    states = resumed["iterations"][0]["states"]
    assert states["plan"] == ["Cached"]
    assert [s == "Cached" for s in states["render"]] == [i in completed for i in (0, 1)]
    for name, (mtime, digest) in kept.items():  # completed shards reused, not rewritten
        p = layout.stage_dir(0, "render") / name
        assert (p.stat().st_mtime_ns, shards.content_hash([p])) == (mtime, digest)
    # the resumed run's training data equals the uninterrupted run's (same settings, different run folder)
    reference = RunLayout(catalog / "runs", "toy", "t1")
    for i in (0, 1):
        a = shards.read_shard(layout.stage_dir(0, "render"), i)[1]
        b = shards.read_shard(reference.stage_dir(0, "render"), i)[1]
        np.testing.assert_array_equal(a["P"], b["P"])
        np.testing.assert_array_equal(a["occupancy"], b["occupancy"])
    assert Path(resumed["iterations"][0]["predictor"]).is_file()
    # and the same metrics as the uninterrupted run (its iteration-0 row)
    resumed_rows = pq.read_table(layout.metrics).to_pylist()
    reference_rows = [r for r in pq.read_table(reference.metrics).to_pylist() if r["iteration"] == 0]
    assert resumed_rows == reference_rows


def test_raw_image_baseline_trains_on_the_photos_with_fitted_labels(first_run, catalog):
    from flows.bootstrap import bootstrap

    result = bootstrap(category="toy", preset="tiny", iterations=1, run_name="raw", raw_images=True,
                       overrides={**TINY, "train.batch_size": 4})  # 4 photos: one batch
    layout = RunLayout(catalog / "runs", "toy", "raw")
    it = result["iterations"][1]
    assert "plan_views" not in it["states"] and set(it["states"]) >= {"infer", "fit", "raw_images", "train", "evaluate"}
    table, arrays = shards.read_shard(layout.stage_dir(1, "render"), 0)
    collection, photos = shards.read_shard(layout.run_stage_dir("collection"), 0)
    # the training images are the collection's own crops, labelled by ray casting the fitted meshes
    np.testing.assert_array_equal(arrays["rgb"], photos["rgb"])
    assert table.column("sample_id").to_pylist() == collection.column("sample_id").to_pylist()
    ok = shards.ok_mask(table)
    assert ok.any() and set(table.column("view_kind").to_pylist()) == {"raw_image"}
    assert arrays["occupancy"][ok].any(axis=(1, 2, 3)).all()


def test_canonical_replay_trains_on_iteration_zero_renders_too(first_run, catalog):
    """train.canonical_replay from another run's Φ₀: iteration 0 renders the canonical set that Φ₀ was trained on
    (same plan and seed: the same samples, the same labels) without training, and iteration 1 trains on its
    pseudo-label renders plus round(ratio × their number) canonical renders per epoch."""
    from flows.bootstrap import bootstrap

    base = RunLayout(catalog / "runs", "toy", "t1")
    result = bootstrap(category="toy", preset="tiny", iterations=1, run_name="replay",
                       overrides={**TINY, "train.canonical_replay": 0.5},
                       init_predictor=str(base.stage_dir(0, "train") / "predictor.pt"))
    layout = RunLayout(catalog / "runs", "toy", "replay")
    assert not layout.stage_dir(0, "train").exists()
    mine, theirs = shards.read_table(layout.stage_dir(0, "render")), shards.read_table(base.stage_dir(0, "render"))
    assert mine.column("sample_id").to_pylist() == theirs.column("sample_id").to_pylist()
    np.testing.assert_allclose(shards.read_shard(layout.stage_dir(0, "render"), 0)[1]["Q"].astype(np.float32),
                               shards.read_shard(base.stage_dir(0, "render"), 0)[1]["Q"].astype(np.float32), atol=2e-3)
    n_canonical = int(shards.ok_mask(mine).sum())
    n_pseudo = int(shards.ok_mask(shards.read_table(layout.stage_dir(1, "render"))).sum())
    train = result["iterations"][1]["stages"]["train"][0]
    assert train["n_replayed"] == min(n_canonical, max(1, round(0.5 * n_pseudo))) > 0
    assert train["n_samples"] == n_pseudo + train["n_replayed"]


def test_random_poses_baseline_from_a_given_phi0_trains_it_on(first_run, catalog):
    """random_poses with init_predictor: the random-poses baseline as an arm from another run's Φ₀ — iteration 0
    renders random poses and trains that Φ₀ on (a warm start), instead of only evaluating it. The sampler's
    settings are overrides (``random_poses.*``): here σ = 0.66 rad, joints bent ~28° on average instead of the
    supplement's ~7°."""
    import torch

    from bat3r_core.poses import mean_joint_angle_deg
    from flows.bootstrap import bootstrap

    base = RunLayout(catalog / "runs", "toy", "t1")
    phi0 = base.stage_dir(0, "train") / "predictor.pt"
    result = bootstrap(category="toy", preset="tiny", iterations=0, run_name="rp-warm", random_poses=True,
                       overrides={**TINY, "train.steps": 3, "random_poses.sigma1": 0.66, "random_poses.sigma2": 0.66},
                       init_predictor=str(phi0))
    layout = RunLayout(catalog / "runs", "toy", "rp-warm")
    it = result["iterations"][0]
    assert it["predictor"] == str(layout.stage_dir(0, "train") / "predictor.pt") != str(phi0)
    table = shards.read_table(layout.stage_dir(0, "render"))
    assert set(table.column("view_kind").to_pylist()) == {"random_pose"}
    bends = mean_joint_angle_deg(shards.read_table(layout.stage_dir(0, "plan")).column("excess_rotations").to_pylist())
    assert 20.0 < bends < 36.0, bends  # the supplement's sampler: ~7°
    mine, theirs = (torch.load(p, map_location="cpu", weights_only=True) for p in (it["predictor"], phi0))
    # 3 steps from Φ₀'s weights: close to them, not equal (a model trained from scratch would be nowhere near)
    key = next(k for k, v in theirs["model"].items() if v.dtype.is_floating_point and v.numel() > 100)
    diff = (mine["model"][key] - theirs["model"][key]).abs()
    assert 0 < diff.max() < 0.1 * theirs["model"][key].abs().max(), diff.max()


def test_baselines_that_do_not_iterate_say_so(prefect_harness, catalog):
    from flows.bootstrap import bootstrap

    with pytest.raises(ValueError, match="random_poses is a baseline trained once on random poses"):
        bootstrap(category="toy", preset="tiny", run_name="t2", overrides=TINY, random_poses=True)


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


CHROMIUM = Path("/usr/bin/chromium")


@pytest.mark.prefect_server
@pytest.mark.browser
def test_server_worker_deployment_run_artifacts_and_dashboard(first_run, catalog, tmp_path):
    """deploy/server.sh → `prefect deployment run bootstrap/toy --watch` (run t1 again: every task is cached) →
    artifacts through the API → the flow run's dashboard page in headless Chromium → deploy/server-stop.sh."""
    port = _free_port()
    home = tmp_path / "prefect-home"
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    env.update(PREFECT_HOME=str(home), BAT3R_PREFECT_PORT=str(port), PREFECT_SERVER_ANALYTICS_ENABLED="false",
               BAT3R_CATALOG=os.environ["BAT3R_CATALOG"], PY=sys.executable, PREFECT_WORKER_QUERY_SECONDS="1")
    api = f"http://127.0.0.1:{port}/api"
    try:
        up = subprocess.run(["bash", str(ROOT / "deploy" / "server.sh")], cwd=ROOT, env=env, capture_output=True,
                            text=True, timeout=240)
        assert up.returncode == 0, up.stdout + up.stderr
        assert f"Prefect dashboard: http://127.0.0.1:{port}" in up.stdout
        for name in ("toy", "horse", "cow", "sheep"):
            assert f"bootstrap/{name}" in up.stdout
        params = '{"run_name": "t1", "overrides": ' + __import__("json").dumps(TINY) + "}"
        run = subprocess.run([sys.executable, "-m", "prefect", "deployment", "run", "bootstrap/toy", "--watch",
                              "--watch-timeout", "300", "--params", params], cwd=ROOT,
                             env={**env, "PREFECT_API_URL": api}, capture_output=True, text=True, timeout=330)
        assert run.returncode == 0 and "Completed" in run.stdout, run.stdout[-3000:] + run.stderr[-3000:]

        check = subprocess.run([sys.executable, "-c", _API_CHECK], cwd=ROOT, env={**env, "PREFECT_API_URL": api},
                               capture_output=True, text=True, timeout=60)
        assert check.returncode == 0, check.stderr
        run_id, summary = check.stdout.split("\n", 1)
        assert "# toy / t1: iteration 0" in summary and "**render**: 2 of 2 task(s) done (2 from cache)" in summary

        if CHROMIUM.exists():
            dom = subprocess.run([str(CHROMIUM), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                                  "--no-first-run", "--disable-background-networking", "--disable-component-update",
                                  "--disable-sync", f"--user-data-dir={tmp_path / 'chromium'}",
                                  "--virtual-time-budget=20000", "--dump-dom",
                                  f"http://127.0.0.1:{port}/runs/flow-run/{run_id.strip()}"],
                                 capture_output=True, text=True, timeout=120)
            assert "toy-t1" in dom.stdout and "Completed" in dom.stdout, dom.stdout[-2000:]
    finally:
        down = subprocess.run(["bash", str(ROOT / "deploy" / "server-stop.sh")], cwd=ROOT, env=env,
                              capture_output=True, text=True, timeout=120)
    assert "server: stopped" in down.stdout and "worker: stopped" in down.stdout, down.stdout + down.stderr
    assert not (home / "bat3r-server" / "server.pid").exists()


_API_CHECK = """
from prefect.client.orchestration import get_client
from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterKey, FlowRunFilter, FlowRunFilterName
with get_client(sync_client=True) as c:
    (run,) = c.read_flow_runs(flow_run_filter=FlowRunFilter(name=FlowRunFilterName(any_=["toy-t1"])))
    assert run.state.is_completed(), run.state
    keys = {a.key for a in c.read_artifacts()}
    needed = {f"toy-t1-iter-00-{s}" for s in ("plan", "render", "features", "train", "summary")}
    assert needed <= keys, sorted(keys)
    key = ArtifactFilter(key=ArtifactFilterKey(any_=["toy-t1-iter-00-summary"]))
    (summary,) = c.read_artifacts(artifact_filter=key)
    print(run.id)
    print(summary.data)
"""
