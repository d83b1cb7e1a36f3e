"""Third-party-like variants of the toy asset for tests: Blender exports (``make_variants.py``) plus three rewrites:
unindexed (every triangle its own three vertices, like the Khronos Fox), quantized (integer positions and
weights with the dequantization in the inverse bind matrices, as gltfpack and gltf-transform write them) and
materials (three primitives with their own materials: textured, textured through a transform, flat colour)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pygltflib

BLENDER_VARIANTS = ("seam_split", "flat", "centimetres", "posed_action", "parent_node", "morph", "rigid_child",
                    "draco", "posed_draco")
SCRIPT = Path(__file__).with_name("make_variants.py")


def _save(gltf: pygltflib.GLTF2, data: bytearray, dst: Path) -> Path:
    """Write ``gltf`` as a GLB whose binary chunk is ``data`` (padded to 4 bytes)."""
    while len(data) % 4:
        data.append(0)
    gltf.buffers[0].byteLength = len(data)
    gltf.set_binary_blob(bytes(data))
    gltf.save_binary(str(dst))
    return dst


def _append(gltf: pygltflib.GLTF2, data: bytearray, arr: np.ndarray) -> int:
    """Append ``arr``'s bytes as a new buffer view (4-byte aligned); its index."""
    while len(data) % 4:
        data.append(0)
    gltf.bufferViews.append(pygltflib.BufferView(buffer=0, byteOffset=len(data), byteLength=arr.nbytes))
    data.extend(np.ascontiguousarray(arr).tobytes())
    return len(gltf.bufferViews) - 1


def _copy_rows(gltf: pygltflib.GLTF2, blob: bytes, data: bytearray, index: int, rows: np.ndarray, src: Path) -> int:
    """Append a copy of accessor ``index`` holding only ``rows`` (stored type kept); the new accessor's index."""
    from bat3r_core.rig_io import _read_accessor

    acc = gltf.accessors[index]
    arr = _read_accessor(gltf, blob, index, src)
    raw = arr if not acc.normalized else (arr * np.iinfo(np.dtype(
        {5121: np.uint8, 5123: np.uint16}[acc.componentType])).max).round()
    out = np.ascontiguousarray(raw[rows]).astype({5126: np.float32, 5121: np.uint8, 5123: np.uint16,
                                                  5125: np.uint32}[acc.componentType])
    new = pygltflib.Accessor(bufferView=_append(gltf, data, out), componentType=acc.componentType,
                             count=len(out), type=acc.type, normalized=acc.normalized)
    if acc.min is not None:
        new.min, new.max = out.min(0).tolist(), out.max(0).tolist()
    gltf.accessors.append(new)
    return len(gltf.accessors) - 1


def deindex_glb(src: Path, dst: Path) -> Path:
    """Rewrite ``src`` with unindexed triangle primitives (attributes expanded through the indices)."""
    from bat3r_core.rig_io import _read_accessor

    gltf = pygltflib.GLTF2().load(str(src))
    blob = gltf.binary_blob()
    data = bytearray(blob)
    for mesh in gltf.meshes:
        for prim in mesh.primitives:
            if prim.indices is None:
                continue
            idx = _read_accessor(gltf, blob, prim.indices, src).reshape(-1).astype(np.int64)
            attrs = prim.attributes
            for name in [k for k, v in vars(attrs).items() if isinstance(v, int)]:
                setattr(attrs, name, _copy_rows(gltf, blob, data, getattr(attrs, name), idx, src))
            prim.indices = None
            prim.targets = None
    return _save(gltf, data, dst)


