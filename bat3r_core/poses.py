"""Pose samplers and pose features.

* :func:`sample_random_poses` — the supplement's random-poses baseline (any rig).
* :func:`sample_toy_natural_poses` — gaits, grazing, rearing, lying, turning for the toy quadruped. It stands in
  for the poses real animals take and is used ONLY to synthesise the toy image collection and its hidden test
  ground truth; the bootstrap never sees its output except through rendered images.
* :func:`pose_features` — f_ang, f_sq, f_dist of the supplement (pose clustering and complexity bins).
* :func:`mean_joint_angle_deg` — how far a set of poses articulates the rig (f_ang of the non-root joints).

Rotations are excess rotations θ (axis-angle, radians) in each joint's rest frame (see
:mod:`bat3r_core.skinning`).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr, ndtri

from .config_utils import ConfigError
from .rig import Rig

__all__ = ["RandomPoseConfig", "sample_random_poses", "sample_toy_natural_poses", "TOY_POSE_FAMILIES",
           "pose_family_weights", "pose_features", "mean_joint_angle_deg"]


@dataclass(frozen=True)
class RandomPoseConfig:
    """The random-poses baseline of the supplement.

    Attributes:
        sigma1, sigma2: bounds of the pose-level complexity σ = σ1 + t (σ2 − σ1), t ~ Beta(beta_a, beta_b).
        beta_a, beta_b: Beta parameters of t (1, 3).
        max_angle: truncation of the half-normal angle (π).
        discard_quantile: poses whose mean angular deviation lies above this quantile are discarded (0.75).
        include_root: also rotate the root joint (False: the root's rotation is a global orientation, which the
            camera sampling already covers).
    """

    sigma1: float = 0.1
    sigma2: float = 0.5
    beta_a: float = 1.0
    beta_b: float = 3.0
    max_angle: float = float(np.pi)
    discard_quantile: float = 0.75
    include_root: bool = False

    def __post_init__(self) -> None:
        for name in ("sigma1", "sigma2", "beta_a", "beta_b", "max_angle"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
                raise ConfigError(f"RandomPoseConfig.{name} must be a number > 0, got {v!r}")
        q = self.discard_quantile
        if isinstance(q, bool) or not isinstance(q, (int, float)) or not 0 < q <= 1:
            raise ConfigError(f"RandomPoseConfig.discard_quantile must be in (0, 1], got {q!r}")


def _unit_vectors(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    v = rng.standard_normal(shape + (3,))
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _truncated_half_normal(rng: np.random.Generator, sigma: np.ndarray, max_angle: float,
                           shape: tuple[int, ...]) -> np.ndarray:
    """Inverse-CDF samples of |N(0, σ²)| truncated at ``max_angle``; ``sigma`` broadcasts against ``shape``."""
    u = rng.random(shape)
    f_max = 2.0 * ndtr(max_angle / sigma) - 1.0  # half-normal CDF at the truncation point
    return sigma * ndtri(0.5 * (1.0 + u * f_max))


def sample_random_poses(rig: Rig, n: int, seed: int, config: RandomPoseConfig = RandomPoseConfig()
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Sample ``n`` random poses for ``rig``.

    Per pose: σ = σ1 + t (σ2 − σ1), t ~ Beta(1, 3); per joint an axis uniform on the sphere and an angle from
    a half-normal with scale σ truncated at π. Poses in the upper quartile of mean angular deviation (f_ang over
    the rotated joints) are discarded: ``ceil(n / q)`` candidates are drawn and the first ``n`` kept ones
    returned.

    Returns:
        excess_rotations (n, J, 3) float64 and sigmas (n,) of the kept poses.
    """
    if n <= 0:
        raise ValueError(f"n must be positive, got {n}")
    rng = np.random.default_rng(seed)
    q = config.discard_quantile
    m = int(np.ceil(n / q)) + 1
    j = rig.num_joints
    t = rng.beta(config.beta_a, config.beta_b, size=m)
    sigma = config.sigma1 + t * (config.sigma2 - config.sigma1)
    axes = _unit_vectors(rng, (m, j))
    angles = _truncated_half_normal(rng, sigma[:, None], config.max_angle, (m, j))
    theta = axes * angles[..., None]
    if not config.include_root:
        theta[:, rig.parents < 0] = 0.0
    rotated = np.ones(j, dtype=bool) if config.include_root else rig.parents >= 0
    f_ang = angles[:, rotated].mean(1)
    keep = f_ang <= np.quantile(f_ang, q)
    idx = np.flatnonzero(keep)[:n]
    return theta[idx], sigma[idx]


