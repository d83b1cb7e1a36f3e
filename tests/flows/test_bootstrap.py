"""The bootstrap flow (canonical initialisation) end to end: real Blender, ray casting and training at tiny sizes;
the rerun hits the cache for every task; a SIGKILLed run resumes and reuses its completed shards."""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from prefect import flow

from bat3r_core import shards
from bat3r_core.runs import RunLayout, read_manifest

ROOT = Path(__file__).resolve().parents[2]
TINY = {"run.canonical_samples": 8, "run.collection_size": 4, "run.test_size": 4, "train.steps": 4,
        "shard_size": 4}
CLI_TINY = [f"--set={k}={v}" for k, v in TINY.items()]


@pytest.fixture(scope="module")
def catalog(tmp_path_factory):
    """A copy of the data catalog in a tmp folder: runs, collections and the toy asset all land there."""
    folder = tmp_path_factory.mktemp("catalog")
    shutil.copy(ROOT / "data_catalog.yaml", folder / "data_catalog.yaml")
    old = {k: os.environ.get(k) for k in ("BAT3R_CATALOG", "BAT3R_STORAGE_ROOT")}
    os.environ["BAT3R_CATALOG"] = str(folder / "data_catalog.yaml")
    os.environ.pop("BAT3R_STORAGE_ROOT", None)
    yield folder
    for k, v in old.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


@pytest.fixture(scope="module")
def first_run(prefect_harness, catalog):
    from flows.bootstrap import bootstrap

    t0 = time.perf_counter()
    result = bootstrap(category="toy", preset="tiny", iterations=0, run_name="t1", overrides=TINY)
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


def test_rerun_hits_the_cache_for_every_task(first_run, catalog):
    from flows.bootstrap import bootstrap

    layout = RunLayout(catalog / "runs", "toy", "t1")
    before = {s: _hashes(layout.stage_dir(0, s)) for s in ("plan", "render", "features")}
    predictor = shards.content_hash([layout.stage_dir(0, "train") / "predictor.pt"])
    again = bootstrap(category="toy", preset="tiny", iterations=0, run_name="t1", overrides=TINY)
    states = again["iterations"][0]["states"]
    assert states == {"plan": ["Cached"], "render": ["Cached", "Cached"], "features": ["Cached", "Cached"],
                      "train": ["Cached"]}
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


def test_killed_run_resumes_from_its_completed_shards(first_run, catalog, prefect_harness):
    from prefect.settings import PREFECT_API_URL

    layout = RunLayout(catalog / "runs", "toy", "k1")
    env = {**os.environ, "PREFECT_API_URL": PREFECT_API_URL.value(), "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, str(ROOT / "flows" / "bootstrap.py"), "--iterations", "0", "--run-name", "k1",
           *CLI_TINY]
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    first_shard = layout.stage_dir(0, "render") / "part-00000.parquet"
    try:
        deadline = time.monotonic() + 240
        while not first_shard.is_file() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        assert first_shard.is_file(), "the first render shard never appeared"
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the flow and its Blender workers, mid-iteration
        proc.wait()
    assert not (layout.stage_dir(0, "train") / "predictor.pt").exists()
    done = set(shards.list_shards(layout.stage_dir(0, "render")))
    kept = _hashes(layout.stage_dir(0, "render"))

    from flows.bootstrap import bootstrap

    resumed = bootstrap(category="toy", preset="tiny", iterations=0, run_name="k1", overrides=TINY)
    states = resumed["iterations"][0]["states"]
    assert states["plan"] == ["Cached"]
    assert [s == "Cached" for s in states["render"]] == [i in done for i in (0, 1)]
    after = _hashes(layout.stage_dir(0, "render"))
    assert all(after[name] == h for name, h in kept.items())  # completed shards reused, not rewritten
    # the resumed run's training data equals the uninterrupted run's (same settings, different run folder)
    reference = RunLayout(catalog / "runs", "toy", "t1")
    for i in (0, 1):
        a = shards.read_shard(layout.stage_dir(0, "render"), i)[1]
        b = shards.read_shard(reference.stage_dir(0, "render"), i)[1]
        np.testing.assert_array_equal(a["P"], b["P"])
        np.testing.assert_array_equal(a["occupancy"], b["occupancy"])
    assert Path(resumed["iterations"][0]["predictor"]).is_file()


def test_iterations_beyond_the_initialisation_name_what_is_missing(prefect_harness, catalog):
    from flows.bootstrap import bootstrap

    with pytest.raises(ValueError, match="iterations=2: bootstrap iterations after the canonical initialisation "
                                         "need bat3r_core functions that do not exist yet"):
        bootstrap(category="toy", preset="tiny", run_name="t2", overrides=TINY)
