"""Predictor network shapes, shard dataset, overfitting, exact resume and 2-process DDP (gloo, CPU)."""
import dataclasses
import socket

import numpy as np
import pytest
import torch
import torch.multiprocessing as mp

from bat3r_core.config_utils import ConfigError
from bat3r_core.pointmaps import decode_float16
from bat3r_core.predictor.config import ModelConfig, TrainConfig
from bat3r_core.predictor.data import DeviceDataset, MixedDataset, ShardDataset, rgb_features
from bat3r_core.predictor.infer import load_predictor
from bat3r_core.predictor.network import DualPointMapNet
from bat3r_core.predictor.synthetic import synthetic_samples, write_synthetic_shards
from bat3r_core.predictor.train import CHECKPOINT_NAME, Trainer, WarmupCosine
from bat3r_core.shards import read_shard, write_shard

SMALL_MODEL = ModelConfig(resolution=16, layers=4, in_channels=3, base_channels=8, depth=2, two_stage=True)
SMALL_TRAIN = TrainConfig(steps=6, batch_size=2, grad_accum=2, lr=3e-3, warmup_steps=2, checkpoint_every=2,
                          loss="robust", grad_clip=1.0, seed=7, deterministic=True, shuffle_shards=1, log_every=1)


@pytest.fixture(scope="module")
def shards16(tmp_path_factory):
    folder = tmp_path_factory.mktemp("shards16")
    write_synthetic_shards(folder, 8, 16, shard_size=3, seed=1)  # shards of 3, 3, 2 samples
    return folder


# ---------------------------------------------------------------------------------------------- network
@pytest.mark.parametrize("two_stage", [True, False])
def test_network_output_shapes(two_stage):
    cfg = ModelConfig(resolution=16, layers=3, in_channels=5, base_channels=4, depth=2, two_stage=two_stage)
    out = DualPointMapNet(cfg)(torch.randn(2, 5, 16, 16), torch.ones(2, 16, 16, dtype=torch.bool))
    assert out.canonical_points.shape == (2, 16, 16, 3, 3)
    assert out.posed_points.shape == (2, 16, 16, 3, 3)
    for t in (out.occupancy_logits, out.canonical_confidence_logits, out.posed_confidence_logits):
        assert t.shape == (2, 16, 16, 3)


def test_two_stage_visible_canonical_map_comes_from_stage_one():
    torch.manual_seed(0)
    net = DualPointMapNet(SMALL_MODEL)
    out = net(torch.randn(1, 3, 16, 16), torch.ones(1, 16, 16, dtype=torch.bool))
    out.canonical_points[..., 0, :].sum().backward(retain_graph=True)
    assert all(p.grad is None or torch.count_nonzero(p.grad) == 0 for p in net.stage2.parameters())
    assert any(p.grad is not None and torch.count_nonzero(p.grad) > 0 for p in net.stage1.parameters())
    net.zero_grad()
    out.posed_points[..., 1, :].sum().backward()  # later layers see stage 1 through the conditioning
    assert any(p.grad is not None and torch.count_nonzero(p.grad) > 0 for p in net.stage1.parameters())


def test_network_input_checks():
    net = DualPointMapNet(SMALL_MODEL)
    with pytest.raises(ValueError, match=r"features: expected shape \(B, 3, 16, 16\), got \(1, 4, 16, 16\)"):
        net(torch.zeros(1, 4, 16, 16), torch.ones(1, 16, 16))
    with pytest.raises(ValueError, match=r"mask: expected shape \(1, 16, 16\)"):
        net(torch.zeros(1, 3, 16, 16), torch.ones(1, 8, 8))
    with pytest.raises(TypeError, match="config: expected ModelConfig"):
        DualPointMapNet({"resolution": 16})


# ---------------------------------------------------------------------------------------------- configs
def test_catalog_presets_build_and_paper_matches_reference():
    from bat3r_core.catalog import load_catalog

    catalog = load_catalog()
    for name in catalog.runs:
        catalog.model_config(name), catalog.train_config(name)
    model, train = catalog.model_config("paper"), catalog.train_config("paper")
    assert (model.layers, model.resolution, model.in_channels, model.two_stage) == (4, 160, 64, True)
    assert model.feature == "dinov2"
    assert (train.batch_size, train.steps, train.lr, train.warmup_steps, train.grad_accum, train.weight_decay) == \
        (12, 60000, 6e-4, 1000, 2, 0.01)
    assert train.loss == "robust" and train.grad_clip > 0
    assert train.betas[0] > 0.9 and train.betas[1] > 0.999
    with pytest.raises(ConfigError, match="resolution: expected a multiple of 2\\*\\*depth = 8, got 20"):
        ModelConfig(resolution=20, depth=3)


