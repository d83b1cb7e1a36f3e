"""``make bench-fidelity``: does the bootstrap loop beat its same-compute control, and by how much of the oracle's gap?

From one Φ₀ (the canonical initialisation of the ``bench`` preset; ``make bench-fidelity`` runs it on ``toy_wide``),
three arms at equal training compute, each evaluated on the same test split with the loop's own metrics
(``bat3r_core.evaluation``):

* **loop**: the bootstrap flow itself (``flows.bootstrap.bootstrap``), ``iterations`` refinement iterations;
* **control**: Φ₀ trained on for the same number of warm-started rounds of the same schedule on its canonical
  renders only (rest pose) — what the loop must beat;
* **oracle**: the same rounds on the collection's own images labelled with their hidden truth (true pose and
  camera, ray-cast through the collection's crop) — what perfect pseudo-labels would give.

``--ablations`` adds the paper's ablations of the loop, each a bootstrap run starting from the same Φ₀
(``init_predictor``): no fitting regularisation, no view augmentation, no pseudo-label filter. ``--seeds 0 S ...``
repeats the three arms from the same Φ₀ with each extra seed (``seed_arms``) and reports their mean, spread and the
paired loop − control difference (``seed_figures``); with ``--references-only`` it runs no loop and only trains
the control and oracle rounds of each seed (``references_of_seeds``; seed 0's only when the benchmark's own are
missing), the references ``compare_loops.py`` measures a loop variant run at those seeds against;
``evaluation_spread`` scores the loop's last test predictions with five evaluation seeds, the part of any spread
between runs that is the evaluation's own sampling.

Two figures say what limits the headroom when there is little: the **map floors** (``map_floors``: the test mCD of
exact point maps and of exact rest-pose maps at the run's crop resolution, the best any oracle and any control can
score) and the **training fit** (``training_fit``: the oracle's last round and Φ₀ scored on the collection images
the oracle was trained on; an oracle about as far off there as on the test split under-fits). The **map errors**
(``map_error_figures``) say how each predictor's test maps are off: depth against lateral error, even errors against
a few gross ones, images whose depth order is reversed.

Every arm is resumable: the loop and the ablations are flow runs (``runs/<category>/<run name>[-<ablation>]``, cached
stages), the control and oracle rounds keep their checkpoints and metrics under
``runs/<category>/<run name>/fidelity/``.
Results: ``benchmarks/results/<record-as>.json`` (test mCD, % > 5 cm and ΔR per arm and iteration; the headroom
``oracle / control`` and the fraction of the control → oracle gap the loop recovers), ``RESULTS.md`` and a plot
``benchmarks/results/<record-as>.png``.

    python benchmarks/bench_fidelity.py [--preset bench] [--run-name bench] [--ablations] [--seeds 0 1 2]
                                        [--references-only] [--set KEY=VALUE ...]

Measured: 75 min on 2 AMD EPYC cores at the ``bench`` preset on ``toy_wide`` (three iterations) without ablations,
the collection and test split rendered from scratch (48 min for the two-iteration paper-recipe preset of 2 December
on ``toy``); each ablation adds about one loop's time (~30 min), ``--oracle-sizes 1536`` about 14 min.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

if __name__ == "__main__":  # before Prefect is imported: it reads its settings once, at import
    from bat3r_core.cli import local_server_environment

    local_server_environment()

from _results import RESULTS_DIR, record, record_name  # noqa: E402
from bench_demo_control import _oracle_dataset, _test_metrics  # noqa: E402

from bat3r_core import evaluation, evaluation_truth, shards  # noqa: E402
from bat3r_core.cli import add_catalog_argument, parse_overrides  # noqa: E402
from bat3r_core.predictor.data import ShardDataset, hold_on_device  # noqa: E402
from bat3r_core.predictor.features import make_feature_fn  # noqa: E402
from bat3r_core.predictor.train import Trainer  # noqa: E402
from bat3r_core.rig_io import load_rig  # noqa: E402

ABLATIONS = ("no_fitting_regularisation", "no_view_augmentation", "no_pseudo_label_filter")
"""The loop's ablations ``--ablations`` runs (``flows._settings.Ablations`` switches), in the paper's order."""

HEADROOM_GOAL = 0.75
"""The benchmark means something only when the oracle's last mCD is at most this fraction of the control's."""
RECOVERY_GOAL = 0.5
"""The loop's last iteration must recover at least this fraction of the control → oracle gap in test mCD."""
MIN_GAP_CM = 0.25
"""Below the headroom goal, the loop's share of a control → oracle gap narrower than this is not reported as a figure
of merit: one arm moves by up to about this much between training seeds (README, "How far apart two runs must be")."""

UNDERFIT_RATIO = 0.9
"""An oracle whose mCD on its own training images is at least this fraction of its test mCD under-fits them."""

_FIGURES = (("mcd", "mcd_cm", 3), ("pct_over_5cm", "pct_mcd_over_5cm", 1), ("rot_err_deg", "rot_err_deg", 1))


def _row_figures(arm: str, iteration: int, row: dict) -> dict[str, float]:
    out = {}
    for short, column, digits in _FIGURES:
        v = row.get(column)
        if v is not None and v == v:
            out[f"{short}_{arm}_iter{iteration}"] = round(float(v), digits)
    return out


