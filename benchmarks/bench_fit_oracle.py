"""Which predicted map spoils the fits? Pseudo-label quality with ground-truth maps substituted.

For a finished run of a generated collection (``runs/<category>/<run name>``, default category ``toy``; the
overrides its manifest records apply), takes the predictions on the collection that iteration ``--iteration``
fitted (by default 1: Φ₀'s predictions) and, for every predicted point, the true canonical point Q* and posed
point P* of the same pixel and layer, ray-cast from the hidden ground truth (pose, camera, and the collection's
crop of the image) with ``bat3r_core.pointmaps.dual_point_maps``. It reports

* the per-image RMS error of the predicted Q and of the predicted P (centred, per camera axis; z is depth);
* the pose error of fits (``bat3r_core.evaluation_truth.pseudo_label_errors``: mean vertex error after rigid alignment)
  with the run's fitting configuration on four versions of the same points: as predicted, with P replaced by P*,
  with Q replaced by Q*, with both replaced, next to the rest pose (no fitting at all);
* how far each version's fits articulate the rig (``fit_joint_angle_deg_<version>``, the mean rotation of the
  non-root joints) next to the true poses (``truth_joint_angle_deg``): fits that barely leave the rest pose can beat
  it without showing the poses the photos show. The bone direction error tells them apart
  (``median_fit_bone_err_deg_<version>``, ``pct_bones_better_than_rest_<version>``, against
  ``median_rest_pose_bone_err_deg``; ``bat3r_core.analysis.bone_direction_error_deg``): a near-rest fit's is
  the rest pose's, only a fit that bends the right joints the right way lowers it. It compares bone directions,
  not the joints' rotations, because a rotation about a limb's own axis (twist) barely moves the surface: no
  point map shows it, yet it dominates a per-joint rotation error.

Only points whose pixel and layer are occupied in the truth take part, in every version, so the four fits see
the same points. A fit is only worth rendering when it beats the rest pose; the table says which map has to
improve for that. Results: ``benchmarks/results/<record-as>.json`` and ``RESULTS.md``.

    python benchmarks/bench_fit_oracle.py [--run-name demo] [--iteration 1] [--record-as fit_oracle]
        [--versions predicted ...] [--fitting KEY=VALUE ...] [--error-scales S ...]

``--fitting weight_angle=1e-3`` refits the same points with a changed fitting setting (the run's stay as they
were), ``--versions predicted`` fits only the listed versions: a sweep of the fitting objective on one run's
predictions. Each version's fits also go through the run's pseudo-label filter (``refit_filter_*``: precision,
recall and base rate of the kept set against the truth). ``--error-scales 0.25 0.5`` adds fits of the points with
both maps' errors scaled down (the truth plus that fraction of each point's prediction error): how much better Φ₀
has to predict before its fits beat the rest pose. About 2 minutes per version on 2 CPU cores for the demo's 192 images.
"""
from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _results import record, record_name  # noqa: E402

from bat3r_core import evaluation_truth, shards  # noqa: E402
from bat3r_core.cameras import PinholeCamera  # noqa: E402
from bat3r_core.evaluation_masks import read_masks  # noqa: E402
from bat3r_core.cli import parse_overrides  # noqa: E402
from bat3r_core.config_utils import ConfigError, replace_path  # noqa: E402
from bat3r_core.fitting.fit import FittingAsset, PointCloudInstance, fit_batch  # noqa: E402
from bat3r_core.fitting.io import fit_rows, instances_from_predictions  # noqa: E402
from bat3r_core.pointmaps import dual_point_maps  # noqa: E402
from bat3r_core.poses import mean_joint_angle_deg  # noqa: E402
from bat3r_core.predictor.collection import CropTransform, crop_transform_from_row  # noqa: E402
from bat3r_core.rig_io import load_rig  # noqa: E402
from flows._settings import recorded_run  # noqa: E402

VERSIONS = {"predicted": (False, False), "true_P": (True, False), "true_Q": (False, True), "true_P_and_Q": (True, True)}


@dataclasses.dataclass(frozen=True)
class Truth:
    """Ground truth at an instance's predicted (pixel, layer) entries."""

    occupied: np.ndarray  # (N,) bool: the entry is on the true surface
    P: np.ndarray  # (N, 3) camera frame minus the true object depth (the posed-map convention)
    Q: np.ndarray  # (N, 3) canonical frame


