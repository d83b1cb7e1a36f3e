"""``bootstrap`` flow: the run's data, the canonical initialisation (iteration 0), then one refinement subflow per
iteration, with metrics, report and dashboard artifacts after each.

Reads like the data flow of ``DESIGN.md``::

    collection + test split ── toy_collection ─▶ <run>/collection, <run>/test shards (generated ones rendered first)
    iteration 0 (camera sampling around the rest-pose mesh instead of infer/fit/plan):
    rest-pose rig           ── plan ───────────▶ iter-00/plan      render jobs (canonical, or random poses)
    iteration i >= 1 (predictor Φ_{i-1}):
    collection              ── infer(Φ_{i-1}) ─▶ iter-ii/infer     predicted dual point maps and clouds
    predictions + rig       ── fit ────────────▶ iter-ii/fit       θ, global similarity, camera, losses, status
    fits + predictions      ── filter ─────────▶ iter-ii/filter    kept flag, status, reason, quality per fit
    kept fits               ── plan views ─────▶ iter-ii/plan      render jobs (estimated + augmented views)
    every iteration:
    render jobs + rig       ── render ─────────▶ iter-ii/render    training shards (RGB, mask, P/Q/occupancy)
    training shards         ── features ───────▶ iter-ii/features  feature shards
    training shards         ── train ──────────▶ iter-ii/train     Φ_i (predictor.pt); with train.canonical_replay
                                                                  also on a share of iter-00/render per epoch
    test split              ── infer(Φ_i) ─────▶ iter-ii/test_infer
    test predictions + GT   ── evaluate ───────▶ iter-ii/evaluate, metrics.parquet, report.html, artifacts

Every task is cached (inputs + stage config + stage code version + output location): rerunning with the same run
name after a crash recomputes only what is missing. A stage that drops more than ``runs.DROP_WARN_FRACTION`` of
its samples says so (log warning, ``…-drops`` artifact, iteration summary); one that leaves fewer samples than the
next stage needs stops the run before that stage (``runs.TooFewSamples``). Local run:
``python flows/bootstrap.py --category toy --preset tiny [--catalog PATH]`` (or ``bat3r bootstrap``, same options).
"""
from __future__ import annotations

import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a script or loaded by path (deployments): make the project root importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

if __name__ == "__main__":  # a local run's temporary Prefect server: no telemetry, time to migrate its database
    from bat3r_core.cli import local_server_environment

    local_server_environment()

import dataclasses
from typing import Any, Mapping, Sequence

from prefect import flow
from prefect.artifacts import create_markdown_artifact
from prefect.logging import get_run_logger

from bat3r_core import shards, stages
from bat3r_core.stages import (COLLECTION, COLLECTION_INFER, EVALUATE, EVALUATE_COLLECTION, FEATURES, FILTER,
                               FILTER_CHECK, FIT, INFER, PLAN, PLAN_VIEWS, PSEUDO_LABELS, RAW_IMAGES, RENDER, TEST,
                               TEST_INFER, TRAIN)
from bat3r_core.catalog import default_catalog_path
from bat3r_core.cli import add_bootstrap_arguments, bootstrap_parameters
from bat3r_core.runs import (SampleDrops, SampleNeed, TooFewSamples, TooManyFailedShards, prune_shards,
                             pseudo_label_filter_notes, require_samples, training_need, write_manifest)
from flows._artifacts import publish_iteration_artifacts
from flows._fanout import StageResult, artifact_key, run_stage
from flows._runners import make_task_runner
from flows._settings import Ablations, RunSettings, StageSpecs, resolve_run, stage_specs
from flows.evaluate import evaluate
from flows.toy_collection import prepare_split
from tasks._cache import for_run

__all__ = ["bootstrap", "canonical_initialisation", "refinement_iteration", "run_bootstrap", "build_parser", "main"]

def _ablations(**switches: bool) -> Ablations:
    return Ablations(**switches)


def _progress(settings: RunSettings, iteration: int, stage: str) -> str:
    return artifact_key(settings.layout.category, settings.layout.run_name, f"iter-{iteration:02d}", stage)


