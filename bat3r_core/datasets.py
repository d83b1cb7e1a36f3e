"""Render-job builders for the training sets, and the toy image collection.

* :func:`canonical_jobs` — iteration 0: ``n`` viewpoints around the rest-pose mesh from the camera prior
  (Student's t or Normal, :class:`bat3r_core.viewpoints.CameraPriorConfig`), random texture, environment map,
  rotation and seed.
* :func:`random_pose_jobs` — the random-poses baseline: poses from :func:`bat3r_core.poses.sample_random_poses`,
  Student's t cameras around each posed mesh.
* :func:`make_toy_collection` / :func:`ensure_toy_collection` — the toy quadruped rendered in natural poses
  (:func:`bat3r_core.poses.sample_toy_natural_poses`) with a random yaw, written as a user's photo collection
  (``images/*.png``, ``masks/*.png``) with its hidden ground truth in a separate folder; cached by a JSON stamp.

Builders are pure and seeded: the same arguments give the same jobs. World frame of the jobs: the canonical frame
moved by each job's global similarity (identity for the canonical set and the random-poses set).
"""
from __future__ import annotations

import json
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from bat3r_core.poses import RandomPoseConfig, sample_random_poses, sample_toy_natural_poses, TOY_POSE_FAMILIES
from bat3r_core.render.config import RenderConfig, SceneAssets, render_config
from bat3r_core.render.jobs import RenderJob
from bat3r_core.rig import Rig
from bat3r_core.viewpoints import BodyFrame, CameraPriorConfig, body_frame, sample_viewpoints

__all__ = ["canonical_jobs", "random_pose_jobs", "toy_collection_jobs", "make_toy_collection",
           "ensure_toy_collection", "toy_collection_and_test_split", "collection_toy_command", "ToyCollection",
           "rig_body_frame", "TOY_TEST_SEED_OFFSET"]

TOY_TEST_SEED_OFFSET = 1_000_003
"""The toy test split uses ``seed + TOY_TEST_SEED_OFFSET``."""
_STAMP = "collection.json"
_GT_FILE = "ground_truth.npz"


def rig_body_frame(rig: Rig, joints: np.ndarray, spec: Mapping) -> BodyFrame:
    """Body frame from joint positions and a catalog spec ``{"origin": name, "forward": (a, b),
    "horizontal": (left, right)}`` (e.g. :data:`bat3r_core.toy.TOY_BODY_FRAME`).

    Args:
        joints: (J, 3) joint positions, metres, world frame.
    """
    for key in ("origin", "forward", "horizontal"):
        if key not in spec:
            raise ValueError(f"body frame spec needs '{key}', got keys {sorted(spec)}")
    idx = rig.joint_index
    return body_frame(joints, idx(spec["origin"]), (idx(spec["forward"][0]), idx(spec["forward"][1])),
                      (idx(spec["horizontal"][0]), idx(spec["horizontal"][1])))