def _test_rows(metrics_rows: list[dict]) -> dict[int, dict]:
    return {int(r["iteration"]): r for r in metrics_rows if r["split"] == "test"}


def _run_loop(category: str, preset: str, run_name: str, overrides: dict, iterations: int, catalog: str | None,
              **extra: Any) -> dict[int, dict]:
    from flows.bootstrap import bootstrap

    result = bootstrap(category=category, preset=preset, run_name=run_name, overrides=overrides,
                       iterations=iterations, catalog=catalog, **extra)
    rows = _test_rows(result["metrics"])
    if not rows:
        raise RuntimeError(f"run {run_name!r}: no test-split metrics (does the test split have ground truth?)")
    return rows


def _round_checkpoint(settings, name: str, iteration: int) -> Path:
    """The checkpoint of round ``iteration`` of reference arm ``name`` (``fidelity/<name>/round-NN``)."""
    return settings.layout.root / "fidelity" / name / f"round-{iteration:02d}" / "train" / "predictor.pt"


def _cached_row(path: Path, compute) -> dict:
    """The JSON row at ``path``, or ``compute()`` written there first: what lets a rerun skip finished work. Rows
    are reused by path only (changed settings need a new run name)."""
    if path.is_file():
        return json.loads(path.read_text())
    row = compute()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(row, default=float))
    return row


def _reference_rounds(settings, name: str, data_fn, iterations: int, run_seed: int,
                      start: Path | None = None) -> dict[int, dict]:
    """Φ₀ (the run's own, or ``start``) trained on ``data_fn(out)`` for ``iterations`` warm-started rounds of the
    run's schedule; the test metrics row of each round (cached in ``round-NN/metrics.json``: a rerun only trains the
    missing rounds)."""
    out = settings.layout.root / "fidelity" / name
    previous = start or settings.layout.stage_dir(0, "train") / "predictor.pt"
    dataset, rows = None, {}

    def train_and_test(it: int, o: Path) -> dict:
        nonlocal dataset
        if dataset is None:
            dataset = hold_on_device(ShardDataset(data_fn(out), make_feature_fn(settings.features),
                                                  cache_shards=settings.train.shuffle_shards),
                                     None, settings.train.mirror_probability)  # once for every round
        checkpoint = Trainer(dataset, settings.model, settings.train, o / "train", init_from=previous,
                             mirror=settings.mirror).train()
        row = _test_metrics(settings, checkpoint, o, it, seed=run_seed + it)  # the loop evaluates i: seed + i
        print(f"{name} round {it}: test mCD {row['mcd_cm']:.2f} cm", flush=True)
        return row

    for it in range(1, iterations + 1):
        o = out / f"round-{it:02d}"
        rows[it] = _cached_row(o / "metrics.json", lambda: train_and_test(it, o))
        previous = _round_checkpoint(settings, name, it)
    return rows


def map_floors(settings) -> dict[str, float]:
    """The test mCD of the two ideal predictors of ``evaluation_truth.map_floor_rows`` on the run's test split, at
    its crop resolution and number of layers (means over the images): ``floor_perfect_map_cm`` (the exact dual point
    map) and ``floor_rest_pose_map_cm`` (the exact map of the rest pose, rigidly aligned), and their ratio
    ``best_headroom``, the headroom a perfect oracle would have over a perfect control. Cached in
    ``fidelity/floors.json``."""
    test = settings.layout.run_stage_dir("test")

    def compute() -> dict:
        gt = evaluation_truth.load_ground_truth(Path(settings.test_split["ground_truth"]) / "ground_truth.npz")
        rows = evaluation_truth.map_floor_rows(shards.read_table(test).to_pylist(), gt,
                                               load_rig(settings.assets.asset), num_layers=settings.model.layers)
        if not rows:
            raise RuntimeError(f"{test}: no test image with ground truth to compute the map floors of")
        perfect = float(np.nanmean([r["perfect_map_cd_cm"] for r in rows]))
        rest = float(np.nanmean([r["rest_pose_map_cd_cm"] for r in rows]))
        return {"floor_perfect_map_cm": round(perfect, 3), "floor_rest_pose_map_cm": round(rest, 3),
                "best_headroom": round(perfect / rest, 3),
                "floor_points_per_image": round(float(np.mean([r["n_points"] for r in rows])), 1)}

    return _cached_row(settings.layout.root / "fidelity" / "floors.json", compute)


def training_fit(settings, predictors: dict[str, Path], iteration: int, run_seed: int) -> dict[str, float]:
    """Does the network fit the images it was trained on? Each of ``predictors`` (name → checkpoint: the oracle's
    last round, Φ₀) scored like the test split on the collection's own images against their hidden truth — the
    oracle's training set: ``mcd_<name>_on_collection``. An oracle that scores about as badly on its training images
    as on the test split under-fits, and no choice of training poses (the loop's, the truth's) can then widen the
    headroom at this compute. Cached in ``fidelity/on_collection/<name>/metrics.json``."""
    figures = {}
    for name, checkpoint in predictors.items():
        out = settings.layout.root / "fidelity" / "on_collection" / name
        row = _cached_row(out / "metrics.json", lambda: _test_metrics(
            settings, checkpoint, out, iteration, seed=run_seed + iteration, split="collection"))
        figures[f"mcd_{name}_on_collection"] = round(float(row["mcd_cm"]), 3)
    return figures


