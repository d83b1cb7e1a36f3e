"""Export variants of a rigged GLB with Blender, the way third-party assets arrive (imports bpy: run it as a script).

    python tests/assets/make_variants.py IN.glb OUT_DIR NAME [NAME ...]

Each NAME writes ``OUT_DIR/NAME.glb`` from a fresh import of ``IN.glb``:

* ``seam_split``: re-unwrapped into UV charts (smart project); Blender's exporter splits vertices at their seams.
* ``flat``: flat-shaded before export, so every triangle gets its own vertices (the test removes the indices).
* ``centimetres``: armature and mesh scaled by 100 and the scale applied (a file in centimetres).
* ``posed_action``: the armature posed away from its rest pose and keyed into an action; exported with the
  current pose as the joints' node transforms (not the rest position) and the animation.
* ``parent_node``: the armature parented to an empty that is rotated 30° about the up axis and scaled by 0.8.
* ``morph``: a shape key that swells the head, exported at a default weight of 0.6.
* ``rigid_child``: an eye (a small sphere) parented to the head bone, not skinned.
* ``draco``: exported Draco-compressed (``KHR_draco_mesh_compression``), as web-optimised downloads are.
* ``posed_draco``: ``posed_action`` exported Draco-compressed.
* ``subdivided_<N>``: the mesh's shape keys cleared (Blender applies no modifier to a mesh with shape keys) and N
  levels of Catmull–Clark subdivision applied before the skin (weights interpolated): a heavier asset of the same
  animal (``benchmarks/bench_assets.py``); ``subdivided_0`` is the asset through Blender's importer and exporter.
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import bpy
from mathutils import Euler, Vector


def _import(src: str):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.import_scene.gltf(filepath=src)
    arm = next(o for o in bpy.context.scene.objects if o.type == "ARMATURE")
    mesh = max((o for o in bpy.context.scene.objects if o.type == "MESH"
                and any(m.type == "ARMATURE" for m in o.modifiers)), key=lambda o: len(o.data.vertices))
    for o in list(bpy.context.scene.objects):  # the importer's bone display shapes are not part of the asset
        if o is not arm and o is not mesh and o.type == "MESH" and o.parent is None:
            bpy.data.objects.remove(o)
    return arm, mesh


def _export(path: Path, **options) -> None:
    bpy.ops.object.select_all(action="SELECT")
    bpy.ops.export_scene.gltf(filepath=str(path), export_format="GLB", use_selection=False, export_skins=True,
                              export_yup=True, **options)


def _head_bone(arm) -> str:
    names = [b.name for b in arm.data.bones]
    return next((n for n in names if "head" in n.lower()), names[-1])


def make(src: str, out_dir: Path, name: str) -> Path:
    arm, mesh = _import(src)
    out = out_dir / f"{name}.glb"
    options = {"export_animations": False}
    if name == "seam_split":  # new UV charts: the exporter splits the vertices along every chart boundary
        bpy.ops.object.select_all(action="DESELECT")
        mesh.select_set(True)
        bpy.context.view_layer.objects.active = mesh
        bpy.ops.object.mode_set(mode="EDIT")
        bpy.ops.mesh.select_all(action="SELECT")
        bpy.ops.uv.smart_project(angle_limit=math.radians(30.0))
        bpy.ops.object.mode_set(mode="OBJECT")
    elif name == "flat":
        for p in mesh.data.polygons:
            p.use_smooth = False
    elif name == "centimetres":
        for o in (arm, mesh):
            o.scale = (100.0, 100.0, 100.0) if o is arm else o.scale
        bpy.context.view_layer.update()
        bpy.ops.object.select_all(action="DESELECT")
        for o in (arm, mesh):
            o.select_set(True)
        bpy.context.view_layer.objects.active = arm
        bpy.ops.object.transform_apply(location=False, rotation=False, scale=True)
    elif name in ("posed_action", "posed_draco"):
        arm.animation_data_create()
        action = bpy.data.actions.new("Trot")
        arm.animation_data.action = action
        for frame, sign in ((1, 1.0), (20, -1.0)):
            for k, pb in enumerate(arm.pose.bones):
                pb.rotation_mode = "XYZ"
                pb.rotation_euler = Euler((sign * 0.25 * math.sin(k), 0.2 * math.cos(k), 0.0))
                pb.keyframe_insert("rotation_euler", frame=frame)
        bpy.context.scene.frame_set(7)  # the saved pose is neither keyframe nor the rest pose
        options = {"export_animations": True, "export_rest_position_armature": False,
                   "export_draco_mesh_compression_enable": name == "posed_draco"}
    elif name == "parent_node":
        empty = bpy.data.objects.new("placement", None)
        bpy.context.scene.collection.objects.link(empty)
        empty.rotation_euler = Euler((0.0, 0.0, math.radians(30.0)))  # Blender's up is +Z
        empty.scale = (0.8, 0.8, 0.8)
        arm.parent = empty
    elif name == "morph":
        mesh.shape_key_add(name="Basis")
        swell = mesh.shape_key_add(name="swell")
        head = arm.data.bones[_head_bone(arm)].head_local
        for v, kv in zip(mesh.data.vertices, swell.data):
            d = (v.co - head).length
            kv.co = v.co + v.normal * 0.05 * max(0.0, 1.0 - d / 0.25)
        swell.value = 0.6
    elif name == "rigid_child":
        bone = _head_bone(arm)
        bpy.ops.mesh.primitive_uv_sphere_add(radius=0.03, segments=12, ring_count=6)
        eye = bpy.context.active_object
        eye.name = "eye"
        head = arm.matrix_world @ arm.data.bones[bone].head_local
        eye.location = head + Vector((0.05, 0.0, 0.05))
        bpy.context.view_layer.update()
        world = eye.matrix_world.copy()
        eye.parent = arm
        eye.parent_type = "BONE"
        eye.parent_bone = bone
        bpy.context.view_layer.update()
        eye.matrix_world = world
    elif name == "draco":
        options["export_draco_mesh_compression_enable"] = True
    elif name.startswith("subdivided_") and name[len("subdivided_"):].isdigit():
        if mesh.data.shape_keys is not None:
            mesh.shape_key_clear()
        levels = int(name[len("subdivided_"):])
        if levels:
            mod = mesh.modifiers.new("subdivision", "SUBSURF")
            mod.levels = mod.render_levels = levels
            with bpy.context.temp_override(object=mesh, active_object=mesh, selected_objects=[mesh]):
                bpy.ops.object.modifier_move_to_index(modifier=mod.name, index=0)  # before the armature
                bpy.ops.object.modifier_apply(modifier=mod.name)
    else:
        raise SystemExit(f"unknown variant {name!r}")
    _export(out, **options)
    return out


def main(argv: list[str]) -> int:
    if len(argv) < 3:
        print(__doc__, file=sys.stderr)
        return 2
    src, out_dir, names = argv[0], Path(argv[1]), argv[2:]
    out_dir.mkdir(parents=True, exist_ok=True)
    for name in names:
        print(make(src, out_dir, name))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
