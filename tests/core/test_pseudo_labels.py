"""The pseudo-label filter on hand-made fits: quality columns, thresholds, the kept quantile, min_kept, the
filter shards, precision against a known truth, and the catalog's validation of the filter section."""
from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from bat3r_core import pseudo_labels as PL
from bat3r_core import shards

ROOT = Path(__file__).resolve().parents[2]


def _q(sample_id, residual, inlier=0.9, status="ok", **more):
    row = {c: float("nan") for c in PL.QUALITY_COLUMNS}
    row.update(sample_id=sample_id, fit_status=status, residual_chamfer_cm=residual, inlier_ratio=inlier, **more)
    return row


def _crafted():
    return [_q("a", 1.0), _q("b", 2.0), _q("c", 3.0, inlier=0.1), _q("d", 4.0), _q("e", 50.0),
            _q("f", float("nan"), inlier=0.0, status="too_few_points")]


def _by_id(rows):
    return {r["sample_id"]: r for r in rows}


def test_thresholds_then_quantile_keep_the_right_fits_with_their_reasons():
    cfg = PL.PseudoLabelFilterConfig(keep_quantile=0.4, min_kept=1, maximum={"residual_chamfer_cm": 10.0},
                                     minimum={"inlier_ratio": 0.3})
    out = _by_id(PL.filter_fits(_crafted(), cfg))
    assert [s for s, r in out.items() if r["kept"]] == ["a", "b"]  # ceil(0.4 * 5 ok fits) = 2, best first
    assert out["a"]["status"] == "ok" and out["a"]["reason"] == ""
    assert out["e"]["status"] == "filtered_residual_chamfer_cm" and out["e"]["reason"] == "residual_chamfer_cm 50 > 10"
    assert out["c"]["status"] == "filtered_inlier_ratio" and out["c"]["reason"] == "inlier_ratio 0.1 < 0.3"
    assert out["d"]["status"] == PL.STATUS_QUANTILE and "ranks 3 of 3" in out["d"]["reason"]
    assert out["f"]["status"] == PL.STATUS_NOT_FITTED and out["f"]["reason"] == "fit too_few_points"
    assert out["d"]["score"] == 4.0 and out["d"]["residual_chamfer_cm"] == 4.0
    counts = PL.filter_counts(list(out.values()))
    assert counts == {"n_fits": 5, "n_kept": 2, "kept_fraction": 0.4, "n_rescued": 0,
                      "drop_counts": {"filtered_inlier_ratio": 1, "filtered_quantile": 1,
                                      "filtered_residual_chamfer_cm": 1}}
    # a larger quantile keeps every threshold survivor: ceil(0.5 * 5) = 3 = a, b, d
    out = _by_id(PL.filter_fits(_crafted(), PL.PseudoLabelFilterConfig(
        keep_quantile=0.5, maximum={"residual_chamfer_cm": 10.0}, minimum={"inlier_ratio": 0.3})))
    assert sorted(s for s, r in out.items() if r["kept"]) == ["a", "b", "d"]


def test_min_kept_keeps_back_the_best_scoring_dropped_fits_but_never_unfitted_ones():
    cfg = PL.PseudoLabelFilterConfig(keep_quantile=0.4, min_kept=4, maximum={"residual_chamfer_cm": 10.0},
                                     minimum={"inlier_ratio": 0.3})
    out = _by_id(PL.filter_fits(_crafted(), cfg))
    assert sorted(s for s, r in out.items() if r["kept"]) == ["a", "b", "c", "d"]  # c (3 cm), d (4 cm) back; not e
    assert out["c"]["status"] == "ok"
    assert out["c"]["reason"] == "kept by min_kept=4 (was filtered_inlier_ratio: inlier_ratio 0.1 < 0.3)"
    assert out["e"]["status"] == "filtered_residual_chamfer_cm"
    assert PL.filter_counts(list(out.values()))["n_rescued"] == 2
    out = PL.filter_fits(_crafted(), PL.PseudoLabelFilterConfig(keep_quantile=0.2, min_kept=100,
                                                                maximum={"residual_chamfer_cm": 0.5}))
    assert [r["kept"] for r in out] == [True] * 5 + [False]  # all 5 ok fits, not the unfitted one
    # a run whose fits all failed keeps nothing (min_kept counts ok fits only)
    out = PL.filter_fits([_q("x", 1.0, status="bad_input")], PL.PseudoLabelFilterConfig(min_kept=3))
    assert not out[0]["kept"] and PL.filter_counts(out)["kept_fraction"] is None


