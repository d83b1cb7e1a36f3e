"""The embedded ``toy`` category: a procedural, deterministic, horse-like rigged quadruped.

The body is the zero level set of a smooth union of tapered capsules placed along the skeleton's bones,
meshed with marching cubes and Taubin-smoothed, so it is watertight by construction. Skin weights blend the
bones whose capsule surfaces are nearest to each vertex (a soft-min over capsule distances, top 4 influences).
UVs are a seamless side projection (u along the body, v up), so no vertex is split at a UV seam, and procedural
coat textures are painted in that UV space.

Frames follow docs/CONVENTIONS.md: metres, +Y up, +Z forward (head), +X the animal's left; the hooves stand on y ≈ 0.
Every joint's rest frame is axis-aligned with the canonical frame, so a rotation about +X flexes a joint in the
sagittal plane (positive angles swing a hanging leg backwards).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .rig import Rig

__all__ = ["TOY_JOINTS", "TOY_BODY_FRAME", "build_toy_rig", "toy_coat_texture", "TOY_COATS"]

# name, parent, rest position (x, y, z) in metres, and the capsule radius at the joint end of its bone
_J = [
    ("root", None, (0.0, 1.22, -0.50)),
    ("spine.1", "root", (0.0, 1.24, -0.22)),
    ("spine.2", "spine.1", (0.0, 1.25, 0.08)),
    ("spine.3", "spine.2", (0.0, 1.27, 0.36)),
    ("neck.1", "spine.3", (0.0, 1.40, 0.58)),
    ("neck.2", "neck.1", (0.0, 1.62, 0.76)),
    ("head", "neck.2", (0.0, 1.80, 0.90)),
    ("tail.1", "root", (0.0, 1.33, -0.78)),
    ("tail.2", "tail.1", (0.0, 1.18, -0.90)),
    ("tail.3", "tail.2", (0.0, 1.00, -0.98)),
    ("tail.4", "tail.3", (0.0, 0.82, -1.02)),
]
for _side, _sx in (("L", 1.0), ("R", -1.0)):
    _x = 0.19 * _sx
    _J += [
        (f"upper_arm.{_side}", "spine.3", (_x, 1.08, 0.38)),
        (f"forearm.{_side}", f"upper_arm.{_side}", (_x, 0.76, 0.42)),
        (f"cannon_front.{_side}", f"forearm.{_side}", (_x, 0.42, 0.40)),
        (f"hoof_front.{_side}", f"cannon_front.{_side}", (_x, 0.10, 0.42)),
        (f"thigh.{_side}", "root", (_x, 1.08, -0.56)),
        (f"shin.{_side}", f"thigh.{_side}", (_x, 0.72, -0.64)),
        (f"cannon_hind.{_side}", f"shin.{_side}", (_x, 0.42, -0.70)),
        (f"hoof_hind.{_side}", f"cannon_hind.{_side}", (_x, 0.10, -0.67)),
    ]

TOY_JOINTS: tuple[str, ...] = tuple(n for n, _, _ in _J)
"""Joint names of the toy in topological order."""

TOY_BODY_FRAME = {"origin": "spine.2", "forward": ("spine.1", "spine.2"), "horizontal": ("thigh.L", "thigh.R")}
"""Body-frame joints of the toy (origin, forward pair, horizontal pair) as the data catalog names them."""


@dataclass(frozen=True)
class _Capsule:
    owner: str  # joint whose frame moves this piece
    a: tuple[float, float, float]
    b: tuple[float, float, float]
    ra: float
    rb: float


def _capsules() -> list[_Capsule]:
    pos = {n: p for n, _, p in _J}
    caps = [
        _Capsule("root", pos["root"], pos["spine.1"], 0.27, 0.29),
        _Capsule("root", (0.0, 1.22, -0.50), (0.0, 1.26, -0.66), 0.27, 0.20),  # rump
        _Capsule("spine.1", pos["spine.1"], pos["spine.2"], 0.29, 0.30),
        _Capsule("spine.2", pos["spine.2"], pos["spine.3"], 0.30, 0.28),
        _Capsule("spine.3", pos["spine.3"], pos["neck.1"], 0.27, 0.19),
        _Capsule("neck.1", pos["neck.1"], pos["neck.2"], 0.17, 0.13),
        _Capsule("neck.2", pos["neck.2"], pos["head"], 0.12, 0.11),
        _Capsule("head", pos["head"], (0.0, 1.54, 1.27), 0.115, 0.08),  # skull to muzzle
        _Capsule("head", (0.06, 1.86, 0.86), (0.08, 2.0, 0.84), 0.045, 0.025),  # ear.L
        _Capsule("head", (-0.06, 1.86, 0.86), (-0.08, 2.0, 0.84), 0.045, 0.025),  # ear.R
        _Capsule("tail.1", pos["tail.1"], pos["tail.2"], 0.065, 0.06),
        _Capsule("tail.2", pos["tail.2"], pos["tail.3"], 0.06, 0.05),
        _Capsule("tail.3", pos["tail.3"], pos["tail.4"], 0.05, 0.04),
        _Capsule("tail.4", pos["tail.4"], (0.0, 0.62, -1.06), 0.04, 0.03),
    ]
    for s in ("L", "R"):
        caps += [
            _Capsule(f"upper_arm.{s}", pos[f"upper_arm.{s}"], pos[f"forearm.{s}"], 0.12, 0.085),
            _Capsule(f"forearm.{s}", pos[f"forearm.{s}"], pos[f"cannon_front.{s}"], 0.075, 0.055),
            _Capsule(f"cannon_front.{s}", pos[f"cannon_front.{s}"], pos[f"hoof_front.{s}"], 0.05, 0.05),
            _Capsule(f"hoof_front.{s}", pos[f"hoof_front.{s}"],
                     (pos[f"hoof_front.{s}"][0], 0.05, pos[f"hoof_front.{s}"][2] + 0.03), 0.055, 0.06),
            _Capsule(f"thigh.{s}", pos[f"thigh.{s}"], pos[f"shin.{s}"], 0.15, 0.09),
            _Capsule(f"shin.{s}", pos[f"shin.{s}"], pos[f"cannon_hind.{s}"], 0.075, 0.055),
            _Capsule(f"cannon_hind.{s}", pos[f"cannon_hind.{s}"], pos[f"hoof_hind.{s}"], 0.05, 0.05),
            _Capsule(f"hoof_hind.{s}", pos[f"hoof_hind.{s}"],
                     (pos[f"hoof_hind.{s}"][0], 0.05, pos[f"hoof_hind.{s}"][2] + 0.03), 0.055, 0.06),
        ]
    return caps


def _capsule_distances(points: np.ndarray, caps: list[_Capsule]) -> np.ndarray:
    """Signed distance-like values of ``points (N, 3)`` to every tapered capsule → ``(N, C)``."""
    a = np.array([c.a for c in caps])  # (C, 3)
    b = np.array([c.b for c in caps])
    ra = np.array([c.ra for c in caps])
    rb = np.array([c.rb for c in caps])
    ab = b - a
    denom = np.maximum((ab * ab).sum(1), 1e-12)
    rel = points[:, None, :] - a[None]  # (N, C, 3)
    t = np.clip((rel * ab[None]).sum(-1) / denom[None], 0.0, 1.0)  # (N, C)
    closest = a[None] + t[..., None] * ab[None]
    return np.linalg.norm(points[:, None, :] - closest, axis=-1) - (ra[None] + t * (rb - ra)[None])


def _smooth_union(d: np.ndarray, k: float) -> np.ndarray:
    """Exponential smooth minimum over the last axis (blends the capsules into one organic surface)."""
    m = d.min(-1, keepdims=True)
    return (m - k * np.log(np.exp(-(d - m) / k).sum(-1, keepdims=True)))[..., 0]


@lru_cache(maxsize=4)
def _toy_mesh(voxel: float) -> tuple[np.ndarray, np.ndarray]:
    import trimesh
    from skimage.measure import marching_cubes

    caps = _capsules()
    lo = np.array([-0.42, -0.08, -1.20])
    hi = np.array([0.42, 2.08, 1.40])
    axes = [np.arange(lo[i], hi[i] + voxel, voxel) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    field = np.concatenate([_smooth_union(_capsule_distances(chunk, caps), 0.035)
                            for chunk in np.array_split(grid, 8)])
    field = field.reshape(len(axes[0]), len(axes[1]), len(axes[2]))
    verts, faces, _, _ = marching_cubes(field, level=0.0, spacing=(voxel, voxel, voxel))
    verts = verts + lo
    mesh = trimesh.Trimesh(verts, faces[:, ::-1], process=True)  # skimage winds inward for this sign
    mesh.merge_vertices()
    components = mesh.split(only_watertight=False)
    mesh = max(components, key=lambda m: len(m.faces))
    trimesh.smoothing.filter_taubin(mesh, lamb=0.5, nu=-0.53, iterations=12)
    if mesh.volume < 0:
        mesh.invert()
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


def _skin_weights(verts: np.ndarray, caps: list[_Capsule], tau: float = 0.02, influences: int = 4) -> np.ndarray:
    d = _capsule_distances(verts, caps)  # (V, C)
    owners = [TOY_JOINTS.index(c.owner) for c in caps]
    j = len(TOY_JOINTS)
    # per joint: the nearest of its capsules
    per_joint = np.full((len(verts), j), np.inf)
    for ci, o in enumerate(owners):
        per_joint[:, o] = np.minimum(per_joint[:, o], d[:, ci])
    rel = per_joint - per_joint.min(1, keepdims=True)
    w = np.exp(-rel / tau)
    # keep the strongest influences; drop negligible ones so weights stay local
    order = np.argsort(-w, axis=1)
    keep = np.zeros_like(w, dtype=bool)
    np.put_along_axis(keep, order[:, :influences], True, axis=1)
    w = np.where(keep & (w > 1e-3), w, 0.0)
    return w / w.sum(1, keepdims=True)


def build_toy_rig(voxel: float = 0.042) -> Rig:
    """The toy quadruped rig (deterministic; about 2.4 m long, 2-6K vertices, 27 joints).

    Args:
        voxel: marching-cubes grid spacing in metres (controls the vertex count).
    """
    verts, faces = _toy_mesh(float(voxel))
    caps = _capsules()
    parents = np.array([-1 if p is None else TOY_JOINTS.index(p) for _, p, _ in _J], dtype=np.int64)
    rest = np.tile(np.eye(4), (len(_J), 1, 1))
    rest[:, :3, 3] = np.array([p for _, _, p in _J])
    weights = _skin_weights(verts, caps)
    lo, hi = verts.min(0), verts.max(0)
    uvs = np.stack([(verts[:, 2] - lo[2]) / (hi[2] - lo[2]), (verts[:, 1] - lo[1]) / (hi[1] - lo[1])], 1)
    return Rig(name="toy", rest_vertices=verts, faces=faces, joint_names=TOY_JOINTS, parents=parents,
               rest_transforms=rest, skin_weights=weights, uvs=uvs)


TOY_COATS = ("bay", "chestnut", "grey", "pinto")
_COAT_COLOURS = {
    "bay": ((120, 70, 35), (35, 25, 20)),
    "chestnut": ((165, 85, 40), (120, 60, 30)),
    "grey": ((185, 182, 178), (90, 88, 86)),
    "pinto": ((235, 230, 220), (70, 45, 30)),
}


def toy_coat_texture(coat: str = "bay", size: int = 256, seed: int = 0) -> np.ndarray:
    """A procedural coat in the toy's UV space (u along the body tail→muzzle, v up) → ``(size, size, 3) uint8``.

    Row 0 of the image is the top (v = 1). Coats: ``bay``, ``chestnut``, ``grey`` (dappled), ``pinto`` (patches);
    all have darker lower legs and a darker mane/back line, with seeded low-frequency noise.
    """
    if coat not in _COAT_COLOURS:
        raise ValueError(f"coat must be one of {TOY_COATS}, got {coat!r}")
    if size < 8:
        raise ValueError(f"size must be >= 8, got {size}")
    import cv2

    rng = np.random.default_rng(seed + 7919 * TOY_COATS.index(coat))
    base, dark = (np.array(c, dtype=np.float64) / 255.0 for c in _COAT_COLOURS[coat])
    v = np.linspace(1.0, 0.0, size)[:, None] * np.ones((1, size))  # v per row (top = 1)

    def noise(scale: int) -> np.ndarray:
        small = rng.random((scale, scale))
        return cv2.resize(small, (size, size), interpolation=cv2.INTER_CUBIC)

    n = 0.6 * noise(6) + 0.4 * noise(24)
    img = base[None, None] * (0.85 + 0.3 * n[..., None])
    legs = np.clip((0.28 - v) / 0.08, 0.0, 1.0)[..., None]  # dark socks below knee height
    img = img * (1 - legs) + dark[None, None] * legs
    spots = noise(10)
    if coat == "grey":
        dapple = (spots > 0.62)[..., None]
        img = np.where(dapple, img * 0.8, img)
    if coat == "pinto":
        patch = (noise(5) > 0.55)[..., None] & (v[..., None] > 0.3)
        img = np.where(patch, dark[None, None] * (0.9 + 0.2 * n[..., None]), img)
    mane = np.clip((v - 0.8) / 0.06, 0.0, 1.0)[..., None] * 0.6
    img = img * (1 - mane) + dark[None, None] * mane
    return (np.clip(img, 0.0, 1.0) * 255).astype(np.uint8)
