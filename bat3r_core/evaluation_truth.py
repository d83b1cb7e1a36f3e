"""Evaluation against 3D ground truth: the ``evaluate`` stage (per-sample metrics of Φ's predictions of a split
whose ground truth is known, ``evaluate_prediction_shard``) and the pseudo-label errors of an iteration's fits
against a generated collection's hidden truth (``write_pseudo_label_errors``). The rows and their aggregation live
in :mod:`bat3r_core.evaluation`; the no-ground-truth mask IoUs in :mod:`bat3r_core.evaluation_masks`.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from bat3r_core import shards
from bat3r_core.cameras import PinholeCamera
from bat3r_core.evaluation import sample_row, write_sample_rows
from bat3r_core.shards import atomic_write

if TYPE_CHECKING:
    from bat3r_core.predictor.collection import CropTransform

__all__ = ["sample_surface", "load_ground_truth", "ground_truth_camera", "evaluate_prediction_shard",
           "map_floor_rows", "MapErrors", "map_errors", "summarise_map_errors",
           "prediction_map_errors", "PSEUDO_LABEL_FILE", "pseudo_label_errors", "write_pseudo_label_errors"]


# ------------------------------------------------------------------------------------ the evaluate stage


def sample_surface(vertices: np.ndarray, faces: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` points uniformly distributed over a triangle mesh's area: vertices (V, 3), faces (F, 3) → (n, 3)."""
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    face = rng.choice(len(tri), size=n, p=area / area.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    t = tri[face]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])


def load_ground_truth(path: str | os.PathLike) -> dict[str, dict[str, np.ndarray]]:
    """The hidden ground truth of a generated collection (``ground_truth.npz`` of ``bat3r_core.datasets``), by
    sample id: ``excess_rotations``, ``global_scale``, ``global_rotation``, ``global_translation``,
    ``camera_rotation``, ``camera_translation``, ``K``, ``posed_vertices`` (world frame)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"ground truth {path} does not exist (generated collections write it beside the "
                                "images; user test splits need a ground_truth.npz in the same format)")
    keys = ("excess_rotations", "global_scale", "global_rotation", "global_translation", "camera_rotation",
            "camera_translation", "K", "posed_vertices")
    with np.load(path, allow_pickle=False) as z:
        missing = [k for k in ("sample_id", *keys) if k not in z.files]
        if missing:
            raise ValueError(f"ground truth {path} lacks array(s) {missing}")
        data = {k: z[k] for k in ("sample_id", *keys)}
    return {str(sid): {k: data[k][i] for k in keys} for i, sid in enumerate(data["sample_id"])}


def ground_truth_camera(truth: Mapping[str, np.ndarray], crop: CropTransform) -> PinholeCamera:
    """The true camera of one generated image (a :func:`load_ground_truth` entry) as the model sees it: through
    the collection's crop ``crop`` (a :class:`~bat3r_core.predictor.collection.CropTransform`; intrinsics
    ``crop.intrinsics(K)``, ``crop.resolution`` pixels square), world → camera as in the ground truth."""
    k = crop.intrinsics(np.asarray(truth["K"], np.float64))
    return PinholeCamera(fx=k[0, 0], fy=k[1, 1], cx=k[0, 2], cy=k[1, 2], width=crop.resolution,
                         height=crop.resolution, R=np.asarray(truth["camera_rotation"], np.float64),
                         t=np.asarray(truth["camera_translation"], np.float64))


def _truth_in_camera(gt: Mapping[str, np.ndarray], faces: np.ndarray, gt_points: int, rng: np.random.Generator
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What a prediction of ground-truth sample ``gt`` is scored against, in its camera frame: the posed vertices
    (V, 3), ``gt_points`` points sampled on the posed surface and the body's up axis (the full alignment's start)."""
    r_cam, t_cam = np.asarray(gt["camera_rotation"], np.float64), np.asarray(gt["camera_translation"], np.float64)
    verts_cam = np.asarray(gt["posed_vertices"], np.float64) @ r_cam.T + t_cam
    up = r_cam @ np.asarray(gt["global_rotation"], np.float64) @ np.array([0.0, 1.0, 0.0])
    return verts_cam, sample_surface(verts_cam, faces, gt_points, rng), up


