"""A category's rigged asset as the pipeline uses it: normalised once, and its body frame read off the skeleton.

:func:`prepare_asset` reads a user's file in bat3r's canonical rest pose (:func:`bat3r_core.rig_io.read_asset`: the
bind pose, scene-graph transforms applied, morph targets at their default weights, rigid children attached to their
joint), scales it to metres and turns it Y-up, refuses an implausible size, and writes it once as a bat3r GLB (the
asset's own base-colour texture embedded) that every stage then loads: the render worker, labelling, fitting and
evaluation all see the same vertices, whatever the file's animations, units or node pose said.

:func:`propose_body_frame` finds the body-centric frame joints from the skeleton alone (``body_frame: auto`` in the
catalog): the mirror plane of the rest mesh, the joints on it (spine, neck, head, tail), the leg pairs (left/right
joint pairs whose chains reach the ground), the spine between the hind and front legs, and the head end (joint names,
else the heavier end of the body).
"""
from __future__ import annotations

import hashlib
import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .rig import Rig, RigError
from .rig_io import AssetInfo, check_plausible_size, load_rig, read_any_asset, save_rig_glb
from .shards import atomic_write

__all__ = ["PreparedAsset", "prepare_asset", "BodyFrameProposal", "propose_body_frame", "ASSET_FORMAT_VERSION"]

ASSET_FORMAT_VERSION = 4
"""Bumped when the normalisation changes, so that normalised GLBs written by older code are rebuilt. 2: quantized
positions dequantized, Draco decoded, textures named by extensions and through KHR_texture_transform, skin weights
normalised. 3: several materials packed into one base-colour atlas, the base-colour factor tinting textures. 4: COLOR_0
vertex colours kept."""


@dataclass(frozen=True)
class PreparedAsset:
    """A normalised asset.

    Attributes:
        path: the bat3r GLB (metres, +Y up, bind pose, base-colour texture embedded when the file has one).
        rig: its rig (as :func:`bat3r_core.rig_io.load_rig` reads ``path`` back).
        info: what the source file held and what was done with it.
        source: the user's file.
    """

    path: Path
    rig: Rig
    info: AssetInfo
    source: Path


def _file_digest(path: Path) -> str:
    h = hashlib.sha256()
    files = [path]
    if path.suffix.lower() == ".gltf":  # its buffers and images are part of the asset
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
            uris = [b.get("uri", "") for b in data.get("buffers", [])] + [i.get("uri", "") for i in
                                                                         data.get("images", [])]
            files += [path.parent / u for u in uris if u and not u.startswith("data:")]
        except (OSError, ValueError):
            pass
    for f in files:
        if f.is_file():
            with open(f, "rb") as fh:
                for chunk in iter(lambda: fh.read(1 << 20), b""):
                    h.update(chunk)
    return h.hexdigest()


def prepare_asset(source: str | os.PathLike, out_dir: str | os.PathLike, scale: float = 1.0,
                  up_axis: str = "+Y", name: str | None = None) -> PreparedAsset:
    """Normalise ``source`` into ``out_dir/<name>-<hash>.glb`` (reused when it already exists).

    Args:
        source: the rigged asset (.glb/.gltf/.fbx/.blend).
        out_dir: where normalised assets live (the pipeline uses ``<storage root>/_assets``).
        scale: file units → metres (the catalog's ``asset_scale``; 0.01 for a file in centimetres).
        up_axis: the file's up axis (the catalog's ``up_axis``), one of :data:`bat3r_core.rig_io.UP_AXES`.
        name: file name stem (default: the source's stem).

    Raises:
        FileNotFoundError: ``source`` does not exist.
        RigError: not a usable rig, or an implausible size (the message gives the extent and the fix).
    """
    source = Path(source)
    rig, info = read_any_asset(source, scale, up_axis)
    check_plausible_size(rig, source, scale)
    key = hashlib.sha256(json.dumps({"file": _file_digest(source), "scale": float(scale),
                                     "up_axis": info.up_axis, "version": ASSET_FORMAT_VERSION}).encode())
    out = Path(out_dir) / f"{name or source.stem}-{key.hexdigest()[:12]}.glb"
    if not out.is_file():
        save_rig_glb(rig, out, texture=info.texture, vertex_colors=info.vertex_colors)
        report = {k: v for k, v in info.__dict__.items() if k not in ("texture", "vertex_colors")}
        atomic_write(out.with_suffix(".json"), lambda tmp: Path(tmp).write_text(json.dumps(report, indent=1)))
    return PreparedAsset(path=out, rig=load_rig(out), info=info, source=source)


