"""Dual point maps by ray casting: checked against a brute-force float64 ray/triangle reference on the toy."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from bat3r_core.cameras import PinholeCamera
from bat3r_core.pointmaps import (FLOAT16_MAX_ABS_M, decode_float16, dual_point_cloud, dual_point_maps,
                                  dual_point_maps_batch, dual_point_maps_parallel, encode_float16)
from bat3r_core.toy import TOY_BODY_FRAME, TOY_JOINTS, build_toy_rig
from bat3r_core.viewpoints import SphericalCoords, body_frame, camera_from_spherical, frame_camera


@pytest.fixture(scope="module")
def toy():
    rig = build_toy_rig(voxel=0.08)  # ~1.3K vertices: small enough for the brute-force reference
    canon = rig.rest_vertices
    # a non-rigid "pose": bend the body along z, then a similarity into some world frame
    bent = canon.copy()
    bent[:, 1] += 0.15 * np.sin(1.3 * canon[:, 2])
    bent[:, 0] += 0.10 * canon[:, 2] ** 2
    Rg = Rotation.from_euler("xyz", [5, 30, -10], degrees=True).as_matrix()
    posed = 1.05 * bent @ Rg.T + [0.3, -0.2, 0.5]
    joints = 1.05 * rig.rest_joint_positions @ Rg.T + [0.3, -0.2, 0.5]
    i = TOY_JOINTS.index
    frame = body_frame(joints, i(TOY_BODY_FRAME["origin"]), tuple(map(i, TOY_BODY_FRAME["forward"])),
                       tuple(map(i, TOY_BODY_FRAME["horizontal"])))
    return canon, posed, rig.faces, frame


def _camera(frame, posed, azimuth, elevation=10.0, roll=5.0, size=(40, 32), margin=0.1):
    return frame_camera(posed, frame, azimuth, elevation, roll, 40.0, size[0], size[1], margin).camera


def _reference_hits(posed_cam, faces, camera):
    """Brute force: every ray through a pixel centre against every triangle (Moller-Trumbore, float64)."""
    d = camera.pixel_ray_directions().reshape(-1, 3)
    tri = posed_cam[faces]  # (F, 3 corners, 3)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    hits = []
    for r in range(d.shape[0]):
        p = np.cross(d[r], e2)
        det = np.einsum("fx,fx->f", e1, p)
        ok = np.abs(det) > 1e-15
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = -tri[:, 0]
        u = np.einsum("fx,fx->f", s, p) * inv
        q = np.cross(s, e1)
        v = (q @ d[r]) * inv
        t = np.einsum("fx,fx->f", e2, q) * inv
        sel = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        order = np.argsort(t[sel])
        hits.append([(t[sel][k], np.flatnonzero(sel)[k], u[sel][k], v[sel][k]) for k in order])
    return hits


def test_maps_match_a_brute_force_reference(toy):
    canon, posed, faces, frame = toy
    cam = _camera(frame, posed, azimuth=75.0)  # lateral: legs give 4+ layers
    m = dual_point_maps(posed, canon, faces, cam, num_layers=4)
    assert m.status == "ok" and m.P.shape == (32, 40, 4, 3) and m.occupancy.shape == (32, 40, 4)
    posed_cam = cam.world_to_camera(posed)
    ref = _reference_hits(posed_cam, faces, cam)
    mismatched = 0
    for r, hits in enumerate(ref):
        i, j = divmod(r, cam.width)
        n = min(len(hits), 4)
        if m.occupancy[i, j].sum() != n:
            mismatched += 1  # a ray grazing an edge can flip between float32 and float64
            continue
        for k in range(n):
            t, f, u, v = hits[k]
            w = np.array([1 - u - v, u, v])
            np.testing.assert_allclose(m.P[i, j, k], w @ posed_cam[faces[f]], atol=2e-5)
            np.testing.assert_allclose(m.Q[i, j, k], w @ canon[faces[f]], atol=2e-5)
    print(f"brute-force reference: {mismatched} of {len(ref)} rays differ in hit count")
    assert mismatched <= 2, mismatched
    assert (m.occupancy.sum(axis=(0, 1)) > 0).all()  # all four layers occur
    assert m.mask.sum() > 100


def test_points_lie_on_surfaces_are_sorted_and_reproject_to_pixel_centres(toy):
    canon, posed, faces, frame = toy
    cam = _camera(frame, posed, azimuth=-120.0, size=(48, 40))
    m = dual_point_maps(posed, canon, faces, cam)
    occ = m.occupancy
    P, Q = m.P[occ].astype(np.float64), m.Q[occ].astype(np.float64)
    posed_mesh = trimesh.Trimesh(cam.world_to_camera(posed), faces, process=False)
    canon_mesh = trimesh.Trimesh(canon, faces, process=False)
    assert trimesh.proximity.closest_point(posed_mesh, P)[1].max() < 1e-4
    assert trimesh.proximity.closest_point(canon_mesh, Q)[1].max() < 1e-4
    # layers front to back, contiguous from layer 0, unoccupied entries zero
    z = m.P[..., 2]
    both = occ[..., 1:] & occ[..., :-1]
    assert (z[..., 1:][both] > z[..., :-1][both]).all()
    assert not (occ[..., 1:] & ~occ[..., :-1]).any()
    assert not m.P[~occ].any() and not m.Q[~occ].any()
    # P projects back onto its pixel centre
    uv, _ = cam.project(cam.camera_to_world(m.P.astype(np.float64)))
    rows, cols, _ = np.nonzero(occ)
    err = np.abs(uv[occ] - np.stack([cols + 0.5, rows + 0.5], 1)).max()
    assert err < 1e-3, err
    pc = cam.world_to_camera(posed)
    assert m.object_depth == pytest.approx(0.5 * (pc[:, 2].min() + pc[:, 2].max()))


def test_layer_zero_is_the_first_hit_of_cast_rays(toy):
    import open3d as o3d

    canon, posed, faces, frame = toy
    cam = _camera(frame, posed, azimuth=10.0, elevation=-20.0, size=(48, 40))
    m = dual_point_maps(posed, canon, faces, cam)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(cam.world_to_camera(posed).astype(np.float32)),
                        o3d.core.Tensor(faces.astype(np.uint32)))
    d = cam.pixel_ray_directions().reshape(-1, 3)
    rays = np.concatenate([np.zeros_like(d), d], 1).astype(np.float32)
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().reshape(40, 48)
    np.testing.assert_array_equal(m.mask, np.isfinite(t))
    np.testing.assert_allclose(m.P[..., 0, 2][m.mask], t[m.mask], rtol=1e-6)


def test_world_and_camera_frame_inputs_agree_and_batches_match(toy):
    canon, posed, faces, frame = toy
    cams = [_camera(frame, posed, a, size=(24, 20)) for a in (0.0, 90.0, 180.0, -60.0)]
    a = dual_point_maps(posed, canon, faces, cams[1])
    b = dual_point_maps(cams[1].world_to_camera(posed), canon, faces, cams[1], frame="camera")
    np.testing.assert_array_equal(a.occupancy, b.occupancy)
    np.testing.assert_allclose(a.P, b.P, atol=1e-6)
    batch = dual_point_maps_batch(np.stack([posed] * 4), canon, faces, cams)
    assert batch.P.shape == (4, 20, 24, 4, 3) and batch.status == ["ok"] * 4
    np.testing.assert_array_equal(batch.P[1], a.P)
    par = dual_point_maps_parallel(np.stack([posed] * 4), canon, faces, cams, workers=2, chunk_size=2)
    np.testing.assert_array_equal(par.P, batch.P)
    np.testing.assert_array_equal(par.Q, batch.Q)
    np.testing.assert_array_equal(par.occupancy, batch.occupancy)
    np.testing.assert_array_equal(par.object_depth, batch.object_depth)


def test_camera_looking_away_gives_empty_maps_with_a_status(toy):
    canon, posed, faces, frame = toy
    cam = _camera(frame, posed, 0.0, size=(16, 12))
    away = cam.with_pose(np.diag([-1.0, 1.0, -1.0]) @ cam.R, np.diag([-1.0, 1.0, -1.0]) @ cam.t)  # turned around
    m = dual_point_maps(posed, canon, faces, away)
    assert m.status == "empty" and "no pixel ray hits the mesh" in m.reason
    assert not m.occupancy.any() and not m.P.any() and not m.Q.any()
    # camera inside the closed body (vertices on both sides of it): every ray leaves the surface once at least
    inside = cam.with_pose(cam.R, cam.R @ -frame.origin)
    m = dual_point_maps(posed, canon, faces, inside)
    assert m.status == "ok" and m.mask.mean() > 0.99 and (m.P[..., 2][m.occupancy] > 0).all()


def test_degenerate_faces_are_skipped(toy):
    canon, posed, faces, frame = toy
    cam = _camera(frame, posed, 45.0, size=(24, 20))
    extra_v = np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.2, 0.0]])  # collinear: zero area
    V = np.concatenate([posed, cam.camera_to_world(np.array([[0, 0, 5.0], [0, 0, 5.0], [0.01, 0, 5.0]]))])
    C = np.concatenate([canon, extra_v])
    n = len(posed)
    bad = np.array([[0, 0, 1], [n, n + 1, n + 2], [n, n + 2, n + 2]])
    m = dual_point_maps(V, C, np.concatenate([faces, bad]), cam)
    ref = dual_point_maps(posed, canon, faces, cam)
    np.testing.assert_array_equal(m.occupancy, ref.occupancy)
    np.testing.assert_array_equal(m.P, ref.P)


def test_bad_inputs_are_rejected(toy):
    canon, posed, faces, frame = toy
    cam = _camera(frame, posed, 0.0, size=(16, 12))
    bad = posed.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match=r"posed_vertices must be finite; 1 rows have nan/inf"):
        dual_point_maps(bad, canon, faces, cam)
    with pytest.raises(ValueError, match=r"canonical_vertices must have \d+ rows \(one per posed vertex\), got 5"):
        dual_point_maps(posed, canon[:5], faces, cam)
    with pytest.raises(ValueError, match=r"faces index vertices in \[0, \d+\), got range \[0, 99999\]"):
        dual_point_maps(posed, canon, np.concatenate([faces, [[0, 1, 99999]]]), cam)
    with pytest.raises(TypeError, match="faces must be an integer array, got dtype float64"):
        dual_point_maps(posed, canon, faces.astype(float), cam)
    with pytest.raises(TypeError, match="camera must be a PinholeCamera, got dict"):
        dual_point_maps(posed, canon, faces, {"fx": 1.0})
    with pytest.raises(ValueError, match=r"PinholeCamera\.t must be finite"):
        cam.with_pose(cam.R, [0.0, np.nan, 1.0])
    with pytest.raises(ValueError, match=r"num_layers must be an int >= 1, got 0"):
        dual_point_maps(posed, canon, faces, cam, num_layers=0)


def test_dual_point_cloud_from_ground_truth_and_predicted_maps(toy):
    canon, posed, faces, frame = toy
    cam = _camera(frame, posed, 100.0, size=(24, 20))
    m = dual_point_maps(posed, canon, faces, cam)
    cloud = dual_point_cloud(m.P, m.Q, m.occupancy)
    assert cloud.posed_points.shape == (m.occupancy.sum(), 3) and cloud.confidence is None
    uv, _ = cam.project(cam.camera_to_world(cloud.posed_points.astype(np.float64)))
    assert np.abs(uv - cloud.pixels).max() < 1e-3
    np.testing.assert_array_equal(cloud.layers, np.nonzero(m.occupancy)[2])
    # predicted maps: occupancy probabilities and raw confidence c, C = 1 + exp(c)
    rng = np.random.default_rng(0)
    prob = rng.uniform(size=m.occupancy.shape)
    c = rng.normal(size=m.occupancy.shape)
    pred = dual_point_cloud(m.P, m.Q, prob, confidence=c)
    expected = [(i, j, k) for i in range(20) for j in range(24) for k in range(4)
                if prob[i, j, k] > 0.5 and 1 + np.exp(c[i, j, k]) >= 2.0]
    assert [(int(p[1] - 0.5), int(p[0] - 0.5), int(k)) for p, k in zip(pred.pixels, pred.layers)] == expected
    np.testing.assert_allclose(pred.confidence, 1 + np.exp([c[e] for e in expected]), rtol=1e-6)
    assert (pred.confidence >= 2).all() and (pred.occupancy > 0.5).all()
    with pytest.raises(ValueError, match=r"occupancy must be bool or probabilities in \[0, 1\]"):
        dual_point_cloud(m.P, m.Q, prob * 3 - 1)
    with pytest.raises(ValueError, match=r"confidence must have shape \(20, 24, 4\), got \(20, 24\)"):
        dual_point_cloud(m.P, m.Q, prob, confidence=c[..., 0])


def test_float16_storage_stays_below_one_millimetre_on_the_toy_at_3_to_8_m():
    rig = build_toy_rig()
    V, F = rig.rest_vertices, rig.faces
    i = TOY_JOINTS.index
    frame = body_frame(rig.rest_joint_positions, i("spine.2"), (i("spine.1"), i("spine.2")),
                       (i("thigh.L"), i("thigh.R")))
    intr = PinholeCamera.from_fov(40.0, 64, 64)
    worst, worst_abs = 0.0, 0.0
    for az, el, radius in [(0, 10, 3.0), (90, 5, 5.0), (-90, -10, 8.0), (180, 30, 8.0), (45, -5, 6.5)]:
        cam = camera_from_spherical(frame, SphericalCoords(az, el, 0.0, radius), intr)
        m = dual_point_maps(V, V, F, cam)
        assert 2.0 < m.object_depth < 8.5
        P16, Q16 = encode_float16(m.P, m.Q, m.occupancy, m.object_depth)
        assert P16.dtype == Q16.dtype == np.float16
        P, Q = decode_float16(P16, Q16, m.occupancy, m.object_depth)
        occ = m.occupancy
        worst = max(worst, np.linalg.norm(P[occ] - m.P[occ], axis=1).max(),
                    np.linalg.norm(Q[occ] - m.Q[occ], axis=1).max())
        worst_abs = max(worst_abs, np.linalg.norm(m.P[occ].astype(np.float16) - m.P[occ], axis=1).max())
        assert not P[~occ].any() and not Q[~occ].any()
    print(f"float16 round trip: max 3D error {worst * 1000:.3f} mm (absolute-depth float16: {worst_abs * 1000:.2f} mm)")
    assert worst < 1e-3
    assert worst_abs > 1e-3  # why P is stored relative to the object depth
    big = np.zeros((1, 1, 1, 3))
    big[..., 0] = FLOAT16_MAX_ABS_M + 0.1
    with pytest.raises(ValueError, match=r"Q reaches 2.100 m >= 2.0 m: float16 would lose > 0.49 mm"):
        encode_float16(np.zeros((1, 1, 1, 3)), big, np.ones((1, 1, 1), bool), 0.0)


def test_storage_dtype_falls_back_to_float32_for_large_rigs():
    from bat3r_core.pointmaps import storage_dtype

    small = np.array([[-1.0, 0.0, -1.2], [1.0, 1.9, 1.2]])
    large = small * np.array([1.0, 1.2, 1.0])  # a head above 2 m
    assert storage_dtype(small) is np.float16
    assert storage_dtype(large) is np.float32
    assert storage_dtype(small, max_scale=3.0) is np.float32
    rng = np.random.default_rng(0)
    P = rng.normal(size=(4, 4, 2, 3)) + [0.0, 0.0, 6.0]
    Q = rng.normal(size=(4, 4, 2, 3)) * 3.0  # beyond float16's sub-millimetre range
    occ = np.ones((4, 4, 2), bool)
    from bat3r_core.pointmaps import decode_float16, encode_float16

    with pytest.raises(ValueError, match="store float32"):
        encode_float16(P, Q, occ, 6.0)
    p32, q32 = encode_float16(P, Q, occ, 6.0, dtype=np.float32)
    assert p32.dtype == np.float32
    P2, Q2 = decode_float16(p32, q32, occ, np.float32(6.0))
    assert np.abs(P2 - P).max() < 1e-5 and np.abs(Q2 - Q).max() < 1e-5
