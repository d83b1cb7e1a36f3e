"""Reading and writing rigged meshes: glTF/GLB natively (pygltflib), FBX and .blend through Blender.

``load_rig(path)`` returns a validated :class:`bat3r_core.rig.Rig`; ``save_rig_glb(rig, path)`` writes a GLB with a
real skin (joint nodes, inverse bind matrices, JOINTS_n/WEIGHTS_n) that Blender's importer and
``load_rig`` read back.
"""
from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import pygltflib
from scipy.spatial.transform import Rotation

from .rig import Rig, RigError
from .shards import atomic_write

__all__ = ["load_rig", "read_asset", "read_any_asset", "save_rig_glb", "check_plausible_size", "up_axis_rotation",
           "AssetInfo", "RigError", "UP_AXES", "PLAUSIBLE_LENGTH_M"]

_COMPONENT = {
    pygltflib.FLOAT: np.float32,
    pygltflib.UNSIGNED_INT: np.uint32,
    pygltflib.UNSIGNED_SHORT: np.uint16,
    pygltflib.UNSIGNED_BYTE: np.uint8,
    pygltflib.SHORT: np.int16,
    pygltflib.BYTE: np.int8,
}
_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
_TRIANGLES, _TRIANGLE_STRIP, _TRIANGLE_FAN = 4, 5, 6
_NOT_SURFACES = {0: "POINTS", 1: "LINES", 2: "LINE_LOOP", 3: "LINE_STRIP"}
_MAX_INFLUENCE_SETS = 2  # JOINTS_0/1, WEIGHTS_0/1: up to 8 influences per vertex
_WEIGHT_SUM_TOLERANCE = 1e-3  # weight sums further from 1 are reported (and normalised like all others)

DRACO = "KHR_draco_mesh_compression"
"""Draco-compressed geometry: the accessors hold no data; the primitive's Draco buffer is decoded (DracoPy) and its
attributes found by the unique ids the extension names."""
QUANTIZATION = "KHR_mesh_quantization"
"""Integer vertex attributes; a skinned mesh's dequantization sits in the inverse bind matrices (see read_asset)."""
_NOT_READABLE = {
    "EXT_meshopt_compression": "meshoptimizer-compressed buffers, which neither bat3r nor Blender's importer decode",
    "KHR_meshopt_compression": "meshoptimizer-compressed buffers, which neither bat3r nor Blender's importer decode",
}
_DECODE_HINT = ("write it uncompressed first, e.g. `npx @gltf-transform/cli copy IN.glb OUT.glb` "
                "(gltf-transform decodes meshopt and writes plain buffers)")


def _read_accessor(gltf: pygltflib.GLTF2, blob: bytes | Sequence[bytes | None], index: int, path: Path
                   ) -> np.ndarray:
    """Accessor ``index`` as an (count, components) array. blob: the bytes of each buffer (one ``bytes``: buffer 0
    only, as a GLB's binary chunk)."""
    blobs = [blob] if isinstance(blob, (bytes, bytearray, memoryview)) or blob is None else list(blob)

    def buffer_of(view: pygltflib.BufferView) -> bytes:
        data = blobs[view.buffer] if 0 <= view.buffer < len(blobs) else None
        if data is None:
            raise RigError(f"{path}: accessor {index} reads buffer {view.buffer}, which has no data")
        return data

    acc = gltf.accessors[index]
    dtype = np.dtype(_COMPONENT[acc.componentType]).newbyteorder("<")
    ncomp = _NCOMP[acc.type]
    if acc.bufferView is None:
        out = np.zeros((acc.count, ncomp), dtype=dtype)
    else:
        view = gltf.bufferViews[acc.bufferView]
        blob = buffer_of(view)
        start = (view.byteOffset or 0) + (acc.byteOffset or 0)
        elem = dtype.itemsize * ncomp
        stride = view.byteStride or elem
        if stride == elem:
            out = np.frombuffer(blob, dtype=dtype, count=acc.count * ncomp, offset=start).reshape(acc.count, ncomp)
        else:
            raw = np.frombuffer(blob, dtype=np.uint8, count=stride * (acc.count - 1) + elem, offset=start)
            rows = np.lib.stride_tricks.as_strided(raw, shape=(acc.count, elem), strides=(stride, 1))
            out = rows.copy().view(dtype).reshape(acc.count, ncomp)
    out = np.array(out)
    if acc.sparse is not None:  # a few replaced elements (Blender writes morph targets this way)
        sp = acc.sparse

        def view_bytes(bv: int, offset: int | None) -> tuple[bytes, int]:
            v = gltf.bufferViews[bv]
            return buffer_of(v), (v.byteOffset or 0) + (offset or 0)

        idx_dtype = np.dtype(_COMPONENT[sp.indices.componentType]).newbyteorder("<")
        data, at = view_bytes(sp.indices.bufferView, sp.indices.byteOffset)
        idx = np.frombuffer(data, dtype=idx_dtype, count=sp.count, offset=at).astype(np.int64)
        data, at = view_bytes(sp.values.bufferView, sp.values.byteOffset)
        values = np.frombuffer(data, dtype=dtype, count=sp.count * ncomp, offset=at).reshape(sp.count, ncomp)
        if idx.size and (idx.min() < 0 or idx.max() >= acc.count):
            raise RigError(f"{path}: sparse accessor {index} replaces element {idx.max()} of {acc.count}")
        out[idx] = values
    if acc.normalized and acc.componentType != pygltflib.FLOAT:
        out = np.maximum(out.astype(np.float64) / np.iinfo(dtype).max, -1.0)  # glTF: max(c / 127, -1) for bytes
    return out


def _node_matrix(node: pygltflib.Node) -> np.ndarray:
    if node.matrix is not None:
        return np.asarray(node.matrix, dtype=np.float64).reshape(4, 4).T  # glTF matrices are column-major
    m = np.eye(4)
    if node.rotation is not None:
        m[:3, :3] = Rotation.from_quat(node.rotation).as_matrix()  # glTF quaternions are (x, y, z, w)
    if node.scale is not None:
        m[:3, :3] = m[:3, :3] * np.asarray(node.scale)[None, :]
    if node.translation is not None:
        m[:3, 3] = node.translation
    return m


def _triangles(mode: int, idx: np.ndarray, path: Path, prim_label: str) -> np.ndarray:
    if mode == _TRIANGLES:
        if len(idx) % 3:
            raise RigError(f"{path}: {prim_label} has {len(idx)} indices, not a multiple of 3")
        return idx.reshape(-1, 3)
    if mode == _TRIANGLE_STRIP:
        tris = [(idx[i], idx[i + 1], idx[i + 2]) if i % 2 == 0 else (idx[i + 1], idx[i], idx[i + 2])
                for i in range(len(idx) - 2)]
        return np.asarray(tris, dtype=np.int64).reshape(-1, 3)
    if mode == _TRIANGLE_FAN:
        return np.asarray([(idx[0], idx[i], idx[i + 1]) for i in range(1, len(idx) - 1)],
                          dtype=np.int64).reshape(-1, 3)
    raise RigError(f"{path}: {prim_label} has primitive mode {_NOT_SURFACES.get(mode, mode)}, which cannot be "
                   f"triangulated; provide a triangle (or quad/polygon, via Blender) mesh")


