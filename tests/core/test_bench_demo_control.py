"""The oracle reference of ``benchmarks/bench_demo_control.py``: fit rows that carry an image's hidden truth."""
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import bench_demo_control as B  # noqa: E402

from bat3r_core.cameras import PinholeCamera, look_at  # noqa: E402
from bat3r_core.fitting.io import camera_from_row  # noqa: E402
from bat3r_core.poses import sample_toy_natural_poses  # noqa: E402
from bat3r_core.predictor.collection import CropTransform  # noqa: E402
from bat3r_core.skinning import axis_angle_to_matrix, skin  # noqa: E402


def _truth(rig, seed):
    theta, _ = sample_toy_natural_poses(1, seed=seed)
    rg = axis_angle_to_matrix(torch.tensor([[0.1, 2.0, -0.2]], dtype=torch.float64))[0].numpy()
    tg = np.array([0.3, -0.1, 0.5])
    tensors = rig.tensors(dtype=torch.float64)
    posed = skin(tensors, torch.as_tensor(theta), global_rotation=torch.as_tensor(rg)[None],
                 global_translation=torch.as_tensor(tg)[None]).vertices[0].numpy()
    R, t = look_at(np.array([1.0, 1.2, 4.0]), posed.mean(0), np.array([0.0, 1.0, 0.0]))
    cam = PinholeCamera.from_fov(40.0, 80, 60, R=R, t=t)
    return theta[0], {"excess_rotations": theta[0], "global_scale": 1.0, "global_rotation": rg,
                      "global_translation": tg, "camera_rotation": R, "camera_translation": t, "K": cam.K,
                      "posed_vertices": posed}, cam


def test_true_fit_rows_put_the_skinned_rig_on_the_crop_pixels_of_the_photo(toy_rig):
    theta, gt, photo_cam = _truth(toy_rig, 3)
    crop = CropTransform(x0=4.0, y0=-6.0, size=70.0, resolution=64)
    coll = [{"sample_id": "a", "status": "ok", "crop_x0": crop.x0, "crop_y0": crop.y0, "crop_size": crop.size,
             "resolution": 64},
            {"sample_id": "b", "status": "unreadable", "crop_x0": 0.0, "crop_y0": 0.0, "crop_size": 0.0,
             "resolution": 64},
            {"sample_id": "c", "status": "ok", "crop_x0": 0.0, "crop_y0": 0.0, "crop_size": 64.0, "resolution": 64}]
    rows = B.true_fit_rows(coll, {"a": gt, "b": gt})  # b failed in the collection, c has no truth
    assert [r["sample_id"] for r in rows] == ["a"]
    row = rows[0]
    np.testing.assert_allclose(np.reshape(row["excess_rotations"], (-1, 3)), theta)
    unplaced = skin(toy_rig.tensors(dtype=torch.float64), torch.as_tensor(theta)[None]).vertices[0].numpy()
    uv_fit, _ = camera_from_row(row).project(unplaced)
    uv_photo, _ = photo_cam.project(gt["posed_vertices"])
    np.testing.assert_allclose(uv_fit, crop.apply(uv_photo), atol=1e-6)
    with pytest.raises(ValueError, match="global scale 1.3"):
        B.true_fit_rows(coll[:1], {"a": {**gt, "global_scale": 1.3}})