def evaluate_prediction_shard(predictions_dir: str | os.PathLike, index: int, ground_truth: Mapping[str, Mapping],
                              rig, body_frame: Mapping[str, Any], split: str, iteration: int,
                              out_dir: str | os.PathLike, gt_points: int = 2000, max_pred_points: int = 3000,
                              seed: int = 0) -> shards.ShardPaths:
    """Per-sample evaluation rows for inference shard ``index`` (``bat3r_core.predictor.infer`` output).

    For every predicted test image: the RMS Chamfer distances (full alignment and model-view alignment) between its
    predicted posed points (all confident layers) and ``gt_points`` points sampled uniformly on the ground-truth
    posed surface in the ground-truth camera frame, and the camera rotation error ΔR between the predicted and
    true orientation of the body in the camera: the rotation of the least-squares rigid fit canonical → camera
    of the predicted dual point cloud (Q → P) against the same fit of the rest mesh onto the true posed mesh.
    Rows also carry the true body-centric camera angles and pose features (failure-rate tables, clusters).

    Args:
        ground_truth: :func:`load_ground_truth` output. rig: the category's :class:`~bat3r_core.rig.Rig`.
        body_frame: catalog body-frame joints ``{"origin", "forward", "horizontal"}``.
    Returns the written shard of ``out_dir`` (rows in prediction row order; unpredicted or unknown samples get a
    non-ok status and the reason).
    """
    import torch

    from bat3r_core.datasets import rig_body_frame
    from bat3r_core.metrics import evaluate_sample, kabsch
    from bat3r_core.poses import pose_features
    from bat3r_core.predictor.infer import clouds_path, load_clouds
    from bat3r_core.skinning import skin
    from bat3r_core.viewpoints import spherical_from_pose

    table, _ = shards.read_shard(predictions_dir, index, with_arrays=False)
    clouds = load_clouds(clouds_path(predictions_dir, index))
    rig_t = rig.tensors(dtype=torch.float64)
    rest_joints = rig.rest_joint_positions
    rows = []
    for i, pred in enumerate(table.to_pylist()):
        sid = pred["sample_id"]
        if pred["status"] != shards.STATUS_OK:
            rows.append(sample_row(sid, split, iteration, None, status=pred["status"],
                                   reason=f"prediction: {pred['reason']}"))
            continue
        gt = ground_truth.get(sid)
        if gt is None:
            rows.append(sample_row(sid, split, iteration, None, status="no_ground_truth",
                                   reason=f"sample {sid!r} is not in the ground truth"))
            continue
        cloud = clouds.instance(i)
        if len(cloud["posed_points"]) < 3:
            rows.append(sample_row(sid, split, iteration, None, status="empty",
                                   reason=f"{len(cloud['posed_points'])} confident predicted points"))
            continue
        rng = np.random.default_rng([seed, iteration, index, i])
        verts_cam, target, up = _truth_in_camera(gt, rig.faces, gt_points, rng)
        pred_p = np.asarray(cloud["posed_points"], np.float64)
        pred_q = np.asarray(cloud["canonical_points"], np.float64)
        if len(pred_p) > max_pred_points:
            keep = rng.choice(len(pred_p), max_pred_points, replace=False)
            pred_p, pred_q = pred_p[keep], pred_q[keep]
        r_pred = kabsch(pred_q, pred_p).rotation
        r_true = kabsch(rig.rest_vertices, verts_cam).rotation
        metrics = evaluate_sample(pred_p, target, up=up, pred_rotation=r_pred, gt_rotation=r_true)
        theta = np.asarray(gt["excess_rotations"], np.float64)
        out = skin(rig_t, torch.as_tensor(theta)[None])
        joints = out.joints[0].numpy()
        feats = pose_features(theta[None], joints[None], rest_joints)[0]
        g = float(gt["global_scale"]) * joints @ np.asarray(gt["global_rotation"], np.float64).T \
            + np.asarray(gt["global_translation"], np.float64)
        sph = spherical_from_pose(rig_body_frame(rig, g, body_frame), np.asarray(gt["camera_rotation"], np.float64),
                                  np.asarray(gt["camera_translation"], np.float64))
        rows.append(sample_row(sid, split, iteration, metrics, azimuth_deg=sph.azimuth_deg,
                               elevation_deg=sph.elevation_deg, roll_deg=sph.roll_deg, pose_features=feats))
    return write_sample_rows(out_dir, index, rows)


