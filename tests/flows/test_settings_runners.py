"""Run settings (presets, overrides, ablations), task runner configs and the iteration summary; no server."""
from __future__ import annotations

from pathlib import Path

import pytest

from bat3r_core.catalog import load_catalog
from bat3r_core.config_utils import ConfigError
from bat3r_core.runs import FailureSummary, ShardFailure
from bat3r_core.viewpoints import REFERENCE_STUDENT_T
from flows._fanout import StageResult, artifact_key

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture()
def catalog(tmp_path, monkeypatch):
    monkeypatch.setenv("BAT3R_STORAGE_ROOT", str(tmp_path / "runs"))
    return load_catalog(ROOT / "data_catalog.yaml")


def test_overrides_reach_their_stage_configs(catalog, tmp_path):
    from flows._settings import resolve_run

    s = resolve_run("toy", "tiny", "r1", {"train.steps": 7, "render.samples": 2, "run.canonical_samples": 12,
                                          "fitting.steps": 5, "shard_size": 3, "max_failed_fraction": 0.25},
                    catalog=catalog)
    assert (s.train.steps, s.render.samples, s.canonical_samples, s.fitting.steps) == (7, 2, 12, 5)
    assert (s.shard_size, s.max_failed_fraction) == (3, 0.25)
    assert s.model.resolution == s.render.resolution == s.image_size == 32
    assert s.layout.root == tmp_path / "runs" / "toy" / "r1"
    assert s.assets.textures == ("toy:bay", "toy:chestnut", "toy:grey", "toy:pinto")
    assert Path(s.assets.asset).is_file()  # the toy asset is generated on first use
    # generated collections are cached per size so presets do not overwrite each other
    assert s.collection["path"].endswith("runs/_collections/toy/train/n16-r32")
    assert s.test_split["ground_truth"].endswith("test_ground_truth/n8-r32") and s.test_split["n"] == 8
    m = s.to_mapping()
    assert m["train"]["steps"] == 7 and m["run_dir"] == str(s.layout.root)
    # run-preset overrides reach the stage configs derived from the preset (resolution, features, fitting)
    s = resolve_run("toy", "tiny", "r2", {"run.image_size": 48, "run.fitting": {"steps": 9}}, catalog=catalog)
    assert s.model.resolution == s.render.resolution == s.image_size == 48 and s.fitting.steps == 9
    assert s.collection["path"].endswith("n16-r48")


def test_mirroring_carries_the_rigs_checked_sagittal_plane_into_the_train_spec(catalog):
    from flows._settings import resolve_run, stage_specs

    off = resolve_run("toy", "tiny", "r1", catalog=catalog)
    assert off.mirror is None and stage_specs(off, 0).train.mirror is None
    on = resolve_run("toy", "tiny", "r1", {"train.mirror_probability": 0.5}, catalog=catalog)
    spec = stage_specs(on, 0).train
    assert spec.mirror == on.mirror and abs(abs(on.mirror.normal[0]) - 1.0) < 1e-6  # the toy's plane is x = 0
    assert spec.train.mirror_probability == 0.5


@pytest.mark.parametrize("overrides, match", [
    ({"trainer.steps": 1}, r"override 'trainer.steps': expected '<section>.<key>'"),
    ({"train.stepz": 1}, r"override 'stepz': no such key on TrainConfig"),
    ({"train.steps": "many"}, r"steps: expected an integer"),
    ({"shard_size": 0}, r"shard_size: must be >= 1, got 0"),
    ({"max_failed_fraction": 2}, r"max_failed_fraction: must be in \[0, 1\], got 2"),
    ({"run.model": {"depth": "deep"}}, r"runs\.tiny\.model\.depth: expected an integer"),  # the preset keeps its name
])
def test_bad_overrides_name_the_key(catalog, overrides, match):
    from flows._settings import resolve_run

    with pytest.raises(ConfigError, match=match):
        resolve_run("toy", "tiny", "r1", overrides, catalog=catalog)