def truth_at_points(inst: PointCloudInstance, gt: dict, rig, resolution: int, crop: CropTransform | None = None
                    ) -> Truth:
    """Ray-cast the true posed mesh of ``inst`` with its true camera and read the maps at its points.

    ``crop``: the collection's crop of the image (the model sees crops; the ground-truth intrinsics are the original
    image's); None when the image is the crop (``resolution`` pixels square).
    """
    crop = crop or CropTransform(0.0, 0.0, float(resolution), resolution)
    camera = evaluation_truth.ground_truth_camera(gt, crop)
    maps = dual_point_maps(gt["posed_vertices"], rig.rest_vertices, rig.faces, camera, 4, "world", nthreads=1)
    u = np.clip(np.floor(inst.pixels[:, 0]).astype(int), 0, resolution - 1)
    v = np.clip(np.floor(inst.pixels[:, 1]).astype(int), 0, resolution - 1)
    layer = np.clip(inst.layers, 0, maps.occupancy.shape[-1] - 1)
    return Truth(maps.occupancy[v, u, layer], maps.P[v, u, layer] - np.array([0.0, 0.0, maps.object_depth]),
                 maps.Q[v, u, layer].astype(np.float64))


def map_errors(inst: PointCloudInstance, truth: Truth) -> dict[str, float]:
    """Per-image RMS errors (cm) of the predicted maps at truly occupied entries; P is compared centred (the fit's
    similarity absorbs a translation), per camera axis."""
    o = truth.occupied
    dq = inst.canonical_points[o] - truth.Q[o]
    dp = inst.posed_points[o] - truth.P[o]
    dp = dp - dp.mean(0)
    rms_p = 100 * np.sqrt((dp ** 2).mean(0))
    return {"occupied_fraction": float(o.mean()), "q_rms_cm": float(100 * np.sqrt((dq ** 2).sum(1).mean())),
            "q_median_cm": float(100 * np.median(np.linalg.norm(dq, axis=1))),
            "p_rms_x_cm": float(rms_p[0]), "p_rms_y_cm": float(rms_p[1]), "p_rms_z_cm": float(rms_p[2])}


def substitute(inst: PointCloudInstance, truth: Truth, true_p: bool, true_q: bool) -> PointCloudInstance:
    """``inst`` restricted to its truly occupied entries, with P and/or Q replaced by the truth (P* moved to the
    predicted centroid so that only its shape differs)."""
    o = truth.occupied
    p, q = inst.posed_points[o], inst.canonical_points[o]
    if true_p:
        p = truth.P[o] - truth.P[o].mean(0) + p.mean(0)
    if true_q:
        q = truth.Q[o]
    keep = (lambda a: None if a is None else a[o])
    return dataclasses.replace(inst, posed_points=p, canonical_points=q, confidence=keep(inst.confidence),
                               pixels=keep(inst.pixels), layers=keep(inst.layers))


def scale_errors(inst: PointCloudInstance, truth: Truth, scale: float) -> PointCloudInstance:
    """``inst`` restricted to its truly occupied entries with both maps' errors scaled by ``scale``: each point is
    ``truth + scale · (prediction − truth)`` (P* moved to the predicted centroid first, as in ``substitute``), so 1
    is the prediction and 0 the truth. The errors keep their structure (bias, smoothness) and only shrink: how much
    better must Φ₀ predict for its fits to beat the rest pose?"""
    if not scale >= 0.0:
        raise ValueError(f"error scale: expected >= 0, got {scale}")
    exact = substitute(inst, truth, true_p=True, true_q=True)
    pred = substitute(inst, truth, true_p=False, true_q=False)
    return dataclasses.replace(
        exact, posed_points=exact.posed_points + scale * (pred.posed_points - exact.posed_points),
        canonical_points=exact.canonical_points + scale * (pred.canonical_points - exact.canonical_points))


def error_scale_version(scale: float) -> str:
    """The figure suffix of the fits at error scale ``scale`` (``errors_x0.25``)."""
    return f"errors_x{scale:g}"


def pose_errors(rows: list[dict], gt: dict, rig) -> tuple[list[dict], list[dict]]:
    """The vertex errors of the ok fits of ``rows`` and of the rest pose for the same fits
    (``evaluation_truth.pseudo_label_errors``, ``pseudo_labels.rest_pose_errors``)."""
    from bat3r_core import pseudo_labels

    ok = [r for r in rows if r["status"] == shards.STATUS_OK]
    return evaluation_truth.pseudo_label_errors(ok, gt, rig), pseudo_labels.rest_pose_errors(ok, gt, rig)


