"""Body-centric camera viewpoints: frame, spherical coordinates, view types, sampling and the camera prior.

Body frame (from three joint choices of the catalog, as in the paper's supplement): an origin joint (mid spine),
a forward pair ``(tail_side, head_side)`` and a horizontal pair ``(left, right)``. The axes are orthogonalised
with the forward direction kept exactly:

* ``forward`` = unit(``joints[head_side] - joints[tail_side]``)
* ``up`` = unit(``forward x (joints[left] - joints[right])``)
* ``left`` = ``up x forward``

so the frame's columns ``(left, up, forward)`` match the canonical frame of a rig (``+X`` left, ``+Y`` up,
``+Z`` forward) and a rig in its rest pose has the identity body rotation.

Spherical coordinates of a camera in that frame (degrees, metres):

* ``radius``: distance from the origin joint to the camera centre.
* ``azimuth`` in ``[-180, 180)``: ``0`` = the camera is in front of the head looking back at it (frontal view),
  ``+90`` = the camera is on the animal's **left** side (left lateral view; the animal's left flank is seen),
  ``-90`` its right side, ``+-180`` behind it (rear view). ``azimuth = atan2(d_left, d_forward)``.
* ``elevation`` in ``[-90, 90]``: positive when the camera is above the origin (looking down).
* ``roll``: rotation of the camera about its own optical axis relative to the upright camera with the same
  optical axis, whose image up (``-y``) is the projection of the body's up. A camera with rotation ``R_up``
  (upright) and roll ``rho`` has ``R = Rz(rho) @ R_up`` with ``Rz`` the rotation by ``rho`` about the camera's
  ``z``: a positive roll turns the image content clockwise on screen (x right, y down).

:func:`camera_from_spherical` places the camera at ``origin + radius * direction`` looking at the origin joint;
:func:`spherical_from_camera` inverts it exactly; for a camera that does not look at the origin, azimuth,
elevation and radius still describe its position and roll its orientation about its own optical axis.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal, Mapping

import numpy as np
from scipy import stats

from bat3r_core.cameras import PinholeCamera, look_at

VIEW_TYPES = ("front", "left", "right", "rear")
"""View types by azimuth: front [-30, 30), left [30, 150), right [-150, -30), rear otherwise."""


# ---------------------------------------------------------------------------------------------- body frame
@dataclass(frozen=True, eq=False)
class BodyFrame:
    """A body-centric frame in the world.

    Attributes:
        origin: (3,) float64, world frame, metres (the origin joint).
        rotation: (3, 3) float64, columns = (left, up, forward) unit axes in world coordinates (body -> world).
    """

    origin: np.ndarray
    rotation: np.ndarray

    @property
    def up(self) -> np.ndarray:
        return self.rotation[:, 1]

    def to_body(self, points_world: np.ndarray) -> np.ndarray:
        """(..., 3) world -> (..., 3) body coordinates (left, up, forward), metres."""
        return (np.asarray(points_world, dtype=np.float64) - self.origin) @ self.rotation

    def to_world(self, points_body: np.ndarray) -> np.ndarray:
        """(..., 3) body coordinates -> (..., 3) world, metres."""
        return np.asarray(points_body, dtype=np.float64) @ self.rotation.T + self.origin


def body_frame(joints: np.ndarray, origin: int, forward: tuple[int, int], horizontal: tuple[int, int]) -> BodyFrame:
    """Body frame from joint positions.

    Args:
        joints: (J, 3) joint positions, metres, world frame.
        origin: index of the origin joint (e.g. mid spine).
        forward: ``(a, b)`` joint indices; the forward axis points from ``a`` to ``b`` (towards the head).
        horizontal: ``(left, right)`` joint indices (e.g. left and right hip); ``left - right`` spans the
            horizontal plane together with the forward axis.
    Returns:
        BodyFrame with columns (left, up, forward).
    """
    j = np.asarray(joints, dtype=np.float64)
    if j.ndim != 2 or j.shape[1] != 3:
        raise ValueError(f"joints must have shape (J, 3), got {j.shape}")
    if not np.isfinite(j).all():
        raise ValueError("joints must be finite")
    n = j.shape[0]
    for name, idx in (("origin", (origin,)), ("forward", tuple(forward)), ("horizontal", tuple(horizontal))):
        for i in idx:
            if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not 0 <= i < n:
                raise ValueError(f"{name} joint index must be an int in [0, {n}), got {i!r}")
    f = j[forward[1]] - j[forward[0]]
    h = j[horizontal[0]] - j[horizontal[1]]
    nf = np.linalg.norm(f)
    if nf < 1e-9:
        raise ValueError(f"forward joints {tuple(forward)} coincide; cannot define the forward axis")
    f = f / nf
    up = np.cross(f, h)
    nu = np.linalg.norm(up)
    if nu < 1e-9 * max(np.linalg.norm(h), 1e-300) or np.linalg.norm(h) < 1e-9:
        raise ValueError(f"horizontal joints {tuple(horizontal)} are parallel to the forward axis or coincide")
    up = up / nu
    left = np.cross(up, f)
    return BodyFrame(origin=j[origin].copy(), rotation=np.stack([left, up, f], axis=1))


def identity_frame(origin: np.ndarray | None = None) -> BodyFrame:
    """The canonical frame itself (left +X, up +Y, forward +Z) at ``origin`` (default 0)."""
    return BodyFrame(origin=np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64).reshape(3),
                     rotation=np.eye(3))


# ---------------------------------------------------------------------------------------------- spherical
@dataclass(frozen=True)
class SphericalCoords:
    """A camera's body-centric spherical coordinates (degrees, metres); see the module docstring."""

    azimuth_deg: float
    elevation_deg: float
    roll_deg: float
    radius: float