def map_floor_rows(collection_rows: Sequence[Mapping[str, Any]], ground_truth: Mapping[str, Mapping], rig,
                   num_layers: int, gt_points: int = 2000, seed: int = 0) -> list[dict[str, Any]]:
    """The test mCD of two ideal predictors, per image of a split with ground truth: how low the metric can go at
    the split's crop resolution, and how low it goes without knowing the pose.

    * ``perfect_map_cd_cm``: the exact dual point map (ray-cast truth, ``num_layers`` layers, through the image's
      crop camera) scored like a prediction (:func:`~bat3r_core.metrics.evaluate_sample` against ``gt_points``
      points on the true posed surface). It is not 0: a K-layer map of R x R pixels holds a few hundred points at
      R = 32, and the Chamfer distance from the dense surface to them grows with their spacing.
    * ``rest_pose_map_cd_cm``: the same for the rest-pose mesh rigidly aligned (Kabsch over all vertices) onto the
      true posed mesh and ray-cast through the same camera: a network that knows the shape and the camera exactly
      but not the pose (what canonical-only training aims at).

    ``collection_rows``: the split's collection-stage rows (``crop_*`` columns); rows that are not ``ok`` or have
    no ground truth are skipped. Returns rows ``sample_id, perfect_map_cd_cm, rest_pose_map_cd_cm, n_points``.
    """
    from bat3r_core.metrics import evaluate_sample, kabsch
    from bat3r_core.pointmaps import dual_point_maps
    from bat3r_core.predictor.collection import crop_transform_from_row

    rest = np.asarray(rig.rest_vertices, np.float64)
    out = []
    for k, row in enumerate(collection_rows):
        gt = ground_truth.get(row["sample_id"])
        if row["status"] != shards.STATUS_OK or gt is None:
            continue
        camera = ground_truth_camera(gt, crop_transform_from_row(dict(row)))
        posed = np.asarray(gt["posed_vertices"], np.float64)
        _, target, up = _truth_in_camera(gt, rig.faces, gt_points, np.random.default_rng([seed, k]))
        figures = {"sample_id": row["sample_id"]}
        for name, verts in (("perfect_map", posed), ("rest_pose_map", kabsch(rest, posed).apply(rest))):
            maps = dual_point_maps(verts, rest, rig.faces, camera, num_layers)
            points = maps.P[maps.occupancy].astype(np.float64)
            figures[f"{name}_cd_cm"] = (float(evaluate_sample(points, target, up=up).cd_cm) if len(points) >= 3
                                        else float("nan"))
            if name == "perfect_map":
                figures["n_points"] = int(len(points))  # of the exact map: what the metric's sparsity comes from
        out.append(figures)
    return out


# ------------------------------------------------------------------ where a prediction's error comes from


@dataclass(frozen=True)
class MapErrors:
    """Per-entry errors of one predicted dual point map against its ray-cast truth (same crop camera, same layers),
    over the (pixel, layer) entries that both occupy (predicted occupancy > 0.5).

    depth: (M,) metres, error of the posed point's camera z relative to the object depth (what the network
        predicts: ``P - (0, 0, object_depth)``). lateral: (M,) metres, norm of the posed point's x, y error.
    canonical: (M,) metres, norm of the canonical point's error.
    lateral_bias: (2,) metres, the mean signed x, y error over the entries (0 when there are none): a whole map
        shifted sideways or vertically, as a training set whose x, y follow another principal point teaches.
    depth_correlation: Pearson correlation of the predicted and true relative depths over the entries (NaN with
        fewer than 3 entries or no spread): negative when the map's depth order is reversed (the animal seen
        facing the camera instead of away, the near flank predicted far).
    occupancy_iou: IoU of the predicted (> 0.5) and true occupancy over all pixels and layers.
    """

    depth: np.ndarray
    lateral: np.ndarray
    canonical: np.ndarray
    depth_correlation: float
    occupancy_iou: float
    lateral_bias: np.ndarray = field(default_factory=lambda: np.zeros(2))