EVAL_SEEDS = 5
"""Evaluation seeds the loop's last test predictions are scored with (``evaluation_spread``)."""


def evaluation_spread(settings, predictions: Path, iteration: int, run_seed: int,
                      n: int = EVAL_SEEDS) -> dict[str, float]:
    """How far the loop's last test mCD moves with the evaluation's own sampling alone (the 2,000 points drawn on
    each true surface, the subsample of predicted points), the predictions fixed: the loop's test predictions of
    ``iteration`` scored with the evaluation seeds ``run_seed + iteration + k``, k = 0..n-1 (k = 0 is the loop's own
    score). ``mcd_loop_eval_seed<k>`` per seed, ``mcd_loop_eval_seeds_sd`` (sample sd) and ``_range`` (cm): the part of
    a cross-seed spread (``--seeds``) that is evaluation, not training. Cached in ``fidelity/eval_seeds/``."""
    import tempfile

    gt = evaluation_truth.load_ground_truth(Path(settings.test_split["ground_truth"]) / "ground_truth.npz")
    rig = load_rig(settings.assets.asset)

    def score(seed: int) -> dict:
        with tempfile.TemporaryDirectory(prefix="bat3r_eval_seed_") as out:
            for i in shards.list_shards(predictions):
                evaluation_truth.evaluate_prediction_shard(predictions, i, gt, rig, settings.body_frame, "test",
                                                           iteration, out, seed=seed)
            return evaluation.aggregate(shards.read_table(out))[0]

    root = settings.layout.root / "fidelity" / "eval_seeds" / f"iter-{iteration:02d}"
    values = [float(_cached_row(root / f"seed-{k}.json", lambda k=k: score(run_seed + iteration + k))["mcd_cm"])
              for k in range(n)]
    out = {f"mcd_loop_eval_seed{k}": round(v, 3) for k, v in enumerate(values)}
    out["mcd_loop_eval_seeds_sd"] = round(float(np.std(values, ddof=1)), 3) if n > 1 else 0.0
    out["mcd_loop_eval_seeds_range"] = round(max(values) - min(values), 3)
    return out


LATERAL_SHIFT_CM = 3.0
"""A mean vertical shift of a predictor's test maps this large (cm) is called out in the verdict."""

MAP_ERROR_FIGURES = ("depth_err_median_cm", "depth_err_rms_cm", "depth_err_tail_share", "depth_reversed_pct",
                     "lateral_err_rms_cm", "lateral_bias_y_cm", "lateral_bias_abs_cm")
"""The figures of ``evaluation_truth.summarise_map_errors`` recorded per predictor (``<figure>_<name>``)."""


def map_error_figures(settings, predictions: dict[str, Path]) -> dict[str, float]:
    """How the test predictions are off, not only how far: each inference folder of ``predictions`` (name → the
    test_infer folder of Φ₀, the control's and the oracle's last round, the loop's last iteration) against the
    exact maps of the test split (``evaluation_truth.prediction_map_errors``), per map entry: median and RMS depth
    error, the share of the squared depth error carried by the worst 10 % of entries, the % of images whose depth
    order is reversed, the lateral RMS error and the mean lateral shift (vertical, and its size). Cached in ``fidelity/map_errors/<name>.json``."""
    from bat3r_core.evaluation_truth import prediction_map_errors, summarise_map_errors

    gt = evaluation_truth.load_ground_truth(Path(settings.test_split["ground_truth"]) / "ground_truth.npz")
    rows = shards.read_table(settings.layout.run_stage_dir("test")).to_pylist()
    rig = load_rig(settings.assets.asset)
    figures = {}
    for name, folder in predictions.items():
        cache = settings.layout.root / "fidelity" / "map_errors" / f"{name}.json"
        if cache.is_file() and not set(MAP_ERROR_FIGURES) <= set(json.loads(cache.read_text())):
            cache.unlink()  # written before a figure was added: recompute
        summary = _cached_row(cache, lambda f=folder: summarise_map_errors(prediction_map_errors(f, rows, gt, rig)))
        figures.update({f"{k}_{name}": round(float(summary[k]), 3) for k in MAP_ERROR_FIGURES})
    return figures


