"""The features task fits the DINOv2 PCA on every shard of its input folder, whichever shard's task runs first,
so a fan-out over shards gives the same PCA (and features) in any order."""
from __future__ import annotations

import numpy as np

from bat3r_core.config_utils import to_mapping
from bat3r_core.predictor.features import Dinov2Options, FeatureConfig, feature_stats, fit_pca_from_shards
from bat3r_core.predictor.synthetic import save_random_dinov2
from bat3r_core.shards import read_shard, write_shard
from tasks.features import extract_features_shard


def _write_crops(folder, seed: int) -> None:
    rng = np.random.default_rng(seed)
    for index in range(2):
        rgb = rng.integers(0, 256, (3, 32, 32, 3), np.uint8)
        mask = np.zeros((3, 32, 32), bool)
        mask[:, 6:26, 4 + 4 * index:28] = True
        rgb[~mask] = 0
        rows = [{"sample_id": f"s{index}-{i}", "status": "ok", "reason": ""} for i in range(3)]
        write_shard(folder, index, rows, {"rgb": rgb, "mask": mask})


def test_pca_is_fitted_on_all_shards_whatever_task_runs_first(tmp_path):
    model = save_random_dinov2(tmp_path / "dinov2", seed=1)
    _write_crops(tmp_path / "render", seed=0)
    grids = {}
    for order in ((1, 0), (0, 1)):
        cfg = FeatureConfig(extractor="dinov2", device="cpu", cache_dir=str(tmp_path / f"cache-{order[0]}"),
                            dinov2=Dinov2Options(model=model, input_size=32, channels=4))
        before = feature_stats().pca_fits
        for index in order:
            extract_features_shard.fn(str(tmp_path / "render"), index, str(tmp_path / f"feat-{order[0]}"),
                                      to_mapping(cfg))
        assert feature_stats().pca_fits == before + 1  # once, by the first task
        pca = fit_pca_from_shards([tmp_path / "render"], cfg)  # loaded: the one the tasks fitted
        assert pca.n_images == 6  # every image of both shards, not just the first task's three
        grids[order] = [read_shard(tmp_path / f"feat-{order[0]}", i)[1]["grid"] for i in (0, 1)]
    for a, b in zip(grids[(1, 0)], grids[(0, 1)]):
        np.testing.assert_array_equal(a, b)
