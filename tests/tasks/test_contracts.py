"""One contract test per task of the stage table: its inputs → the shard (or file) it writes → the fields of the
record it returns. The tasks run in pipeline order on the toy at tiny sizes, each on the previous ones' real
outputs, with the typed stage specs the flow builds (``flows._settings.stage_specs`` of ``resolve_run``), called
as plain functions (``task.fn``) inside one Prefect flow run so their loggers and artifacts work.

A record's ``content_hash`` must be the hash of the files it names, its row counts those of its shard: downstream
stages and the cache trust both."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from bat3r_core import shards, stages
from bat3r_core.specs import EvaluateSpec, GeneratedCollectionSpec, TruthSpec
from bat3r_core.predictor.collection import CollectionConfig, list_collection
from bat3r_core.runs import summarize_drops

# the shard-record fields (bat3r_core.runs.shard_record) downstream stages and the drop reports read
SHARD_RECORD = {"stage", "index", "parquet", "npz", "content_hash", "n_rows", "n_ok", "n_failed", "failed_samples",
                "status_counts", "status_examples"}
TINY = {"run.image_size": 32, "run.canonical_samples": 4, "run.collection_size": 4, "run.test_size": 4,
        "shard_size": 4, "train.steps": 3, "train.batch_size": 2, "train.warmup_steps": 1, "train.checkpoint_every": 2,
        "fitting.steps": 10, "render.samples": 2}


def _task(name: str):
    return stages.resolve(stages.stage(name).task)


def _hash_of(record) -> str:
    return shards.content_hash([Path(f) for f in record["files"]])


def _shard_contract(record, stage: str, folder: Path, index: int = 0) -> None:
    """A shard record: the fields, the files of shard ``index`` of ``folder``, their hash and row counts."""
    assert SHARD_RECORD <= set(record), SHARD_RECORD - set(record)
    paths = shards.shard_paths(folder, index)
    assert record["stage"] == stage and record["index"] == index and paths.complete
    assert record["parquet"] == str(paths.parquet)
    files = [paths.parquet] + ([paths.npz] if paths.npz.is_file() else [])
    assert record["content_hash"] == shards.content_hash(files)
    table = pq.read_table(paths.parquet)
    assert record["n_rows"] == table.num_rows and record["n_ok"] == int(shards.ok_mask(table).sum())
    assert record["n_failed"] == record["n_rows"] - record["n_ok"] == sum(record["status_counts"].values())
    drops = summarize_drops(stage, [record])
    assert (drops.n_total, drops.n_ok) == (record["n_rows"], record["n_ok"])


@pytest.fixture(scope="module")
def chain(prefect_harness, catalog, tmp_path_factory):
    """Every task once, in data-flow order, on one tiny toy run; returns {stage: (record, output folder)}."""
    from prefect import flow

    from flows._settings import resolve_run
    from flows._settings import stage_specs

    settings = resolve_run("toy", "tiny", "contracts", TINY)
    cfg = stage_specs(settings, seed=0)
    layout = settings.layout.create()
    root, asset = layout.root, settings.assets.asset
    spec = settings.collection
    out: dict[str, tuple[dict, Path]] = {}

    def at(stage: str, iteration: int | None = None) -> str:
        return str(stages.output_dir(root, stage, iteration))

    @flow(name="task-contracts")
    def run_chain() -> None:
        images = Path(spec["path"])
        gen = _task("generated_collection").fn(str(images), GeneratedCollectionSpec(
            n=spec["n"], seed=spec["seed"], resolution=settings.image_size, render=settings.render,
            ground_truth_dir=spec["ground_truth"], pose_sampler=spec["pose_sampler"]))
        out["generated_collection"] = (gen, images)
        samples = [{"sample_id": s.sample_id, "image_path": str(s.image_path), "mask_path": str(s.mask_path)}
                   for s in list_collection(images)]
        ccfg = CollectionConfig(resolution=settings.image_size, shard_size=settings.shard_size)
        for split in ("collection", "test"):  # the collection doubles as the test split: it has ground truth
            out[split] = (_task(split).fn(samples, 0, at(split), ccfg), Path(at(split)))
        plan = _task("plan").fn(asset, at("plan", 0), cfg.plan)
        out["plan"] = (plan, Path(at("plan", 0)))
        out["render"] = (_task("render").fn(plan["files"][0], 0, at("render", 0), cfg.render),
                         Path(at("render", 0)))
        out["features"] = (_task("features").fn(at("render", 0), 0, at("features", 0), cfg.features),
                           Path(at("features", 0)))
        train = _task("train").fn(at("render", 0), at("train", 0), cfg.train_from(None),
                                  features_dir=at("features", 0))
        out["train"] = (train, Path(at("train", 0)))
        for stage, split, it in (("infer", "collection", 1), ("collection_infer", "collection", 0),
                                 ("test_infer", "test", 0)):
            out[stage] = (_task(stage).fn(train["predictor"], at(split), 0, at(stage, it), cfg.infer),
                          Path(at(stage, it)))
        out["fit"] = (_task("fit").fn(asset, at("infer", 1), 0, at("fit", 1), cfg.fit), Path(at("fit", 1)))
        truth = TruthSpec(asset=asset, ground_truth=str(Path(spec["ground_truth"]) / "ground_truth.npz"))
        out["pseudo_labels"] = (_task("pseudo_labels").fn(at("fit", 1), at("pseudo_labels", 1),
                                                          truth),
                                Path(at("pseudo_labels", 1)))
        out["filter"] = (_task("filter").fn(asset, at("fit", 1), at("infer", 1), at("filter", 1), cfg.filter),
                         Path(at("filter", 1)))
        errors = str(Path(at("pseudo_labels", 1)) / "pseudo_labels.parquet")
        out["filter_check"] = (_task("filter_check").fn(at("fit", 1), at("filter", 1), errors, at("filter_check", 1),
                                                        truth),
                               Path(at("filter_check", 1)))
        out["plan_views"] = (_task("plan_views").fn(asset, at("fit", 1), 0, at("plan_views", 1), cfg.plan_views,
                                                    filter_dir=at("filter", 1)), Path(at("plan_views", 1)))
        out["raw_images"] = (_task("raw_images").fn(asset, at("fit", 1), at("collection"), 0, at("raw_images", 1),
                                                    cfg.raw_images), Path(at("raw_images", 1)))
        out["evaluate"] = (_task("evaluate").fn(at("test_infer", 0), 0, at("evaluate", 0),
                                                EvaluateSpec(asset=asset, ground_truth=truth.ground_truth,
                                                             body_frame=settings.body_frame, split="test",
                                                             iteration=0)),
                           Path(at("evaluate", 0)))
        out["evaluate_collection"] = (_task("evaluate_collection").fn(
            at("collection_infer", 0), 0, at("collection"), None, at("evaluate_collection", 0),
            cfg.collection_evaluation_at(0)), Path(at("evaluate_collection", 0)))
        out["metrics"] = (_task("metrics").fn(str(root), {}), root)
        out["report"] = (_task("report").fn(str(root)), root)

    run_chain()
    return out


def test_every_stage_of_the_table_has_a_contract_here(chain):
    assert set(chain) == {s.name for s in stages.STAGES}


@pytest.mark.parametrize("stage", ["collection", "test", "render", "features", "infer", "collection_infer",
                                   "test_infer", "fit", "raw_images", "evaluate", "evaluate_collection"])
def test_shard_tasks_write_one_shard_and_describe_it(chain, stage):
    record, folder = chain[stage]
    _shard_contract(record, stages.stage(stage).own_task if stage != "test" else "collection", folder)
    table, arrays = shards.read_shard(folder, 0)
    n_in = {"collection": 4, "test": 4, "render": 4, "features": 4, "raw_images": 4}.get(stage, table.num_rows)
    assert table.num_rows == n_in and record["n_ok"] >= 1
    expected_arrays = {"collection": {"rgb", "mask"}, "test": {"rgb", "mask"},
                       "render": {"rgb", "mask", "P", "Q", "occupancy", "object_depth"},
                       "features": {"grid", "mask"}, "raw_images": {"rgb", "mask", "P", "Q", "occupancy"}}
    assert expected_arrays.get(stage, set()) <= set(arrays)
    if stage in ("infer", "collection_infer", "test_infer"):
        assert Path(record["clouds"]).is_file() and record["clouds"].startswith(str(folder))
    if stage == "features":  # row for row with the training shard it describes
        render_rows = shards.read_table(chain["render"][1]).column("sample_id").to_pylist()
        assert table.column("sample_id").to_pylist() == render_rows and arrays["grid"].dtype == np.float32


def test_generated_collection_writes_images_masks_and_hidden_truth(chain):
    record, images = chain["generated_collection"]
    assert {"images_dir", "masks_dir", "ground_truth_dir", "n_images", "reused", "files", "content_hash",
            "n_rows", "n_ok"} <= set(record)
    assert record["n_images"] == record["n_ok"] == 4 and not record["reused"]
    assert len(list(Path(record["images_dir"]).iterdir())) == 4 == len(list(Path(record["masks_dir"]).iterdir()))
    assert (Path(record["ground_truth_dir"]) / "ground_truth.npz").is_file()
    assert record["content_hash"] == _hash_of(record)


def test_plan_and_plan_views_write_job_files(chain):
    from bat3r_core.render.jobs import read_jobs

    plan, _ = chain["plan"]
    assert {"stage", "files", "content_hash", "n_jobs", "n_shards"} <= set(plan)
    assert plan["stage"] == "plan" and plan["n_jobs"] == 4 == len(read_jobs(plan["files"][0]))
    assert plan["content_hash"] == _hash_of(plan)
    views, _ = chain["plan_views"]
    assert {"stage", "index", "files", "content_hash", "n_jobs", "n_fits", "n_kept"} <= set(views)
    jobs = read_jobs(views["files"][0])
    assert views["stage"] == "plan_views" and views["n_jobs"] == len(jobs) and views["n_kept"] <= views["n_fits"]
    kept = {r["sample_id"] for r in shards.read_table(chain["filter"][1]).to_pylist() if r["kept"]}
    assert {j.source_id for j in jobs} <= kept and views["content_hash"] == _hash_of(views)


def test_train_writes_a_predictor_from_the_feature_shards(chain):
    record, folder = chain["train"]
    assert {"stage", "predictor", "files", "content_hash", "steps", "final_loss", "n_samples",
            "shards_without_features"} <= set(record)
    assert record["predictor"] == str(folder / "predictor.pt") and record["n_samples"] == chain["render"][0]["n_ok"]
    assert record["steps"] == 3 and np.isfinite(record["final_loss"]) and record["shards_without_features"] == []
    assert record["content_hash"] == _hash_of(record)


def test_filter_and_its_check_describe_their_files(chain):
    record, folder = chain["filter"]
    assert {"stage", "files", "parquet"} <= set(record) and record["stage"] == "filter"
    decided = pq.read_table(record["parquet"]).to_pylist()
    assert [r["sample_id"] for r in decided] == shards.read_table(chain["fit"][1]).column("sample_id").to_pylist()
    check, _ = chain["filter_check"]
    assert check["stage"] == "filter_check" and check["content_hash"] == _hash_of(check)
    assert json.loads(Path(check["files"][0]).read_text())  # the precision figures, as JSON
    labels, _ = chain["pseudo_labels"]
    assert labels["stage"] == "pseudo_labels" and labels["content_hash"] == _hash_of(labels)
    assert pq.read_table(labels["files"][0]).num_rows == shards.read_table(chain["fit"][1]).num_rows


def test_metrics_and_report_cover_the_evaluated_iteration(chain):
    record, root = chain["metrics"]
    assert {"stage", "files", "content_hash", "rows"} <= set(record) and record["content_hash"] == _hash_of(record)
    splits = {(r["iteration"], r["split"]) for r in record["rows"]}
    assert {(0, "test"), (0, "collection")} <= splits
    report, _ = chain["report"]
    assert {"stage", "report", "files", "content_hash", "file_digests"} <= set(report)
    assert report["report"] == str(root / "report.html") == report["files"][0]
    assert "metrics-over-iterations" in Path(report["report"]).read_text() and report["content_hash"] == _hash_of(report)


def test_every_record_carries_the_writers_digests_of_its_files(chain):
    """Hash once: the digest a downstream key or intact check needs comes with the record, checked by stat."""
    from tasks._cache import record_files

    for stage, (record, _) in chain.items():
        digests = record["file_digests"]
        files = record_files(record)
        assert files and sorted(digests) == sorted(str(f.resolve()) for f in files), stage
        for f in files:
            sha, inode, size, _, _ = digests[str(f.resolve())]
            assert sha == shards.file_digest(f).hex() and (inode, size) == (f.stat().st_ino, f.stat().st_size)
