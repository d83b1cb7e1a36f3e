"""benchmarks/gpu_rounds.py: the compact pack of training shards and the split training it carries to a GPU machine."""
from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

import gpu_rounds  # noqa: E402

from bat3r_core import shards  # noqa: E402
from bat3r_core.predictor.config import ModelConfig, TrainConfig  # noqa: E402
from bat3r_core.predictor.data import ShardDataset, rgb_features  # noqa: E402
from bat3r_core.predictor.features import FeatureConfig  # noqa: E402
from bat3r_core.predictor.infer import load_predictor  # noqa: E402
from bat3r_core.predictor.synthetic import synthetic_samples, write_synthetic_shards  # noqa: E402


def test_pack_round_trip_keeps_every_sample_within_half_a_millimetre(tmp_path):
    write_synthetic_shards(tmp_path / "src", 10, 16, shard_size=4, seed=3)  # shards of 4, 4, 2
    n = gpu_rounds.pack_folder(tmp_path / "src", tmp_path / "pack")
    assert n == 10
    assert gpu_rounds.unpack_folder(tmp_path / "pack", tmp_path / "dst") == 10
    assert shards.list_shards(tmp_path / "dst") == shards.list_shards(tmp_path / "src") == [0, 1, 2]
    a = ShardDataset(tmp_path / "src", rgb_features)
    b = ShardDataset(tmp_path / "dst", rgb_features)
    ia, ib = a.get_batch(np.arange(10)), b.get_batch(np.arange(10))
    assert torch.equal(ia.features, ib.features) and torch.equal(ia.mask, ib.mask)
    assert torch.equal(ia.targets.occupancy, ib.targets.occupancy)
    occ = ia.targets.occupancy
    for name in ("canonical_points", "posed_points"):
        x, y = getattr(ia.targets, name), getattr(ib.targets, name)
        assert float((x[occ] - y[occ]).abs().max()) <= 5e-4
        assert float(y[~occ].abs().max()) == 0.0
    # the pack is much smaller than the shards it holds
    size = lambda d: sum(p.stat().st_size for p in d.iterdir())  # noqa: E731
    assert size(tmp_path / "pack") < 0.25 * size(tmp_path / "src")


def test_pack_refuses_absolute_posed_points_with_the_array_and_the_loss():
    arrays = synthetic_samples(2, 16, seed=0)
    arrays = {k: np.asarray(v) for k, v in arrays.items()}
    absolute = arrays["P"].astype(np.float32).copy()
    absolute[..., 2] += 5.3 * arrays["occupancy"]  # camera-frame depth, not relative to the object depth
    with pytest.raises(ValueError, match=r"shard.npz: array 'P' loses .* mm in float16"):
        gpu_rounds.pack_arrays({**arrays, "P": absolute}, source="shard.npz")
    with pytest.raises(ValueError, match=r"x.npz: not a training shard \(missing arrays \['occupancy'"):
        gpu_rounds.pack_arrays({"rgb": arrays["rgb"]}, source="x.npz")