def wrap_degrees(angle_deg: np.ndarray | float) -> np.ndarray | float:
    """Wrap angles (degrees) into ``[-180, 180)``."""
    return (np.asarray(angle_deg, dtype=np.float64) + 180.0) % 360.0 - 180.0


def view_type(azimuth_deg: np.ndarray | float) -> np.ndarray | str:
    """View type of azimuth(s) in degrees (wrapped first): front [-30, 30), left [30, 150), right [-150, -30),
    rear otherwise. Returns a str for a scalar, else an array of str with the input's shape."""
    a = np.asarray(wrap_degrees(azimuth_deg))
    if not np.isfinite(a).all():
        raise ValueError(f"azimuth_deg must be finite; {int((~np.isfinite(a)).sum())} value(s) are not")
    out = np.full(a.shape, "rear", dtype="<U5")
    out[(a >= -30) & (a < 30)] = "front"
    out[(a >= 30) & (a < 150)] = "left"
    out[(a >= -150) & (a < -30)] = "right"
    return str(out) if out.ndim == 0 else out


def _direction(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit vector from the origin to the camera in body coordinates (left, up, forward)."""
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.cos(e) * math.sin(a), math.sin(e), math.cos(e) * math.cos(a)])


def _roll_matrix(roll_deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(roll_deg)), math.sin(math.radians(roll_deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def pose_from_spherical(frame: BodyFrame, coords: SphericalCoords) -> tuple[np.ndarray, np.ndarray]:
    """World -> camera ``(R (3, 3), t (3,))`` of the camera at ``coords`` looking at the frame's origin.

    ``|elevation|`` must be below 90 degrees (the upright direction is undefined at the poles).
    """
    for name in ("azimuth_deg", "elevation_deg", "roll_deg", "radius"):
        if not math.isfinite(getattr(coords, name)):
            raise ValueError(f"coords.{name} must be finite, got {getattr(coords, name)}")
    if coords.radius <= 0:
        raise ValueError(f"coords.radius must be > 0, got {coords.radius}")
    if abs(coords.elevation_deg) >= 90.0:
        raise ValueError(f"coords.elevation_deg must be in (-90, 90), got {coords.elevation_deg}")
    eye = frame.origin + coords.radius * (frame.rotation @ _direction(coords.azimuth_deg, coords.elevation_deg))
    R_up, _ = look_at(eye, frame.origin, frame.up)
    R = _roll_matrix(coords.roll_deg) @ R_up
    return R, -R @ eye


def camera_from_spherical(frame: BodyFrame, coords: SphericalCoords, intrinsics: PinholeCamera) -> PinholeCamera:
    """``intrinsics`` (its fx, fy, cx, cy, size) posed at ``coords`` looking at the frame's origin."""
    R, t = pose_from_spherical(frame, coords)
    return intrinsics.with_pose(R, t)


def spherical_from_pose(frame: BodyFrame, R: np.ndarray, t: np.ndarray) -> SphericalCoords:
    """Spherical coordinates of the camera with world -> camera rotation ``R`` (3, 3) and translation ``t`` (3,).

    Azimuth, elevation and radius come from the camera centre; roll from its orientation about its own optical
    axis (see the module docstring). Exact inverse of :func:`pose_from_spherical`.
    """
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if R.shape != (3, 3) or t.shape != (3,):
        raise ValueError(f"R must be (3, 3) and t (3,), got {R.shape} and {t.shape}")
    if not (np.isfinite(R).all() and np.isfinite(t).all()):
        raise ValueError("camera pose must be finite")
    d = frame.to_body(-R.T @ t)
    radius = float(np.linalg.norm(d))
    if radius == 0:
        raise ValueError("the camera centre coincides with the body origin; its direction is undefined")
    azimuth = float(wrap_degrees(math.degrees(math.atan2(d[0], d[2]))))
    elevation = math.degrees(math.asin(float(np.clip(d[1] / radius, -1.0, 1.0))))
    z = R[2]
    x_up = np.cross(z, frame.up)
    n = np.linalg.norm(x_up)
    if n < 1e-12:
        roll = 0.0  # optical axis along the body's up: roll is undefined, report 0
    else:
        x_up = x_up / n
        R_up = np.stack([x_up, np.cross(z, x_up), z])
        rel = R @ R_up.T  # rotation about the optical axis by the roll
        roll = math.degrees(math.atan2(rel[1, 0], rel[0, 0]))
    return SphericalCoords(azimuth_deg=azimuth, elevation_deg=elevation, roll_deg=float(wrap_degrees(roll)),
                           radius=radius)


def spherical_from_camera(frame: BodyFrame, camera: PinholeCamera) -> SphericalCoords:
    """:func:`spherical_from_pose` of a :class:`PinholeCamera`."""
    return spherical_from_pose(frame, camera.R, camera.t)


def spherical_from_poses(frame: BodyFrame, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Batched :func:`spherical_from_pose`: R (N, 3, 3), t (N, 3) -> (N, 4) [azimuth, elevation, roll, radius]."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if R.ndim != 3 or R.shape[1:] != (3, 3) or t.shape != (R.shape[0], 3):
        raise ValueError(f"R must be (N, 3, 3) and t (N, 3), got {R.shape} and {t.shape}")
    out = np.empty((R.shape[0], 4))
    for i in range(R.shape[0]):
        s = spherical_from_pose(frame, R[i], t[i])
        out[i] = (s.azimuth_deg, s.elevation_deg, s.roll_deg, s.radius)
    return out


# ---------------------------------------------------------------------------------------------- prior
@dataclass(frozen=True)
class AnglePrior:
    """One angle's distribution, degrees.

    Attributes:
        loc: location (mean for a Normal).
        scale: scale (> 0; standard deviation for a Normal).
        df: degrees of freedom (> 0) for a Student's t; must be left unset (``None``) for a Normal.
    """

    loc: float
    scale: float
    df: float | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.loc) and math.isfinite(self.scale)) or self.scale <= 0:
            raise ValueError(f"AnglePrior needs finite loc and scale > 0, got loc={self.loc}, scale={self.scale}")
        if self.df is not None and not (math.isfinite(self.df) and self.df > 0):
            raise ValueError(f"AnglePrior.df must be > 0, got {self.df}")


