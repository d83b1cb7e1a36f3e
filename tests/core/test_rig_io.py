import numpy as np
import pygltflib
import pytest

from bat3r_core.rig import Rig, RigError, find_left_right_pairs
from bat3r_core.rig_io import load_rig, read_asset, save_rig_glb
from bat3r_core.toy import toy_coat_texture


@pytest.fixture(scope="module")
def toy_glb(toy_rig, tmp_path_factory):
    path = tmp_path_factory.mktemp("glb") / "toy.glb"
    save_rig_glb(toy_rig, path, texture=toy_coat_texture("bay", 64))
    return path


def test_glb_round_trip_is_exact(toy_rig, toy_glb):
    back = load_rig(toy_glb)
    np.testing.assert_allclose(back.rest_vertices, toy_rig.rest_vertices, atol=1e-6)  # float32 storage
    np.testing.assert_array_equal(back.faces, toy_rig.faces)
    np.testing.assert_allclose(back.skin_weights, toy_rig.skin_weights, atol=1e-6)
    assert back.joint_names == toy_rig.joint_names
    np.testing.assert_array_equal(back.parents, toy_rig.parents)
    np.testing.assert_allclose(back.rest_transforms, toy_rig.rest_transforms, atol=1e-6)
    np.testing.assert_allclose(back.uvs, toy_rig.uvs, atol=1e-6)
    assert back.left_right_pairs == toy_rig.left_right_pairs


def _mutate(src, dst, fn):
    gltf = pygltflib.GLTF2().load(str(src))
    blob = bytearray(gltf.binary_blob())
    fn(gltf, blob)
    gltf.set_binary_blob(bytes(blob))
    gltf.save_binary(str(dst))
    return dst


def _accessor_view(gltf, blob, acc_index, dtype, ncomp):
    acc = gltf.accessors[acc_index]
    view = gltf.bufferViews[acc.bufferView]
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    return np.frombuffer(memoryview(blob)[start:start + acc.count * ncomp * np.dtype(dtype).itemsize],
                         dtype=dtype).reshape(acc.count, ncomp)


def _no_skin(gltf, blob):
    gltf.skins = []
    for n in gltf.nodes:
        n.skin = None


def _loose_weights(gltf, blob):
    attrs = gltf.meshes[0].primitives[0].attributes
    w = _accessor_view(gltf, blob, attrs.WEIGHTS_0, np.float32, 4)
    w[10] *= 0.5  # vertex 10's weights sum to 0.5 (an exporter that dropped influences without renormalising)
    w[11] *= 0.97
    w[12] = 0.0  # vertex 12 has none


def _nan_vertex(gltf, blob):
    attrs = gltf.meshes[0].primitives[0].attributes
    _accessor_view(gltf, blob, attrs.POSITION, np.float32, 3)[3, 1] = np.nan


def _lines(gltf, blob):
    gltf.meshes[0].primitives[0].mode = 1


def _cycle(gltf, blob):
    skin = gltf.skins[0]
    root = skin.joints[0]
    arm = [n for n in gltf.nodes if n.children and root in n.children and n.mesh is None
           and gltf.nodes.index(n) not in skin.joints][0]
    arm.children.remove(root)
    leaf = [j for j in skin.joints if not gltf.nodes[j].children][0]
    gltf.nodes[leaf].children = [root]


def _two_roots(gltf, blob):
    skin = gltf.skins[0]
    root = gltf.nodes[skin.joints[0]]
    moved = root.children.pop()  # detach one child subtree from the root joint
    arm = [n for n in gltf.nodes if n.children and skin.joints[0] in n.children][0]
    arm.children.append(moved)


@pytest.mark.parametrize("mutation, message", [
    (_no_skin, "has no skin"),
    (_nan_vertex, "NaN/inf vertex positions"),
    (_lines, "no usable mesh .*primitive 0 of mesh .* draws LINES, not a surface"),
    (_cycle, "cycle"),
    (_two_roots, "exactly one root, found 2"),
])
def test_malformed_assets_are_rejected_with_a_clear_message(toy_glb, tmp_path, mutation, message):
    bad = _mutate(toy_glb, tmp_path / "bad.glb", mutation)
    with pytest.raises(RigError, match=message) as err:
        load_rig(bad)
    assert "bad.glb" in str(err.value)


