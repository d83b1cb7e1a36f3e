"""Pinhole cameras in the OpenCV convention, and their conversion to Blender's camera.

Conventions (written once, here):

* Camera frame: OpenCV, ``x`` right, ``y`` down, ``z`` forward (into the scene), metres.
* Extrinsics map world -> camera: ``x_cam = R @ x_world + t``; the camera centre is ``-R.T @ t``.
* Pixels: the image spans ``[0, W] x [0, H]``; pixel (row ``i``, column ``j``) has its centre at
  ``(u, v) = (j + 0.5, i + 0.5)``; arrays are indexed ``[row, col] = [v, u]``.
* Intrinsics ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels; ``u = fx * x / z + cx``,
  ``v = fy * y / z + cy``.
* Focal length in millimetres refers to a 36 mm wide sensor with a horizontal sensor fit:
  ``fx = lens_mm * W / sensor_width_mm``.
* Blender's camera looks down its local ``-z`` with ``y`` up and ``x`` right, i.e. its local axes are the OpenCV
  axes flipped by ``diag(1, -1, -1)``. :func:`to_blender` turns a :class:`PinholeCamera` into the numbers a
  Blender camera object needs (lens, sensor width, shifts and ``matrix_world``); the render worker only copies
  them. With ``sensor_fit = 'HORIZONTAL'`` Blender measures its shifts in units of the image *width*:
  ``shift_x = (W / 2 - cx) / W``, ``shift_y = (cy - H / 2) / W`` (checked in bpy 5.0 on landscape and portrait
  images; dividing by ``max(W, H)`` instead is wrong for portrait images under this fit).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

SENSOR_WIDTH_MM = 36.0
"""Sensor width (mm) that focal lengths in millimetres refer to (horizontal sensor fit)."""

BLENDER_FROM_OPENCV = np.diag([1.0, -1.0, -1.0])
"""Axis flip between the OpenCV camera frame and Blender's camera frame (its own inverse)."""

GLTF_TO_BLENDER_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
"""Rotation from glTF's Y-up world to Blender's Z-up world, as applied by Blender's glTF importer
(``(x, y, z) -> (x, -z, y)``). Pass it to :func:`to_blender` when the mesh was imported from glTF."""

_ROTATION_TOL = 1e-6


def _finite_float(name: str, value) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise TypeError(f"PinholeCamera.{name} must be a real number, got {type(value).__name__} {value!r}") from None
    if not math.isfinite(out):
        raise ValueError(f"PinholeCamera.{name} must be finite, got {out}")
    return out


def _check_rotation(name: str, R: np.ndarray) -> None:
    err = np.abs(R @ R.T - np.eye(3)).max()
    if err > _ROTATION_TOL or np.linalg.det(R) <= 0:
        raise ValueError(f"{name} must be a rotation matrix (orthonormal, det +1); got |R R^T - I|max={err:.3g}, "
                         f"det={np.linalg.det(R):.6g}")