class _Iteration:
    """The stages of one iteration as they run: each stage's fan-out (``run_stage``, which reports dropped samples)
    and, where the next stage needs a number of samples, the check that stops the iteration before that stage
    starts (``bat3r_core.runs.require_samples``). A stage that stops the iteration (too many failed shards, too few
    samples) still gets the iteration's summary artifact published, with the stages that ran and the error."""

    def __init__(self, settings: RunSettings, iteration: int, data_drops: Sequence[SampleDrops] = ()) -> None:
        self.settings, self.iteration, self.data_drops = settings, iteration, tuple(data_drops)
        self.stages: list[StageResult] = []
        self.notes: list[str] = []

    def dir(self, stage: str) -> str:
        """Where ``stage`` (a name of ``bat3r_core.stages.STAGES``) writes in this run and iteration."""
        return str(stages.output_dir(self.settings.layout.root, stage, self.iteration))

    def ran(self, stage: str) -> bool:
        return any(r.stage == stage for r in self.stages)

    def run(self, stage: str, calls: list[dict[str, Any]], *, max_failed_fraction: float,
            needs: SampleNeed | None = None) -> StageResult:
        """Fan ``calls`` out over the task the stage table names for ``stage``."""
        settings = self.settings
        stage_task = stages.resolve(stages.stage(stage).task)
        try:
            result = run_stage(stage, for_run(stage_task, settings.layout), calls,
                               progress_key=_progress(settings, self.iteration, stage),
                               max_failed_fraction=max_failed_fraction, label=f"iteration {self.iteration} {stage}")
            self.stages.append(result)
            if needs is not None:
                require_samples(result.drops, needs, [r.drops for r in self.stages[:-1]], **settings.hint_context())
        except (TooManyFailedShards, TooFewSamples) as exc:
            get_run_logger().error("%s", exc)
            publish_iteration_artifacts(settings.layout, self.iteration, self.stages, [], data_drops=self.data_drops,
                                        stopped=str(exc))
            raise
        return result


def _data_drops(mappings: Sequence[Mapping[str, Any]] | None) -> list[SampleDrops]:
    return [SampleDrops.from_mapping(m) for m in mappings or ()]


@flow(name="canonical-initialisation", flow_run_name="{category}-{run_name}-iter-00")
def canonical_initialisation(category: str, preset: str, run_name: str, overrides: dict[str, Any],
                             ablations: dict[str, bool], seed: int, max_failed_fraction: float,
                             catalog: str | None = None, data_drops: list[dict] | None = None,
                             init_predictor: str | None = None) -> dict[str, Any]:
    """Iteration 0: sample render jobs around the rest-pose mesh, render them, extract features, train Φ_0.
    catalog: the data catalog file (default: ``$BAT3R_CATALOG`` / ``./data_catalog.yaml``). data_drops: the run
    data's ``SampleDrops`` mappings (collection, test split), listed in this iteration's summary.
    init_predictor: a trained Φ_0 checkpoint to start from instead (iteration 0 then only evaluates it; with the
        ``random_poses`` ablation it trains that checkpoint on for ``train.steps`` on renders of random poses, the
        random-poses baseline as an arm of equal training compute next to a loop from the same Φ_0).
    Returns ``{"stages": {stage: [records]}, "states": {stage: [state names]}, "predictor": path, "metrics": rows}``."""
    settings = resolve_run(category, preset, run_name, overrides, ablations, catalog=catalog,
                           max_failed_fraction=max_failed_fraction)
    cfg = stage_specs(settings, seed)
    it = _Iteration(settings, 0, _data_drops(data_drops))
    replay = settings.train.canonical_replay > 0
    if init_predictor is not None and settings.ablations.random_poses:
        # the random-poses baseline as an arm from a given Φ_0: its weights trained on for train.steps on renders of
        # random poses (as the loop's iterations and the control are trained on from the same Φ_0)
        get_run_logger().info("iteration 0: Φ_0 from %s, trained on renders of random poses", init_predictor)
        it.notes.append(f"random-poses baseline started from {init_predictor} (init_predictor; train.warm_start = "
                        f"{settings.train.warm_start}).")
        _render_canonical(it, cfg)  # the plan of this run's ablations: random-pose jobs
        return _train_and_evaluate(it, cfg, str(init_predictor))
    if init_predictor is not None:
        get_run_logger().info("iteration 0: Φ_0 from %s (no training%s)", init_predictor,
                              "; canonical renders for train.canonical_replay" if replay else ", no canonical renders")
        it.notes.append(f"Φ_0 is {init_predictor} (init_predictor): not trained in this run.")
        if replay:  # the canonical renders the refinement iterations replay (the same plan and seed as Φ_0's run)
            _extract_features(it, cfg, _render_canonical(it, cfg))
        _evaluate_test(it, cfg, str(init_predictor))
        return _finish_iteration(it, str(init_predictor))
    _render_canonical(it, cfg)
    return _train_and_evaluate(it, cfg, None)


