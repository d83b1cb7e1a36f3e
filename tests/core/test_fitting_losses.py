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
                                       regulariser_mesh, repulsion_term, scale_term, wrap_axis_angle)

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
    ref = np.mean((np.array(list(v1.values())) - np.array(list(v0.values()))) ** 2)  # absolute change, m^6
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
    assert torch.allclose(got, (ref * m).sum(-1) / m.sum(-1), atol=1e-7)  # the mean over valid points
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


# ------------------------------------------------------------------------------------------ weighting
def test_data_term_is_the_mean_over_valid_control_points():
    # hand-computed: distances 0.05 (Huber 0.5 * 0.05^2 = 0.00125) and 0.3 (0.1 * (0.3 - 0.05) = 0.025), padding
    posed = torch.zeros(2, 3, 3, dtype=torch.float64)
    targets = torch.tensor([[[0.05, 0, 0], [0, 0.3, 0], [9.0, 9, 9]], [[0, 0, 0.3], [0, 0, 0], [0, 0, 0]]],
                           dtype=torch.float64)
    mask = torch.tensor([[1.0, 1, 0], [1, 1, 1]])
    got = data_term(posed, targets, mask, 0.1)
    np.testing.assert_allclose(got.numpy(), [(0.00125 + 0.025) / 2, 0.025 / 3], rtol=1e-9)
    assert data_term(posed, targets, torch.zeros(2, 3), 0.1).abs().max().item() == 0.0  # no valid point: 0


def test_volume_term_is_the_mean_squared_absolute_change_in_cubic_metres():
    # a unit-ish tetrahedron per bone: faces of bone 0 (corners 0-3) and of bone 1 (corners 4-7, scaled x2)
    tet = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]) * 0.1
    v = np.concatenate([tet, 2 * tet + 1.0])
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    faces = np.concatenate([f, f + 4])
    w = np.zeros((8, 2))
    w[:4, 0] = w[4:, 1] = 1.0
    reg = MeshRegularisers.from_mesh(v, faces, w, dtype=torch.float64)
    rest = reg.rest_volumes.numpy()
    np.testing.assert_allclose(np.sort(np.abs(rest)), [1e-3 / 6, 8e-3 / 6], rtol=1e-9)  # 0.1^3/6, 0.2^3/6 m^3
    moved = v.copy()
    moved[:4] = tet.mean(0) + 1.5 * (tet - tet.mean(0))  # bone 0 grows 1.5^3 x; bone 1 untouched
    dv = (1.5 ** 3 - 1) * 1e-3 / 6
    assert reg.volume(torch.as_tensor(moved)[None]).item() == pytest.approx(dv ** 2 / 2, rel=1e-9)
    assert reg.num_bones == 2 and reg.edge_weights is None and reg.repulsion_scale == 1.0
    # as a proxy of a "full mesh" with three bones, the sum is divided by 3
    w3 = np.zeros((8, 3))
    w3[:, :2] = w
    full_w = np.eye(3)[[0] * 4 + [1] * 2 + [2] * 2]  # faces 4-7 split between bones 1 and 2
    proxy = MeshRegularisers.from_mesh(v, faces, w3, dtype=torch.float64, full_mesh=(v, faces, full_w))
    assert proxy.num_bones == 3
    assert proxy.volume(torch.as_tensor(moved)[None]).item() == pytest.approx(dv ** 2 / 3, rel=1e-9)