@dataclass(frozen=True, eq=False)
class PinholeCamera:
    """A pinhole camera (OpenCV convention, metres, pixels of a ``width`` x ``height`` image).

    Attributes:
        fx, fy: focal lengths in pixels (> 0).
        cx, cy: principal point in pixels (continuous coordinates, image spans ``[0, W] x [0, H]``).
        width, height: image size in pixels (> 0).
        R: (3, 3) float64 rotation, world -> camera.
        t: (3,) float64 translation, world -> camera, metres: ``x_cam = R @ x_world + t``.

    Construction validates every field: non-finite numbers raise ``ValueError`` naming the field. Arrays are
    copied and made read-only. Equality is identity (use :meth:`allclose` to compare values).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            object.__setattr__(self, name, _finite_float(name, getattr(self, name)))
        for name in ("fx", "fy"):
            if getattr(self, name) <= 0:
                raise ValueError(f"PinholeCamera.{name} must be > 0, got {getattr(self, name)}")
        for name in ("width", "height"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                raise TypeError(f"PinholeCamera.{name} must be an int, got {type(v).__name__} {v!r}")
            if v <= 0:
                raise ValueError(f"PinholeCamera.{name} must be > 0, got {v}")
            object.__setattr__(self, name, int(v))
        for name, shape in (("R", (3, 3)), ("t", (3,))):
            a = np.array(getattr(self, name), dtype=np.float64)
            if a.shape != shape:
                raise ValueError(f"PinholeCamera.{name} must have shape {shape}, got {a.shape}")
            if not np.isfinite(a).all():
                raise ValueError(f"PinholeCamera.{name} must be finite, got {a.tolist()}")
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        _check_rotation("PinholeCamera.R", self.R)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_fov(cls, fov_deg: float, width: int, height: int, R: np.ndarray | None = None,
                 t: np.ndarray | None = None, cx: float | None = None, cy: float | None = None) -> "PinholeCamera":
        """Camera with square pixels from the horizontal field of view ``fov_deg`` (degrees, in (0, 180)).

        ``fx = fy = (width / 2) / tan(fov / 2)``; the principal point defaults to the image centre.
        """
        fov = _finite_float("fov_deg", fov_deg)
        if not 0.0 < fov < 180.0:
            raise ValueError(f"fov_deg must be in (0, 180) degrees, got {fov}")
        f = 0.5 * width / math.tan(math.radians(fov) / 2.0)
        return cls._square(f, width, height, R, t, cx, cy)

    @classmethod
    def from_focal_mm(cls, lens_mm: float, width: int, height: int, R: np.ndarray | None = None,
                      t: np.ndarray | None = None, cx: float | None = None, cy: float | None = None,
                      sensor_width_mm: float = SENSOR_WIDTH_MM) -> "PinholeCamera":
        """Camera with square pixels from a focal length in mm on a ``sensor_width_mm`` wide sensor (horizontal fit).

        ``fx = fy = lens_mm * width / sensor_width_mm``; the principal point defaults to the image centre.
        """
        lens = _finite_float("lens_mm", lens_mm)
        sensor = _finite_float("sensor_width_mm", sensor_width_mm)
        if lens <= 0 or sensor <= 0:
            raise ValueError(f"lens_mm and sensor_width_mm must be > 0, got {lens} and {sensor}")
        return cls._square(lens * width / sensor, width, height, R, t, cx, cy)

    @classmethod
    def _square(cls, f, width, height, R, t, cx, cy) -> "PinholeCamera":
        return cls(fx=f, fy=f, cx=width / 2.0 if cx is None else cx, cy=height / 2.0 if cy is None else cy,
                   width=width, height=height, R=np.eye(3) if R is None else R, t=np.zeros(3) if t is None else t)

    def with_pose(self, R: np.ndarray, t: np.ndarray) -> "PinholeCamera":
        """Same intrinsics, new extrinsics (world -> camera)."""
        return PinholeCamera(self.fx, self.fy, self.cx, self.cy, self.width, self.height, R, t)

    def with_principal_point(self, cx: float, cy: float) -> "PinholeCamera":
        """Same camera with the principal point moved to ``(cx, cy)`` pixels."""
        return PinholeCamera(self.fx, self.fy, cx, cy, self.width, self.height, self.R, self.t)

    # ------------------------------------------------------------------ properties
    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 intrinsic matrix in pixels."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates, metres: ``-R.T @ t``."""
        return -self.R.T @ self.t

    @property
    def image_size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels."""
        return self.width, self.height

    def allclose(self, other: "PinholeCamera", atol: float = 1e-9) -> bool:
        """True when every field of ``other`` matches within ``atol``."""
        return (self.width == other.width and self.height == other.height
                and np.allclose([self.fx, self.fy, self.cx, self.cy], [other.fx, other.fy, other.cx, other.cy],
                                atol=atol)
                and np.allclose(self.R, other.R, atol=atol) and np.allclose(self.t, other.t, atol=atol))

    # ------------------------------------------------------------------ geometry
    def world_to_camera(self, points_world: np.ndarray) -> np.ndarray:
        """points_world: (..., 3) metres, world frame -> (..., 3) metres, camera frame."""
        p = _points("points_world", points_world)
        return p @ self.R.T + self.t

    def camera_to_world(self, points_cam: np.ndarray) -> np.ndarray:
        """points_cam: (..., 3) metres, camera frame -> (..., 3) metres, world frame."""
        p = _points("points_cam", points_cam)
        return (p - self.t) @ self.R

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points to pixels.

        Args:
            points_world: (..., 3) metres, world frame.
        Returns:
            uv: (..., 2) continuous pixel coordinates (``nan`` where the depth is not positive).
            depth: (..., ) camera-frame ``z`` in metres.
        """
        return project_points(self.world_to_camera(points_world), self.K)

    def unproject(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`project`: uv (..., 2) pixels and depth (...) camera-frame z (m) -> (..., 3) world."""
        return self.camera_to_world(unproject_points(uv, depth, self.K))

    def pixel_centers(self) -> np.ndarray:
        """(H, W, 2) float64 pixel-centre coordinates ``(u, v) = (j + 0.5, i + 0.5)``."""
        return pixel_centers(self.width, self.height)

    def pixel_ray_directions(self) -> np.ndarray:
        """(H, W, 3) float64 ray directions through pixel centres in the camera frame, scaled so that ``z = 1``.

        A point at parameter ``s`` along a ray has camera-frame depth ``z = s``.
        """
        uv = self.pixel_centers()
        d = np.empty(uv.shape[:2] + (3,))
        d[..., 0] = (uv[..., 0] - self.cx) / self.fx
        d[..., 1] = (uv[..., 1] - self.cy) / self.fy
        d[..., 2] = 1.0
        return d

    def pixel_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Rays through the pixel centres in the world frame.

        Returns:
            origins: (H, W, 3) camera centre, metres, world frame.
            directions: (H, W, 3) unit directions, world frame.
        """
        d = self.pixel_ray_directions() @ self.R  # (H, W, 3): R.T @ d per pixel
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return np.broadcast_to(self.center, d.shape).copy(), d


def _points(name: str, points: np.ndarray) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim == 0 or p.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., 3), got {p.shape}")
    return p


