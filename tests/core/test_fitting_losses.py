"""Fitting losses: each regulariser is zero at rest and grows under the deformation it guards against; fast
batched forms agree with slow loops."""
from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from bat3r_core.skinning import skin
from bat3r_core.toy import build_toy_rig
from bat3r_core.fitting.geodesics import DenseGeodesics, geodesic_distances, landmark_geodesics
from bat3r_core.fitting.losses import (MeshRegularisers, angle_term, data_term, find_repulsion_pairs, huber,
                                       regulariser_mesh, repulsion_term, scale_term)

pytestmark = pytest.mark.usefixtures("torch_single_thread")  # steadier on 2 shared cores


@pytest.fixture(scope="module")
def coarse():
    rig = build_toy_rig(voxel=0.07)
    reg = MeshRegularisers.from_mesh(rig.rest_vertices, rig.faces, rig.skin_weights, dtype=torch.float64)
    return rig, reg


def _posed(rig, joint_rotations: dict) -> torch.Tensor:
    theta = np.zeros((1, rig.num_joints, 3))
    for name, rot in joint_rotations.items():
        theta[0, rig.joint_index(name)] = rot
    return skin(rig.tensors(dtype=torch.float64), torch.as_tensor(theta)).vertices


def test_edge_term_zero_at_rest_grows_with_stretch_and_matches_a_loop(coarse):
    rig, reg = coarse
    rest = torch.as_tensor(rig.rest_vertices.copy())[None]
    assert reg.edge(rest).item() == pytest.approx(0.0, abs=1e-18)
    values = [reg.edge(rest * (1 + eps)).item() for eps in (0.02, 0.05, 0.1)]
    assert 0 < values[0] < values[1] < values[2]
    # slow reference over trimesh's unique edges
    rng = np.random.default_rng(1)
    moved = rig.rest_vertices + rng.normal(0, 0.01, rig.rest_vertices.shape)
    edges = trimesh.Trimesh(rig.rest_vertices, rig.faces, process=False).edges_unique
    ref = np.mean([(np.sum((moved[a] - moved[b]) ** 2) - np.sum((rig.rest_vertices[a] - rig.rest_vertices[b]) ** 2))
                   ** 2 for a, b in edges])
    assert reg.edge(torch.as_tensor(moved)[None]).item() == pytest.approx(ref, rel=1e-9)


def test_volume_term_zero_at_rest_grows_with_volume_loss_and_matches_a_loop(coarse):
    rig, reg = coarse
    rest = torch.as_tensor(rig.rest_vertices.copy())[None]
    assert reg.volume(rest).item() == pytest.approx(0.0, abs=1e-18)
    # rigid motion keeps every local volume
    rot = torch.as_tensor(trimesh.transformations.rotation_matrix(0.7, [1, 2, 3])[:3, :3])
    assert reg.volume(rest @ rot.T + 0.3).item() == pytest.approx(0.0, abs=1e-12)
    # shrink the thigh region towards its centroid: volume loss
    dom = rig.skin_weights.argmax(1)
    region = dom == rig.joint_index("thigh.L")
    c = rig.rest_vertices[region].mean(0)
    values = []
    for factor in (0.9, 0.7, 0.5):
        v = rig.rest_vertices.copy()
        v[region] = c + factor * (v[region] - c)
        values.append(reg.volume(torch.as_tensor(v)[None]).item())
    assert 0 < values[0] < values[1] < values[2]
    # slow reference: per face, the dominant bone of its corners' summed weights; tetrahedra to the bone centroid
    rng = np.random.default_rng(2)
    moved = rig.rest_vertices + rng.normal(0, 0.01, rig.rest_vertices.shape)

    def volumes(x):
        out = {}
        bone = [int(np.argmax(rig.skin_weights[list(f)].sum(0))) for f in rig.faces]
        for b in set(bone):
            fs = [f for f, bb in zip(rig.faces, bone) if bb == b]
            cen = np.mean([x[i] for f in fs for i in f], axis=0)
            out[b] = sum(np.dot(x[f[0]] - cen, np.cross(x[f[1]] - cen, x[f[2]] - cen)) / 6 for f in fs)
        return out

    v0, v1 = volumes(rig.rest_vertices), volumes(moved)
    ref_scale = np.maximum(np.abs(list(v0.values())), 0.1 * np.mean(np.abs(list(v0.values()))))
    ref = np.mean(((np.array(list(v1.values())) - np.array(list(v0.values()))) / ref_scale) ** 2)
    assert reg.volume(torch.as_tensor(moved)[None]).item() == pytest.approx(ref, rel=1e-8)


def test_repulsion_zero_at_rest_and_grows_when_a_limb_goes_through_the_body(coarse):
    rig, _ = coarse
    geo = DenseGeodesics(geodesic_distances(rig.rest_vertices, rig.faces))
    threshold = 0.5 * np.ptp(rig.rest_vertices, axis=0).max() / 2.7

    def repulsion(verts: torch.Tensor) -> float:
        pairs = find_repulsion_pairs(verts[0].numpy(), geo, threshold, 0.1, 100)
        t = torch.as_tensor(pairs)
        return repulsion_term(verts, torch.zeros(len(pairs), dtype=torch.long), t, 0.05, 1).item()

    assert repulsion(torch.as_tensor(rig.rest_vertices.copy())[None]) == 0.0
    # swing the left hind leg sideways under the belly into the right hind leg: the penalty grows from first
    # contact (0.32 rad) until the legs' surfaces cross (0.38 rad); deeper crossings leave fewer surface pairs
    # within r, a limitation of surface-pair repulsion that the paper's formulation shares
    values = [repulsion(_posed(rig, {"thigh.L": [0.0, 0.0, -a]})) for a in (0.30, 0.32, 0.34, 0.36, 0.38)]
    assert values[0] == 0.0 and 0 < values[1] < values[2] < values[3] < values[4]
    # and bend the neck down into the chest
    assert repulsion(_posed(rig, {"neck.1": [2.2, 0, 0], "neck.2": [0.8, 0, 0]})) > 0