# ------------------------------------------------------------------------------------------------- body frame
_HEAD = re.compile(r"head|neck|skull|jaw|nose|snout|muzzle|ear|eye|mouth", re.IGNORECASE)
_TAIL = re.compile(r"tail", re.IGNORECASE)


@dataclass(frozen=True)
class BodyFrameProposal:
    """A body frame read off the skeleton.

    Attributes:
        origin: mid-spine joint name. forward: ``(tail side, head side)`` adjacent spine joints.
        horizontal: ``(left, right)`` hind-leg root joints.
        spine: the spine joints from the hind legs to the front legs, tail side first.
        legs: ``(left, right)`` leg root pairs, hind first.
        lateral_axis: (3,) unit normal of the mirror plane (canonical frame; +X for a conforming asset).
        mirror_error: median distance (metres) of the mirrored rest vertices to the mesh, relative to its length.
        head_from: how the head end was decided (``"joint names"`` or ``"vertex mass"``).
    """

    origin: str
    forward: tuple[str, str]
    horizontal: tuple[str, str]
    spine: tuple[str, ...]
    legs: tuple[tuple[str, str], ...]
    lateral_axis: np.ndarray
    mirror_error: float
    head_from: str

    def as_spec(self) -> dict:
        """The catalog's ``body_frame`` mapping."""
        return {"origin": self.origin, "forward": list(self.forward), "horizontal": list(self.horizontal)}