@dataclass(frozen=True)
class ViewTypePrior:
    """Elevation and roll distributions of one view type."""

    elevation: AnglePrior
    roll: AnglePrior


REFERENCE_STUDENT_T: dict[str, ViewTypePrior] = {
    "front": ViewTypePrior(elevation=AnglePrior(df=1.75, loc=8.25, scale=5.49),
                           roll=AnglePrior(df=1.275, loc=-0.18, scale=4.85)),
    "left": ViewTypePrior(elevation=AnglePrior(df=2.31, loc=0.95, scale=6.93),
                          roll=AnglePrior(df=1.63, loc=-6.33, scale=5.14)),
    "right": ViewTypePrior(elevation=AnglePrior(df=2.20, loc=1.39, scale=6.79),
                           roll=AnglePrior(df=1.67, loc=6.32, scale=5.13)),
    "rear": ViewTypePrior(elevation=AnglePrior(df=1.54, loc=-5.69, scale=4.86),
                          roll=AnglePrior(df=1.30, loc=0.09, scale=4.80)),
}
"""The reference implementation's per-view-type Student's t (df, loc, scale) in degrees, fitted to the DualPM
camera distribution (REFERENCE.md). Used with this module's angle conventions as they are."""


@dataclass(frozen=True)
class CameraPriorConfig:
    """Camera prior for viewpoint sampling (a data-catalog section, loaded with ``config_utils.from_mapping``).

    Attributes:
        distribution: ``'student_t'`` (the paper's choice) or ``'normal'`` (the Gaussian ablation).
        elevation: elevation distribution (degrees) used when ``per_view_type`` is ``None`` or lacks the view type.
        roll: roll distribution (degrees), likewise.
        per_view_type: distributions per view type (``front``/``left``/``right``/``rear``), chosen after the
            azimuth is drawn. Default: :data:`REFERENCE_STUDENT_T`, the reference implementation's table.
            For ``distribution: normal`` give Normal parameters (no ``df``) or set it to ``null``.
        fov_deg: horizontal field of view of the sampled cameras, degrees.
        margin_range: the relative framing margin is drawn from ``U(margin_range)`` (paper: ``[0.1, 0.25]``).
        max_abs_elevation_deg: elevations are redrawn until ``|elevation|`` is below this (the heavy-tailed t
            would otherwise place cameras past the poles).
    """

    distribution: Literal["student_t", "normal"] = "student_t"
    elevation: AnglePrior | None = None
    roll: AnglePrior | None = None
    per_view_type: dict[str, ViewTypePrior] | None = field(default_factory=lambda: dict(REFERENCE_STUDENT_T))
    fov_deg: float = 40.0
    margin_range: tuple[float, float] = (0.1, 0.25)
    max_abs_elevation_deg: float = 85.0

    def __post_init__(self) -> None:
        if self.distribution not in ("student_t", "normal"):
            raise ValueError(f"distribution must be 'student_t' or 'normal', got {self.distribution!r}")
        table = self.per_view_type or {}
        unknown = sorted(set(table) - set(VIEW_TYPES))
        if unknown:
            raise ValueError(f"per_view_type: unknown view type(s) {unknown}; allowed: {list(VIEW_TYPES)}")
        if (self.elevation is None or self.roll is None) and set(table) != set(VIEW_TYPES):
            raise ValueError("elevation and roll are required unless per_view_type covers all of "
                             f"{list(VIEW_TYPES)}; got per_view_type keys {sorted(table)}")
        priors = [("elevation", self.elevation), ("roll", self.roll)]
        priors += [(f"per_view_type.{k}.{a}", getattr(v, a)) for k, v in table.items() for a in ("elevation", "roll")]
        for name, p in priors:
            if p is None:
                continue
            if self.distribution == "student_t" and p.df is None:
                raise ValueError(f"{name}: distribution 'student_t' needs df")
            if self.distribution == "normal" and p.df is not None:
                raise ValueError(f"{name}: distribution 'normal' takes no df (got df={p.df}); give Normal "
                                 "parameters, or set per_view_type to null and use elevation/roll")
        lo, hi = self.margin_range
        if not 0.0 <= lo <= hi < 0.5:
            raise ValueError(f"margin_range must satisfy 0 <= lo <= hi < 0.5, got {self.margin_range}")
        if not 0.0 < self.fov_deg < 180.0:
            raise ValueError(f"fov_deg must be in (0, 180), got {self.fov_deg}")
        if not 0.0 < self.max_abs_elevation_deg < 90.0:
            raise ValueError(f"max_abs_elevation_deg must be in (0, 90), got {self.max_abs_elevation_deg}")

    def prior_for(self, view: str) -> ViewTypePrior:
        """Elevation and roll distributions for a view type."""
        table = self.per_view_type or {}
        if view in table:
            return table[view]
        return ViewTypePrior(elevation=self.elevation, roll=self.roll)