def map_errors(pred_posed: np.ndarray, pred_canonical: np.ndarray, pred_occupancy: np.ndarray,
               true_posed: np.ndarray, true_canonical: np.ndarray, true_occupancy: np.ndarray,
               object_depth: float) -> MapErrors:
    """:class:`MapErrors` of one image: predicted maps (H, W, K, 3) and occupancy probabilities (H, W, K) (the
    inference stage's ``posed_points``, ``canonical_points``, ``occupancy``) against the exact maps of
    :func:`~bat3r_core.pointmaps.dual_point_maps` (camera-frame ``P``, ``Q``, boolean occupancy, and its
    ``object_depth``, metres)."""
    shapes = {np.shape(a)[:3] for a in (pred_posed, pred_canonical, pred_occupancy, true_posed, true_canonical,
                                        true_occupancy)}
    if len(shapes) != 1:
        raise ValueError(f"map_errors: predicted and true maps must share (H, W, K), got shapes {sorted(shapes)}")
    occ_pred = np.asarray(pred_occupancy, np.float32) > 0.5
    occ_true = np.asarray(true_occupancy, bool)
    both = occ_pred & occ_true
    union = int((occ_pred | occ_true).sum())
    p_pred = np.asarray(pred_posed, np.float64)[both]
    p_true = np.asarray(true_posed, np.float64)[both] - np.array([0.0, 0.0, float(object_depth)])
    e = p_pred - p_true
    q = np.linalg.norm(np.asarray(pred_canonical, np.float64)[both] - np.asarray(true_canonical, np.float64)[both],
                       axis=1)
    corr = float("nan")
    if len(e) >= 3 and np.std(p_pred[:, 2]) > 0 and np.std(p_true[:, 2]) > 0:
        corr = float(np.corrcoef(p_pred[:, 2], p_true[:, 2])[0, 1])
    return MapErrors(depth=np.abs(e[:, 2]), lateral=np.linalg.norm(e[:, :2], axis=1), canonical=q,
                     depth_correlation=corr, occupancy_iou=1.0 if union == 0 else float(both.sum() / union),
                     lateral_bias=e[:, :2].mean(axis=0) if len(e) else np.zeros(2))