def _render_canonical(it: _Iteration, cfg: StageSpecs) -> StageResult:
    """Iteration 0's render jobs around the rest-pose mesh, rendered: the canonical training shards."""
    settings = it.settings
    plan = it.run(PLAN, [{"asset": settings.assets.asset, "out_dir": it.dir(PLAN), "config": cfg.plan}],
                  max_failed_fraction=0.0, needs=training_need(settings.train.batch_size))
    job_files = plan.records[0]["files"]
    for stage in (PLAN, RENDER, FEATURES):  # shards of an earlier, larger plan of this run
        prune_shards(it.dir(stage), range(len(job_files)))
    return _render(it, cfg, list(enumerate(job_files)))


def _evaluate_collection(it: _Iteration, cfg: StageSpecs, predictor: str) -> None:
    """Φ_iteration on the collection, without 3D ground truth (``bat3r_core.evaluation_masks``): its predictions
    (``iter-ii/evaluate/collection_infer``), then mask IoUs of them and of this iteration's fits (none at 0)."""
    mff, collection_dir = it.settings.max_failed_fraction, it.dir(COLLECTION)
    if not shards.list_shards(collection_dir):
        return
    infer = it.run(COLLECTION_INFER, [{"predictor": predictor, "collection_dir": collection_dir, "index": i,
                                       "out_dir": it.dir(COLLECTION_INFER), "config": cfg.infer}
                                      for i in shards.list_shards(collection_dir)], max_failed_fraction=mff)
    fit_dir = it.dir(FIT) if it.iteration > 0 else None
    it.run(EVALUATE_COLLECTION,
           [{"predictions_dir": it.dir(COLLECTION_INFER), "index": r["index"], "collection_dir": collection_dir,
             "fit_dir": fit_dir, "out_dir": it.dir(EVALUATE_COLLECTION),
             "config": cfg.collection_evaluation_at(it.iteration)} for r in infer.records],
           max_failed_fraction=mff)


def _evaluate_test(it: _Iteration, cfg: StageSpecs, predictor: str) -> None:
    """Φ_iteration on the collection (mask IoUs, :func:`_evaluate_collection`) and on the test split: inference
    shards, then per-sample evaluation rows (needs ground truth)."""
    _evaluate_collection(it, cfg, predictor)
    mff, test_dir = it.settings.max_failed_fraction, it.dir(TEST)
    if cfg.evaluate is None or not shards.list_shards(test_dir):
        return
    infer = it.run(TEST_INFER, [{"predictor": predictor, "collection_dir": test_dir, "index": i,
                                 "out_dir": it.dir(TEST_INFER), "config": cfg.infer}
                                for i in shards.list_shards(test_dir)], max_failed_fraction=mff)
    it.run(EVALUATE, [{"predictions_dir": it.dir(TEST_INFER), "index": r["index"], "out_dir": it.dir(EVALUATE),
                       "config": cfg.evaluate_at(it.iteration)} for r in infer.records],
           max_failed_fraction=mff)