def map_error_line(figures: dict[str, float]) -> str | None:
    """The verdict sentence of :func:`map_error_figures` (None when they were not measured)."""
    if "depth_err_rms_cm_phi0" not in figures:
        return None

    def one(name: str) -> str:
        f = {k: figures[f"{k}_{name}"] for k in ("depth_err_median_cm", "depth_err_rms_cm", "depth_err_tail_share",
                                                   "depth_reversed_pct")}
        return (f"median {f['depth_err_median_cm']:.1f} cm, RMS {f['depth_err_rms_cm']:.1f} cm, the worst 10 % of "
                f"entries carry {f['depth_err_tail_share']:.0%} of the squared error, "
                f"{f['depth_reversed_pct']:.0f} % of images with their depth order reversed")

    line = "per map entry, Φ₀'s relative depth is off by " + one("phi0")
    for name in ("control", "oracle", "loop"):
        if f"depth_err_rms_cm_{name}" in figures:
            line += f"; the {name}'s by " + one(name)
    oracle_tail = figures.get("depth_err_tail_share_oracle")
    if oracle_tail is not None and oracle_tail >= 0.5:
        image = f"a {figures['crop_px']:.0f} px image" if "crop_px" in figures else "the image"
        line += (": gross depth errors on a few entries and images (the animal's depth order misread from "
                 f"{image}) dominate even the oracle's error, and training on true poses does not remove them")
    for name in ("phi0", "control", "oracle", "loop"):
        shift = figures.get(f"lateral_bias_y_cm_{name}")
        if shift is not None and abs(shift) >= LATERAL_SHIFT_CM:
            line += (f"; the {'Φ₀' if name == 'phi0' else name}'s test maps are shifted {abs(shift):.1f} cm "
                     f"{'up' if shift < 0 else 'down'} on average (what training renders whose x, y follow another "
                     "principal point teach, docs/fitting.md)")
    return line


def larger_oracles(sizes: list[int], preset: str, run_name: str, overrides: dict, catalog: str | None, phi0: Path,
                   iterations: int, run_seed: int, category: str = "toy"
                   ) -> tuple[dict[str, dict[int, dict]], dict[str, float]]:
    """The oracle again with ``--oracle-sizes`` collections of N images (same Φ₀, rounds and test split): does the
    headroom grow with the number of distinct posed training images? Each size is a run of its own,
    ``<run name>-oracle-n<N>`` (iteration 0 only evaluates Φ₀; its collection is rendered from the catalog's seed),
    with the oracle rounds under its ``fidelity/oracle``. Returns arms ``oracle_n<N>`` and figures
    ``mcd_oracle_n<N>_iter<i>``, ``mcd_oracle_n<N>_on_collection``."""
    from flows._settings import resolve_run

    arms, figures = {}, {}
    for n in sizes:
        name = f"{run_name}-oracle-n{n}"
        sized = {**overrides, "run.collection_size": n}
        start = _run_loop(category, preset, name, sized, 0, catalog, init_predictor=str(phi0))
        settings = resolve_run(category, preset, name, sized, catalog=catalog)
        rows = _reference_rounds(settings, "oracle", lambda out, s=settings: _oracle_dataset(
            s, load_rig(s.assets.asset), out), iterations, run_seed, start=phi0)
        arms[f"oracle_n{n}"] = {0: start[0], **rows}
        fit = training_fit(settings, {"oracle": _round_checkpoint(settings, "oracle", iterations)}, iterations,
                           run_seed)
        figures[f"mcd_oracle_n{n}_on_collection"] = fit["mcd_oracle_on_collection"]
    return arms, figures


SEED_ARMS = ("loop", "control", "oracle")
"""The arms ``--seeds`` repeats for each extra seed."""


def seed_arms(seeds: list[int], preset: str, run_name: str, overrides: dict, catalog: str | None, phi0: Path,
              iterations: int, category: str = "toy") -> dict[str, dict[int, dict]]:
    """The loop, the control and the oracle again from the same Φ₀ for each seed ``s`` of ``--seeds`` other than 0
    (seed 0 is the benchmark's own arms): the loop is the run ``<run name>-seed<s>`` started from Φ₀ with
    ``--seed s`` and ``train.seed = s`` (other render jobs, data order and mirroring), the control and the oracle are
    that run's ``fidelity/control`` and ``fidelity/oracle`` rounds with ``train.seed = s``, on the same canonical
    renders (Φ₀'s run's) and the same collection. Every test evaluation uses the loop's seeds (``s + i``). Returns
    arms ``<arm>_seed<s>``: how far one arm moves between seeds, which bounds what a single run can tell apart."""
    from flows._settings import resolve_run

    arms: dict[str, dict[int, dict]] = {}
    for s in seeds:
        if s == 0:
            continue
        loop = _run_loop(category, preset, f"{run_name}-seed{s}", {**overrides, "train.seed": s}, iterations, catalog,
                         init_predictor=str(phi0), seed=s)
        arms[f"loop_seed{s}"] = loop
        arms.update(seed_references(s, preset, run_name, overrides, catalog, phi0, iterations, category, loop[0]))
    return arms


def seed_references(seed: int, preset: str, run_name: str, overrides: dict, catalog: str | None, phi0: Path,
                    iterations: int, category: str = "toy", phi0_row: dict | None = None) -> dict[str, dict[int, dict]]:
    """The control and the oracle of seed ``seed`` (arms ``control_seed<s>``, ``oracle_seed<s>``): Φ₀ trained on
    with ``train.seed = s`` and scored with the evaluation seeds ``s + i``, cached under the run
    ``<run name>-seed<s>`` (``fidelity/{control,oracle}/round-NN``). Without ``phi0_row`` (Φ₀'s test row at that
    seed, which the seed's loop gives) that run is prepared by a bootstrap run of 0 iterations from Φ₀ (its
    collection and test split, Φ₀ scored at seed s): the references alone, what ``--references-only`` trains and
    what ``compare_loops.py`` reads for a loop variant run at seed s (``RUN:LABEL@<run name>-seed<s>``)."""
    from flows._settings import resolve_run

    canonical = resolve_run(category, preset, run_name, overrides, catalog=catalog).layout.stage_dir(0, "render")
    name, seeded = f"{run_name}-seed{seed}", {**overrides, "train.seed": seed}
    if phi0_row is None:
        phi0_row = _run_loop(category, preset, name, seeded, 0, catalog, init_predictor=str(phi0), seed=seed)[0]
    settings = resolve_run(category, preset, name, seeded, catalog=catalog)
    return {f"control_seed{seed}": {0: phi0_row, **_reference_rounds(settings, "control", lambda out: canonical,
                                                                    iterations, seed, start=phi0)},
            f"oracle_seed{seed}": {0: phi0_row, **_reference_rounds(
                settings, "oracle", lambda out: _oracle_dataset(settings, load_rig(settings.assets.asset), out),
                iterations, seed, start=phi0)}}


