"""Real assets: the canonical rest pose of third-party files, units and axes, the normalised asset, the body-frame
proposal and ``bat3r asset check`` on Blender-made variants of the toy and on the shared third-party rigs."""
from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pygltflib
import pytest
import torch
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from bat3r_core.asset_check import THRESHOLDS, check_asset
from bat3r_core.assets import prepare_asset, propose_body_frame
from bat3r_core.rig import RigError
from bat3r_core.rig_io import load_rig, read_asset, save_rig_glb, up_axis_rotation
from bat3r_core.skinning import skin
from bat3r_core.toy import TOY_BODY_FRAME, toy_coat_texture
from tests.assets.variants import make_variants, split_materials_glb

SHARED = Path(__file__).resolve().parents[3] / "shared" / "assets"
FOX = SHARED / "fox" / "Fox.glb"
DOG = SHARED / "dog_puppy" / "scene.gltf"
needs_shared = pytest.mark.skipif(not FOX.is_file() or not DOG.is_file(),
                                  reason=f"the shared third-party assets are not in {SHARED}")


@pytest.fixture(scope="module")
def variants(tmp_path_factory, toy_rig):
    root = tmp_path_factory.mktemp("variants")
    glb = save_rig_glb(toy_rig, root / "toy.glb", texture=toy_coat_texture("bay", size=256))
    return make_variants(glb, root / "out")


def _same_points(a: np.ndarray, b: np.ndarray) -> float:
    """Largest distance from a point of either set to the other set (vertex order may differ)."""
    return float(max(cKDTree(b).query(a)[0].max(), cKDTree(a).query(b)[0].max()))


def test_up_axis_rotation_maps_each_axis_to_plus_y():
    for axis in ("+X", "-X", "+Y", "-Y", "+Z", "-Z"):
        v = np.zeros(3)
        v["XYZ".index(axis[1])] = 1.0 if axis[0] == "+" else -1.0
        r = up_axis_rotation(axis)
        np.testing.assert_allclose(r @ v, [0.0, 1.0, 0.0], atol=1e-12)
        assert np.isclose(np.linalg.det(r), 1.0)
    with pytest.raises(ValueError, match="up_axis must be one of"):
        up_axis_rotation("up")


@pytest.mark.blender
def test_variants_share_the_toys_bind_pose(variants, toy_rig):
    rest = toy_rig.rest_vertices
    for name in ("seam_split", "flat", "unindexed", "posed_action"):
        rig = load_rig(variants[name])
        assert _same_points(rig.rest_vertices, rest) < 1e-5, name
    seam = load_rig(variants["seam_split"])
    assert seam.num_vertices > 1.5 * toy_rig.num_vertices  # really split at the new UV seams
    assert load_rig(variants["unindexed"]).num_vertices == 3 * len(toy_rig.faces)
    # the posed file's animation and node pose are ignored, but it has them
    info = read_asset(variants["posed_action"])[1]
    assert info.animations == ("Trot",)
    # a scaled, rotated node above the armature places the bind mesh (30 degrees about the up axis, x 0.8)
    placed = 0.8 * rest @ Rotation.from_euler("y", 30, degrees=True).as_matrix().T
    assert _same_points(load_rig(variants["parent_node"]).rest_vertices, placed) < 1e-5
    # centimetres: refused without asset_scale, the toy's own size with it
    with pytest.raises(RigError, match=r"236\.\d m long .*asset_scale: 0.01"):
        load_rig(variants["centimetres"])
    assert _same_points(load_rig(variants["centimetres"], scale=0.01).rest_vertices, rest) < 1e-5