def _draw(prior: AnglePrior, distribution: str, rng: np.random.Generator) -> float:
    if distribution == "student_t":
        return prior.loc + prior.scale * float(rng.standard_t(prior.df))
    return prior.loc + prior.scale * float(rng.standard_normal())


def sample_angles(config: CameraPriorConfig, n: int, rng: np.random.Generator) -> np.ndarray:
    """Draw ``n`` (azimuth, elevation, roll) triples in degrees: azimuth ~ U[-180, 180), then elevation and roll
    from the view type's prior; elevation redrawn while ``|elevation| >= max_abs_elevation_deg``; roll wrapped
    into [-180, 180). Returns (n, 3) float64."""
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    out = np.empty((n, 3))
    for i in range(n):
        az = float(rng.uniform(-180.0, 180.0))
        prior = config.prior_for(view_type(az))
        el = _draw(prior.elevation, config.distribution, rng)
        while abs(el) >= config.max_abs_elevation_deg:
            el = _draw(prior.elevation, config.distribution, rng)
        roll = float(wrap_degrees(_draw(prior.roll, config.distribution, rng)))
        out[i] = (az, el, roll)
    return out


# ---------------------------------------------------------------------------------------------- framing
@dataclass(frozen=True, eq=False)
class Viewpoint:
    """A sampled camera with its body-centric coordinates and framing margin."""

    camera: PinholeCamera
    coords: SphericalCoords
    view_type: str
    margin: float


