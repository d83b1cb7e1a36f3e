import numpy as np
import pytest
import trimesh

from bat3r_core.toy import TOY_BODY_FRAME, TOY_COATS, build_toy_rig, toy_coat_texture


def test_toy_meets_its_specification(toy_rig):
    mesh = trimesh.Trimesh(toy_rig.rest_vertices, toy_rig.faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert 2000 <= toy_rig.num_vertices <= 6000
    length = np.ptp(toy_rig.rest_vertices[:, 2])
    assert 2.2 <= length <= 2.6  # about 2.4 m, +Z forward
    assert toy_rig.num_joints >= 25
    names = toy_rig.joint_names
    assert sum(n.startswith("spine") for n in names) >= 3
    assert sum(n.startswith("tail") for n in names) >= 3
    assert any(n.startswith("neck") for n in names) and "head" in names
    for leg in ("upper_arm", "thigh"):
        for side in ("L", "R"):  # every leg has a chain of at least 3 joints
            chain = toy_rig.descendants(toy_rig.joint_index(f"{leg}.{side}"))
            assert len(chain) >= 3
    assert len(toy_rig.left_right_pairs) == 8
    for left, right in toy_rig.left_right_pairs:  # .L joints on +X
        assert names[left].endswith(".L") and toy_rig.rest_joint_positions[left, 0] > 0
    for key in ("origin",):
        assert TOY_BODY_FRAME[key] in names
    # smooth weights: several influences where bones meet, every vertex sums to one
    assert (toy_rig.skin_weights > 0).sum(1).max() >= 3
    np.testing.assert_allclose(toy_rig.skin_weights.sum(1), 1.0, atol=1e-9)
    assert toy_rig.uvs is not None and toy_rig.uvs.min() >= 0 and toy_rig.uvs.max() <= 1


def test_toy_is_deterministic(toy_rig):
    build_toy_rig.__wrapped__ if hasattr(build_toy_rig, "__wrapped__") else None
    other = build_toy_rig()
    np.testing.assert_array_equal(other.rest_vertices, toy_rig.rest_vertices)
    np.testing.assert_array_equal(other.skin_weights, toy_rig.skin_weights)


def test_coat_textures():
    imgs = [toy_coat_texture(c, 64, seed=1) for c in TOY_COATS]
    assert all(i.shape == (64, 64, 3) and i.dtype == np.uint8 for i in imgs)
    means = np.array([i.reshape(-1, 3).mean(0) for i in imgs])
    assert np.linalg.norm(means[0] - means[2]) > 30  # bay and grey differ
    np.testing.assert_array_equal(toy_coat_texture("bay", 64, seed=1), imgs[0])
    with pytest.raises(ValueError, match="coat must be one of"):
        toy_coat_texture("zebra")