def test_proxy_edge_term_is_the_area_weighted_relative_change_in_full_mesh_units():
    rig = build_toy_rig()
    proxy = regulariser_mesh(rig.rest_vertices, rig.faces, rig.skin_weights, 1500)
    reg = MeshRegularisers.from_mesh(proxy.rest_vertices, proxy.faces, proxy.skin_weights, dtype=torch.float64,
                                     full_mesh=(rig.rest_vertices, rig.faces, rig.skin_weights))
    full = MeshRegularisers.from_mesh(rig.rest_vertices, rig.faces, rig.skin_weights, dtype=torch.float64)
    full_m4 = np.mean(trimesh.Trimesh(rig.rest_vertices, rig.faces, process=False).edges_unique_length ** 4)
    pm = trimesh.Trimesh(proxy.rest_vertices, proxy.faces, process=False)
    # hand-made weights: a third of each bordering face's area, over the total area, per proxy edge
    share = {tuple(e): 0.0 for e in pm.edges_unique}
    for f, a in zip(proxy.faces, pm.area_faces):
        for u, w in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0])):
            share[(min(u, w), max(u, w))] += a / 3
    assert sum(share.values()) == pytest.approx(pm.area)
    rng = np.random.default_rng(5)
    moved = proxy.rest_vertices + rng.normal(0, 0.005, proxy.rest_vertices.shape)
    ref = full_m4 * sum(a / pm.area * ((np.sum((moved[i] - moved[j]) ** 2) - np.sum((proxy.rest_vertices[i]
                                                                                    - proxy.rest_vertices[j]) ** 2))
                                        / np.sum((proxy.rest_vertices[i] - proxy.rest_vertices[j]) ** 2)) ** 2
                        for (i, j), a in share.items())
    assert reg.edge(torch.as_tensor(moved)[None]).item() == pytest.approx(ref, rel=1e-9)
    # a uniform 5 % stretch: both meshes give (1.05² − 1)² mean|e_rest|⁴ of the full mesh
    expect = (1.05 ** 2 - 1) ** 2 * full_m4
    assert reg.edge(torch.as_tensor(proxy.rest_vertices * 1.05)[None]).item() == pytest.approx(expect, rel=1e-9)
    assert full.edge(torch.as_tensor(rig.rest_vertices * 1.05)[None]).item() == pytest.approx(expect, rel=1e-9)
    assert reg.repulsion_scale == pytest.approx((rig.num_vertices / len(proxy.rest_vertices)) ** 2)
    assert reg.num_bones == full.num_bones == 27


def test_wrap_axis_angle_keeps_the_rotation_and_bounds_the_angle():
    from bat3r_core.skinning import axis_angle_to_matrix

    axis = torch.tensor([0.36, 0.48, 0.8], dtype=torch.float64)
    theta = torch.stack([a * axis for a in (0.3, 3.0, 3.5, 6.0, 7.0, 10.0)])
    wrapped = wrap_axis_angle(theta)
    assert torch.all(wrapped.norm(dim=-1) <= np.pi + 1e-12)
    torch.testing.assert_close(wrapped[:2], theta[:2])  # within pi: unchanged
    torch.testing.assert_close(wrapped[2], (3.5 - 2 * np.pi) * axis)
    torch.testing.assert_close(axis_angle_to_matrix(wrapped), axis_angle_to_matrix(theta))


def _reference_regularisers(rig, theta, control_vertex, targets, scale, rotation, translation, geodesics,
                            threshold, radius=0.05, k=100, delta=0.1):
    """The objective as the reference computes it, written out slowly on the full (welded) mesh: mean Huber data
    term over the control points, mean squared edge term over the full mesh's edges, mean over bones of the
    squared absolute volume change (m^3), repulsion over each vertex's k nearest neighbours that are geodesically
    far, mean squared axis angle."""
    from scipy.spatial import cKDTree

    verts = skin(rig.tensors(dtype=torch.float64), theta).vertices[0]  # (V, 3) unscaled articulated
    rest = torch.as_tensor(rig.rest_vertices.copy())
    # data
    posed = scale * verts[control_vertex] @ rotation.T + translation
    d = torch.sqrt(((posed - targets) ** 2).sum(-1) + 1e-18)
    data = torch.where(d <= delta, 0.5 * d ** 2, delta * (d - 0.5 * delta)).mean()
    # edge
    edges = torch.as_tensor(np.array(trimesh.Trimesh(rig.rest_vertices, rig.faces, process=False).edges_unique))
    cur = ((verts[edges[:, 0]] - verts[edges[:, 1]]) ** 2).sum(-1)
    ref = ((rest[edges[:, 0]] - rest[edges[:, 1]]) ** 2).sum(-1)
    edge = ((cur - ref) ** 2).mean()
    # volume
    bone = rig.skin_weights[rig.faces].sum(1).argmax(1)
    changes = []
    for b in np.unique(bone):
        fs = torch.as_tensor(rig.faces[bone == b])

        def vol(x):
            c = x[fs.reshape(-1)].mean(0)
            a, bb, cc = x[fs[:, 0]] - c, x[fs[:, 1]] - c, x[fs[:, 2]] - c
            return (a * torch.cross(bb, cc, dim=-1)).sum() / 6.0

        changes.append((vol(verts) - vol(rest)) ** 2)
    volume = torch.stack(changes).mean()
    # repulsion
    x = verts.detach().numpy()
    _, nn = cKDTree(x).query(x, k=k + 1)
    cand = {(min(i, int(j)), max(i, int(j))) for i in range(len(x)) for j in nn[i, 1:]}
    cand = np.array(sorted(cand))
    cand = cand[geodesics.pair_distances(cand[:, 0], cand[:, 1]) > threshold]
    dd = ((verts[cand[:, 0]] - verts[cand[:, 1]]) ** 2).sum(-1)
    repulsion = (torch.relu(radius ** 2 - dd) ** 2).sum()
    angle = (theta[0] ** 2).sum(-1).mean()
    return {"data": data, "edge": edge, "volume": volume, "repulsion": repulsion, "angle": angle}


