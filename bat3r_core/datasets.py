"""Render-job builders for the training sets, and the toy image collection.

* :func:`canonical_jobs` — iteration 0: ``n`` viewpoints around the rest-pose mesh from the camera prior
  (Student's t or Normal, :class:`bat3r_core.viewpoints.CameraPriorConfig`), random texture, environment map,
  rotation and seed.
* :func:`random_pose_jobs` — the random-poses baseline: poses from :func:`bat3r_core.poses.sample_random_poses`,
  Student's t cameras around each posed mesh.
* :func:`collection_jobs` / :func:`make_collection` — a synthetic photo collection of any rig: posed by a pose
  sampler (``random``: :func:`bat3r_core.poses.sample_random_poses`, any rig; ``toy_natural``: the toy's gaits,
  grazing, rearing, … of :func:`bat3r_core.poses.sample_toy_natural_poses`), a random yaw, one camera from the
  camera prior around each posed mesh (the category's body frame), a random texture; written as a user's photo
  collection (``images/*.png``, ``masks/*.png``) with its hidden ground truth in a separate folder; cached by a
  JSON stamp. :func:`make_toy_collection` / :func:`toy_collection_jobs` are the embedded toy's (natural poses,
  procedural coats).

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

__all__ = ["canonical_jobs", "random_pose_jobs", "collection_jobs", "toy_collection_jobs", "make_collection",
           "make_toy_collection", "ensure_collection", "ensure_toy_collection", "toy_collection_and_test_split",
           "collection_toy_command", "GeneratedCollection", "ToyCollection", "collection_drops_record",
           "rig_body_frame", "POSE_SAMPLERS", "TOY_TEST_SEED_OFFSET"]

POSE_SAMPLERS = ("random", "toy_natural")
"""Pose samplers of generated collections: ``random`` (any rig) and ``toy_natural`` (the toy's joints only)."""

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


def _collection_poses(rig: Rig, n: int, seed: int, pose_sampler: str, families: Sequence[str],
                      pose_config: RandomPoseConfig) -> tuple[np.ndarray, list[str]]:
    """θ (n, J, 3) and a pose family per pose (``random`` for the random sampler)."""
    if pose_sampler == "toy_natural":
        from bat3r_core.toy import TOY_JOINTS

        if tuple(rig.joint_names) != tuple(TOY_JOINTS):
            raise ValueError(f"pose_sampler 'toy_natural' poses the toy's {len(TOY_JOINTS)} joints "
                             f"({', '.join(TOY_JOINTS[:4])}, ...); this rig has {rig.num_joints} joints "
                             f"({', '.join(rig.joint_names[:4])}, ...): use pose_sampler 'random'")
        theta, fams = sample_toy_natural_poses(n, seed, tuple(families))
        return theta, list(fams)
    if pose_sampler == "random":
        theta, _ = sample_random_poses(rig, n, seed, pose_config)
        return theta, ["random"] * n
    raise ValueError(f"pose_sampler must be one of {list(POSE_SAMPLERS)}, got {pose_sampler!r}")


def collection_jobs(rig: Rig, n: int, seed: int, body_frame_spec: Mapping, resolution: int = 128,
                    prior: CameraPriorConfig | None = None, pose_sampler: str = "random",
                    families: Sequence[str] = TOY_POSE_FAMILIES, num_textures: int = 1, num_envmaps: int = 0,
                    prefix: str = "collection", pose_config: RandomPoseConfig = RandomPoseConfig()
                    ) -> tuple[list[RenderJob], list[str], np.ndarray]:
    """Jobs of a synthetic image collection of ``rig``: poses from ``pose_sampler`` (``random`` or
    ``toy_natural``, which takes ``families``), a random yaw ``U[-pi, pi)`` about +Y as the global rotation, one
    camera per image from ``prior`` (default: the reference Student's t per view type) around the posed mesh in
    the body frame of its posed joints (``body_frame_spec``: ``{"origin", "forward", "horizontal"}`` joint
    names), and a random texture (``[0, num_textures)``) and environment map (``-1``, a procedural sky, when
    ``num_envmaps == 0``). Seeded: the same arguments give the same jobs.

    Returns:
        (jobs, pose family per job, posed vertices (n, V, 3) float64 in the world frame).
    """
    _check_common(n, resolution, num_textures, num_envmaps)
    prior = prior or CameraPriorConfig()
    theta, fams = _collection_poses(rig, n, seed, pose_sampler, families, pose_config)
    rng = np.random.default_rng([seed, 0x70])
    yaws = rng.uniform(-math.pi, math.pi, size=n)
    rot = np.stack([_yaw(a) for a in yaws])
    verts, joints = _skin(rig, theta, rot)
    jobs = []
    for i in range(n):
        frame = rig_body_frame(rig, joints[i], body_frame_spec)
        (view,) = sample_viewpoints(verts[i], frame, 1, prior, resolution, resolution, rng)
        jobs.append(RenderJob(sample_id=f"{prefix}-{i:05d}", excess_rotations=theta[i], camera=view.camera,
                              global_rotation=rot[i], view_kind="collection", view_type=str(view.view_type),
                              **_appearance(rng, num_textures, num_envmaps)))
    return jobs, fams, verts


def toy_collection_jobs(n: int, seed: int, resolution: int = 128, prior: CameraPriorConfig | None = None,
                        families: Sequence[str] = TOY_POSE_FAMILIES, prefix: str = "toy", rig: Rig | None = None
                        ) -> tuple[list[RenderJob], list[str], np.ndarray]:
    """:func:`collection_jobs` of the embedded toy: natural poses, the toy's body frame, a random procedural coat
    (:data:`bat3r_core.toy.TOY_COATS`) and a procedural sky.

    Returns:
        (jobs, pose family per job, posed vertices (n, V, 3) float64 in the world frame).
    """
    from bat3r_core.toy import TOY_BODY_FRAME, TOY_COATS, build_toy_rig

    return collection_jobs(rig or build_toy_rig(), n, seed, TOY_BODY_FRAME, resolution, prior, "toy_natural",
                           families, num_textures=len(TOY_COATS), num_envmaps=0, prefix=prefix)


@dataclass(frozen=True)
class GeneratedCollection:
    """A generated image collection on disk.

    Attributes:
        images_dir: ``<out>/images`` with ``<sample_id>.png`` (RGB). masks_dir: ``<out>/masks`` (0/255 PNG).
        ground_truth_dir: the hidden ground truth (only evaluation reads it): ``ground_truth.npz``, the rendered
            training-format shard(s) under ``render/`` (every job, with its status; renders that failed are there
            with their reason), the asset (``toy.glb`` for the toy, else a copy of the rendered asset file) and
            ``collection.json``.
        sample_ids: the images written (renders that failed are left out).
        reused: True when an existing collection with the same parameters was found.
    """

    images_dir: Path
    masks_dir: Path
    ground_truth_dir: Path
    sample_ids: tuple[str, ...]
    reused: bool


ToyCollection = GeneratedCollection
"""The former name of :class:`GeneratedCollection`."""


def _default_gt_dir(out_dir: Path) -> Path:
    return out_dir.parent / f"{out_dir.name}_ground_truth"


def _params(n: int, seed: int, resolution: int, config: RenderConfig, families: Sequence[str],
            prior: CameraPriorConfig, source: dict | None = None) -> dict:
    """The stamp parameters; ``source`` (asset hash, body frame, textures, environment maps, pose sampler, prefix)
    for anything but the toy in natural poses, whose stamp keeps its first form (cached toy collections stay
    valid)."""
    from bat3r_core.config_utils import to_mapping

    params = {"kind": "toy_collection", "version": 1, "n": int(n), "seed": int(seed), "resolution": int(resolution),
              "render": to_mapping(config), "families": list(families), "prior": to_mapping(prior)}
    if source is not None:
        params.update(kind="generated_collection", **source)
    return params


def _load_existing(out_dir: Path, gt_dir: Path, params: dict) -> GeneratedCollection | None:
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
    return GeneratedCollection(out_dir / "images", out_dir / "masks", gt_dir, ids, reused=True)


def make_collection(out_dir: str | os.PathLike, n: int, seed: int = 0, resolution: int = 128,
                    config: RenderConfig | str | None = "demo", ground_truth_dir: str | os.PathLike | None = None,
                    families: Sequence[str] = TOY_POSE_FAMILIES, prior: CameraPriorConfig | None = None,
                    force: bool = False, *, asset: str | os.PathLike | None = None,
                    body_frame: Mapping | None = None, textures: Sequence[str] | None = None,
                    envmaps: Sequence[str] = (), pose_sampler: str | None = None, prefix: str | None = None
                    ) -> GeneratedCollection:
    """Render a synthetic image collection (cached: reused when the JSON stamp's parameters match, unless
    ``force``).

    The subject: ``asset`` None is the embedded toy (built in-process, saved as ``toy.glb``; default pose sampler
    ``toy_natural``, body frame :data:`bat3r_core.toy.TOY_BODY_FRAME`, the four procedural coats); otherwise the
    rigged GLB ``asset`` (e.g. ``Catalog.asset_path(category)``, the normalised asset with its own texture), which
    needs ``body_frame`` (the category's joint names) and defaults to pose sampler ``random``. ``textures``: image
    files or ``toy:<coat>`` entries, one per texture id; ``()`` (the default for an asset) renders the asset's own
    embedded texture. ``envmaps``: HDR/EXR files (none: a procedural sky). ``prefix``: of the sample ids
    (default ``toy``, or the asset file's stem). Poses, yaw, cameras and textures: :func:`collection_jobs`.

    Layout: ``out_dir/images/<id>.png``, ``out_dir/masks/<id>.png`` (what a user's photo collection looks like);
    the hidden ground truth goes to ``ground_truth_dir`` (default ``<out_dir>_ground_truth`` beside it):
    ``ground_truth.npz`` with ``sample_id (N,) str``, ``excess_rotations (N, J, 3)`` radians,
    ``global_scale (N,)``, ``global_rotation (N, 3, 3)``, ``global_translation (N, 3)`` (canonical -> world),
    ``K (N, 3, 3)`` pixels, ``camera_rotation (N, 3, 3)``, ``camera_translation (N, 3)`` (OpenCV world -> camera),
    ``posed_vertices (N, V, 3) float32`` metres world frame, ``pose_family (N,) str`` (``random`` for random
    poses), ``view_type (N,) str``; plus the training-format render shard(s) under ``render/`` (exact
    P/Q/occupancy; every job with its status) and the asset file. Renders that fail are left out of the images and
    the ground truth (:func:`collection_drops_record` reports them).
    """
    import cv2

    from bat3r_core.rig_io import load_rig, save_rig_glb
    from bat3r_core.render.runner import render_jobs
    from bat3r_core.shards import content_hash, list_shards, read_shard
    from bat3r_core.toy import TOY_BODY_FRAME, TOY_COATS, build_toy_rig

    out_dir = Path(out_dir)
    gt_dir = Path(ground_truth_dir) if ground_truth_dir is not None else _default_gt_dir(out_dir)
    if gt_dir.resolve() == out_dir.resolve() or out_dir.resolve() in gt_dir.resolve().parents:
        raise ValueError(f"ground_truth_dir {gt_dir} must be outside the collection folder {out_dir}")
    config = render_config(config)
    prior = prior or CameraPriorConfig()
    if asset is None:
        sampler = pose_sampler or "toy_natural"
        frame_spec = dict(body_frame or TOY_BODY_FRAME)
        texture_list = tuple(f"toy:{c}" for c in TOY_COATS) if textures is None else tuple(textures)
        prefix = prefix or "toy"
        toy_default = (sampler == "toy_natural" and body_frame is None and textures is None and not envmaps
                       and prefix == "toy")
        source = None if toy_default else {"asset": "generated:toy"}
    else:
        asset = Path(asset)
        if not asset.is_file():
            raise FileNotFoundError(f"asset {asset} does not exist (a rigged, skinned GLB: e.g. "
                                    f"Catalog.asset_path(category))")
        if body_frame is None:
            raise ValueError(f"body_frame: a generated collection of {asset.name} needs the category's body-frame "
                             f"joints ({{'origin', 'forward', 'horizontal'}})")
        sampler = pose_sampler or "random"
        frame_spec = dict(body_frame)
        texture_list = () if textures is None else tuple(textures)
        prefix = prefix or asset.stem
        source = {"asset": content_hash([asset])}
    if source is not None:
        files = [Path(t) for t in (*texture_list, *envmaps) if not str(t).startswith("toy:")]
        source.update(body_frame={k: (list(v) if isinstance(v, (list, tuple)) else v) for k, v in frame_spec.items()},
                      textures=list(texture_list), envmaps=[str(e) for e in envmaps], pose_sampler=sampler,
                      prefix=prefix, files=content_hash([f for f in files if f.is_file()]))
    params = _params(n, seed, resolution, config, families, prior, source)
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
    if asset is None:
        rig = build_toy_rig()
        glb = save_rig_glb(rig, gt_dir / "toy.glb")
    else:
        glb = Path(shutil.copy2(asset, gt_dir / asset.name))
        rig = load_rig(glb)
    jobs, fams, verts = collection_jobs(rig, n, seed, frame_spec, resolution, prior, sampler, families,
                                        num_textures=max(len(texture_list), 1), num_envmaps=len(envmaps),
                                        prefix=prefix)
    assets = SceneAssets(asset=str(glb), textures=texture_list, envmaps=tuple(str(e) for e in envmaps))
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
    (out_dir / _STAMP).write_text(json.dumps({"kind": params["kind"], "n_images": len(ids),
                                              "resolution": int(resolution)}, indent=1))
    return GeneratedCollection(out_dir / "images", out_dir / "masks", gt_dir, ids, reused=False)


def make_toy_collection(out_dir: str | os.PathLike, n: int, seed: int = 0, resolution: int = 128,
                        config: RenderConfig | str | None = "demo", ground_truth_dir: str | os.PathLike | None = None,
                        families: Sequence[str] = TOY_POSE_FAMILIES, prior: CameraPriorConfig | None = None,
                        force: bool = False) -> GeneratedCollection:
    """:func:`make_collection` of the embedded toy in natural poses with its procedural coats (see there for the
    layout)."""
    return make_collection(out_dir, n, seed, resolution, config, ground_truth_dir, families, prior, force)


def ensure_collection(out_dir: str | os.PathLike, n: int, seed: int = 0, resolution: int = 128,
                      config: RenderConfig | str | None = "demo", **kwargs) -> GeneratedCollection:
    """:func:`make_collection` that reuses a matching cached collection (generated on first use)."""
    return make_collection(out_dir, n, seed, resolution, config, force=False, **kwargs)


def collection_drops_record(collection: GeneratedCollection, stage: str = "generated_collection") -> dict:
    """The task record of a generated collection's renders (``bat3r_core.runs.folder_record`` over the hidden
    ``render/`` shards: jobs rendered, kept, and the failed ones with their status, reason and shard), for the
    dropped-sample report."""
    from bat3r_core.runs import folder_record

    return folder_record(stage, collection.ground_truth_dir / "render")


def ensure_toy_collection(out_dir: str | os.PathLike, n: int, seed: int = 0, resolution: int = 128,
                          config: RenderConfig | str | None = "demo", **kwargs) -> GeneratedCollection:
    """:func:`make_toy_collection` that reuses a matching cached collection (generated on first use)."""
    return make_toy_collection(out_dir, n, seed, resolution, config, force=False, **kwargs)


def toy_collection_and_test_split(root: str | os.PathLike, n: int, n_test: int, seed: int = 0,
                                  resolution: int = 128, config: RenderConfig | str | None = "demo"
                                  ) -> tuple[GeneratedCollection, GeneratedCollection]:
    """The toy category's collection (``root/toy_collection``) and its test split (``root/toy_test``, seed
    ``seed + TOY_TEST_SEED_OFFSET``), each with its ``*_ground_truth`` folder beside it; cached."""
    root = Path(root)
    train = ensure_toy_collection(root / "toy_collection", n, seed, resolution, config)
    test = ensure_toy_collection(root / "toy_test", n_test, seed + TOY_TEST_SEED_OFFSET, resolution, config)
    return train, test


def collection_toy_command(n: int, out: str | os.PathLike, seed: int = 0, resolution: int = 128,
                           config: RenderConfig | str | None = "demo", force: bool = False) -> GeneratedCollection:
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
    from bat3r_core.labels import label_job
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