def own_references(settings, iterations: int) -> dict[str, dict[int, dict]] | None:
    """Seed 0's control and oracle as the benchmark itself trained them, under the run (``fidelity/{control,oracle}``),
    when every round up to ``iterations`` is there (arms ``control_seed0``, ``oracle_seed0``, Φ₀'s test row at 0);
    None otherwise (nothing is trained)."""
    root = settings.layout.root / "fidelity"
    if not all((root / arm / f"round-{i:02d}" / "metrics.json").is_file()
               for arm in SEED_ARMS[1:] for i in range(1, iterations + 1)):
        return None
    phi0_row = _test_rows(evaluation.read_metrics(settings.layout.root).to_pylist()).get(0)
    if phi0_row is None:
        return None
    return {f"{arm}_seed0": {0: phi0_row, **_reference_rounds(settings, arm, None, iterations, 0)}
            for arm in SEED_ARMS[1:]}  # every round is cached: nothing trains, data_fn is never called


def references_of_seeds(seeds: list[int], preset: str, run_name: str, overrides: dict, catalog: str | None,
                        phi0: Path, iterations: int, category: str = "toy") -> tuple[dict[str, dict[int, dict]],
                                                                                    dict[int, str]]:
    """What ``--references-only`` trains: the control and the oracle of every seed of ``seeds`` (arms
    ``control_seed<s>``, ``oracle_seed<s>``) and, per seed, the run that holds them, the ``@REFERENCE_RUN`` of
    ``compare_loops.py --runs``. Seed ``s`` > 0: ``seed_references`` under ``<run name>-seed<s>``. Seed 0: the
    benchmark's own rounds under the run when it trained all of them, else ``seed_references(0, …)`` under
    ``<run name>-seed0``: same Φ₀, seed, canonical renders and collection, so the same figures, under a name of
    their own that a partly trained or deleted ``fidelity/`` of the run cannot mix with."""
    from flows._settings import resolve_run

    references: dict[str, dict[int, dict]] = {}
    holders: dict[int, str] = {}
    for s in seeds:
        own = None
        if s == 0:
            own = own_references(resolve_run(category, preset, run_name, overrides, catalog=catalog), iterations)
        references.update(own or seed_references(s, preset, run_name, overrides, catalog, phi0, iterations,
                                                 category))
        holders[s] = run_name if own else f"{run_name}-seed{s}"
    return references, holders


def seed_figures(seeds: list[int], arms: dict[str, dict[int, dict]], iterations: int) -> dict[str, float]:
    """Over the seeds (seed 0: the arms ``loop``, ``control``, ``oracle``; others ``<arm>_seed<s>``), the last
    iteration's test mCD of each arm: ``mcd_<arm>_seeds_mean`` and ``_sd`` (sample standard deviation), the paired
    ``loop_minus_control_seeds_mean`` / ``_sd``, ``loop_ahead_of_control_seeds`` (seeds where the loop's mCD is below
    the control's), ``headroom_seeds_mean`` (mean oracle / mean control) and ``loop_gap_recovered_seeds_mean``;
    empty with fewer than two seeds."""
    if len(seeds) < 2:
        return {}
    last = {arm: np.array([float(arms[arm if s == 0 else f"{arm}_seed{s}"][iterations]["mcd_cm"]) for s in seeds])
            for arm in SEED_ARMS}
    out: dict[str, float] = {"seeds": len(seeds)}
    for arm, values in last.items():
        out[f"mcd_{arm}_seeds_mean"] = round(float(values.mean()), 3)
        out[f"mcd_{arm}_seeds_sd"] = round(float(values.std(ddof=1)), 3)
    diff = last["loop"] - last["control"]
    out["loop_minus_control_seeds_mean"] = round(float(diff.mean()), 3)
    out["loop_minus_control_seeds_sd"] = round(float(diff.std(ddof=1)), 3)
    out["loop_ahead_of_control_seeds"] = int((diff < 0).sum())
    control, oracle, loop = (float(last[a].mean()) for a in ("control", "oracle", "loop"))
    out["headroom_seeds_mean"] = round(oracle / control, 3)
    recovered = gap_recovered(control, oracle, loop)
    if recovered == recovered:
        out["loop_gap_recovered_seeds_mean"] = round(recovered, 3)
    return out


