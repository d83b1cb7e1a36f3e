"""Render jobs: one row per image to render (schema owned here; see docs/CONVENTIONS.md "Render jobs").

A :class:`RenderJob` is pure data (numpy, no bpy). :func:`jobs_to_table` / :func:`jobs_from_table` convert a list of
jobs to and from a ``pyarrow.Table`` with exactly the documented columns; :func:`write_jobs` / :func:`read_jobs`
store them as Parquet. Reading validates every column and raises :class:`JobSchemaError` naming the column.

Frames: ``excess_rotations`` are θ ``(J, 3)`` axis-angle radians in each joint's rest frame (rig joint order); the
global similarity maps the canonical frame to the world: ``x_world = s R x + t``; the camera is OpenCV
(world -> camera ``x_cam = R_c x_world + t_c``), intrinsics in pixels of the ``width`` x ``height`` image.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from bat3r_core.cameras import PinholeCamera
from bat3r_core.shards import atomic_write

__all__ = ["RenderJob", "JobSchemaError", "JOB_SCHEMA", "VIEW_KINDS", "VIEW_TYPES", "jobs_to_table",
           "jobs_from_table", "write_jobs", "read_jobs", "job_to_dict", "job_from_dict"]

VIEW_KINDS = ("canonical", "estimated", "augmented", "random_pose", "collection")
VIEW_TYPES = ("front", "left", "right", "rear")
_F64_LIST = pa.list_(pa.float64())

JOB_SCHEMA = pa.schema([
    ("sample_id", pa.string()),
    ("source_id", pa.string()),
    ("view_kind", pa.string()),
    ("view_type", pa.string()),
    ("excess_rotations", _F64_LIST),
    ("global_scale", pa.float64()),
    ("global_rotation", _F64_LIST),
    ("global_translation", _F64_LIST),
    ("fx", pa.float64()),
    ("fy", pa.float64()),
    ("cx", pa.float64()),
    ("cy", pa.float64()),
    ("width", pa.int32()),
    ("height", pa.int32()),
    ("camera_rotation", _F64_LIST),
    ("camera_translation", _F64_LIST),
    ("texture_id", pa.int32()),
    ("envmap_id", pa.int32()),
    ("envmap_rotation", pa.float64()),
    ("seed", pa.int64()),
])
"""The Parquet schema of a render-job table (column order as documented)."""


class JobSchemaError(ValueError):
    """A render-job table or row does not follow the schema; the message names the column (and row)."""


@dataclass(frozen=True, eq=False)
class RenderJob:
    """One image to render.

    Attributes:
        sample_id: unique id of the sample in its run.
        source_id: id of the collection sample it came from, or ``""``.
        view_kind: one of :data:`VIEW_KINDS`. view_type: one of :data:`VIEW_TYPES`.
        excess_rotations: (J, 3) float64 axis-angle, radians, rest frame of each joint.
        global_scale: s > 0. global_rotation: (3, 3) rotation. global_translation: (3,) metres
            (canonical -> world ``x_world = s R x + t``).
        camera: :class:`PinholeCamera` (OpenCV, world -> camera, pixels).
        texture_id: index into the category's texture list (toy: its procedural coats), >= 0.
        envmap_id: index into the category's environment maps, ``-1`` = procedural sky.
        envmap_rotation: radians about Blender's world up axis.
        seed: Cycles seed of this image (and of any per-image randomness such as the sky).

    Construction does not validate the numbers (a bad row must reach the worker, which records why it cannot
    render it); :meth:`problems` lists what is wrong.
    """

    sample_id: str
    excess_rotations: np.ndarray
    camera: PinholeCamera | None
    global_scale: float = 1.0
    global_rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    global_translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    source_id: str = ""
    view_kind: str = "canonical"
    view_type: str = "front"
    texture_id: int = 0
    envmap_id: int = -1
    envmap_rotation: float = 0.0
    seed: int = 0
    camera_values: dict | None = None  # raw camera numbers when they do not form a valid PinholeCamera

    @property
    def num_joints(self) -> int:
        return int(np.asarray(self.excess_rotations).reshape(-1, 3).shape[0])

    def camera_numbers(self) -> dict:
        """The camera columns of this job (raw numbers, possibly invalid)."""
        if self.camera is not None:
            c = self.camera
            return {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "width": c.width, "height": c.height,
                    "camera_rotation": np.asarray(c.R, dtype=np.float64).reshape(-1).tolist(),
                    "camera_translation": np.asarray(c.t, dtype=np.float64).reshape(-1).tolist()}
        return dict(self.camera_values or {})

    def problems(self, num_joints: int | None = None) -> list[str]:
        """Reasons this job cannot be rendered (empty when it can)."""
        out = []
        th = np.asarray(self.excess_rotations, dtype=np.float64)
        if th.ndim != 2 or th.shape[1] != 3:
            out.append(f"excess_rotations must have shape (J, 3), got {th.shape}")
        elif num_joints is not None and th.shape[0] != num_joints:
            out.append(f"excess_rotations has {th.shape[0]} joints, the rig has {num_joints}")
        if not np.isfinite(th).all():
            out.append("excess_rotations contain NaN/inf")
        if not (math.isfinite(self.global_scale) and self.global_scale > 0):
            out.append(f"global_scale must be finite and > 0, got {self.global_scale}")
        r = np.asarray(self.global_rotation, dtype=np.float64)
        if r.shape != (3, 3) or not np.isfinite(r).all() or np.abs(r @ r.T - np.eye(3)).max() > 1e-5 \
                or np.linalg.det(r) <= 0:
            out.append("global_rotation must be a finite 3x3 rotation matrix")
        t = np.asarray(self.global_translation, dtype=np.float64)
        if t.shape != (3,) or not np.isfinite(t).all():
            out.append(f"global_translation must be 3 finite numbers, got {t.tolist()}")
        if self.camera is None:
            out.append(f"invalid camera: {(self.camera_values or {}).get('_error', 'missing')}")
        if self.texture_id < 0:
            out.append(f"texture_id must be >= 0, got {self.texture_id}")
        if self.envmap_id < -1:
            out.append(f"envmap_id must be >= -1, got {self.envmap_id}")
        if not math.isfinite(self.envmap_rotation):
            out.append(f"envmap_rotation must be finite, got {self.envmap_rotation}")
        return out


def job_to_dict(job: RenderJob) -> dict:
    """A job as a plain dict with the schema's columns (lists for the array columns)."""
    row = {
        "sample_id": str(job.sample_id),
        "source_id": str(job.source_id),
        "view_kind": str(job.view_kind),
        "view_type": str(job.view_type),
        "excess_rotations": np.asarray(job.excess_rotations, dtype=np.float64).reshape(-1).tolist(),
        "global_scale": float(job.global_scale),
        "global_rotation": np.asarray(job.global_rotation, dtype=np.float64).reshape(-1).tolist(),
        "global_translation": np.asarray(job.global_translation, dtype=np.float64).reshape(-1).tolist(),
    }
    row.update(job.camera_numbers())
    row.update({"texture_id": int(job.texture_id), "envmap_id": int(job.envmap_id),
                "envmap_rotation": float(job.envmap_rotation), "seed": int(job.seed)})
    return {name: row[name] for name in JOB_SCHEMA.names}


