"""A stage never drops samples silently: a real run (`bat3r bootstrap --catalog`, real Blender) of a category whose
photo collection has a corrupt image and an image without a mask, and one of whose two textures is a corrupt file.
The collection stage drops 2 of 6 images and continues with a warning; the render stage drops every job that drew
the corrupt texture, and the run stops before features and training, naming where the samples were lost."""
from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pyarrow.parquet as pq
import pytest
import yaml

from bat3r_core import shards
from bat3r_core.runs import RunLayout, read_manifest
from bat3r_core.toy import TOY_BODY_FRAME

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.blender


def _photos(folder: Path) -> None:
    """Six 48×48 photos with masks: four good ones, one truncated PNG, one without a mask."""
    (folder / "images").mkdir(parents=True)
    (folder / "masks").mkdir()
    rng = np.random.default_rng(7)
    for i in range(6):
        mask = np.zeros((48, 48), np.uint8)
        cv2.ellipse(mask, (24, 24), (16, 9), 15 * i, 0, 360, 255, -1)
        image = (rng.integers(40, 200, (48, 48, 3)) * (mask[..., None] > 0)).astype(np.uint8)
        cv2.imwrite(str(folder / "images" / f"p{i}.png"), image)
        if i != 5:
            cv2.imwrite(str(folder / "masks" / f"p{i}.png"), mask)
    data = (folder / "images" / "p4.png").read_bytes()
    (folder / "images" / "p4.png").write_bytes(data[: len(data) // 2])  # truncated: no IEND chunk


class _Records(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


def _artifact(key: str) -> str:
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterKey

    with get_client(sync_client=True) as client:
        found = client.read_artifacts(artifact_filter=ArtifactFilter(key=ArtifactFilterKey(any_=[key])))
    assert found, f"no artifact {key}"
    return found[0].data


def test_a_run_that_drops_samples_says_how_many_why_and_where(prefect_harness, tmp_path, monkeypatch, capsys):
    folder = tmp_path / "catalog"
    _photos(folder / "photos")
    (folder / "textures").mkdir()
    broken = folder / "textures" / "broken.png"
    broken.write_bytes(b"\x89PNG\r\n\x1a\n this is not an image")
    data = yaml.safe_load((ROOT / "data_catalog.yaml").read_text())
    data["categories"] = {"spotty": {
        "asset": "generated:toy", "body_frame": {k: (list(v) if isinstance(v, tuple) else v)
                                                 for k, v in TOY_BODY_FRAME.items()},
        "textures": ["procedural:bay", "textures/broken.png"], "environment_maps": [],
        "collection": {"kind": "folder", "path": "photos"}, "fitting": {"preset": "synthetic"}}}
    catalog = folder / "my_catalog.yaml"
    catalog.write_text(yaml.safe_dump(data))
    monkeypatch.delenv("BAT3R_STORAGE_ROOT", raising=False)
    monkeypatch.setenv("BAT3R_CATALOG", str(ROOT / "data_catalog.yaml"))  # not the catalog this run uses
    from bat3r_core.cli import main
    import flows.bootstrap  # noqa: F401  (its imports reconfigure logging: add the handler afterwards)

    handler = _Records()
    logging.getLogger("prefect").addHandler(handler)
    try:
        rc = main(["bootstrap", "--catalog", str(catalog), "--category", "spotty", "--iterations", "0",
                   "--run-name", "drops", "--set", "run.canonical_samples=8", "--set", "shard_size=8",
                   "--set", "train.steps=2"])
    finally:
        logging.getLogger("prefect").removeHandler(handler)
    err = capsys.readouterr().err
    assert rc == 1, err

    # the run lives under the given catalog's storage root, and its manifest records that catalog
    layout = RunLayout(folder / "runs", "spotty", "drops")
    assert read_manifest(layout)["config"]["parameters"]["catalog"] == str(catalog)

    # collection: 2 of 6 dropped (33 % > 5 %), reported and the run went on
    collection_line = ("collection: 2 of 6 images dropped (33.3 %): bad_image ×1 (image "
                       f"{folder / 'photos' / 'images' / 'p4.png'}")
    assert any(m.startswith(collection_line) for m in handler.messages), (handler.messages, err)
    assert any("missing_mask ×1" in m for m in handler.messages if m.startswith("collection:"))
    table = _artifact("spotty-drops-collection-drops")
    assert "**collection: 2 of 6 images dropped (33.3 %)**; 4 kept." in table
    assert "| bad_image | 1 | 16.7 % |" in table and "| missing_mask | 1 | 16.7 % |" in table
    assert f"`p4` | `{layout.run_stage_dir('collection') / 'part-00000.parquet'}` |" in table

    # render: every job that drew texture 1 (the corrupt file) is dropped; the expected count comes from the plan
    jobs = pq.read_table(layout.stage_dir(0, "plan") / "part-00000.parquet").to_pylist()
    bad = [j["sample_id"] for j in jobs if j["texture_id"] == 1]
    assert len(jobs) == 8 and 1 <= len(bad) < 8
    rows = shards.read_table(layout.stage_dir(0, "render")).to_pylist()
    assert sorted(r["sample_id"] for r in rows if r["status"] == "bad_texture") == sorted(bad)
    k, shard = len(bad), layout.stage_dir(0, "render") / "part-00000.parquet"
    reason = f"texture file {broken} cannot be read"
    headline = f"iteration 0 render: {k} of 8 renders dropped ({100 * k / 8:.1f} %)"
    assert any(m.startswith(f"{headline}: bad_texture ×{k} ({reason}") for m in handler.messages)
    table = _artifact("spotty-drops-iter-00-render-drops")
    assert f"**{headline}**; {8 - k} kept." in table
    assert f"| bad_texture | {k} | {100 * k / 8:.1f} % | {reason}" in table and f"`{bad[0]}` | `{shard}` |" in table

    # the failure names the stage, the counts, the reason, what to do, what training needs and an example file
    message = (f"{headline}: bad_texture ×{k} ({reason}")
    assert f"bootstrap stopped: {message}" in err
    assert (f") — check categories.spotty.textures in the data catalog; training needs at least 8 "
            f"(batch_size × world_size), {8 - k} left (e.g. sample {bad[0]} in {shard})") in err
    # ... before the next stage started
    assert not shards.list_shards(layout.stage_dir(0, "features"))
    assert not layout.stage_dir(0, "train").exists()

    # the iteration summary of the stopped iteration says the same
    summary = _artifact("spotty-drops-iter-00-summary")
    assert f"**Stopped:** {message}" in summary
    assert "- run data: collection: 2 of 6 images dropped (33.3 %): bad_image ×1" in summary
    assert "## Dropped samples (stages that dropped more than 5 %)" in summary
    assert f"- {headline}: bad_texture ×{k}" in summary
    assert "**render**: 1 of 1 task(s) done (0 from cache); " + f"{8 - k} samples ok, {k} skipped" in summary