def seed_line(figures: dict[str, float]) -> str | None:
    """The verdict over ``--seeds`` (``seed_figures``), or None without it."""
    if "seeds" not in figures:
        return None
    n, f = int(figures["seeds"]), figures
    arms = ", ".join(f"{a} {f[f'mcd_{a}_seeds_mean']:.2f} ± {f[f'mcd_{a}_seeds_sd']:.2f}" for a in SEED_ARMS)
    diff, sd = f["loop_minus_control_seeds_mean"], f["loop_minus_control_seeds_sd"]
    line = (f"over {n} seeds from the same Φ₀ (mean ± sd of the last iteration's test mCD, cm): {arms}; the loop is "
            f"{abs(diff):.2f} cm {'ahead of' if diff < 0 else 'behind'} the control on average (paired sd {sd:.2f}; "
            f"ahead in {int(f['loop_ahead_of_control_seeds'])} of {n} seeds), headroom of the means "
            f"{f['headroom_seeds_mean']:.3f}")
    control, oracle = f["mcd_control_seeds_mean"], f["mcd_oracle_seeds_mean"]
    if "loop_gap_recovered_seeds_mean" not in f or not _gap_meaningful(control, oracle):
        return line
    line += f", share of the gap recovered {f['loop_gap_recovered_seeds_mean']:.0%}"
    return line if f["headroom_seeds_mean"] <= HEADROOM_GOAL else line + f" (of a gap of {control - oracle:.2f} cm)"


def _gap_meaningful(control: float, oracle: float) -> bool:
    """Whether the loop's share of a control → oracle gap is a figure of merit: with the headroom goal met, or over
    a gap of at least ``MIN_GAP_CM`` (about one arm's seed spread)."""
    return oracle / control <= HEADROOM_GOAL or control - oracle >= MIN_GAP_CM


def gap_recovered(control: float, oracle: float, loop: float) -> float:
    """The fraction of the control → oracle gap in mCD the loop closes (1: as good as the oracle; 0: no better
    than the control; negative: worse). NaN when the oracle is no better than the control (no gap to close)."""
    gap = control - oracle
    return float("nan") if gap <= 0 else (control - loop) / gap


def ablation_ordering(full: float, no_aug: float | None, no_reg: float | None) -> str:
    """Whether the paper's ordering full < no view augmentation < no regularisation holds for these mCDs."""
    if no_aug is None or no_reg is None:
        return "not measured (run with --ablations)"
    pairs = (("the full loop", full, "no view augmentation", no_aug),
             ("no view augmentation", no_aug, "no fitting regularisation", no_reg),
             ("the full loop", full, "no fitting regularisation", no_reg))
    reversed_ = [f"{a} ({x:.2f}) is not ahead of {b} ({y:.2f})" for a, x, b, y in pairs if not x < y]
    return (f"{'does not hold' if reversed_ else 'holds'}: full {full:.2f} cm, no view augmentation {no_aug:.2f} cm, "
            f"no fitting regularisation {no_reg:.2f} cm" + (" (" + "; ".join(reversed_) + ")" if reversed_ else ""))


def verdict_lines(figures: dict[str, float]) -> list[str]:
    """The benchmark's verdicts from its recorded figures (``fidelity.json``): headroom, the loop's share of the
    control → oracle gap (reported with headroom, or without it when the gap is at least ``MIN_GAP_CM``), and the
    paper's ablation ordering where measured."""
    n = int(figures["iterations"])
    loop, control, oracle = (figures[f"mcd_{a}_iter{n}"] for a in ("loop", "control", "oracle"))
    headroom = oracle / control
    lines = [f"headroom oracle/control {headroom:.3f} (goal <= {HEADROOM_GOAL}: "
             f"{'met' if headroom <= HEADROOM_GOAL else 'NOT met'}; oracle {oracle:.2f} cm, control {control:.2f} cm)"]
    recovered = gap_recovered(control, oracle, loop)
    if _gap_meaningful(control, oracle):
        lines.append(f"the loop ({loop:.2f} cm) recovers {recovered:.0%} of the control -> oracle gap (goal >= "
                     f"{RECOVERY_GOAL:.0%}: {'met' if recovered >= RECOVERY_GOAL else 'NOT met'})"
                     + ("" if headroom <= HEADROOM_GOAL else
                        f", of a gap of {control - oracle:.2f} cm, narrower than the headroom goal asks for: the loop "
                        "closes that share of what perfect pseudo-labels give at this scale, which is not yet the "
                        "paper's gain"))
    else:
        lines.append(f"the loop's share of the control -> oracle gap is not meaningful without headroom (gap "
                     f"{control - oracle:.2f} cm); the loop ({loop:.2f} cm) is "
                     + (f"{loop - control:.2f} cm behind" if loop >= control else f"{control - loop:.2f} cm ahead of")
                     + " the control: recovery goal NOT met")
    if "floor_perfect_map_cm" in figures:
        lines.append(f"at this crop resolution exact point maps score {figures['floor_perfect_map_cm']:.2f} cm and "
                     f"exact rest-pose maps {figures['floor_rest_pose_map_cm']:.2f} cm: a perfect oracle over a "
                     f"perfect control would have a headroom of {figures['best_headroom']:.3f}")
    if "mcd_oracle_on_collection" in figures:
        train, test = figures["mcd_oracle_on_collection"], oracle
        start = figures.get("mcd_phi0_on_collection")
        lines.append(f"on the collection images it was trained on (true labels) the oracle scores {train:.2f} cm "
                     + (f"(Φ₀: {start:.2f}) " if start is not None else "") + f"against {test:.2f} on the test "
                     "split: " + ("it fits its training images better than unseen ones"
                                  if train < UNDERFIT_RATIO * test else
                                  "it under-fits even its training images, so the network's capacity to learn at "
                                  "this compute, not the poses it is shown, sets the test error"))
    errors = map_error_line(figures)
    if errors:
        lines.append(errors)
    for key in sorted(k for k in figures if k.startswith("mcd_oracle_n") and k.endswith(f"_iter{n}")):
        size = key[len("mcd_oracle_n"):-len(f"_iter{n}")]
        lines.append(f"with {size} collection images the oracle reaches {figures[key]:.2f} cm (headroom "
                     f"{figures[key] / control:.3f}"
                     + (f"; {figures[f'mcd_oracle_n{size}_on_collection']:.2f} cm on its training images"
                        if f"mcd_oracle_n{size}_on_collection" in figures else "") + ")")
    seeds = seed_line(figures)
    if seeds:
        lines.append(seeds)
    if "mcd_loop_eval_seeds_sd" in figures:
        k = sum(1 for key in figures if key.startswith("mcd_loop_eval_seed") and key[-1].isdigit())
        lines.append(f"scored with {k} evaluation seeds, the loop's own test predictions move by sd "
                     f"{figures['mcd_loop_eval_seeds_sd']:.3f} cm (range {figures['mcd_loop_eval_seeds_range']:.3f}): "
                     "that much of any spread between runs is the evaluation's sampling, the rest is training")
    lines.append("paper's ablation ordering " + ablation_ordering(
        loop, figures.get(f"mcd_no_view_augmentation_iter{n}"), figures.get(f"mcd_no_fitting_regularisation_iter{n}")))
    return lines


