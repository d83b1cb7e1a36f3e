"""Third-party-like variants of the toy asset for tests: Blender exports (``make_variants.py``) plus two rewrites:
unindexed (every triangle its own three vertices, like the Khronos Fox) and quantized (integer positions and
weights with the dequantization in the inverse bind matrices, as gltfpack and gltf-transform write them)."""
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
                acc = gltf.accessors[getattr(attrs, name)]
                arr = _read_accessor(gltf, blob, getattr(attrs, name), src)
                raw = arr if not acc.normalized else (arr * np.iinfo(np.dtype(
                    {5121: np.uint8, 5123: np.uint16}[acc.componentType])).max).round()
                out = np.ascontiguousarray(raw[idx]).astype({5126: np.float32, 5121: np.uint8, 5123: np.uint16,
                                                            5125: np.uint32}[acc.componentType])
                new = pygltflib.Accessor(bufferView=_append(gltf, data, out), componentType=acc.componentType,
                                         count=len(idx), type=acc.type, normalized=acc.normalized)
                if name == "POSITION":
                    new.min, new.max = out.min(0).tolist(), out.max(0).tolist()
                gltf.accessors.append(new)
                setattr(attrs, name, len(gltf.accessors) - 1)
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


def make_variants(source_glb: Path, out_dir: Path) -> dict[str, Path]:
    """All variants of ``source_glb`` in ``out_dir``: the Blender ones, ``unindexed`` and ``quantized``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    proc = subprocess.run([sys.executable, str(SCRIPT), str(source_glb), str(out_dir), *BLENDER_VARIANTS],
                          capture_output=True, text=True, timeout=600)
    if proc.returncode != 0:
        raise RuntimeError(f"make_variants.py failed:\n{proc.stderr[-3000:]}")
    paths = {name: out_dir / f"{name}.glb" for name in BLENDER_VARIANTS}
    paths["unindexed"] = deindex_glb(paths["flat"], out_dir / "unindexed.glb")
    paths["quantized"] = quantize_glb(source_glb, out_dir / "quantized.glb")
    return paths
