"""Convert a rigged FBX or .blend asset to a skinned GLB with Blender (imports bpy; run as a subprocess)::

    python -m bat3r_core.render.blender_convert IN.fbx|IN.blend OUT.glb

The GLB keeps the armature, bone names and hierarchy, vertex groups (as a glTF skin with inverse bind matrices),
meshes parented to the armature or its bones (eyes, tack), UVs and the first material's textures, in glTF's Y-up
frame. :func:`bat3r_core.rig_io.load_rig` calls this for ``.fbx`` and ``.blend`` files. (glTF is read natively:
Blender's glTF importer bakes the pose a file was saved in into the mesh and makes it the rest pose.) Exit code 0 on
success; 2 with a message on stderr when the input has no armature or no mesh bound to one.
"""
from __future__ import annotations

import sys
from pathlib import Path


def convert(src: str | Path, dst: str | Path) -> Path:
    """Convert ``src`` (.fbx or .blend) into the GLB ``dst``; raises ValueError for unusable inputs."""
    try:
        import bpy
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("converting FBX/.blend needs Blender's Python module: pip install bpy==5.0.1") from e
    src, dst = Path(src), Path(dst)
    if not src.is_file():
        raise FileNotFoundError(f"input asset {src} does not exist")
    suffix = src.suffix.lower()
    if suffix == ".blend":
        bpy.ops.wm.open_mainfile(filepath=str(src))
    elif suffix == ".fbx":
        bpy.ops.wm.read_factory_settings(use_empty=True)
        bpy.ops.import_scene.fbx(filepath=str(src))
    else:
        raise ValueError(f"input must be .fbx or .blend, got {src.name}")
    objects = list(bpy.context.scene.objects)
    armatures = [o for o in objects if o.type == "ARMATURE"]
    skinned = [o for o in objects if o.type == "MESH" and any(m.type == "ARMATURE" and m.object is not None
                                                              for m in o.modifiers)]
    if not armatures:
        raise ValueError(f"{src}: no armature; bat3r needs a rigged, skinned mesh")
    if not skinned:
        raise ValueError(f"{src}: no mesh is bound to an armature (Armature modifier); bat3r needs a skinned mesh")

    def below_armature(o) -> bool:
        while o.parent is not None:
            if o.parent.type == "ARMATURE":
                return True
            o = o.parent
        return False

    attached = [o for o in objects if o.type == "MESH" and o not in skinned and below_armature(o)]  # eyes, tack
    bpy.ops.object.select_all(action="DESELECT")
    for o in armatures + skinned + attached:
        o.hide_set(False)
        o.select_set(True)
    for o in armatures:  # export the rest pose, not whatever pose the file was saved in
        o.data.pose_position = "REST"
    dst.parent.mkdir(parents=True, exist_ok=True)
    bpy.ops.export_scene.gltf(filepath=str(dst), export_format="GLB", use_selection=True, export_skins=True,
                              export_yup=True, export_animations=False, export_apply=False)
    if not dst.is_file():
        raise RuntimeError(f"Blender's glTF exporter wrote nothing to {dst}")
    return dst


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2:
        print("usage: python -m bat3r_core.render.blender_convert IN.fbx|IN.blend OUT.glb", file=sys.stderr)
        return 2
    try:
        convert(args[0], args[1])
    except (ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
