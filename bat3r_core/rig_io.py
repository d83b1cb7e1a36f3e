"""Reading and writing rigged meshes: glTF/GLB natively (pygltflib), FBX and .blend through Blender.

``load_rig(path)`` returns a validated :class:`bat3r_core.rig.Rig`; ``save_rig_glb(rig, path)`` writes a GLB with a
real skin (joint nodes, inverse bind matrices, JOINTS_n/WEIGHTS_n) that Blender's importer and
``load_rig`` read back.
"""
from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pygltflib
from scipy.spatial.transform import Rotation

from .rig import Rig, RigError
from .shards import atomic_write

__all__ = ["load_rig", "save_rig_glb", "RigError"]

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
_MAX_INFLUENCE_SETS = 2  # JOINTS_0/1, WEIGHTS_0/1: up to 8 influences per vertex


def _read_accessor(gltf: pygltflib.GLTF2, blob: bytes, index: int, path: Path) -> np.ndarray:
    acc = gltf.accessors[index]
    dtype = np.dtype(_COMPONENT[acc.componentType]).newbyteorder("<")
    ncomp = _NCOMP[acc.type]
    if acc.bufferView is None:
        out = np.zeros((acc.count, ncomp), dtype=dtype)
    else:
        view = gltf.bufferViews[acc.bufferView]
        if view.buffer != 0:
            raise RigError(f"{path}: only single-buffer glTF/GLB files are supported (accessor {index})")
        start = (view.byteOffset or 0) + (acc.byteOffset or 0)
        elem = dtype.itemsize * ncomp
        stride = view.byteStride or elem
        if stride == elem:
            out = np.frombuffer(blob, dtype=dtype, count=acc.count * ncomp, offset=start).reshape(acc.count, ncomp)
        else:
            raw = np.frombuffer(blob, dtype=np.uint8, count=stride * (acc.count - 1) + elem, offset=start)
            rows = np.lib.stride_tricks.as_strided(raw, shape=(acc.count, elem), strides=(stride, 1))
            out = rows.copy().view(dtype).reshape(acc.count, ncomp)
    if acc.sparse is not None:
        raise RigError(f"{path}: sparse accessors are not supported (accessor {index})")
    out = np.array(out)
    if acc.normalized and acc.componentType != pygltflib.FLOAT:
        out = out.astype(np.float64) / np.iinfo(dtype).max
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
    names = {0: "POINTS", 1: "LINES", 2: "LINE_LOOP", 3: "LINE_STRIP"}
    raise RigError(f"{path}: {prim_label} has primitive mode {names.get(mode, mode)}, which cannot be "
                   f"triangulated; provide a triangle (or quad/polygon, via Blender) mesh")


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