def pixel_centers(width: int, height: int) -> np.ndarray:
    """(height, width, 2) float64 pixel centres ``(u, v) = (j + 0.5, i + 0.5)`` for row ``i``, column ``j``."""
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    return np.stack([u, v], axis=-1)


def project_points(points_cam: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project camera-frame points with intrinsics; batched.

    Args:
        points_cam: (..., 3) metres, camera frame.
        K: (3, 3) or (..., 3, 3) intrinsics in pixels, broadcast against the points' leading axes
           (for a batch of cameras pass points (B, N, 3) and K (B, 1, 3, 3)).
    Returns:
        uv: (..., 2) pixels, ``nan`` where ``z <= 0``; depth: (...) camera-frame z in metres.
    """
    p = _points("points_cam", points_cam)
    K = np.asarray(K, dtype=np.float64)
    if K.shape[-2:] != (3, 3):
        raise ValueError(f"K must have shape (..., 3, 3), got {K.shape}")
    z = p[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.where(z > 0, p[..., 0] / z, np.nan)
        y = np.where(z > 0, p[..., 1] / z, np.nan)
    u = K[..., 0, 0] * x + K[..., 0, 1] * y + K[..., 0, 2]
    v = K[..., 1, 1] * y + K[..., 1, 2]
    return np.stack([u, v], axis=-1), z


def unproject_points(uv: np.ndarray, depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame points from pixels and depth; batched like :func:`project_points`.

    Args:
        uv: (..., 2) pixels. depth: (...) camera-frame z, metres. K: (3, 3) or (..., 3, 3).
    Returns:
        (..., 3) metres, camera frame.
    """
    uv = np.asarray(uv, dtype=np.float64)
    if uv.ndim == 0 or uv.shape[-1] != 2:
        raise ValueError(f"uv must have shape (..., 2), got {uv.shape}")
    z = np.asarray(depth, dtype=np.float64)
    if z.shape != uv.shape[:-1]:
        raise ValueError(f"depth must have shape {uv.shape[:-1]} (uv without its last axis), got {z.shape}")
    K = np.asarray(K, dtype=np.float64)
    y = (uv[..., 1] - K[..., 1, 2]) / K[..., 1, 1]
    x = (uv[..., 0] - K[..., 0, 2] - K[..., 0, 1] * y) / K[..., 0, 0]
    return np.stack([x * z, y * z, z], axis=-1)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World -> camera extrinsics of a camera at ``eye`` looking at ``target``.

    The image's up direction (``-y`` of the camera) is the projection of ``up`` (world) onto the image plane,
    so a world ``up`` vector appears pointing up in the image.

    Args:
        eye, target, up: (3,) world frame; ``up`` must not be parallel to ``target - eye``.
    Returns:
        R (3, 3), t (3,) with ``x_cam = R @ x_world + t``.
    """
    eye, target, up = (_points(n, a).reshape(3) for n, a in (("eye", eye), ("target", target), ("up", up)))
    z = target - eye
    nz = np.linalg.norm(z)
    if nz == 0:
        raise ValueError(f"look_at: eye and target coincide at {eye.tolist()}")
    z = z / nz
    x = np.cross(z, up)
    nx = np.linalg.norm(x)
    if nx < 1e-12 * max(np.linalg.norm(up), 1e-300):
        raise ValueError(f"look_at: up {up.tolist()} is parallel to the viewing direction {z.tolist()}")
    x = x / nx
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ eye


def stack_intrinsics(cameras: Sequence[PinholeCamera]) -> np.ndarray:
    """(N, 3, 3) float64 intrinsics of a list of cameras."""
    return np.stack([c.K for c in cameras]) if cameras else np.zeros((0, 3, 3))


def stack_extrinsics(cameras: Sequence[PinholeCamera]) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3, 3) rotations and (N, 3) translations (world -> camera) of a list of cameras."""
    if not cameras:
        return np.zeros((0, 3, 3)), np.zeros((0, 3))
    return np.stack([c.R for c in cameras]), np.stack([c.t for c in cameras])


def to_blender(camera: PinholeCamera, world_rotation: np.ndarray | None = None,
               sensor_width_mm: float = SENSOR_WIDTH_MM) -> dict:
    """The settings of a Blender camera that renders exactly what ``camera`` sees.

    Blender's camera object looks down its local ``-z`` with ``y`` up: its local axes are OpenCV's flipped by
    ``diag(1, -1, -1)``, so its ``matrix_world`` (camera local -> world) is
    ``[[R_w @ R.T @ diag(1, -1, -1), R_w @ centre], [0, 0, 0, 1]]`` where ``R_w`` (``world_rotation``) maps bat3r's
    world into Blender's world (identity when the mesh's vertices are written into Blender unchanged;
    :data:`GLTF_TO_BLENDER_WORLD` when the mesh went through Blender's glTF importer).

    The camera must have square pixels (``fx == fy``); use ``sensor_fit = 'HORIZONTAL'`` and a render resolution
    of ``width`` x ``height`` at 100 %.

    Returns:
        dict with ``lens_mm``, ``sensor_width_mm``, ``sensor_fit`` (``'HORIZONTAL'``), ``shift_x``, ``shift_y``,
        ``resolution_x``, ``resolution_y`` and ``matrix_world`` ((4, 4) float64).
    """
    if not isinstance(camera, PinholeCamera):
        raise TypeError(f"camera must be a PinholeCamera, got {type(camera).__name__}")
    if abs(camera.fx - camera.fy) > 1e-9 * camera.fx:
        raise ValueError(f"to_blender needs square pixels (fx == fy), got fx={camera.fx}, fy={camera.fy}")
    Rw = np.eye(3) if world_rotation is None else np.asarray(world_rotation, dtype=np.float64)
    if Rw.shape != (3, 3):
        raise ValueError(f"world_rotation must have shape (3, 3), got {Rw.shape}")
    _check_rotation("world_rotation", Rw)
    W, H = camera.width, camera.height
    side = float(W)  # horizontal sensor fit: shifts are fractions of the width
    M = np.eye(4)
    M[:3, :3] = Rw @ camera.R.T @ BLENDER_FROM_OPENCV
    M[:3, 3] = Rw @ camera.center
    return {
        "lens_mm": camera.fx * sensor_width_mm / W,
        "sensor_width_mm": float(sensor_width_mm),
        "sensor_fit": "HORIZONTAL",
        "shift_x": (W / 2.0 - camera.cx) / side,
        "shift_y": (camera.cy - H / 2.0) / side,
        "resolution_x": W,
        "resolution_y": H,
        "matrix_world": M,
    }