# --------------------------------------------------------------------------------- toy natural poses

TOY_POSE_FAMILIES = ("stand", "walk", "trot", "gallop", "graze", "rear", "lie", "turn")


def _rx(a):  # sagittal flexion: rotation about the lateral axis (+X)
    return np.array([a, 0.0, 0.0])


def _ry(a):  # yaw: rotation about the up axis (+Y)
    return np.array([0.0, a, 0.0])


def _rz(a):  # roll about the body axis (+Z)
    return np.array([0.0, 0.0, a])


def _leg_swing(phase: float, amp: float) -> tuple[float, float]:
    """(hip, knee) flexion for a leg at gait phase in [0, 1): swing forward then stance backwards."""
    s = np.sin(2 * np.pi * phase)
    lift = max(0.0, np.sin(2 * np.pi * phase + 0.6))  # the leg folds while it swings forward
    return -amp * s, amp * 1.4 * lift


def pose_family_weights(pose_families: Mapping[str, float]) -> tuple[tuple[str, ...], tuple[float, ...]]:
    """A ``pose_families`` mapping (toy pose family → relative frequency, e.g. the catalog's) as the ``families``
    and ``weights`` of :func:`sample_toy_natural_poses`. ValueError for an empty mapping, an unknown family, or
    frequencies that are not finite numbers >= 0 with a positive sum."""
    if not isinstance(pose_families, Mapping) or not pose_families:
        raise ValueError("expected a non-empty mapping of pose family -> relative frequency, got "
                         f"{pose_families!r}")
    unknown = sorted(set(pose_families) - set(TOY_POSE_FAMILIES))
    if unknown:
        raise ValueError(f"unknown pose families {unknown}; choose from {list(TOY_POSE_FAMILIES)}")
    weights = tuple(pose_families.values())
    if (not all(isinstance(w, (int, float)) and not isinstance(w, bool) and np.isfinite(w) and w >= 0
                for w in weights) or sum(weights) <= 0):
        raise ValueError(f"expected relative frequencies >= 0 with a positive sum, got {dict(pose_families)!r}")
    return tuple(pose_families), tuple(float(w) for w in weights)