def frame_camera(vertices: np.ndarray, frame: BodyFrame, azimuth_deg: float, elevation_deg: float, roll_deg: float,
                 fov_deg: float, width: int, height: int, margin: float) -> Viewpoint:
    """Place a camera at the given angles, looking at the body origin, so that the mesh fills the frame.

    *Relative margin*: with ``m = margin``, the projected vertex bounding box is centred in the image by moving
    the principal point, and the radius is chosen so that on the tighter axis the gap between the box and each
    image border is exactly ``m`` times that image side (box extent ``(1 - 2m) * side``); on the other axis the gap
    is at least ``m`` times that side. The focal length follows from ``fov_deg`` (horizontal).

    Args:
        vertices: (V, 3) posed mesh vertices, metres, world frame.
        frame: body frame of the posed mesh.
        fov_deg: horizontal field of view, degrees. width, height: image size in pixels.
        margin: relative margin in [0, 0.5).
    """
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
        raise ValueError(f"vertices must have shape (V, 3) with V > 0, got {v.shape}")
    if not np.isfinite(v).all():
        raise ValueError("vertices must be finite")
    if not 0.0 <= margin < 0.5:
        raise ValueError(f"margin must be in [0, 0.5), got {margin}")
    intr = PinholeCamera.from_fov(fov_deg, width, height)
    R, _ = pose_from_spherical(frame, SphericalCoords(azimuth_deg, elevation_deg, roll_deg, 1.0))
    # camera-frame coordinates relative to the origin joint; the camera sits at distance r on the -z axis
    rel = (v - frame.origin) @ R.T  # (V, 3)
    target = 1.0 - 2.0 * margin

    def fill(r: float) -> tuple[float, np.ndarray, np.ndarray]:
        z = rel[:, 2] + r
        x, y = rel[:, 0] / z, rel[:, 1] / z
        ext = np.array([intr.fx * (x.max() - x.min()) / width, intr.fy * (y.max() - y.min()) / height])
        return float(ext.max()), np.array([x.min(), x.max()]), np.array([y.min(), y.max()])

    extent = float(np.linalg.norm(v.max(0) - v.min(0)))
    r_lo = float(-rel[:, 2].min()) + 1e-6 * max(extent, 1e-9)  # every vertex strictly in front
    r_hi = max(r_lo, 1e-9) * 2.0 + extent
    while fill(r_hi)[0] > target:
        r_hi *= 2.0
    for _ in range(200):  # bisection on the monotone fill fraction
        r_mid = 0.5 * (r_lo + r_hi)
        if fill(r_mid)[0] > target:
            r_lo = r_mid
        else:
            r_hi = r_mid
        if r_hi - r_lo <= 1e-13 * r_hi:
            break
    r = r_hi
    _, xr, yr = fill(r)
    cx = width / 2.0 - intr.fx * xr.mean()
    cy = height / 2.0 - intr.fy * yr.mean()
    coords = SphericalCoords(float(wrap_degrees(azimuth_deg)), float(elevation_deg), float(wrap_degrees(roll_deg)), r)
    camera = camera_from_spherical(frame, coords, intr.with_principal_point(cx, cy))
    return Viewpoint(camera=camera, coords=coords, view_type=view_type(azimuth_deg), margin=float(margin))


