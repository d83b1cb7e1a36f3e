"""Predictor inference: maps, reference filters against a per-entry loop, shards and cloud files, resume."""
import numpy as np
import pytest
import torch

from bat3r_core.predictor.config import ModelConfig, TrainConfig
from bat3r_core.predictor.data import ShardDataset, rgb_features
from bat3r_core.predictor.infer import (PredictedMaps, clouds_path, load_clouds, load_predictor, maps_to_clouds,
                                        predict_collection, predict_maps)
from bat3r_core.predictor.synthetic import synthetic_samples, write_synthetic_shards
from bat3r_core.predictor.train import Trainer
from bat3r_core.shards import read_shard, write_shard

MODEL = ModelConfig(resolution=16, layers=4, base_channels=8, depth=2, two_stage=True)


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    root = tmp_path_factory.mktemp("infer")
    write_synthetic_shards(root / "train", 4, 16, shard_size=4, seed=5)
    cfg = TrainConfig(steps=3, batch_size=2, warmup_steps=1, checkpoint_every=3, seed=1)
    return Trainer(ShardDataset(root / "train"), MODEL, cfg, root / "model").train()


def _slow_filter(maps: PredictedMaps, i):
    kept = []
    _, h, w, k = maps.occupancy.shape
    for r in range(h):
        for c in range(w):
            for layer in range(k):
                if (maps.occupancy[i, r, c, layer] > 0.5 and maps.canonical_confidence[i, r, c, layer] >= 2
                        and maps.posed_confidence[i, r, c, layer] >= 2):
                    kept.append((c + 0.5, r + 0.5, layer))
    return kept


def test_maps_to_clouds_matches_per_entry_filter():
    rng = np.random.default_rng(0)
    n, h, k = 3, 5, 2
    maps = PredictedMaps(canonical_points=rng.normal(size=(n, h, h, k, 3)).astype(np.float32),
                         posed_points=rng.normal(size=(n, h, h, k, 3)).astype(np.float32),
                         occupancy=rng.uniform(size=(n, h, h, k)).astype(np.float32),
                         canonical_confidence=(1 + rng.exponential(1.5, size=(n, h, h, k))).astype(np.float32),
                         posed_confidence=(1 + rng.exponential(1.5, size=(n, h, h, k))).astype(np.float32))
    maps.occupancy[1] = 0.0  # an instance with no point
    clouds = maps_to_clouds(maps)
    assert clouds.offsets[0] == 0 and clouds.offsets[-1] == len(clouds.layers) and len(clouds) == n
    for i in range(n):
        expected = _slow_filter(maps, i)
        got = clouds.instance(i)
        assert [(float(u), float(v), int(l)) for (u, v), l in zip(got["pixels"], got["layers"])] == expected
        for (u, v), layer, p, q, cq in zip(got["pixels"], got["layers"], got["posed_points"],
                                           got["canonical_points"], got["canonical_confidence"]):
            r, c = int(v - 0.5), int(u - 0.5)
            assert np.array_equal(p, maps.posed_points[i, r, c, layer])
            assert np.array_equal(q, maps.canonical_points[i, r, c, layer])
            assert cq == maps.canonical_confidence[i, r, c, layer]
    assert clouds.offsets[2] - clouds.offsets[1] == 0


def test_predict_collection_writes_maps_rows_and_clouds(checkpoint, tmp_path):
    arrays = synthetic_samples(4, 16, seed=9)
    arrays = {"rgb": arrays["rgb"], "mask": arrays["mask"]}
    arrays["mask"][2] = False  # empty mask
    rows = [{"sample_id": f"img{i}", "status": "ok", "reason": ""} for i in range(4)]
    rows[3] = {"sample_id": "img3", "status": "bad_image", "reason": "truncated file"}
    write_shard(tmp_path / "collection", 0, rows, arrays)

    out = predict_collection(checkpoint, tmp_path / "collection", tmp_path / "pred", device="cpu")
    assert [p.complete for p in out] == [True]
    table, maps = read_shard(tmp_path / "pred", 0)
    assert table.column("status").to_pylist() == ["ok", "ok", "empty", "bad_image"]
    assert table.column("reason").to_pylist()[2:] == ["the mask has no foreground pixel", "truncated file"]
    assert maps["posed_points"].shape == (4, 16, 16, 4, 3) and maps["posed_points"].dtype == np.float16
    assert not maps["occupancy"][2:].any()

    model, _ = load_predictor(checkpoint, device="cpu")
    ref = predict_maps(model, rgb_features(arrays["rgb"][:2], arrays["mask"][:2]), arrays["mask"][:2])
    np.testing.assert_allclose(maps["canonical_points"][:2].astype(np.float32), ref.canonical_points, atol=2e-3)
    assert not maps["occupancy"][:2][~arrays["mask"][:2]].any()  # nothing outside the mask

    clouds = load_clouds(clouds_path(tmp_path / "pred", 0))
    expected = maps_to_clouds(ref)
    assert len(clouds) == 4
    assert np.diff(clouds.offsets).tolist() == table.column("n_points").to_pylist()
    assert clouds.offsets[2] == expected.offsets[2]
    np.testing.assert_array_equal(clouds.layers[:clouds.offsets[2]], expected.layers)
    np.testing.assert_array_equal(clouds.posed_points[:clouds.offsets[2]], expected.posed_points)

    mtime = (tmp_path / "pred" / "part-00000.parquet").stat().st_mtime_ns
    predict_collection(checkpoint, tmp_path / "collection", tmp_path / "pred", device="cpu")  # complete: skipped
    assert (tmp_path / "pred" / "part-00000.parquet").stat().st_mtime_ns == mtime


def test_predict_checks_inputs(checkpoint, tmp_path):
    model, configs = load_predictor(checkpoint, device="cpu")
    assert configs.model == MODEL
    with pytest.raises(ValueError, match=r"features/mask: expected \(N, C, H, W\) and \(N, H, W\)"):
        predict_maps(model, np.zeros((2, 3, 16, 16), np.float32), np.zeros((2, 8, 8), bool))
    arrays = synthetic_samples(1, 32, seed=1)
    write_shard(tmp_path / "c", 0, [{"sample_id": "a", "status": "ok", "reason": ""}],
                {"rgb": arrays["rgb"], "mask": arrays["mask"]})
    with pytest.raises(ValueError, match="the model expects 16x16 crops"):
        predict_collection(checkpoint, tmp_path / "c", tmp_path / "o", device="cpu")
    torch.save({"format": "something-else"}, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="is not a 'bat3r-predictor/1' predictor checkpoint"):
        load_predictor(tmp_path / "bad.pt")