def test_warmup_then_cosine():
    f = WarmupCosine(warmup=4, total=14)
    assert [round(f(s), 6) for s in range(4)] == [0.2, 0.4, 0.6, 0.8]
    assert f(4) == pytest.approx(1.0)
    assert f(9) == pytest.approx(0.5)
    assert f(14) == pytest.approx(0.0, abs=1e-12)


# ---------------------------------------------------------------------------------------------- dataset
def test_dataset_targets_follow_the_shard_format(tmp_path):
    arrays = synthetic_samples(3, 16, seed=2)
    rows = [{"sample_id": f"s{i}", "status": "ok" if i != 1 else "failed", "reason": "" if i != 1 else "x"}
            for i in range(3)]
    write_shard(tmp_path, 0, rows, arrays)
    ds = ShardDataset(tmp_path)
    assert len(ds) == 2 and (ds.height, ds.layers, ds.channels) == (16, 4, 3)
    batch = ds.get_batch([0, 1])  # rows 0 and 2 (row 1 failed)
    _, a = read_shard(tmp_path, 0)
    P, Q = decode_float16(a["P"], a["Q"], a["occupancy"], a["object_depth"])
    for j, row in enumerate((0, 2)):
        occ = a["occupancy"][row]
        assert torch.equal(batch.targets.occupancy[j], torch.from_numpy(occ))
        rel = P[row].copy()
        rel[..., 2] -= a["object_depth"][row]
        rel[~occ] = 0
        np.testing.assert_allclose(batch.targets.posed_points[j].numpy(), rel, atol=2e-6)
        np.testing.assert_allclose(batch.targets.canonical_points[j].numpy(), Q[row], atol=0)
        expected = a["rgb"][row].astype(np.float32) / 255 * a["mask"][row][..., None]
        np.testing.assert_allclose(batch.features[j].numpy().transpose(1, 2, 0), expected, atol=1e-6)
    with pytest.raises(ValueError, match=r"rgb must be \(N, H, W, 3\) uint8"):
        rgb_features(a["rgb"].astype(np.float32), a["mask"])
    with pytest.raises(TypeError, match="mask must be bool, got uint8"):  # a 0/255 mask would scale the features
        rgb_features(a["rgb"], a["mask"].astype(np.uint8) * 255)


def test_dataset_streams_the_feature_shards_of_the_features_stage(tmp_path):
    """features_dir: the same batches as computing the features per batch, from the stored grids (rgb and a
    DINOv2-like coarse grid), row for row; a feature shard of other samples is refused, a missing one skipped."""
    from bat3r_core.predictor.features import FeatureConfig, extract_feature_shard, grid_features

    write_synthetic_shards(tmp_path / "s", 12, 16, shard_size=4, seed=5, with_head=False)
    for i in range(3):
        extract_feature_shard(tmp_path / "s", i, tmp_path / "f", FeatureConfig())
    computed, streamed = ShardDataset(tmp_path / "s"), ShardDataset(tmp_path / "s", features_dir=tmp_path / "f")
    assert len(streamed) == len(computed) == 12 and streamed.channels == 3
    a, b = computed.get_batch([0, 5, 11]), streamed.get_batch([0, 5, 11])
    assert torch.equal(a.features, b.features) and torch.equal(a.targets.posed_points, b.targets.posed_points)
    # a coarse grid (as DINOv2 stores) is upsampled and masked on the way in
    table, arrays = read_shard(tmp_path / "f", 1)
    coarse = np.random.default_rng(0).normal(size=(4, 5, 4, 4)).astype(np.float32)
    write_shard(tmp_path / "f", 1, table.to_pylist(), {"grid": coarse, "mask": arrays["mask"]})
    got = ShardDataset(tmp_path / "s", features_dir=tmp_path / "f").get_batch([4, 6]).features.numpy()
    np.testing.assert_array_equal(got, grid_features(coarse[[0, 2]], arrays["mask"][[0, 2]].astype(bool)))
    assert got.shape == (2, 5, 16, 16) and not got[:, :, ~arrays["mask"][0].astype(bool)][0].any()
    # a feature shard of other samples, and a missing one
    write_shard(tmp_path / "f", 2, [{**r, "sample_id": "other"} for r in table.to_pylist()], arrays)
    with pytest.raises(ValueError, match=r"features_dir: .*part-00002 holds samples \['other'"):
        ShardDataset(tmp_path / "s", features_dir=tmp_path / "f").get_batch([8])
    for suffix in (".parquet", ".npz"):
        (tmp_path / "f" / f"part-00002{suffix}").unlink()
    partial = ShardDataset(tmp_path / "s", features_dir=tmp_path / "f")
    assert len(partial) == 8 and partial.shards_without_features == [2]
    with pytest.raises(ValueError, match="feature_fn or features_dir"):
        ShardDataset(tmp_path / "s", rgb_features, features_dir=tmp_path / "f")