def test_ablation_switches(catalog):
    from flows._settings import Ablations, resolve_run

    base = resolve_run("toy", "tiny", "r1", catalog=catalog)
    s = resolve_run("toy", "tiny", "r1", ablations={"gaussian_cameras": True, "no_fitting_regularisation": True},
                    catalog=catalog)
    assert base.camera_prior.distribution == "student_t"
    assert s.camera_prior.distribution == "normal"
    for view, ref in REFERENCE_STUDENT_T.items():
        got = s.camera_prior.per_view_type[view]
        assert (got.elevation.loc, got.elevation.scale, got.elevation.df) == (ref.elevation.loc,
                                                                               ref.elevation.scale, None)
        assert (got.roll.loc, got.roll.scale, got.roll.df) == (ref.roll.loc, ref.roll.scale, None)
    f = s.fitting
    assert (f.weight_angle, f.weight_edge, f.weight_volume, f.weight_repulsion, f.weight_scale) == (0, 0, 0, 0, 0)
    assert base.fitting.weight_edge > 0 and s.fitting.steps == base.fitting.steps
    assert s.ablations == Ablations(gaussian_cameras=True, no_fitting_regularisation=True)
    with pytest.raises(ConfigError, match=r"ablations: unknown key\(s\) \['gausian'\]"):
        resolve_run("toy", "tiny", "r1", ablations={"gausian": True}, catalog=catalog)


def test_task_runner_presets_and_configs(tmp_path):
    from prefect.task_runners import ThreadPoolTaskRunner
    from prefect_dask import DaskTaskRunner

    from flows._runners import load_task_runner_config, make_task_runner

    local = make_task_runner("local")
    assert isinstance(local, ThreadPoolTaskRunner) and local._max_workers == 2
    dask = make_task_runner({"kind": "dask", "workers": 3, "processes": False, "local_directory": str(tmp_path)})
    assert isinstance(dask, DaskTaskRunner)
    assert dask.cluster_class == "distributed.LocalCluster"
    assert dask.cluster_kwargs == {"n_workers": 3, "threads_per_worker": 1, "processes": False,
                                    "dashboard_address": None, "local_directory": str(tmp_path)}
    path = tmp_path / "runner.yaml"
    path.write_text("kind: dask\nworkers: 4\nadapt: {minimum: 1, maximum: 4}\n")
    assert load_task_runner_config(path).adapt == {"minimum": 1, "maximum": 4}
    with pytest.raises(ConfigError, match=r"unknown task runner preset 'cluster'.*available: \['dask', "
                                          r"'dask-cuda', 'local', 'slurm'\]"):
        load_task_runner_config("cluster")
    with pytest.raises(ConfigError, match=r"task_runner: workers and threads_per_worker must be >= 1, got 0"):
        load_task_runner_config({"kind": "local", "workers": 0})
    with pytest.raises(ConfigError, match=r"task_runner.kind: expected one of"):
        load_task_runner_config({"kind": "ray"})
    with pytest.raises(FileNotFoundError, match="missing.yaml does not exist"):
        load_task_runner_config(tmp_path / "missing.yaml")


def test_slurm_preset_makes_a_job_script():
    pytest.importorskip("dask_jobqueue", reason="the slurm extra (dask-jobqueue) is not installed")
    from dask_jobqueue import SLURMCluster

    from flows._runners import load_task_runner_config, make_task_runner

    cfg = load_task_runner_config("slurm")
    runner = make_task_runner(cfg)
    assert runner.cluster_class == "dask_jobqueue.SLURMCluster" and runner.adapt_kwargs == {"minimum": 1,
                                                                                            "maximum": 8}
    cluster = SLURMCluster(**{**runner.cluster_kwargs, "log_directory": None})
    try:
        script = cluster.job_script()
    finally:
        cluster.close()
    for line in ("#SBATCH -p gpu", "#SBATCH --cpus-per-task=8", "#SBATCH -t 24:00:00", "#SBATCH --gres=gpu:1"):
        assert line in script