def sample_viewpoints(vertices: np.ndarray, frame: BodyFrame, n: int, config: CameraPriorConfig, width: int,
                      height: int, rng: np.random.Generator) -> list[Viewpoint]:
    """Sample ``n`` framed viewpoints of a posed mesh from the camera prior.

    Azimuth ~ U[-180, 180); elevation and roll from ``config`` (per view type where given); margin ~
    ``U(config.margin_range)``; radius and principal point from :func:`frame_camera`. Reproducible for a seeded
    ``rng``.

    Args:
        vertices: (V, 3) posed vertices, metres, world frame. frame: its body frame.
        width, height: image size in pixels.
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise ValueError(f"n must be a non-negative int, got {n!r}")
    angles = sample_angles(config, n, rng)
    margins = rng.uniform(config.margin_range[0], config.margin_range[1], size=n)
    return [frame_camera(vertices, frame, a, e, r, config.fov_deg, width, height, float(m))
            for (a, e, r), m in zip(angles, margins)]


# ---------------------------------------------------------------------------------------------- fitting
@dataclass(frozen=True)
class AngleFit:
    """Maximum-likelihood fits of an angle sample (degrees).

    Attributes:
        student_t: (df, loc, scale) of the Student's t.
        normal: (loc, scale) of the Normal.
        loglik_t, loglik_normal: total log-likelihood of the samples under each fit (higher is better).
    """

    student_t: tuple[float, float, float]
    normal: tuple[float, float]
    loglik_t: float
    loglik_normal: float


def fit_angle_distribution(samples_deg: np.ndarray) -> AngleFit:
    """Fit a Student's t and a Normal to angle samples by maximum likelihood (``scipy.stats``).

    Args:
        samples_deg: (N,) finite angles in degrees, N >= 3.
    """
    x = np.asarray(samples_deg, dtype=np.float64)
    if x.ndim != 1 or x.shape[0] < 3:
        raise ValueError(f"samples_deg must have shape (N,) with N >= 3, got {x.shape}")
    if not np.isfinite(x).all():
        raise ValueError(f"samples_deg must be finite; {int((~np.isfinite(x)).sum())} of {x.shape[0]} are not")
    if np.ptp(x) == 0:
        raise ValueError(f"samples_deg are all equal ({x[0]}); a scale cannot be fitted")
    df, loc, scale = stats.t.fit(x)
    mu, sigma = stats.norm.fit(x)
    return AngleFit(student_t=(float(df), float(loc), float(scale)), normal=(float(mu), float(sigma)),
                    loglik_t=float(stats.t.logpdf(x, df, loc, scale).sum()),
                    loglik_normal=float(stats.norm.logpdf(x, mu, sigma).sum()))


def view_type_counts(azimuth_deg: np.ndarray) -> Mapping[str, int]:
    """Number of azimuths (degrees) per view type."""
    types = np.atleast_1d(view_type(np.asarray(azimuth_deg, dtype=np.float64)))
    return {t: int((types == t).sum()) for t in VIEW_TYPES}
