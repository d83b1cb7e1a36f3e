"""Run folder layout, manifest, stage code versions, shard records and the failed-shard policy."""
from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

from bat3r_core import evaluation, runs, shards


def test_layout_paths_match_the_storage_contract(tmp_path):
    layout = runs.RunLayout(tmp_path, "toy", "r1")
    assert layout.root == tmp_path / "toy" / "r1"
    assert layout.manifest == layout.root / "manifest.json"
    assert layout.metrics == layout.root / "metrics.parquet"
    assert layout.report == layout.root / "report.html"
    assert layout.stage_dir(3, "fit") == layout.root / "iter-03" / "fit"
    assert layout.stage_dir(12, "evaluate") == layout.root / "iter-12" / "evaluate"
    assert layout.run_stage_dir("collection") == layout.root / "collection"
    assert not layout.root.exists()
    layout.create()
    assert layout.root.is_dir()
    for i in (0, 1, 12):
        layout.iteration_dir(i).mkdir()
    # the evaluation module finds the same iteration folders
    assert [i for i, _ in evaluation.iteration_dirs(layout.root)] == [0, 1, 12]


@pytest.mark.parametrize("kwargs, match", [
    ({"category": "../x", "run_name": "r"}, "category must be a folder name"),
    ({"category": "toy", "run_name": ""}, "run_name must be a folder name"),
    ({"category": "toy", "run_name": "a/b"}, "run_name must be a folder name"),
])
def test_layout_rejects_bad_names(tmp_path, kwargs, match):
    with pytest.raises(ValueError, match=match):
        runs.RunLayout(tmp_path, **kwargs)


def test_layout_rejects_bad_stage_and_iteration(tmp_path):
    layout = runs.RunLayout(tmp_path, "toy", "r")
    with pytest.raises(ValueError, match="stage must be one of"):
        layout.stage_dir(0, "rendering")
    with pytest.raises(ValueError, match="iteration must be an integer >= 0, got -1"):
        layout.iteration_dir(-1)
    with pytest.raises(ValueError, match="run-level stage must be one of"):
        layout.run_stage_dir("fit")
    with pytest.raises(TypeError, match="storage_root must be a path"):
        runs.RunLayout(3, "toy", "r")


def _fake_package(root):
    pkg = root / "bat3r_core"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("from .b import thing\n")
    (pkg / "a.py").write_text("import os\nfrom bat3r_core import b\n\ndef f():\n    from .sub.c import x\n")
    (pkg / "b.py").write_text("thing = 1\n")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "sub" / "c.py").write_text("from ..d import y\nx = 2\n")
    (pkg / "d.py").write_text("y = 3\n")
    (pkg / "unrelated.py").write_text("z = 4\n")
    return pkg