@pytest.mark.blender
def test_quantized_and_compressed_gltf_read_as_their_source(variants, toy_rig, tmp_path):
    rest, extent = toy_rig.rest_vertices, float(np.ptp(toy_rig.rest_vertices, axis=0).max())
    joints = {n: toy_rig.rest_transforms[k, :3, 3] for k, n in enumerate(toy_rig.joint_names)}

    def joint_error(rig):
        return max(float(np.linalg.norm(rig.rest_transforms[k, :3, 3] - joints[n]))
                   for k, n in enumerate(rig.joint_names))

    # int16 positions over the bounding box, uint8 weights, the dequantization in the inverse bind matrices: the
    # mesh as stored is the integer grid (extent 2), the scene shows it at the toy's size
    rig, info = read_asset(variants["quantized"])
    assert _same_points(rig.rest_vertices, rest) <= extent / 65534 + 1e-6
    assert joint_error(rig) < 1e-5
    w = toy_rig.skin_weights  # rounded down to 1/255 but for the largest, which takes the remainder
    assert np.abs(rig.skin_weights - w).max() <= (np.count_nonzero(w, axis=1).max() + 1) / 255
    assert info.dequantization is not None and abs(info.dequantization[0] - extent / 2) < 1e-4
    assert any("KHR_mesh_quantization" in n for n in info.notes)
    assert prepare_asset(variants["quantized"], tmp_path).rig.num_vertices == toy_rig.num_vertices
    # Draco (Blender's exporter: 14-bit positions), also saved posed with an action: the bind pose as ever
    for name in ("draco", "posed_draco"):
        rig, info = read_asset(variants[name])
        assert _same_points(rig.rest_vertices, rest) < 2 * extent / 2 ** 14 and joint_error(rig) < 1e-5, name
        assert rig.num_vertices == toy_rig.num_vertices and len(rig.faces) == len(toy_rig.faces)
        np.testing.assert_allclose(rig.skin_weights.sum(1), 1.0, atol=1e-5)
    assert info.node_pose_deg > 5 and info.animations == ("Trot",)
    g = pygltflib.GLTF2().load(str(variants["draco"]))  # a torn Draco buffer: refused by name
    blob = bytearray(g.binary_blob())
    view = g.bufferViews[g.meshes[0].primitives[0].extensions["KHR_draco_mesh_compression"]["bufferView"]]
    blob[(view.byteOffset or 0):(view.byteOffset or 0) + view.byteLength] = bytes(view.byteLength)
    g.set_binary_blob(bytes(blob))
    g.save_binary(str(tmp_path / "torn.glb"))
    with pytest.raises(RigError, match=r"torn\.glb: a Draco-compressed primitive cannot be decoded"):
        read_asset(tmp_path / "torn.glb")
    # meshopt: neither bat3r nor Blender decodes it; refused with the fix
    g = pygltflib.GLTF2().load(str(variants["quantized"]))
    g.extensionsUsed = g.extensionsUsed + ["EXT_meshopt_compression"]
    g.extensionsRequired = g.extensionsRequired + ["EXT_meshopt_compression"]
    g.save_binary(str(tmp_path / "meshopt.glb"))
    with pytest.raises(RigError, match=r"meshopt\.glb: the file requires EXT_meshopt_compression .*gltf-transform"):
        load_rig(tmp_path / "meshopt.glb")


@pytest.mark.blender
def test_morph_targets_apply_at_their_default_weight(variants, toy_rig):
    rig, info = read_asset(variants["morph"])
    assert info.morph_targets == 1 and info.morph_weights == pytest.approx((0.6,), abs=1e-6)
    from bat3r_core.rig_io import _Gltf

    g = _Gltf(variants["morph"])
    base = g.accessor(g.gltf.meshes[0].primitives[0].attributes.POSITION).astype(np.float64)
    moved = np.linalg.norm(rig.rest_vertices - base, axis=1)  # the bind frames are the identity here
    # 0.6 x 5 cm along the normals at the head joint, fading out 25 cm away; the rest of the body stays
    assert 0.01 < moved.max() <= 0.0301 and np.median(moved) < 1e-6
    assert _same_points(base, toy_rig.rest_vertices) < 1e-5


