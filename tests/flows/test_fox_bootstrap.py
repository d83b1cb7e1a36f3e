"""A third-party asset through the whole loop: the Khronos Fox (centimetres, unindexed, animated) as a catalog
category with `asset_scale`, `body_frame: auto`, no `textures` and generated collection and test split, bootstrapped
at the `tiny` preset for one iteration."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import yaml

from bat3r_core.catalog import load_catalog
from bat3r_core.runs import RunLayout

ROOT = Path(__file__).resolve().parents[2]
FOX = ROOT.parent / "shared" / "assets" / "fox" / "Fox.glb"
TINY = {"run.canonical_samples": 8, "run.collection_size": 4, "run.test_size": 4, "train.steps": 4, "shard_size": 4}

pytestmark = [pytest.mark.blender,
              pytest.mark.skipif(not FOX.is_file(), reason=f"the shared Fox asset is not at {FOX}")]


def test_tiny_bootstrap_on_the_fox(prefect_harness, tmp_path):
    from flows.bootstrap import bootstrap

    data = yaml.safe_load((ROOT / "data_catalog.yaml").read_text())
    data["storage_root"] = str(tmp_path / "runs")
    data["categories"] = {"fox": {
        "asset": str(FOX), "asset_scale": 0.01, "body_frame": "auto",  # no textures: the Fox's own
        "collection": {"kind": "generated", "path": "collections/fox/train", "seed": 3},
        "test_split": {"kind": "generated", "path": "collections/fox/test", "seed": 4},
        "fitting": {"preset": "synthetic", "overrides": {"inlier_distance": 0.05}}}}
    path = tmp_path / "fox_catalog.yaml"
    path.write_text(yaml.safe_dump(data))
    catalog = load_catalog(path)
    frame = catalog.body_frame("fox")
    assert frame.horizontal == ("b_LeftLeg01_015", "b_RightLeg01_019")
    prepared = catalog.asset_path("fox")
    assert prepared.parent == tmp_path / "runs" / "_assets" and prepared.suffix == ".glb"

    bootstrap(category="fox", preset="tiny", iterations=1, run_name="f1", overrides=TINY, catalog=str(path))
    layout = RunLayout(tmp_path / "runs", "fox", "f1")
    metrics = pq.read_table(layout.root / "metrics.parquet").to_pylist()
    test = {r["iteration"]: r for r in metrics if r["split"] == "test"}
    assert sorted(test) == [0, 1]
    for row in test.values():
        assert row["n"] >= 1 and np.isfinite(row["mcd_cm"]) and row["mcd_cm"] > 0
    assert (layout.root / "report.html").is_file()
