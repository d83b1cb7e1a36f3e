"""`bat3r fit` on ray-cast dual point clouds of the toy (the fitting accuracy itself is tested in tests/core)."""
import numpy as np
import torch

from bat3r_core.cameras import PinholeCamera
from bat3r_core.cli import main
from bat3r_core.fitting.fit import PointCloudInstance
from bat3r_core.fitting.io import write_points_npz
from bat3r_core.pointmaps import dual_point_cloud, dual_point_maps
from bat3r_core.poses import sample_toy_natural_poses
from bat3r_core.shards import read_table
from bat3r_core.skinning import skin


def test_bat3r_fit(toy_rig, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("BAT3R_CACHE", str(tmp_path / "geo"))
    theta, _ = sample_toy_natural_poses(1, seed=77_001)
    verts = skin(toy_rig.tensors(torch.float64), torch.as_tensor(theta)).vertices[0].numpy()
    cam = PinholeCamera.from_fov(40.0, 64, 64)
    # camera 6 m in front of the toy's left side, looking at it (OpenCV axes: x right, y down, z forward)
    r = np.array([[0.0, 0.0, -1.0], [0.0, -1.0, 0.0], [-1.0, 0.0, 0.0]])
    cam = cam.with_pose(r, -r @ np.array([6.0, 1.0, 0.0]))
    maps = dual_point_maps(verts, toy_rig.rest_vertices, toy_rig.faces, cam)
    pc = dual_point_cloud(maps.P, maps.Q, maps.occupancy)
    P = pc.posed_points.astype(np.float64)
    P[:, 2] -= maps.object_depth
    inst = PointCloudInstance("pose-0", P, pc.canonical_points, None, pc.pixels, pc.layers, cam.K, (64, 64))
    empty = PointCloudInstance("nothing", np.zeros((2, 3)), np.zeros((2, 3)), None, np.zeros((2, 2)),
                               np.zeros(2, np.int64), cam.K, (64, 64))
    points = write_points_npz(tmp_path / "points.npz", [inst, empty])
    assert main(["fit", "--asset", "toy", "--points", str(points), "--preset", "synthetic", "--steps", "20",
                 "--out", str(tmp_path / "fits")]) == 0
    out = capsys.readouterr().out
    assert "fitted 1/2 instances (synthetic preset, 20 steps)" in out and "nothing:" in out
    rows = {r["sample_id"]: r for r in read_table(tmp_path / "fits").to_pylist()}
    assert rows["pose-0"]["status"] == "ok" and rows["nothing"]["status"] != "ok"
