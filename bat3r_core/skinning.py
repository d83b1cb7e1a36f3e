"""Batched, differentiable linear blend skinning of a rig (torch).

Conventions (the single place they are defined; see also docs/CONVENTIONS.md):

* ``excess_rotations`` θ ``(B, J, 3)``: axis-angle, radians, each joint rotating about its own origin in its own
  **rest** frame. Zero θ is the rest pose.
* ``bone_scales`` S ``(B, J)``: uniform scale of joint ``j``'s frame, inherited by its subtree.
* Joint ``j``'s posed global transform: ``G_j = G_parent(j) @ L_j @ diag(s_j · R(θ_j), 1)`` with the rest local
  transform ``L_j = G_rest[parent]^-1 @ G_rest[j]`` (``G_parent(root) = I``).
* Skinning: ``v' = Σ_j w_vj · G_j @ G_rest[j]^-1 @ v``.
* Global similarity: ``x_out = s · R_g @ x + t_g`` applied after skinning (to vertices and joints).

Everything is pure tensor math and works for float32/float64 on CPU and CUDA.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

__all__ = [
    "axis_angle_to_matrix",
    "matrix_to_axis_angle",
    "RigTensors",
    "SkinningOutput",
    "forward_kinematics",
    "skin",
    "apply_similarity",
]


def axis_angle_to_matrix(axis_angle: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula. ``axis_angle (..., 3)`` radians → rotation matrices ``(..., 3, 3)``.

    Smooth at zero (uses the Taylor expansion of sin(x)/x and (1-cos x)/x² below 1e-4 rad), so gradients at
    the rest pose are exact.
    """
    if axis_angle.shape[-1] != 3:
        raise ValueError(f"axis_angle must have a last dimension of 3, got shape {tuple(axis_angle.shape)}")
    theta2 = (axis_angle * axis_angle).sum(-1, keepdim=True)  # (..., 1)
    small = theta2 < 1e-8
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = torch.sqrt(safe2)
    # a = sin(t)/t, b = (1 - cos t)/t²
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / safe2)
    x, y, z = axis_angle.unbind(-1)
    zero = torch.zeros_like(x)
    # skew-symmetric cross-product matrix, (..., 3, 3)
    k = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*axis_angle.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=axis_angle.dtype, device=axis_angle.device).expand_as(k)
    return eye + a[..., None] * k + b[..., None] * (k @ k)