def _check_common(n: int, resolution: int, num_textures: int, num_envmaps: int) -> None:
    for name, value, low in (("n", n, 1), ("resolution", resolution, 8), ("num_textures", num_textures, 1),
                             ("num_envmaps", num_envmaps, 0)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
            raise ValueError(f"{name} must be an int >= {low}, got {value!r}")


def _appearance(rng: np.random.Generator, num_textures: int, num_envmaps: int) -> dict:
    return {"texture_id": int(rng.integers(num_textures)),
            "envmap_id": int(rng.integers(num_envmaps)) if num_envmaps > 0 else -1,
            "envmap_rotation": float(rng.uniform(0.0, 2.0 * math.pi)),
            "seed": int(rng.integers(0, 2 ** 31 - 1))}


def _skin(rig: Rig, theta: np.ndarray, rotation: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Posed (vertices (B, V, 3), joints (B, J, 3)) in float64, optional global rotation (B, 3, 3)."""
    import torch

    from bat3r_core.skinning import skin

    t = rig.tensors(dtype=torch.float64)
    rot = None if rotation is None else torch.as_tensor(rotation, dtype=torch.float64)
    out = skin(t, torch.as_tensor(theta, dtype=torch.float64), global_rotation=rot)
    return out.vertices.numpy(), out.joints.numpy()


def canonical_jobs(rig: Rig, n: int, seed: int, body_frame_spec: Mapping, prior: CameraPriorConfig | None = None,
                   resolution: int = 128, num_textures: int = 1, num_envmaps: int = 0,
                   prefix: str = "canonical") -> list[RenderJob]:
    """Iteration-0 jobs: ``n`` views of the rest-pose mesh (θ = 0, identity similarity).

    Azimuth uniform, elevation and roll from ``prior`` (default: the reference Student's t per view type), framing
    margin ``U(prior.margin_range)``; texture, environment map (``-1`` = procedural sky when ``num_envmaps == 0``),
    its rotation and the Cycles seed are drawn from the same seeded generator.
    """
    _check_common(n, resolution, num_textures, num_envmaps)
    prior = prior or CameraPriorConfig()
    rng = np.random.default_rng([seed, 0xC0])
    frame = rig_body_frame(rig, rig.rest_joint_positions, body_frame_spec)
    views = sample_viewpoints(rig.rest_vertices, frame, n, prior, resolution, resolution, rng)
    theta = np.zeros((rig.num_joints, 3))
    return [RenderJob(sample_id=f"{prefix}-{i:06d}", excess_rotations=theta, camera=v.camera,
                      view_kind="canonical", view_type=str(v.view_type), **_appearance(rng, num_textures, num_envmaps))
            for i, v in enumerate(views)]


def random_pose_jobs(rig: Rig, n: int, seed: int, body_frame_spec: Mapping, prior: CameraPriorConfig | None = None,
                     resolution: int = 128, num_textures: int = 1, num_envmaps: int = 0,
                     pose_config: RandomPoseConfig = RandomPoseConfig(), prefix: str = "random_pose"
                     ) -> list[RenderJob]:
    """Random-poses baseline jobs: θ from :func:`sample_random_poses` (seeded), one Student's t camera per pose
    framed around the posed mesh (body frame of the posed joints)."""
    _check_common(n, resolution, num_textures, num_envmaps)
    prior = prior or CameraPriorConfig(distribution="student_t")
    theta, _ = sample_random_poses(rig, n, seed, pose_config)
    verts, joints = _skin(rig, theta)
    rng = np.random.default_rng([seed, 0xBA5E])
    jobs = []
    for i in range(n):
        frame = rig_body_frame(rig, joints[i], body_frame_spec)
        (view,) = sample_viewpoints(verts[i], frame, 1, prior, resolution, resolution, rng)
        jobs.append(RenderJob(sample_id=f"{prefix}-{i:06d}", excess_rotations=theta[i], camera=view.camera,
                              view_kind="random_pose", view_type=str(view.view_type),
                              **_appearance(rng, num_textures, num_envmaps)))
    return jobs


def _yaw(angle: float) -> np.ndarray:
    """Rotation about the canonical up axis (+Y) by ``angle`` radians."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def toy_collection_jobs(n: int, seed: int, resolution: int = 128, prior: CameraPriorConfig | None = None,
                        families: Sequence[str] = TOY_POSE_FAMILIES, prefix: str = "toy", rig: Rig | None = None
                        ) -> tuple[list[RenderJob], list[str], np.ndarray]:
    """Jobs of a toy image collection: natural poses, a random yaw ``U[-pi, pi)`` as the global rotation, one camera
    per image from ``prior`` around the posed mesh, a random procedural coat and a procedural sky.

    Returns:
        (jobs, pose family per job, posed vertices (n, V, 3) float64 in the world frame).
    """
    from bat3r_core.toy import TOY_BODY_FRAME, TOY_COATS, build_toy_rig

    _check_common(n, resolution, 1, 0)
    rig = rig or build_toy_rig()
    prior = prior or CameraPriorConfig()
    theta, fams = sample_toy_natural_poses(n, seed, tuple(families))
    rng = np.random.default_rng([seed, 0x70])
    yaws = rng.uniform(-math.pi, math.pi, size=n)
    rot = np.stack([_yaw(a) for a in yaws])
    verts, joints = _skin(rig, theta, rot)
    jobs = []
    for i in range(n):
        frame = rig_body_frame(rig, joints[i], TOY_BODY_FRAME)
        (view,) = sample_viewpoints(verts[i], frame, 1, prior, resolution, resolution, rng)
        jobs.append(RenderJob(sample_id=f"{prefix}-{i:05d}", excess_rotations=theta[i], camera=view.camera,
                              global_rotation=rot[i], view_kind="collection", view_type=str(view.view_type),
                              **_appearance(rng, len(TOY_COATS), 0)))
    return jobs, list(fams), verts


@dataclass(frozen=True)
class ToyCollection:
    """A toy image collection on disk.

    Attributes:
        images_dir: ``<out>/images`` with ``<sample_id>.png`` (RGB). masks_dir: ``<out>/masks`` (0/255 PNG).
        ground_truth_dir: the hidden ground truth (only evaluation reads it): ``ground_truth.npz``, the rendered
            training-format shard(s) under ``render/``, the toy asset ``toy.glb`` and ``collection.json``.
        sample_ids: the images written (renders that failed are left out).
        reused: True when an existing collection with the same parameters was found.
    """

    images_dir: Path
    masks_dir: Path
    ground_truth_dir: Path
    sample_ids: tuple[str, ...]
    reused: bool


def _default_gt_dir(out_dir: Path) -> Path:
    return out_dir.parent / f"{out_dir.name}_ground_truth"


def _params(n: int, seed: int, resolution: int, config: RenderConfig, families: Sequence[str],
            prior: CameraPriorConfig) -> dict:
    from bat3r_core.config_utils import to_mapping

    return {"kind": "toy_collection", "version": 1, "n": int(n), "seed": int(seed), "resolution": int(resolution),
            "render": to_mapping(config), "families": list(families), "prior": to_mapping(prior)}


def _load_existing(out_dir: Path, gt_dir: Path, params: dict) -> ToyCollection | None:
    stamp = gt_dir / _STAMP
    if not stamp.is_file() or not (gt_dir / _GT_FILE).is_file():
        return None
    try:
        saved = json.loads(stamp.read_text())
    except json.JSONDecodeError:
        return None
    if saved.get("params") != json.loads(json.dumps(params)):
        return None
    ids = tuple(saved.get("sample_ids", ()))
    if not all((out_dir / "images" / f"{s}.png").is_file() and (out_dir / "masks" / f"{s}.png").is_file()
               for s in ids):
        return None
    return ToyCollection(out_dir / "images", out_dir / "masks", gt_dir, ids, reused=True)


def make_toy_collection(out_dir: str | os.PathLike, n: int, seed: int = 0, resolution: int = 128,
                        config: RenderConfig | str | None = "demo", ground_truth_dir: str | os.PathLike | None = None,
                        families: Sequence[str] = TOY_POSE_FAMILIES, prior: CameraPriorConfig | None = None,
                        force: bool = False) -> ToyCollection:
    """Render a toy image collection (cached: reused when the JSON stamp's parameters match, unless ``force``).

    Layout: ``out_dir/images/<id>.png``, ``out_dir/masks/<id>.png`` (what a user's photo collection looks like);
    the hidden ground truth goes to ``ground_truth_dir`` (default ``<out_dir>_ground_truth`` beside it):
    ``ground_truth.npz`` with ``sample_id (N,) str``, ``excess_rotations (N, J, 3)`` radians,
    ``global_scale (N,)``, ``global_rotation (N, 3, 3)``, ``global_translation (N, 3)`` (canonical -> world),
    ``K (N, 3, 3)`` pixels, ``camera_rotation (N, 3, 3)``, ``camera_translation (N, 3)`` (OpenCV world -> camera),
    ``posed_vertices (N, V, 3) float32`` metres world frame, ``pose_family (N,) str``, ``view_type (N,) str``;
    plus the training-format render shard(s) under ``render/`` (exact P/Q/occupancy) and the asset ``toy.glb``.
    """
    import cv2

    from bat3r_core.rig_io import save_rig_glb
    from bat3r_core.render.runner import render_jobs
    from bat3r_core.shards import list_shards, read_shard
    from bat3r_core.toy import TOY_COATS, build_toy_rig

    out_dir = Path(out_dir)
    gt_dir = Path(ground_truth_dir) if ground_truth_dir is not None else _default_gt_dir(out_dir)
    if gt_dir.resolve() == out_dir.resolve() or out_dir.resolve() in gt_dir.resolve().parents:
        raise ValueError(f"ground_truth_dir {gt_dir} must be outside the collection folder {out_dir}")
    config = render_config(config)
    prior = prior or CameraPriorConfig()
    params = _params(n, seed, resolution, config, families, prior)
    if not force:
        existing = _load_existing(out_dir, gt_dir, params)
        if existing is not None:
            return existing
    for d in (out_dir / "images", out_dir / "masks", gt_dir):
        if d.exists():
            shutil.rmtree(d)
    (out_dir / "images").mkdir(parents=True)
    (out_dir / "masks").mkdir(parents=True)
    gt_dir.mkdir(parents=True)
    rig = build_toy_rig()
    asset = save_rig_glb(rig, gt_dir / "toy.glb")
    jobs, fams, verts = toy_collection_jobs(n, seed, resolution, prior, families, rig=rig)
    assets = SceneAssets(asset=str(asset), textures=tuple(f"toy:{c}" for c in TOY_COATS))
    render_jobs(jobs, assets, gt_dir / "render", config, shard_size=max(config.recycle_every, 1), rig=rig)
    by_id = {j.sample_id: k for k, j in enumerate(jobs)}
    kept: list[int] = []
    for index in list_shards(gt_dir / "render"):
        table, arrays = read_shard(gt_dir / "render", index)
        for r, (sid, status) in enumerate(zip(table.column("sample_id").to_pylist(),
                                              table.column("status").to_pylist())):
            if status != "ok":
                continue
            cv2.imwrite(str(out_dir / "images" / f"{sid}.png"), arrays["rgb"][r][..., ::-1])
            cv2.imwrite(str(out_dir / "masks" / f"{sid}.png"), arrays["mask"][r].astype(np.uint8) * 255)
            kept.append(by_id[sid])
    kept_jobs = [jobs[k] for k in kept]
    np.savez(gt_dir / _GT_FILE,
             sample_id=np.array([j.sample_id for j in kept_jobs], dtype=str),
             excess_rotations=np.array([j.excess_rotations for j in kept_jobs]).reshape(len(kept), -1, 3),
             global_scale=np.array([j.global_scale for j in kept_jobs], dtype=np.float64),
             global_rotation=np.array([j.global_rotation for j in kept_jobs]).reshape(len(kept), 3, 3),
             global_translation=np.array([j.global_translation for j in kept_jobs]).reshape(len(kept), 3),
             K=np.array([j.camera.K for j in kept_jobs]).reshape(len(kept), 3, 3),
             camera_rotation=np.array([j.camera.R for j in kept_jobs]).reshape(len(kept), 3, 3),
             camera_translation=np.array([j.camera.t for j in kept_jobs]).reshape(len(kept), 3),
             posed_vertices=verts[kept].astype(np.float32),
             pose_family=np.array([fams[k] for k in kept], dtype=str),
             view_type=np.array([j.view_type for j in kept_jobs], dtype=str))
    ids = tuple(j.sample_id for j in kept_jobs)
    # the stamp goes last: its presence marks a complete collection
    (gt_dir / _STAMP).write_text(json.dumps({"params": params, "sample_ids": list(ids)}, indent=1))
    (out_dir / _STAMP).write_text(json.dumps({"kind": "toy_collection", "n_images": len(ids),
                                              "resolution": int(resolution)}, indent=1))
    return ToyCollection(out_dir / "images", out_dir / "masks", gt_dir, ids, reused=False)


def ensure_toy_collection(out_dir: str | os.PathLike, n: int, seed: int = 0, resolution: int = 128,
                          config: RenderConfig | str | None = "demo", **kwargs) -> ToyCollection:
    """:func:`make_toy_collection` that reuses a matching cached collection (generated on first use)."""
    return make_toy_collection(out_dir, n, seed, resolution, config, force=False, **kwargs)


def toy_collection_and_test_split(root: str | os.PathLike, n: int, n_test: int, seed: int = 0,
                                  resolution: int = 128, config: RenderConfig | str | None = "demo"
                                  ) -> tuple[ToyCollection, ToyCollection]:
    """The toy category's collection (``root/toy_collection``) and its test split (``root/toy_test``, seed
    ``seed + TOY_TEST_SEED_OFFSET``), each with its ``*_ground_truth`` folder beside it; cached."""
    root = Path(root)
    train = ensure_toy_collection(root / "toy_collection", n, seed, resolution, config)
    test = ensure_toy_collection(root / "toy_test", n_test, seed + TOY_TEST_SEED_OFFSET, resolution, config)
    return train, test


def collection_toy_command(n: int, out: str | os.PathLike, seed: int = 0, resolution: int = 128,
                           config: RenderConfig | str | None = "demo", force: bool = False) -> ToyCollection:
    """``bat3r collection toy --n N --out DIR``: render (or reuse) a toy collection in ``DIR`` with its ground
    truth in ``DIR_ground_truth``."""
    return make_toy_collection(out, n, seed, resolution, config, force=force)


def raw_image_shard(rig: Rig, fit_dir: str | os.PathLike, collection_dir: str | os.PathLike, index: int,
                    out_dir: str | os.PathLike, num_layers: int = 4):
    """The raw-image baseline's training shard: the collection's own crops (RGB, mask) of collection shard
    ``index`` with pseudo-labels ray-cast from their fits (fit shard ``index``: θ and the recovered camera of the
    crop), without re-rendering. Rows that were not fitted, or whose fit has no camera, get status ``no_fit``.

    Writes shard ``index`` of ``out_dir`` in the training-shard format (docs/CONVENTIONS.md) and returns its
    :class:`~bat3r_core.shards.ShardPaths`.
    """
    from bat3r_core.fitting.io import camera_from_row
    from bat3r_core.pointmaps import encode_float16, storage_dtype
    from bat3r_core.render.runner import label_job
    from bat3r_core.shards import read_shard, write_shard

    fits = {r["sample_id"]: r for r in read_shard(fit_dir, index, with_arrays=False)[0].to_pylist()}
    table, arrays = read_shard(collection_dir, index)
    rows_in = table.to_pylist()
    n, res = len(rows_in), arrays["rgb"].shape[1]
    dtype = storage_dtype(rig.rest_vertices)
    out = {"rgb": arrays["rgb"].copy(), "mask": arrays["mask"].astype(bool).copy(),
           "P": np.zeros((n, res, res, num_layers, 3), dtype), "Q": np.zeros((n, res, res, num_layers, 3), dtype),
           "occupancy": np.zeros((n, res, res, num_layers), bool), "object_depth": np.zeros(n, np.float32),
           "K_intrinsics": np.zeros((n, 3, 3), np.float32)}
    rows = []
    for i, src in enumerate(rows_in):
        row = {"sample_id": src["sample_id"], "source_id": src["sample_id"], "view_kind": "raw_image",
               "status": src["status"], "reason": src["reason"]}
        fit = fits.get(src["sample_id"])
        camera = None if fit is None else camera_from_row(fit)
        if row["status"] == "ok" and camera is None:
            row["status"], row["reason"] = "no_fit", "no fitted mesh with a recovered camera for this image"
        if row["status"] == "ok":
            theta = np.asarray(fit["excess_rotations"], dtype=np.float64).reshape(-1, 3)
            _, maps = label_job(rig, RenderJob(sample_id=src["sample_id"], excess_rotations=theta, camera=camera),
                                num_layers)
            if maps.status != "ok":
                row["status"], row["reason"] = maps.status, maps.reason
            else:
                out["P"][i], out["Q"][i] = encode_float16(maps.P, maps.Q, maps.occupancy,
                                                          np.float64(maps.object_depth), dtype)
                out["occupancy"][i] = maps.occupancy
                out["object_depth"][i] = maps.object_depth
                out["K_intrinsics"][i] = camera.K
        rows.append(row)
    return write_shard(out_dir, index, rows, out)