def summarise_map_errors(errors: Sequence[MapErrors], tail: float = 0.1) -> dict[str, float]:
    """Figures of a split's :class:`MapErrors` (entries of all images pooled, cm): ``depth_err_median_cm``,
    ``depth_err_rms_cm``, ``depth_err_tail_share`` (the share of the summed squared depth error carried by the
    worst ``tail`` fraction of entries: near ``tail`` for even errors, near 1 when a few gross errors dominate),
    ``lateral_err_rms_cm``, ``lateral_bias_x_cm`` and ``lateral_bias_y_cm`` (the images' mean signed x, y errors,
    averaged over images: a shift every image shares), ``lateral_bias_abs_cm`` (the mean norm of each image's
    shift), ``canonical_err_median_cm``, ``canonical_err_rms_cm``, ``depth_reversed_pct`` (images
    whose depth correlation is negative), ``occupancy_iou`` (mean) and ``n_images``."""
    if not 0.0 < tail < 1.0:
        raise ValueError(f"tail: expected a fraction in (0, 1), got {tail}")
    if not errors:
        raise ValueError("summarise_map_errors: no image to summarise")
    depth = np.concatenate([m.depth for m in errors]) * 100.0
    if len(depth) == 0:
        raise ValueError("summarise_map_errors: no map entry is occupied in both the prediction and the truth")
    lateral = np.concatenate([m.lateral for m in errors]) * 100.0
    canonical = np.concatenate([m.canonical for m in errors]) * 100.0
    sq = np.sort(depth ** 2)[::-1]
    worst = max(1, int(round(tail * len(sq))))
    corr = np.array([m.depth_correlation for m in errors])
    return {"depth_err_median_cm": float(np.median(depth)), "depth_err_rms_cm": float(np.sqrt(np.mean(sq))),
            "depth_err_tail_share": float(sq[:worst].sum() / sq.sum()) if sq.sum() > 0 else 0.0,
            "lateral_err_rms_cm": float(np.sqrt(np.mean(lateral ** 2))),
            "lateral_bias_x_cm": float(100.0 * np.mean([m.lateral_bias[0] for m in errors])),
            "lateral_bias_y_cm": float(100.0 * np.mean([m.lateral_bias[1] for m in errors])),
            "lateral_bias_abs_cm": float(100.0 * np.mean([np.linalg.norm(m.lateral_bias) for m in errors])),
            "canonical_err_median_cm": float(np.median(canonical)),
            "canonical_err_rms_cm": float(np.sqrt(np.mean(canonical ** 2))),
            "depth_reversed_pct": float(100.0 * np.mean(corr[np.isfinite(corr)] < 0)) if np.isfinite(corr).any()
            else float("nan"),
            "occupancy_iou": float(np.mean([m.occupancy_iou for m in errors])), "n_images": float(len(errors))}


def prediction_map_errors(predictions_dir: str | os.PathLike, collection_rows: Sequence[Mapping[str, Any]],
                          ground_truth: Mapping[str, Mapping], rig) -> list[MapErrors]:
    """:class:`MapErrors` of every ok prediction of an inference folder (``bat3r_core.predictor.infer`` shards)
    whose image has ground truth: its maps against the exact maps of the true posed mesh through the split's crop
    camera (``collection_rows``: the split's collection-stage rows, ``crop_*`` columns), at the prediction's
    resolution and number of layers. Where :func:`evaluate_prediction_shard` says how far off a prediction is, this
    says how: depth against lateral error, even errors against a few gross ones, reversed depth order."""
    from bat3r_core.pointmaps import dual_point_maps
    from bat3r_core.predictor.collection import crop_transform_from_row

    crops = {r["sample_id"]: r for r in collection_rows if r["status"] == shards.STATUS_OK}
    out = []
    for index in shards.list_shards(predictions_dir):
        table, arrays = shards.read_shard(predictions_dir, index)
        for key in ("posed_points", "canonical_points", "occupancy"):
            if key not in arrays:
                raise ValueError(f"{shards.shard_paths(predictions_dir, index).npz}: lacks array {key!r} (expected "
                                 "an inference shard of bat3r_core.predictor.infer)")
        for i, row in enumerate(table.to_pylist()):
            sid = row["sample_id"]
            if row["status"] != shards.STATUS_OK or sid not in ground_truth or sid not in crops:
                continue
            gt = ground_truth[sid]
            camera = ground_truth_camera(gt, crop_transform_from_row(dict(crops[sid])))
            if camera.height != arrays["occupancy"].shape[1]:
                raise ValueError(f"{predictions_dir}: sample {sid!r} is predicted at {arrays['occupancy'].shape[1]} "
                                 f"px but its crop is {camera.height} px")
            truth = dual_point_maps(np.asarray(gt["posed_vertices"], np.float64), rig.rest_vertices, rig.faces,
                                    camera, arrays["occupancy"].shape[-1])
            out.append(map_errors(arrays["posed_points"][i], arrays["canonical_points"][i], arrays["occupancy"][i],
                                  truth.P, truth.Q, truth.occupancy, truth.object_depth))
    return out


PSEUDO_LABEL_FILE = "pseudo_labels.parquet"
"""``iter-NN/evaluate/pseudo_labels.parquet``: fitted-pose vs hidden ground-truth pose errors of the collection."""