def test_score_direction_nan_and_the_default_that_keeps_every_ok_fit():
    rows = [_q("a", 1.0, inlier=0.2), _q("b", 2.0, inlier=0.9), _q("c", 3.0, inlier=0.5),
            _q("d", 4.0, inlier=float("nan"))]
    out = PL.filter_fits(rows, PL.PseudoLabelFilterConfig(score="inlier_ratio", keep_quantile=0.5))
    assert [r["sample_id"] for r in out if r["kept"]] == ["b", "c"]  # higher inlier ratio is better; NaN last
    out = PL.filter_fits(rows, PL.PseudoLabelFilterConfig(score="inlier_ratio", keep_quantile=0.75, min_kept=0))
    assert [r["sample_id"] for r in out if r["kept"]] == ["a", "b", "c"]
    out = _by_id(PL.filter_fits(rows, PL.PseudoLabelFilterConfig(maximum={"camera_reprojection_px": 2.0},
                                                                 min_kept=0)))
    assert out["a"]["status"] == "filtered_camera_reprojection_px" and out["a"]["reason"] == \
        "camera_reprojection_px is NaN"
    assert all(r["kept"] for r in PL.filter_fits(_crafted()[:5], PL.PseudoLabelFilterConfig()))


def test_quality_rows_compute_the_canonical_chamfer_and_pose_distance(toy_rig):
    j = toy_rig.num_joints
    bent = np.zeros((j, 3))
    bent[toy_rig.joint_index("forearm.L")] = [0.8, 0.0, 0.0]
    rest = np.asarray(toy_rig.rest_vertices)
    fits = [{"sample_id": "rest", "status": "ok", "excess_rotations": [0.0] * (3 * j), "residual_chamfer_cm": 1.5,
             "inlier_ratio": 0.7, "mean_confidence": 2.0, "loss_data": 0.1, "loss_total": 0.2,
             "camera_reprojection_px": 0.4, "camera_inlier_ratio": 0.9},
            {"sample_id": "bent", "status": "ok", "excess_rotations": bent.ravel().tolist()},
            {"sample_id": "bad", "status": "too_few_points", "excess_rotations": []}]
    points = [rest[::7], rest[::7] + [0.03, 0.0, 0.04], None]
    q = _by_id(PL.quality_rows(fits, toy_rig, points))
    assert q["rest"]["canonical_chamfer_cm"] == pytest.approx(0.0, abs=1e-9)
    assert 0.5 < q["bent"]["canonical_chamfer_cm"] <= 5.0 + 1e-9  # 5 cm offset, nearest vertex at most that far
    assert q["rest"]["pose_joint_dist_cm"] == pytest.approx(0.0, abs=1e-6)
    assert q["bent"]["pose_joint_dist_cm"] > 1.0
    assert q["rest"]["residual_chamfer_cm"] == 1.5 and q["rest"]["camera_reprojection_px"] == 0.4
    assert math.isnan(q["bent"]["residual_chamfer_cm"])  # missing fit column → NaN
    assert math.isnan(q["bad"]["canonical_chamfer_cm"]) and math.isnan(q["bad"]["pose_joint_dist_cm"])
    assert q["bad"]["fit_status"] == "too_few_points"
    with pytest.raises(ValueError, match="one per fit row"):
        PL.quality_rows(fits, toy_rig, points[:2])


