"""Third-party-like variants of the toy asset for tests: Blender exports (``make_variants.py``) plus an unindexed
rewrite (every triangle its own three vertices, like the Khronos Fox)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pygltflib

BLENDER_VARIANTS = ("seam_split", "flat", "centimetres", "posed_action", "parent_node", "morph", "rigid_child")
SCRIPT = Path(__file__).with_name("make_variants.py")


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
                while len(data) % 4:
                    data.append(0)
                gltf.bufferViews.append(pygltflib.BufferView(buffer=0, byteOffset=len(data), byteLength=out.nbytes))
                data.extend(out.tobytes())
                new = pygltflib.Accessor(bufferView=len(gltf.bufferViews) - 1, componentType=acc.componentType,
                                         count=len(idx), type=acc.type, normalized=acc.normalized)
                if name == "POSITION":
                    new.min, new.max = out.min(0).tolist(), out.max(0).tolist()
                gltf.accessors.append(new)
                setattr(attrs, name, len(gltf.accessors) - 1)
            prim.indices = None
            prim.targets = None
    while len(data) % 4:
        data.append(0)
    gltf.buffers[0].byteLength = len(data)
    gltf.set_binary_blob(bytes(data))
    gltf.save_binary(str(dst))
    return dst


def make_variants(source_glb: Path, out_dir: Path) -> dict[str, Path]:
    """All variants of ``source_glb`` in ``out_dir``: the Blender ones and ``unindexed``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    proc = subprocess.run([sys.executable, str(SCRIPT), str(source_glb), str(out_dir), *BLENDER_VARIANTS],
                          capture_output=True, text=True, timeout=600)
    if proc.returncode != 0:
        raise RuntimeError(f"make_variants.py failed:\n{proc.stderr[-3000:]}")
    paths = {name: out_dir / f"{name}.glb" for name in BLENDER_VARIANTS}
    paths["unindexed"] = deindex_glb(paths["flat"], out_dir / "unindexed.glb")
    return paths