def sample_toy_natural_poses(n: int, seed: int, families: tuple[str, ...] = TOY_POSE_FAMILIES,
                             weights: tuple[float, ...] | None = None) -> tuple[np.ndarray, list[str]]:
    """Natural poses of the toy quadruped (joints as in :data:`bat3r_core.toy.TOY_JOINTS`).

    Families: standing, walk/trot/gallop gait phases (diagonal and transverse leg pairs), grazing (neck and head
    down), rearing (body pitched up, hind legs flexed), lying (legs folded), turning (spine and neck yaw), each
    with random head, neck and tail motion. For hold-out evaluation only; never used to train.

    Args:
        families: the families drawn from. weights: their relative frequencies (one per family; None: uniform),
            e.g. to widen a collection towards the poses furthest from the rest pose (catalog ``pose_families``).

    Returns:
        excess_rotations (n, 27, 3) float64 and the family name of each pose.
    """
    from .toy import TOY_JOINTS

    unknown = [f for f in families if f not in TOY_POSE_FAMILIES]
    if unknown:
        raise ValueError(f"unknown pose families {unknown}; choose from {TOY_POSE_FAMILIES}")
    if n <= 0:
        raise ValueError(f"n must be positive, got {n}")
    p = None
    if weights is not None:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (len(families),) or not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
            raise ValueError(f"weights must be {len(families)} non-negative numbers (one per family of "
                             f"{tuple(families)}) with a positive sum, got {tuple(weights)!r}")
        p = w / w.sum()
    rng = np.random.default_rng(seed)
    idx = {name: i for i, name in enumerate(TOY_JOINTS)}
    out = np.zeros((n, len(TOY_JOINTS), 3))
    names: list[str] = []
    for k in range(n):
        fam = str(rng.choice(families, p=p))
        names.append(fam)
        th = out[k]

        def add(joint: str, rot: np.ndarray) -> None:
            th[idx[joint]] += rot

        legs = {"front.L": ("upper_arm.L", "forearm.L", "cannon_front.L"),
                "front.R": ("upper_arm.R", "forearm.R", "cannon_front.R"),
                "hind.L": ("thigh.L", "shin.L", "cannon_hind.L"),
                "hind.R": ("thigh.R", "shin.R", "cannon_hind.R")}
        if fam in ("walk", "trot", "gallop"):
            amp = {"walk": 0.3, "trot": 0.4, "gallop": 0.6}[fam] * rng.uniform(0.8, 1.2)
            base = rng.random()
            offs = {"walk": {"hind.L": 0.0, "front.L": 0.25, "hind.R": 0.5, "front.R": 0.75},
                    "trot": {"hind.L": 0.0, "front.R": 0.0, "hind.R": 0.5, "front.L": 0.5},
                    "gallop": {"hind.L": 0.0, "hind.R": 0.1, "front.L": 0.45, "front.R": 0.55}}[fam]
            for leg, off in offs.items():
                hip, knee = _leg_swing((base + off) % 1.0, amp)
                a, b, c = legs[leg]
                add(a, _rx(hip))
                if leg.startswith("front"):  # elbow slightly forward, carpus folds the cannon back
                    add(b, _rx(-0.3 * knee))
                    add(c, _rx(1.2 * knee))
                else:  # stifle folds the gaskin back, the hock brings the cannon forward
                    add(b, _rx(0.7 * knee))
                    add(c, _rx(-1.1 * knee))
            if fam == "gallop":
                add("spine.2", _rx(0.12 * np.sin(2 * np.pi * base)))
                add("neck.1", _rx(-0.25 * np.sin(2 * np.pi * base)))
        elif fam == "graze":
            add("neck.1", _rx(rng.uniform(0.6, 0.9)))
            add("neck.2", _rx(rng.uniform(0.3, 0.6)))
            add("head", _rx(rng.uniform(0.1, 0.4)))
            front = rng.uniform(-0.15, 0.15)
            add("upper_arm.L", _rx(front))
            add("upper_arm.R", _rx(-front))
        elif fam == "rear":
            pitch = rng.uniform(0.5, 0.9)
            add("root", _rx(-pitch))
            for s in ("L", "R"):
                add(f"thigh.{s}", _rx(pitch * rng.uniform(0.7, 1.0)))
                add(f"shin.{s}", _rx(-0.3))
                add(f"upper_arm.{s}", _rx(-rng.uniform(0.3, 0.9)))
                add(f"forearm.{s}", _rx(rng.uniform(0.8, 1.5)))
                add(f"cannon_front.{s}", _rx(-0.3))
            add("neck.1", _rx(-rng.uniform(0.0, 0.3)))
        elif fam == "lie":
            for s in ("L", "R"):
                add(f"upper_arm.{s}", _rx(-rng.uniform(0.3, 0.6)))
                add(f"forearm.{s}", _rx(rng.uniform(1.8, 2.3)))
                add(f"cannon_front.{s}", _rx(-rng.uniform(0.2, 0.5)))
                add(f"thigh.{s}", _rx(-rng.uniform(0.6, 0.9)))
                add(f"shin.{s}", _rx(rng.uniform(1.6, 2.0)))
                add(f"cannon_hind.{s}", _rx(-rng.uniform(1.4, 1.8)))
            add("neck.1", _rx(rng.uniform(-0.3, 0.3)))
        elif fam == "turn":
            yaw = rng.uniform(0.05, 0.15) * rng.choice([-1.0, 1.0])
            for jn in ("spine.1", "spine.2", "spine.3"):
                add(jn, _ry(yaw))
            add("neck.1", _ry(1.5 * yaw))
            add("neck.2", _ry(1.5 * yaw))
            add("head", _rz(rng.uniform(-0.2, 0.2)))
        # head, neck and tail motion for every family
        add("neck.2", _rx(rng.normal(0.0, 0.12)) + _ry(rng.normal(0.0, 0.12)))
        add("head", _rx(rng.normal(0.0, 0.15)) + _ry(rng.normal(0.0, 0.1)))
        tail_up = rng.uniform(-0.2, 0.9) if fam != "lie" else rng.uniform(-0.2, 0.2)
        tail_side = rng.normal(0.0, 0.25)
        for i, jn in enumerate(("tail.1", "tail.2", "tail.3", "tail.4")):
            add(jn, _rx(-tail_up / (i + 1)) + _ry(tail_side / 2))
    return out, names


