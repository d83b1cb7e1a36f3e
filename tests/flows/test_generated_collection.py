"""A generated collection for a rig that is not the toy: `python flows/toy_collection.py --catalog` on a catalog
whose category points at a modified toy (other joint names, its own embedded texture, no `textures`), rendered for
real in random poses with the toy's hidden ground-truth layout."""
from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from bat3r_core import evaluation_truth, shards
from bat3r_core.rig_io import load_rig, save_rig_glb
from bat3r_core.runs import RunLayout
from bat3r_core.toy import toy_coat_texture

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.blender
FRAME = {"origin": "Spine_2", "forward": ["Spine_1", "Spine_2"], "horizontal": ["Thigh_L", "Thigh_R"]}


def test_a_generated_collection_of_another_rig_has_the_toy_layout(prefect_harness, toy_rig, tmp_path):
    from prefect.settings import PREFECT_API_URL

    folder = tmp_path / "catalog"
    folder.mkdir()
    names = tuple(n[0].upper() + n[1:].replace(".", "_") for n in toy_rig.joint_names)
    rig = dataclasses.replace(toy_rig, name="critter", joint_names=names)
    save_rig_glb(rig, folder / "critter.glb", texture=toy_coat_texture("grey"))
    data = yaml.safe_load((ROOT / "data_catalog.yaml").read_text())
    data["categories"] = {"critter": {
        "asset": "critter.glb", "body_frame": FRAME, "environment_maps": [],  # no textures: the asset's own
        "collection": {"kind": "generated", "path": "collections/critter/train", "seed": 11},
        "test_split": {"kind": "generated", "path": "collections/critter/test", "seed": 12,
                       "ground_truth": "collections/critter/test_truth"},
        "fitting": {"preset": "synthetic"}}}
    catalog = folder / "critter_catalog.yaml"
    catalog.write_text(yaml.safe_dump(data))
    env = {k: v for k, v in os.environ.items() if k != "BAT3R_STORAGE_ROOT"}
    env.update(PREFECT_API_URL=PREFECT_API_URL.value(), BAT3R_CATALOG=str(ROOT / "data_catalog.yaml"),
               PYTHONPATH=str(ROOT))
    proc = subprocess.run([sys.executable, str(ROOT / "flows" / "toy_collection.py"), "--catalog", str(catalog),
                           "--category", "critter", "--run-name", "g1", "--set", "run.collection_size=3",
                           "--set", "run.test_size=2"], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "collection (generated_collection): 3 renders, none dropped" in proc.stdout
    assert "test (collection): 2 images, none dropped" in proc.stdout

    train = folder / "collections" / "critter" / "train" / "n3-r32"
    truth = folder / "collections" / "critter" / "train_ground_truth" / "n3-r32"
    assert (folder / "collections" / "critter" / "test_truth" / "n2-r32" / "ground_truth.npz").is_file()
    with np.load(truth / "ground_truth.npz", allow_pickle=False) as gt:
        ids = [str(s) for s in gt["sample_id"]]
        assert ids == [f"critter-{i:05d}" for i in range(3)]
        theta = gt["excess_rotations"]
        assert theta.shape == (3, rig.num_joints, 3) and set(gt["pose_family"]) == {"random"}
        assert not theta[:, 0].any() and np.linalg.norm(theta[:, 1:], axis=-1).mean() > 0.05  # root unrotated
        np.testing.assert_allclose(gt["global_rotation"][:, :, 1], [[0, 1, 0]] * 3, atol=1e-9)  # yaw only
        for k, sid in enumerate(ids):
            image = cv2.imread(str(train / "images" / f"{sid}.png"))
            mask = cv2.imread(str(train / "masks" / f"{sid}.png"), cv2.IMREAD_GRAYSCALE) > 127
            assert image.shape == (32, 32, 3) and mask.sum() > 20
            K, R, t = gt["K"][k], gt["camera_rotation"][k], gt["camera_translation"][k]
            cam = gt["posed_vertices"][k] @ R.T + t
            uv = cam[:, :2] / cam[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
            cols, rows = np.clip(np.floor(uv).astype(int), 0, 31).T
            near = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
            assert near[rows, cols].mean() > 0.95  # the hidden posed mesh is what was rendered
    # evaluation reads it unchanged; the asset rendered is beside it, with the category's joints
    assert set(evaluation_truth.load_ground_truth(truth / "ground_truth.npz")) == set(ids)
    (asset,) = truth.glob("*.glb")
    assert load_rig(asset).joint_names == names
    stamp = json.loads((truth / "collection.json").read_text())["params"]
    assert (stamp["kind"], stamp["pose_sampler"], stamp["textures"], stamp["prefix"]) == \
        ("generated_collection", "random", [], "critter")
    assert stamp["body_frame"] == FRAME
    assert sorted(p.name for p in train.iterdir()) == ["collection.json", "images", "masks"]  # truth is elsewhere
    # the run's collection and test shards (the predictor's input)
    layout = RunLayout(folder / "runs", "critter", "g1")
    assert shards.read_table(layout.run_stage_dir("collection")).column("status").to_pylist() == ["ok"] * 3
    assert shards.read_table(layout.run_stage_dir("test")).num_rows == 2