def _finish_iteration(it: _Iteration, predictor: str) -> dict[str, Any]:
    """metrics.parquet, report.html and the iteration's dashboard artifacts; the subflow's result."""
    layout, stages = it.settings.layout, it.stages
    metrics = evaluate(layout.category, layout.run_name, storage_root=str(layout.storage_root))
    notes = list(it.notes) + ([] if it.ran(EVALUATE) else
                              ["The test split has no ground truth: no per-sample evaluation."])
    publish_iteration_artifacts(layout, it.iteration, stages, metrics["rows"], notes=notes, data_drops=it.data_drops)
    return {"stages": {r.stage: list(r.records) for r in stages},
            "states": {r.stage: list(r.states) for r in stages},
            "drops": {r.stage: r.drops.to_mapping() for r in stages},
            "predictor": predictor, "metrics": metrics["rows"]}


@flow(name="refinement-iteration", flow_run_name="{category}-{run_name}-iter-{iteration:02d}")
def refinement_iteration(category: str, preset: str, run_name: str, iteration: int, predictor: str,
                         overrides: dict[str, Any], ablations: dict[str, bool], seed: int,
                         max_failed_fraction: float, catalog: str | None = None) -> dict[str, Any]:
    """Iteration i >= 1: Φ_{i-1} predicts the collection, the rig is fitted to every prediction, the fitted poses are
    rendered from their estimated and augmented viewpoints, and Φ_i is trained on those renders alone (earlier
    iterations' data are discarded, as in the paper). Returns like :func:`canonical_initialisation`."""
    settings = resolve_run(category, preset, run_name, overrides, ablations, catalog=catalog,
                           max_failed_fraction=max_failed_fraction)
    cfg, mff = stage_specs(settings, seed + iteration), settings.max_failed_fraction
    it = _Iteration(settings, iteration)
    need = training_need(settings.train.batch_size)
    infer = it.run(INFER, [{"predictor": predictor, "collection_dir": it.dir(COLLECTION), "index": i,
                            "out_dir": it.dir(INFER), "config": cfg.infer}
                           for i in shards.list_shards(it.dir(COLLECTION))],
                   max_failed_fraction=mff, needs=SampleNeed(1, "fitting", "one prediction to fit the rig to"))
    fit = it.run(FIT, [{"asset": settings.assets.asset, "predictions_dir": it.dir(INFER), "index": r["index"],
                        "out_dir": it.dir(FIT), "config": cfg.fit} for r in infer.records],
                 max_failed_fraction=mff, needs=SampleNeed(1, "view planning", "one fitted pose to render"))
    if cfg.pseudo_label_truth is not None:  # pseudo-label quality against the collection's hidden truth (toy)
        it.run(PSEUDO_LABELS, [{"fit_dir": it.dir(FIT), "out_dir": it.dir(PSEUDO_LABELS),
                                "config": cfg.pseudo_label_truth}],
               max_failed_fraction=1.0)
    filter_dir = None if settings.ablations.no_pseudo_label_filter or settings.ablations.raw_images else \
        _filter_fits(it, cfg)
    if settings.ablations.raw_images:  # the raw-image baseline: train on the photos with fitted pseudo-labels
        it.run(RAW_IMAGES, [{"asset": settings.assets.asset, "fit_dir": it.dir(FIT), "index": r["index"],
                             "collection_dir": it.dir(COLLECTION), "out_dir": it.dir(RAW_IMAGES),
                             "config": cfg.raw_images} for r in fit.records],
               max_failed_fraction=mff, needs=need)
        return _train_and_evaluate(it, cfg, predictor)
    plan = it.run(PLAN_VIEWS, [{"asset": settings.assets.asset, "fit_dir": it.dir(FIT), "index": r["index"],
                                "out_dir": it.dir(PLAN_VIEWS), "config": cfg.plan_views, "filter_dir": filter_dir}
                               for r in fit.records], max_failed_fraction=mff, needs=need)
    job_files = [(r["index"], r["files"][0]) for r in plan.records if r["n_jobs"] > 0]
    for stage in (RENDER, FEATURES):  # shards of an earlier plan of this run that this plan does not have
        prune_shards(it.dir(stage), [i for i, _ in job_files])
    _render(it, cfg, job_files)
    return _train_and_evaluate(it, cfg, predictor)


