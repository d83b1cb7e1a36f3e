"""A real stage task (features) mapped over 2 shards in a flow: cache hits on rerun, integrity, failures, Dask."""
from __future__ import annotations

import pytest
from prefect import flow

from bat3r_core import shards
from bat3r_core.predictor.synthetic import write_synthetic_shards
from bat3r_core.runs import RunLayout, TooManyFailedShards
from flows._fanout import artifact_key, run_stage
from tasks._cache import for_run
from tasks.features import extract_features_shard

CONFIG = {"extractor": "rgb", "batch_size": 4, "device": "cpu"}


@flow(name="test-features-fanout")
def features_flow(root: str, config: dict, max_failed_fraction: float = 0.0, retries: int = 0):
    layout = RunLayout(root, "toy", "fanout")
    task = for_run(extract_features_shard, layout, retries=retries, retry_delay_seconds=0)
    calls = [{"input_dir": str(layout.stage_dir(0, "render")), "index": i,
              "out_dir": str(layout.stage_dir(0, "features")), "config": config} for i in (0, 1)]
    return run_stage("features", task, calls, progress_key=artifact_key("fanout", "features"),
                     max_failed_fraction=max_failed_fraction)


def _inputs(root):
    layout = RunLayout(root, "toy", "fanout")
    write_synthetic_shards(layout.stage_dir(0, "render"), n=6, resolution=16, layers=2, shard_size=3, seed=3)
    return layout


def _snapshot(folder):
    return {p.name: (p.stat().st_mtime_ns, shards.content_hash([p])) for p in sorted(folder.iterdir())
            if p.suffix in (".parquet", ".npz")}


def test_rerun_hits_the_cache_and_recomputes_only_what_vanished(prefect_harness, tmp_path):
    layout = _inputs(tmp_path)
    first = features_flow(str(tmp_path), CONFIG)
    assert first.states == ("Completed", "Completed") and first.cached == 0
    out = layout.stage_dir(0, "features")
    table, arrays = shards.read_shard(out, 1)
    assert arrays["grid"].shape == (3, 3, 16, 16) and table.num_rows == 3
    before = _snapshot(out)
    assert sorted(before) == ["part-00000.npz", "part-00000.parquet", "part-00001.npz", "part-00001.parquet"]
    assert list(layout.results_dir.iterdir())  # results persisted under the run folder

    second = features_flow(str(tmp_path), CONFIG)
    assert second.states == ("Cached", "Cached") and second.cached == 2 and second.recomputed == 0
    assert second.records == first.records
    assert _snapshot(out) == before  # nothing rewritten

    (out / "part-00001.npz").unlink()  # a vanished output is recomputed, identically
    third = features_flow(str(tmp_path), CONFIG)
    assert third.cached == 1 and third.recomputed == 1
    after = _snapshot(out)
    assert after["part-00000.npz"] == before["part-00000.npz"]
    assert after["part-00001.npz"][1] == before["part-00001.npz"][1]

    changed = features_flow(str(tmp_path), {**CONFIG, "batch_size": 2})  # a changed setting recomputes
    assert changed.states == ("Completed", "Completed")


def test_failing_shard_is_retried_then_reported(prefect_harness, tmp_path):
    layout = _inputs(tmp_path)
    (layout.stage_dir(0, "render") / "part-00001.npz").write_bytes(b"not an npz")  # inject a broken shard
    result = features_flow(str(tmp_path), CONFIG, max_failed_fraction=0.5, retries=1)
    assert result.states == ("Completed", "Failed")
    assert [r["index"] for r in result.records] == [0]
    (failure,) = result.summary.failures
    assert failure.label == "part-00001" and "(after 2 attempt(s))" in failure.reason
    with pytest.raises(TooManyFailedShards, match=r"features: 1 of 2 shards failed \(50.0%, limit 0.0%\)"):
        features_flow(str(tmp_path), CONFIG, max_failed_fraction=0.0)


def test_dask_local_cluster_runs_and_caches(prefect_harness, tmp_path):
    from flows._runners import make_task_runner

    _inputs(tmp_path)
    runner = make_task_runner({"kind": "dask", "workers": 2, "threads_per_worker": 1, "processes": False,
                               "local_directory": str(tmp_path / "dask")})
    dask_flow = features_flow.with_options(task_runner=runner)
    first = dask_flow(str(tmp_path), CONFIG)
    assert first.states == ("Completed", "Completed")
    second = dask_flow(str(tmp_path), CONFIG)
    assert second.states == ("Cached", "Cached") and second.records == first.records