def test_held_and_mixed_sets_still_report_shards_without_features(tmp_path):
    """What the train task's record lists as ``shards_without_features`` survives holding the set on a device and
    mixing it with the canonical replay."""
    from bat3r_core.predictor.features import FeatureConfig, extract_feature_shard

    write_synthetic_shards(tmp_path / "s", 12, 16, shard_size=4, seed=5, with_head=False)
    for i in range(2):  # no feature shard for training shard 2
        extract_feature_shard(tmp_path / "s", i, tmp_path / "f", FeatureConfig())
    held = DeviceDataset(ShardDataset(tmp_path / "s", features_dir=tmp_path / "f"), "cpu")
    assert len(held) == 8 and held.shards_without_features == [2]
    assert MixedDataset([held, ShardDataset(tmp_path / "s", features_dir=tmp_path / "f")], [8, 4]
                        ).shards_without_features == [2, 2]


def test_epoch_order_is_a_seeded_permutation(shards16):
    ds = ShardDataset(shards16)
    a = ds.epoch_order(3, 0, shuffle_shards=1)
    assert sorted(a.tolist()) == list(range(8))
    assert np.array_equal(a, ds.epoch_order(3, 0, shuffle_shards=1))
    assert not np.array_equal(a, ds.epoch_order(3, 1, shuffle_shards=1))
    # shuffle_shards=1: each shard's samples stay contiguous
    shard_of = np.array([ds.locate(int(i))[0] for i in a])
    assert (np.diff(shard_of) != 0).sum() == 2


# ------------------------------------------------------------------------------------- canonical replay
@pytest.fixture(scope="module")
def replay16(tmp_path_factory):
    folder = tmp_path_factory.mktemp("replay16")
    write_synthetic_shards(folder, 10, 16, shard_size=4, seed=2)  # another set: shards of 4, 4, 2
    return folder


def test_mixed_dataset_takes_its_share_of_each_part_per_epoch(shards16, replay16):
    main, replay = ShardDataset(shards16), ShardDataset(replay16)
    mixed = MixedDataset([main, replay], [8, 3])
    assert len(mixed) == 11
    seen = []
    for epoch in range(4):
        order = mixed.epoch_order(5, epoch, shuffle_shards=1)
        assert np.array_equal(order, mixed.epoch_order(5, epoch, shuffle_shards=1))
        main_part, replay_part = order[order < 8], order[order >= 8] - 8
        assert sorted(main_part.tolist()) == list(range(8))  # every pseudo-label sample once per epoch
        assert len(replay_part) == 3 and len(set(replay_part.tolist())) == 3
        assert np.array_equal(replay_part, replay.epoch_order(6, epoch, shuffle_shards=1)[:3])
        seen.append(set(replay_part.tolist()))
    assert len(set.union(*seen)) > 3  # a different share of the canonical set each epoch
    # a batch across both parts holds exactly the samples asked for, in the order asked
    order = mixed.epoch_order(5, 0, shuffle_shards=1)
    batch = mixed.get_batch(order[:6])
    for row, index in enumerate(order[:6]):
        part, local = (main, index) if index < 8 else (replay, index - 8)
        single = part.get_batch([int(local)])
        assert torch.equal(batch.features[row], single.features[0])
        assert all(torch.equal(t[row], s[0]) for t, s in zip(batch.targets, single.targets))


