"""The ``bat3r`` command line: the pieces of the pipeline a user runs by hand.

Every subcommand is a thin wrapper over a bat3r_core function; run ``bat3r <command> --help`` for its options.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path


def _cmd_catalog_validate(args: argparse.Namespace) -> int:
    from .catalog import ConfigError, load_catalog

    try:
        catalog = load_catalog(args.path)
    except (ConfigError, FileNotFoundError) as e:
        print(f"invalid catalog: {e}", file=sys.stderr)
        return 2
    print(f"catalog {catalog.path}: storage {catalog.storage()}, image size {catalog.image_size}, "
          f"K = {catalog.layers}, shard size {catalog.shard_size}, run presets {sorted(catalog.runs)}")
    usable = 0
    for name, cat in catalog.categories.items():
        missing = cat.missing()
        status = "ready" if not missing else f"missing {len(missing)}"
        kind = "generated on first use" if cat.is_generated else cat.asset
        print(f"  {name:<8} {status:<10} asset: {kind}; collection: {cat.collection.kind} "
              f"{cat.collection.path}; fitting: {cat.fitting.preset}")
        for m in missing:
            print(f"           - needs {m}")
        usable += not missing
    print(f"{usable}/{len(catalog.categories)} categories ready")
    return 0


def _cmd_asset_toy(args: argparse.Namespace) -> int:
    from .rig_io import load_rig, save_rig_glb
    from .toy import build_toy_rig, toy_coat_texture

    rig = build_toy_rig()
    out = save_rig_glb(rig, args.out, texture=toy_coat_texture(args.coat))
    back = load_rig(out)
    print(f"wrote {out} ({out.stat().st_size / 1e3:.0f} kB)")
    print(back.summary())
    print("joints: " + ", ".join(back.joint_names))
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from .evaluation import evaluate_run, read_metrics
    from .report import build_report

    run = Path(args.run)
    if not run.is_dir():
        print(f"run folder {run} does not exist", file=sys.stderr)
        return 2
    metrics = evaluate_run(run)
    report = build_report(run)
    table = read_metrics(run).to_pylist()
    cols = ["iteration", "split", "n", "mcd_cm", "pct_mcd_over_5cm", "rot_err_deg", "rms_cd_cm", "mv_rms_cd_cm"]
    print("  ".join(f"{c:>16}" for c in cols))
    for row in table:
        print("  ".join(f"{row.get(c):>16.3f}" if isinstance(row.get(c), float) else f"{str(row.get(c)):>16}"
                        for c in cols))
    print(f"wrote {metrics} and {report}")
    return 0


def _feature_fn(catalog, extractor: str):
    """None for the built-in ``rgb`` features, else the catalog-configured extractor as a callable."""
    if extractor == "rgb":
        return None
    from .predictor.features import make_feature_fn

    return make_feature_fn(catalog.feature_config(extractor=extractor))


def _cmd_train(args: argparse.Namespace) -> int:
    from .catalog import load_catalog
    from .predictor.train import train_predictor

    catalog = load_catalog(args.catalog)
    model_cfg, train_cfg = catalog.model_config(args.preset), catalog.train_config(args.preset)
    if args.steps is not None:
        import dataclasses

        train_cfg = dataclasses.replace(train_cfg, steps=args.steps)
    ckpt = train_predictor(args.shards, args.out, model_cfg, train_cfg, _feature_fn(catalog, model_cfg.feature),
                           init_from=args.init_from)
    print(f"trained {train_cfg.steps} steps ({args.preset} preset): {ckpt}")
    return 0


def _cmd_predict(args: argparse.Namespace) -> int:
    from .catalog import load_catalog
    from .predictor.collection import CollectionConfig, write_collection_shards
    from .predictor.infer import load_predictor, predict_collection
    from .shards import list_shards, read_table

    catalog = load_catalog(args.catalog)
    _, configs = load_predictor(args.model, "cpu")
    model_cfg = configs.model
    collection = Path(args.collection)
    if not list_shards(collection):  # a raw folder / Parquet index: preprocess and shard it first
        sharded = Path(args.out) / "collection"
        write_collection_shards(collection, sharded, CollectionConfig(resolution=model_cfg.resolution,
                                                                      shard_size=catalog.shard_size))
        collection = sharded
    out = Path(args.out) / "predictions"
    predict_collection(args.model, collection, out, _feature_fn(catalog, model_cfg.feature))
    rows = read_table(out).to_pylist()
    ok = sum(r["status"] == "ok" for r in rows)
    print(f"predicted {ok}/{len(rows)} samples into {out}")
    for r in rows:
        if r["status"] != "ok":
            print(f"  {r['sample_id']}: {r['status']}: {r['reason']}")
    return 0


def _cmd_render(args: argparse.Namespace) -> int:
    from .catalog import load_catalog
    from .render.runner import render_command

    catalog = load_catalog(args.catalog)
    result = render_command(args.jobs, args.asset, args.out, config=catalog.render_config(args.preset),
                            textures=args.texture or None, envmaps=tuple(args.envmap or ()),
                            shard_index=args.shard)
    print(f"rendered {result.num_ok} ok, {result.num_failed} failed in {result.seconds:.1f} s "
          f"({result.processes} worker process(es), {result.crashes} crash(es)): {result.parquet}")
    if result.num_failed:
        from .shards import read_shard

        table, _ = read_shard(args.out, args.shard, with_arrays=False)
        for row in table.select(["sample_id", "status", "reason"]).to_pylist():
            if row["status"] != "ok":
                print(f"  {row['sample_id']}: {row['status']}: {row['reason']}")
    return 0


def _cmd_collection_toy(args: argparse.Namespace) -> int:
    from .catalog import load_catalog
    from .datasets import collection_toy_command

    catalog = load_catalog(args.catalog)
    col = collection_toy_command(args.n, args.out, seed=args.seed, resolution=args.resolution,
                                 config=catalog.render_config(args.preset), force=args.force)
    state = "reused" if col.reused else "rendered"
    print(f"{state} {len(col.sample_ids)} images: {col.images_dir} (masks: {col.masks_dir}); hidden ground truth: "
          f"{col.ground_truth_dir}")
    return 0


def _cmd_fit(args: argparse.Namespace) -> int:
    from .fitting.config import preset
    from .fitting.io import fit_points_file
    from .shards import read_table

    config = preset(args.preset, catalog=args.catalog)
    if args.steps is not None:
        import dataclasses

        config = dataclasses.replace(config, steps=args.steps)
    summary = fit_points_file(args.asset, args.points, config, args.out, device=args.device,
                              fit_focal=args.fit_focal)
    print(f"fitted {summary['num_ok']}/{summary['num_instances']} instances ({args.preset} preset, "
          f"{config.steps} steps) into {args.out}")
    for row in read_table(args.out).select(["sample_id", "status", "reason"]).to_pylist():
        if row["status"] != "ok":
            print(f"  {row['sample_id']}: {row['status']}: {row['reason']}")
    return 0


def _catalog_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--catalog", type=Path, default=None, help="data catalog (default: ./data_catalog.yaml)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="bat3r", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    cat = sub.add_parser("catalog", help="data catalog commands")
    cat_sub = cat.add_subparsers(dest="catalog_command", required=True)
    val = cat_sub.add_parser("validate", help="print the categories and what each is missing")
    val.add_argument("path", nargs="?", default=None, help="catalog file (default: ./data_catalog.yaml)")
    val.set_defaults(func=_cmd_catalog_validate)

    asset = sub.add_parser("asset", help="generate assets")
    asset_sub = asset.add_subparsers(dest="asset_command", required=True)
    toy = asset_sub.add_parser("toy", help="write the embedded toy quadruped as a rigged GLB")
    toy.add_argument("--out", type=Path, required=True, help="output .glb path")
    toy.add_argument("--coat", default="bay", help="procedural coat texture (bay, chestnut, grey, pinto)")
    toy.set_defaults(func=_cmd_asset_toy)

    rd = sub.add_parser("render", help="render one shard of render jobs with Blender (+ exact ray-cast labels)")
    rd.add_argument("--jobs", required=True, type=Path, help="render jobs (Parquet, docs/CONVENTIONS.md schema)")
    rd.add_argument("--asset", required=True, type=Path, help="rigged asset (.glb/.gltf/.fbx/.blend)")
    rd.add_argument("--out", required=True, type=Path, help="output folder of the training shard")
    rd.add_argument("--preset", default="tiny", help="run preset whose render settings to use (tiny, demo, paper)")
    rd.add_argument("--texture", action="append", help="texture image or toy:<coat> (repeatable; default: the "
                    "asset's own base-colour texture)")
    rd.add_argument("--envmap", action="append", help="HDR/EXR environment map (repeatable; default: a sky)")
    rd.add_argument("--shard", type=int, default=0, help="shard index of the output (part-NNNNN)")
    _catalog_option(rd)
    rd.set_defaults(func=_cmd_render)

    col = sub.add_parser("collection", help="synthesise image collections")
    col_sub = col.add_subparsers(dest="collection_command", required=True)
    ct = col_sub.add_parser("toy", help="render the toy in natural poses into images/ + masks/ (+ hidden truth)")
    ct.add_argument("--n", type=int, required=True, help="number of images")
    ct.add_argument("--out", type=Path, required=True, help="collection folder (truth goes to <out>_ground_truth)")
    ct.add_argument("--seed", type=int, default=0)
    ct.add_argument("--resolution", type=int, default=128, help="image side in pixels")
    ct.add_argument("--preset", default="demo", help="run preset whose render settings to use")
    ct.add_argument("--force", action="store_true", help="re-render even if a matching collection exists")
    _catalog_option(ct)
    ct.set_defaults(func=_cmd_collection_toy)

    tr = sub.add_parser("train", help="train a dual point map predictor on rendered training shards")
    tr.add_argument("--shards", required=True, type=Path, help="folder of training shards (part-NNNNN.parquet/.npz)")
    tr.add_argument("--out", required=True, type=Path, help="output folder (checkpoint.pt, predictor.pt, log)")
    tr.add_argument("--preset", default="tiny", help="run preset of the data catalog (tiny, demo, paper)")
    tr.add_argument("--steps", type=int, default=None, help="override the preset's number of steps")
    tr.add_argument("--init-from", type=Path, default=None,
                    help="predictor.pt whose weights initialise the model (warm start, e.g. the previous iteration's)")
    _catalog_option(tr)
    tr.set_defaults(func=_cmd_train)

    pr = sub.add_parser("predict", help="predict dual point maps for an image collection")
    pr.add_argument("--model", required=True, type=Path, help="predictor.pt written by `bat3r train`")
    pr.add_argument("--collection", required=True, type=Path,
                    help="collection shards, a folder with images/ and masks/, or a Parquet index")
    pr.add_argument("--out", required=True, type=Path, help="output folder (predictions/ and clouds)")
    _catalog_option(pr)
    pr.set_defaults(func=_cmd_predict)

    ft = sub.add_parser("fit", help="fit the rigged mesh to predicted dual point clouds")
    ft.add_argument("--asset", required=True, help="rigged asset (.glb/.gltf/.fbx/.blend) or 'toy'")
    ft.add_argument("--points", required=True, type=Path, help="points npz (format in the README)")
    ft.add_argument("--preset", required=True, choices=["synthetic", "real"], help="fitting preset")
    ft.add_argument("--out", required=True, type=Path, help="output folder of fit shards")
    ft.add_argument("--steps", type=int, default=None, help="override the preset's optimisation steps")
    ft.add_argument("--device", default="cpu", help="torch device (cpu, cuda, cuda:N)")
    ft.add_argument("--fit-focal", action="store_true", help="also search the focal length in camera recovery")
    _catalog_option(ft)
    ft.set_defaults(func=_cmd_fit)

    ev = sub.add_parser("evaluate", help="recompute metrics.parquet and report.html of a run from its stored rows")
    ev.add_argument("--run", required=True, type=Path, help="run folder (<storage>/<category>/<run name>)")
    ev.set_defaults(func=_cmd_evaluate)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