def plot(path: Path, arms: dict[str, dict[int, dict]], floors: dict[str, float] | None = None) -> None:
    """Test mCD per iteration of each arm (one line per arm), with the map floors (``map_floors``) as dashed lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    for name, rows in arms.items():
        its = sorted(rows)
        ax.plot(its, [rows[i]["mcd_cm"] for i in its], marker="o", label=name)
    for key, label in (("floor_rest_pose_map_cm", "exact rest-pose maps"), ("floor_perfect_map_cm", "exact maps")):
        if floors and key in floors:
            ax.axhline(floors[key], ls="--", lw=1, color="grey")
            ax.annotate(label, (ax.get_xlim()[0], floors[key]), fontsize=8, color="grey", va="bottom")
    ax.set_xlabel("iteration (rounds of equal training compute)")
    ax.set_ylabel("test mCD (cm)")
    ax.set_xticks(sorted({i for rows in arms.values() for i in rows}))
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="bench", help="run preset (default: bench)")
    p.add_argument("--category", default="toy",
                   help="a category whose collection and test split are generated with hidden truth (default: toy; "
                        "toy_wide: the toy in poses further from the rest pose)")
    p.add_argument("--run-name", default=None, help="run folder under runs/<category> (default: the preset name)")
    p.add_argument("--iterations", type=int, default=None, help="refinement iterations (default: the preset's)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a setting of every arm, e.g. --set train.steps=100 (repeatable)")
    p.add_argument("--ablations", nargs="*", default=None, choices=ABLATIONS, metavar="ABLATION",
                   help="also run the loop's ablations from the same Φ₀ (no names: all of " + ", ".join(ABLATIONS)
                        + ")")
    p.add_argument("--oracle-sizes", nargs="+", type=int, default=[], metavar="N",
                   help="also train the oracle on generated collections of N images each (does the headroom grow "
                        "with the number of distinct posed images?)")
    p.add_argument("--seeds", nargs="+", type=int, default=[0], metavar="S",
                   help="repeat the loop, the control and the oracle from the same Φ₀ with these seeds (0: the "
                        "benchmark's own arms) and report each arm's mean and spread (~25 min per extra seed and "
                        "iteration on 2 cores)")
    p.add_argument("--references-only", action="store_true",
                   help="only train and cache the control and oracle rounds of every seed of --seeds (seed s under "
                        "<run name>-seed<s>, from the finished run's Φ₀; seed 0: the benchmark's own rounds when all "
                        "are there, else under <run name>-seed0), run no loop and record nothing: the seed-matched "
                        "references compare_loops.py reads for loop variants run at those seeds")
    p.add_argument("--record-as", type=record_name, default="fidelity", help="name of results/<name>.json and .png")
    p.add_argument("--results-dir", type=Path, default=RESULTS_DIR,
                   help="folder of the json and plot (default: benchmarks/results, which also refreshes RESULTS.md)")
    add_catalog_argument(p)
    args = p.parse_args(argv)
    from flows._settings import resolve_run

    run_name = args.run_name or args.preset
    overrides = parse_overrides(args.overrides, p)
    catalog = None if args.catalog is None else str(Path(args.catalog).resolve())
    from bat3r_core.catalog import load_catalog

    spec = load_catalog(catalog).category(args.category)
    if spec.collection.kind != "generated" or spec.test_split is None or spec.test_split.kind != "generated":
        p.error(f"--category {args.category}: the benchmark needs a generated collection (the oracle's true labels) "
                "and a generated test split (hidden ground truth)")
    settings = resolve_run(args.category, args.preset, run_name, overrides, catalog=catalog)
    iterations = settings.iterations if args.iterations is None else args.iterations
    if iterations < 1:
        p.error("--iterations must be >= 1: the arms differ only after iteration 0")
    if any(s < 0 for s in args.seeds) or len(set(args.seeds)) != len(args.seeds) or 0 not in args.seeds:
        p.error(f"--seeds: expected distinct seeds >= 0 including 0 (the benchmark's own arms), got {args.seeds}")
    if any(n < 1 for n in args.oracle_sizes):
        p.error("--oracle-sizes: expected collection sizes >= 1")

    phi0 = settings.layout.stage_dir(0, "train") / "predictor.pt"
    if args.references_only:
        if not phi0.is_file():
            p.error(f"--references-only: {phi0} does not exist (run the benchmark, or the bootstrap flow for run "
                    f"{run_name!r}, first)")
        references, holders = references_of_seeds(args.seeds, args.preset, run_name, overrides, catalog, phi0,
                                                  iterations, args.category)
        for arm, rows in references.items():
            print(f"{arm}: test mCD " + ", ".join(f"{rows[i]['mcd_cm']:.2f}" for i in sorted(rows))
                  + f" cm (iterations 0..{iterations})")
        for s, holder in holders.items():
            print(f"seed {s}: compare a loop variant run at seed {s} with compare_loops.py --runs "
                  f"RUN:LABEL@{holder}")
        return references
    loop = _run_loop(args.category, args.preset, run_name, overrides, iterations, catalog)
    run_seed = 0  # bootstrap's default seed: the loop evaluates iteration i with seed + i
    control = {0: loop[0], **_reference_rounds(settings, "control", lambda out: settings.layout.stage_dir(0, "render"),
                                               iterations, run_seed)}
    oracle = {0: loop[0], **_reference_rounds(
        settings, "oracle", lambda out: _oracle_dataset(settings, load_rig(settings.assets.asset), out),
        iterations, run_seed)}
    arms = {"loop": loop, "control": control, "oracle": oracle}
    ablations = [] if args.ablations is None else (args.ablations or list(ABLATIONS))
    for name in ablations:
        arms[name] = _run_loop(args.category, args.preset, f"{run_name}-{name}", overrides, iterations, catalog,
                               init_predictor=str(phi0), **{name: True})

    sized_arms, sized_figures = larger_oracles(args.oracle_sizes, args.preset, run_name, overrides, catalog, phi0,
                                               iterations, run_seed, args.category)
    arms.update(sized_arms)
    arms.update(seed_arms(args.seeds, args.preset, run_name, overrides, catalog, phi0, iterations, args.category))

    figures: dict[str, float] = {"iterations": iterations}
    for arm, rows in arms.items():
        for it in sorted(rows):
            figures.update(_row_figures(arm, it, rows[it]))
    last = {arm: float(rows[iterations]["mcd_cm"]) for arm, rows in arms.items()}
    recovered = gap_recovered(last["control"], last["oracle"], last["loop"])
    figures.update({"headroom_oracle_over_control": round(last["oracle"] / last["control"], 3),
                    "loop_over_control": round(last["loop"] / last["control"], 3)})
    if recovered == recovered:  # NaN (no gap to recover) is left out
        figures["loop_gap_recovered"] = round(recovered, 3)
    figures.update(map_floors(settings))
    figures.update(training_fit(settings, {"oracle": _round_checkpoint(settings, "oracle", iterations), "phi0": phi0},
                                iterations, run_seed))
    figures.update(sized_figures)
    figures.update(seed_figures(args.seeds, arms, iterations))
    figures.update(evaluation_spread(settings, settings.layout.stage_dir(iterations, "test_infer"), iterations,
                                     run_seed))
    root = settings.layout.root / "fidelity"
    figures["crop_px"] = settings.model.resolution
    figures.update(map_error_figures(settings, {
        "phi0": settings.layout.stage_dir(0, "test_infer"),
        "control": root / "control" / f"round-{iterations:02d}" / "test_infer",
        "oracle": root / "oracle" / f"round-{iterations:02d}" / "test_infer",
        "loop": settings.layout.stage_dir(iterations, "test_infer")}))
    verdicts = verdict_lines(figures)
    for line in verdicts:
        print(line, flush=True)
    notes = (f"{args.category}, {args.preset} preset, run {run_name!r} (overrides {overrides}), {os.cpu_count()} CPU cores: from "
             f"one Φ₀, {iterations} iterations of the loop next to {iterations} warm-started rounds of "
             f"{settings.train.steps} steps on the canonical renders (control) and on the collection's images with "
             f"their true labels (oracle)" + ("; ablations from the same Φ₀: " + ", ".join(ablations)
                                             if ablations else "") + ". " + "; ".join(verdicts) + ".")
    record(args.record_as, figures, notes=notes, results_dir=args.results_dir)
    plot(args.results_dir / f"{args.record_as}.png", arms, figures)
    return figures


if __name__ == "__main__":
    main()
