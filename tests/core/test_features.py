"""Feature extractors: rgb, the DINOv2 path end to end with a tiny random model, PCA and feature caches."""
from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from bat3r_core.predictor.features import (
    Dinov2Options, FeatureConfig, extract_feature_shard, extract_features, feature_stats, fit_pca_from_shards,
    grid_features,
    get_extractor, load_pca, make_feature_fn,
)
from bat3r_core.shards import read_shard, write_shard

R = 32  # crop resolution of these tests


def _save_tiny_dinov2(folder, seed: int) -> None:
    from bat3r_core.predictor.synthetic import save_random_dinov2

    save_random_dinov2(folder, seed=seed, patch_size=8, image_size=32)


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory):
    folder = tmp_path_factory.mktemp("dinov2_tiny")
    _save_tiny_dinov2(folder, seed=0)
    return folder


def _crops(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """n masked crops (R x R) with an ellipse of random size and position as foreground."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:R, 0:R] + 0.5
    rgb = rng.integers(0, 256, (n, R, R, 3), np.uint8)
    mask = np.zeros((n, R, R), bool)
    for i in range(n):
        cx, cy = rng.uniform(12, 20, 2)
        a, b = rng.uniform(8, 13, 2)
        mask[i] = ((xx - cx) / a) ** 2 + ((yy - cy) / b) ** 2 <= 1
    rgb[~mask] = 0
    return rgb, mask


def _cfg(model, cache_dir, **dino) -> FeatureConfig:
    return FeatureConfig(extractor="dinov2", batch_size=4, device="cpu", cache_dir=str(cache_dir),
                         dinov2=Dinov2Options(**{"model": str(model), "input_size": 32, "channels": 8, **dino}))


def _reference_tokens(model_dir, rgb, mask, input_size):
    """Slow reference: per image, normalise by hand, run the model, keep patch tokens and foreground patches."""
    from transformers import Dinov2Model

    net = Dinov2Model.from_pretrained(str(model_dir), local_files_only=True).eval()
    g = input_size // 8
    toks, fgs = [], []
    for i in range(len(rgb)):
        x = torch.tensor(rgb[i], dtype=torch.float32).permute(2, 0, 1)[None] / 255.0
        if input_size != R:
            x = F.interpolate(x, size=(input_size, input_size), mode="bilinear", align_corners=False)
        for c, (m, s) in enumerate(zip((0.485, 0.456, 0.406), (0.229, 0.224, 0.225))):
            x[:, c] = (x[:, c] - m) / s
        with torch.no_grad():
            h = net(pixel_values=x).last_hidden_state[0, 1:]  # drop the CLS token
        toks.append(h.reshape(g, g, -1).numpy())
        cell = R // g
        fgs.append(mask[i].reshape(g, cell, g, cell).mean(axis=(1, 3)) >= 0.5)
    return np.stack(toks), np.stack(fgs)


# ---------------------------------------------------------------------------------------------------------- rgb
def test_rgb_extractor_matches_reference():
    rgb, mask = _crops(3, 0)
    rgb[0, 5, 5] = 200  # a background pixel with colour must still come out 0
    mask[0, 5, 5] = False
    out = extract_features("rgb", rgb, mask, FeatureConfig())
    assert out.shape == (3, 3, R, R) and out.dtype == np.float32
    ref = np.zeros_like(out)
    for n in range(3):
        for i in range(R):
            for j in range(R):
                if mask[n, i, j]:
                    ref[n, :, i, j] = rgb[n, i, j] / 255.0
    np.testing.assert_allclose(out, ref, atol=1e-7)
    fn = make_feature_fn(FeatureConfig())
    np.testing.assert_array_equal(fn(rgb, mask), out)
    t = fn(torch.from_numpy(rgb), torch.from_numpy(mask))
    assert isinstance(t, torch.Tensor) and torch.equal(t, torch.from_numpy(out))


def test_input_checks():
    rgb, mask = _crops(2, 1)
    with pytest.raises(ValueError, match=r"rgb must be \(N, H, W, 3\) uint8, got \(2, 32, 32, 3\) float32"):
        extract_features("rgb", rgb.astype(np.float32), mask)
    with pytest.raises(ValueError, match=r"mask must have shape \(2, 32, 32\)"):
        extract_features("rgb", rgb, mask[:1])
    with pytest.raises(TypeError, match="mask must be bool, got uint8"):
        extract_features("rgb", rgb, mask.astype(np.uint8))
    with pytest.raises(ValueError, match=r"unknown feature extractor 'sd'; registered: \['dinov2', 'rgb'\]"):
        extract_features("sd", rgb, mask)
    with pytest.raises(ValueError, match="dinov2.channels must be >= 1, got 0"):
        Dinov2Options(channels=0)
    with pytest.raises(ValueError, match="batch_size must be >= 1, got 0"):
        FeatureConfig(batch_size=0)
    with pytest.raises(ValueError, match="device must be 'auto', 'cpu', 'cuda' or 'cuda:N', got 'gpu0'"):
        extract_features("dinov2", rgb, mask, FeatureConfig(device="gpu0", dinov2=Dinov2Options(model="x")))


# ------------------------------------------------------------------------------------------------------- dinov2
def test_dinov2_end_to_end_pca_and_cache(tiny_model, tmp_path):
    from sklearn.decomposition import PCA

    cache = tmp_path / "cache"
    cfg = _cfg(tiny_model, cache)
    rgb, mask = _crops(6, 2)
    s0 = feature_stats()
    feats = extract_features("dinov2", rgb, mask, cfg)
    s1 = feature_stats()
    assert feats.shape == (6, 8, R, R) and feats.dtype == np.float32 and np.isfinite(feats).all()
    assert (feats.transpose(0, 2, 3, 1)[~mask] == 0).all()
    assert np.abs(feats).max() > 0.1
    assert s1.pca_fits == s0.pca_fits + 1 and s1.cache_misses == s0.cache_misses + 6

    # the PCA is saved with its config hash and agrees with scikit-learn on the reference foreground tokens
    pca_path = get_extractor("dinov2").pca_path(cfg)
    assert pca_path.is_file() and pca_path.parent == cache / "pca"
    pca = load_pca(pca_path)
    tokens, fg = _reference_tokens(tiny_model, rgb, mask, 32)
    fit_tokens = tokens[fg].astype(np.float64)
    assert pca.n_tokens == len(fit_tokens) == fg.sum() and pca.n_images == 6
    ref = PCA(n_components=8, svd_solver="full").fit(fit_tokens)
    np.testing.assert_allclose(pca.mean, ref.mean_, atol=1e-5)
    np.testing.assert_allclose(np.abs(pca.components @ ref.components_.T), np.eye(8), atol=1e-4)
    np.testing.assert_allclose(pca.explained_variance, ref.explained_variance_, rtol=1e-4)
    # features = bilinear upsampling of the projected patch grid, zero on the background
    grid = (tokens - pca.mean) @ pca.components.T * pca.scale  # (N, 4, 4, 8)
    up = F.interpolate(torch.from_numpy(grid.transpose(0, 3, 1, 2)).float(), size=(R, R), mode="bilinear",
                       align_corners=False).numpy() * mask[:, None]
    np.testing.assert_allclose(feats, up, atol=2e-4)
    # the first channel has unit variance on the fitted tokens
    assert abs(np.var(pca.project(fit_tokens)[:, 0], ddof=1) - 1.0) < 1e-6

    # second call: PCA reused (not refitted, file untouched), features from the cache (no model forward)
    mtime = pca_path.stat().st_mtime_ns
    n_shards = len(list(cache.glob("dinov2-*/*.npz")))
    again = extract_features("dinov2", rgb, mask, cfg)
    s2 = feature_stats()
    np.testing.assert_array_equal(again, feats)
    assert s2.pca_fits == s1.pca_fits and s2.model_batches == s1.model_batches
    assert s2.cache_hits == s1.cache_hits + 6 and s2.cache_misses == s1.cache_misses
    assert pca_path.stat().st_mtime_ns == mtime and len(list(cache.glob("dinov2-*/*.npz"))) == n_shards

    # a mix of known and new crops computes only the new ones, in order
    rgb_new, mask_new = _crops(2, 3)
    mix = extract_features("dinov2", np.concatenate([rgb[:3], rgb_new]), np.concatenate([mask[:3], mask_new]), cfg)
    s3 = feature_stats()
    assert s3.cache_hits == s2.cache_hits + 3 and s3.cache_misses == s2.cache_misses + 2
    np.testing.assert_array_equal(mix[:3], feats[:3])
    assert s3.pca_fits == s2.pca_fits

    # a changed config (channels) fits its own PCA and recomputes
    cfg6 = _cfg(tiny_model, cache, channels=6)
    f6 = extract_features("dinov2", rgb, mask, cfg6)
    s4 = feature_stats()
    assert f6.shape == (6, 6, R, R) and s4.pca_fits == s3.pca_fits + 1 and s4.cache_misses == s3.cache_misses + 6
    assert get_extractor("dinov2").pca_path(cfg6) != pca_path
    # ... and so does a changed input size (a 5 x 5 patch grid)
    f40 = extract_features("dinov2", rgb, mask, _cfg(tiny_model, cache, input_size=40))
    s5 = feature_stats()
    assert f40.shape == (6, 8, R, R) and s5.cache_misses == s4.cache_misses + 6 and s5.pca_fits == s4.pca_fits + 1


def test_dinov2_changed_weights_recompute(tmp_path):
    model = tmp_path / "model"
    _save_tiny_dinov2(model, seed=1)
    cfg = _cfg(model, tmp_path / "cache")
    rgb, mask = _crops(5, 4)
    a = extract_features("dinov2", rgb, mask, cfg)
    s0 = feature_stats()
    _save_tiny_dinov2(model, seed=2)  # same folder, new weights
    b = extract_features("dinov2", rgb, mask, cfg)
    s1 = feature_stats()
    assert s1.pca_fits == s0.pca_fits + 1 and s1.cache_misses == s0.cache_misses + 5 and s1.cache_hits == s0.cache_hits
    assert np.abs(a - b).max() > 1e-3


def test_dinov2_config_errors(tiny_model, tmp_path):
    rgb, mask = _crops(4, 5)
    with pytest.raises(ValueError, match="dinov2.input_size must be a multiple of the model's patch size 8, got 30"):
        extract_features("dinov2", rgb, mask, _cfg(tiny_model, tmp_path, input_size=30))
    with pytest.raises(ValueError, match="dinov2.channels=40 exceeds the model's token dimension D=32"):
        extract_features("dinov2", rgb, mask, _cfg(tiny_model, tmp_path, channels=40))
    with pytest.raises(ValueError, match=r"dinov2.model folder /no/such/folder does not exist; expected a folder"):
        extract_features("dinov2", rgb, mask, FeatureConfig(device="cpu", dinov2=Dinov2Options(model="/no/such/folder")))
    (tmp_path / "empty_model").mkdir()
    with pytest.raises(ValueError, match=r"dinov2.model folder .*empty_model holds no config.json or weight files"):
        extract_features("dinov2", rgb, mask, _cfg(tmp_path / "empty_model", tmp_path))
    # an explicit PCA file fitted for another config is refused, not silently reused
    pca_file = tmp_path / "pca.npz"
    extract_features("dinov2", rgb, mask, _cfg(tiny_model, tmp_path / "c1", pca_path=str(pca_file)))
    with pytest.raises(ValueError, match=r"PCA file .*pca\.npz was fitted for extractor config \w+, but the current"):
        extract_features("dinov2", rgb, mask, _cfg(tiny_model, tmp_path / "c1", pca_path=str(pca_file), channels=4))


def test_feature_shards_and_pca_from_shards(tiny_model, tmp_path):
    rgb, mask = _crops(5, 6)
    rows = [{"sample_id": f"s{i}", "status": "ok" if i != 2 else "bad_image",
             "reason": "" if i != 2 else "broken"} for i in range(5)]
    rgb[2], mask[2] = 0, False
    write_shard(tmp_path / "coll", 0, rows, {"rgb": rgb, "mask": mask})
    cfg = _cfg(tiny_model, tmp_path / "cache")
    s0 = feature_stats()
    pca = fit_pca_from_shards([tmp_path / "coll"], cfg)
    s1 = feature_stats()
    assert s1.pca_fits == s0.pca_fits + 1 and pca.n_images == 4
    assert fit_pca_from_shards([tmp_path / "coll"], cfg).content_hash == pca.content_hash  # loaded, not refitted
    extract_feature_shard(tmp_path / "coll", 0, tmp_path / "feat", cfg)
    assert feature_stats().pca_fits == s1.pca_fits
    table, arrays = read_shard(tmp_path / "feat", 0)
    assert table.column("status").to_pylist() == ["ok", "ok", "bad_image", "ok", "ok"]
    assert set(table.column("extractor").to_pylist()) == {"dinov2"}
    grid = arrays["grid"]  # the native patch grid (R / 14 cells a side at input_size 14 * cells), not R x R
    assert grid.dtype == np.float32 and grid.shape[:2] == (5, 8) and grid.shape[2] < R
    assert not grid[2].any()
    ok = [0, 1, 3, 4]
    direct = extract_features("dinov2", rgb[ok], mask[ok], cfg)
    np.testing.assert_array_equal(grid_features(grid[ok], arrays["mask"][ok]), direct)  # what training streams
    fn = make_feature_fn(cfg)
    np.testing.assert_array_equal(fn(rgb[ok], mask[ok]), direct)
    with pytest.raises(ValueError, match=r"no ok samples in shard folders .* to fit the PCA on"):
        fit_pca_from_shards([tmp_path / "empty"], _cfg(tiny_model, tmp_path / "cache2"))