def pose_quality(rows: list[dict], gt: dict, rig, errors: tuple[list[dict], list[dict]] | None = None
                 ) -> dict[str, float]:
    """Mean and median vertex error (cm) of the fitted poses and of the rest pose, and how often the fit beats the
    rest pose; the same for the bone direction error (degrees, ``bone_err_deg``), which a fit that barely leaves
    the rest pose cannot lower much. ``errors``: ``pose_errors(rows, gt, rig)`` when already
    computed."""
    fitted, rest = errors if errors is not None else pose_errors(rows, gt, rig)
    f = np.array([e["vertex_err_cm"] for e in fitted])
    n = np.array([e["vertex_err_cm"] for e in rest])
    fb = np.array([e["bone_err_deg"] for e in fitted])
    nb = np.array([e["bone_err_deg"] for e in rest])
    return {"fitted": len(fitted), "vertex_err_cm": float(f.mean()), "rest_pose_vertex_err_cm": float(n.mean()),
            "median_vertex_err_cm": float(np.median(f)), "median_rest_pose_vertex_err_cm": float(np.median(n)),
            "pct_better_than_rest": float(100 * np.mean(f < n)),
            "median_bone_err_deg": float(np.median(fb)), "median_rest_pose_bone_err_deg": float(np.median(nb)),
            "pct_bones_better_than_rest": float(100 * np.mean(fb < nb))}


def refit_quality(rows: list[dict], instances: list[PointCloudInstance], rig, masks: dict | None = None
                  ) -> list[dict]:
    """The quality columns of these fits (``pseudo_labels.quality_rows``), with the canonical points they were
    fitted to and (``masks``: sample id → crop mask) the masks of the mask columns."""
    from bat3r_core import pseudo_labels

    return pseudo_labels.quality_rows(rows, rig, [inst.canonical_points for inst in instances],
                                      None if masks is None else [masks.get(inst.sample_id) for inst in instances])


def refit_filter_precision(rows: list[dict], instances: list[PointCloudInstance], gt: dict, rig, config,
                           errors: tuple[list[dict], list[dict]] | None = None,
                           quality: list[dict] | None = None) -> dict[str, float | None]:
    """The run's pseudo-label filter (``config``: a ``PseudoLabelFilterConfig``) applied to these fits — their own
    quality columns (``quality``: ``refit_quality`` of them when already computed; else without masks) — scored
    against the truth (``bat3r_core.pseudo_labels.filter_precision``: precision, recall, base rate of the kept
    set). ``errors``: ``pose_errors(rows, gt, rig)`` when already computed."""
    from bat3r_core import pseudo_labels

    fitted, rest = errors if errors is not None else pose_errors(rows, gt, rig)
    quality = quality if quality is not None else refit_quality(rows, instances, rig)
    return pseudo_labels.filter_precision(fitted, rest, pseudo_labels.filter_fits(quality, config))


def _ranking_figures(ranking: dict[str, dict]) -> dict[str, float]:
    """``rank_rho_<column>`` and ``rank_precision_q<q>_<column>`` of a ``pseudo_labels.score_ranking`` result (its
    ``"all"`` entry left out); a ρ is NaN where a column is constant (or absent) over the fits."""
    figures: dict[str, float] = {}
    for column, entry in ranking.items():
        if column == "all":
            continue
        figures[f"rank_rho_{column}"] = round(entry["rho"], 2)
        figures.update({f"rank_precision_q{k.split('@')[1]}_{column}": round(v, 2)
                        for k, v in entry.items() if k.startswith("precision@") and v is not None})
    return figures


def refit_ranking(errors: tuple[list[dict], list[dict]], quality: list[dict]) -> dict[str, float]:
    """How each quality column ranks these fits against the truth (``pseudo_labels.score_ranking`` of their
    ``refit_quality``; ``errors``: their ``pose_errors``): ``rank_rho_<column>`` and ``rank_precision_q0.25_<column>``,
    as ``ranking_figures`` gives them for the run's own fits."""
    from bat3r_core import pseudo_labels

    return _ranking_figures(pseudo_labels.score_ranking(*errors, quality, quantiles=(0.25,)))


def _finite(figures: dict[str, float]) -> dict[str, float]:
    """``figures`` without the NaN ones (a ρ over a constant column): what ``record`` accepts."""
    return {k: v for k, v in figures.items() if math.isfinite(v)}


PRECISION_GOAL = 0.8
"""The pseudo-label filter's kept fits must beat the rest pose this often (``benchmarks/bench_fidelity.py``)."""