def test_train_runs_phi0_and_equal_step_rounds_from_it(tmp_path):
    write_synthetic_shards(tmp_path / "canonical", 8, 16, shard_size=4, seed=1, with_head=False)
    write_synthetic_shards(tmp_path / "posed", 8, 16, shard_size=4, seed=2)
    pack = tmp_path / "pack"
    for name, folder in (("canonical", "canonical"), ("oracle", "posed")):
        gpu_rounds.pack_folder(tmp_path / folder, pack / name)
    model = ModelConfig(resolution=16, depth=2, base_channels=4, two_stage=False)
    train = TrainConfig(steps=3, batch_size=2, warmup_steps=1, checkpoint_every=2)
    plan = {"format": gpu_rounds.PACK_FORMAT, "run_name": "t", "preset": "tiny", "overrides": {}, "seed": 0,
            "samples": {"canonical": 8, "oracle": 8}, "model": dataclasses.asdict(model),
            "train": dataclasses.asdict(train), "features": dataclasses.asdict(FeatureConfig())}
    (pack / "plan.json").write_text(json.dumps(plan))
    out = tmp_path / "out"
    gpu_rounds.main(["train", "--pack", str(pack), "--out", str(out), "--work", str(tmp_path / "work"),
                     "--phi0-steps", "4", "--round-steps", "2", "--batch-size", "2"])
    timings = json.loads((out / "timings.json").read_text())
    assert timings["phi0"]["steps"] == 4 and timings["round_steps"] == 2
    assert timings["control"]["steps"] == timings["oracle"]["steps"] == 2 and timings["batch_size"] == 2
    phi0, _ = load_predictor(out / "phi0.pt", "cpu")
    nets = {name: load_predictor(out / f"{name}.pt", "cpu")[0] for name in ("control", "oracle")}
    w0 = torch.cat([p.detach().flatten() for p in phi0.parameters()])
    for name, net in nets.items():
        w = torch.cat([p.detach().flatten() for p in net.parameters()])
        assert w.shape == w0.shape
        # two warm-started steps from Φ₀: close to it, but moved (trained from Φ₀, not from scratch or not at all)
        assert 0 < float((w - w0).abs().max()) < 0.05, name
    # the control and the oracle saw different data
    wc = torch.cat([p.detach().flatten() for p in nets["control"].parameters()])
    wo = torch.cat([p.detach().flatten() for p in nets["oracle"].parameters()])
    assert not torch.equal(wc, wo)
    # a second call with Φ₀ given trains only the named rounds, for the same steps
    gpu_rounds.main(["train", "--pack", str(pack), "--out", str(tmp_path / "out2"), "--work", str(tmp_path / "w2"),
                     "--phi0", str(out / "phi0.pt"), "--round-steps", "2", "--rounds", "oracle"])
    assert sorted(p.name for p in (tmp_path / "out2").iterdir()) == ["oracle.pt", "timings.json"]
    again = torch.cat([p.detach().flatten() for p in load_predictor(tmp_path / "out2" / "oracle.pt", "cpu")[0]
                       .parameters()])
    assert torch.allclose(again, wo, atol=1e-6)  # same Φ₀, data, seed and steps: the same round on CPU
    # a loop pack of a run with canonical replay carries the canonical renders as set `replay`: the loop round trains
    # on its renders mixed with as many canonical ones (train.canonical_replay = 1), as the flow's iteration does,
    # and the replayed set is no round of its own
    loop_pack = tmp_path / "loop_pack"
    for name, folder in (("loop1", "posed"), (gpu_rounds.REPLAY, "canonical")):
        gpu_rounds.pack_folder(tmp_path / folder, loop_pack / name)
    loop_plan = {**plan, "samples": {"loop1": 8, gpu_rounds.REPLAY: 8},
                 "train": {**plan["train"], "canonical_replay": 1.0}}
    (loop_pack / "plan.json").write_text(json.dumps(loop_plan))
    gpu_rounds.main(["train", "--pack", str(loop_pack), "--out", str(tmp_path / "out3"), "--work",
                     str(tmp_path / "w3"), "--phi0", str(out / "phi0.pt"), "--round-steps", "2"])
    assert sorted(p.name for p in (tmp_path / "out3").iterdir()) == ["loop1.pt", "timings.json"]
    state = torch.load(tmp_path / "w3" / "loop1" / "checkpoint.pt", map_location="cpu", weights_only=True)
    assert state["n_samples"] == 16  # an epoch: the 8 loop renders and 8 canonical ones
    wl = torch.cat([p.detach().flatten() for p in load_predictor(tmp_path / "out3" / "loop1.pt", "cpu")[0]
                    .parameters()])
    assert not torch.allclose(wl, wo, atol=1e-6)  # the same renders without the canonical ones train the oracle's