def _load_gltf(path: Path) -> Rig:
    try:
        gltf = pygltflib.GLTF2().load(str(path))
    except Exception as e:  # pygltflib raises assorted errors on corrupt files
        raise RigError(f"{path}: not a readable glTF/GLB file ({type(e).__name__}: {e})") from e
    blob = gltf.binary_blob()
    if blob is None and gltf.buffers:
        uri = gltf.buffers[0].uri or ""
        if uri.startswith("data:"):
            import base64
            blob = base64.b64decode(uri.split(",", 1)[1])
        else:
            blob = (path.parent / uri).read_bytes()
    if not gltf.skins:
        raise RigError(f"{path}: the mesh has no skin (no glTF 'skins'); bat3r needs a rigged, skinned mesh "
                       f"(armature + vertex weights)")
    skin = gltf.skins[0]
    joint_nodes = list(skin.joints)
    skinned = [n for n in gltf.nodes if n.mesh is not None and n.skin == 0]
    if not skinned:
        raise RigError(f"{path}: no mesh node uses the skin; the mesh must be bound to the armature")
    node_parent = _parents_of_nodes(gltf, path)
    jset = {n: k for k, n in enumerate(joint_nodes)}
    parents = []
    for n in joint_nodes:
        p = node_parent[n]
        while p != -1 and p not in jset:
            p = node_parent[p]
        parents.append(jset[p] if p != -1 else -1)
    names = [gltf.nodes[n].name or f"joint_{k}" for k, n in enumerate(joint_nodes)]
    if skin.inverseBindMatrices is not None:
        ibm = _read_accessor(gltf, blob, skin.inverseBindMatrices, path).astype(np.float64)
        ibm = ibm.reshape(-1, 4, 4).transpose(0, 2, 1)
        rest = np.linalg.inv(ibm)
    else:  # bind pose = the nodes' global transforms
        glob = {}

        def world(i):
            if i not in glob:
                p = node_parent[i]
                glob[i] = (world(p) if p != -1 else np.eye(4)) @ _node_matrix(gltf.nodes[i])
            return glob[i]

        rest = np.stack([world(n) for n in joint_nodes])
    verts, faces, uvs, weights = [], [], [], []
    offset = 0
    has_uv = True
    for node in skinned:
        mesh = gltf.meshes[node.mesh]
        for pi, prim in enumerate(mesh.primitives):
            label = f"mesh '{mesh.name}' primitive {pi}"
            attrs = prim.attributes
            if attrs.POSITION is None:
                raise RigError(f"{path}: {label} has no POSITION attribute")
            pos = _read_accessor(gltf, blob, attrs.POSITION, path).astype(np.float64)
            if not np.isfinite(pos).all():
                raise RigError(f"{path}: {label} has NaN/inf vertex positions")
            idx = (_read_accessor(gltf, blob, prim.indices, path).reshape(-1).astype(np.int64)
                   if prim.indices is not None else np.arange(len(pos)))
            mode = _TRIANGLES if prim.mode is None else prim.mode
            faces.append(_triangles(mode, idx, path, label) + offset)
            w = np.zeros((len(pos), len(joint_nodes)))
            found = False
            for s in range(_MAX_INFLUENCE_SETS + 2):
                ja = getattr(attrs, f"JOINTS_{s}", None)
                wa = getattr(attrs, f"WEIGHTS_{s}", None)
                if ja is None or wa is None:
                    break
                found = True
                jj = _read_accessor(gltf, blob, ja, path).astype(np.int64)
                ww = _read_accessor(gltf, blob, wa, path).astype(np.float64)
                if jj.max(initial=0) >= len(joint_nodes):
                    raise RigError(f"{path}: {label} JOINTS_{s} references joint {jj.max()} but the skin has "
                                   f"{len(joint_nodes)} joints")
                np.add.at(w, (np.repeat(np.arange(len(pos)), jj.shape[1]), jj.reshape(-1)), ww.reshape(-1))
            if not found:
                raise RigError(f"{path}: {label} has no JOINTS_0/WEIGHTS_0 skin attributes")
            weights.append(w)
            verts.append(pos)
            if attrs.TEXCOORD_0 is not None:
                uvs.append(_read_accessor(gltf, blob, attrs.TEXCOORD_0, path).astype(np.float64))
            else:
                has_uv = False
            offset += len(pos)
    uv = None
    if has_uv and uvs:
        uv = np.concatenate(uvs)
        uv[:, 1] = 1.0 - uv[:, 1]  # glTF's UV origin is top-left; bat3r stores OpenGL-style (origin bottom-left)
    name = Path(path).stem
    try:
        return Rig.from_unordered(name, np.concatenate(verts), np.concatenate(faces), names, np.asarray(parents),
                                  rest, np.concatenate(weights), uvs=uv)
    except RigError as e:
        raise RigError(f"{path}: {e}") from None


def _convert_with_blender(path: Path) -> Path:
    out = Path(tempfile.mkdtemp(prefix="bat3r_convert_")) / (path.stem + ".glb")
    cmd = [sys.executable, "-m", "bat3r_core.render.blender_convert", str(path), str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    if proc.returncode != 0 or not out.is_file():
        tail = (proc.stderr or proc.stdout)[-2000:]
        raise RigError(f"{path}: Blender could not convert it to GLB (exit {proc.returncode}):\n{tail}")
    return out


def load_rig(path: str | os.PathLike) -> Rig:
    """Load a rigged, skinned mesh (``.glb``/``.gltf``; ``.fbx``/``.blend`` are converted through Blender).

    Raises:
        FileNotFoundError: the file does not exist (the message names it).
        RigError: the asset is not a usable rig (no skin, bad weights, cycles or several roots, NaN vertices,
            faces that cannot be triangulated, ...); the message names the file and the problem.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"rigged asset {path} does not exist; provide a rigged, skinned mesh "
                                f"(.glb/.gltf, or .fbx/.blend converted through Blender)")
    suffix = path.suffix.lower()
    if suffix in (".glb", ".gltf"):
        return _load_gltf(path)
    if suffix in (".fbx", ".blend"):
        converted = _convert_with_blender(path)
        rig = _load_gltf(converted)
        return Rig(name=path.stem, rest_vertices=rig.rest_vertices, faces=rig.faces, joint_names=rig.joint_names,
                   parents=rig.parents, rest_transforms=rig.rest_transforms, skin_weights=rig.skin_weights,
                   uvs=rig.uvs)
    raise RigError(f"{path}: unsupported rig format '{suffix}'; expected .glb, .gltf, .fbx or .blend")


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


def save_rig_glb(rig: Rig, path: str | os.PathLike, texture: np.ndarray | None = None) -> Path:
    """Write ``rig`` as a binary glTF with a skin.

    Joint nodes carry the rest pose as local TRS (rotation + translation; a rest frame with scale or shear is
    written as a matrix). Up to 8 influences per vertex are written (JOINTS_0/1, WEIGHTS_0/1); weights beyond
    the 8 largest are dropped and the rest renormalised.

    Args:
        texture: optional (H, W, 3) uint8 RGB base-colour image, embedded as PNG.
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