def filter_figures(layout, iteration: int) -> dict[str, float]:
    """The run's own pseudo-label filter against the hidden truth at ``iteration`` (``tasks.filter.PRECISION_FILE``,
    written by the flow's ``filter_check`` stage): kept fraction, precision and the base rate (the precision of
    keeping every fit); empty when the run had no filter (``--no-pseudo-label-filter``) or no truth."""
    from tasks.filter import PRECISION_FILE

    path = layout.stage_dir(iteration, "evaluate") / PRECISION_FILE
    if not path.is_file():
        return {}
    data = json.loads(path.read_text())
    return {f"filter_{k}": round(float(data[k]), 3) for k in ("precision", "recall", "base_rate", "n_kept",
                                                               "n_kept_good") if data.get(k) is not None}


def ranking_figures(layout, iteration: int, gt: dict, rig) -> dict[str, float]:
    """Which quality column ranks the run's own fits of ``iteration`` (``pseudo_labels.score_ranking`` of its fit,
    filter and ``pseudo_labels.parquet`` files): ``rank_rho_<column>`` and ``rank_precision_q<q>_<column>`` per
    column, ``rank_base_rate``; empty when the run has no filter shards or no pseudo-label errors."""
    import pyarrow.parquet as pq

    from bat3r_core import pseudo_labels

    filter_dir, errors = layout.stage_dir(iteration, "filter"), layout.stage_dir(iteration, "evaluate") / \
        evaluation_truth.PSEUDO_LABEL_FILE
    if not shards.list_shards(filter_dir) or not errors.is_file():
        return {}
    fits = [r for r in shards.read_table(layout.stage_dir(iteration, "fit")).to_pylist()
            if r["status"] == shards.STATUS_OK and r["sample_id"] in gt]
    ranking = pseudo_labels.score_ranking(pq.read_table(errors).to_pylist(),
                                          pseudo_labels.rest_pose_errors(fits, gt, rig),
                                          shards.read_table(filter_dir).to_pylist())
    return {"rank_base_rate": round(ranking["all"]["base_rate"] or float("nan"), 3), **_ranking_figures(ranking)}