def _render(it: _Iteration, cfg: StageSpecs, job_files: Sequence[tuple[int, str]]) -> StageResult:
    """Blender renders of the planned jobs ``(shard index, jobs file)``: the iteration's training shards."""
    return it.run(RENDER, [{"jobs_file": f, "index": i, "out_dir": it.dir(RENDER), "config": cfg.render}
                           for i, f in job_files],
                  max_failed_fraction=it.settings.max_failed_fraction,
                  needs=training_need(it.settings.train.batch_size))


def _filter_fits(it: _Iteration, cfg: StageSpecs) -> str:
    """The pseudo-label filter over the iteration's fits (``tasks.filter``); with the collection's hidden truth,
    its precision against it. Adds the kept fraction (and the precision) to the iteration's notes; returns the
    filter folder plan views reads."""
    settings, iteration = it.settings, it.iteration
    result = it.run(FILTER, [{"asset": settings.assets.asset, "fit_dir": it.dir(FIT), "predictions_dir": it.dir(INFER),
                              "out_dir": it.dir(FILTER), "config": cfg.filter, "collection_dir": it.dir(COLLECTION)}],
                    max_failed_fraction=0.0, needs=SampleNeed(1, "view planning", "one kept fit to render"))
    errors = Path(it.dir(PSEUDO_LABELS)) / "pseudo_labels.parquet"
    check_record = None
    if it.ran(PSEUDO_LABELS) and errors.is_file():
        check = it.run(FILTER_CHECK, [{"fit_dir": it.dir(FIT), "filter_dir": it.dir(FILTER), "errors_file": str(errors),
                                       "out_dir": it.dir(FILTER_CHECK),
                                       "config": cfg.pseudo_label_truth}],
                       max_failed_fraction=1.0)
        check_record = check.records[0] if check.records else None
    lines = pseudo_label_filter_notes(result.records[0], check_record)
    it.notes += lines
    create_markdown_artifact(markdown="\n".join(f"- {line}" for line in lines),
                             key=_progress(settings, iteration, "pseudo-label-filter"),
                             description=f"iteration {iteration}: pseudo-label filter")
    return it.dir(FILTER)


def _extract_features(it: _Iteration, cfg: StageSpecs, training: StageResult) -> StageResult:
    """Feature shards of the iteration's training shards (``training``: the render or raw-image stage)."""
    return it.run(FEATURES, [{"input_dir": it.dir(RENDER), "index": r["index"], "out_dir": it.dir(FEATURES),
                              "config": cfg.features} for r in training.records],
                  max_failed_fraction=it.settings.max_failed_fraction)


def _train_and_evaluate(it: _Iteration, cfg: StageSpecs, previous: str | None) -> dict[str, Any]:
    """The tail every iteration shares: features of the iteration's training shards → train Φ_iteration (from
    Φ_{iteration-1}'s weights ``previous`` when ``train.warm_start``; from scratch at iteration 0) → evaluate it
    on the collection (masks) and the test split."""
    settings = it.settings
    _extract_features(it, cfg, it.stages[-1])  # render (or raw_images): the training shards
    init_from = previous if previous is not None and settings.train.warm_start else None
    replay = {}
    if it.iteration > 0 and settings.train.canonical_replay > 0:  # iteration 0's canonical renders, mixed in
        canonical = _Iteration(settings, 0)
        replay = {"replay_dir": canonical.dir(RENDER), "replay_features_dir": canonical.dir(FEATURES)}
        if not shards.list_shards(replay["replay_dir"]):
            raise FileNotFoundError(f"train.canonical_replay = {settings.train.canonical_replay}: no canonical "
                                    f"renders in {replay['replay_dir']} (iteration 0 of this run renders them; "
                                    "rerun the run from iteration 0)")
    train = it.run(TRAIN, [{"shards_dir": it.dir(RENDER), "features_dir": it.dir(FEATURES), "out_dir": it.dir(TRAIN),
                            "config": cfg.train_from(init_from), **replay}], max_failed_fraction=0.0)
    record = train.records[0]
    if replay:
        it.notes.append(f"canonical replay: {record['n_replayed']} of iteration 0's canonical renders per epoch next "
                        f"to {record['n_samples'] - record['n_replayed']} pseudo-label renders "
                        f"(train.canonical_replay = {settings.train.canonical_replay}).")
    predictor = record["predictor"]
    _evaluate_test(it, cfg, predictor)
    return _finish_iteration(it, predictor)