def _list(row: dict, name: str, length: int | None, where: str) -> np.ndarray:
    v = row.get(name)
    if v is None:
        raise JobSchemaError(f"{where}column '{name}' is null")
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if length is not None and a.shape[0] != length:
        raise JobSchemaError(f"{where}column '{name}' must hold {length} numbers, got {a.shape[0]}")
    return a


def job_from_dict(row: dict, where: str = "") -> RenderJob:
    """Inverse of :func:`job_to_dict`. Structural errors (missing column, wrong list length, bad view kind) raise
    :class:`JobSchemaError`; numeric problems (NaN pose, invalid camera) are kept for the worker to report."""
    missing = [n for n in JOB_SCHEMA.names if n not in row]
    if missing:
        raise JobSchemaError(f"{where}missing column(s) {missing}")
    if row["view_kind"] not in VIEW_KINDS:
        raise JobSchemaError(f"{where}column 'view_kind' must be one of {VIEW_KINDS}, got {row['view_kind']!r}")
    if row["view_type"] not in VIEW_TYPES:
        raise JobSchemaError(f"{where}column 'view_type' must be one of {VIEW_TYPES}, got {row['view_type']!r}")
    theta = _list(row, "excess_rotations", None, where)
    if theta.shape[0] % 3:
        raise JobSchemaError(f"{where}column 'excess_rotations' must hold J*3 numbers, got {theta.shape[0]}")
    cam_values = {k: row[k] for k in ("fx", "fy", "cx", "cy", "width", "height")}
    cam_values["camera_rotation"] = _list(row, "camera_rotation", 9, where).tolist()
    cam_values["camera_translation"] = _list(row, "camera_translation", 3, where).tolist()
    try:
        camera = PinholeCamera(fx=row["fx"], fy=row["fy"], cx=row["cx"], cy=row["cy"], width=int(row["width"]),
                               height=int(row["height"]),
                               R=np.asarray(cam_values["camera_rotation"]).reshape(3, 3),
                               t=np.asarray(cam_values["camera_translation"]))
    except (TypeError, ValueError) as e:
        camera = None
        cam_values["_error"] = str(e)
    return RenderJob(
        sample_id=str(row["sample_id"]), source_id=str(row["source_id"]), view_kind=row["view_kind"],
        view_type=row["view_type"], excess_rotations=theta.reshape(-1, 3),
        global_scale=float(row["global_scale"]),
        global_rotation=_list(row, "global_rotation", 9, where).reshape(3, 3),
        global_translation=_list(row, "global_translation", 3, where), camera=camera,
        camera_values=None if camera is not None else cam_values, texture_id=int(row["texture_id"]),
        envmap_id=int(row["envmap_id"]), envmap_rotation=float(row["envmap_rotation"]), seed=int(row["seed"]))


