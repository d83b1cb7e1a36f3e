"""The stage cache key: it changes with input content, config, code version and output location, nothing else."""
from __future__ import annotations

import hashlib
import threading
import time

import numpy as np
import pytest

from bat3r_core import shards
from bat3r_core.predictor.features import FeatureConfig
from tasks._cache import record_is_intact, shard_input_files, stage_cache_key
from tasks._devices import DevicePool


@pytest.fixture()
def shard(tmp_path):
    rows = [{"sample_id": "a", "status": "ok", "reason": ""}, {"sample_id": "b", "status": "ok", "reason": ""}]
    shards.write_shard(tmp_path / "in", 0, rows, {"x": np.arange(2.0)})
    return tmp_path / "in"


def _key(shard, config=None, code="v1", out=None, tmp=None):
    return stage_cache_key("features", code, shard_input_files(shard, 0), config or {"extractor": "rgb"},
                           out or shard.parent / "out" / "part-00000")


def test_key_is_stable_for_equal_inputs(shard, tmp_path):
    k1 = _key(shard)
    assert k1.startswith("features-") and len(k1) == len("features-") + 32
    # rewriting identical bytes (new mtime) and a relative output path to the same place keep the key
    time.sleep(0.01)
    shards.write_shard(shard, 0, shards.read_shard(shard, 0)[0], {"x": np.arange(2.0)})
    assert _key(shard) == k1
    # a config dataclass hashes like its mapping, key order does not matter
    cfg = FeatureConfig(extractor="rgb", batch_size=4)
    from bat3r_core.config_utils import to_mapping

    mapping = dict(reversed(list(to_mapping(cfg).items())))
    assert _key(shard, config=cfg) == _key(shard, config=mapping)


def test_key_changes_with_each_ingredient(shard, tmp_path):
    base = _key(shard)
    assert _key(shard, config={"extractor": "rgb", "batch_size": 2}) != base
    assert _key(shard, code="v2") != base
    assert _key(shard, out=tmp_path / "other" / "part-00000") != base
    assert _key(shard, out=tmp_path / "out" / "part-00001") != base
    assert stage_cache_key("render", "v1", shard_input_files(shard, 0), {"extractor": "rgb"},
                           tmp_path / "out" / "part-00000") != base
    # one changed value in the npz changes the key
    shards.write_shard(shard, 0, shards.read_shard(shard, 0)[0], {"x": np.array([0.0, 1.5])})
    assert _key(shard) != base


def test_key_matches_a_direct_reference(shard, tmp_path):
    files = shard_input_files(shard, 0)
    assert [f.name for f in files] == ["part-00000.parquet", "part-00000.npz"]
    out = tmp_path / "out" / "part-00000"
    h = hashlib.sha256()
    h.update(b"stage=features\0code=v1\0")
    for f in files:
        h.update(f"input={f.resolve()}:{hashlib.sha256(f.name.encode() + hashlib.sha256(f.read_bytes()).digest()).hexdigest()[:16]}\0"
                 .encode())
    h.update(b'config={"extractor":"rgb"}\0')
    h.update(f"output={out.resolve()}\0".encode())
    assert _key(shard, out=out) == f"features-{h.hexdigest()[:32]}"


def test_missing_input_still_gives_a_key_and_bad_arguments_raise(tmp_path):
    k = stage_cache_key("fit", "v1", [tmp_path / "nope.parquet"], {}, tmp_path / "out")
    assert k.startswith("fit-")
    with pytest.raises(ValueError, match="stage must be a non-empty string"):
        stage_cache_key("", "v1", [], {}, tmp_path)
    with pytest.raises(ValueError, match="code_version must be a non-empty string"):
        stage_cache_key("fit", "", [], {}, tmp_path)
    with pytest.raises(ValueError, match="config must be JSON-serialisable"):
        stage_cache_key("fit", "v1", [], {"w": float("inf")}, tmp_path)


def test_record_is_intact_detects_changed_and_missing_files(shard):
    from bat3r_core.runs import shard_record

    rec = shard_record("features", 0, shards.shard_paths(shard, 0))
    assert record_is_intact(rec)
    shards.write_shard(shard, 0, shards.read_shard(shard, 0)[0], {"x": np.array([9.0, 9.0])})
    assert not record_is_intact(rec)
    (shard / "part-00000.parquet").unlink()
    assert not record_is_intact(rec)


def test_device_pool_lends_each_device_to_one_holder():
    pool = DevicePool([0, 1])
    active: dict[int, int] = {0: 0, 1: 0}
    peak = {0: 0, 1: 0}
    total_peak = [0]
    lock = threading.Lock()

    def work():
        with pool.slot() as d:
            with lock:
                active[d] += 1
                peak[d] = max(peak[d], active[d])
                total_peak[0] = max(total_peak[0], sum(active.values()))
            time.sleep(0.02)
            with lock:
                active[d] -= 1

    threads = [threading.Thread(target=work) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert peak == {0: 1, 1: 1} and total_peak[0] == 2
    with DevicePool([]).slot() as d:
        assert d is None
    busy = DevicePool([3])
    with busy.slot() as d:
        assert d == 3
        with pytest.raises(TimeoutError, match=r"no free GPU among \[3\]"):
            with busy.slot(timeout=0.05):
                pass
    with pytest.raises(ValueError, match="devices must be distinct"):
        DevicePool([1, 1])