@pytest.mark.blender
def test_a_rigid_child_mesh_is_skinned_to_its_joint(variants, toy_rig):
    rig, info = read_asset(variants["rigid_child"])
    assert any(name == "eye" and "rigid on joint 'head'" in what for name, what in info.meshes)
    head = rig.joint_index("head")
    eye = np.flatnonzero(cKDTree(toy_rig.rest_vertices).query(rig.rest_vertices)[0] > 1e-4)
    assert len(eye) == rig.num_vertices - toy_rig.num_vertices and (rig.skin_weights[eye, head] == 1.0).all()
    theta = torch.zeros(1, rig.num_joints, 3, dtype=torch.float64)
    theta[0, head] = torch.tensor([0.0, 0.6, 0.0])
    out = skin(rig.tensors(dtype=torch.float64), theta)
    g = out.joint_transforms[0, head].numpy() @ np.linalg.inv(rig.rest_transforms[head])
    moved = rig.rest_vertices[eye] @ g[:3, :3].T + g[:3, 3]
    np.testing.assert_allclose(out.vertices[0].numpy()[eye], moved, atol=1e-9)  # it follows the head rigidly


@pytest.mark.blender
def test_several_materials_share_one_base_colour_atlas(toy_rig, tmp_path):
    """Three primitives with their own materials (the toy's coat; a checker through a texture transform; a flat red
    factor without UVs) read as one rig whose UVs sample, from one atlas, the colour each material shows."""
    coat = toy_coat_texture("bay", size=256)
    src = save_rig_glb(toy_rig, tmp_path / "toy.glb", texture=coat)
    path, checker = split_materials_glb(src, tmp_path / "materials.glb")
    toy, _ = read_asset(src)
    rig, info = read_asset(path)
    assert _same_points(rig.rest_vertices, toy_rig.rest_vertices) < 1e-6
    atlas = info.texture
    assert atlas.shape == (512, 512, 3)  # three 256 px tiles in a 2 x 2 grid, the coat (most faces) first
    assert info.texture_source.startswith("atlas of 0: embedded image 0; 1: embedded image 1; 2: base-colour factor")
    assert any("3 materials: their base colours are packed into one 512x512 atlas" in n for n in info.notes)

    def sample(image, uv):  # nearest texel at bat3r's UVs (origin bottom-left)
        h, w = image.shape[:2]
        return image[np.clip(((1 - uv[:, 1]) * h).astype(int), 0, h - 1), np.clip((uv[:, 0] * w).astype(int), 0, w - 1)]

    g = pygltflib.GLTF2().load(str(path))
    counts = [g.accessors[p.attributes.POSITION].count for p in g.meshes[0].primitives]
    body, head, hooves = np.split(np.arange(rig.num_vertices), np.cumsum(counts)[:-1])
    near = cKDTree(toy.rest_vertices).query(rig.rest_vertices[body])[1]  # the same vertex in the one-material file
    coat_here = sample(coat, toy.uvs[near]).astype(int)
    assert np.median(np.abs(sample(atlas, rig.uvs[body]).astype(int) - coat_here)) <= 6
    uv_head = toy.uvs[cKDTree(toy.rest_vertices).query(rig.rest_vertices[head])[1]].copy()
    uv_head[:, 0] += 0.125  # the head's KHR_texture_transform offset, in the checker's own UV space
    uv_head[:, 1] = 1 - ((1 - uv_head[:, 1]) % 1.0)
    uv_head[:, 0] %= 1.0
    blue = (sample(checker, uv_head)[:, 2] > 128)  # which checker square each vertex falls in
    got = sample(atlas, rig.uvs[head]).astype(int)
    nearer_blue = np.abs(got - (20, 60, 230)).sum(1) < np.abs(got - (240, 220, 40)).sum(1)
    texel = np.c_[uv_head[:, 0], 1 - uv_head[:, 1]] * 64  # checker texels (8 per square)
    edge = np.minimum(texel % 8, 8 - texel % 8).min(1)
    assert np.mean(nearer_blue == blue) > 0.95 and (edge[nearer_blue != blue] < 0.3).all()  # misses: on edges
    assert (sample(atlas, rig.uvs[hooves]) == (255, 0, 0)).all()
    prepared = prepare_asset(path, tmp_path / "prepared")  # the normalised GLB keeps the atlas and its UVs
    again, again_info = read_asset(prepared.path)
    assert np.abs(again_info.texture.astype(int) - atlas.astype(int)).max() <= 1
    assert np.abs(again.uvs - rig.uvs).max() < 1e-6