def pseudo_label_errors(fit_rows: Sequence[Mapping[str, Any]], ground_truth: Mapping[str, Mapping], rig
                        ) -> list[dict[str, Any]]:
    """Pose errors of the fits (pseudo-labels) against the hidden ground truth, where it exists.

    The pose alone is compared: the rig is posed by the fitted and the true θ (unit bone scales, no global
    similarity), the fitted mesh is rigidly aligned onto the true one (Kabsch over all vertices), and the mean
    vertex and joint distances (cm), the mean rotation difference over the joints (degrees; the root counts as
    0, its rotation being a global orientation) and the mean angle between the fitted and the true bones (degrees,
    ``analysis.bone_direction_error_deg``: the swing alone, blind to the twist no point map shows) are reported.
    Fits whose status is not ``ok`` or that have no ground truth are left out.

    Returns rows ``sample_id, joint_err_cm, vertex_err_cm, angle_err_deg, bone_err_deg``.
    """
    import torch

    from bat3r_core.analysis import bone_direction_error_deg, pose_errors
    from bat3r_core.metrics import kabsch
    from bat3r_core.skinning import skin

    keep = [r for r in fit_rows if r["status"] == shards.STATUS_OK and r["sample_id"] in ground_truth]
    if not keep:
        return []
    j = rig.num_joints
    fitted = np.stack([np.asarray(r["excess_rotations"], np.float64).reshape(j, 3) for r in keep])
    truth = np.stack([np.asarray(ground_truth[r["sample_id"]]["excess_rotations"], np.float64) for r in keep])
    tensors = rig.tensors(dtype=torch.float64)
    fo, to = skin(tensors, torch.as_tensor(fitted)), skin(tensors, torch.as_tensor(truth))
    fv, fj, tv, tj = fo.vertices.numpy(), fo.joints.numpy(), to.vertices.numpy(), to.joints.numpy()
    for i in range(len(keep)):
        align = kabsch(fv[i], tv[i])
        fv[i], fj[i] = align.apply(fv[i]), align.apply(fj[i])
    root = rig.parents < 0  # the root's rotation is a global orientation, not pose: compare it as equal
    f_local, t_local = fitted.copy(), truth.copy()
    f_local[:, root] = 0.0
    t_local[:, root] = 0.0
    errors = pose_errors(fj, tj, fv, tv, f_local, t_local)
    bones = bone_direction_error_deg(fj, tj, rig.parents, rig.rest_joint_positions)
    return [{"sample_id": r["sample_id"], "joint_err_cm": float(errors.joint_err_cm[i]),
             "vertex_err_cm": float(errors.vertex_err_cm[i]), "angle_err_deg": float(errors.angle_err_deg[i]),
             "bone_err_deg": float(bones[i])}
            for i, r in enumerate(keep)]


def write_pseudo_label_errors(fit_dir: str | os.PathLike, ground_truth: Mapping[str, Mapping], rig,
                              out_dir: str | os.PathLike) -> tuple[Path, dict[str, Any]]:
    """:func:`pseudo_label_errors` of every fit shard of ``fit_dir`` → ``out_dir/pseudo_labels.parquet``.

    Returns the file and a summary ``{"n", "joint_err_cm", "vertex_err_cm", "angle_err_deg", "bone_err_deg"}``
    (means over the rows; None without rows)."""
    rows = pseudo_label_errors(shards.read_table(fit_dir).to_pylist(), ground_truth, rig)
    columns = ("joint_err_cm", "vertex_err_cm", "angle_err_deg", "bone_err_deg")
    schema = pa.schema([("sample_id", pa.string())] + [(c, pa.float64()) for c in columns])
    table = pa.Table.from_pylist(rows, schema=schema)
    path = atomic_write(Path(out_dir) / PSEUDO_LABEL_FILE, lambda tmp: pq.write_table(table, tmp))
    means = {c: (float(np.mean([r[c] for r in rows])) if rows else None) for c in columns}
    return path, {"n": len(rows), **means}