def test_weights_that_do_not_sum_to_one_are_normalised_and_reported(toy_rig, toy_glb, tmp_path):
    gltf = pygltflib.GLTF2().load(str(toy_glb))
    first_joint = gltf.nodes[gltf.skins[0].joints[0]].name
    rig, info = read_asset(_mutate(toy_glb, tmp_path / "loose.glb", _loose_weights))
    np.testing.assert_allclose(rig.rest_vertices, toy_rig.rest_vertices, atol=1e-6)  # the mesh as stored
    np.testing.assert_allclose(rig.skin_weights[[10, 11]], toy_rig.skin_weights[[10, 11]], atol=1e-6)
    assert rig.skin_weights[12, rig.joint_names.index(first_joint)] == 1.0 and rig.skin_weights[12].sum() == 1.0
    assert any("skin weights of 2 vertices summed to 0.5-0.97, not 1; normalised" in n for n in info.notes)
    assert any("1 vertices have no skin weight" in n for n in info.notes)


def test_line_primitives_beside_the_surface_are_left_out(toy_rig, toy_glb, tmp_path):
    def add_lines(gltf, blob):  # whiskers drawn as lines over the mesh's own vertices
        prim = gltf.meshes[0].primitives[0]
        gltf.meshes[0].primitives.append(pygltflib.Primitive(attributes=prim.attributes, mode=pygltflib.LINES))

    rig, info = read_asset(_mutate(toy_glb, tmp_path / "whiskers.glb", add_lines))
    np.testing.assert_allclose(rig.rest_vertices, toy_rig.rest_vertices, atol=1e-6)
    np.testing.assert_array_equal(rig.faces, toy_rig.faces)
    assert any("primitive 1 of mesh" in what and "draws LINES" in what for _, what in info.meshes)


def test_a_webp_texture_and_a_texture_transform_are_read(toy_rig, toy_glb, tmp_path):
    import cv2

    from bat3r_core.rig_io import _texture_transform
    from tests.assets.variants import _append

    own = read_asset(toy_glb)[1].texture
    offset, scale = np.array([0.25, -0.5]), np.array([2.0, 0.5])

    def webp_and_atlas(gltf, blob):
        ok, webp = cv2.imencode(".webp", own[..., ::-1], [cv2.IMWRITE_WEBP_QUALITY, 101])  # 101: lossless
        assert ok
        gltf.images.append(pygltflib.Image(bufferView=_append(gltf, blob, webp), mimeType="image/webp"))
        gltf.textures[0].source = None  # no PNG fallback: only the extension names the image
        gltf.textures[0].extensions = {"EXT_texture_webp": {"source": len(gltf.images) - 1}}
        gltf.extensionsUsed = ["EXT_texture_webp", "KHR_texture_transform"]
        gltf.extensionsRequired = ["EXT_texture_webp"]
        # the UVs stored for an atlas: the transform maps them back to the toy's own
        attrs = gltf.meshes[0].primitives[0].attributes
        uv = _accessor_view(gltf, blob, attrs.TEXCOORD_0, np.float32, 2)
        uv[:] = (uv - offset) / scale
        gltf.materials[0].pbrMetallicRoughness.baseColorTexture.extensions = {
            "KHR_texture_transform": {"offset": offset.tolist(), "scale": scale.tolist()}}

    rig, info = read_asset(_mutate(toy_glb, tmp_path / "webp.glb", webp_and_atlas))
    assert info.texture_source == "embedded image 1" and np.array_equal(info.texture, own)
    np.testing.assert_allclose(rig.uvs, toy_rig.uvs, atol=1e-6)
    assert any("KHR_texture_transform" in n for n in info.notes)
    # the extension's rotation turns UVs counter-clockwise: (1, 0) by 90 degrees is (0, 1)
    np.testing.assert_allclose(_texture_transform(np.array([[1.0, 0.0]]), {"rotation": np.pi / 2}), [[0.0, 1.0]],
                               atol=1e-12)


