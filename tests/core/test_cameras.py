"""Pinhole camera: intrinsics constructors, projection, rays, validation, Blender conversion (checked in bpy)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bat3r_core.cameras import (GLTF_TO_BLENDER_WORLD, PinholeCamera, look_at, project_points, stack_extrinsics,
                                stack_intrinsics, to_blender, unproject_points)


def _random_camera(seed: int, width: int = 64, height: int = 48) -> PinholeCamera:
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=seed).as_matrix()
    return PinholeCamera(fx=rng.uniform(50, 90), fy=rng.uniform(50, 90), cx=rng.uniform(20, 40),
                         cy=rng.uniform(15, 30), width=width, height=height, R=R, t=rng.normal(size=3))


def test_from_fov_puts_the_fov_edge_on_the_image_border():
    cam = PinholeCamera.from_fov(60.0, 160, 120)
    assert cam.fx == pytest.approx(80.0 / math.tan(math.radians(30.0)))
    assert cam.fy == cam.fx and (cam.cx, cam.cy) == (80.0, 60.0)
    edge = np.array([math.tan(math.radians(30.0)), 0.0, 1.0]) * 3.0
    uv, depth = cam.project(edge)
    assert uv[0] == pytest.approx(160.0) and uv[1] == pytest.approx(60.0) and depth == pytest.approx(3.0)


def test_from_focal_mm_uses_a_36mm_horizontal_sensor():
    cam = PinholeCamera.from_focal_mm(50.0, 160, 90)
    assert cam.fx == pytest.approx(50.0 * 160 / 36.0) and cam.fy == cam.fx
    # 50 mm on 36 mm: horizontal fov 2 atan(18 / 50)
    fov = math.degrees(2 * math.atan(18.0 / 50.0))
    assert PinholeCamera.from_fov(fov, 160, 90).fx == pytest.approx(cam.fx)


def test_project_matches_the_homogeneous_formula_and_unproject_inverts_it():
    cam = _random_camera(1)
    rng = np.random.default_rng(2)
    pts = cam.camera_to_world(np.c_[rng.uniform(-1, 1, (100, 2)), rng.uniform(1, 5, 100)])
    uv, depth = cam.project(pts)
    h = (cam.K @ (cam.R @ pts.T + cam.t[:, None])).T  # slow reference, one formula
    np.testing.assert_allclose(uv, h[:, :2] / h[:, 2:], atol=1e-9)
    np.testing.assert_allclose(depth, h[:, 2], atol=1e-12)
    np.testing.assert_allclose(cam.unproject(uv, depth), pts, atol=1e-9)


def test_points_behind_the_camera_project_to_nan():
    cam = PinholeCamera.from_fov(50, 32, 32)
    uv, depth = cam.project(np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 2.0]]))
    assert np.isnan(uv[0]).all() and np.isfinite(uv[1]).all() and depth[0] == -1.0


def test_batched_projection_with_one_camera_per_row():
    cams = [_random_camera(s) for s in range(3)]
    Ks = stack_intrinsics(cams)
    Rs, ts = stack_extrinsics(cams)
    pts = np.random.default_rng(0).normal(size=(3, 10, 3)) * 0.3 + [0, 0, 0]
    pts_cam = np.einsum("bij,bnj->bni", Rs, pts) + ts[:, None]
    pts_cam[..., 2] = np.abs(pts_cam[..., 2]) + 1.0
    uv, z = project_points(pts_cam, Ks[:, None])
    for b, cam in enumerate(cams):
        uv_b, _ = project_points(pts_cam[b], cam.K)
        np.testing.assert_allclose(uv[b], uv_b, atol=1e-12)
    np.testing.assert_allclose(unproject_points(uv, z, Ks[:, None]), pts_cam, atol=1e-9)


def test_centre_and_pixel_rays_go_through_pixel_centres():
    cam = _random_camera(3, width=7, height=5)
    np.testing.assert_allclose(cam.world_to_camera(cam.center), 0.0, atol=1e-12)
    origins, dirs = cam.pixel_rays()
    assert origins.shape == dirs.shape == (5, 7, 3)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=-1), 1.0, atol=1e-12)
    uv, _ = cam.project(origins + 2.5 * dirs)
    j, i = np.meshgrid(np.arange(7), np.arange(5))
    np.testing.assert_allclose(uv[..., 0], j + 0.5, atol=1e-9)
    np.testing.assert_allclose(uv[..., 1], i + 0.5, atol=1e-9)
    d = cam.pixel_ray_directions()
    np.testing.assert_allclose(d[..., 2], 1.0)


def test_look_at_centres_the_target_and_keeps_up_upward():
    R, t = look_at(eye=[3.0, 1.0, 4.0], target=[0.0, 0.5, 0.0], up=[0.0, 1.0, 0.0])
    cam = PinholeCamera.from_fov(45, 64, 64, R=R, t=t)
    uv, depth = cam.project(np.array([[0.0, 0.5, 0.0], [0.0, 0.6, 0.0]]))
    np.testing.assert_allclose(uv[0], [32.0, 32.0], atol=1e-9)
    assert depth[0] == pytest.approx(math.sqrt(9 + 0.25 + 16))
    assert uv[1, 1] < uv[0, 1]  # higher in the world -> smaller row
    assert abs(uv[1, 0] - 32.0) < 1e-9  # straight up stays on the vertical centre line
    with pytest.raises(ValueError, match="parallel to the viewing direction"):
        look_at([0, 5, 0], [0, 0, 0], [0, 1, 0])


@pytest.mark.parametrize("field, value, match", [
    ("fx", float("nan"), r"PinholeCamera\.fx must be finite, got nan"),
    ("cy", float("inf"), r"PinholeCamera\.cy must be finite, got inf"),
    ("fy", -1.0, r"PinholeCamera\.fy must be > 0, got -1\.0"),
    ("width", 0, r"PinholeCamera\.width must be > 0, got 0"),
    ("t", np.array([0.0, np.nan, 0.0]), r"PinholeCamera\.t must be finite"),
    ("R", np.full((3, 3), np.nan), r"PinholeCamera\.R must be finite"),
    ("R", np.diag([1.0, 1.0, -1.0]), r"PinholeCamera\.R must be a rotation matrix"),
    ("t", np.zeros(4), r"PinholeCamera\.t must have shape \(3,\), got \(4,\)"),
])
def test_bad_camera_fields_are_rejected_with_the_field_name(field, value, match):
    kwargs = dict(fx=50.0, fy=50.0, cx=16.0, cy=16.0, width=32, height=32, R=np.eye(3), t=np.zeros(3))
    kwargs[field] = value
    with pytest.raises(ValueError, match=match):
        PinholeCamera(**kwargs)


def test_bad_types_and_fov():
    with pytest.raises(TypeError, match=r"PinholeCamera\.height must be an int, got float"):
        PinholeCamera(50.0, 50.0, 16.0, 16.0, 32, 32.0)
    with pytest.raises(ValueError, match=r"fov_deg must be in \(0, 180\) degrees, got 180\.0"):
        PinholeCamera.from_fov(180.0, 32, 32)
    with pytest.raises(ValueError, match=r"points_world must have shape \(\.\.\., 3\), got \(4, 2\)"):
        PinholeCamera.from_fov(50, 32, 32).project(np.zeros((4, 2)))


def test_camera_is_immutable():
    cam = _random_camera(0)
    with pytest.raises(Exception):
        cam.fx = 1.0
    with pytest.raises(ValueError):
        cam.R[0, 0] = 2.0  # read-only array


def _blender_projection(settings: dict, points_world: np.ndarray) -> np.ndarray:
    """Blender's pinhole model, written from its definitions: camera looks down local -z with y up, the sensor
    width spans the image width (horizontal fit), and so do the shifts."""
    M = settings["matrix_world"]
    local = (points_world - M[:3, 3]) @ M[:3, :3]  # world -> camera local (M is orthonormal)
    W, H = settings["resolution_x"], settings["resolution_y"]
    f_px = settings["lens_mm"] / settings["sensor_width_mm"] * W
    x, y = local[:, 0] / -local[:, 2], local[:, 1] / -local[:, 2]
    side = W
    u = W / 2 + f_px * x - settings["shift_x"] * side
    v = H / 2 - f_px * y + settings["shift_y"] * side
    return np.stack([u, v], axis=1)


@pytest.mark.parametrize("width, height", [(96, 64), (48, 80)])
def test_to_blender_reproduces_the_projection_in_blenders_model(width, height):
    rng = np.random.default_rng(5)
    cam = PinholeCamera.from_focal_mm(35.0, width, height, R=Rotation.random(random_state=5).as_matrix(),
                                      t=[0.1, -0.2, 4.0], cx=40.0, cy=37.0)
    pts = cam.camera_to_world(np.c_[rng.uniform(-1, 1, (50, 2)), rng.uniform(2, 6, 50)])
    s = to_blender(cam)
    np.testing.assert_allclose(_blender_projection(s, pts), cam.project(pts)[0], atol=1e-9)
    assert s["lens_mm"] == pytest.approx(35.0) and s["sensor_fit"] == "HORIZONTAL"
    np.testing.assert_allclose(s["matrix_world"][:3, 3], cam.center)
    with pytest.raises(ValueError, match=r"square pixels \(fx == fy\), got fx=50\.0, fy=60\.0"):
        to_blender(PinholeCamera(50.0, 60.0, 16, 16, 32, 32))


@pytest.mark.blender
@pytest.mark.parametrize("width, height, world", [(96, 64, None), (48, 80, GLTF_TO_BLENDER_WORLD)])
def test_to_blender_in_real_blender(width, height, world):
    bpy = pytest.importorskip("bpy")
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Matrix, Vector

    rng = np.random.default_rng(7)
    cam = PinholeCamera.from_focal_mm(42.0, width, height, R=Rotation.random(random_state=7).as_matrix(),
                                      t=[0.2, 0.1, 5.0], cx=width * 0.4, cy=height * 0.6)
    s = to_blender(cam, world_rotation=world)
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    scene.render.pixel_aspect_x = scene.render.pixel_aspect_y = 1.0
    data = bpy.data.cameras.new("bat3r_test_cam")
    data.lens, data.sensor_width, data.sensor_fit = s["lens_mm"], s["sensor_width_mm"], s["sensor_fit"]
    data.shift_x, data.shift_y = s["shift_x"], s["shift_y"]
    obj = bpy.data.objects.new("bat3r_test_cam", data)
    scene.collection.objects.link(obj)
    obj.matrix_world = Matrix(s["matrix_world"].tolist())
    bpy.context.view_layer.update()
    pts = cam.camera_to_world(np.c_[rng.uniform(-0.8, 0.8, (20, 2)), rng.uniform(2, 6, 20)])
    Rw = np.eye(3) if world is None else world
    ndc = np.array([tuple(world_to_camera_view(scene, obj, Vector((Rw @ p).tolist()))) for p in pts])
    uv_blender = np.stack([ndc[:, 0] * width, (1.0 - ndc[:, 1]) * height], axis=1)
    np.testing.assert_allclose(uv_blender, cam.project(pts)[0], atol=1e-3)
    np.testing.assert_allclose(ndc[:, 2], cam.project(pts)[1], atol=1e-5)
    bpy.data.objects.remove(obj)
