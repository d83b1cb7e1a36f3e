"""Generated image collections: a synthetic photo collection of any rig (or the embedded toy), rendered with Blender
and written as a user's collection (``images/*.png``, ``masks/*.png``) with its hidden ground truth in a separate
folder, cached by a JSON stamp (:func:`make_collection`, :func:`ensure_collection`; the toy's
:func:`make_toy_collection`). The render jobs come from :func:`bat3r_core.datasets.collection_jobs`.
"""
from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from bat3r_core.poses import TOY_POSE_FAMILIES, pose_family_weights
from bat3r_core.render.config import RenderConfig, SceneAssets, render_config
from bat3r_core.viewpoints import CameraPriorConfig

from bat3r_core.datasets import collection_jobs

__all__ = ["GeneratedCollection", "ToyCollection", "make_collection", "make_toy_collection", "ensure_collection",
           "ensure_toy_collection", "toy_collection_and_test_split", "collection_toy_command",
           "collection_drops_record", "TOY_TEST_SEED_OFFSET"]

TOY_TEST_SEED_OFFSET = 1_000_003
"""The toy test split uses ``seed + TOY_TEST_SEED_OFFSET``."""
_STAMP = "collection.json"
_GT_FILE = "ground_truth.npz"


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
                    config: RenderConfig | Mapping | None = None, ground_truth_dir: str | os.PathLike | None = None,
                    families: Sequence[str] = TOY_POSE_FAMILIES, prior: CameraPriorConfig | None = None,
                    force: bool = False, *, asset: str | os.PathLike | None = None,
                    body_frame: Mapping | None = None, textures: Sequence[str] | None = None,
                    envmaps: Sequence[str] = (), pose_sampler: str | None = None, prefix: str | None = None,
                    pose_families: Mapping[str, float] | None = None) -> GeneratedCollection:
    """Render a synthetic image collection (cached: reused when the JSON stamp's parameters match, unless
    ``force``).

    The subject: ``asset`` None is the embedded toy (built in-process, saved as ``toy.glb``; default pose sampler
    ``toy_natural``, body frame :data:`bat3r_core.toy.TOY_BODY_FRAME`, the four procedural coats); otherwise the
    rigged GLB ``asset`` (e.g. ``Catalog.asset_path(category)``, the normalised asset with its own texture), which
    needs ``body_frame`` (the category's joint names) and defaults to pose sampler ``random``. ``textures``: image
    files or ``toy:<coat>`` entries, one per texture id; ``()`` (the default for an asset) renders the asset's own
    embedded texture. ``envmaps``: HDR/EXR files (none: a procedural sky). ``prefix``: of the sample ids
    (default ``toy``, or the asset file's stem). ``pose_families``: pose family → relative frequency for the
    ``toy_natural`` sampler (replaces ``families``; None: ``families``, uniformly), e.g. a collection widened
    towards the poses furthest from the rest pose. Poses, yaw, cameras and textures: :func:`collection_jobs`.

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
    weights = None
    if pose_families is not None:
        try:
            families, weights = pose_family_weights(pose_families)
        except ValueError as e:
            raise ValueError(f"pose_families: {e}") from None
    if asset is None:
        sampler = pose_sampler or "toy_natural"
        frame_spec = dict(body_frame or TOY_BODY_FRAME)
        texture_list = tuple(f"toy:{c}" for c in TOY_COATS) if textures is None else tuple(textures)
        prefix = prefix or "toy"
        toy_default = (sampler == "toy_natural" and body_frame is None and textures is None and not envmaps
                       and prefix == "toy" and weights is None)
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
        if weights is not None:
            source["pose_families"] = dict(zip(families, weights))
    if weights is not None and sampler != "toy_natural":
        raise ValueError(f"pose_families: only pose_sampler 'toy_natural' has pose families (pose_sampler is "
                         f"{sampler!r})")
    params = _params(n, seed, resolution, config, families, prior, source)
    if not force:
        existing = _load_existing(out_dir, gt_dir, params)
        if existing is not None:
            return existing
    # the jobs first: a rig, body frame or sampler they cannot be made for leaves a cached collection in place
    rig = build_toy_rig() if asset is None else load_rig(asset)
    jobs, fams, verts = collection_jobs(rig, n, seed, frame_spec, resolution, prior, sampler, families,
                                        num_textures=max(len(texture_list), 1), num_envmaps=len(envmaps),
                                        prefix=prefix, family_weights=weights)
    for d in (out_dir / "images", out_dir / "masks", gt_dir):
        if d.exists():
            shutil.rmtree(d)
    (out_dir / "images").mkdir(parents=True)
    (out_dir / "masks").mkdir(parents=True)
    gt_dir.mkdir(parents=True)
    glb = save_rig_glb(rig, gt_dir / "toy.glb") if asset is None else Path(shutil.copy2(asset, gt_dir / asset.name))
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
                        config: RenderConfig | Mapping | None = None, ground_truth_dir: str | os.PathLike | None = None,
                        families: Sequence[str] = TOY_POSE_FAMILIES, prior: CameraPriorConfig | None = None,
                        force: bool = False) -> GeneratedCollection:
    """:func:`make_collection` of the embedded toy in natural poses with its procedural coats (see there for the
    layout)."""
    return make_collection(out_dir, n, seed, resolution, config, ground_truth_dir, families, prior, force)


def ensure_collection(out_dir: str | os.PathLike, n: int, seed: int = 0, resolution: int = 128,
                      config: RenderConfig | Mapping | None = None, **kwargs) -> GeneratedCollection:
    """:func:`make_collection` that reuses a matching cached collection (generated on first use)."""
    return make_collection(out_dir, n, seed, resolution, config, force=False, **kwargs)


def collection_drops_record(collection: GeneratedCollection, stage: str = "generated_collection") -> dict:
    """The task record of a generated collection's renders (``bat3r_core.runs.folder_record`` over the hidden
    ``render/`` shards: jobs rendered, kept, and the failed ones with their status, reason and shard), for the
    dropped-sample report."""
    from bat3r_core.runs import folder_record

    return folder_record(stage, collection.ground_truth_dir / "render")


def ensure_toy_collection(out_dir: str | os.PathLike, n: int, seed: int = 0, resolution: int = 128,
                          config: RenderConfig | Mapping | None = None, **kwargs) -> GeneratedCollection:
    """:func:`make_toy_collection` that reuses a matching cached collection (generated on first use)."""
    return make_toy_collection(out_dir, n, seed, resolution, config, force=False, **kwargs)


def toy_collection_and_test_split(root: str | os.PathLike, n: int, n_test: int, seed: int = 0,
                                  resolution: int = 128, config: RenderConfig | Mapping | None = None
                                  ) -> tuple[GeneratedCollection, GeneratedCollection]:
    """The toy category's collection (``root/toy_collection``) and its test split (``root/toy_test``, seed
    ``seed + TOY_TEST_SEED_OFFSET``), each with its ``*_ground_truth`` folder beside it; cached."""
    root = Path(root)
    train = ensure_toy_collection(root / "toy_collection", n, seed, resolution, config)
    test = ensure_toy_collection(root / "toy_test", n_test, seed + TOY_TEST_SEED_OFFSET, resolution, config)
    return train, test


def collection_toy_command(n: int, out: str | os.PathLike, seed: int = 0, resolution: int = 128,
                           config: RenderConfig | Mapping | None = None, force: bool = False) -> GeneratedCollection:
    """``bat3r collection toy --n N --out DIR``: render (or reuse) a toy collection in ``DIR`` with its ground
    truth in ``DIR_ground_truth``."""
    return make_toy_collection(out, n, seed, resolution, config, force=force)