def test_mixed_dataset_rejects_mismatched_parts(shards16, replay16, tmp_path):
    write_synthetic_shards(tmp_path / "s8", 4, 8, shard_size=4, seed=3)
    with pytest.raises(ValueError, match=r"part 1 \(.*s8\) has \(height, width, layers, channels\) \(8, 8, 4, 3\)"):
        MixedDataset([ShardDataset(shards16), ShardDataset(tmp_path / "s8")], [8, 4])
    with pytest.raises(ValueError, match=r"take of part 1 \(.*replay16.*\): expected 1 ≤ take ≤ 10, got 11"):
        MixedDataset([ShardDataset(shards16), ShardDataset(replay16)], [8, 11])


def test_training_set_mixes_canonical_replay_by_ratio(shards16, replay16):
    from bat3r_core.predictor.features.config import FeatureConfig
    from bat3r_core.specs import TrainSpec
    from tasks.train import training_set

    def spec(ratio):
        return TrainSpec(model=SMALL_MODEL, train=dataclasses.replace(SMALL_TRAIN, canonical_replay=ratio),
                         features=FeatureConfig())

    plain = training_set(str(shards16), spec(0.0), "cpu", replay_dir=str(replay16))
    assert isinstance(plain, ShardDataset) and len(plain) == 8  # 0: the paper's recipe, no replay
    half = training_set(str(shards16), spec(0.5), "cpu", replay_dir=str(replay16))
    assert isinstance(half, MixedDataset) and half.takes == [8, 4]
    assert training_set(str(shards16), spec(3.0), "cpu", replay_dir=str(replay16)).takes == [8, 10]  # all of it
    with pytest.raises(ConfigError, match="canonical_replay: expected >= 0, got -1"):
        dataclasses.replace(SMALL_TRAIN, canonical_replay=-1.0)


def test_training_on_a_mixed_set_resumes_exactly(shards16, replay16, tmp_path):
    def mixed():
        return MixedDataset([ShardDataset(shards16, cache_shards=1), ShardDataset(replay16, cache_shards=1)], [8, 4])

    full = Trainer(mixed(), SMALL_MODEL, SMALL_TRAIN, tmp_path / "full")
    full.train()
    run = Trainer(mixed(), SMALL_MODEL, SMALL_TRAIN, tmp_path / "killed")
    run.train(until_step=5)
    del run
    resumed = Trainer(mixed(), SMALL_MODEL, SMALL_TRAIN, tmp_path / "killed")
    resumed.train()
    reference, got = _state(full), _state(resumed)
    assert all(torch.equal(got[k], reference[k]) for k in reference)
    alone = Trainer(ShardDataset(shards16, cache_shards=1), SMALL_MODEL, SMALL_TRAIN, tmp_path / "alone")
    alone.train()
    assert not all(torch.equal(_state(alone)[k], reference[k]) for k in reference)  # the replay changed training


# ---------------------------------------------------------------------------------------------- training
def _state(trainer):
    return {k: v.clone() for k, v in trainer.model.state_dict().items()}


def test_resume_after_kill_reproduces_uninterrupted_weights(shards16, tmp_path):
    full = Trainer(ShardDataset(shards16, cache_shards=1), SMALL_MODEL, SMALL_TRAIN, tmp_path / "full")
    final_path = full.train()
    reference = _state(full)

    run = Trainer(ShardDataset(shards16, cache_shards=1), SMALL_MODEL, SMALL_TRAIN, tmp_path / "killed")
    run.train(until_step=5)  # checkpoint at step 4, step 5 is lost with the "killed" process
    assert (tmp_path / "killed" / CHECKPOINT_NAME).is_file()
    del run
    resumed = Trainer(ShardDataset(shards16, cache_shards=1), SMALL_MODEL, SMALL_TRAIN, tmp_path / "killed")
    assert resumed.step == 4
    resumed.train()
    got = _state(resumed)
    assert got.keys() == reference.keys()
    assert all(torch.equal(got[k], reference[k]) for k in reference)
    assert not all(torch.equal(reference[k], v) for k, v in
                   DualPointMapNet(SMALL_MODEL).state_dict().items())  # training changed the weights
    for a, b in zip(full.optimizer.state_dict()["state"].values(), resumed.optimizer.state_dict()["state"].values()):
        assert torch.equal(a["exp_avg"], b["exp_avg"]) and torch.equal(a["exp_avg_sq"], b["exp_avg_sq"])

    model, configs = load_predictor(final_path, device="cpu")
    assert configs.model == SMALL_MODEL and configs.train == SMALL_TRAIN
    assert all(torch.equal(model.state_dict()[k], reference[k]) for k in reference)


