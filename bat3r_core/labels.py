"""Exact training labels of a render job: the rig skinned with the job's pose, ray-cast through its camera.

What the Blender worker renders and what its shard's P/Q/occupancy say must be the same mesh: the renderer poses
the armature so Blender's mesh equals :mod:`bat3r_core.skinning` (docs/rendering.md), and the labels ray-cast that
very skinned mesh (:func:`posed_vertices`) with :func:`bat3r_core.pointmaps.dual_point_maps`. The raw-image baseline
labels the collection's own crops the same way through their recovered cameras
(:func:`bat3r_core.raw_images.raw_image_shard`).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from bat3r_core.pointmaps import DualPointMaps, dual_point_maps
from bat3r_core.rig import Rig

if TYPE_CHECKING:  # bat3r_core.render imports this module (its runner labels every render)
    from bat3r_core.render.jobs import RenderJob

__all__ = ["posed_vertices", "label_job"]


def posed_vertices(rig: Rig, job: RenderJob) -> np.ndarray:
    """(V, 3) float64: the rig skinned by :mod:`bat3r_core.skinning` with the job's θ and global similarity
    (world frame, metres) — what the worker renders and what the labels ray-cast."""
    import torch

    from bat3r_core.skinning import skin

    tensors = rig.tensors(dtype=torch.float64)
    out = skin(tensors, torch.as_tensor(np.asarray(job.excess_rotations, dtype=np.float64))[None],
               global_scale=torch.tensor([float(job.global_scale)], dtype=torch.float64),
               global_rotation=torch.as_tensor(np.asarray(job.global_rotation, dtype=np.float64))[None],
               global_translation=torch.as_tensor(np.asarray(job.global_translation, dtype=np.float64))[None])
    return out.vertices[0].numpy()


def label_job(rig: Rig, job: RenderJob, num_layers: int = 4, posed: np.ndarray | None = None
              ) -> tuple[np.ndarray, DualPointMaps]:
    """Exact labels of a job: the rig skinned with the job's pose (:func:`posed_vertices`, or ``posed`` when
    given), ray-cast through its camera.

    Returns:
        (posed_vertices (V, 3) float64 world frame metres, :class:`bat3r_core.pointmaps.DualPointMaps`).
    """
    posed = posed_vertices(rig, job) if posed is None else posed
    maps = dual_point_maps(posed, rig.rest_vertices, rig.faces, job.camera, num_layers=num_layers)
    return posed, maps