def test_filter_shards_round_trip_and_drop_stale_shards(tmp_path):
    rows = PL.filter_fits(_crafted(), PL.PseudoLabelFilterConfig(keep_quantile=0.4))
    shards.write_shard(tmp_path, 7, [{"sample_id": "old", "status": "ok", "reason": ""}])  # an earlier run's
    paths = PL.write_filter_shards(tmp_path, [0, 2], rows, [4, 2])
    assert [p.parquet.name for p in paths] == ["part-00000.parquet", "part-00002.parquet"]
    assert shards.list_shards(tmp_path) == [0, 2]
    back = PL.read_kept(tmp_path, 2, ["e", "f"])
    assert [r["kept"] for r in back] == [False, False] and back[1]["status"] == PL.STATUS_NOT_FITTED
    assert [r["kept"] for r in PL.read_kept(tmp_path, 0, ["a", "b", "c", "d"])] == [True, True, False, False]
    with pytest.raises(ValueError, match="rerun the filter stage"):
        PL.read_kept(tmp_path, 0, ["a", "b", "x", "d"])
    with pytest.raises(ValueError, match="sum to 6 rows"):
        PL.write_filter_shards(tmp_path, [0], rows, [5])


def test_filter_precision_against_a_known_truth(toy_rig):
    errors = [{"sample_id": s, "vertex_err_cm": e} for s, e in (("a", 5.0), ("b", 12.0), ("c", 3.0), ("d", 20.0))]
    rest = [{"sample_id": s, "vertex_err_cm": 9.0} for s in "abcd"]
    kept = [{"sample_id": s, "kept": s in "ab"} for s in "abcde"]
    assert PL.filter_precision(errors, rest, kept) == {"n": 4, "n_good": 2, "n_kept": 2, "n_kept_good": 1,
                                                       "precision": 0.5, "recall": 0.5, "base_rate": 0.5}
    none_kept = PL.filter_precision(errors, rest, [{"sample_id": s, "kept": False} for s in "abcd"])
    assert none_kept["precision"] is None and none_kept["recall"] == 0.0
    with pytest.raises(ValueError, match="filter_rows lack samples"):
        PL.filter_precision(errors, rest, kept[:2])
    # the rest-pose errors are the evaluation's pseudo-label errors of θ = 0: a true fit beats them
    from bat3r_core.evaluation_truth import pseudo_label_errors
    from bat3r_core.poses import sample_toy_natural_poses

    theta, _ = sample_toy_natural_poses(2, seed=7)
    gt = {f"s{i}": {"excess_rotations": theta[i]} for i in range(2)}
    fits = [{"sample_id": "s0", "status": "ok", "excess_rotations": theta[0].ravel().tolist()},
            {"sample_id": "s1", "status": "ok", "excess_rotations": np.zeros(theta[1].size).tolist()}]
    err, rest = pseudo_label_errors(fits, gt, toy_rig), PL.rest_pose_errors(fits, gt, toy_rig)
    assert err[0]["vertex_err_cm"] < 1e-6 < rest[0]["vertex_err_cm"]
    assert err[1]["vertex_err_cm"] == pytest.approx(rest[1]["vertex_err_cm"])  # the rest pose does not beat itself
    figures = PL.filter_precision(err, rest, [{"sample_id": "s0", "kept": True}, {"sample_id": "s1", "kept": True}])
    assert figures["n_good"] == 1 and figures["precision"] == 0.5 and figures["recall"] == 1.0


@pytest.mark.parametrize("section, message", [
    ({"keep_quantile": 0}, r"runs\.tiny\.pseudo_label_filter: keep_quantile: must be in \(0, 1\], got 0"),
    ({"keep_quantile": 1.5}, r"runs\.tiny\.pseudo_label_filter: keep_quantile: must be in \(0, 1\]"),
    ({"quantile": 0.5}, r"runs\.tiny\.pseudo_label_filter: unknown key\(s\) \['quantile'\]"),
    ({"score": "chamfer"}, r"runs\.tiny\.pseudo_label_filter: score: expected one of"),
    ({"min_kept": -1}, r"runs\.tiny\.pseudo_label_filter: min_kept: must be an integer >= 0"),
    ({"min_kept": "4"}, r"runs\.tiny\.pseudo_label_filter\.min_kept: expected an integer"),
    ({"maximum": {"joint_distance": 3.0}}, r"runs\.tiny\.pseudo_label_filter: maximum\.joint_distance: unknown"),
    ({"minimum": {"inlier_ratio": "high"}}, r"runs\.tiny\.pseudo_label_filter\.minimum\.inlier_ratio: expected"),
])
def test_catalog_rejects_a_bad_filter_section_naming_the_key(tmp_path, section, message):
    from bat3r_core.catalog import ConfigError, load_catalog

    raw = yaml.safe_load((ROOT / "data_catalog.yaml").read_text())
    raw["runs"]["tiny"]["pseudo_label_filter"] = section
    path = tmp_path / "data_catalog.yaml"
    path.write_text(yaml.safe_dump(raw))
    with pytest.raises(ConfigError, match=message):
        load_catalog(path)


