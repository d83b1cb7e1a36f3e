"""Viewpoint augmentation: new cameras around each fitted mesh, as render jobs.

For each fitted instance the base view type (front / left / right / rear, by body-frame azimuth, see
:mod:`bat3r_core.viewpoints`) is read from the fitted camera. ``N`` extra views are added, ``N = 2`` with
probability 0.65 for a lateral base view and 0.35 for a frontal or rear one (else ``N = 1``). Each extra view's
type is drawn from a conditional table that penalises repeating the base type and favours front/rear from lateral
bases, never zero for any pair (:data:`VIEW_TRANSITIONS`; the front row is the reference's). Within the drawn type
the azimuth is uniform over the type's range, elevation and roll come from that type's Student's t, and the camera
is framed around the fitted mesh with a relative margin ``U(0.1, 0.25)`` (:func:`bat3r_core.viewpoints.frame_camera`).

The estimated view keeps the recovered camera's direction (azimuth, elevation and roll in the body frame) and is
framed the same way (``AugmentConfig.estimated_framing = "canonical"``): its optical axis passes through the body
origin and its principal point is where the framing centres the mesh, as in every canonical render, augmented view
and collection crop of the toy. The recovered camera itself (``"recovered"``) has the principal point at the centre
of the crop it was fitted in: its posed map's x, y are measured from another axis, and the network, which does not
see the intrinsics, is taught two answers for the same picture. Measured at 64×64: a third of the loop's renders
had the principal point 6.5 px from where every other training render has it, and the loop's test predictions were
shifted by 9.9 cm vertically on average (docs/fidelity_history.md, "At 64×64").

The world of the jobs is the canonical frame: the fitted mesh is the rig posed by θ with unit bone scales and an
identity global similarity; cameras are world → camera.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from bat3r_core.cameras import PinholeCamera
from bat3r_core.render.jobs import RenderJob
from bat3r_core.viewpoints import (VIEW_TYPES, BodyFrame, CameraPriorConfig, frame_camera, spherical_from_camera,
                                   view_type, wrap_degrees)

__all__ = ["VIEW_TRANSITIONS", "AZIMUTH_RANGES", "AugmentConfig", "base_view_type", "sample_extra_view_types",
           "plan_views", "plan_views_for_fits"]

VIEW_TRANSITIONS: dict[str, dict[str, float]] = {
    "front": {"front": 0.05, "rear": 0.15, "right": 0.40, "left": 0.40},
    "rear": {"front": 0.15, "rear": 0.05, "right": 0.40, "left": 0.40},
    "left": {"front": 0.40, "rear": 0.40, "right": 0.15, "left": 0.05},
    "right": {"front": 0.40, "rear": 0.40, "right": 0.05, "left": 0.15},
}
"""P(new view type | base view type). Front row from the reference; rear mirrors it (the other frontal/rear type
gets 0.15); lateral rows favour front and rear (0.40 each), the opposite side 0.15, the same side 0.05."""

AZIMUTH_RANGES: dict[str, tuple[float, float]] = {
    "front": (-30.0, 30.0), "left": (30.0, 150.0), "right": (-150.0, -30.0), "rear": (150.0, 210.0)}
"""Azimuth interval (degrees, half-open) of each view type; rear wraps through ±180."""


@dataclass(frozen=True)
class AugmentConfig:
    """Viewpoint augmentation settings.

    Attributes:
        p_two_lateral: P(N = 2) for a left/right base view (0.65).
        p_two_frontal: P(N = 2) for a front/rear base view (0.35).
        transitions: P(new type | base type), rows over :data:`VIEW_TYPES`, each summing to 1, all entries > 0.
        camera_prior: per-view-type elevation/roll distributions, field of view and margin range.
        width, height: image size of the augmented views (None: the base camera's).
        num_textures: texture ids are drawn uniformly from ``[0, num_textures)``.
        num_envmaps: environment maps drawn from ``[0, num_envmaps)``; 0 → ``-1`` (procedural sky).
        include_estimated: also emit the job of the estimated (fitted) camera itself (view_kind ``estimated``).
        estimated_framing: ``"canonical"``: the estimated view is the recovered camera's direction framed like the
            canonical renders (see the module docstring); ``"recovered"``: the recovered camera as it is.
        augment: add the 1–2 augmented views (False: the "no viewpoint augmentation" ablation).
    """

    p_two_lateral: float = 0.65
    p_two_frontal: float = 0.35
    transitions: dict[str, dict[str, float]] = field(default_factory=lambda: {k: dict(v) for k, v in
                                                                               VIEW_TRANSITIONS.items()})
    camera_prior: CameraPriorConfig = field(default_factory=CameraPriorConfig)
    width: int | None = None
    height: int | None = None
    num_textures: int = 1
    num_envmaps: int = 0
    include_estimated: bool = True
    estimated_framing: str = "canonical"
    augment: bool = True

    def __post_init__(self) -> None:
        for name in ("p_two_lateral", "p_two_frontal"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"AugmentConfig.{name} must be in [0, 1], got {getattr(self, name)}")
        if set(self.transitions) != set(VIEW_TYPES):
            raise ValueError(f"AugmentConfig.transitions must have one row per view type {list(VIEW_TYPES)}, "
                             f"got {sorted(self.transitions)}")
        for base, row in self.transitions.items():
            if set(row) != set(VIEW_TYPES) or min(row.values()) <= 0 or abs(sum(row.values()) - 1.0) > 1e-6:
                raise ValueError(f"AugmentConfig.transitions[{base!r}] must give every view type a probability > 0 "
                                 f"summing to 1, got {row}")
        if self.estimated_framing not in ("canonical", "recovered"):
            raise ValueError(f"AugmentConfig.estimated_framing must be 'canonical' or 'recovered', got "
                             f"{self.estimated_framing!r}")
        if self.num_textures < 1 or self.num_envmaps < 0:
            raise ValueError(f"AugmentConfig needs num_textures >= 1 and num_envmaps >= 0, got "
                             f"{self.num_textures}, {self.num_envmaps}")
        if (self.width is None) != (self.height is None) or (self.width is not None and min(self.width,
                                                                                            self.height) < 1):
            raise ValueError(f"AugmentConfig.width and height must both be None or both >= 1, got "
                             f"{self.width}, {self.height}")


def base_view_type(frame: BodyFrame, camera_rotation: np.ndarray) -> tuple[str, float]:
    """View type and azimuth (degrees) of a camera from its rotation alone: the direction from the body towards the
    camera is minus its optical axis (``−R[2]`` in world coordinates), so the translation is not needed.

    Args:
        frame: the body frame of the fitted (posed) mesh, world frame.
        camera_rotation: (3, 3) world → camera.
    """
    R = np.asarray(camera_rotation, dtype=np.float64)
    if R.shape != (3, 3) or not np.isfinite(R).all():
        raise ValueError(f"camera_rotation must be a finite (3, 3) matrix, got shape {R.shape}")
    d = frame.rotation.T @ (-R[2])  # body coordinates (left, up, forward)
    az = float(wrap_degrees(np.degrees(np.arctan2(d[0], d[2]))))
    return str(view_type(az)), az


def sample_extra_view_types(base: str, config: AugmentConfig, rng: np.random.Generator) -> list[str]:
    """``N ∈ {1, 2}`` new view types for a base view type (see the module docstring)."""
    if base not in VIEW_TYPES:
        raise ValueError(f"base must be one of {VIEW_TYPES}, got {base!r}")
    p_two = config.p_two_lateral if base in ("left", "right") else config.p_two_frontal
    n = 2 if rng.random() < p_two else 1
    row = config.transitions[base]
    p = np.array([row[t] for t in VIEW_TYPES])
    return [VIEW_TYPES[int(i)] for i in rng.choice(len(VIEW_TYPES), size=n, p=p / p.sum())]


def _draw(prior, rng: np.random.Generator) -> float:
    z = rng.standard_t(prior.df) if prior.df is not None else rng.standard_normal()
    return float(prior.loc + prior.scale * z)


def _new_view(vertices: np.ndarray, frame: BodyFrame, vtype: str, config: AugmentConfig, width: int, height: int,
              rng: np.random.Generator):
    lo, hi = AZIMUTH_RANGES[vtype]
    az = float(wrap_degrees(rng.uniform(lo, hi)))
    prior = config.camera_prior.prior_for(vtype)
    el = _draw(prior.elevation, rng)
    while abs(el) >= config.camera_prior.max_abs_elevation_deg:
        el = _draw(prior.elevation, rng)
    roll = float(wrap_degrees(_draw(prior.roll, rng)))
    margin = float(rng.uniform(*config.camera_prior.margin_range))
    return frame_camera(vertices, frame, az, el, roll, config.camera_prior.fov_deg, width, height, margin)


def plan_views(source_id: str, excess_rotations: np.ndarray, world_vertices: np.ndarray, frame: BodyFrame,
               camera: PinholeCamera, config: AugmentConfig, rng: np.random.Generator) -> list[RenderJob]:
    """Render jobs for one fitted instance: its estimated view (optional) and 1–2 augmented views.

    Args:
        source_id: the fitted collection sample's id (job ids are ``<source_id>-est``, ``<source_id>-aug<k>``).
        excess_rotations: (J, 3) fitted θ, radians.
        world_vertices: (V, 3) the rig posed by θ with unit bone scales, metres, world (= canonical) frame.
        frame: body frame of that posed mesh.
        camera: the recovered camera (intrinsics of the input image, world → camera).
        rng: seeded generator (every random choice of this instance).
    """
    if not isinstance(camera, PinholeCamera):
        raise TypeError(f"camera must be a PinholeCamera, got {type(camera).__name__}")
    theta = np.asarray(excess_rotations, dtype=np.float64)
    base, _ = base_view_type(frame, camera.R)
    width = config.width or camera.width
    height = config.height or camera.height

    def job(sample_id: str, kind: str, vtype: str, cam: PinholeCamera) -> RenderJob:
        return RenderJob(sample_id=sample_id, excess_rotations=theta, camera=cam, source_id=str(source_id),
                         view_kind=kind, view_type=vtype, texture_id=int(rng.integers(config.num_textures)),
                         envmap_id=int(rng.integers(config.num_envmaps)) if config.num_envmaps else -1,
                         envmap_rotation=float(rng.uniform(0.0, 2.0 * np.pi)),
                         seed=int(rng.integers(0, np.iinfo(np.int64).max)))

    jobs = []
    if config.include_estimated:
        estimated = camera
        if config.estimated_framing == "canonical":
            c = spherical_from_camera(frame, camera)
            margin = float(rng.uniform(*config.camera_prior.margin_range))
            estimated = frame_camera(world_vertices, frame, c.azimuth_deg, c.elevation_deg, c.roll_deg,
                                     config.camera_prior.fov_deg, width, height, margin).camera
        jobs.append(job(f"{source_id}-est", "estimated", base, estimated))
    extra = sample_extra_view_types(base, config, rng) if config.augment else []
    for k, vtype in enumerate(extra):
        vp = _new_view(world_vertices, frame, vtype, config, width, height, rng)
        jobs.append(job(f"{source_id}-aug{k}", "augmented", vp.view_type, vp.camera))
    return jobs


def plan_views_for_fits(rig, rows: list[dict], frame_joints: dict, config: AugmentConfig, seed: int
                        ) -> list[RenderJob]:
    """Render jobs for every fitted row (fit shard rows, :func:`bat3r_core.fitting.io.fit_rows`) with a camera.

    Args:
        rig: the :class:`bat3r_core.rig.Rig` that was fitted.
        rows: fit rows; rows whose status is not ``"ok"`` or that have no camera are skipped.
        frame_joints: body-frame joint names as the catalog gives them:
            ``{"origin": name, "forward": (tail_side, head_side), "horizontal": (left, right)}``.
        seed: base seed; instance ``k``'s choices use ``default_rng([seed, k])`` (reproducible per row).
    """
    import torch

    from bat3r_core.skinning import skin
    from bat3r_core.viewpoints import body_frame

    from .io import camera_from_row

    idx = {n: i for i, n in enumerate(rig.joint_names)}
    try:
        origin = idx[frame_joints["origin"]]
        forward = tuple(idx[n] for n in frame_joints["forward"])
        horizontal = tuple(idx[n] for n in frame_joints["horizontal"])
    except KeyError as e:
        raise ValueError(f"frame_joints names a joint the rig does not have or misses a key: {e}; joints: "
                         f"{list(rig.joint_names)}") from None
    usable = [(k, r, camera_from_row(r)) for k, r in enumerate(rows)]
    usable = [(k, r, c) for k, r, c in usable if c is not None]
    if not usable:
        return []
    theta = np.stack([np.asarray(r["excess_rotations"], dtype=np.float64).reshape(-1, 3) for _, r, _ in usable])
    posed = skin(rig.tensors(dtype=torch.float64), torch.as_tensor(theta))
    verts, joints = posed.vertices.numpy(), posed.joints.numpy()
    jobs: list[RenderJob] = []
    for i, (k, row, cam) in enumerate(usable):
        frame = body_frame(joints[i], origin, forward, horizontal)
        jobs += plan_views(row["sample_id"], theta[i], verts[i], frame, cam, config,
                           np.random.default_rng([int(seed), k]))
    return jobs