# ------------------------------------------------------------------------------------------- features


def pose_features(excess_rotations: np.ndarray, posed_joints: np.ndarray, rest_joints: np.ndarray,
                  exclude: np.ndarray | None = None) -> np.ndarray:
    """Pose features ``[f_ang, f_sq, f_dist]`` of the supplement.

    f_ang = mean_j ‖θ_j‖, f_sq = mean_j ‖θ_j‖², f_dist = Σ_j ‖T_align(x_j(θ)) − x^c_j‖ with T_align the rigid
    (rotation + translation) Kabsch alignment of the posed joints onto the rest joints.

    Args:
        excess_rotations: (N, J, 3) axis-angle, radians.
        posed_joints: (N, J, 3) posed joint positions (any frame: the alignment removes it).
        rest_joints: (J, 3) rest joint positions.
        exclude: optional (J,) bool of joints left out of f_ang/f_sq (e.g. the root, whose rotation is a global
            orientation).
    Returns:
        (N, 3) float64.
    """
    theta = np.asarray(excess_rotations, dtype=np.float64)
    posed = np.asarray(posed_joints, dtype=np.float64)
    rest = np.asarray(rest_joints, dtype=np.float64)
    if theta.ndim != 3 or theta.shape[2] != 3:
        raise ValueError(f"excess_rotations must be (N, J, 3), got {theta.shape}")
    if posed.shape != theta.shape or rest.shape != theta.shape[1:]:
        raise ValueError(f"posed_joints must be {theta.shape} and rest_joints {theta.shape[1:]}; got "
                         f"{posed.shape} and {rest.shape}")
    keep = np.ones(theta.shape[1], dtype=bool) if exclude is None else ~np.asarray(exclude, dtype=bool)
    ang = np.linalg.norm(theta[:, keep], axis=-1)
    f_ang = ang.mean(1)
    f_sq = (ang ** 2).mean(1)
    from .metrics import kabsch

    f_dist = np.array([np.linalg.norm(kabsch(posed[i], rest).apply(posed[i]) - rest, axis=1).sum()
                       for i in range(len(theta))])
    return np.stack([f_ang, f_sq, f_dist], 1)


def mean_joint_angle_deg(poses) -> float:
    """Mean rotation angle, degrees, of the non-root joints over ``poses``: each an excess rotation θ, (J, 3) or flat
    J·3 axis-angle. Joint 0 is the root (rigs keep parents before children), whose rotation overlaps the global
    one and is left out. How far a set of fits or render jobs articulates the rig away from its rest pose."""
    angles = [np.linalg.norm(np.asarray(t, dtype=np.float64).reshape(-1, 3)[1:], axis=1) for t in poses]
    if not angles:
        raise ValueError("poses is empty")
    return float(np.degrees(np.concatenate(angles)).mean())
