"""The stage table (``bat3r_core.stages``) against the tasks, the flow, the run layout and the manifest: a stage
without a task, a task naming a stage the table lacks, or a flow step outside the table fails here."""
from __future__ import annotations

import ast
import importlib
import pkgutil
from pathlib import Path

import pytest
from prefect import Task

import tasks
from bat3r_core import runs, stages
from bat3r_core.stages import STAGES

ROOT = Path(__file__).resolve().parents[1]


def _all_tasks() -> dict[str, Task]:
    """Every Prefect task object defined in a module of the ``tasks`` package, by ``module:attribute``."""
    found = {}
    for info in pkgutil.iter_modules(tasks.__path__):
        mod = importlib.import_module(f"tasks.{info.name}")
        for attr, obj in vars(mod).items():
            if isinstance(obj, Task) and obj.fn.__module__ == mod.__name__:
                found[f"tasks.{info.name}:{attr}"] = obj
    return found


@pytest.mark.parametrize("entry", STAGES, ids=lambda s: s.name)
def test_every_stage_has_its_task_and_function(entry):
    task = stages.resolve(entry.task)
    assert isinstance(task, Task), f"{entry.name}: {entry.task} is not a Prefect task"
    assert task.name == entry.own_task, f"{entry.name}: {entry.task} is the task of {task.name!r}"
    assert callable(stages.resolve(entry.function)), entry.function
    assert entry.module.startswith("bat3r_core.")
    assert all(i.removeprefix("previous:") in {s.name for s in STAGES} for i in entry.inputs), entry.inputs
    if entry.task_stage is not None:  # a stage reusing another's task runs that stage's code
        assert stages.stage(entry.task_stage).task == entry.task
    assert task.cache_key_fn is not None, f"{entry.name}: its task is not cached"


def test_every_task_names_a_stage_of_the_table():
    found = _all_tasks()
    assert len(found) >= 15
    listed = {s.task for s in STAGES}
    for ref, task in found.items():
        assert ref in listed, f"{ref} (task {task.name!r}) is not in bat3r_core.stages.STAGES"
        assert task.name in {s.name for s in STAGES}
    with pytest.raises(KeyError, match="unknown stage 'plann'.*'plan_views'"):
        from tasks._cache import stage_task

        stage_task("plann", inputs=list, output=str)
    with pytest.raises(ValueError, match="runs the task of stage 'infer'"):
        stage_task("test_infer", inputs=list, output=str)


def _flow_stage_names(path: Path) -> set[str]:
    """The stage constants a flow module passes to ``_Iteration.run`` / ``run_stage``."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", None)) in (
                "run", "run_stage") and node.args:
            arg = node.args[0]
            if isinstance(arg, ast.Name) and arg.id.isupper():
                names.add(getattr(stages, arg.id))
            elif isinstance(arg, ast.Constant):
                names.add(arg.value)
    return names


def test_the_flow_runs_only_stages_of_the_table_and_every_stage_is_run_somewhere():
    ran = set()
    for path in (ROOT / "flows").glob("*.py"):
        ran |= _flow_stage_names(path)
    table = {s.name for s in STAGES}
    split_steps = {"split"}  # flows/toy_collection.py: run_stage(split, ...) for "collection" and "test"
    assert ran - split_steps <= table, ran - table
    # metrics and report run through flows/evaluate.py's calls of their tasks, collection/test through `split`
    assert table - ran <= {"collection", "test", "metrics", "report"}


def test_layout_manifest_and_reader_names_come_from_the_table(tmp_path):
    assert runs.ITERATION_STAGES == ("plan", "infer", "fit", "evaluate", "filter", "render", "features", "train",
                                     "test_infer")
    assert runs.RUN_STAGES == ("collection", "test")
    assert runs.STAGE_NOUNS["plan_views"] == "render jobs" and runs.STAGE_NOUNS["fit"] == "fits"
    modules = stages.stage_modules()
    assert set(modules) == {s.name for s in STAGES} and modules["fit"] == "bat3r_core.fitting.io"
    layout = runs.RunLayout(tmp_path, "toy", "r").create()
    manifest = runs.write_manifest(layout, {}, modules)
    assert set(manifest["stage_code_versions"]) == set(modules)
    assert stages.output_dir(layout.root, stages.COLLECTION_INFER, 2) == layout.stage_dir(2, "evaluate") / \
        "collection_infer"
    assert stages.output_dir(layout.root, stages.METRICS) == layout.root
    assert stages.output_dir(layout.root, stages.TEST, 3) == layout.run_stage_dir("test")
    with pytest.raises(ValueError, match="stage 'fit' writes inside an iteration"):
        stages.output_dir(layout.root, stages.FIT)
    from bat3r_core import evaluation, evaluation_masks, report

    assert (report.FIT_STAGE, evaluation.EVALUATE_STAGE) == ("fit", "evaluate")
    assert (evaluation_masks.COLLECTION_INFER_DIR, evaluation_masks.COLLECTION_ROWS_DIR) == \
        ("collection_infer", "collection")


def test_stage_code_versions_follow_the_table_module():
    from tasks._cache import stage_cache_key
    from tasks.fit import _inputs, fit_shard

    from bat3r_core.config_utils import to_mapping
    from bat3r_core.fitting.config import FittingConfig
    from bat3r_core.specs import CropCamera, FitSpec

    spec = FitSpec(fitting=FittingConfig(), camera=CropCamera(fov_deg=50.0, resolution=32))
    params = {"asset": "a.glb", "predictions_dir": "/nonexistent", "index": 0, "out_dir": "/tmp/x", "config": spec}
    key = fit_shard.cache_key_fn(None, params)
    version = runs.stage_code_version(stages.stage("fit").module)
    assert key == stage_cache_key("fit", version, _inputs(params), spec, Path("/tmp/x/part-00000"))
    assert key != stage_cache_key("fit", runs.stage_code_version("bat3r_core.shards"), _inputs(params), spec,
                                  Path("/tmp/x/part-00000"))
    # the spec and its mapping form (a deployment's parameter) share one key; a changed setting does not
    assert fit_shard.cache_key_fn(None, {**params, "config": to_mapping(spec)}) == key
    changed = FitSpec(fitting=FittingConfig(), camera=CropCamera(fov_deg=51.0, resolution=32))
    assert fit_shard.cache_key_fn(None, {**params, "config": changed}) != key
