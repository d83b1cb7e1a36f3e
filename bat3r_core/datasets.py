"""Render-job builders for the training sets and for synthetic collections, and the body frame of a posed rig.

* :func:`canonical_jobs` — iteration 0: ``n`` viewpoints around the rest-pose mesh from the camera prior
  (Student's t or Normal, :class:`bat3r_core.viewpoints.CameraPriorConfig`), random texture, environment map,
  rotation and seed.
* :func:`random_pose_jobs` — the random-poses baseline: poses from :func:`bat3r_core.poses.sample_random_poses`,
  Student's t cameras around each posed mesh.
* :func:`collection_jobs` — a synthetic photo collection of any rig: posed by a pose sampler (``random``:
  :func:`bat3r_core.poses.sample_random_poses`, any rig; ``toy_natural``: the toy's gaits, grazing, rearing, … of
  :func:`bat3r_core.poses.sample_toy_natural_poses`), a random yaw, one camera from the camera prior around each
  posed mesh (the category's body frame), a random texture; :func:`toy_collection_jobs` is the embedded toy's
  (natural poses, procedural coats). :mod:`bat3r_core.generated_collections` renders them into a user-style
  collection with hidden ground truth; :mod:`bat3r_core.raw_images` holds the raw-image baseline.

Builders are pure and seeded: the same arguments give the same jobs. World frame of the jobs: the canonical frame
moved by each job's global similarity (identity for the canonical set and the random-poses set).
"""
from __future__ import annotations

import math
from typing import Mapping, Sequence

import numpy as np

from bat3r_core.poses import RandomPoseConfig, sample_random_poses, sample_toy_natural_poses, TOY_POSE_FAMILIES
from bat3r_core.render.jobs import RenderJob
from bat3r_core.rig import Rig
from bat3r_core.viewpoints import BodyFrame, CameraPriorConfig, body_frame, sample_viewpoints

__all__ = ["canonical_jobs", "random_pose_jobs", "collection_jobs", "toy_collection_jobs", "rig_body_frame",
           "POSE_SAMPLERS"]

POSE_SAMPLERS = ("random", "toy_natural")
"""Pose samplers of generated collections: ``random`` (any rig) and ``toy_natural`` (the toy's joints only)."""

_MOVED = {"generated_collections": ("GeneratedCollection", "ToyCollection", "make_collection", "make_toy_collection",
                                     "ensure_collection", "ensure_toy_collection", "toy_collection_and_test_split",
                                     "collection_toy_command", "collection_drops_record", "TOY_TEST_SEED_OFFSET"),
          "raw_images": ("raw_image_shard",)}


def __getattr__(name: str):
    """Generated collections moved to :mod:`bat3r_core.generated_collections` and the raw-image baseline to
    :mod:`bat3r_core.raw_images`; their names still resolve here."""
    import importlib

    for module, names in _MOVED.items():
        if name in names:
            return getattr(importlib.import_module(f"bat3r_core.{module}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


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
                      pose_config: RandomPoseConfig, family_weights: Sequence[float] | None = None
                      ) -> tuple[np.ndarray, list[str]]:
    """θ (n, J, 3) and a pose family per pose (``random`` for the random sampler)."""
    if pose_sampler == "toy_natural":
        from bat3r_core.toy import TOY_JOINTS

        if tuple(rig.joint_names) != tuple(TOY_JOINTS):
            raise ValueError(f"pose_sampler 'toy_natural' poses the toy's {len(TOY_JOINTS)} joints "
                             f"({', '.join(TOY_JOINTS[:4])}, ...); this rig has {rig.num_joints} joints "
                             f"({', '.join(rig.joint_names[:4])}, ...): use pose_sampler 'random'")
        theta, fams = sample_toy_natural_poses(n, seed, tuple(families), family_weights)
        return theta, list(fams)
    if family_weights is not None:
        raise ValueError(f"family_weights: only pose_sampler 'toy_natural' has pose families "
                         f"(pose_sampler is {pose_sampler!r})")
    if pose_sampler == "random":
        theta, _ = sample_random_poses(rig, n, seed, pose_config)
        return theta, ["random"] * n
    raise ValueError(f"pose_sampler must be one of {list(POSE_SAMPLERS)}, got {pose_sampler!r}")


def collection_jobs(rig: Rig, n: int, seed: int, body_frame_spec: Mapping, resolution: int = 128,
                    prior: CameraPriorConfig | None = None, pose_sampler: str = "random",
                    families: Sequence[str] = TOY_POSE_FAMILIES, num_textures: int = 1, num_envmaps: int = 0,
                    prefix: str = "collection", pose_config: RandomPoseConfig = RandomPoseConfig(),
                    family_weights: Sequence[float] | None = None
                    ) -> tuple[list[RenderJob], list[str], np.ndarray]:
    """Jobs of a synthetic image collection of ``rig``: poses from ``pose_sampler`` (``random`` or
    ``toy_natural``, which takes ``families`` and their relative frequencies ``family_weights``, None:
    uniform), a random yaw ``U[-pi, pi)`` about +Y as the global rotation, one
    camera per image from ``prior`` (default: the reference Student's t per view type) around the posed mesh in
    the body frame of its posed joints (``body_frame_spec``: ``{"origin", "forward", "horizontal"}`` joint
    names), and a random texture (``[0, num_textures)``) and environment map (``-1``, a procedural sky, when
    ``num_envmaps == 0``). Seeded: the same arguments give the same jobs.

    Returns:
        (jobs, pose family per job, posed vertices (n, V, 3) float64 in the world frame).
    """
    _check_common(n, resolution, num_textures, num_envmaps)
    prior = prior or CameraPriorConfig()
    theta, fams = _collection_poses(rig, n, seed, pose_sampler, families, pose_config, family_weights)
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