def test_the_body_frame_proposal_finds_the_toys_catalog_frame(toy_rig, variants):
    p = propose_body_frame(toy_rig)
    assert p.as_spec() == {"origin": TOY_BODY_FRAME["origin"], "forward": list(TOY_BODY_FRAME["forward"]),
                           "horizontal": list(TOY_BODY_FRAME["horizontal"])}
    assert p.head_from == "joint names" and abs(p.lateral_axis[0]) > 0.999
    # the same frame from a seam-split export
    assert propose_body_frame(load_rig(variants["seam_split"])).as_spec() == p.as_spec()


@needs_shared
def test_shared_assets_load_in_metres_with_their_texture(tmp_path):
    with pytest.raises(RigError, match=r"154\.7 m long .*centimetres: set `asset_scale: 0.01`"):
        load_rig(FOX)
    prepared = prepare_asset(FOX, tmp_path, scale=0.01)
    rig = prepared.rig
    assert rig.num_vertices == 1728 and rig.num_joints == 24
    assert 1.5 < np.ptp(rig.rest_vertices, axis=0).max() < 1.6
    assert prepared.info.animations == ("Survey", "Walk", "Run")
    own = read_asset(prepared.path)[1].texture
    assert own is not None and own.shape == prepared.info.texture.shape == (1024, 1024, 3)
    assert np.abs(own.astype(int) - prepared.info.texture.astype(int)).max() <= 1  # PNG round trip
    assert prepare_asset(FOX, tmp_path, scale=0.01).path == prepared.path  # cached
    dog, info = read_asset(DOG)
    assert dog.num_joints == 46 and info.morph_targets == 2 and len(dog.left_right_pairs) == 15
    assert any("1.75x the size of its bind pose" in n for n in info.notes)
    left = [dog.joint_names[a] for a, _ in dog.left_right_pairs]
    assert all("_l_" in n for n in left)  # +X is the animal's left


def _assert_check_passes(report):
    assert not report.failed, report.text()
    f = report.figures
    assert min(f["mask_iou"]) >= THRESHOLDS["mask_iou"] and len(f["mask_iou"]) == 8
    assert max(f["blender_vertex_error_mm"]) <= THRESHOLDS["vertex_mm"]
    fit, rest = np.array(f["fit_vertex_error_cm"]), np.array(f["rest_vertex_error_cm"])
    assert fit.mean() < THRESHOLDS["fit_cm"] and np.mean(fit < rest) >= THRESHOLDS["fit_beats_rest"]
    assert report.contact_sheet.is_file()


@pytest.mark.blender
@pytest.mark.parametrize("name", ["seam_split", "unindexed", "centimetres", "posed_action", "parent_node", "morph",
                                  "rigid_child", "quantized", "draco", "materials"])
def test_asset_check_passes_on_the_toy_variants(variants, name, tmp_path):
    report = check_asset(variants[name], tmp_path, scale=0.01 if name == "centimetres" else 1.0, resolution=64,
                         importer=name in ("seam_split", "parent_node", "posed_action"))
    _assert_check_passes(report)
    assert report.body_frame["horizontal"] == list(TOY_BODY_FRAME["horizontal"])
    if name in ("seam_split", "parent_node"):  # Blender's own importer reads the same rest pose
        assert report.figures["importer_rest_error_mm"] <= THRESHOLDS["importer_mm"]
    if name == "posed_action":  # saved posed: the importer takes that pose as its rest, so it is not compared
        assert "importer_rest_error_mm" not in report.figures


@needs_shared
@pytest.mark.blender
@pytest.mark.parametrize("path, scale", [(FOX, 0.01), (DOG, 1.0)], ids=["fox", "dog_puppy"])
def test_asset_check_passes_on_the_shared_assets(path, scale, tmp_path):
    _assert_check_passes(check_asset(path, tmp_path, scale=scale, resolution=64))