def _reference_hash(pkg, names):
    # slow, obvious reference: hash the listed modules' bytes in name order
    h = hashlib.sha256()
    for name in sorted(names):
        rel = name.split(".")[1:]
        path = pkg.joinpath(*rel).with_suffix(".py")
        h.update(name.encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()[:16]


def test_stage_code_version_follows_imports(tmp_path, monkeypatch):
    pkg = _fake_package(tmp_path)
    monkeypatch.setattr(runs, "_PACKAGE_DIR", pkg)
    closure = runs._module_closure("bat3r_core.a")
    assert sorted(closure) == ["bat3r_core.a", "bat3r_core.b", "bat3r_core.d", "bat3r_core.sub.c"]
    v1 = runs.stage_code_version("bat3r_core.a")
    assert v1 == _reference_hash(pkg, closure)
    (pkg / "unrelated.py").write_text("z = 5\n")
    (pkg / "__init__.py").write_text("# re-exports changed\n")
    assert runs.stage_code_version("bat3r_core.a") == v1
    (pkg / "d.py").write_text("y = 30\n")  # reached through a function-level relative import
    v2 = runs.stage_code_version("bat3r_core.a")
    assert v2 != v1 and v2 == _reference_hash(pkg, closure)


def test_stage_code_version_of_real_modules():
    v = runs.stage_code_version("bat3r_core.evaluation")
    assert len(v) == 16 and v == runs.stage_code_version(evaluation)
    assert {"bat3r_core.shards", "bat3r_core.metrics"} <= set(runs._module_closure("bat3r_core.evaluation"))
    with pytest.raises(ValueError, match="must name a bat3r_core module"):
        runs.stage_code_version("numpy")
    with pytest.raises(TypeError, match="module or a dotted name"):
        runs.stage_code_version(3)


def test_manifest_round_trip_keeps_created(tmp_path):
    layout = runs.RunLayout(tmp_path, "toy", "r").create()
    assert runs.read_manifest(layout) == {}
    m1 = runs.write_manifest(layout, {"preset": "tiny", "train": {"steps": 4}}, {"evaluate": "bat3r_core.evaluation"})
    on_disk = json.loads(layout.manifest.read_text())
    assert on_disk == m1
    assert m1["config"] == {"preset": "tiny", "train": {"steps": 4}}
    assert m1["stage_code_versions"] == {"evaluate": runs.stage_code_version("bat3r_core.evaluation")}
    assert m1["code_version"] == runs.code_version() and m1["code_version"]
    stat = layout.manifest.stat()
    same = runs.write_manifest(layout, {"preset": "tiny", "train": {"steps": 4}}, {"evaluate": "bat3r_core.evaluation"})
    assert same == m1 and layout.manifest.stat().st_ino == stat.st_ino  # nothing changed: the file is not rewritten
    m2 = runs.write_manifest(layout, {"preset": "demo"}, {})
    assert m2["created"] == m1["created"] and m2["config"] == {"preset": "demo"}
    assert json.loads(layout.manifest.read_text()) == m2
    with pytest.raises(ValueError, match="JSON-serialisable"):
        runs.write_manifest(layout, {"x": float("nan")}, {})
    with pytest.raises(TypeError, match="config must be a mapping"):
        runs.write_manifest(layout, [1], {})


def test_shard_record_counts_and_hash(tmp_path):
    rows = [{"sample_id": f"s{i}", "status": "ok" if i != 1 else "bad_image", "reason": "" if i != 1 else "torn"}
            for i in range(3)]
    paths = shards.write_shard(tmp_path / "stage", 4, rows, {"x": np.arange(3.0)})
    rec = runs.shard_record("render", 4, paths)
    assert rec["n_rows"] == 3 and rec["n_ok"] == 2 and rec["n_failed"] == 1
    assert rec["failed_samples"] == [["s1", "bad_image", "torn"]]
    assert rec["content_hash"] == shards.content_hash([paths.parquet, paths.npz])
    assert rec["parquet"].endswith("part-00004.parquet") and rec["npz"].endswith("part-00004.npz")
    json.dumps(rec)
    with pytest.raises(FileNotFoundError, match="part-00005.parquet"):
        runs.shard_record("render", 5, shards.shard_paths(tmp_path / "stage", 5))


def test_failure_policy_continues_below_limit_and_fails_above():
    ok = runs.apply_failure_policy("render", 4, [("part-00002", "Blender crashed")], max_failed_fraction=0.25)
    assert ok.failed_fraction == pytest.approx(0.25)
    assert "render: 1 of 4 shards failed (25.0%, limit 25.0%)" in ok.describe()
    assert "part-00002: Blender crashed" in ok.describe()
    assert runs.apply_failure_policy("fit", 0, [], 0.0).failed_fraction == 0.0
    with pytest.raises(runs.TooManyFailedShards, match=r"render: 2 of 4 shards failed \(50.0%, limit 25.0%\)"
                       ) as info:
        runs.apply_failure_policy("render", 4, [("part-00001", "a"), runs.ShardFailure("part-00003", "b")], 0.25)
    assert "part-00003: b" in str(info.value) and info.value.summary.failed_fraction == 0.5
    import pickle

    assert str(pickle.loads(pickle.dumps(info.value))) == str(info.value)  # survives Prefect/Dask serialisation
    with pytest.raises(runs.TooManyFailedShards, match="1 of 10 shards failed"):
        runs.apply_failure_policy("train", 10, [("model", "nan loss")], 0.0)


@pytest.mark.parametrize("n_total, failures, limit, match", [
    (-1, [], 0.1, "n_total must be an integer >= 0"),
    (2, [], 1.5, r"max_failed_fraction must be a number in \[0, 1\]"),
    (2, [], float("nan"), r"max_failed_fraction must be a number in \[0, 1\]"),
    (1, [("a", "x"), ("b", "y")], 1.0, "2 failures reported"),
])
def test_failure_policy_checks_inputs(n_total, failures, limit, match):
    with pytest.raises(ValueError, match=match):
        runs.apply_failure_policy("s", n_total, failures, limit)


def test_prune_shards_removes_only_unplanned_indices(tmp_path):
    rows = [{"sample_id": "a", "status": "ok", "reason": ""}]
    for i in range(4):
        shards.write_shard(tmp_path, i, rows, {"x": np.zeros(1)})
    assert runs.prune_shards(tmp_path, keep=[0, 2]) == [1, 3]
    assert shards.list_shards(tmp_path) == [0, 2]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["part-00000.npz", "part-00000.parquet",
                                                          "part-00002.npz", "part-00002.parquet"]
    assert runs.prune_shards(tmp_path / "missing", keep=[]) == []


def _render_rows(statuses):
    reasons = {"ok": "", "mask_mismatch": "Blender mask and ray-cast occupancy disagree (IoU 0.412 < 0.8)",
               "failed": "the render worker crashed twice on this job"}
    return [{"sample_id": f"c{i:02d}", "status": s, "reason": reasons[s]} for i, s in enumerate(statuses)]


def test_drops_are_counted_over_shards_with_their_top_reason_and_an_example(tmp_path):
    # shard 0: 25 mismatches and 1 crash in 30 rows (more than the 20 rows failed_samples lists); shard 1: 2 ok
    p0 = shards.write_shard(tmp_path, 0, _render_rows(["ok"] * 4 + ["mask_mismatch"] * 25 + ["failed"]),
                            {"x": np.zeros(30)})
    p1 = shards.write_shard(tmp_path, 1, _render_rows(["ok", "ok"]), {"x": np.zeros(2)})
    records = [runs.shard_record("render", 0, p0), runs.shard_record("render", 1, p1)]
    assert records[0]["status_counts"] == {"mask_mismatch": 25, "failed": 1}
    assert records[0]["status_examples"]["failed"] == ["c29", "the render worker crashed twice on this job"]
    drops = runs.summarize_drops("render", records, "iteration 0 render")
    assert (drops.n_total, drops.n_ok, drops.n_dropped, drops.noun) == (32, 6, 26, "renders")
    assert [(r.status, r.count, r.sample_id) for r in drops.reasons] == [("mask_mismatch", 25, "c04"),
                                                                          ("failed", 1, "c29")]
    assert drops.reasons[0].shard == str(p0.parquet) and drops.exceeds()
    assert drops.describe() == (
        "iteration 0 render: 26 of 32 renders dropped (81.2 %): mask_mismatch ×25 (Blender mask and ray-cast "
        "occupancy disagree (IoU 0.412 < 0.8)); failed ×1 (the render worker crashed twice on this job) — e.g. "
        f"sample c04 in {p0.parquet}")
    table = drops.markdown()
    assert "| mask_mismatch | 25 | 78.1 % | Blender mask and ray-cast occupancy disagree (IoU 0.412 < 0.8) | " \
           f"`c04` | `{p0.parquet}` |" in table and "| failed | 1 | 3.1 % |" in table
    assert runs.SampleDrops.from_mapping(json.loads(json.dumps(drops.to_mapping()))) == drops
    # a record written before status_counts existed falls back on its listed failed samples
    old = {k: v for k, v in records[0].items() if k not in ("status_counts", "status_examples")}
    fallback = runs.summarize_drops("render", [old])
    assert fallback.n_dropped == 26 and [(r.status, r.count) for r in fallback.reasons] == [("mask_mismatch", 20)]
    # job files count their jobs as kept; training records count nothing
    jobs = runs.summarize_drops("plan", [{"n_jobs": 5, "files": []}, {"steps": 3}])
    assert (jobs.n_total, jobs.n_ok, jobs.noun, jobs.exceeds()) == (5, 5, "render jobs", False)


def test_the_warning_threshold_is_more_than_five_percent():
    assert runs.DROP_WARN_FRACTION == 0.05
    one = runs.SampleDrops("render", "render", "renders", 20, 19)
    two = runs.SampleDrops("render", "render", "renders", 20, 18)
    assert not one.exceeds() and two.exceeds() and one.exceeds(0.01)
    assert not runs.SampleDrops("x", "x", "samples", 0, 0).exceeds()


def test_too_few_samples_names_the_stage_the_reason_the_fix_and_the_need(tmp_path, monkeypatch):
    p0 = shards.write_shard(tmp_path, 0, _render_rows(["ok"] * 7 + ["mask_mismatch"] * 25), {"x": np.zeros(32)})
    drops = runs.summarize_drops("render", [runs.shard_record("render", 0, p0)], "iteration 0 render")
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    need = runs.training_need(8)
    assert need == runs.SampleNeed(8, "training", "batch_size × world_size")
    with pytest.raises(runs.TooFewSamples) as info:
        runs.require_samples(drops, need, category="horse", asset="assets/horse/horse.glb", catalog="my.yaml")
    assert str(info.value) == (
        "iteration 0 render: 25 of 32 renders dropped (78.1 %): mask_mismatch ×25 (Blender mask and ray-cast "
        "occupancy disagree (IoU 0.412 < 0.8)) — run `bat3r asset check assets/horse/horse.glb --category horse "
        "--catalog my.yaml` (the asset Blender renders and the rig bat3r ray-casts disagree: scale, up axis, skin); "
        f"training needs at least 8 (batch_size × world_size), 7 left (e.g. sample c07 in {p0.parquet})")
    assert info.value.drops == drops and info.value.need == need
    assert runs.require_samples(drops, runs.training_need(7)) is drops  # enough: the run goes on
    # samples lost upstream are named too; a pickled error keeps its message (Prefect, Dask)
    monkeypatch.setenv("WORLD_SIZE", "2")
    plan = runs.SampleDrops("iteration 1 plan", "plan", "render jobs", 6, 6)
    fit = runs.SampleDrops("iteration 1 fit", "fit", "fits", 4, 2, (runs.DropReason("too_few_points", 2, "3 inlier "
                                                                                   "points", "a", "f.parquet"),))
    with pytest.raises(runs.TooFewSamples) as info:
        runs.require_samples(plan, runs.training_need(4), [fit])
    assert str(info.value) == ("iteration 1 plan: 6 render jobs, none dropped; training needs at least 8 (batch_size "
                               "× world_size = 4 × 2), 6 left. Dropped before: iteration 1 fit: 2 of 4 fits dropped "
                               "(50.0 %): too_few_points ×2 (3 inlier points) — e.g. sample a in f.parquet")
    import pickle

    assert str(pickle.loads(pickle.dumps(info.value))) == str(info.value)


def test_folder_record_sums_the_shards_of_a_folder(tmp_path):
    shards.write_shard(tmp_path, 0, _render_rows(["ok", "failed"]), {"x": np.zeros(2)})
    p1 = shards.write_shard(tmp_path, 1, _render_rows(["mask_mismatch", "ok", "ok"]), {"x": np.zeros(3)})
    rec = runs.folder_record("generated_collection", tmp_path)
    assert (rec["n_rows"], rec["n_ok"], rec["n_failed"], rec["n_shards"]) == (5, 3, 2, 2)
    assert rec["failed_samples"][1] == ["c00", "mask_mismatch", _render_rows(["mask_mismatch"])[0]["reason"],
                                        str(p1.parquet)]
    drops = runs.summarize_drops("generated_collection", [rec], "collection images")
    assert drops.reasons[1].shard == str(p1.parquet) and drops.noun == "renders"
    with pytest.raises(FileNotFoundError, match="no complete shard"):
        runs.folder_record("x", tmp_path / "empty")
