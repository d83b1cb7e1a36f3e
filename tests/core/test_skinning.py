import numpy as np
import pytest
import torch

from bat3r_core.skinning import (RigTensors, apply_similarity, axis_angle_to_matrix, forward_kinematics,
                                 matrix_to_axis_angle, skin)
from scipy.spatial.transform import Rotation


def _random_theta(rig, b, scale=0.4, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(b, rig.num_joints, 3, generator=g, dtype=torch.float64) * scale


def test_axis_angle_matches_scipy_and_round_trips():
    rng = np.random.default_rng(0)
    aa = rng.normal(size=(200, 3)) * 1.2
    aa[:3] = [[0, 0, 0], [1e-9, 0, 0], [0, np.pi - 1e-6, 0]]
    ours = axis_angle_to_matrix(torch.tensor(aa)).numpy()
    ref = Rotation.from_rotvec(aa).as_matrix()
    np.testing.assert_allclose(ours, ref, atol=1e-12)
    back = matrix_to_axis_angle(torch.tensor(ref)).numpy()
    np.testing.assert_allclose(Rotation.from_rotvec(back).as_matrix(), ref, atol=1e-9)


def test_zero_pose_reproduces_rest_mesh(toy_rig):
    rt = toy_rig.tensors(torch.float64)
    out = skin(rt, torch.zeros(2, toy_rig.num_joints, 3, dtype=torch.float64))
    np.testing.assert_allclose(out.vertices[0].numpy(), toy_rig.rest_vertices, atol=1e-12)
    np.testing.assert_allclose(out.joints[1].numpy(), toy_rig.rest_joint_positions, atol=1e-12)


def test_rotating_one_joint_moves_only_its_subtree(toy_rig):
    rt = toy_rig.tensors(torch.float64)
    j = toy_rig.joint_index("forearm.L")
    theta = torch.zeros(1, toy_rig.num_joints, 3, dtype=torch.float64)
    theta[0, j] = torch.tensor([0.7, 0.1, -0.2])
    rest = skin(rt, torch.zeros_like(theta)).vertices[0].numpy()
    posed = skin(rt, theta).vertices[0].numpy()
    subtree = toy_rig.descendants(j)
    influenced = toy_rig.skin_weights[:, subtree].sum(1) > 0
    moved = np.abs(posed - rest).max(1) > 0
    assert influenced.sum() > 50
    assert not moved[~influenced].any(), "vertices not weighted to the subtree must not move"
    assert np.array_equal(posed[~influenced], rest[~influenced])  # bit-identical
    assert moved[influenced].mean() > 0.95
    # joints outside the subtree stay exactly in place
    joints = skin(rt, theta).joints[0].numpy()
    rest_joints = skin(rt, torch.zeros_like(theta)).joints[0].numpy()
    outside = np.setdiff1d(np.arange(toy_rig.num_joints), subtree)
    np.testing.assert_array_equal(joints[outside], rest_joints[outside])
    assert np.abs(joints[subtree[1:]] - rest_joints[subtree[1:]]).max() > 0.05


def test_batched_equals_per_instance_loop(toy_rig):
    rt = toy_rig.tensors(torch.float64)
    b = 5
    theta = _random_theta(toy_rig, b)
    scales = 1 + 0.2 * torch.rand(b, toy_rig.num_joints, dtype=torch.float64)
    gs = 0.5 + torch.rand(b, dtype=torch.float64)
    gr = axis_angle_to_matrix(torch.randn(b, 3, dtype=torch.float64))
    gt = torch.randn(b, 3, dtype=torch.float64)
    batched = skin(rt, theta, scales, gs, gr, gt)
    for i in range(b):
        single = skin(rt, theta[i:i + 1], scales[i:i + 1], gs[i:i + 1], gr[i:i + 1], gt[i:i + 1])
        np.testing.assert_allclose(batched.vertices[i].numpy(), single.vertices[0].numpy(), atol=1e-12)
        np.testing.assert_allclose(batched.joints[i].numpy(), single.joints[0].numpy(), atol=1e-12)


def test_skinning_matches_a_slow_numpy_reference(toy_rig):
    """Per-vertex, per-joint loops with scipy rotations: obviously correct, slow."""
    theta = _random_theta(toy_rig, 1, seed=3)[0].numpy()
    scales = np.linspace(0.8, 1.2, toy_rig.num_joints)
    g_rest = toy_rig.rest_transforms
    glob = []
    for j in range(toy_rig.num_joints):
        p = toy_rig.parents[j]
        local = g_rest[j] if p < 0 else np.linalg.inv(g_rest[p]) @ g_rest[j]
        m = np.eye(4)
        m[:3, :3] = scales[j] * Rotation.from_rotvec(theta[j]).as_matrix()
        gj = (np.eye(4) if p < 0 else glob[p]) @ local @ m
        glob.append(gj)
    idx = np.arange(0, toy_rig.num_vertices, 37)
    ref = np.zeros((len(idx), 3))
    for k, v in enumerate(idx):
        x = np.append(toy_rig.rest_vertices[v], 1.0)
        for j in np.flatnonzero(toy_rig.skin_weights[v]):
            ref[k] += toy_rig.skin_weights[v, j] * (glob[j] @ np.linalg.inv(g_rest[j]) @ x)[:3]
    out = skin(toy_rig.tensors(torch.float64), torch.tensor(theta)[None], torch.tensor(scales)[None])
    np.testing.assert_allclose(out.vertices[0].numpy()[idx], ref, atol=1e-10)


def test_gradcheck_float64():
    # a small chain rig keeps gradcheck fast
    from bat3r_core.rig import Rig

    rest = np.tile(np.eye(4), (3, 1, 1))
    rest[:, :3, 3] = [[0, 0, 0], [0, 0.5, 0], [0, 1.0, 0.1]]
    verts = np.array([[0.1, 0.2, 0], [0, 0.6, 0.1], [0.05, 1.1, 0], [-0.1, 0.8, 0.05]])
    w = np.array([[1, 0, 0], [0.3, 0.7, 0], [0, 0.2, 0.8], [0, 0.5, 0.5]], dtype=float)
    rig = Rig("chain", verts, np.array([[0, 1, 2], [1, 3, 2]]), ("a", "b", "c"), np.array([-1, 0, 1]), rest, w)
    rt = rig.tensors(torch.float64)
    theta = (torch.randn(2, 3, 3, dtype=torch.float64) * 0.5).requires_grad_()
    theta.data[0, 1] = 0.0  # includes the exact rest-pose branch
    s = (1 + 0.1 * torch.rand(2, 3, dtype=torch.float64)).requires_grad_()
    gs = torch.tensor([1.2, 0.8], dtype=torch.float64, requires_grad=True)
    gr_aa = torch.randn(2, 3, dtype=torch.float64, requires_grad=True)
    gt = torch.randn(2, 3, dtype=torch.float64, requires_grad=True)

    def f(theta, s, gs, gr_aa, gt):
        out = skin(rt, theta, s, gs, axis_angle_to_matrix(gr_aa), gt)
        return out.vertices, out.joints

    assert torch.autograd.gradcheck(f, (theta, s, gs, gr_aa, gt), eps=1e-6, atol=1e-6)


def test_float32_close_to_float64(toy_rig):
    theta = _random_theta(toy_rig, 3, seed=1)
    v64 = skin(toy_rig.tensors(torch.float64), theta).vertices
    v32 = skin(toy_rig.tensors(torch.float32), theta.float()).vertices
    assert v32.dtype == torch.float32
    assert (v64 - v32.double()).abs().max() < 1e-5


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu(toy_rig):
    theta = _random_theta(toy_rig, 4, seed=2)
    cpu = skin(toy_rig.tensors(torch.float64), theta).vertices
    gpu = skin(toy_rig.tensors(torch.float64, "cuda"), theta.cuda()).vertices
    assert (cpu - gpu.cpu()).abs().max() < 1e-10


def test_bad_shapes_are_rejected(toy_rig):
    rt = toy_rig.tensors()
    with pytest.raises(ValueError, match=r"excess_rotations must have shape \(B, 27, 3\)"):
        skin(rt, torch.zeros(2, 5, 3))
    with pytest.raises(ValueError, match=r"bone_scales must have shape \(2, 27\)"):
        forward_kinematics(rt, torch.zeros(2, 27, 3), torch.ones(2, 3))
    with pytest.raises(ValueError, match="global_rotation must have shape"):
        skin(rt, torch.zeros(2, 27, 3), global_rotation=torch.eye(3))


def test_apply_similarity():
    pts = torch.tensor([[[1.0, 0.0, 0.0]]])
    r = axis_angle_to_matrix(torch.tensor([[0.0, 0.0, np.pi / 2]]))
    out = apply_similarity(pts, torch.tensor([2.0]), r, torch.tensor([[0.0, 0.0, 1.0]]))
    np.testing.assert_allclose(out[0, 0].numpy(), [0.0, 2.0, 1.0], atol=1e-6)