def changed_fitting(config, changes: dict):
    """``config`` (a ``FittingConfig``) with each ``field: value`` of ``changes`` set, values converted to the field's
    type; a ``ConfigError`` naming the key for an unknown field or a value of the wrong type."""
    for key, value in changes.items():
        config = replace_path(config, key, value)
    return config


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--category", default="toy", help="the run's category (default: toy; e.g. toy_wide)")
    p.add_argument("--run-name", default="demo")
    p.add_argument("--iteration", type=int, default=1, help="the iteration whose infer stage is analysed (>= 1)")
    p.add_argument("--record-as", type=record_name, default="fit_oracle", help="name of the results/<name>.json to write")
    p.add_argument("--versions", nargs="+", choices=list(VERSIONS), default=list(VERSIONS),
                   help="which versions of the points to fit (default: all four)")
    p.add_argument("--fitting", action="append", default=[], metavar="KEY=VALUE",
                   help="change a fitting setting (bat3r_core.fitting.FittingConfig field, value parsed as JSON) "
                        "for these fits only, e.g. --fitting weight_angle=1e-3 (repeatable)")
    p.add_argument("--error-scales", nargs="+", type=float, default=[], metavar="S",
                   help="also fit the points with both maps' errors scaled by S (0: the truth, 1: as predicted), "
                        "e.g. --error-scales 0.25 0.5 0.75: how much better Φ₀ must predict")
    p.add_argument("--results-dir", type=Path, default=None,
                   help="write <record-as>.json here instead of benchmarks/results (RESULTS.md is left alone)")
    args = p.parse_args(argv)
    if any(not s >= 0.0 for s in args.error_scales):
        p.error(f"--error-scales: expected values >= 0, got {args.error_scales}")
    if args.iteration < 1:
        raise SystemExit(f"--iteration: expected >= 1 (iteration 0 fits nothing), got {args.iteration}")
    settings, parameters = recorded_run(args.category, args.run_name)
    fitting_changes = parse_overrides(args.fitting, p)
    try:
        fitting = changed_fitting(settings.fitting, fitting_changes)
    except ConfigError as e:
        p.error(f"--fitting: {e}")
    layout = settings.layout
    infer_dir = layout.stage_dir(args.iteration, "infer")
    if not shards.list_shards(infer_dir):
        raise FileNotFoundError(f"{infer_dir}: no inference shards; run iteration {args.iteration} first")
    gt = evaluation_truth.load_ground_truth(Path(settings.collection["ground_truth"]) / "ground_truth.npz")
    rig = load_rig(settings.assets.asset)
    r = settings.image_size
    camera = PinholeCamera.from_fov(settings.camera_prior.fov_deg, r, r)
    crops = {row["sample_id"]: crop_transform_from_row(row)
             for row in shards.read_table(layout.run_stage_dir("collection")).to_pylist() if row["status"] == "ok"}
    masks = read_masks(layout.run_stage_dir("collection"))
    instances = [inst for i in shards.list_shards(infer_dir) for inst in instances_from_predictions(infer_dir, i,
                                                                                                    camera)[0]
                 if len(inst.posed_points) and inst.sample_id in gt and inst.sample_id in crops]
    truths = [truth_at_points(inst, gt[inst.sample_id], rig, r, crops[inst.sample_id]) for inst in instances]
    errors = [map_errors(inst, t) for inst, t in zip(instances, truths)]
    figures: dict[str, float] = {"images": len(instances)}
    for key in errors[0]:
        figures[f"median_{key}"] = round(float(np.median([e[key] for e in errors])), 3)
    figures["truth_joint_angle_deg"] = round(mean_joint_angle_deg([gt[i.sample_id]["excess_rotations"]
                                                                   for i in instances]), 1)
    asset = FittingAsset.prepare(rig, fitting, cache_dir=layout.storage_root / "_cache" / "geodesics")
    versions = [(name, functools.partial(substitute, true_p=VERSIONS[name][0], true_q=VERSIONS[name][1]))
                for name in args.versions]
    versions += [(error_scale_version(s), functools.partial(scale_errors, scale=s)) for s in args.error_scales]
    for name, make in versions:
        fitted = [make(i, t) for i, t in zip(instances, truths)]
        rows = fit_rows(fit_batch(asset, fitted, fitting))
        errors = pose_errors(rows, gt, rig)
        quality = pose_quality(rows, gt, rig, errors)
        refit = refit_quality(rows, fitted, rig, masks)
        if not settings.ablations.no_pseudo_label_filter:  # what the run's filter would keep of these fits
            check = refit_filter_precision(rows, fitted, gt, rig, settings.pseudo_label_filter, errors, refit)
            figures.update({f"refit_filter_{k}_{name}": round(float(check[k]), 3)
                            for k in ("precision", "recall", "base_rate") if check[k] is not None})
        ranked_refit = _finite(refit_ranking(errors, refit))
        figures.update({f"refit_{k}_{name}": v for k, v in ranked_refit.items()})
        figures[f"fit_vertex_err_cm_{name}"] = round(quality["vertex_err_cm"], 2)
        figures[f"pct_better_than_rest_{name}"] = round(quality["pct_better_than_rest"], 1)
        figures[f"median_fit_vertex_err_cm_{name}"] = round(quality["median_vertex_err_cm"], 2)
        ok = [r["excess_rotations"] for r in rows if r["status"] == "ok"]
        if ok:  # how far the fits articulate the rig: near-rest fits can beat the rest pose by barely leaving it
            figures[f"fit_joint_angle_deg_{name}"] = round(mean_joint_angle_deg(ok), 1)
        figures[f"median_fit_bone_err_deg_{name}"] = round(quality["median_bone_err_deg"], 2)
        figures[f"pct_bones_better_than_rest_{name}"] = round(quality["pct_bones_better_than_rest"], 1)
        figures["median_rest_pose_bone_err_deg"] = round(quality["median_rest_pose_bone_err_deg"], 2)
        figures["rest_pose_vertex_err_cm"] = round(quality["rest_pose_vertex_err_cm"], 2)
        figures["median_rest_pose_vertex_err_cm"] = round(quality["median_rest_pose_vertex_err_cm"], 2)
        print(f"{name:>13}: fits {quality['vertex_err_cm']:.2f} cm from the truth (rest pose "
              f"{quality['rest_pose_vertex_err_cm']:.2f} cm), better than the rest pose for "
              f"{quality['pct_better_than_rest']:.0f}% of {quality['fitted']} images; mean joint angle "
              f"{figures.get(f'fit_joint_angle_deg_{name}', float('nan')):.1f}° (truth "
              f"{figures['truth_joint_angle_deg']:.1f}°); bone direction error {quality['median_bone_err_deg']:.1f}° "
              f"(median; rest pose {quality['median_rest_pose_bone_err_deg']:.1f}°, beaten by "
              f"{quality['pct_bones_better_than_rest']:.0f}%)"
              + (f"; the run's filter keeps them with precision {figures[f'refit_filter_precision_{name}']:.2f}"
                 if f"refit_filter_precision_{name}" in figures else ""), flush=True)
        quarters = {k[len("rank_precision_q0.25_"):]: v for k, v in ranked_refit.items()
                    if k.startswith("rank_precision_q0.25_")}
        if quarters:
            print(f"{'':>13}  best quarter by each quality column beats the rest pose for: " + ", ".join(
                f"{c} {v:.0%}" for c, v in sorted(quarters.items(), key=lambda kv: -kv[1])), flush=True)
    print("median per-image errors of the predictions: " + ", ".join(
        f"{k[len('median_'):]} {v}" for k, v in figures.items()
        if k.startswith("median_") and not k.startswith(("median_fit_", "median_rest_"))))
    figures.update(filter_figures(layout, args.iteration))
    ranked = _finite(ranking_figures(layout, args.iteration, gt, rig))
    figures.update(ranked)
    if ranked:
        best = max((k for k in ranked if k.startswith("rank_precision_q0.25_")), key=lambda k: ranked[k])
        print(f"the run's fits ranked by each quality column: best quarter by {best[len('rank_precision_q0.25_'):]} "
              f"beats the rest pose for {ranked[best]:.0%} (base rate {ranked.get('rank_base_rate', float('nan')):.0%}); Spearman rho "
              "with fit-minus-rest error: " + ", ".join(f"{k[len('rank_rho_'):]} {v:+.2f}" for k, v in ranked.items()
                                                      if k.startswith("rank_rho_")))
    verdicts = []
    if "median_fit_vertex_err_cm_predicted" in figures:
        verdicts.append(f"median fit {figures['median_fit_vertex_err_cm_predicted']:.2f} cm vs rest pose "
                        f"{figures['median_rest_pose_vertex_err_cm']:.2f} cm ("
                        + ("below: met" if figures["median_fit_vertex_err_cm_predicted"]
                           < figures["median_rest_pose_vertex_err_cm"] else "NOT below") + ")")
    if "median_fit_bone_err_deg_predicted" in figures:  # the articulation: near-rest fits cannot lower it
        verdicts.append(f"median bone direction error {figures['median_fit_bone_err_deg_predicted']:.2f}° vs rest "
                        f"pose {figures['median_rest_pose_bone_err_deg']:.2f}° (beaten by "
                        f"{figures['pct_bones_better_than_rest_predicted']:.0f}% of the fits)")
    # with a changed fitting setting the run's own filter judged other fits: judge the refits instead
    which = ("refit_filter_", "_predicted") if fitting_changes else ("filter_", "")
    precision = figures.get(f"{which[0]}precision{which[1]}")
    if precision is not None:
        verdicts.append(f"{'refit ' if fitting_changes else ''}filter precision {precision:.2f} (base rate "
                        f"{figures.get(f'{which[0]}base_rate{which[1]}', float('nan')):.2f}; goal >= "
                        f"{PRECISION_GOAL}: {'met' if precision >= PRECISION_GOAL else 'NOT met'})")
    for line in verdicts:
        print(line)
    notes = ("; ".join(verdicts) + ". "
             f"{args.category}, {settings.preset} preset, run {args.run_name!r} (overrides {parameters['overrides']}), the "
             f"predictions iteration {args.iteration} fitted ("
             + ("Φ₀ loaded from a checkpoint (init_predictor), "
                if parameters.get("init_predictor") and args.iteration == 1
                else f"{settings.train.steps} training steps per model, ")
             + f"{r}x{r}); fits with the run's fitting settings"
             + (f" changed by {fitting_changes}" if fitting_changes else "")
             + " on the predicted maps" + ("" if args.versions == ["predicted"] else
                                            " and with P, Q or both replaced by the ray-cast truth at the same "
                                            "pixels and layers (versions: " + ", ".join(args.versions) + ")")
             + ("" if not args.error_scales else
                "; with both maps' errors scaled by " + ", ".join(f"{s:g}" for s in args.error_scales)
                + " (errors_x<scale>: the truth plus that fraction of the prediction's error)"))
    record(args.record_as, figures, notes=notes, results_dir=args.results_dir)
    return figures


if __name__ == "__main__":
    main()