def test_a_finished_model_exported_again_has_the_same_bytes(shards16, tmp_path):
    """A train stage re-run on a finished checkpoint (its cache invalidated by a code change) exports predictor.pt
    again: the bytes must not change, or the content hashes of every later stage change with them and the next
    iteration retrains from scratch."""
    first = Trainer(ShardDataset(shards16, cache_shards=1), SMALL_MODEL, SMALL_TRAIN, tmp_path / "t").train()
    before = first.read_bytes()
    again = Trainer(ShardDataset(shards16, cache_shards=1), SMALL_MODEL, SMALL_TRAIN, tmp_path / "t")
    assert again.step == SMALL_TRAIN.steps
    assert again.train() == first and first.read_bytes() == before


def test_a_stop_request_ends_training_with_a_checkpoint_of_its_step_and_resume_is_exact(shards16, tmp_path):
    """A stopped run (``bat3r_core.stopping``: SIGTERM, a cancel, Ctrl-C) writes ``checkpoint.pt`` at the step it
    reached — off the ``checkpoint_every`` grid too — and the rerun ends with the uninterrupted run's weights."""
    from bat3r_core.stopping import StopRequested, clear_stop_request, request_stop, stop_requested

    reference = Trainer(ShardDataset(shards16, cache_shards=1), SMALL_MODEL, SMALL_TRAIN, tmp_path / "full")
    reference.train()

    def stop_at_step_3(report):
        if report["step"] == 3:
            request_stop("the test")

    stopped = Trainer(ShardDataset(shards16, cache_shards=1), SMALL_MODEL, SMALL_TRAIN, tmp_path / "stopped",
                      progress=stop_at_step_3, progress_interval_s=0.0)
    try:
        with pytest.raises(StopRequested, match=r"training in .*stopped at step 3 of 6 .*\(the test\)"):
            stopped.train()
        assert stopped.step == 3 and not (tmp_path / "stopped" / "predictor.pt").exists()
        # a StopRequested is no Exception: no per-sample or per-shard handler takes it for a bad input
        assert not issubclass(StopRequested, Exception)
        with pytest.raises(StopRequested):  # it stays requested until withdrawn
            Trainer(ShardDataset(shards16, cache_shards=1), SMALL_MODEL, SMALL_TRAIN, tmp_path / "other").train()
    finally:
        clear_stop_request()
    assert not stop_requested()
    resumed = Trainer(ShardDataset(shards16, cache_shards=1), SMALL_MODEL, SMALL_TRAIN, tmp_path / "stopped")
    assert resumed.step == 3  # checkpoint_every is 2: only the stop wrote step 3
    resumed.train()
    want, got = _state(reference), _state(resumed)
    assert all(torch.equal(got[k], want[k]) for k in want)


def test_resume_rejects_a_different_config(shards16, tmp_path):
    Trainer(ShardDataset(shards16), SMALL_MODEL, SMALL_TRAIN, tmp_path).train(until_step=2)
    other = TrainConfig(**{**SMALL_TRAIN.__dict__, "lr": 1e-3})
    with pytest.raises(ValueError, match="train_config differs"):
        Trainer(ShardDataset(shards16), SMALL_MODEL, other, tmp_path)


def test_warm_start_begins_from_the_given_weights_and_resumes_from_its_own_checkpoint(shards16, tmp_path):
    first = Trainer(ShardDataset(shards16), SMALL_MODEL, SMALL_TRAIN, tmp_path / "phi0")
    phi0 = first.train()
    source = _state(first)
    cold = _state(Trainer(ShardDataset(shards16), SMALL_MODEL, SMALL_TRAIN, tmp_path / "cold"))
    warm = Trainer(ShardDataset(shards16), SMALL_MODEL, SMALL_TRAIN, tmp_path / "phi1", init_from=phi0)
    assert warm.step == 0
    assert all(torch.equal(v, source[k]) for k, v in warm.model.state_dict().items())
    assert not all(torch.equal(v, cold[k]) for k, v in warm.model.state_dict().items())
    warm.train(until_step=4)  # checkpoint at step 4; a rerun resumes it and ignores init_from
    resumed = Trainer(ShardDataset(shards16), SMALL_MODEL, SMALL_TRAIN, tmp_path / "phi1", init_from=phi0)
    assert resumed.step == 4
    assert all(torch.equal(v, warm.model.state_dict()[k]) for k, v in resumed.model.state_dict().items())