def test_summary_markdown_lists_failures_skips_and_metrics(tmp_path):
    from bat3r_core.runs import RunLayout
    from flows._artifacts import summary_markdown

    layout = RunLayout(tmp_path, "toy", "r_1")
    render = StageResult("render", (
        {"index": 0, "n_rows": 4, "n_ok": 3, "n_failed": 1, "failed_samples": [["s2", "mask_mismatch", "IoU 0.5"]]},
    ), FailureSummary("render", 2, (ShardFailure("part-00001", "RuntimeError: Blender died"),), 0.5), cached=1,
        recomputed=0)
    train = StageResult("train", ({"steps": 40, "n_samples": 3, "final_loss": 0.25},),
                        FailureSummary("train", 1, (), 0.0), cached=0, recomputed=0)
    md = summary_markdown(layout, 1, [render, train], [
        {"iteration": 1, "split": "test", "n": 8, "n_failed": 0, "mcd_cm": 3.5, "pct_mcd_over_5cm": 12.5,
         "rot_err_deg": float("nan"), "rms_cd_cm": 4.0, "mv_rms_cd_cm": 3.0},
        {"iteration": 0, "split": "test", "n": 8, "n_failed": 0, "mcd_cm": 9.0}])
    assert "# toy / r_1: iteration 1" in md
    assert "**render**: 1 of 2 task(s) done (1 from cache); 3 samples ok, 1 skipped" in md
    assert "- render `part-00001`: RuntimeError: Blender died" in md
    assert "- render `s2`: mask_mismatch (IoU 0.5)" in md
    assert "40 steps on 3 samples, final loss 0.250" in md
    assert "| 1 | test | 8 | 0 | 3.500 | 12.500 | – | 4.000 | 3.000 |" in md
    assert "| 0 | test" not in md
    assert layout.report.resolve().as_uri() in md
    # render dropped 1 of 4 (25 % > 5 %): listed with its reason and table; train (no rows) is not
    assert "## Dropped samples (stages that dropped more than 5 %)" in md
    assert "- render: 1 of 4 renders dropped (25.0 %): mask_mismatch ×1 (IoU 0.5)" in md
    assert "| mask_mismatch | 1 | 25.0 % | IoU 0.5 | `s2` |" in md
    # a stopped iteration says why; the run data's drops come first
    from bat3r_core.runs import DropReason, SampleDrops

    data = SampleDrops("collection", "collection", "images", 10, 9,
                       (DropReason("bad_image", 1, "image a.png is truncated", "a", "c.parquet"),))
    stopped = summary_markdown(layout, 0, [render], [], data_drops=[data], stopped="iteration 0 render: too few")
    assert stopped.index("**Stopped:** iteration 0 render: too few") < stopped.index("- run data: collection: 1 of "
                                                                                     "10 images dropped (10.0 %)")
    assert "| bad_image | 1 | 10.0 % | image a.png is truncated | `a` | `c.parquet` |" in stopped
    quiet = StageResult("features", ({"index": 0, "n_rows": 40, "n_ok": 39, "n_failed": 1},),
                        FailureSummary("features", 1, (), 0.1), cached=0, recomputed=0)
    assert "Dropped samples" not in summary_markdown(layout, 0, [quiet], [])  # 2.5 %: below the threshold
    assert artifact_key("Toy", "r_1.x", "iter-01") == "toy-r-1-x-iter-01"


def test_generated_collections_resolve_what_they_are_rendered_from(tmp_path, monkeypatch):
    import yaml

    from bat3r_core.rig_io import save_rig_glb
    from bat3r_core.toy import build_toy_rig
    from flows._settings import resolve_run

    monkeypatch.setenv("BAT3R_STORAGE_ROOT", str(tmp_path / "runs"))
    data = yaml.safe_load((ROOT / "data_catalog.yaml").read_text())
    save_rig_glb(build_toy_rig(), tmp_path / "beast.glb")
    data["categories"]["beast"] = {
        "asset": "beast.glb", "body_frame": data["categories"]["toy"]["body_frame"],
        "collection": {"kind": "generated", "path": "gen/train", "seed": 3},
        "test_split": {"kind": "generated", "path": "gen/test", "pose_sampler": "toy_natural"},
        "fitting": {"preset": "synthetic"}}
    path = tmp_path / "catalog.yaml"
    path.write_text(yaml.safe_dump(data))
    s = resolve_run("beast", "tiny", "r1", catalog=str(path))  # the catalog given by its file
    assert s.collection["pose_sampler"] == "random" and s.test_split["pose_sampler"] == "toy_natural"
    assert s.collection["asset"] == s.assets.asset and s.collection["textures"] == [] == list(s.assets.textures)
    assert s.collection["body_frame"] == s.body_frame and s.collection["prefix"] == "beast"
    assert s.collection["path"] == str(tmp_path / "gen" / "train" / "n16-r32")
    assert (s.catalog_file, s.source_asset) == (str(path), str(tmp_path / "beast.glb"))
    assert s.hint_context() == {"category": "beast", "asset": str(tmp_path / "beast.glb"), "catalog": str(path)}
    toy = resolve_run("toy", "tiny", "r1", catalog=str(path))
    assert toy.collection["pose_sampler"] == "toy_natural" and "asset" not in toy.collection  # built in-process
    data["categories"]["beast"]["collection"] = {"kind": "folder", "path": "photos", "pose_sampler": "random"}
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=r"categories\.beast\.collection\.pose_sampler: only a generated "
                                          r"collection samples poses \(kind is 'folder'\)"):
        load_catalog(path)