def _texture_transform(uv: np.ndarray, transform: dict) -> np.ndarray:
    """UVs through ``KHR_texture_transform`` (glTF UV space): ``offset + R(rotation) · (scale ⊙ uv)``, with the
    extension's rotation matrix (columns ``(cos, sin)`` and ``(-sin, cos)``)."""
    offset = np.asarray(transform.get("offset", (0.0, 0.0)), dtype=np.float64)
    scale = np.asarray(transform.get("scale", (1.0, 1.0)), dtype=np.float64)
    a = float(transform.get("rotation", 0.0))
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return offset + (uv * scale) @ rot.T


_ATLAS_TILE = 1024  # the largest tile side of a base-colour atlas (512 beyond four materials)


def _srgb_times_factor(image: np.ndarray, factor: np.ndarray) -> np.ndarray:
    """An sRGB uint8 image times a linear base-colour factor, as glTF shades it (texture decoded to linear)."""
    lin = (image.astype(np.float64) / 255.0) ** 2.2 * np.clip(factor[:3], 0.0, 1.0)
    return np.clip(np.round(lin ** (1 / 2.2) * 255.0), 0, 255).astype(np.uint8)


def _material_colour(g: "_Gltf", material: int | None) -> tuple[np.ndarray | None, str, int, dict]:
    """Base colour of ``material`` (None: glTF's default material): (the texture image times the base-colour
    factor, or a 4x4 tile of the factor where there is no texture (None when that is white and no material); a
    description; the texCoord set the texture is sampled with; its ``KHR_texture_transform``)."""
    if material is None:
        return None, "no material (glTF's default: white)", 0, {}
    pbr = g.gltf.materials[material].pbrMetallicRoughness
    factor = np.asarray(pbr.baseColorFactor if pbr is not None and pbr.baseColorFactor is not None
                        else (1.0, 1.0, 1.0, 1.0), dtype=np.float64)
    colour_map = pbr.baseColorTexture if pbr is not None else None
    if colour_map is not None:
        transform = (colour_map.extensions or {}).get("KHR_texture_transform") or {}
        channel = int(transform.get("texCoord", colour_map.texCoord or 0))
        tex = g.gltf.textures[colour_map.index]
        # the image itself, or one an extension names (EXT_texture_webp, KHR_texture_basisu, ...): the first
        # that decodes
        images = [e.get("source") for e in (tex.extensions or {}).values() if isinstance(e, dict)] + [tex.source]
        texture, source = None, "the texture names no image"
        for k in dict.fromkeys(i for i in images if i is not None):
            texture, source = g.image(int(k))
            if texture is not None:
                break
        if texture is None:
            return None, source, channel, transform  # why it did not decode: the asset check reports it
        if not np.allclose(factor[:3], 1.0):
            texture = _srgb_times_factor(texture, factor)
            source += f" times base-colour factor {tuple(round(float(x), 4) for x in factor[:3])}"
        return texture, source, channel, transform
    colour = np.clip(np.round(np.clip(factor[:3], 0, 1) ** (1 / 2.2) * 255), 0, 255).astype(np.uint8)
    return np.tile(colour, (4, 4, 1)), f"base-colour factor of material {material}", 0, {}


