"""The in-memory rigged canonical mesh (rest pose) and its validation.

A :class:`Rig` is pure data; files are read and written by :mod:`bat3r_core.rig_io`. Frames and units follow
docs/CONVENTIONS.md: metres, canonical frame +Y up, +Z forward, +X the animal's left.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Rig", "RigError", "find_left_right_pairs", "topological_order"]

WEIGHT_SUM_TOLERANCE = 1e-3


class RigError(ValueError):
    """A rigged mesh is malformed; the message says which part and what was expected."""


_SIDE_PATTERNS = [
    (re.compile(r"^(.*)\.L(\.\d+)?$"), r"\1.R\2", re.compile(r"^(.*)\.R(\.\d+)?$")),
    (re.compile(r"^(.*)_L(_\d+)?$"), r"\1_R\2", None),
    (re.compile(r"^(.*)\.l$"), r"\1.r", None),
    (re.compile(r"^(.*)_l$"), r"\1_r", None),
    (re.compile(r"^(.*)_l_(.*)$"), r"\1_r_\2", None),
    (re.compile(r"^(.*)_L_(.*)$"), r"\1_R_\2", None),
    (re.compile(r"^[Ll]eft(.*)$"), r"Right\1", None),
    (re.compile(r"^(.*)[Ll]eft(.*)$"), r"\1Right\2", None),
]


def _mirror_name(name: str) -> str | None:
    for pat, repl, _ in _SIDE_PATTERNS:
        if pat.match(name):
            other = pat.sub(repl, name)
            return other
    return None


def find_left_right_pairs(joint_names: list[str] | tuple[str, ...], joint_positions: np.ndarray,
                          tolerance: float = 0.05) -> tuple[tuple[int, int], ...]:
    """Left/right joint pairs ``(left, right)``.

    First by name convention (``x.L``/``x.R``, ``x_L``/``x_R``, ``left*``/``right*``, case variants); joints not
    paired by name are paired by mirroring their rest positions in ``x`` (the canonical frame's lateral axis):
    ``j`` (with ``x > tolerance``) pairs with the unpaired joint nearest to its mirror image if that is closer than
    ``tolerance`` times the skeleton's extent.

    Args:
        joint_names: J names.
        joint_positions: (J, 3) rest joint origins, canonical frame.
    """
    names = list(joint_names)
    index = {n: i for i, n in enumerate(names)}
    lower = {n.lower(): i for i, n in enumerate(names)}
    pairs: list[tuple[int, int]] = []
    paired: set[int] = set()
    for i, n in enumerate(names):
        other = _mirror_name(n)
        if other is None:
            continue
        j = index.get(other, lower.get(other.lower()))
        if j is not None and j != i and i not in paired and j not in paired:
            pairs.append((i, j))
            paired.update((i, j))
    pos = np.asarray(joint_positions, dtype=np.float64)
    extent = float(np.ptp(pos, axis=0).max()) if len(pos) > 1 else 1.0
    thresh = tolerance * extent
    for i in range(len(names)):
        if i in paired or pos[i, 0] <= thresh:
            continue
        mirror = pos[i] * np.array([-1.0, 1.0, 1.0])
        cands = [j for j in range(len(names)) if j not in paired and j != i and pos[j, 0] < -thresh]
        if not cands:
            continue
        d = np.linalg.norm(pos[cands] - mirror, axis=1)
        k = int(np.argmin(d))
        if d[k] < thresh:
            pairs.append((i, cands[k]))
            paired.update((i, cands[k]))
    return tuple(sorted(pairs))


def topological_order(parents: np.ndarray, joint_names: list[str] | tuple[str, ...] | None = None) -> np.ndarray:
    """Order joints so every parent precedes its children; raise :class:`RigError` on cycles or several roots.

    Args:
        parents: (J,) parent index per joint, -1 for the root.
    Returns:
        (J,) permutation ``order`` such that joint ``order[k]`` comes k-th.
    """
    parents = np.asarray(parents, dtype=np.int64)
    n = len(parents)
    names = list(joint_names) if joint_names is not None else [str(i) for i in range(n)]
    if n == 0:
        raise RigError("the skeleton has no joints")
    bad = [i for i, p in enumerate(parents) if p < -1 or p >= n or p == i]
    if bad:
        raise RigError(f"joint '{names[bad[0]]}' has an invalid parent index {parents[bad[0]]} "
                       f"(expected -1 or another joint's index in [0, {n}))")
    roots = [i for i, p in enumerate(parents) if p == -1]
    if len(roots) != 1:
        if not roots:
            raise RigError("the joint hierarchy has a cycle: no joint is a root (parent -1)")
        raise RigError(f"the joint hierarchy must have exactly one root, found {len(roots)}: "
                       f"{[names[r] for r in roots]}")
    # stable topological order: keeps the given order wherever it is already valid
    placed = np.zeros(n, dtype=bool)
    order: list[int] = []
    progress = True
    while progress and len(order) < n:
        progress = False
        for i in range(n):
            if not placed[i] and (parents[i] == -1 or placed[parents[i]]):
                placed[i] = True
                order.append(i)
                progress = True
    if len(order) != n:
        missing = sorted(set(range(n)) - set(order))
        raise RigError(f"the joint hierarchy has a cycle: joints {[names[m] for m in missing][:5]} are not "
                       f"reachable from the root '{names[roots[0]]}'")
    return np.asarray(order, dtype=np.int64)


@dataclass(frozen=True, eq=False)
class Rig:
    """A rigged, skinned canonical mesh in its rest pose.

    Attributes:
        name: asset name.
        rest_vertices: (V, 3) float64, metres, canonical frame.
        faces: (F, 3) int64 triangle vertex indices (counter-clockwise seen from outside).
        joint_names: J unique names, in topological order (parents first).
        parents: (J,) int64, ``parents[j] < j``; -1 for the single root.
        rest_transforms: (J, 4, 4) float64 rest joint frames → canonical frame (``G_rest``; inverse bind matrices
            are their inverses).
        skin_weights: (V, J) float64, non-negative, rows sum to 1.
        uvs: (V, 2) float64 texture coordinates or None.
        left_right_pairs: (left, right) joint index pairs.
    """

    name: str
    rest_vertices: np.ndarray
    faces: np.ndarray
    joint_names: tuple[str, ...]
    parents: np.ndarray
    rest_transforms: np.ndarray
    skin_weights: np.ndarray
    uvs: np.ndarray | None = None
    left_right_pairs: tuple[tuple[int, int], ...] = field(default=())

    def __post_init__(self) -> None:
        v = np.asarray(self.rest_vertices, dtype=np.float64)
        f = np.asarray(self.faces)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
            raise RigError(f"rest_vertices must have shape (V, 3) with V > 0, got {v.shape}")
        if not np.isfinite(v).all():
            bad = int(np.argwhere(~np.isfinite(v).all(1))[0, 0])
            raise RigError(f"rest_vertices contain NaN/inf values (first at vertex {bad})")
        if f.ndim != 2 or f.shape[1] != 3:
            raise RigError(f"faces must be triangles with shape (F, 3), got {f.shape}")
        if f.size and (f.min() < 0 or f.max() >= len(v)):
            raise RigError(f"faces index vertices outside [0, {len(v)}): min {f.min()}, max {f.max()}")
        names = tuple(self.joint_names)
        j = len(names)
        if len(set(names)) != j:
            raise RigError("joint names must be unique")
        parents = np.asarray(self.parents, dtype=np.int64)
        if parents.shape != (j,):
            raise RigError(f"parents must have shape ({j},), got {parents.shape}")
        topological_order(parents, names)  # cycles / several roots
        if not all(parents[k] < k for k in range(j)):
            raise RigError("joints must be in topological order (parents[j] < j); use Rig.from_unordered")
        g = np.asarray(self.rest_transforms, dtype=np.float64)
        if g.shape != (j, 4, 4) or not np.isfinite(g).all():
            raise RigError(f"rest_transforms must be finite with shape ({j}, 4, 4), got {g.shape}")
        w = np.asarray(self.skin_weights, dtype=np.float64)
        if w.shape != (len(v), j):
            raise RigError(f"skin_weights must have shape (V={len(v)}, J={j}), got {w.shape}")
        if not np.isfinite(w).all() or (w < -1e-9).any():
            raise RigError("skin_weights must be finite and non-negative")
        sums = w.sum(1)
        off = np.abs(sums - 1.0)
        if (off > WEIGHT_SUM_TOLERANCE).any():
            k = int(np.argmax(off))
            raise RigError(f"skin weights of vertex {k} sum to {sums[k]:.6f}; every vertex's weights must sum to 1 "
                           f"(tolerance {WEIGHT_SUM_TOLERANCE})")
        w = np.clip(w, 0.0, None)
        w = w / w.sum(1, keepdims=True)
        uvs = None if self.uvs is None else np.asarray(self.uvs, dtype=np.float64)
        if uvs is not None and uvs.shape != (len(v), 2):
            raise RigError(f"uvs must have shape (V={len(v)}, 2), got {uvs.shape}")
        for name, arr in (("rest_vertices", v), ("faces", f.astype(np.int64)), ("parents", parents),
                          ("rest_transforms", g), ("skin_weights", w), ("uvs", uvs)):
            if arr is not None:
                arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "joint_names", names)
        if not self.left_right_pairs:
            object.__setattr__(self, "left_right_pairs", find_left_right_pairs(names, g[:, :3, 3]))

    @staticmethod
    def from_unordered(name: str, rest_vertices: np.ndarray, faces: np.ndarray, joint_names: list[str],
                       parents: np.ndarray, rest_transforms: np.ndarray, skin_weights: np.ndarray,
                       uvs: np.ndarray | None = None) -> "Rig":
        """Build a rig from joints in any order, reordering them topologically (weights columns follow)."""
        order = topological_order(parents, joint_names)
        inv = np.empty_like(order)
        inv[order] = np.arange(len(order))
        parents = np.asarray(parents, dtype=np.int64)
        new_parents = np.array([inv[parents[o]] if parents[o] >= 0 else -1 for o in order], dtype=np.int64)
        return Rig(name=name, rest_vertices=rest_vertices, faces=faces,
                   joint_names=tuple(joint_names[o] for o in order), parents=new_parents,
                   rest_transforms=np.asarray(rest_transforms)[order],
                   skin_weights=np.asarray(skin_weights)[:, order], uvs=uvs)

    @property
    def num_vertices(self) -> int:
        return int(self.rest_vertices.shape[0])

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    @property
    def rest_joint_positions(self) -> np.ndarray:
        """(J, 3) rest joint origins, canonical frame, metres."""
        return self.rest_transforms[:, :3, 3]

    def joint_index(self, name: str) -> int:
        """Index of joint ``name``; ``KeyError`` listing the available names if absent."""
        try:
            return self.joint_names.index(name)
        except ValueError:
            raise KeyError(f"rig '{self.name}' has no joint named '{name}'; joints: {list(self.joint_names)}") \
                from None

    def descendants(self, j: int) -> np.ndarray:
        """Indices of joint ``j`` and its whole subtree, sorted."""
        inside = np.zeros(self.num_joints, dtype=bool)
        inside[j] = True
        for k in range(j + 1, self.num_joints):
            if self.parents[k] >= 0 and inside[self.parents[k]]:
                inside[k] = True
        return np.flatnonzero(inside)

    def tensors(self, dtype=None, device="cpu"):
        """The :class:`bat3r_core.skinning.RigTensors` of this rig."""
        import torch

        from .skinning import RigTensors

        return RigTensors.from_arrays(self.rest_vertices, self.parents, self.rest_transforms, self.skin_weights,
                                      dtype=dtype or torch.float32, device=device)

    def summary(self) -> str:
        ext = np.ptp(self.rest_vertices, axis=0)
        return (f"rig '{self.name}': {self.num_vertices} vertices, {len(self.faces)} faces, "
                f"{self.num_joints} joints ({len(self.left_right_pairs)} left/right pairs), "
                f"extent x/y/z = {ext[0]:.3f}/{ext[1]:.3f}/{ext[2]:.3f} m, "
                f"UVs {'yes' if self.uvs is not None else 'no'}")
