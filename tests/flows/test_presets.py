"""Every run preset of the shipped catalog through the bootstrap flow, cut down to CPU sizes (as nerfstudio runs its
method configs): `tiny` in test_bootstrap.py, `bench` in test_bench_fidelity.py, `demo` and `paper` here — `paper`
with the `dinov2` features of a small randomly initialised DINOv2 saved locally and the robust loss. At `paper`,
the features of every image are computed once in the run: the training renders by the features stage (training
streams its shards), the collection and test images once, then from the feature cache."""
from __future__ import annotations

from pathlib import Path

import pytest

from bat3r_core import evaluation, shards
from bat3r_core.catalog import load_catalog
from bat3r_core.runs import RunLayout, read_manifest

# what every preset is cut to: one shard per stage, a few steps, and the same collection (n8-r32) for all
CUT = {"run.image_size": 32, "run.canonical_samples": 8, "run.collection_size": 8, "run.test_size": 4,
       "shard_size": 8, "train.steps": 4, "train.batch_size": 4, "train.warmup_steps": 1,
       "train.checkpoint_every": 2, "model.base_channels": 8, "model.depth": 2, "fitting.steps": 20,
       "fitting.min_valid_points": 5, "fitting.inlier_distance": 1.0, "render.samples": 2, "render.denoise": False,
       "pseudo_label_filter.min_kept": 2}
COVERED_ELSEWHERE = {"tiny": "tests/flows/test_bootstrap.py", "bench": "tests/flows/test_bench_fidelity.py"}
HERE = ("demo", "paper")


def test_every_catalog_preset_runs_through_the_flow_in_ci(catalog):
    presets = set(load_catalog(catalog / "data_catalog.yaml").runs)
    assert presets == set(COVERED_ELSEWHERE) | set(HERE), "a new run preset needs a cut-down flow run in CI"


@pytest.fixture(scope="module")
def dinov2_folder(tmp_path_factory):
    from bat3r_core.predictor.synthetic import save_random_dinov2

    return save_random_dinov2(tmp_path_factory.mktemp("dinov2") / "random", seed=0, patch_size=8, image_size=32)


def _overrides(preset: str, dinov2: str) -> dict:
    if preset != "paper":
        return dict(CUT)
    # 32-pixel crops into a 32-pixel ViT of 8-pixel patches: a 4x4 grid of 8 PCA channels
    return {**CUT, "features.dinov2.model": dinov2, "features.dinov2.input_size": 32, "features.dinov2.channels": 8,
            "model.in_channels": 8, "features.batch_size": 16}