def _mirror_plane(vertices: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """Vertical mirror plane of a Y-up mesh: (unit horizontal normal, median mirrored distance / length)."""
    from scipy.spatial import cKDTree

    v = vertices if len(vertices) <= 3000 else vertices[rng.choice(len(vertices), 3000, replace=False)]
    tree = cKDTree(vertices)
    centre = vertices.mean(0)
    length = float(np.ptp(vertices, axis=0).max())
    best = (np.inf, np.array([1.0, 0.0, 0.0]))
    for phi in np.deg2rad(np.arange(0.0, 180.0, 1.0)):
        n = np.array([np.cos(phi), 0.0, np.sin(phi)])
        mirrored = v - 2.0 * ((v - centre) @ n)[:, None] * n
        err = float(np.median(tree.query(mirrored)[0]))
        if err < best[0]:
            best = (err, n)
    return best[1], best[0] / max(length, 1e-12)


def _path(rig: Rig, a: int, b: int) -> list[int]:
    """Joints on the tree path from ``a`` to ``b`` (both included)."""
    def up(j):
        out = [j]
        while rig.parents[out[-1]] >= 0:
            out.append(int(rig.parents[out[-1]]))
        return out
    pa, pb = up(a), up(b)
    common = next(j for j in pa if j in set(pb))
    return pa[:pa.index(common) + 1] + pb[:pb.index(common)][::-1]


def propose_body_frame(rig: Rig, seed: int = 0) -> BodyFrameProposal:
    """Body-frame joints of ``rig`` from its skeleton and rest mesh (canonical frame, +Y up).

    Raises:
        RigError: the skeleton has no left/right leg pairs to span the horizontal plane, or no spine between them;
            the message says what was found (set ``body_frame`` by hand in the catalog then).
    """
    rng = np.random.default_rng(seed)
    verts = rig.rest_vertices
    joints = rig.rest_joint_positions
    names = rig.joint_names
    lateral, mirror_error = _mirror_plane(verts, rng)
    length = float(np.ptp(verts, axis=0).max())
    height = float(np.ptp(verts[:, 1]))
    ground = float(verts[:, 1].min())
    centre = verts.mean(0)
    side = (joints - centre) @ lateral
    midline = np.abs(side) < 0.03 * length
    along = np.cross(lateral, [0.0, 1.0, 0.0])  # horizontal, perpendicular to the mirror normal
    along /= np.linalg.norm(along)
    pairs = [(int(a), int(b)) for a, b in rig.left_right_pairs]
    # leg roots: the outermost pairs below midline joints whose chains reach near the ground
    legs = []
    for a, b in pairs:
        pa, pb = int(rig.parents[a]), int(rig.parents[b])
        if pa < 0 or pb < 0 or pa != pb and not (midline[pa] and midline[pb]):
            continue
        if not midline[pa]:
            continue
        low = min(joints[rig.descendants(a), 1].min(), joints[rig.descendants(b), 1].min())
        if low - ground < 0.3 * height:
            legs.append((a, b))
    if len(legs) < 2:
        raise RigError(f"rig '{rig.name}': found {len(legs)} leg pair(s) among the left/right joint pairs "
                       f"{[(names[a], names[b]) for a, b in pairs]}; body_frame: auto needs a hind and a front "
                       f"pair of legs below the spine. Set body_frame (origin, forward, horizontal) by hand.")
    # head end: joint names, else the end of the body with more mesh
    proj = joints @ along
    head_joints = [j for j in range(rig.num_joints) if midline[j] and _HEAD.search(names[j])]
    tail_joints = [j for j in range(rig.num_joints) if midline[j] and _TAIL.search(names[j])]
    if head_joints or tail_joints:
        h = np.mean(proj[head_joints]) if head_joints else None
        t = np.mean(proj[tail_joints]) if tail_joints else None
        mid = float(np.mean(proj[[j for a, b in legs for j in (a, b)]]))
        score = (h - mid if h is not None else 0.0) - (t - mid if t is not None else 0.0)
        head_from = "joint names"
    else:
        vp = verts @ along
        lo, hi = np.quantile(vp, [0.15, 0.85])
        radial = np.linalg.norm((verts - centre) - np.outer(vp - centre @ along, along), axis=1)
        score = float(radial[vp >= hi].sum() - radial[vp <= lo].sum())  # a head is bulkier than a tail
        head_from = "vertex mass"
    if score < 0:
        along = -along
        proj = -proj
    legs.sort(key=lambda p: float(proj[list(p)].mean()))
    hind, front = legs[0], legs[-1]
    spine = _path(rig, int(rig.parents[hind[0]]), int(rig.parents[front[0]]))
    spine = [j for j in spine if midline[j]] or spine
    if len(spine) >= 2:
        k = max(0, (len(spine) - 1) // 2)
        a, b = spine[k], spine[k + 1]
        origin = spine[k] if len(spine) % 2 else b
    else:  # both leg pairs hang from one joint: its child towards the head sets the forward axis
        children = [c for c in range(rig.num_joints) if rig.parents[c] == spine[0] and midline[c]]
        if not children:
            raise RigError(f"rig '{rig.name}': the leg pairs {names[hind[0]]}/{names[front[0]]} hang from one joint "
                           f"with no spine joint beside it; set body_frame by hand in the catalog")
        b = max(children, key=lambda c: proj[c])
        a = origin = spine[0]
    if proj[b] < proj[a]:
        a, b = b, a
    left_axis = np.cross([0.0, 1.0, 0.0], along)  # the animal's left: up x forward (+X for a +Z-facing asset)
    left, right = hind if joints[hind[0]] @ left_axis > joints[hind[1]] @ left_axis else hind[::-1]
    return BodyFrameProposal(origin=names[origin], forward=(names[a], names[b]), horizontal=(names[left], names[right]),
                             spine=tuple(names[j] for j in spine),
                             legs=tuple((names[x], names[y]) for x, y in legs), lateral_axis=lateral,
                             mirror_error=mirror_error, head_from=head_from)