@pytest.fixture(scope="module")
def gradient_case(tmp_path_factory):
    """A noisy (1 cm) ray-cast cloud of the toy in a pose with self-contact: 200 FPS control points (their
    vertices and posed targets), the initial similarity, and a current estimate near the truth."""
    from bat3r_core.fitting.geodesics import load_or_compute_landmark_geodesics
    from bat3r_core.fitting.correspondences import VertexIndex
    from bat3r_core.fitting.sampling import farthest_point_sampling
    from bat3r_core.metrics import umeyama
    from bat3r_core.pointmaps import dual_point_cloud, dual_point_maps
    from bat3r_core.toy import TOY_BODY_FRAME
    from bat3r_core.viewpoints import CameraPriorConfig, body_frame, sample_viewpoints

    rig = build_toy_rig()
    cache = tmp_path_factory.mktemp("geodesics")
    # the true pose: legs and neck bent, the left hind leg swung under the belly into the right one (contact)
    truth = {"thigh.L": [0.0, 0.0, -0.36], "neck.1": [0.9, 0.0, 0.2], "shin.R": [0.6, 0.0, 0.0],
             "upper_arm.L": [-0.5, 0.1, 0.0]}
    theta_true = np.zeros((1, rig.num_joints, 3))
    for name, r in truth.items():
        theta_true[0, rig.joint_index(name)] = r
    out = skin(rig.tensors(dtype=torch.float64), torch.as_tensor(theta_true))
    idx = {n: i for i, n in enumerate(rig.joint_names)}
    frame = body_frame(out.joints[0].numpy(), idx[TOY_BODY_FRAME["origin"]],
                       tuple(idx[n] for n in TOY_BODY_FRAME["forward"]),
                       tuple(idx[n] for n in TOY_BODY_FRAME["horizontal"]))
    rng = np.random.default_rng(77_301)
    cam = sample_viewpoints(out.vertices[0].numpy(), frame, 1, CameraPriorConfig(), 96, 96, rng)[0].camera
    maps = dual_point_maps(out.vertices[0].numpy(), rig.rest_vertices, rig.faces, cam, num_layers=4)
    pc = dual_point_cloud(maps.P, maps.Q, maps.occupancy)
    P = pc.posed_points.astype(np.float64) + rng.normal(0, 0.01, pc.posed_points.shape)
    Q = pc.canonical_points.astype(np.float64) + rng.normal(0, 0.01, pc.canonical_points.shape)
    corr = VertexIndex(rig.rest_vertices).match(Q, None, 0.1, 2.0)
    inl = np.flatnonzero(corr.inlier)
    geo = load_or_compute_landmark_geodesics(rig.rest_vertices, rig.faces, cache)
    pick = inl[farthest_point_sampling(corr.distance[inl], corr.vertex[inl], geo, 200, rng)]
    sim = umeyama(rig.rest_vertices[corr.vertex[pick]], P[pick], with_scale=True)
    theta0 = theta_true + np.random.default_rng(77_302).normal(0, 0.08, theta_true.shape)
    return dict(rig=rig, cache=cache, vertex=corr.vertex[pick], targets=torch.as_tensor(P[pick]),
                similarity=(float(sim.scale), torch.as_tensor(sim.rotation), torch.as_tensor(sim.translation)),
                theta=theta0)


