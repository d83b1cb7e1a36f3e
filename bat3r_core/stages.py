"""The pipeline's one stage table: every stage of a bootstrap run, the ``bat3r_core`` function it runs, the
Prefect task that runs it, the stages whose outputs it reads and the folder it writes. No Prefect.

Everything that names stages is derived from :data:`STAGES`:

* the code version in each stage's cache key (``tasks._cache.stage_task`` looks the stage's module up here);
* ``manifest.json``'s ``stage_code_versions`` (:func:`stage_modules`);
* the run layout's stage folders (``bat3r_core.runs.ITERATION_STAGES`` / ``RUN_STAGES``, :func:`output_dir`);
* the stage names the report and the evaluation read (:data:`FIT`, :data:`EVALUATE`, ...);
* the flow's steps (``flows.bootstrap`` runs ``stage_task_of(name)`` for a table name).

``tests/test_stages.py`` fails when a stage of the table has no task, when a task names a stage that is not in
the table, or when a stage's function is not where the table says. Several stages may run the same task on other
folders (``test_infer`` and ``collection_infer`` run ``infer``'s task): the task's own name is then the stage
whose code it caches (``task_stage``).

The data flow, in the order of the table::

    generated_collection ─▶ collection, test          (run level)
    iteration 0:  plan ─▶ render ─▶ features ─▶ train ─▶ collection_infer ─▶ evaluate_collection
                                                     └─▶ test_infer ─▶ evaluate ─▶ metrics, report
    iteration i:  infer(Φ_{i-1}) ─▶ fit ─▶ pseudo_labels, filter ─▶ filter_check ─▶ plan_views ─▶ render ...
                  (raw_images replaces plan_views ─▶ render in the raw-image baseline)
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Mapping

__all__ = ["Stage", "STAGES", "stage", "stage_modules", "iteration_folders", "run_folders", "output_dir",
           "resolve", "COLLECTION", "TEST", "PLAN", "PLAN_VIEWS", "INFER", "FIT", "PSEUDO_LABELS", "FILTER",
           "FILTER_CHECK", "RAW_IMAGES", "RENDER", "FEATURES", "TRAIN", "COLLECTION_INFER", "EVALUATE_COLLECTION",
           "TEST_INFER", "EVALUATE", "METRICS", "REPORT", "GENERATED_COLLECTION"]

Scope = Literal["external", "run", "iteration"]


@dataclass(frozen=True)
class Stage:
    """One stage of a run.

    Attributes:
        name: the stage's name: its Prefect task name (or, for a stage reusing another's task, the name of its
            step in the flow and its progress artifact), its manifest key.
        function: ``"module:function"`` of the ``bat3r_core`` code it runs; the module's code version keys the
            cache of the stage's task.
        task: ``"module:attribute"`` of the Prefect task that runs it (``tasks/*.py``).
        inputs: the stages whose outputs it reads (``previous:train`` is the previous iteration's).
        folder: where it writes: relative to the iteration folder (``scope="iteration"``, e.g. ``fit`` or
            ``evaluate/collection_infer``), to the run folder (``scope="run"``, ``"."`` for the run folder
            itself), or a folder the catalog names (``scope="external"``: a generated collection's images).
        scope: ``external``, ``run`` or ``iteration``.
        task_stage: the stage whose task it runs, when that is another stage's (default: itself).
        noun: what its samples are called where drops are reported (``bat3r_core.runs.summarize_drops``).
    """

    name: str
    function: str
    task: str
    inputs: tuple[str, ...]
    folder: str
    scope: Scope = "iteration"
    task_stage: str | None = None
    noun: str = "samples"

    @property
    def module(self) -> str:
        """The ``bat3r_core`` module of :attr:`function`."""
        return self.function.partition(":")[0]

    @property
    def own_task(self) -> str:
        """The stage whose Prefect task this stage runs (its cache key's stage name)."""
        return self.task_stage or self.name


STAGES: tuple[Stage, ...] = (
    # name                  bat3r_core function                                  task (tasks/*.py)
    #                       inputs                                               folder, ...
    Stage("generated_collection", "bat3r_core.generated_collections:ensure_collection", "tasks.render:render_generated_collection",
          (), "", scope="external", noun="renders"),
    Stage("collection", "bat3r_core.predictor.collection:write_collection_shard",
          "tasks.predict:ingest_collection_shard",
          ("generated_collection",), "collection", scope="run", noun="images"),
    Stage("test", "bat3r_core.predictor.collection:write_collection_shard", "tasks.predict:ingest_collection_shard",
          ("generated_collection",), "test", scope="run", task_stage="collection", noun="images"),
    Stage("plan", "bat3r_core.datasets:canonical_jobs", "tasks.plan:plan_sampled_jobs",
          (), "plan", noun="render jobs"),
    Stage("infer", "bat3r_core.predictor.infer:predict_shard", "tasks.predict:infer_shard",
          ("collection", "previous:train"), "infer", noun="predictions"),
    Stage("fit", "bat3r_core.fitting.io:fit_prediction_shard", "tasks.fit:fit_shard",
          ("infer",), "fit", noun="fits"),
    Stage("pseudo_labels", "bat3r_core.evaluation_truth:write_pseudo_label_errors", "tasks.evaluate:pseudo_label_quality",
          ("fit",), "evaluate"),
    Stage("filter", "bat3r_core.pseudo_labels:filter_fits", "tasks.filter:filter_pseudo_labels",
          ("fit", "infer"), "filter", noun="fits"),
    Stage("filter_check", "bat3r_core.pseudo_labels:filter_precision", "tasks.filter:filter_precision_check",
          ("fit", "filter", "pseudo_labels"), "evaluate"),
    Stage("plan_views", "bat3r_core.fitting.augment:plan_views_for_fits", "tasks.plan:plan_views_shard",
          ("fit", "filter"), "plan", noun="render jobs"),
    Stage("raw_images", "bat3r_core.raw_images:raw_image_shard", "tasks.raw_images:raw_image_shard",
          ("fit", "collection"), "render", noun="renders"),
    Stage("render", "bat3r_core.render.runner:render_shard", "tasks.render:render_shard",
          ("plan",), "render", noun="renders"),
    Stage("features", "bat3r_core.predictor.features:extract_feature_shard", "tasks.features:extract_features_shard",
          ("render",), "features", noun="feature rows"),
    Stage("train", "bat3r_core.predictor.train:Trainer", "tasks.train:train_model",
          ("render", "features"), "train"),
    Stage("collection_infer", "bat3r_core.predictor.infer:predict_shard", "tasks.predict:infer_shard",
          ("collection", "train"), "evaluate/collection_infer", task_stage="infer", noun="predictions"),
    Stage("evaluate_collection", "bat3r_core.evaluation_masks:evaluate_collection_shard",
          "tasks.evaluate:evaluate_collection_shard",
          ("collection_infer", "collection", "fit"), "evaluate/collection", noun="evaluation rows"),
    Stage("test_infer", "bat3r_core.predictor.infer:predict_shard", "tasks.predict:infer_shard",
          ("test", "train"), "test_infer", task_stage="infer", noun="predictions"),
    Stage("evaluate", "bat3r_core.evaluation_truth:evaluate_prediction_shard", "tasks.evaluate:evaluate_shard",
          ("test_infer",), "evaluate", noun="evaluation rows"),
    Stage("metrics", "bat3r_core.evaluation:evaluate_run", "tasks.evaluate:update_metrics",
          ("evaluate", "evaluate_collection"), ".", scope="run"),
    Stage("report", "bat3r_core.report:build_report", "tasks.evaluate:build_report",
          ("metrics", "evaluate", "evaluate_collection", "fit", "pseudo_labels"), ".", scope="run"),
)
"""Every stage, in data-flow order."""

_BY_NAME: dict[str, Stage] = {s.name: s for s in STAGES}
if len(_BY_NAME) != len(STAGES):  # pragma: no cover - a table edit that repeats a name
    raise RuntimeError("bat3r_core.stages.STAGES repeats a stage name")

(GENERATED_COLLECTION, COLLECTION, TEST, PLAN, INFER, FIT, PSEUDO_LABELS, FILTER, FILTER_CHECK, PLAN_VIEWS,
 RAW_IMAGES, RENDER, FEATURES, TRAIN, COLLECTION_INFER, EVALUATE_COLLECTION, TEST_INFER, EVALUATE, METRICS,
 REPORT) = (s.name for s in STAGES)


def stage(name: str) -> Stage:
    """The table's stage ``name``; a clear error listing the stages otherwise."""
    try:
        return _BY_NAME[name]
    except KeyError:
        raise KeyError(f"unknown stage {name!r}: the stages of bat3r_core.stages.STAGES are {list(_BY_NAME)}") \
            from None


def stage_modules() -> dict[str, str]:
    """Stage name → its ``bat3r_core`` module (``manifest.json``'s ``stage_code_versions`` keys and values)."""
    return {s.name: s.module for s in STAGES}


def iteration_folders() -> tuple[str, ...]:
    """The top-level folders of ``iter-NN/`` the stages write, in data-flow order of their first writer."""
    return tuple(dict.fromkeys(s.folder.split("/")[0] for s in STAGES if s.scope == "iteration"))


def run_folders() -> tuple[str, ...]:
    """The run-level stage folders (``collection``, ``test``)."""
    return tuple(s.folder for s in STAGES if s.scope == "run" and s.folder != ".")


def output_dir(run_dir: str | Path, name: str, iteration: int | None = None) -> Path:
    """Where stage ``name`` writes in run folder ``run_dir`` (``iteration`` for an iteration's stage)."""
    s = stage(name)
    if s.scope == "external":
        raise ValueError(f"stage {name!r} writes where the catalog says (a generated collection's folder)")
    if s.scope == "run":
        return Path(run_dir) if s.folder == "." else Path(run_dir) / s.folder
    if isinstance(iteration, bool) or not isinstance(iteration, int) or iteration < 0:
        raise ValueError(f"stage {name!r} writes inside an iteration: iteration must be an integer >= 0, "
                         f"got {iteration!r}")
    return Path(run_dir) / f"iter-{iteration:02d}" / s.folder


def resolve(ref: str) -> Any:
    """The object a ``"module:attribute"`` reference of the table names (imports the module)."""
    module, _, attr = ref.partition(":")
    obj: Any = importlib.import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


def describe() -> list[Mapping[str, Any]]:
    """The table as rows (name, function, task, inputs, folder, scope) for docs and ``bat3r stages``."""
    def folder(s: Stage) -> str:
        return {"iteration": f"iter-NN/{s.folder}", "external": "(the catalog's collection folder)"}.get(
            s.scope, s.folder)

    return [{"stage": s.name, "function": s.function, "task": s.task, "inputs": list(s.inputs), "folder": folder(s),
             "scope": s.scope} for s in STAGES]