@pytest.mark.parametrize("preset", HERE)
def test_preset_runs_one_refinement_iteration(preset, prefect_harness, catalog, dinov2_folder):
    from bat3r_core.predictor.config import TrainConfig
    from bat3r_core.predictor.features import feature_stats
    from flows.bootstrap import bootstrap

    before = feature_stats()
    result = bootstrap(category="toy", preset=preset, iterations=1, run_name=f"preset-{preset}",
                       overrides=_overrides(preset, dinov2_folder))
    after = feature_stats()
    layout = RunLayout(catalog / "runs", "toy", f"preset-{preset}")
    config = read_manifest(layout)["config"]
    rows = {(r["iteration"], r["split"]): r for r in evaluation.read_metrics(layout.root).to_pylist()}
    assert {(0, "test"), (1, "test"), (0, "collection"), (1, "collection")} <= set(rows)
    assert (layout.stage_dir(1, "train") / "predictor.pt").is_file()
    assert all(s in {"Completed", "Cached"} for states in result["iterations"][1]["states"].values() for s in states)
    run = load_catalog(catalog / "data_catalog.yaml").runs[preset]
    assert config["features"]["extractor"] == run.features
    assert config["train"]["loss"] == run.train.get("loss", TrainConfig().loss)
    # the preset's own fitting and training settings that the cut leaves alone reach the run, e.g. the demo's
    # silhouette term and canonical replay
    for section in ("fitting", "train"):
        kept = {k: v for k, v in getattr(run, section).items() if f"{section}.{k}" not in CUT}
        assert {k: config[section][k] for k in kept} == kept, section
    if preset == "demo":
        assert config["train"]["canonical_replay"] > 0 and config["fitting"]["weight_silhouette"] > 0
    if preset != "paper":
        return
    # the catalog's features section reaches the flow (the model folder, the channels) and the robust loss is on
    assert config["features"]["dinov2"]["model"] == dinov2_folder and config["train"]["loss"] == "robust"
    grid = shards.read_shard(layout.stage_dir(1, "features"), 0)[1]["grid"]
    assert grid.shape[1:] == (8, 4, 4)  # the stored grid is the ViT's patch grid, not the 32x32 crop
    # each image's features are computed once in the whole run: the renders of both iterations by the features
    # stage, the collection and the test split by their first inference; later inferences hit the cache and
    # training reads the feature shards (it never calls the extractor)
    n_ok = sum(shards.ok_mask(shards.read_table(layout.stage_dir(i, "render"))).sum() for i in (0, 1))
    n_collection = shards.read_table(layout.run_stage_dir("collection")).num_rows
    n_test = shards.read_table(layout.run_stage_dir("test")).num_rows
    assert after.cache_misses - before.cache_misses == n_ok + n_collection + n_test
    # iteration 1 reads the collection twice (infer for fitting, collection_infer) and the test split once
    assert after.cache_hits - before.cache_hits == 2 * n_collection + n_test
    # model batches of up to 16 images per call: each feature shard, the collection's and the test split's first
    # inference, and the PCA fit on the first renders (one batch: 8 images) -- none for training
    per_call = [shards.ok_mask(shards.read_table(layout.stage_dir(i, "render"))).sum() for i in (0, 1)]
    calls = per_call + [n_collection, n_test]
    assert after.model_batches - before.model_batches == sum(-(-int(n) // 16) for n in calls) + (
        after.pca_fits - before.pca_fits)


def test_a_cached_rerun_of_the_demo_reads_each_run_file_at_most_once(prefect_harness, catalog, dinov2_folder):
    """Hash once, read once: rerunning the (cut-down) demo in a fresh process state hits the cache for every task
    and opens each file of the run folder at most once, whoever opens it (Prefect's result records, the cache keys'
    hashing, the intact checks, the report and the metrics: all counted by inotify, ``tests/file_reads.py``)."""
    from file_reads import FileReads
    from flows.bootstrap import bootstrap

    layout = RunLayout(catalog / "runs", "toy", "preset-demo")
    if not layout.metrics.is_file():  # the demo run of test_preset_runs_one_refinement_iteration
        bootstrap(category="toy", preset="demo", iterations=1, run_name="preset-demo",
                  overrides=_overrides("demo", dinov2_folder))
    shards.forget_file_digests()  # as a fresh process starts: no digest in memory
    with FileReads(layout.root) as reads:
        again = bootstrap(category="toy", preset="demo", iterations=1, run_name="preset-demo",
                          overrides=_overrides("demo", dinov2_folder))
    for it in again["iterations"]:
        assert all(s == "Cached" for states in it["states"].values() for s in states), it["states"]
    assert reads.counts, "nothing was read: the watch saw no event"
    results = layout.results_dir.relative_to(layout.root).as_posix() + "/"
    data = {f: n for f, n in reads.read_more_than_once().items() if not f.startswith(results)}
    assert data == {}, data
    # Prefect's result store reads a cached task's JSON record twice per lookup (its exists() check loads the payload,
    # then read() loads it again: ResultStore._exists in prefect/results.py reads the whole record); outside bat3r,
    # and bounded: metrics and report are looked up once per iteration, every other task once
    lookups = {"metrics": len(again["iterations"]), "report": len(again["iterations"])}
    records = {f: n for f, n in reads.read_more_than_once().items() if f.startswith(results)}
    assert all(n <= 2 * lookups.get(Path(f).name.rsplit("-", 1)[0], 1) for f, n in records.items()), records
    # most files were not even hashed: their digests came with the cached records. Hashed are only the files of the
    # last iteration that the run-level metrics and report keys already name at iteration 0 (before that
    # iteration's records are loaded), never a training shard
    hashed = sorted(Path(f).relative_to(layout.root).as_posix() for f in shards.file_digest_reads()
                    if str(layout.root) in f)
    assert hashed and not any(f.startswith("iter-00/") or "/render/" in f or "/features/" in f for f in hashed), hashed