def _gradient_norms(terms: dict, theta: torch.Tensor) -> dict:
    return {k: torch.autograd.grad(v.sum(), theta, retain_graph=True)[0].norm().item() for k, v in terms.items()}


def _bat3r_terms(asset, config, case, theta):
    """The terms as fitting optimises them (fit._optimise): regulariser mesh for edge, volume and repulsion."""
    s, R, t = case["similarity"]
    reg = asset.regularisers
    verts = skin(asset.reg_tensors, theta).vertices  # (1, Vr, 3) unscaled articulated regulariser mesh
    ctrl = skin(asset.fitting_tensors, theta).vertices[:, case["vertex"]]
    pairs = find_repulsion_pairs(verts[0].detach().numpy(), asset.reg_geodesics, asset.geodesic_threshold,
                                 2 * config.repulsion_radius, config.repulsion_k)
    return {"data": data_term(s * ctrl @ R.T + t, case["targets"][None], torch.ones(1, len(case["vertex"])),
                              config.huber_delta),
            "edge": reg.edge(verts), "volume": reg.volume(verts),
            "repulsion": reg.repulsion(verts, torch.zeros(len(pairs), dtype=torch.long), torch.as_tensor(pairs),
                                       config.repulsion_radius, 1),
            "angle": angle_term(theta)}


# Measured (bat3r's |grad reg_k| / |grad data| over the reference's), regulariser mesh full / proxy:
#   edge 1.0000 / 0.86, volume 1.0000 / 0.54, repulsion 1.0000 / 0.74, angle 1 / 1. On the full welded mesh the
#   objective is the reference's; no fixed normalisation makes the decimated proxy's edge and volume terms the
#   full mesh's (their proxy/full ratio varies 0.7-1.3x (edge) and 0.6-1.8x (volume) from pose to pose: the proxy
#   does not resolve the skinning blend zones), so the proxy is held to a factor 1.5 (volume: 2; the summed data
#   term that this replaces was 200x off).
TOLERANCE = {0: {"edge": 0.01, "volume": 0.01, "repulsion": 0.01, "angle": 1e-9},
             1500: {"edge": np.log(1.5), "volume": np.log(2.0), "repulsion": np.log(1.5), "angle": 1e-9}}


@pytest.mark.parametrize("max_vertices", [0, 1500])
def test_gradient_ratios_match_the_full_mesh_reference(gradient_case, max_vertices):
    """|dL_k/dθ| / |dL_data/dθ| of bat3r's objective against the slow full-mesh reference, on the full welded mesh
    (``regulariser_max_vertices: 0``) and on the default proxy."""
    from bat3r_core.catalog import fitting_preset as preset
    from bat3r_core.fitting import FittingAsset

    case = gradient_case
    config = preset("synthetic", {"regulariser_max_vertices": max_vertices})
    asset = FittingAsset.prepare(case["rig"], config, cache_dir=case["cache"], dtype=torch.float64)
    assert asset.reg_mesh.is_proxy == (max_vertices > 0) and asset.densify_levels == 0
    theta = torch.tensor(case["theta"], requires_grad=True)
    ours = _bat3r_terms(asset, config, case, theta)
    g_ours = _gradient_norms(ours, theta)
    theta_r = torch.tensor(case["theta"], requires_grad=True)
    s, R, t = case["similarity"]
    ref = _reference_regularisers(asset.welded_rig, theta_r, torch.as_tensor(case["vertex"]), case["targets"], s, R,
                                  t, asset.geodesics, asset.geodesic_threshold)
    g_ref = _gradient_norms(ref, theta_r)
    assert all(g_ref[k] > 0 for k in g_ref)
    ratios = {k: (g_ours[k] / g_ours["data"]) / (g_ref[k] / g_ref["data"]) for k in TOLERANCE[max_vertices]}
    print(max_vertices, {k: round(v, 4) for k, v in ratios.items()},
          {k: (g_ours[k] / g_ours["data"], g_ref[k] / g_ref["data"]) for k in ratios})
    if max_vertices == 0:
        assert ours["data"].item() == pytest.approx(ref["data"].item(), rel=1e-9)
    for k, r in ratios.items():
        assert abs(np.log(r)) <= TOLERANCE[max_vertices][k], ratios