def _bootstrap_run_name() -> str:
    from prefect.runtime import flow_run

    p = flow_run.parameters
    return f"{p.get('category', 'toy')}-{p.get('run_name') or p.get('preset', 'tiny')}"


@flow(name="bootstrap", flow_run_name=_bootstrap_run_name)
def bootstrap(category: str = "toy", preset: str = "tiny", iterations: int | None = None,
              run_name: str | None = None, overrides: dict[str, Any] | None = None,
              gaussian_cameras: bool = False, no_fitting_regularisation: bool = False,
              no_view_augmentation: bool = False, random_poses: bool = False, raw_images: bool = False,
              no_pseudo_label_filter: bool = False,
              task_runner: str = "local", max_failed_fraction: float = 0.1, seed: int = 0,
              catalog: str | None = None, init_predictor: str | None = None) -> dict[str, Any]:
    """The bootstrap loop of ``category`` at run preset ``preset`` (``tiny``, ``demo``, ``paper``).

    Args:
        iterations: bootstrap iterations after the canonical initialisation (default: the preset's).
        run_name: the run folder ``<storage root>/<category>/<run name>`` (default: the preset name). Rerunning
            with the same name reuses every completed task.
        overrides: dotted settings, e.g. ``{"train.steps": 100, "run.canonical_samples": 64}``
            (``flows._settings``).
        gaussian_cameras ... no_pseudo_label_filter: the ablation switches (``flows._settings.Ablations``);
            ``no_pseudo_label_filter`` plans views for every ok fit instead of the filter's kept fits.
        task_runner: a preset of ``deploy/task_runners.yaml`` (``local``, ``dask``, ``dask-cuda``, ``slurm``) or
            the path of a YAML file with one runner config.
        max_failed_fraction: a stage continues while at most this fraction of its shards failed after retries.
        seed: seed of the sampled render jobs.
        catalog: the data catalog file (default: ``$BAT3R_CATALOG``, else ``./data_catalog.yaml`` of the process
            running the flow — a deployment's worker). The resolved absolute path is what every subflow reads and
            what ``manifest.json`` records (``config.parameters.catalog``).
        init_predictor: start the loop from this trained Φ_0 checkpoint (e.g. another run's
            ``iter-00/train/predictor.pt``) instead of training one: iteration 0 only evaluates it. Ablations of
            one Φ_0 (``benchmarks/bench_fidelity.py``) share it this way. With ``random_poses`` (iterations 0)
            iteration 0 trains it on for ``train.steps`` on renders of random poses: the random-poses baseline as
            an arm of equal training compute.

    A stage that drops more than ``bat3r_core.runs.DROP_WARN_FRACTION`` of its samples is reported (log warning,
    ``…-drops`` artifact, iteration summary); a stage that leaves fewer samples than the next one needs stops the
    run with ``bat3r_core.runs.TooFewSamples`` before that stage starts.

    Returns ``{"run_dir", "iterations": [result of each iteration], "metrics": rows}``.
    """
    logger = get_run_logger()
    run_name = run_name or preset
    catalog_file = str(Path(catalog).expanduser().resolve() if catalog else default_catalog_path().resolve())
    switches = dict(gaussian_cameras=gaussian_cameras, no_fitting_regularisation=no_fitting_regularisation,
                    no_view_augmentation=no_view_augmentation, random_poses=random_poses, raw_images=raw_images,
                    no_pseudo_label_filter=no_pseudo_label_filter)
    overrides = dict(overrides or {})
    settings = resolve_run(category, preset, run_name, overrides, _ablations(**switches), catalog=catalog_file,
                           max_failed_fraction=max_failed_fraction)
    n_iter = settings.iterations if iterations is None else int(iterations)
    if n_iter < 0:
        raise ValueError(f"iterations must be >= 0, got {n_iter}")
    if random_poses and n_iter > 0:
        raise ValueError("random_poses is a baseline trained once on random poses: run it with iterations=0")
    layout = settings.layout.create()
    if init_predictor is not None:
        init_predictor = str(Path(init_predictor).expanduser().resolve())
        if not Path(init_predictor).is_file():
            raise FileNotFoundError(f"init_predictor: {init_predictor} is not a file (expected a predictor "
                                    "checkpoint, e.g. runs/<category>/<run>/iter-00/train/predictor.pt)")
    write_manifest(layout, {**settings.to_mapping(), "parameters": {
        "iterations": n_iter, "task_runner": task_runner, "seed": seed, "overrides": overrides,
        "catalog": catalog_file, "init_predictor": init_predictor}}, stages.stage_modules())
    logger.info("run folder %s (catalog %s)", layout.root, catalog_file)

    runner = make_task_runner(task_runner)
    data_drops = []
    needs = {"collection": SampleNeed(1, "inference of iteration 1", "one collection image to predict")
             if n_iter > 0 else None,
             "test": SampleNeed(1, "evaluation", "one test image") if (settings.test_split or {}).get("ground_truth")
             else None}
    for split, spec in (("collection", settings.collection), ("test", settings.test_split)):
        if spec is not None:
            data_drops += [r.drops.to_mapping() for r in prepare_split(settings, split, spec, needs=needs[split])]
    ablation_dict = dataclasses.asdict(settings.ablations)
    results = [canonical_initialisation.with_options(task_runner=runner)(
        category, preset, run_name, overrides, ablation_dict, seed, settings.max_failed_fraction, catalog_file,
        data_drops, init_predictor)]
    for iteration in range(1, n_iter + 1):
        logger.info("iteration %d of %d", iteration, n_iter)
        results.append(refinement_iteration.with_options(task_runner=runner)(
            category, preset, run_name, iteration, results[-1]["predictor"], overrides, ablation_dict, seed,
            settings.max_failed_fraction, catalog_file))
    return {"run_dir": str(layout.root), "iterations": results, "metrics": results[-1]["metrics"]}