def jobs_to_table(jobs: Sequence[RenderJob]) -> pa.Table:
    """A ``pyarrow.Table`` with :data:`JOB_SCHEMA`; raises :class:`JobSchemaError` on duplicate sample ids."""
    ids = [j.sample_id for j in jobs]
    if len(set(ids)) != len(ids):
        dup = sorted({i for i in ids if ids.count(i) > 1})[:5]
        raise JobSchemaError(f"column 'sample_id' must be unique; duplicated: {dup}")
    rows = [job_to_dict(j) for j in jobs]
    return pa.Table.from_pylist(rows, schema=JOB_SCHEMA)


def jobs_from_table(table: pa.Table) -> list[RenderJob]:
    """Validate a job table against :data:`JOB_SCHEMA` and return its jobs.

    Raises:
        JobSchemaError: a column is missing, has the wrong type, a list column has the wrong length, a view
            kind/type is unknown or a sample id repeats; the message names the column (and the row).
    """
    if not isinstance(table, pa.Table):
        raise TypeError(f"table must be a pyarrow.Table, got {type(table).__name__}")
    missing = [n for n in JOB_SCHEMA.names if n not in table.column_names]
    if missing:
        raise JobSchemaError(f"render-job table lacks column(s) {missing}; columns: {table.column_names}")
    for f in JOB_SCHEMA:
        actual = table.schema.field(f.name).type
        ok = actual == f.type or (pa.types.is_integer(f.type) and pa.types.is_integer(actual)) or (
            pa.types.is_floating(f.type) and (pa.types.is_floating(actual) or pa.types.is_integer(actual))) or (
            pa.types.is_list(f.type) and (pa.types.is_list(actual) or pa.types.is_large_list(actual))
            and (pa.types.is_floating(actual.value_type) or pa.types.is_integer(actual.value_type)))
        if not ok:
            raise JobSchemaError(f"column '{f.name}' must have type {f.type}, got {actual}")
    rows = table.select(JOB_SCHEMA.names).to_pylist()
    jobs = [job_from_dict(r, where=f"row {i} ('{r.get('sample_id')}'): ") for i, r in enumerate(rows)]
    ids = [j.sample_id for j in jobs]
    if len(set(ids)) != len(ids):
        dup = sorted({i for i in ids if ids.count(i) > 1})[:5]
        raise JobSchemaError(f"column 'sample_id' must be unique; duplicated: {dup}")
    return jobs


def write_jobs(jobs: Sequence[RenderJob], path: str | os.PathLike) -> Path:
    """Write jobs to a Parquet file (atomically: temporary name, then rename)."""
    table = jobs_to_table(jobs)
    return atomic_write(path, lambda tmp: pq.write_table(table, tmp))


def read_jobs(path: str | os.PathLike) -> list[RenderJob]:
    """Read and validate a render-job Parquet file (see :func:`jobs_from_table`)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"render-job file {path} does not exist")
    return jobs_from_table(pq.read_table(path))