def test_catalog_filter_config_per_preset_and_override(tmp_path):
    from bat3r_core.catalog import load_catalog
    from flows._settings import resolve_run

    shutil.copy(ROOT / "data_catalog.yaml", tmp_path / "data_catalog.yaml")
    catalog = load_catalog(tmp_path / "data_catalog.yaml")
    assert catalog.pseudo_label_filter_config("tiny") == PL.PseudoLabelFilterConfig(
        score="residual_chamfer_cm", keep_quantile=0.75, min_kept=4)
    assert catalog.pseudo_label_filter_config("paper") == PL.PseudoLabelFilterConfig()  # no section: keep all
    settings = resolve_run("toy", "tiny", "r", {"pseudo_label_filter.keep_quantile": 0.5}, catalog=catalog)
    assert settings.pseudo_label_filter.keep_quantile == 0.5 and settings.pseudo_label_filter.min_kept == 4
    assert settings.to_mapping()["pseudo_label_filter"]["keep_quantile"] == 0.5


def test_score_ranking_on_crafted_fits_against_hand_counts():
    # six fits; fit minus rest error: a -3, b -2, c +1, d -1, e +4, f +2 (good: a, b, d: base rate 0.5)
    fit_err = {"a": 7.0, "b": 8.0, "c": 11.0, "d": 9.0, "e": 14.0, "f": 12.0}
    errors = [{"sample_id": s, "vertex_err_cm": v} for s, v in fit_err.items()]
    rest = [{"sample_id": s, "vertex_err_cm": 10.0} for s in fit_err]
    # residual ranks the fits exactly by their error; inlier_ratio (higher is better) reverses it; c has no
    # confidence (NaN ranks last)
    residual = {"a": 1.0, "b": 2.0, "d": 3.0, "c": 4.0, "f": 5.0, "e": 6.0}
    inlier = {"a": 0.1, "b": 0.2, "d": 0.3, "c": 0.4, "f": 0.5, "e": 0.6}
    confidence = {"a": 0.9, "b": 0.1, "c": float("nan"), "d": 0.8, "e": 0.7, "f": 0.2}
    quality = [_q(s, residual[s], inlier=inlier[s], mean_confidence=confidence[s]) for s in fit_err]
    quality.append(_q("z", 0.5))  # a quality row without truth takes no part
    out = PL.score_ranking(errors, rest, quality, columns=("residual_chamfer_cm", "inlier_ratio",
                                                            "mean_confidence"), quantiles=(0.5, 0.25))
    assert out["all"] == {"n": 6, "base_rate": 0.5}
    assert out["residual_chamfer_cm"]["rho"] == pytest.approx(1.0)
    assert out["residual_chamfer_cm"]["precision@0.5"] == 1.0  # a, b, d
    assert out["residual_chamfer_cm"]["precision@0.25"] == 1.0  # ceil(1.5) = 2: a, b
    assert out["inlier_ratio"]["rho"] == pytest.approx(1.0)  # larger inlier ratio, worse fit here
    assert out["inlier_ratio"]["precision@0.5"] == 0.0  # e, f, c
    # confidence best first: a (0.9, good), d (0.8, good), e (0.7, bad); c's NaN counts as the worst value
    assert out["mean_confidence"]["precision@0.5"] == pytest.approx(2 / 3)
    assert out["mean_confidence"]["precision@0.25"] == 1.0
    from scipy.stats import spearmanr
    filled = [0.9, 0.1, 0.1, 0.8, 0.7, 0.2]  # c's NaN → the column's worst (smallest, higher is better)
    expected = spearmanr(filled, [-3, -2, 1, -1, 4, 2])[0]
    assert out["mean_confidence"]["rho"] == pytest.approx(expected)
