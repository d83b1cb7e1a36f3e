"""`bat3r train` and `bat3r predict` end to end on tiny synthetic data (the real renders are tested elsewhere)."""
import cv2
import numpy as np

from bat3r_core.cli import main
from bat3r_core.predictor.synthetic import write_synthetic_shards
from bat3r_core.shards import read_table


def _photo_folder(root, n=3, size=48):
    (root / "images").mkdir(parents=True)
    (root / "masks").mkdir()
    rng = np.random.default_rng(0)
    for i in range(n):
        img = (rng.random((size, size + 8, 3)) * 255).astype(np.uint8)
        mask = np.zeros((size, size + 8), np.uint8)
        cv2.circle(mask, (20 + i, 24), 10 + i, 255, -1)
        cv2.imwrite(str(root / "images" / f"img{i}.png"), img)
        cv2.imwrite(str(root / "masks" / f"img{i}.png"), mask)
    # an empty mask is recorded and skipped, not fatal
    cv2.imwrite(str(root / "images" / "blank.png"), np.zeros((size, size, 3), np.uint8))
    cv2.imwrite(str(root / "masks" / "blank.png"), np.zeros((size, size), np.uint8))
    return root


def test_train_then_predict(tmp_path, capsys):
    shards = tmp_path / "shards"
    write_synthetic_shards(shards, n=8, resolution=32, shard_size=4, seed=0)
    assert main(["train", "--shards", str(shards), "--out", str(tmp_path / "model"), "--preset", "tiny",
                 "--steps", "3"]) == 0
    ckpt = tmp_path / "model" / "predictor.pt"
    assert ckpt.is_file()
    photos = _photo_folder(tmp_path / "photos")
    assert main(["predict", "--model", str(ckpt), "--collection", str(photos), "--out", str(tmp_path / "pred")]) == 0
    out = capsys.readouterr().out
    rows = read_table(tmp_path / "pred" / "predictions").to_pylist()
    assert sorted(r["sample_id"] for r in rows) == ["blank", "img0", "img1", "img2"]
    status = {r["sample_id"]: r["status"] for r in rows}
    assert status["blank"] == "empty_mask" and "predicted" in out and "blank: empty_mask" in out


def test_train_init_from_starts_from_the_given_predictor(tmp_path):
    import torch

    from bat3r_core.predictor.infer import load_predictor

    shards = tmp_path / "shards"
    write_synthetic_shards(shards, n=8, resolution=32, shard_size=4, seed=0)
    base = ["train", "--shards", str(shards), "--preset", "tiny"]
    assert main([*base, "--out", str(tmp_path / "phi0"), "--steps", "20"]) == 0
    phi0 = tmp_path / "phi0" / "predictor.pt"
    # one step moves the weights only slightly from where they started: from Φ0 when warm, from a fresh init when not
    assert main([*base, "--out", str(tmp_path / "warm"), "--steps", "1", "--init-from", str(phi0)]) == 0
    assert main([*base, "--out", str(tmp_path / "cold"), "--steps", "1"]) == 0
    start = load_predictor(phi0, "cpu")[0].state_dict()

    def distance(folder):
        got = load_predictor(tmp_path / folder / "predictor.pt", "cpu")[0].state_dict()
        return sum(float((got[k].float() - start[k].float()).norm()) for k in start)

    warm, cold = distance("warm"), distance("cold")
    assert warm < 0.3 * cold, (warm, cold)


def test_train_mirror_uses_the_categorys_checked_sagittal_plane(tmp_path, capsys, monkeypatch):
    import pytest

    monkeypatch.setenv("BAT3R_STORAGE_ROOT", str(tmp_path / "runs"))

    from bat3r_core.predictor.infer import load_predictor

    shards = tmp_path / "shards"
    write_synthetic_shards(shards, n=8, resolution=32, shard_size=4, seed=0)
    base = ["train", "--shards", str(shards), "--preset", "tiny", "--steps", "2"]
    assert main([*base, "--out", str(tmp_path / "m"), "--mirror", "toy"]) == 0
    assert "0.5 of the samples mirrored" in capsys.readouterr().out
    assert load_predictor(tmp_path / "m" / "predictor.pt", "cpu")[1].train.mirror_probability == 0.5
    with pytest.raises(FileNotFoundError, match="category .horse.: rigged asset"):  # no asset: named
        main([*base, "--out", str(tmp_path / "h"), "--mirror", "horse"])