def test_device_dataset_gives_the_source_batches_and_the_same_training(tmp_path):
    from bat3r_core.predictor.data import DeviceDataset
    from bat3r_core.predictor.train import Trainer

    write_synthetic_shards(tmp_path / "s", 10, 16, shard_size=4, seed=4)
    source = ShardDataset(tmp_path / "s", rgb_features, cache_shards=1)
    held = DeviceDataset(source, "cpu", chunk=3)
    assert len(held) == 10 and (held.height, held.width, held.layers, held.channels) == (16, 16, 4, 3)
    assert np.array_equal(held.epoch_order(7, 2, 2), source.epoch_order(7, 2, 2))
    idx = [9, 0, 4, 4, 7]
    a, b = source.get_batch(idx), held.get_batch(np.array(idx))
    assert torch.equal(a.features, b.features) and torch.equal(a.mask, b.mask)
    for x, y in zip(a.targets, b.targets):
        assert torch.equal(x, y)
    model = ModelConfig(resolution=16, depth=2, base_channels=4, two_stage=False)
    train = TrainConfig(steps=3, batch_size=2, warmup_steps=1, checkpoint_every=5)
    weights = []
    for name, data in (("shards", source), ("held", held)):
        Trainer(data, model, train, tmp_path / name, device="cpu", progress=None).train()
        net, _ = load_predictor(tmp_path / name / "predictor.pt", "cpu")
        weights.append(torch.cat([p.detach().flatten() for p in net.parameters()]))
    assert torch.equal(weights[0], weights[1])


def test_save_half_halves_the_file_and_loads_as_a_predictor(tmp_path):
    write_synthetic_shards(tmp_path / "s", 4, 16, shard_size=4, seed=4)
    from bat3r_core.predictor.train import Trainer

    model = ModelConfig(resolution=16, depth=2, base_channels=8, two_stage=False)
    full = Trainer(ShardDataset(tmp_path / "s"), model, TrainConfig(steps=1, batch_size=2), tmp_path / "t",
                   device="cpu", progress=None).train()
    half = gpu_rounds.save_half(full, tmp_path / "half.pt")
    assert half.stat().st_size < 0.6 * full.stat().st_size
    a, _ = load_predictor(full, "cpu")
    b, _ = load_predictor(half, "cpu")
    for (k, x), (_, y) in zip(a.state_dict().items(), b.state_dict().items()):
        assert y.dtype == x.dtype, k
        assert torch.allclose(x, y, rtol=1e-3, atol=1e-4), k


def test_hold_on_device_keeps_shards_on_cpu_and_when_mirroring(tmp_path, monkeypatch):
    from bat3r_core.predictor import data as D

    write_synthetic_shards(tmp_path / "s", 4, 16, shard_size=4, seed=4)
    source = ShardDataset(tmp_path / "s", rgb_features)
    assert D.DeviceDataset.nbytes(source) == 4 * 16 * 16 * (4 * 3 + 25 * 4 + 1)
    held = D.DeviceDataset(source, "cpu")
    stored = sum(t.numel() * t.element_size() for t in (held._features, held._mask, *held._targets))
    assert stored == D.DeviceDataset.nbytes(source)
    assert D.hold_on_device(source, "cpu") is source
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert D.hold_on_device(source, None) is source
    # a CUDA device (its free memory reported as plenty) holds it unless samples are mirrored or it does not fit
    made = []
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device: (10 * D.DeviceDataset.nbytes(source), 0))
    monkeypatch.setattr(D, "DeviceDataset", type("Fake", (), {"__init__": lambda self, s, d: made.append(d),
                                                             "nbytes": staticmethod(held.nbytes)}))
    assert D.hold_on_device(source, "cuda:1", mirror_probability=0.5) is source and not made
    assert not isinstance(D.hold_on_device(source, "cuda:1"), ShardDataset) and made == [torch.device("cuda:1")]
    assert D.hold_on_device(source, "cuda:0", max_fraction=0.05) is source and len(made) == 1