def test_a_gltf_with_several_buffer_files_reads_as_its_glb(toy_rig, toy_glb, tmp_path):
    gltf = pygltflib.GLTF2().load(str(toy_glb))
    blob = gltf.binary_blob()
    skin_view = gltf.bufferViews[gltf.accessors[gltf.skins[0].inverseBindMatrices].bufferView]
    start = skin_view.byteOffset or 0
    (tmp_path / "skin data.bin").write_bytes(blob[start:start + skin_view.byteLength])
    (tmp_path / "mesh.bin").write_bytes(blob)
    skin_view.buffer, skin_view.byteOffset = 1, 0  # the inverse bind matrices from a second file
    gltf.buffers = [pygltflib.Buffer(uri="mesh.bin", byteLength=len(blob)),
                    pygltflib.Buffer(uri="skin%20data.bin", byteLength=skin_view.byteLength)]
    gltf.set_binary_blob(b"")
    gltf.save_json(str(tmp_path / "toy.gltf"))
    back = load_rig(tmp_path / "toy.gltf")
    np.testing.assert_allclose(back.rest_vertices, toy_rig.rest_vertices, atol=1e-6)
    np.testing.assert_allclose(back.rest_transforms, toy_rig.rest_transforms, atol=1e-6)
    (tmp_path / "skin data.bin").unlink()
    with pytest.raises(RigError, match=r"toy\.gltf: its buffer file .*skin data\.bin does not exist"):
        load_rig(tmp_path / "toy.gltf")


def test_missing_and_unsupported_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.glb does not exist"):
        load_rig(tmp_path / "nope.glb")
    p = tmp_path / "mesh.obj"
    p.write_text("v 0 0 0\n")
    with pytest.raises(RigError, match="unsupported rig format '.obj'"):
        load_rig(p)
    g = tmp_path / "garbage.glb"
    g.write_bytes(b"not a gltf at all")
    with pytest.raises(RigError, match="not a readable glTF/GLB"):
        load_rig(g)


def test_rig_validation_messages():
    rest = np.tile(np.eye(4), (2, 1, 1))
    v = np.zeros((3, 3))
    f = np.array([[0, 1, 2]])
    w = np.array([[1, 0], [0, 1], [0.5, 0.5]])
    Rig("ok", v, f, ("a", "b"), np.array([-1, 0]), rest, w)
    with pytest.raises(RigError, match="faces must be triangles"):
        Rig("x", v, np.array([[0, 1, 2, 0]]), ("a", "b"), np.array([-1, 0]), rest, w)
    with pytest.raises(RigError, match="exactly one root"):
        Rig("x", v, f, ("a", "b"), np.array([-1, -1]), rest, w)
    with pytest.raises(RigError, match="cycle"):
        Rig("x", v, f, ("a", "b"), np.array([1, 0]), rest, w)
    with pytest.raises(RigError, match="NaN/inf"):
        Rig("x", np.full((3, 3), np.nan), f, ("a", "b"), np.array([-1, 0]), rest, w)
    # reordering joints given children-first
    r = Rig.from_unordered("x", v, f, ["b", "a"], np.array([1, -1]), rest[[1, 0]], w[:, [1, 0]])
    assert r.joint_names == ("a", "b") and list(r.parents) == [-1, 0]
    np.testing.assert_array_equal(r.skin_weights, w)


def test_left_right_pairs_by_name_and_by_mirroring():
    names = ["root", "arm.L", "arm.R", "left_ear", "right_ear", "hipA", "hipB"]
    pos = np.array([[0, 0, 0], [0.3, 1, 0], [-0.3, 1, 0], [0.1, 2, 0], [-0.1, 2, 0], [0.4, 0, 0], [-0.4, 0, 0.01]])
    pairs = find_left_right_pairs(names, pos)
    assert (1, 2) in pairs and (5, 6) in pairs  # by name and by mirroring
    assert len(pairs) == 3
