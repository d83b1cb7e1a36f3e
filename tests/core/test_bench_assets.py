"""``benchmarks/bench_assets.py``: the Blender subdivision it checks heavy assets with, and its argument checks."""
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import bench_assets as A  # noqa: E402

from bat3r_core.rig_io import read_asset, save_rig_glb  # noqa: E402


@pytest.mark.blender
def test_subdivision_makes_a_heavier_rig_of_the_same_shape(toy_rig, tmp_path):
    """One Catmull–Clark level through Blender: each triangle becomes three quads (six triangles), a rig that still loads (skin weights
    interpolated, every vertex weighted), the same animal (bounding box within 3 %: subdivision shrinks convex
    parts a little), and level 0 the same mesh through Blender's exporter."""
    src = save_rig_glb(toy_rig, tmp_path / "toy.glb")
    same, _ = read_asset(A.subdivide(src, tmp_path, 0))
    heavy, _ = read_asset(A.subdivide(src, tmp_path, 1))
    assert len(same.faces) == len(toy_rig.faces)
    assert len(heavy.faces) == 6 * len(toy_rig.faces)
    assert heavy.num_vertices > 3 * same.num_vertices
    np.testing.assert_allclose(heavy.skin_weights.sum(1), 1.0, atol=1e-5)
    assert heavy.joint_names == same.joint_names
    extent = np.ptp(toy_rig.rest_vertices, axis=0)
    assert np.abs(np.ptp(heavy.rest_vertices, axis=0) - extent).max() < 0.03 * extent.max()


def test_bad_arguments_are_refused_before_blender_runs(tmp_path, capsys):
    with pytest.raises(SystemExit):
        A.main(["--asset", str(tmp_path / "missing.glb"), "--results-dir", str(tmp_path)])
    assert "--asset" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        A.main(["--asset", __file__, "--levels", "-1", "--results-dir", str(tmp_path)])
    assert "--levels" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        A.main(["--record-as", "assets.v2", "--results-dir", str(tmp_path)])
    assert "--record-as" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