def matrix_to_axis_angle(matrix: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``(..., 3, 3)`` → axis-angle ``(..., 3)`` (angle in [0, π]).

    Uses the quaternion route, which is stable near 0 and π.
    """
    if matrix.shape[-2:] != (3, 3):
        raise ValueError(f"matrix must have trailing shape (3, 3), got {tuple(matrix.shape)}")
    m = matrix
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    # four candidate quaternion magnitudes; pick the largest for stability
    q_abs = torch.sqrt(torch.clamp(torch.stack([
        1.0 + tr,
        1.0 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
        1.0 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2],
        1.0 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2],
    ], dim=-1), min=1e-12))
    # candidates (w, x, y, z) each scaled by 4·q_i
    cands = torch.stack([
        torch.stack([q_abs[..., 0] ** 2, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0],
                     m[..., 1, 0] - m[..., 0, 1]], -1),
        torch.stack([m[..., 2, 1] - m[..., 1, 2], q_abs[..., 1] ** 2, m[..., 1, 0] + m[..., 0, 1],
                     m[..., 0, 2] + m[..., 2, 0]], -1),
        torch.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] + m[..., 0, 1], q_abs[..., 2] ** 2,
                     m[..., 2, 1] + m[..., 1, 2]], -1),
        torch.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 2, 0] + m[..., 0, 2], m[..., 2, 1] + m[..., 1, 2],
                     q_abs[..., 3] ** 2], -1),
    ], dim=-2)  # (..., 4, 4)
    cands = cands / (2.0 * q_abs[..., None])
    best = q_abs.argmax(-1)
    quat = torch.gather(cands, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    quat = quat * torch.where(quat[..., :1] < 0, -1.0, 1.0)  # w >= 0 → angle in [0, π]
    quat = quat / quat.norm(dim=-1, keepdim=True)
    w, xyz = quat[..., 0], quat[..., 1:]
    sin_half = xyz.norm(dim=-1)
    angle = 2.0 * torch.atan2(sin_half, w)
    scale = torch.where(sin_half > 1e-8, angle / torch.clamp(sin_half, min=1e-12), 2.0 / torch.clamp(w, min=1e-12))
    return xyz * scale[..., None]


@dataclass(frozen=True)
class RigTensors:
    """The tensors of a rig that skinning needs, on one device and dtype.

    Attributes:
        rest_vertices: (V, 3) canonical frame, metres.
        parents: (J,) int64, ``parents[j] < j``, root = -1.
        rest_transforms: (J, 4, 4) joint frame → canonical frame at rest (``G_rest``).
        inverse_rest_transforms: (J, 4, 4) ``G_rest^-1`` (the inverse bind matrices).
        local_rest_transforms: (J, 4, 4) ``L_j = G_rest[parent]^-1 @ G_rest[j]`` (``G_rest[j]`` for roots).
        skin_weights: (V, J), rows sum to 1.
    """

    rest_vertices: torch.Tensor
    parents: torch.Tensor
    rest_transforms: torch.Tensor
    inverse_rest_transforms: torch.Tensor
    local_rest_transforms: torch.Tensor
    skin_weights: torch.Tensor

    @property
    def num_joints(self) -> int:
        return int(self.parents.shape[0])

    @property
    def num_vertices(self) -> int:
        return int(self.rest_vertices.shape[0])

    @property
    def rest_joint_positions(self) -> torch.Tensor:
        """(J, 3) joint origins at rest, canonical frame."""
        return self.rest_transforms[:, :3, 3]

    @staticmethod
    def from_arrays(rest_vertices: np.ndarray, parents: np.ndarray, rest_transforms: np.ndarray,
                    skin_weights: np.ndarray, dtype: torch.dtype = torch.float32,
                    device: str | torch.device = "cpu") -> "RigTensors":
        """Build from numpy arrays (validated by :class:`bat3r_core.rig.Rig`)."""
        g = torch.tensor(np.asarray(rest_transforms, dtype=np.float64))
        g_inv = torch.linalg.inv(g)
        parents_t = torch.tensor(np.asarray(parents, dtype=np.int64))
        local = g.clone()
        has_parent = parents_t >= 0
        local[has_parent] = g_inv[parents_t[has_parent]] @ g[has_parent]
        # the (V, J) dense weight matrix; float64 inverse kept exact before the cast
        to = dict(dtype=dtype, device=device)
        return RigTensors(
            rest_vertices=torch.tensor(np.asarray(rest_vertices, dtype=np.float64)).to(**to),
            parents=parents_t.to(device),
            rest_transforms=g.to(**to),
            inverse_rest_transforms=g_inv.to(**to),
            local_rest_transforms=local.to(**to),
            skin_weights=torch.tensor(np.asarray(skin_weights, dtype=np.float64)).to(**to),
        )

    def to(self, dtype: torch.dtype | None = None, device: str | torch.device | None = None) -> "RigTensors":
        def cv(t: torch.Tensor) -> torch.Tensor:
            if t.is_floating_point():
                return t.to(dtype=dtype or t.dtype, device=device or t.device)
            return t.to(device=device or t.device)
        return RigTensors(*(cv(getattr(self, f)) for f in self.__dataclass_fields__))


@dataclass(frozen=True)
class SkinningOutput:
    """Result of :func:`skin`.

    Attributes:
        vertices: (B, V, 3) posed vertices (after the global similarity).
        joints: (B, J, 3) posed joint origins (after the global similarity).
        joint_transforms: (B, J, 4, 4) posed global joint transforms ``G_j`` before the global similarity.
    """

    vertices: torch.Tensor
    joints: torch.Tensor
    joint_transforms: torch.Tensor


def _check_batch(name: str, t: torch.Tensor | None, shape: tuple[int, ...]) -> None:
    if t is None:
        return
    if tuple(t.shape) != shape:
        raise ValueError(f"{name} must have shape {shape}, got {tuple(t.shape)}")


def forward_kinematics(rig: RigTensors, excess_rotations: torch.Tensor,
                       bone_scales: torch.Tensor | None = None) -> torch.Tensor:
    """Posed global joint transforms ``G_j`` ``(B, J, 4, 4)`` (canonical frame, no global similarity).

    Args:
        excess_rotations: (B, J, 3) axis-angle, radians, in each joint's rest frame.
        bone_scales: (B, J) positive, or None for all ones.
    """
    if excess_rotations.ndim != 3 or excess_rotations.shape[1:] != (rig.num_joints, 3):
        raise ValueError(f"excess_rotations must have shape (B, {rig.num_joints}, 3), "
                         f"got {tuple(excess_rotations.shape)}")
    b = excess_rotations.shape[0]
    _check_batch("bone_scales", bone_scales, (b, rig.num_joints))
    rot = axis_angle_to_matrix(excess_rotations)  # (B, J, 3, 3)
    if bone_scales is not None:
        rot = rot * bone_scales[..., None, None]
    # local posed transform: L_j @ [sR | 0]
    local_rot = rig.local_rest_transforms[:, :3, :3] @ rot  # (B, J, 3, 3)
    local_t = rig.local_rest_transforms[:, :3, 3].expand(b, -1, -1)  # (B, J, 3)
    parents = rig.parents.tolist()
    g_rot: list[torch.Tensor] = []
    g_t: list[torch.Tensor] = []
    # the kinematic chain is sequential over joints (J ~ 30), batched over B
    for j, p in enumerate(parents):
        if p < 0:
            g_rot.append(local_rot[:, j])
            g_t.append(local_t[:, j])
        else:
            g_rot.append(g_rot[p] @ local_rot[:, j])
            g_t.append((g_rot[p] @ local_t[:, j, :, None])[..., 0] + g_t[p])
    rot_all = torch.stack(g_rot, 1)  # (B, J, 3, 3)
    t_all = torch.stack(g_t, 1)  # (B, J, 3)
    bottom = torch.zeros(b, rig.num_joints, 1, 4, dtype=rot_all.dtype, device=rot_all.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([torch.cat([rot_all, t_all[..., None]], -1), bottom], -2)


def apply_similarity(points: torch.Tensor, scale: torch.Tensor | None, rotation: torch.Tensor | None,
                     translation: torch.Tensor | None) -> torch.Tensor:
    """``s · R @ x + t`` for ``points (B, N, 3)``, ``scale (B,)``, ``rotation (B, 3, 3)``, ``translation (B, 3)``;
    any of the three may be None (identity)."""
    out = points
    if rotation is not None:
        out = out @ rotation.transpose(-1, -2)
    if scale is not None:
        out = out * scale[:, None, None]
    if translation is not None:
        out = out + translation[:, None, :]
    return out


def skin(rig: RigTensors, excess_rotations: torch.Tensor, bone_scales: torch.Tensor | None = None,
         global_scale: torch.Tensor | None = None, global_rotation: torch.Tensor | None = None,
         global_translation: torch.Tensor | None = None) -> SkinningOutput:
    """Linear blend skinning of a batch of poses.

    Args:
        rig: the rig's tensors (dtype/device of the result).
        excess_rotations: (B, J, 3) axis-angle, radians, relative to rest, in each joint's rest frame.
        bone_scales: (B, J) or None (ones).
        global_scale: (B,) or None (1). global_rotation: (B, 3, 3) or None (I). global_translation: (B, 3) or None.

    Returns:
        :class:`SkinningOutput` with vertices (B, V, 3) and joints (B, J, 3), metres, in the frame the global
        similarity maps to (the canonical frame when it is the identity).
    """
    b = excess_rotations.shape[0] if excess_rotations.ndim == 3 else -1
    _check_batch("global_scale", global_scale, (b,))
    _check_batch("global_rotation", global_rotation, (b, 3, 3))
    _check_batch("global_translation", global_translation, (b, 3))
    g = forward_kinematics(rig, excess_rotations, bone_scales)  # (B, J, 4, 4)
    b, j = g.shape[:2]
    skinning_mats = (g @ rig.inverse_rest_transforms)[:, :, :3, :].reshape(b, j, 12)  # (B, J, 12)
    # blend the 3×4 affine parts per vertex with one GEMM: (V, J) @ (B, J, 12) → (B, V, 3, 4)
    blended = torch.matmul(rig.skin_weights, skinning_mats).view(b, -1, 3, 4)
    # apply to the rest vertices elementwise (avoids B·V tiny matmuls): (B, V, 3)
    verts = (blended[..., :3] * rig.rest_vertices[None, :, None, :]).sum(-1) + blended[..., 3]
    joints = g[:, :, :3, 3]
    verts = apply_similarity(verts, global_scale, global_rotation, global_translation)
    joints = apply_similarity(joints, global_scale, global_rotation, global_translation)
    return SkinningOutput(vertices=verts, joints=joints, joint_transforms=g)