def quantize_glb(src: Path, dst: Path) -> Path:
    """Rewrite ``src`` the way a quantizing optimiser does (``KHR_mesh_quantization``): each skinned primitive's
    POSITION as normalized int16 in its bounding box and WEIGHTS_n as normalized uint8 summing to exactly 255, the
    dequantization ``p = s·q + t`` folded into the skin's inverse bind matrices (``IBM · D``), so that glTF
    skinning shows the mesh where it was."""
    from bat3r_core.rig_io import _read_accessor

    gltf = pygltflib.GLTF2().load(str(src))
    blob = gltf.binary_blob()
    data = bytearray(blob)
    skinned = [n for n in gltf.nodes if n.mesh is not None and n.skin is not None]
    if len({n.skin for n in skinned}) != 1:
        raise ValueError(f"{src}: expected one skin")
    prims = [p for n in skinned for p in gltf.meshes[n.mesh].primitives]
    pos = np.concatenate([_read_accessor(gltf, blob, p.attributes.POSITION, src) for p in prims]).astype(np.float64)
    lo, hi = pos.min(0), pos.max(0)
    t, s = (lo + hi) / 2.0, float((hi - lo).max()) / 2.0
    for p in prims:
        x = _read_accessor(gltf, blob, p.attributes.POSITION, src).astype(np.float64)
        q = np.round((x - t) / s * 32767.0).astype(np.int16)
        gltf.accessors.append(pygltflib.Accessor(bufferView=_append(gltf, data, q), componentType=pygltflib.SHORT,
                                                 normalized=True, count=len(q), type="VEC3",
                                                 min=q.min(0).tolist(), max=q.max(0).tolist()))
        p.attributes.POSITION = len(gltf.accessors) - 1
        sets = [k for k in range(2) if getattr(p.attributes, f"WEIGHTS_{k}", None) is not None]
        w = np.concatenate([_read_accessor(gltf, blob, getattr(p.attributes, f"WEIGHTS_{k}"), src)
                            for k in sets], axis=1).astype(np.float64)
        w = w / w.sum(1, keepdims=True)
        wq = np.floor(w * 255.0).astype(np.int64)
        top = np.argmax(w, axis=1)  # the largest weight absorbs the rounding: every vertex's weights sum to 255
        wq[np.arange(len(wq)), top] += 255 - wq.sum(1)
        for k in sets:
            part = np.ascontiguousarray(wq[:, 4 * k:4 * k + 4]).astype(np.uint8)
            gltf.accessors.append(pygltflib.Accessor(bufferView=_append(gltf, data, part), count=len(part),
                                                     componentType=pygltflib.UNSIGNED_BYTE, normalized=True,
                                                     type="VEC4"))
            setattr(p.attributes, f"WEIGHTS_{k}", len(gltf.accessors) - 1)
        p.targets = None
    skin = gltf.skins[skinned[0].skin]
    ibm = _read_accessor(gltf, blob, skin.inverseBindMatrices, src).astype(np.float64).reshape(-1, 4, 4)
    d = np.eye(4)
    d[:3, :3] *= s
    d[:3, 3] = t
    ibm_q = (ibm.transpose(0, 2, 1) @ d).transpose(0, 2, 1)  # glTF matrices are column-major
    gltf.accessors.append(pygltflib.Accessor(bufferView=_append(gltf, data, ibm_q.astype(np.float32)),
                                             componentType=pygltflib.FLOAT, count=len(ibm_q), type="MAT4"))
    skin.inverseBindMatrices = len(gltf.accessors) - 1
    gltf.extensionsUsed = sorted(set(gltf.extensionsUsed or []) | {"KHR_mesh_quantization"})
    gltf.extensionsRequired = sorted(set(gltf.extensionsRequired or []) | {"KHR_mesh_quantization"})
    return _save(gltf, data, dst)