def test_find_repulsion_pairs_matches_brute_force():
    rng = np.random.default_rng(4)
    v = rng.uniform(0, 0.6, (150, 3))
    geo = rng.uniform(0, 1, (150, 150))
    geo = (geo + geo.T) / 2
    got = find_repulsion_pairs(v, DenseGeodesics(geo), 0.5, 0.1, k=1000)
    d = np.linalg.norm(v[:, None] - v[None], axis=-1)
    ref = {(i, j) for i in range(150) for j in range(i + 1, 150) if d[i, j] < 0.1 and geo[i, j] > 0.5}
    assert {tuple(p) for p in got.tolist()} == ref and len(ref) > 10
    capped = find_repulsion_pairs(v, DenseGeodesics(geo), 0.5, 0.1, k=1)
    assert 0 < len(capped) < len(ref)
    ends = np.concatenate([capped[:, 0], capped[:, 1]])
    assert len(capped) <= len(np.unique(ends))
    with pytest.raises(TypeError, match="geodesics must be a geodesic object with pair_distances"):
        find_repulsion_pairs(v, geo, 0.5, 0.1, k=10)
    with pytest.raises(ValueError, match="geodesics cover 150 vertices, vertices has 20"):
        find_repulsion_pairs(v[:20], DenseGeodesics(geo), 0.5, 0.1, k=10)


def test_find_repulsion_pairs_under_landmark_geodesics_matches_brute_force(coarse):
    rig, _ = coarse
    geo = landmark_geodesics(rig.rest_vertices, rig.faces, 64)
    posed = _posed(rig, {"thigh.L": [0.0, 0.0, -0.36], "neck.1": [2.2, 0, 0], "neck.2": [0.8, 0, 0]})[0].numpy()
    got = find_repulsion_pairs(posed, geo, 0.4, 0.1, k=1000)
    n = len(posed)
    d = np.linalg.norm(posed[:, None] - posed[None], axis=-1)
    ref = set()
    for i in range(n):
        for j in np.flatnonzero(d[i, i + 1:] < 0.1) + i + 1:
            # the landmark estimate, written out: through the landmark nearest to either end
            via_i = geo.offset[i] + geo.rows[geo.nearest[i], j]
            via_j = geo.offset[j] + geo.rows[geo.nearest[j], i]
            if min(float(via_i), float(via_j)) > 0.4:
                ref.add((i, int(j)))
    assert {tuple(p) for p in got.tolist()} == ref and len(ref) > 10


def test_angle_scale_data_terms():
    theta = torch.zeros(2, 5, 3)
    assert torch.all(angle_term(theta) == 0)
    theta[1, 2] = torch.tensor([0.3, 0.0, 0.4])
    assert angle_term(theta)[1].item() == pytest.approx(0.25 / 5)
    mask = torch.tensor([1.0, 1, 0, 1, 1])
    assert angle_term(theta, mask)[1].item() == 0.0
    pairs = torch.tensor([[0, 1], [2, 3]])
    ones = torch.ones(1, 5)
    assert scale_term(ones, pairs).item() == 0.0
    sym = torch.tensor([[1.2, 1.2, 1.0, 1.0, 1.0]])
    asym = torch.tensor([[1.2, 1.0, 1.0, 1.0, 1.0]])
    log12 = np.log(1.2)
    assert scale_term(sym, pairs).item() == pytest.approx(2 * log12 ** 2 / 5)
    assert scale_term(asym, pairs).item() == pytest.approx(log12 ** 2 / 2 + log12 ** 2 / 5)
    rng = torch.Generator().manual_seed(0)
    a, b = torch.randn(2, 50, 3, generator=rng) * 0.1, torch.randn(2, 50, 3, generator=rng) * 0.1
    m = torch.ones(2, 50)
    m[1, 25:] = 0
    d = (a - b).norm(dim=-1)
    ref = torch.nn.functional.huber_loss(d, torch.zeros_like(d), reduction="none", delta=0.1)
    got = data_term(a, b, m, 0.1)
    assert torch.allclose(got, (ref * m).sum(-1), atol=1e-6)
    assert data_term(a, a, m, 0.1).abs().max().item() < 1e-8
    assert torch.allclose(huber(torch.tensor([0.05, 0.3]), 0.1), torch.tensor([0.00125, 0.025]))


def test_regulariser_mesh_proxy():
    rig = build_toy_rig()
    full = regulariser_mesh(rig.rest_vertices, rig.faces, rig.skin_weights, 0)
    assert not full.is_proxy and len(full.rest_vertices) == rig.num_vertices
    proxy = regulariser_mesh(rig.rest_vertices, rig.faces, rig.skin_weights, 1500)
    assert proxy.is_proxy and 1300 <= len(proxy.rest_vertices) <= 1600
    m = trimesh.Trimesh(proxy.rest_vertices, proxy.faces, process=False)
    full_volume = trimesh.Trimesh(rig.rest_vertices, rig.faces, process=False).volume
    assert m.is_watertight and m.volume == pytest.approx(full_volume, rel=0.02)
    d = np.linalg.norm(proxy.rest_vertices - rig.rest_vertices[proxy.source_vertex], axis=1)
    assert d.max() < 0.05
    np.testing.assert_allclose(proxy.skin_weights.sum(1), 1.0)
