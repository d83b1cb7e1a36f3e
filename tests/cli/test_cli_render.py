"""`bat3r render` and `bat3r collection toy` for real (Blender, tiny sizes)."""
import cv2
import numpy as np
import pytest

from bat3r_core.cli import main
from bat3r_core.datasets import canonical_jobs
from bat3r_core.render.jobs import write_jobs
from bat3r_core.rig_io import save_rig_glb
from bat3r_core.shards import read_shard
from bat3r_core.toy import TOY_BODY_FRAME

pytestmark = pytest.mark.blender


def test_bat3r_render_one_shard(toy_rig, tmp_path, capsys):
    asset = save_rig_glb(toy_rig, tmp_path / "toy.glb")
    jobs = canonical_jobs(toy_rig, 3, seed=4, body_frame_spec=TOY_BODY_FRAME, resolution=32)
    write_jobs(jobs, tmp_path / "jobs.parquet")
    assert main(["render", "--jobs", str(tmp_path / "jobs.parquet"), "--asset", str(asset),
                 "--out", str(tmp_path / "out")]) == 0
    assert "rendered 3 ok, 0 failed" in capsys.readouterr().out
    table, arrays = read_shard(tmp_path / "out", 0)
    assert table.num_rows == 3 and arrays["rgb"].shape == (3, 32, 32, 3)
    assert (arrays["mask"].sum((1, 2)) > 30).all()
    # exact labels: the mask is the ray-cast layer-0 occupancy (up to anti-aliased border pixels)
    agree = (arrays["mask"] == arrays["occupancy"][..., 0]).mean()
    assert agree > 0.97


def test_bat3r_collection_toy(tmp_path, capsys):
    out = tmp_path / "toy_photos"
    assert main(["collection", "toy", "--n", "2", "--out", str(out), "--resolution", "32", "--preset", "tiny"]) == 0
    assert "rendered 2 images" in capsys.readouterr().out
    images = sorted((out / "images").glob("*.png"))
    masks = sorted((out / "masks").glob("*.png"))
    assert len(images) == 2 and [p.name for p in images] == [p.name for p in masks]
    assert cv2.imread(str(masks[0]), cv2.IMREAD_GRAYSCALE).astype(bool).sum() > 20
    assert not any(p.name.startswith("ground") for p in out.iterdir())  # the truth lives outside the collection
    assert main(["collection", "toy", "--n", "2", "--out", str(out), "--resolution", "32", "--preset", "tiny"]) == 0
    assert "reused 2 images" in capsys.readouterr().out
    assert np.asarray(cv2.imread(str(images[0]))).shape == (32, 32, 3)