def run_bootstrap(parameters: Mapping[str, Any]) -> int:
    """Run the flow with ``parameters`` (``bat3r_core.cli.bootstrap_parameters``) and print the run folder and the
    metrics rows; a run stopped by too few samples or too many failed shards prints why (stderr) and returns 1.
    What ``python flows/bootstrap.py`` and ``bat3r bootstrap`` do. The catalog, category and preset are checked
    before Prefect starts: a wrong one prints the error and returns 2."""
    from bat3r_core.catalog import ConfigError, load_catalog

    try:
        catalog = load_catalog(parameters.get("catalog"))
        catalog.category(parameters.get("category", "toy"))
        catalog.run_preset(parameters.get("preset", "tiny"))
    except (ConfigError, FileNotFoundError, KeyError) as exc:
        print(f"bootstrap: {exc.args[0] if isinstance(exc, KeyError) else exc}", file=sys.stderr)
        return 2
    try:
        result = bootstrap(**parameters)
    except (TooFewSamples, TooManyFailedShards) as exc:
        print(f"bootstrap stopped: {exc}", file=sys.stderr)
        return 1
    print(f"run folder: {result['run_dir']}")
    for row in result["metrics"]:
        print(row)
    return 0


def build_parser():
    """The command line of ``python flows/bootstrap.py``: ``bat3r_core.cli.add_bootstrap_arguments`` (the options
    of ``bat3r bootstrap`` too)."""
    import argparse

    parser = argparse.ArgumentParser(description="Run the bat3r bootstrap flow locally.")
    add_bootstrap_arguments(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    return run_bootstrap(bootstrap_parameters(parser.parse_args(argv), parser))


if __name__ == "__main__":
    sys.exit(main())