def split_materials_glb(src: Path, dst: Path) -> tuple[Path, np.ndarray]:
    """Rewrite ``src`` (one textured primitive) as a game asset is often cut: the front third of the triangles
    (along +Z) a second primitive with its own material and texture (a checker, sampled through texCoord 0 with a
    ``KHR_texture_transform`` offset), the lowest fifth a third one with a flat red base-colour factor and no UVs.
    Returns the path and the checker image (RGB)."""
    import cv2

    from bat3r_core.rig_io import _read_accessor

    gltf = pygltflib.GLTF2().load(str(src))
    blob = gltf.binary_blob()
    data = bytearray(blob)
    mesh = next(m for m in gltf.meshes if m.primitives)
    (prim,) = mesh.primitives
    idx = _read_accessor(gltf, blob, prim.indices, src).reshape(-1, 3).astype(np.int64)
    pos = _read_accessor(gltf, blob, prim.attributes.POSITION, src).astype(np.float64)
    centre = pos[idx].mean(1)
    low = centre[:, 1] < np.quantile(centre[:, 1], 0.2)
    front = ~low & (centre[:, 2] > np.quantile(centre[:, 2], 2 / 3))
    checker = np.zeros((64, 64, 3), np.uint8)
    checker[(np.arange(64)[:, None] // 8 + np.arange(64)[None] // 8) % 2 == 0] = (20, 60, 230)
    checker[(np.arange(64)[:, None] // 8 + np.arange(64)[None] // 8) % 2 == 1] = (240, 220, 40)
    ok, png = cv2.imencode(".png", checker[..., ::-1])
    assert ok
    gltf.images.append(pygltflib.Image(bufferView=_append(gltf, data, np.frombuffer(png.tobytes(), np.uint8)),
                                       mimeType="image/png"))
    gltf.textures.append(pygltflib.Texture(source=len(gltf.images) - 1))
    info = pygltflib.TextureInfo(index=len(gltf.textures) - 1, texCoord=0)
    info.extensions = {"KHR_texture_transform": {"offset": [0.125, 0.0]}}  # one checker square
    gltf.materials.append(pygltflib.Material(name="head", pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
        baseColorTexture=info)))
    gltf.materials.append(pygltflib.Material(name="hooves", pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
        baseColorFactor=[1.0, 0.0, 0.0, 1.0])))
    gltf.extensionsUsed = sorted(set(gltf.extensionsUsed or []) | {"KHR_texture_transform"})
    primitives = []
    for material, keep in ((prim.material, ~front & ~low), (len(gltf.materials) - 2, front),
                           (len(gltf.materials) - 1, low)):
        tri = idx[keep]
        used, local = np.unique(tri, return_inverse=True)
        attrs = pygltflib.Attributes()
        for name in [k for k, v in vars(prim.attributes).items() if isinstance(v, int)]:
            if name.startswith("TEXCOORD") and material == len(gltf.materials) - 1:
                continue  # the flat red part has no UVs
            setattr(attrs, name, _copy_rows(gltf, blob, data, getattr(prim.attributes, name), used, src))
        ind = local.reshape(-1).astype(np.uint32)
        gltf.accessors.append(pygltflib.Accessor(bufferView=_append(gltf, data, ind), count=len(ind),
                                                 componentType=pygltflib.UNSIGNED_INT, type="SCALAR"))
        primitives.append(pygltflib.Primitive(attributes=attrs, indices=len(gltf.accessors) - 1,
                                              material=material))
    mesh.primitives = primitives
    return _save(gltf, data, dst), checker


def vertex_colours_glb(src: Path, dst: Path) -> tuple[Path, np.ndarray]:
    """``src`` with ``COLOR_0`` as low-poly packs export it (normalised unsigned-byte RGBA): the front half (+Z)
    red, the back half blue, alpha 128 (which shading ignores). Returns the path and the colours as stored (V, 4)
    uint8."""
    from bat3r_core.rig_io import _read_accessor

    gltf = pygltflib.GLTF2().load(str(src))
    blob = gltf.binary_blob()
    data = bytearray(blob)
    prim = next(m for m in gltf.meshes if m.primitives).primitives[0]
    pos = _read_accessor(gltf, blob, prim.attributes.POSITION, src)
    front = pos[:, 2] > np.median(pos[:, 2])
    rgba = np.where(front[:, None], [230, 20, 10, 128], [15, 40, 220, 128]).astype(np.uint8)
    gltf.accessors.append(pygltflib.Accessor(bufferView=_append(gltf, data, rgba), count=len(rgba),
                                             componentType=pygltflib.UNSIGNED_BYTE, normalized=True, type="VEC4"))
    prim.attributes.COLOR_0 = len(gltf.accessors) - 1
    return _save(gltf, data, dst), rgba


def make_variants(source_glb: Path, out_dir: Path) -> dict[str, Path]:
    """All variants of ``source_glb`` in ``out_dir``: the Blender ones, ``unindexed``, ``quantized``, ``materials``,
    ``vertex_colours``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    proc = subprocess.run([sys.executable, str(SCRIPT), str(source_glb), str(out_dir), *BLENDER_VARIANTS],
                          capture_output=True, text=True, timeout=600)
    if proc.returncode != 0:
        raise RuntimeError(f"make_variants.py failed:\n{proc.stderr[-3000:]}")
    paths = {name: out_dir / f"{name}.glb" for name in BLENDER_VARIANTS}
    paths["unindexed"] = deindex_glb(paths["flat"], out_dir / "unindexed.glb")
    paths["quantized"] = quantize_glb(source_glb, out_dir / "quantized.glb")
    paths["materials"] = split_materials_glb(source_glb, out_dir / "materials.glb")[0]
    paths["vertex_colours"] = vertex_colours_glb(source_glb, out_dir / "vertex_colours.glb")[0]
    return paths
