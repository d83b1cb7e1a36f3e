"""Blender's own glTF importer's view of an asset's rest pose (imports bpy; run as a subprocess)::

    python -m bat3r_core.render.blender_rest IN.glb|IN.gltf OUT.npy

Imports the file with Blender's glTF importer, puts every armature in its rest position, and saves the evaluated
vertices of every mesh, in Blender's world frame (Z up), as one ``(N, 3)`` float64 array. ``bat3r asset check``
compares bat3r's rest vertices with them (an independent reading of the same file).
"""
from __future__ import annotations

import sys

import numpy as np


def rest_vertices(src: str) -> np.ndarray:
    """(N, 3) world-frame vertices of every mesh of ``src`` after import, armatures at rest."""
    try:
        import bpy
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("reading an asset with Blender needs its Python module: pip install bpy==5.0.1") from e
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.import_scene.gltf(filepath=src)
    for o in bpy.context.scene.objects:
        if o.type == "ARMATURE":
            o.data.pose_position = "REST"
    dg = bpy.context.evaluated_depsgraph_get()
    dg.update()
    chunks = []
    for o in bpy.context.scene.objects:
        if o.type != "MESH" or o.hide_render or o.hide_get():
            continue
        ev = o.evaluated_get(dg)
        me = ev.to_mesh()
        co = np.empty(len(me.vertices) * 3)
        me.vertices.foreach_get("co", co)
        m = np.array(ev.matrix_world)
        chunks.append(co.reshape(-1, 3) @ m[:3, :3].T + m[:3, 3])
        ev.to_mesh_clear()
    return np.concatenate(chunks) if chunks else np.zeros((0, 3))


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2:
        print("usage: python -m bat3r_core.render.blender_rest IN.glb OUT.npy", file=sys.stderr)
        return 2
    np.save(args[1], rest_vertices(args[0]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