def test_warm_start_rejects_another_architecture_and_missing_files(shards16, tmp_path):
    phi0 = Trainer(ShardDataset(shards16), SMALL_MODEL, SMALL_TRAIN, tmp_path / "phi0").train()
    other = ModelConfig(**{**SMALL_MODEL.__dict__, "base_channels": 4})
    with pytest.raises(ValueError, match="init_from: .* has model_config"):
        Trainer(ShardDataset(shards16), other, SMALL_TRAIN, tmp_path / "other", init_from=phi0)
    with pytest.raises(FileNotFoundError, match="init_from: no such file"):
        Trainer(ShardDataset(shards16), SMALL_MODEL, SMALL_TRAIN, tmp_path / "x", init_from=tmp_path / "nope.pt")


def test_trainer_checks_dataset_against_model(shards16, tmp_path):
    with pytest.raises(ValueError, match=r"dataset: expected \(H, W, K, C\) = \(32, 32, 4, 3\)"):
        Trainer(ShardDataset(shards16), ModelConfig(resolution=32, depth=2), SMALL_TRAIN, tmp_path)


def _posed_error(trainer, batch) -> float:
    """Mean posed-point error (metres) of the occupied entries of ``batch`` under the trainer's model."""
    with torch.no_grad():
        out = trainer.model(batch.features, batch.mask)
    occ = batch.targets.occupancy
    return (out.posed_points - batch.targets.posed_points).norm(dim=-1)[occ].mean().item()


def test_overfits_eight_samples_below_two_centimetres(tmp_path):
    write_synthetic_shards(tmp_path / "s", 8, 32, shard_size=8, seed=0, with_head=False)
    ds = ShardDataset(tmp_path / "s")
    model_cfg = ModelConfig(resolution=32, base_channels=16, depth=2, two_stage=False)
    train_cfg = TrainConfig(steps=400, batch_size=8, lr=3e-3, warmup_steps=20, checkpoint_every=1000,
                            betas=(0.9, 0.999), log_every=100)
    trainer = Trainer(ds, model_cfg, train_cfg, tmp_path / "out")
    batch = ds.get_batch(range(8))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # 1 thread is as fast on 2 shared cores and much faster when they are busy
    try:
        before = _posed_error(trainer, batch)
        trainer.train()
        after = _posed_error(trainer, batch)
    finally:
        torch.set_num_threads(threads)
    assert before > 0.1
    assert after < 0.02, f"posed-map error of occupied entries {after * 100:.2f} cm after {train_cfg.steps} steps"


@pytest.mark.blender
def test_overfits_eight_rendered_toy_samples_below_two_centimetres(tmp_path, toy_rig, torch_single_thread):
    """The acceptance check on real data: 8 Blender renders of the toy with their ray-cast labels (32x32)."""
    from bat3r_core.datasets import canonical_jobs
    from bat3r_core.render.config import RenderConfig, SceneAssets
    from bat3r_core.render.runner import render_shard
    from bat3r_core.rig_io import save_rig_glb
    from bat3r_core.toy import TOY_BODY_FRAME

    glb = save_rig_glb(toy_rig, tmp_path / "toy.glb")
    jobs = canonical_jobs(toy_rig, 8, seed=3, body_frame_spec=TOY_BODY_FRAME, resolution=32)
    config = RenderConfig(resolution=32, samples=2, recycle_every=64, timeout_s=30.0)
    render_shard(jobs, SceneAssets(asset=str(glb)), tmp_path / "s", 0, config, rig=toy_rig)
    ds = ShardDataset(tmp_path / "s")
    assert len(ds) == 8
    trainer = Trainer(ds, ModelConfig(resolution=32, base_channels=24, depth=2, two_stage=False),
                      TrainConfig(steps=1500, batch_size=8, lr=3e-3, warmup_steps=20, checkpoint_every=10_000,
                                  betas=(0.9, 0.999), log_every=500), tmp_path / "out")
    batch = ds.get_batch(range(8))
    before = _posed_error(trainer, batch)
    trainer.train()
    after = _posed_error(trainer, batch)
    assert before > 0.3
    assert after < 0.02, f"posed-map error of occupied entries {after * 100:.2f} cm after 1500 steps"