@needs_shared
def test_asset_check_command_exit_codes(tmp_path):
    cmd = [sys.executable, "-m", "bat3r_core.cli", "asset", "check", str(FOX), "--out", str(tmp_path / "a"),
           "--no-render", "--no-fit"]
    bad = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert bad.returncode == 1 and "[FAIL] load" in bad.stdout and "154.7 m long" in bad.stdout
    good = subprocess.run(cmd + ["--asset-scale", "0.01"], capture_output=True, text=True, timeout=300)
    assert good.returncode == 0, good.stdout + good.stderr
    assert "1728 in the file, 290 welded by position" in good.stdout
    assert "animations: 3 ['Survey', 'Walk', 'Run']" in good.stdout and "all checks passed" in good.stdout
    assert math.isfinite(float(good.stdout.split("longest ")[1].split(" m")[0]))


@pytest.mark.blender
def test_vertex_colours_are_read_kept_and_rendered(toy_rig, tmp_path):
    """COLOR_0 as low-poly packs export it (normalised bytes, RGBA) is read as linear RGB, kept by the prepared
    asset, and multiplied into the base colour the render worker shades: the toy's front half renders red and its
    back half blue, pixel by pixel as the render's own canonical labels place them. A category's own textures
    replace the asset's look, vertex colours included."""
    from bat3r_core.render.config import RenderConfig, SceneAssets
    from bat3r_core.render.jobs import RenderJob
    from bat3r_core.render.runner import render_shard
    from bat3r_core.shards import read_shard
    from bat3r_core.viewpoints import frame_camera, identity_frame
    from tests.assets.variants import vertex_colours_glb

    src = save_rig_glb(toy_rig, tmp_path / "toy.glb")  # no texture: the base colour is white
    path, rgba = vertex_colours_glb(src, tmp_path / "coloured.glb")
    rig, info = read_asset(path)
    np.testing.assert_allclose(info.vertex_colors, rgba[:, :3] / 255.0, atol=1e-6)
    assert any("COLOR_0 vertex colours on 1 of 1 primitives" in n for n in info.notes)
    assert read_asset(src)[1].vertex_colors is None
    prepared = prepare_asset(path, tmp_path / "prepared")
    np.testing.assert_allclose(read_asset(prepared.path)[1].vertex_colors, info.vertex_colors, atol=1e-7)

    theta = np.zeros((rig.num_joints, 3))
    verts = rig.rest_vertices
    view = frame_camera(verts, identity_frame(verts.mean(0)), -70.0, 10.0, 4.0, 40.0, 64, 64, 0.1)
    job = RenderJob(sample_id="side", excess_rotations=theta, camera=view.camera, global_scale=1.0,
                    global_rotation=np.eye(3), global_translation=np.zeros(3), seed=1)
    config = RenderConfig(resolution=64, samples=4)
    front_z = np.median(verts[:, 2])
    for name, assets in (("own", SceneAssets(str(prepared.path), textures=())),
                         ("category", SceneAssets(str(prepared.path), textures=("toy:grey",)))):
        render_shard([job], assets, tmp_path / name, 0, config, rig=rig)
        table, arrays = read_shard(tmp_path / name, 0)
        assert table.column("status").to_pylist() == ["ok"]
        rgb, occ = arrays["rgb"][0].astype(float), arrays["occupancy"][0][..., 0]
        front = occ & (arrays["Q"][0][..., 0, 2] > front_z + 0.1)
        back = occ & (arrays["Q"][0][..., 0, 2] < front_z - 0.1)
        assert front.sum() > 100 and back.sum() > 100
        f, b = rgb[front].mean(0), rgb[back].mean(0)
        if name == "own":
            assert f[0] > f[2] + 40 and b[2] > b[0] + 40, (f, b)  # red front, blue back
        else:
            assert abs(f[0] - f[2]) < 30 and abs(b[0] - b[2]) < 30, (f, b)  # a grey coat, no tint