def test_the_local_runner_asks_running_tasks_to_stop_only_when_its_flow_is_stopped():
    from prefect.exceptions import TerminationSignal

    from bat3r_core.stopping import clear_stop_request, stop_requested
    from flows._runners import StoppableThreadPoolTaskRunner, make_task_runner

    runner = make_task_runner("local")
    assert isinstance(runner, StoppableThreadPoolTaskRunner) and isinstance(runner.duplicate(),
                                                                            StoppableThreadPoolTaskRunner)
    try:
        with pytest.raises(ValueError):  # a failed stage: nothing else to stop
            with runner:
                raise ValueError("a stage failed")
        assert not stop_requested()
        for signal_exception in (TerminationSignal(signal=15), KeyboardInterrupt()):
            with pytest.raises(type(signal_exception)):
                with make_task_runner("local"):
                    raise signal_exception
            assert stop_requested()
            with make_task_runner("local"):  # a new flow run in this process withdraws it
                assert not stop_requested()
    finally:
        clear_stop_request()


def test_pose_families_reach_the_generated_collection_and_bad_ones_are_named(tmp_path, monkeypatch):
    import yaml

    from bat3r_core.specs import GeneratedCollectionSpec
    from flows._settings import resolve_run

    monkeypatch.setenv("BAT3R_STORAGE_ROOT", str(tmp_path / "runs"))
    s = resolve_run("toy_wide", "tiny", "r1")  # the shipped catalog's widened toy
    families = {"gallop": 2.0, "rear": 2.0, "lie": 2.0, "trot": 1.0, "graze": 1.0}
    assert s.collection["pose_families"] == families == s.test_split["pose_families"]
    assert "pose_families" not in resolve_run("toy", "tiny", "r1").collection  # the toy keeps its sampler
    spec = GeneratedCollectionSpec(n=4, seed=1, resolution=32, render=s.render, pose_families=families)
    assert spec.collection_options()["pose_families"] == families

    data = yaml.safe_load((ROOT / "data_catalog.yaml").read_text())
    path = tmp_path / "catalog.yaml"
    bad = {"photos": ({"kind": "folder", "path": "photos", "pose_families": {"lie": 1}},
                      r"categories\.toy_wide\.collection\.pose_families: only a generated collection with "
                      r"pose_sampler 'toy_natural' has pose families \(kind 'folder'"),
           "random": ({"kind": "generated", "path": "g", "pose_sampler": "random", "pose_families": {"lie": 1}},
                      r"pose_sampler 'random'\)"),
           "unknown": ({"kind": "generated", "path": "g", "pose_families": {"dance": 1}},
                       r"categories\.toy_wide\.collection\.pose_families: unknown pose families \['dance'\]"),
           "negative": ({"kind": "generated", "path": "g", "pose_families": {"lie": -1, "rear": 2}},
                        r"expected relative frequencies >= 0 with a positive sum"),
           "text": ({"kind": "generated", "path": "g", "pose_families": {"lie": "often"}},
                    r"categories\.toy_wide\.collection\.pose_families\.lie: expected a number")}
    for name, (collection, message) in bad.items():
        data["categories"]["toy_wide"]["collection"] = collection
        path.write_text(yaml.safe_dump(data))
        with pytest.raises(ConfigError, match=message):
            load_catalog(path)