# ---------------------------------------------------------------------------------------------- DDP
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ddp_worker(rank, world, port, shards, out, result_dir):
    import os

    import torch.distributed as dist

    os.environ.update({"RANK": str(rank), "WORLD_SIZE": str(world), "LOCAL_RANK": str(rank),
                       "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port)})
    torch.set_num_threads(1)
    cfg = TrainConfig(**{**SMALL_TRAIN.__dict__, "steps": 3, "batch_size": 1, "checkpoint_every": 2})
    trainer = Trainer(ShardDataset(shards), SMALL_MODEL, cfg, out)
    trainer.train()
    torch.save({k: v.clone() for k, v in trainer.model.state_dict().items()}, f"{result_dir}/rank{rank}.pt")
    dist.destroy_process_group()


def test_ddp_two_processes_gloo_keep_identical_weights(shards16, tmp_path):
    mp.spawn(_ddp_worker, args=(2, _free_port(), str(shards16), str(tmp_path / "out"), str(tmp_path)), nprocs=2,
             join=True)
    a = torch.load(tmp_path / "rank0.pt", weights_only=True)
    b = torch.load(tmp_path / "rank1.pt", weights_only=True)
    assert all(torch.equal(a[k], b[k]) for k in a)
    torch.manual_seed(SMALL_TRAIN.seed)
    init = DualPointMapNet(SMALL_MODEL).state_dict()
    assert not all(torch.equal(a[k], init[k]) for k in a)
    model, _ = load_predictor(tmp_path / "out" / "predictor.pt", device="cpu")
    assert all(torch.equal(model.state_dict()[k], a[k]) for k in a)
    ckpt = torch.load(tmp_path / "out" / CHECKPOINT_NAME, weights_only=True)
    assert (ckpt["step"], ckpt["world_size"]) == (3, 2)


def test_training_reports_its_progress_at_a_steady_interval(shards16, tmp_path, caplog, monkeypatch):
    import itertools

    from bat3r_core.predictor import train as training
    from bat3r_core.predictor.train import progress_line

    # a steady clock (0.1 s per reading): the ETA's countdown must not depend on how busy the machine is
    clock = itertools.count(step=0.1)
    monkeypatch.setattr(training.time, "perf_counter", lambda: next(clock))
    reports = []
    trainer = Trainer(ShardDataset(shards16), SMALL_MODEL, SMALL_TRAIN, tmp_path / "a", progress=reports.append,
                      progress_interval_s=0.0)
    trainer.train()
    assert [r["step"] for r in reports] == list(range(1, SMALL_TRAIN.steps + 1))  # interval 0: every step
    assert all(r["steps"] == SMALL_TRAIN.steps and r["steps_per_s"] > 0 for r in reports)
    assert reports[-1]["eta_s"] == 0.0 and reports[-1]["fraction"] == 1.0
    assert reports[0]["eta_s"] > reports[-2]["eta_s"] > 0
    line = progress_line({"step": 1200, "steps": 5000, "fraction": 0.24, "steps_per_s": 9.44, "loss": -2.1814,
                          "eta_s": 402.5})
    assert line == "step 1200/5000 (24%), 9.4 steps/s, loss -2.18, ETA 6.7 min"
    # the default: an INFO line after the last step (the interval is longer than this run)
    with caplog.at_level("INFO", logger="bat3r_core.predictor.train"):
        Trainer(ShardDataset(shards16), SMALL_MODEL, SMALL_TRAIN, tmp_path / "b").train()
    lines = [r.getMessage() for r in caplog.records if r.name == "bat3r_core.predictor.train"]
    assert lines == [f"training step {SMALL_TRAIN.steps}/{SMALL_TRAIN.steps} (100%), " + lines[0].split(", ", 1)[1]]
    assert "ETA 0 s" in lines[0]