def _base_colour_atlas(g: "_Gltf", parts: list[tuple[int | None, dict[int, np.ndarray], int]],
                       faces_per_material: dict[int | None, int]) -> tuple[np.ndarray, np.ndarray, str, list[str]]:
    """One base-colour image for a mesh whose primitives use several materials: each material's colour (texture
    times factor, or its flat factor) resized into a square tile of a grid, and every primitive's UVs (through
    its material's texCoord set and ``KHR_texture_transform``, wrapped into [0, 1) as glTF's repeat mode samples
    them) mapped into its tile, one texel inside the tile's border; a primitive without a texture or UVs gets its
    tile's centre. ``parts``: per primitive in vertex order (material, UV sets, vertex count).
    Returns (atlas (H, W, 3) uint8, UVs (V, 2) in glTF orientation (origin top-left), description, notes)."""
    import cv2

    order = sorted(faces_per_material, key=lambda m: (-faces_per_material[m], -1 if m is None else m))
    colours = {m: _material_colour(g, m) for m in order}
    white = np.full((4, 4, 3), 255, np.uint8)
    sizes = [max(c[0].shape[:2]) for c in colours.values() if c[0] is not None and c[0].shape[0] > 4]
    tile = min(max(sizes, default=64), _ATLAS_TILE if len(order) <= 4 else _ATLAS_TILE // 2)
    cols = int(np.ceil(np.sqrt(len(order))))
    rows = int(np.ceil(len(order) / cols))
    atlas = np.full((rows * tile, cols * tile, 3), 128, np.uint8)
    place = {}
    for k, m in enumerate(order):
        img = colours[m][0] if colours[m][0] is not None else white
        r, c = divmod(k, cols)
        interp = cv2.INTER_AREA if max(img.shape[:2]) > tile else cv2.INTER_LINEAR
        atlas[r * tile:(r + 1) * tile, c * tile:(c + 1) * tile] = cv2.resize(img, (tile, tile), interpolation=interp)
        place[m] = (c, r)
    height, width = atlas.shape[:2]
    uv_parts, wrapped = [], 0
    for m, uv_sets, count in parts:
        if m not in place:  # a primitive without triangles: any UV will do
            uv_parts.append(np.full((count, 2), 0.5 / cols))
            continue
        c, r = place[m]
        texture, _, channel, transform = colours[m]
        if texture is not None and texture.shape[0] > 4 and channel in uv_sets:
            uv = uv_sets[channel]
            if transform:
                uv = _texture_transform(uv, transform)
            outside = (uv < 0.0) | (uv > 1.0)
            wrapped += int(outside.any(1).sum())
            uv = np.where(outside, uv - np.floor(uv), uv)
        else:
            uv = np.full((count, 2), 0.5)
        uv_parts.append(np.c_[(c * tile + 1 + uv[:, 0] * (tile - 2)) / width,
                              (r * tile + 1 + uv[:, 1] * (tile - 2)) / height])
    notes = [f"{len(order)} materials: their base colours are packed into one {width}x{height} atlas "
             f"({tile} px tiles, materials {', '.join('default' if m is None else str(m) for m in order)} row by "
             f"row) and the UVs remapped to it; a category's own `textures` must follow this layout (the asset "
             f"check's contact sheet shows it)"]
    if wrapped:
        notes.append(f"{wrapped} vertices have UVs outside [0, 1] (a repeating texture): wrapped into their tile, "
                     f"so a triangle that crosses a repeat boundary samples across its tile")
    source = "atlas of " + "; ".join(f"{'default' if m is None else m}: {colours[m][1]}" for m in order)
    return atlas, np.concatenate(uv_parts), source, notes


def _parents_of_nodes(gltf: pygltflib.GLTF2, path: Path) -> list[int]:
    parent = [-1] * len(gltf.nodes)
    for i, node in enumerate(gltf.nodes):
        for c in node.children or []:
            if parent[c] != -1 and parent[c] != i:
                raise RigError(f"{path}: node {c} has several parents ({parent[c]} and {i}); the hierarchy must be a "
                               f"tree")
            parent[c] = i
    for i in range(len(parent)):  # cycle check
        seen, k = set(), i
        while k != -1:
            if k in seen:
                raise RigError(f"{path}: the node hierarchy has a cycle through node {k} "
                               f"('{gltf.nodes[k].name}')")
            seen.add(k)
            k = parent[k]
    return parent


UP_AXES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")
"""Values of a category's ``up_axis``: the asset's axis that points up (glTF's own convention is ``+Y``)."""

PLAUSIBLE_LENGTH_M = (0.05, 20.0)
"""Longest side (metres) of a plausible animal's rest-pose bounding box; outside it :func:`load_rig` refuses."""


def up_axis_rotation(up_axis: str) -> np.ndarray:
    """(3, 3) rotation taking the asset axis ``up_axis`` (one of :data:`UP_AXES`) to bat3r's up, ``+Y``.

    Proper rotations only (no mirroring): ``+Z`` up maps ``(x, y, z) -> (x, z, -y)``, the inverse of glTF's
    Y-up to Blender's Z-up change.
    """
    key = str(up_axis).strip().upper()
    if key not in UP_AXES:
        raise ValueError(f"up_axis must be one of {list(UP_AXES)}, got {up_axis!r}")
    axis = np.zeros(3)
    axis["XYZ".index(key[1])] = 1.0 if key[0] == "+" else -1.0
    target = np.array([0.0, 1.0, 0.0])
    if np.allclose(axis, target):
        return np.eye(3)
    if np.allclose(axis, -target):
        return np.diag([1.0, -1.0, -1.0])  # half turn about +X
    rotvec = np.cross(axis, target)  # quarter turn about axis x target
    return Rotation.from_rotvec(rotvec / np.linalg.norm(rotvec) * np.pi / 2).as_matrix()


def _rigid_part(m: np.ndarray) -> np.ndarray:
    """The nearest rigid transform (polar rotation, same origin) of a 4x4 affine frame."""
    u, _, vt = np.linalg.svd(m[:3, :3])
    r = u @ vt
    if np.linalg.det(r) < 0:  # a mirrored frame: flip its least significant axis
        u[:, -1] *= -1
        r = u @ vt
    out = np.eye(4)
    out[:3, :3] = r
    out[:3, 3] = m[:3, 3]
    return out


@dataclass(frozen=True)
class AssetInfo:
    """What :func:`read_asset` found in a file and what it did with it (the rig report's raw material).

    Attributes:
        path: the file. skin: index of the glTF skin used (the one binding the most vertices). joints: J.
        file_vertices: V, the rig's vertex count (the file's own vertices, split at seams as stored).
        meshes: ``(node name, what was done)`` for every mesh node of the scene: skinned, rigidly attached to a
            joint (skinned to it with weight 1), or left out (and why).
        morph_targets: number of morph targets on the used meshes (applied at their default weights).
        morph_weights: the default weights applied (non-zero ones only move vertices).
        animations: names of the file's animations (never applied: the rest pose is the bind pose).
        scale: the asset scale applied (file units → metres). up_axis: the file's up axis.
        texture: (H, W, 3) uint8 RGB base-colour texture of the dominant material, or None.
        texture_source: where the texture came from (``"embedded image 0"``, a file name) or why there is none.
        notes: further remarks (e.g. several materials, a mesh node transform the glTF spec ignores).
        node_pose_deg: how far the pose the file was saved in is from its bind pose (largest joint rotation, degrees;
            0 for a file saved at its bind pose). The rest pose never uses it.
        bind_scale: (min, max) scale of the joints' bind frames relative to the skeleton's parent node (the
            singular values of the inverse inverse-bind matrices; (1, 1) for rigid bind frames).
        vertex_colors: (V, 3) float32 linear RGB of the file's ``COLOR_0`` (white for primitives without one), which
            glTF multiplies into the base colour; None when no primitive has vertex colours.
        dequantization: for a ``KHR_mesh_quantization`` file whose inverse bind matrices carry the dequantization
            of its integer positions, the ``(scale, x, y, z)`` offset applied to place the bind pose as the file's
            scene shows it (in file units, before ``scale``); None otherwise.
    """

    path: str
    skin: int
    joints: int
    file_vertices: int
    meshes: tuple[tuple[str, str], ...]
    morph_targets: int
    morph_weights: tuple[float, ...]
    animations: tuple[str, ...]
    scale: float
    up_axis: str
    texture: np.ndarray | None
    texture_source: str
    notes: tuple[str, ...]
    bind_scale: tuple[float, float] = (1.0, 1.0)
    node_pose_deg: float = 0.0
    dequantization: tuple[float, float, float, float] | None = None
    vertex_colors: np.ndarray | None = None


def _vertex_colours(data: np.ndarray | None, count: int, path: Path, label: str) -> np.ndarray | None:
    """A primitive's ``COLOR_0`` as (count, 3) float32 linear RGB in [0, 1] (RGBA: alpha dropped; normalised
    integers already read as fractions), or None without one."""
    if data is None:
        return None
    c = np.asarray(data, dtype=np.float64)
    if c.ndim != 2 or c.shape[0] != count or c.shape[1] not in (3, 4):
        raise RigError(f"{path}: {label}: COLOR_0 must be VEC3 or VEC4 with one entry per vertex ({count}), got "
                       f"shape {c.shape}")
    if not np.isfinite(c).all():
        raise RigError(f"{path}: {label}: COLOR_0 has non-finite values")
    return np.clip(c[:, :3], 0.0, 1.0).astype(np.float32)


class _Gltf:
    """A parsed glTF file: nodes, world matrices at the file's node TRS, accessors."""

    def __init__(self, path: Path):
        self.path = path
        try:
            self.gltf = pygltflib.GLTF2().load(str(path))
        except Exception as e:  # pygltflib raises assorted errors on corrupt files
            raise RigError(f"{path}: not a readable glTF/GLB file ({type(e).__name__}: {e})") from e
        self.blobs = self._blobs()
        self.parent = _parents_of_nodes(self.gltf, path)
        self._world: dict[int, np.ndarray] = {}
        self._decoded: dict[int, dict[str, np.ndarray]] = {}

    def _blobs(self) -> list[bytes | None]:
        """The bytes of every buffer: a GLB's binary chunk, a data URI, or a file beside the .gltf (None for a buffer
        with neither; reading it is an error then)."""
        gltf = self.gltf
        out: list[bytes | None] = []
        for k, buffer in enumerate(gltf.buffers or []):
            uri = buffer.uri or ""
            if not uri:
                out.append(gltf.binary_blob() if k == 0 else None)
            elif uri.startswith("data:"):
                import base64

                out.append(base64.b64decode(uri.split(",", 1)[1]))
            else:
                from urllib.parse import unquote

                f = self.path.parent / unquote(uri)
                if not f.is_file():
                    raise RigError(f"{self.path}: its buffer file {f} does not exist (keep the .bin beside the "
                                   f".gltf)")
                out.append(f.read_bytes())
        return out

    def accessor(self, index: int) -> np.ndarray:
        return _read_accessor(self.gltf, self.blobs, index, self.path)

    def view_bytes(self, index: int, what: str) -> bytes:
        """The bytes of buffer view ``index``; RigError naming ``what`` reads it when its buffer has no data."""
        view = self.gltf.bufferViews[index]
        blob = self.blobs[view.buffer] if view.buffer < len(self.blobs) else None
        if blob is None:
            raise RigError(f"{self.path}: {what} reads buffer {view.buffer}, which has no data")
        start = view.byteOffset or 0
        return bytes(blob[start:start + view.byteLength])

    def _draco(self, prim) -> dict[str, np.ndarray] | None:
        """The decoded Draco buffer of ``prim`` (``indices`` and every attribute the extension names), or None
        for a plain primitive."""
        ext = (prim.extensions or {}).get(DRACO)
        if not ext:
            return None
        key = id(prim)
        if key not in self._decoded:
            import DracoPy

            data = self.view_bytes(ext["bufferView"], "a Draco-compressed primitive")
            try:
                mesh = DracoPy.decode(data)
            except Exception as e:  # noqa: BLE001 - DracoPy raises its own errors on corrupt buffers
                raise RigError(f"{self.path}: a Draco-compressed primitive cannot be decoded "
                               f"({type(e).__name__}: {e})") from None
            out = {"indices": np.asarray(mesh.faces).reshape(-1).astype(np.int64)}
            for name, uid in (ext.get("attributes") or {}).items():
                att = mesh.get_attribute_by_unique_id(int(uid))
                if att is None:
                    raise RigError(f"{self.path}: the Draco buffer of a primitive has no attribute {uid} ({name})")
                data = np.asarray(att["data"])
                out[name] = data.reshape(len(data), -1)
            self._decoded[key] = out
        return self._decoded[key]

    def attribute(self, prim, name: str) -> np.ndarray | None:
        """Vertex attribute ``name`` (``POSITION``, ``JOINTS_0``, ...) of a primitive, from its Draco buffer when it
        is compressed, else from its accessor; None when the primitive has no such attribute."""
        index = getattr(prim.attributes, name, None)
        draco = self._draco(prim)
        if draco is not None and name in draco:
            data = draco[name]
            acc = self.gltf.accessors[index] if index is not None else None
            if acc is not None and acc.normalized and np.issubdtype(data.dtype, np.integer):
                data = np.maximum(data.astype(np.float64) / np.iinfo(data.dtype).max, -1.0)
            return data
        return None if index is None else self.accessor(index)

    def indices(self, prim) -> np.ndarray | None:
        """A primitive's vertex indices (None for an unindexed one)."""
        draco = self._draco(prim)
        if draco is not None:
            return draco["indices"]
        return None if prim.indices is None else self.accessor(prim.indices).reshape(-1).astype(np.int64)

    def world(self, i: int) -> np.ndarray:
        """(4, 4) world matrix of node ``i`` at the file's node TRS (animations not applied)."""
        if i not in self._world:
            p = self.parent[i]
            self._world[i] = (self.world(p) if p != -1 else np.eye(4)) @ _node_matrix(self.gltf.nodes[i])
        return self._world[i]

    def scene_nodes(self) -> list[int]:
        """Nodes reachable from the default scene (all nodes when the file names no scene)."""
        gltf = self.gltf
        if not gltf.scenes:
            return list(range(len(gltf.nodes)))
        roots = gltf.scenes[gltf.scene or 0].nodes or []
        out, stack = [], list(roots)
        while stack:
            k = stack.pop()
            out.append(k)
            stack.extend(gltf.nodes[k].children or [])
        return sorted(out)

    def image(self, index: int) -> tuple[np.ndarray | None, str]:
        """Decode image ``index`` to (H, W, 3) uint8 RGB, with a description of its source."""
        import cv2

        img = self.gltf.images[index]
        if img.bufferView is not None:
            try:
                data = self.view_bytes(img.bufferView, f"image {index}")
            except RigError as e:
                return None, str(e)
            source = f"embedded image {index}"
        elif img.uri and img.uri.startswith("data:"):
            import base64
            data = base64.b64decode(img.uri.split(",", 1)[1])
            source = f"data-URI image {index}"
        elif img.uri:
            from urllib.parse import unquote

            f = self.path.parent / unquote(img.uri)
            if not f.is_file():
                return None, f"image file {f} does not exist"
            data = f.read_bytes()
            source = f.name
        else:
            return None, f"image {index} has no data"
        arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        if arr is None:
            return None, f"{source} cannot be decoded"
        return np.ascontiguousarray(arr[..., ::-1]), source


def _primitive_positions(g: _Gltf, mesh: pygltflib.Mesh, node: pygltflib.Node, prim, label: str
                         ) -> tuple[np.ndarray, int]:
    """POSITION with the morph targets applied at their default weights; (positions, number of targets)."""
    attrs = prim.attributes
    if attrs.POSITION is None:
        raise RigError(f"{g.path}: {label} has no POSITION attribute")
    pos = g.attribute(prim, "POSITION").astype(np.float64)
    targets = prim.targets or []
    weights = getattr(node, "weights", None) or mesh.weights or []
    for k, target in enumerate(targets):
        w = float(weights[k]) if k < len(weights) else 0.0
        index = target.get("POSITION") if isinstance(target, dict) else getattr(target, "POSITION", None)
        if w != 0.0 and index is not None:
            pos = pos + w * g.accessor(index).astype(np.float64)
    if not np.isfinite(pos).all():
        raise RigError(f"{g.path}: {label} has NaN/inf vertex positions")
    return pos, len(targets)


def _primitive_weights(g: _Gltf, prim, label: str, num_joints: int) -> np.ndarray | None:
    """(n, num_joints) skin weights of a primitive from JOINTS_n/WEIGHTS_n (None when it has none)."""
    attrs = prim.attributes
    w = None
    for s in range(_MAX_INFLUENCE_SETS + 2):
        if getattr(attrs, f"JOINTS_{s}", None) is None or getattr(attrs, f"WEIGHTS_{s}", None) is None:
            break
        jj = g.attribute(prim, f"JOINTS_{s}").astype(np.int64)
        ww = g.attribute(prim, f"WEIGHTS_{s}").astype(np.float64)
        if w is None:
            w = np.zeros((len(jj), num_joints))
        if jj.max(initial=0) >= num_joints:
            raise RigError(f"{g.path}: {label} JOINTS_{s} references joint {jj.max()} but the skin has "
                           f"{num_joints} joints")
        np.add.at(w, (np.repeat(np.arange(len(jj)), jj.shape[1]), jj.reshape(-1)), ww.reshape(-1))
    return w


def _skin_frames(g: _Gltf, skin: pygltflib.Skin) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(joints (n,) node indices, bind frames (n, 4, 4) joint → world, inverse bind matrices (n, 4, 4)).

    A vertex is skinned as ``Σ w_j J_j IBM_j v`` (glTF 2.0, skins; the mesh node's own transform is ignored), so the
    joint configuration in which the mesh appears as stored is ``J_j = IBM_j^-1``: that is the bind pose, and the
    scene graph above the skeleton enters it only through the inverse bind matrices (exporters bake it there).
    Without inverse bind matrices (identity by the spec) the joints' world matrices at the file's node TRS are
    taken as the bind pose.
    """
    joints = list(skin.joints)
    if skin.inverseBindMatrices is None:
        world = np.stack([g.world(n) for n in joints])
        return np.asarray(joints), world, np.linalg.inv(world)
    ibm = g.accessor(skin.inverseBindMatrices).astype(np.float64).reshape(-1, 4, 4).transpose(0, 2, 1)
    if len(ibm) != len(joints):
        raise RigError(f"{g.path}: skin '{skin.name}' has {len(joints)} joints but {len(ibm)} inverse bind matrices")
    try:
        return np.asarray(joints), np.linalg.inv(ibm), ibm
    except np.linalg.LinAlgError:
        raise RigError(f"{g.path}: skin '{skin.name}' has a singular inverse bind matrix") from None


def _node_pose(g: _Gltf, joints: np.ndarray, ibm: np.ndarray) -> tuple[float, float, np.ndarray]:
    """How the file's node pose relates to its bind pose: (scale of the skeleton's root joint at the node pose
    relative to its bind frame, largest angle in degrees between two joints' ``J_j @ IBM_j``, the root joint's
    ``J_root @ IBM_root``: where the file's scene places the mesh as stored).

    In the bind pose every ``J_j @ IBM_j`` is the same matrix (the identity when the scene graph above the skeleton
    is baked into the inverse bind matrices): a non-zero angle means the file was saved posed or animated.
    """
    jset = set(int(j) for j in joints)
    roots = [k for k, n in enumerate(joints) if g.parent[int(n)] not in jset]
    m = np.stack([g.world(int(n)) @ ibm[k] for k, n in enumerate(joints)])
    ref = m[roots[0] if roots else 0]
    scale = float(np.cbrt(abs(np.linalg.det(ref[:3, :3]))))
    rel = np.linalg.inv(ref[:3, :3])[None] @ m[:, :3, :3]
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return scale, float(np.degrees(np.arccos(cos)).max()), ref


def read_asset(path: str | os.PathLike, scale: float = 1.0, up_axis: str = "+Y") -> tuple[Rig, AssetInfo]:
    """Read a glTF/GLB rig in bat3r's canonical rest pose, with a report of what was found and done.

    The canonical rest pose is the **bind pose** defined by the inverse bind matrices (never the node pose the file
    was saved in, nor any animation): the joints at ``IBM_j^-1``, where glTF's skinning shows the mesh as stored
    (:func:`_skin_frames`), then scaled by ``scale`` (file units → metres) and rotated so that ``up_axis`` points
    up (+Y). Meshes of the scene:

    * skinned by the skin that binds the most vertices: used as they are;
    * skinned by another skin whose joints all belong to it: re-bound into its bind pose by linear blend skinning;
    * not skinned but below a joint in the hierarchy (eyes, tack): attached rigidly to that joint (weight 1);
    * anything else (static props, other skeletons): left out, and listed in :attr:`AssetInfo.meshes`.

    Morph targets are applied at their default weights (the node's ``weights``, else the mesh's, else 0). Skin
    weights are normalised per vertex (sums off 1 are counted in the notes; a vertex with none follows its skin's
    first joint). Web-optimised files: Draco primitives are decoded in place; a quantized file
    (``KHR_mesh_quantization``) whose inverse bind matrices carry the dequantization is placed by the root joint's
    ``J · IBM`` scale and offset (:attr:`AssetInfo.dequantization`); meshopt buffers are refused with the fix.
    Vertices stay as the file stores them (split at UV seams, or one triple per triangle); fitting welds them
    (:mod:`bat3r_core.topology`). Joint rest frames are made rigid (the polar rotation of each bind frame, the
    joint origin kept): θ then rotates about orthonormal axes, and skinning reproduces the bind pose exactly.
    """
    path = Path(path)
    if not np.isfinite(scale) or scale <= 0:
        raise ValueError(f"asset scale must be a positive number (file units -> metres), got {scale!r}")
    g = _Gltf(path)
    gltf = g.gltf
    required = set(gltf.extensionsRequired or [])
    unreadable = sorted(required & set(_NOT_READABLE))
    if unreadable:
        raise RigError(f"{path}: the file requires {unreadable[0]} ({_NOT_READABLE[unreadable[0]]}); "
                       f"{_DECODE_HINT}")
    if not gltf.skins:
        raise RigError(f"{path}: the mesh has no skin (no glTF 'skins'); bat3r needs a rigged, skinned mesh "
                       f"(armature + vertex weights)")
    in_scene = g.scene_nodes()
    mesh_nodes = [n for n in in_scene if gltf.nodes[n].mesh is not None]

    def vertex_count(n: int) -> int:
        return sum(gltf.accessors[p.attributes.POSITION].count for p in gltf.meshes[gltf.nodes[n].mesh].primitives
                   if p.attributes.POSITION is not None)

    skinned = [n for n in mesh_nodes if gltf.nodes[n].skin is not None]
    if not skinned:
        raise RigError(f"{path}: no mesh node uses a skin; the mesh must be bound to the armature")
    per_skin: dict[int, int] = {}
    for n in skinned:
        per_skin[gltf.nodes[n].skin] = per_skin.get(gltf.nodes[n].skin, 0) + vertex_count(n)
    skin_index = max(per_skin, key=lambda s: (per_skin[s], -s))
    skin = gltf.skins[skin_index]
    joint_nodes, bind, skin_ibm = _skin_frames(g, skin)
    jset = set(int(n) for n in joint_nodes)
    above = next((g.parent[int(n)] for n in joint_nodes if g.parent[int(n)] not in jset), -1)
    frame_above = g.world(above) if above != -1 else np.eye(4)
    bind_sv = np.linalg.svd((np.linalg.inv(frame_above) @ np.linalg.inv(skin_ibm))[:, :3, :3], compute_uv=False)
    pose_scale, pose_angle, root_frame = _node_pose(g, joint_nodes, skin_ibm)
    jpos = {int(n): k for k, n in enumerate(joint_nodes)}
    u = np.eye(4)
    u[:3, :3] = float(scale) * up_axis_rotation(up_axis)
    dequantization = None
    if QUANTIZATION in set(gltf.extensionsUsed or []) and abs(pose_scale - 1.0) > 1e-3:
        # A quantizing exporter (gltfpack, gltf-transform) stores a skinned mesh's positions as integers and folds
        # their dequantization (a uniform scale and an offset) into the inverse bind matrices: the mesh "as
        # stored" is the integer grid. Place the bind pose as the file's scene shows it at the root joint, scale
        # and offset only (a rotation there would be the root's own pose, not part of the mesh).
        dq = np.eye(4)
        dq[:3, :3] *= pose_scale
        dq[:3, 3] = root_frame[:3, 3]
        u = u @ dq
        dequantization = (float(pose_scale), *(float(x) for x in root_frame[:3, 3]))
        bind_sv = bind_sv * pose_scale  # the bind frames once dequantized
    bind = u @ bind  # joint bind frames in bat3r's canonical frame (may carry the file's scale)
    parents = []
    for n in joint_nodes:
        p = g.parent[n]
        while p != -1 and p not in jpos:
            p = g.parent[p]
        parents.append(jpos[p] if p != -1 else -1)
    names = [gltf.nodes[n].name or f"joint_{k}" for k, n in enumerate(joint_nodes)]
    nj = len(joint_nodes)

    verts, faces, uv_sets, weights, report, notes = [], [], [], [], [], []
    colours: list[np.ndarray | None] = []  # per primitive: its COLOR_0 (n, 3) linear RGB, or None
    weight_sums: list[float] = []  # the sums of the vertices whose weights did not sum to 1 (normalised)
    n_unweighted = 0
    material_faces: dict[int | None, int] = {}  # faces per material (None: primitives without one)
    parts: list[tuple[int | None, dict[int, np.ndarray], int]] = []  # per primitive: material, UV sets, vertices
    offset, n_targets, morph_w = 0, 0, []
    for n in mesh_nodes:
        node = gltf.nodes[n]
        mesh = gltf.meshes[node.mesh]
        label_node = node.name or f"node {n}"
        if node.skin is not None:
            other = gltf.skins[node.skin]
            if node.skin != skin_index and not all(int(j) in jpos for j in other.joints):
                report.append((label_node, f"left out: skinned to skin {node.skin}, whose joints are not all in "
                                           f"the rig's skin {skin_index}"))
                continue
            other_joints, _, other_ibm = _skin_frames(g, other)
            # per influence joint: mesh space -> joint (this skin's IBM) -> the rig's canonical bind frame
            rebind = np.stack([bind[jpos[int(j)]] @ other_ibm[k] for k, j in enumerate(other_joints)])
            column = np.array([jpos[int(j)] for j in other_joints])
            how = "skinned" if node.skin == skin_index else f"skinned (skin {node.skin}, re-bound)"
        else:
            anc = g.parent[n]
            while anc != -1 and anc not in jpos:
                anc = g.parent[anc]
            if anc == -1:
                report.append((label_node, "left out: a static mesh, neither skinned nor below a joint"))
                continue
            j = jpos[anc]
            local = np.linalg.inv(g.world(anc)) @ g.world(n)  # joint -> mesh node at the file's TRS
            rigid = bind[j] @ local  # the mesh node in the rig's bind pose
            how = f"rigid on joint '{names[j]}' (skinned to it with weight 1)"
        n_before = offset
        for pi, prim in enumerate(mesh.primitives):
            label = f"mesh '{mesh.name}' primitive {pi} (node '{label_node}')"
            mode = _TRIANGLES if prim.mode is None else prim.mode
            if mode in _NOT_SURFACES:  # guide lines, hair strands, point helpers: nothing a camera sees as skin
                report.append((label_node, f"left out: primitive {pi} of mesh '{mesh.name}' draws "
                                           f"{_NOT_SURFACES[mode]}, not a surface"))
                continue
            pos, nt = _primitive_positions(g, mesh, node, prim, label)
            n_targets += nt
            ws = getattr(node, "weights", None) or mesh.weights or []
            morph_w.extend(float(x) for x in list(ws)[:nt])
            idx = g.indices(prim)
            idx = np.arange(len(pos)) if idx is None else idx
            tri = _triangles(mode, idx, path, label)
            if tri.size and tri.max() >= len(pos):
                raise RigError(f"{path}: {label} indexes vertex {tri.max()} of {len(pos)}")
            faces.append(tri + offset)
            material_faces[prim.material] = material_faces.get(prim.material, 0) + len(tri)
            ph = np.c_[pos, np.ones(len(pos))]
            if node.skin is not None:
                w_local = _primitive_weights(g, prim, label, len(other_joints))
                if w_local is None:
                    raise RigError(f"{path}: {label} has no JOINTS_0/WEIGHTS_0 skin attributes")
                # glTF viewers and Blender normalise weights that do not sum to 1 (exporters that cut more
                # influences down to four leave such sums); a vertex with none follows the skin's first joint
                sums = w_local.sum(1)
                unweighted = ~(sums > 0)
                w_local[unweighted, 0] = 1.0
                sums[unweighted] = 1.0
                off = np.abs(sums - 1.0) > _WEIGHT_SUM_TOLERANCE
                if off.any():
                    weight_sums.extend(sums[off & ~unweighted].tolist())
                n_unweighted += int(unweighted.sum())
                w_norm = w_local / sums[:, None]
                blended = np.einsum("vk,kij->vij", w_norm, rebind)  # (n, 4, 4)
                x = np.einsum("vij,vj->vi", blended, ph)[:, :3]
                w = np.zeros((len(pos), nj))
                np.add.at(w, (slice(None), column), w_norm)
            else:
                x = ph @ rigid.T
                x = x[:, :3]
                w = np.zeros((len(pos), nj))
                w[:, j] = 1.0
            verts.append(x)
            weights.append(w)
            uv_sets.append({k: g.attribute(prim, f"TEXCOORD_{k}").astype(np.float64)
                            for k in (0, 1) if getattr(prim.attributes, f"TEXCOORD_{k}", None) is not None})
            parts.append((prim.material, uv_sets[-1], len(pos)))
            colours.append(_vertex_colours(g.attribute(prim, "COLOR_0"), len(pos), path, label))
            offset += len(pos)
        report.append((label_node, f"{how}: {offset - n_before} vertices"))
    if not verts:
        why = "; ".join(f"'{n}': {what}" for n, what in report)
        raise RigError(f"{path}: no usable mesh (a skinned surface, or one rigidly below a joint) in the default "
                       f"scene{': ' + why if why else ''}")
    uv, texture, source = None, None, "the file has no base-colour texture"
    used = [m for m in material_faces if material_faces[m] > 0]
    if len(used) > 1:  # several materials: one atlas of their base colours, the UVs remapped into it
        texture, uv, source, atlas_notes = _base_colour_atlas(g, parts, {m: material_faces[m] for m in used})
        notes.extend(atlas_notes)
    elif used:
        texture, colour_source, channel, transform = _material_colour(g, used[0])
        if texture is not None or used[0] is not None:
            source = colour_source
        if uv_sets and all(channel in u for u in uv_sets):  # the UV set the base-colour texture is sampled with
            uv = np.concatenate([u[channel] for u in uv_sets])
            if transform:
                uv = _texture_transform(uv, transform)
                notes.append(f"the base-colour texture's KHR_texture_transform {transform} is applied to the UVs")
    if uv is not None:
        uv = uv.copy()
        uv[:, 1] = 1.0 - uv[:, 1]  # glTF's UV origin is top-left; bat3r stores OpenGL-style (origin bottom-left)
    vertex_colors = None
    if any(c is not None for c in colours):  # glTF: COLOR_0 multiplies the base colour; none means white
        vertex_colors = np.concatenate([c if c is not None else np.ones((p[2], 3), np.float32)
                                        for c, p in zip(colours, parts)])
        with_colour = sum(c is not None for c in colours)
        notes.append(f"COLOR_0 vertex colours on {with_colour} of {len(colours)} primitives: multiplied into the "
                     f"base colour, as glTF shades them (linear RGB {np.round(vertex_colors.min(0), 3).tolist()} to "
                     f"{np.round(vertex_colors.max(0), 3).tolist()}); a category's own `textures` replace both")
    rest = np.stack([_rigid_part(b) for b in bind])
    try:
        rig = Rig.from_unordered(path.stem, np.concatenate(verts), np.concatenate(faces), names,
                                 np.asarray(parents), rest, np.concatenate(weights), uvs=uv)
    except RigError as e:
        raise RigError(f"{path}: {e}") from None
    if weight_sums:
        notes.append(f"the skin weights of {len(weight_sums)} vertices summed to {min(weight_sums):.4g}-"
                     f"{max(weight_sums):.4g}, not 1; normalised, as glTF viewers and Blender do")
    if n_unweighted:
        notes.append(f"{n_unweighted} vertices have no skin weight; each follows its skin's first joint rigidly")
    if dequantization is not None:
        notes.append(f"{QUANTIZATION}: integer positions dequantized by the scale {pose_scale:.6g} and offset "
                     f"({', '.join(f'{x:.4g}' for x in dequantization[1:])}) its inverse bind matrices carry")
    elif abs(pose_scale - 1.0) > 1e-3:
        notes.append(f"the file's scene graph shows the skeleton {pose_scale:.4g}x the size of its bind pose (a "
                     f"transform above the skeleton that its inverse bind matrices do not include); bat3r uses the "
                     f"bind pose: check asset_scale")
    info = AssetInfo(path=str(path), skin=skin_index, joints=nj, file_vertices=rig.num_vertices,
                     meshes=tuple(report), morph_targets=n_targets, morph_weights=tuple(morph_w),
                     animations=tuple(a.name or f"animation {k}" for k, a in enumerate(gltf.animations or [])),
                     scale=float(scale), up_axis=str(up_axis).upper(), texture=texture, texture_source=source,
                     notes=tuple(notes), bind_scale=(float(bind_sv.min()), float(bind_sv.max())),
                     node_pose_deg=pose_angle, dequantization=dequantization, vertex_colors=vertex_colors)
    return rig, info


def check_plausible_size(rig: Rig, path: str | os.PathLike, scale: float = 1.0) -> float:
    """The rest-pose mesh's longest bounding-box side (metres); :class:`RigError` when it is outside
    :data:`PLAUSIBLE_LENGTH_M`, with the extent and the fix (the catalog's ``asset_scale``)."""
    extent = np.ptp(rig.rest_vertices, axis=0)
    length = float(extent.max())
    lo, hi = PLAUSIBLE_LENGTH_M
    if lo <= length <= hi:
        return length
    file_length = length / scale
    proposal = 10.0 ** np.round(np.log10(1.0 / file_length))  # the power of ten that makes it ~1 m long
    units = {0.01: "centimetres", 0.001: "millimetres", 0.0254: "inches", 100.0: "hectometres"}
    guess = units.get(float(proposal), f"units of {proposal:g} m")
    raise RigError(
        f"{path}: the rest-pose mesh is {length:.4g} m long (bounding box {extent[0]:.4g} x {extent[1]:.4g} x "
        f"{extent[2]:.4g} m after asset_scale {scale:g}); an animal is {lo:g}-{hi:g} m. The file is probably in "
        f"{guess}: set `asset_scale: {proposal:g}` for this category in the data catalog (or pass "
        f"--asset-scale {proposal:g}), and `up_axis` if it is not Y-up.")


def _convert_with_blender(path: Path) -> Path:
    out = Path(tempfile.mkdtemp(prefix="bat3r_convert_")) / (path.stem + ".glb")
    cmd = [sys.executable, "-m", "bat3r_core.render.blender_convert", str(path), str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    if proc.returncode != 0 or not out.is_file():
        tail = (proc.stderr or proc.stdout)[-2000:]
        raise RigError(f"{path}: Blender could not convert it to GLB (exit {proc.returncode}):\n{tail}")
    return out


def read_any_asset(path: str | os.PathLike, scale: float = 1.0, up_axis: str = "+Y") -> tuple[Rig, AssetInfo]:
    """:func:`read_asset` for ``.glb``/``.gltf``, and for ``.fbx``/``.blend`` after conversion through Blender."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"rigged asset {path} does not exist; provide a rigged, skinned mesh "
                                f"(.glb/.gltf, or .fbx/.blend converted through Blender)")
    suffix = path.suffix.lower()
    if suffix in (".glb", ".gltf"):
        return read_asset(path, scale, up_axis)
    if suffix in (".fbx", ".blend"):
        converted = _convert_with_blender(path)
        rig, info = read_asset(converted, scale, up_axis)
        rig = Rig(name=path.stem, rest_vertices=rig.rest_vertices, faces=rig.faces, joint_names=rig.joint_names,
                  parents=rig.parents, rest_transforms=rig.rest_transforms, skin_weights=rig.skin_weights,
                  uvs=rig.uvs)
        return rig, dataclasses.replace(info, path=str(path))
    raise RigError(f"{path}: unsupported rig format '{suffix}'; expected .glb, .gltf, .fbx or .blend")


def load_rig(path: str | os.PathLike, scale: float = 1.0, up_axis: str = "+Y", check_size: bool = True) -> Rig:
    """Load a rigged, skinned mesh (``.glb``/``.gltf``; ``.fbx``/``.blend`` are converted through Blender) in
    bat3r's canonical rest pose (:func:`read_asset`), scaled to metres by ``scale`` and turned Y-up.

    Raises:
        FileNotFoundError: the file does not exist (the message names it).
        RigError: the asset is not a usable rig (no skin, bad weights, cycles or several roots, NaN vertices,
            faces that cannot be triangulated, ...) or, with ``check_size``, its size is implausible for an animal
            (:func:`check_plausible_size`: e.g. a file in centimetres); the message names the file and the fix.
    """
    rig, _ = read_any_asset(path, scale, up_axis)
    if check_size:
        check_plausible_size(rig, path, scale)
    return rig


# ----------------------------------------------------------------------------------------------------- writing


class _BlobBuilder:
    def __init__(self, gltf: pygltflib.GLTF2):
        self.gltf = gltf
        self.data = bytearray()

    def add(self, arr: np.ndarray, gltf_type: str, component: int, target: int | None = None,
            minmax: bool = False) -> int:
        arr = np.ascontiguousarray(arr, dtype=_COMPONENT[component])
        while len(self.data) % 4:
            self.data.append(0)
        offset = len(self.data)
        self.data.extend(arr.tobytes())
        self.gltf.bufferViews.append(pygltflib.BufferView(buffer=0, byteOffset=offset, byteLength=arr.nbytes,
                                                          target=target))
        count = arr.shape[0] if gltf_type != "MAT4" else arr.shape[0]
        acc = pygltflib.Accessor(bufferView=len(self.gltf.bufferViews) - 1, componentType=component, count=count,
                                 type=gltf_type)
        if minmax:
            flat = arr.reshape(count, -1)
            acc.min = flat.min(0).tolist()
            acc.max = flat.max(0).tolist()
        self.gltf.accessors.append(acc)
        return len(self.gltf.accessors) - 1


def _png_bytes(image: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError("could not encode the texture as PNG")
    return buf.tobytes()


def save_rig_glb(rig: Rig, path: str | os.PathLike, texture: np.ndarray | None = None,
                 vertex_colors: np.ndarray | None = None) -> Path:
    """Write ``rig`` as a binary glTF with a skin.

    Joint nodes carry the rest pose as local TRS (rotation + translation; a rest frame with scale or shear is
    written as a matrix). Up to 8 influences per vertex are written (JOINTS_0/1, WEIGHTS_0/1); weights beyond
    the 8 largest are dropped and the rest renormalised.

    Args:
        texture: optional (H, W, 3) uint8 RGB base-colour image, embedded as PNG.
        vertex_colors: optional (V, 3) linear RGB in [0, 1], written as ``COLOR_0`` (float), which glTF
            multiplies into the base colour.
    """
    path = Path(path)
    gltf = pygltflib.GLTF2(asset=pygltflib.Asset(generator="bat3r", version="2.0"))
    gltf.buffers = [pygltflib.Buffer()]
    gltf.scene = 0
    blob = _BlobBuilder(gltf)
    v = rig.rest_vertices.astype(np.float32)
    pos_acc = blob.add(v, "VEC3", pygltflib.FLOAT, pygltflib.ARRAY_BUFFER, minmax=True)
    idx_acc = blob.add(rig.faces.reshape(-1).astype(np.uint32), "SCALAR", pygltflib.UNSIGNED_INT,
                       pygltflib.ELEMENT_ARRAY_BUFFER)
    attrs = pygltflib.Attributes(POSITION=pos_acc)
    try:
        import trimesh

        normals = trimesh.Trimesh(rig.rest_vertices, rig.faces, process=False).vertex_normals
        attrs.NORMAL = blob.add(np.asarray(normals, np.float32), "VEC3", pygltflib.FLOAT, pygltflib.ARRAY_BUFFER)
    except Exception:  # normals are optional for the importer
        pass
    if rig.uvs is not None:
        uv = rig.uvs.copy()
        uv[:, 1] = 1.0 - uv[:, 1]
        attrs.TEXCOORD_0 = blob.add(uv.astype(np.float32), "VEC2", pygltflib.FLOAT, pygltflib.ARRAY_BUFFER)
    if vertex_colors is not None:
        vc = np.asarray(vertex_colors, dtype=np.float64)
        if vc.shape != (rig.num_vertices, 3) or not np.isfinite(vc).all():
            raise ValueError(f"vertex_colors must be a finite ({rig.num_vertices}, 3) array, got {vc.shape}")
        attrs.COLOR_0 = blob.add(np.clip(vc, 0.0, 1.0).astype(np.float32), "VEC3", pygltflib.FLOAT,
                                 pygltflib.ARRAY_BUFFER)
    nj = rig.num_joints
    w = rig.skin_weights
    order = np.argsort(-w, axis=1, kind="stable")[:, :4 * _MAX_INFLUENCE_SETS]
    top_w = np.take_along_axis(w, order, axis=1)
    top_w = top_w / top_w.sum(1, keepdims=True)
    n_sets = 1 if (top_w[:, 4:] <= 0).all() or nj <= 4 else 2
    if nj < 4 * n_sets:
        pad = 4 * n_sets - order.shape[1]
        order = np.pad(order, ((0, 0), (0, pad)))
        top_w = np.pad(top_w, ((0, 0), (0, pad)))
    for s in range(n_sets):
        jj = order[:, 4 * s:4 * s + 4]
        ww = top_w[:, 4 * s:4 * s + 4]
        jj = np.where(ww > 0, jj, 0)
        setattr(attrs, f"JOINTS_{s}", blob.add(jj.astype(np.uint16), "VEC4", pygltflib.UNSIGNED_SHORT,
                                                pygltflib.ARRAY_BUFFER))
        setattr(attrs, f"WEIGHTS_{s}", blob.add(ww.astype(np.float32), "VEC4", pygltflib.FLOAT,
                                                 pygltflib.ARRAY_BUFFER))
    prim = pygltflib.Primitive(attributes=attrs, indices=idx_acc, mode=_TRIANGLES)
    if texture is not None:
        tex = np.asarray(texture)
        if tex.ndim != 3 or tex.shape[2] != 3 or tex.dtype != np.uint8:
            raise ValueError(f"texture must be an (H, W, 3) uint8 RGB image, got {tex.dtype} {tex.shape}")
        png = _png_bytes(tex)
        while len(blob.data) % 4:
            blob.data.append(0)
        gltf.bufferViews.append(pygltflib.BufferView(buffer=0, byteOffset=len(blob.data), byteLength=len(png)))
        blob.data.extend(png)
        gltf.images = [pygltflib.Image(bufferView=len(gltf.bufferViews) - 1, mimeType="image/png", name="coat")]
        gltf.samplers = [pygltflib.Sampler(magFilter=9729, minFilter=9987, wrapS=10497, wrapT=10497)]
        gltf.textures = [pygltflib.Texture(sampler=0, source=0)]
        gltf.materials = [pygltflib.Material(
            name="coat", pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
                baseColorTexture=pygltflib.TextureInfo(index=0), metallicFactor=0.0, roughnessFactor=0.8))]
        prim.material = 0
    gltf.meshes = [pygltflib.Mesh(name=rig.name, primitives=[prim])]
    # joint nodes 0..J-1 (same order as the rig), the mesh node J, a scene root J+1
    g = rig.rest_transforms
    nodes = []
    for j in range(nj):
        p = rig.parents[j]
        local = g[j] if p < 0 else np.linalg.inv(g[p]) @ g[j]
        node = pygltflib.Node(name=rig.joint_names[j],
                              children=[int(c) for c in np.flatnonzero(rig.parents == j)])
        r = local[:3, :3]
        if np.allclose(r.T @ r, np.eye(3), atol=1e-6) and np.linalg.det(r) > 0:
            q = Rotation.from_matrix(r).as_quat()
            node.rotation = [float(x) for x in q]
            node.translation = [float(x) for x in local[:3, 3]]
        else:
            node.matrix = [float(x) for x in local.T.reshape(-1)]
        nodes.append(node)
    ibm = np.linalg.inv(g).transpose(0, 2, 1).astype(np.float32)  # column-major
    ibm_acc = blob.add(ibm.reshape(nj, 16), "MAT4", pygltflib.FLOAT)
    root = int(np.flatnonzero(rig.parents < 0)[0])
    nodes.append(pygltflib.Node(name=rig.name, mesh=0, skin=0))
    nodes.append(pygltflib.Node(name=f"{rig.name}_armature", children=[root, nj]))
    gltf.nodes = nodes
    gltf.skins = [pygltflib.Skin(name=f"{rig.name}_skin", joints=list(range(nj)), inverseBindMatrices=ibm_acc,
                                 skeleton=root)]
    gltf.scenes = [pygltflib.Scene(nodes=[nj + 1])]
    while len(blob.data) % 4:
        blob.data.append(0)
    gltf.buffers[0].byteLength = len(blob.data)
    gltf.set_binary_blob(bytes(blob.data))
    return atomic_write(path, lambda tmp: gltf.save_binary(str(tmp)))
