"""``toy_collection`` flow: a category's image collection and test split → preprocessed shards of a run.

For a ``generated`` collection (the embedded ``toy``'s, or any category's: its own rig posed, yawed, framed and
textured, ``bat3r_core.generated_collections.make_collection``) the images are rendered first (Blender, cached by their
parameters); for a user's folder/Parquet collection they are listed. Either way the images are cropped around
their masks into ``<run>/collection`` and ``<run>/test`` shards at the model resolution (the predictor's input).
Dropped renders and bad images are reported like any stage's dropped samples (``flows._fanout.report_drops``).

Local run: ``python flows/toy_collection.py --category toy --preset tiny [--catalog PATH]``.
"""
from __future__ import annotations

import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a script or loaded by path (deployments): make the project root importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from typing import Any

from prefect import flow

from bat3r_core.predictor.collection import CollectionConfig, list_collection, plan_shards
from bat3r_core.runs import SampleNeed, require_samples, summarize_drops
from bat3r_core.specs import GeneratedCollectionSpec
from bat3r_core.stages import GENERATED_COLLECTION
from flows._fanout import StageResult, artifact_key, run_stage
from flows._runners import StoppableThreadPoolTaskRunner
from flows._settings import RunSettings, resolve_run
from tasks._cache import for_run
from tasks.predict import ingest_collection_shard
from tasks.render import render_generated_collection

__all__ = ["toy_collection", "prepare_split"]


_GENERATED_KEYS = ("asset", "body_frame", "textures", "envmaps", "pose_sampler", "prefix", "pose_families")


def prepare_split(settings: RunSettings, split: str, spec: dict[str, Any],
                  needs: SampleNeed | None = None) -> list[StageResult]:
    """Render (generated collections) and ingest one split (``collection`` or ``test``) of a run. needs: what the
    run needs of this split; a split left with fewer usable images stops the run (``TooFewSamples``) before the
    next stage starts."""
    layout = settings.layout
    results = []
    folder = Path(spec["path"])

    def check(result: StageResult) -> StageResult:
        results.append(result)
        if needs is not None:
            require_samples(result.drops, needs, [r.drops for r in results[:-1]], **settings.hint_context())
        return result

    if spec["kind"] == "generated":
        cfg = GeneratedCollectionSpec(
            n=spec["n"], seed=spec["seed"], resolution=settings.image_size, render=settings.render,
            ground_truth_dir=spec["ground_truth"],
            **{k: tuple(spec[k]) if k in ("textures", "envmaps") else spec[k] for k in _GENERATED_KEYS if k in spec})
        check(run_stage(GENERATED_COLLECTION, for_run(render_generated_collection, layout),
                        [{"out_dir": str(folder), "config": cfg}],
                        progress_key=artifact_key(layout.category, layout.run_name, split, "images"),
                        max_failed_fraction=0.0, label=f"{split} images"))
    samples = [{"sample_id": s.sample_id, "image_path": str(s.image_path),
                "mask_path": "" if s.mask_path is None else str(s.mask_path)}
               for s in list_collection(folder)]
    ccfg = CollectionConfig(resolution=settings.image_size, shard_size=settings.shard_size)
    chunks = plan_shards(samples, ccfg.shard_size)
    out_dir = layout.run_stage_dir(split)
    calls = [{"samples": chunk, "index": i, "out_dir": str(out_dir), "config": ccfg}
             for i, chunk in enumerate(chunks)]
    if not calls:
        raise ValueError(f"{split}: no image in {folder} (expected images/ with masks/, or a Parquet index)")
    check(run_stage(split, for_run(ingest_collection_shard, layout), calls,
                    progress_key=artifact_key(layout.category, layout.run_name, split),
                    max_failed_fraction=settings.max_failed_fraction, label=split))
    return results


@flow(name="toy_collection", flow_run_name="{category}-{run_name}-collections",
      task_runner=StoppableThreadPoolTaskRunner())
def toy_collection(category: str = "toy", preset: str = "tiny", run_name: str | None = None,
                   overrides: dict[str, Any] | None = None, catalog: str | None = None) -> dict[str, Any]:
    """Prepare the training collection and the test split of run ``run_name`` (default: the preset name) of
    ``category`` in ``catalog`` (default: ``$BAT3R_CATALOG``, else ``./data_catalog.yaml``).
    Returns ``{split: [stage records]}``."""
    settings = resolve_run(category, preset, run_name or preset, overrides, catalog=catalog)
    settings.layout.create()
    out: dict[str, Any] = {}
    for split, spec in (("collection", settings.collection), ("test", settings.test_split)):
        if spec is not None:
            out[split] = [list(r.records) for r in prepare_split(settings, split, spec)]
    return out


def main(argv: list[str] | None = None) -> int:
    import argparse

    from bat3r_core.cli import add_catalog_argument, parse_overrides

    parser = argparse.ArgumentParser(description="Prepare a category's collection and test split for a run.")
    parser.add_argument("--category", default="toy")
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--run-name", default=None)
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a setting (as for flows/bootstrap.py), e.g. --set run.collection_size=8")
    add_catalog_argument(parser)
    args = parser.parse_args(argv)
    out = toy_collection(args.category, args.preset, args.run_name, parse_overrides(args.overrides, parser),
                         None if args.catalog is None else str(Path(args.catalog).resolve()))
    for split, stages in out.items():
        for records in stages:
            if records:
                stage = records[0]["stage"]
                print(summarize_drops(stage, records, label=f"{split} ({stage})").describe())
    return 0


if __name__ == "__main__":
    sys.exit(main())
