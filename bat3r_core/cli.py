"""The ``bat3r`` command line: the pieces of the pipeline a user runs by hand.

Every subcommand is a thin wrapper over a bat3r_core function (``bat3r bootstrap`` over the ``bootstrap`` flow of
the checkout's ``flows/``); run ``bat3r <command> --help`` for its options. Every subcommand that reads the data
catalog takes ``--catalog PATH`` (default ``$BAT3R_CATALOG``, else ``./data_catalog.yaml``).

The options of ``bat3r bootstrap`` and ``python flows/bootstrap.py`` are one definition,
:func:`add_bootstrap_arguments`, turned into the flow's keyword arguments by :func:`bootstrap_parameters`.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

__all__ = ["main", "build_parser", "add_catalog_argument", "add_bootstrap_arguments", "bootstrap_parameters",
           "parse_overrides", "ABLATION_SWITCHES", "local_server_environment", "LOCAL_SERVER_ENVIRONMENT",
           "exit_on_sigterm", "SIGTERM_EXIT_CODE"]

LOCAL_SERVER_ENVIRONMENT = {
    "PREFECT_SERVER_ANALYTICS_ENABLED": "false",  # no telemetry (and no ERROR line offline)
    # Prefect waits 20 s for its temporary server by default; the first start on a fresh machine creates and
    # migrates the database, which took longer than that on 2 busy cores (a `make bench-fidelity` that died
    # before its first task)
    "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "180",
}
"""Defaults for a local flow run's temporary Prefect server; a value already in the environment wins."""


def local_server_environment() -> None:
    """Set :data:`LOCAL_SERVER_ENVIRONMENT` where the environment does not already say otherwise, and make SIGTERM
    exit through :func:`exit_on_sigterm`. Call before a local flow run starts Prefect's temporary server
    (``make demo``, ``bat3r bootstrap``, the benchmarks)."""
    for key, value in LOCAL_SERVER_ENVIRONMENT.items():
        os.environ.setdefault(key, value)
    exit_on_sigterm()


SIGTERM_EXIT_CODE = 128 + 15
"""The exit status of a local run stopped by SIGTERM (what the default action reports to a shell)."""


def _raise_system_exit(signum: int, frame: Any) -> None:
    raise SystemExit(SIGTERM_EXIT_CODE)


def exit_on_sigterm() -> bool:
    """Make SIGTERM raise ``SystemExit(143)`` in the main thread instead of killing the process outright, so that
    ``atexit`` runs: Prefect stops its temporary server there (under the default action every stopped local run
    left an orphaned server process behind). During a flow run Prefect's own SIGTERM handler comes first (it marks
    the run crashed or cancelled) and then re-delivers the signal to this one. Only replaces the default action,
    only from the main thread; returns whether it installed the handler."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return False
    if signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        return signal.getsignal(signal.SIGTERM) is _raise_system_exit
    signal.signal(signal.SIGTERM, _raise_system_exit)
    return True

ABLATION_SWITCHES = {
    "gaussian_cameras": "Normal viewpoint priors (the Student's t loc/scale per view type, no df)",
    "no_fitting_regularisation": "mesh fitting without the angle, edge, volume, repulsion and scale terms",
    "no_view_augmentation": "render only the estimated view of each fit",
    "no_pseudo_label_filter": "render every ok fit (skip the pseudo-label filter between fit and plan views)",
    "random_poses": "the random-poses baseline (iteration-0 jobs from random poses; use --iterations 0)",
    "raw_images": "the raw-image baseline (train on the photos with their fitted pseudo-labels)",
}
"""The paper's ablation switches (``flows._settings.Ablations`` fields) and their help texts."""


def add_catalog_argument(parser: argparse.ArgumentParser) -> None:
    """``--catalog PATH``: the data catalog (default ``$BAT3R_CATALOG``, else ``./data_catalog.yaml``)."""
    parser.add_argument("--catalog", type=Path, default=None,
                        help="data catalog file (default: $BAT3R_CATALOG, else ./data_catalog.yaml)")


def parse_overrides(items: list[str], parser: argparse.ArgumentParser | None = None) -> dict[str, Any]:
    """``["train.steps=100", "run.fitting={\"steps\": 9}"]`` → ``{"train.steps": 100, ...}``: each value parsed as
    JSON, else kept as a string. An item without ``=`` is an error naming it (``parser.error`` when given)."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            message = f"--set expects KEY=VALUE, got {item!r}"
            if parser is not None:
                parser.error(message)
            raise ValueError(message)
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def add_bootstrap_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of a bootstrap run (``bat3r bootstrap`` and ``python flows/bootstrap.py``)."""
    parser.add_argument("--category", default="toy", help="catalog category (default: toy)")
    parser.add_argument("--preset", default="tiny",
                        help="run preset of the catalog: tiny, demo, bench, paper (default: tiny)")
    add_catalog_argument(parser)
    parser.add_argument("--iterations", type=int, default=None,
                        help="bootstrap iterations after the canonical initialisation (default: the preset's)")
    parser.add_argument("--run-name", default=None,
                        help="run folder <storage root>/<category>/<run name> (default: the preset name); a rerun "
                             "with the same name reuses every completed task")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a setting, e.g. --set train.steps=100 (value parsed as JSON, else a string; "
                             "repeatable)")
    for name, text in ABLATION_SWITCHES.items():
        parser.add_argument(f"--{name.replace('_', '-')}", dest=name, action="store_true", help=text)
    parser.add_argument("--task-runner", default="local",
                        help="preset of deploy/task_runners.yaml (local, dask, dask-cuda, slurm) or a YAML file")
    parser.add_argument("--max-failed-fraction", type=float, default=0.1,
                        help="a stage continues while at most this fraction of its shards failed (default 0.1)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the sampled render jobs (default 0)")
    parser.add_argument("--init-predictor", type=Path, default=None, metavar="CHECKPOINT",
                        help="start from this trained Φ_0 (e.g. runs/toy/demo/iter-00/train/predictor.pt) instead of "
                             "training one; iteration 0 only evaluates it")


def bootstrap_parameters(args: argparse.Namespace, parser: argparse.ArgumentParser | None = None
                         ) -> dict[str, Any]:
    """The keyword arguments of the ``bootstrap`` flow from options parsed by :func:`add_bootstrap_arguments`
    (``catalog`` as an absolute path, or None for the default)."""
    params: dict[str, Any] = {
        "category": args.category, "preset": args.preset, "iterations": args.iterations, "run_name": args.run_name,
        "overrides": parse_overrides(args.overrides, parser), "task_runner": args.task_runner,
        "max_failed_fraction": args.max_failed_fraction, "seed": args.seed,
        "catalog": None if args.catalog is None else str(Path(args.catalog).expanduser().resolve()),
        "init_predictor": (None if args.init_predictor is None
                           else str(Path(args.init_predictor).expanduser().resolve())),
    }
    params.update({name: bool(getattr(args, name)) for name in ABLATION_SWITCHES})
    return params


def _cmd_catalog_validate(args: argparse.Namespace) -> int:
    from .catalog import ConfigError, load_catalog

    if args.path is not None and args.catalog is not None and Path(args.path) != Path(args.catalog):
        print(f"catalog validate: give the catalog once (PATH {args.path} or --catalog {args.catalog})",
              file=sys.stderr)
        return 2
    try:
        catalog = load_catalog(args.path if args.path is not None else args.catalog)
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
        if not cat.is_generated and not missing:
            print(f"           - before a long run: bat3r asset check {cat.resolve(cat.asset)} --category {name}"
                  + (f" --catalog {catalog.path}" if args.catalog or args.path else ""))
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


def _cmd_asset_check(args: argparse.Namespace) -> int:
    from .asset_check import check_asset

    scale, up_axis, body_frame, fitting = args.asset_scale, args.up_axis, None, None
    if args.category:
        from .catalog import BodyFrameJoints, load_catalog

        catalog = load_catalog(args.catalog)
        cat = catalog.category(args.category)
        scale = scale if scale is not None else cat.asset_scale
        up_axis = up_axis or cat.up_axis
        if isinstance(cat.body_frame, BodyFrameJoints):
            body_frame = {"origin": cat.body_frame.origin, "forward": list(cat.body_frame.forward),
                          "horizontal": list(cat.body_frame.horizontal)}
        fitting = catalog.fitting_config(args.category)
    report = check_asset(args.path, args.out, scale=1.0 if scale is None else scale, up_axis=up_axis or "+Y",
                         body_frame=body_frame, fitting_config=fitting, num_views=args.views, num_poses=args.poses,
                         render=not args.no_render, fit=not args.no_fit)
    print(report.text())
    if report.contact_sheet is not None:
        print(f"contact sheet: {report.contact_sheet}")
    return 1 if report.failed else 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from .evaluation import evaluate_run, read_metrics
    from .report import build_report

    if (args.run is None) == (args.category is None) or (args.category is not None and not args.run_name):
        print("evaluate: give either --run DIR or --category NAME --run-name NAME", file=sys.stderr)
        return 2
    if args.run is not None:
        run = Path(args.run)
    else:
        from .catalog import load_catalog
        from .runs import RunLayout

        catalog = load_catalog(args.catalog)
        catalog.category(args.category)  # an unknown category is an error naming the catalog
        run = RunLayout(catalog.storage(), args.category, args.run_name).root
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
    import dataclasses

    from .catalog import load_catalog
    from .predictor.train import train_predictor

    catalog = load_catalog(args.catalog)
    model_cfg, train_cfg = catalog.model_config(args.preset), catalog.train_config(args.preset)
    if args.steps is not None:
        train_cfg = dataclasses.replace(train_cfg, steps=args.steps)
    mirror = None
    if args.mirror is not None:
        from .predictor.mirror import canonical_mirror_for_rig

        mirror = canonical_mirror_for_rig(catalog.load_rig(args.mirror),
                                          dataclasses.asdict(catalog.body_frame(args.mirror)),
                                          source=f"--mirror {args.mirror}")
        if train_cfg.mirror_probability == 0:
            train_cfg = dataclasses.replace(train_cfg, mirror_probability=0.5)
    ckpt = train_predictor(args.shards, args.out, model_cfg, train_cfg, _feature_fn(catalog, model_cfg.feature),
                           init_from=args.init_from, mirror=mirror)
    print(f"trained {train_cfg.steps} steps ({args.preset} preset"
          f"{f', {train_cfg.mirror_probability:g} of the samples mirrored' if mirror else ''}): {ckpt}")
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


def _cmd_collection_coco(args: argparse.Namespace) -> int:
    from .predictor.coco import CONVERSION_FILE, coco_to_collection

    try:
        conv = coco_to_collection(args.annotations, args.images, args.category, args.out, min_area=args.min_area,
                                  largest_only=args.largest_only, exclude_truncated=args.exclude_truncated,
                                  max_occlusion=args.max_occlusion)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"{conv.samples} samples from {conv.images} images: {conv.index} (masks in {args.out / 'masks'})")
    for reason, n in sorted(conv.skipped.items(), key=lambda t: -t[1]):
        print(f"  skipped {n}: {reason} (e.g. annotation {', '.join(map(str, conv.examples[reason]))})")
    print(f"details: {args.out / CONVERSION_FILE}; use it in the catalog as collection: {{kind: parquet, path: "
          f"{conv.index}}}")
    return 0


def _cmd_collection_toy(args: argparse.Namespace) -> int:
    from .catalog import load_catalog
    from .generated_collections import collection_toy_command

    catalog = load_catalog(args.catalog)
    col = collection_toy_command(args.n, args.out, seed=args.seed, resolution=args.resolution,
                                 config=catalog.render_config(args.preset), force=args.force)
    state = "reused" if col.reused else "rendered"
    print(f"{state} {len(col.sample_ids)} images: {col.images_dir} (masks: {col.masks_dir}); hidden ground truth: "
          f"{col.ground_truth_dir}")
    return 0


def _cmd_fit(args: argparse.Namespace) -> int:
    from .catalog import fitting_preset
    from .fitting.io import fit_points_file
    from .shards import read_table

    config = fitting_preset(args.preset, catalog=args.catalog)
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


def _cmd_bootstrap(args: argparse.Namespace) -> int:
    root = Path(__file__).resolve().parent.parent
    if not (root / "flows" / "bootstrap.py").is_file():
        print(f"bat3r bootstrap runs the bootstrap flow of a bat3r checkout ({root / 'flows' / 'bootstrap.py'} "
              f"is missing): install bat3r from its repository (pip install -e .)", file=sys.stderr)
        return 2
    if str(root) not in sys.path:
        sys.path.insert(0, str(root))
    local_server_environment()  # a local run's temporary server: no telemetry, time to migrate its database
    from flows.bootstrap import run_bootstrap

    return run_bootstrap(bootstrap_parameters(args, args.parser))


def _cmd_stages(args: argparse.Namespace) -> int:
    """The pipeline's stage table (``bat3r_core.stages.STAGES``), one row per stage in data-flow order."""
    from .stages import describe

    rows = describe()
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    columns = ("stage", "inputs", "folder", "task", "function")
    cells = [[r[c] if c != "inputs" else ", ".join(r[c]) or "-" for c in columns] for r in rows]
    widths = [max(len(c), *(len(row[i]) for row in cells)) for i, c in enumerate(columns)]
    print("  ".join(c.ljust(w) for c, w in zip(columns, widths)).rstrip())
    for row in cells:
        print("  ".join(v.ljust(w) for v, w in zip(row, widths)).rstrip())
    return 0


_catalog_option = add_catalog_argument


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="bat3r", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    cat = sub.add_parser("catalog", help="data catalog commands")
    cat_sub = cat.add_subparsers(dest="catalog_command", required=True)
    val = cat_sub.add_parser("validate", help="print the categories and what each is missing")
    val.add_argument("path", nargs="?", default=None,
                     help="catalog file (default: $BAT3R_CATALOG, else ./data_catalog.yaml)")
    _catalog_option(val)
    val.set_defaults(func=_cmd_catalog_validate)

    st = sub.add_parser("stages", help="print the pipeline's stage table: each stage's inputs, output folder, "
                                       "Prefect task and bat3r_core function, in data-flow order")
    st.add_argument("--json", action="store_true", help="print the rows as JSON")
    st.set_defaults(func=_cmd_stages)

    bs = sub.add_parser("bootstrap", help="run the bootstrap flow locally (the options of python flows/bootstrap.py)",
                        description="Run the bat3r bootstrap flow locally (Prefect starts a temporary server "
                                    "unless PREFECT_API_URL points at one).")
    add_bootstrap_arguments(bs)
    bs.set_defaults(func=_cmd_bootstrap, parser=bs)

    asset = sub.add_parser("asset", help="check a rigged asset, or generate the toy")
    asset_sub = asset.add_subparsers(dest="asset_command", required=True)
    toy = asset_sub.add_parser("toy", help="write the embedded toy quadruped as a rigged GLB")
    toy.add_argument("--out", type=Path, required=True, help="output .glb path")
    toy.add_argument("--coat", default="bay", help="procedural coat texture (bay, chestnut, grey, pinto)")
    toy.set_defaults(func=_cmd_asset_toy)
    chk = asset_sub.add_parser("check", help="preflight a rigged asset: rig report, body frame, renders vs labels, "
                                             "exact-cloud fits; exits 1 naming every failed check")
    chk.add_argument("path", type=Path, help="rigged asset (.glb/.gltf/.fbx/.blend)")
    chk.add_argument("--category", help="catalog category whose asset_scale, up_axis, body_frame and fitting to use")
    _catalog_option(chk)
    chk.add_argument("--out", type=Path, help="folder for the normalised asset, renders and contact_sheet.png "
                                              "(default: a new temporary folder)")
    chk.add_argument("--asset-scale", type=float, default=None, help="file units -> metres (0.01 for centimetres)")
    chk.add_argument("--up-axis", default=None, help="the file's up axis (+Y, +Z, ...; default +Y)")
    chk.add_argument("--views", type=int, default=8, help="canonical views to render (default 8)")
    chk.add_argument("--poses", type=int, default=8, help="random moderate poses to fit (default 8)")
    chk.add_argument("--no-render", action="store_true", help="skip the Blender renders")
    chk.add_argument("--no-fit", action="store_true", help="skip the exact-cloud fits")
    chk.set_defaults(func=_cmd_asset_check)

    rd = sub.add_parser("render", help="render one shard of render jobs with Blender (+ exact ray-cast labels)")
    rd.add_argument("--jobs", required=True, type=Path, help="render jobs (Parquet, docs/CONVENTIONS.md schema)")
    rd.add_argument("--asset", required=True, type=Path, help="rigged asset (.glb/.gltf/.fbx/.blend)")
    rd.add_argument("--out", required=True, type=Path, help="output folder of the training shard")
    rd.add_argument("--preset", default="tiny",
                    help="run preset whose render settings to use (tiny, demo, bench, paper)")
    rd.add_argument("--texture", action="append", help="texture image or toy:<coat> (repeatable; default: the "
                    "asset's own base-colour texture)")
    rd.add_argument("--envmap", action="append", help="HDR/EXR environment map (repeatable; default: a sky)")
    rd.add_argument("--shard", type=int, default=0, help="shard index of the output (part-NNNNN)")
    _catalog_option(rd)
    rd.set_defaults(func=_cmd_render)

    col = sub.add_parser("collection", help="synthesise image collections, or convert COCO annotations")
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
    cc = col_sub.add_parser("coco", help="one category of a COCO instances JSON as a collection (mask PNGs + a "
                            "Parquet index; the photos stay where they are)")
    cc.add_argument("annotations", type=Path, help="COCO instances JSON (images, annotations, categories)")
    cc.add_argument("--images", type=Path, required=True, help="folder the images' file_name entries are relative to")
    cc.add_argument("--category", required=True, help="category name (case-insensitive) or id, e.g. horse")
    cc.add_argument("--out", type=Path, required=True, help="collection folder: masks/, index.parquet, "
                    "coco_conversion.json")
    cc.add_argument("--min-area", type=int, default=1024, help="skip instances with fewer mask pixels (default 1024)")
    cc.add_argument("--largest-only", action="store_true", help="one sample per image: its largest instance")
    cc.add_argument("--exclude-truncated", action="store_true",
                    help="skip instances whose mask touches the image border (cut off by the photo's edge)")
    cc.add_argument("--max-occlusion", type=float, default=None, metavar="F",
                    help="skip instances whose outline runs along other annotated objects (a rider, another "
                    "animal) for more than this fraction of it, e.g. 0.1 (default: keep them)")
    cc.set_defaults(func=_cmd_collection_coco)

    tr = sub.add_parser("train", help="train a dual point map predictor on rendered training shards")
    tr.add_argument("--shards", required=True, type=Path, help="folder of training shards (part-NNNNN.parquet/.npz)")
    tr.add_argument("--out", required=True, type=Path, help="output folder (checkpoint.pt, predictor.pt, log)")
    tr.add_argument("--preset", default="tiny", help="run preset of the data catalog (tiny, demo, bench, paper)")
    tr.add_argument("--steps", type=int, default=None, help="override the preset's number of steps")
    tr.add_argument("--init-from", type=Path, default=None,
                    help="predictor.pt whose weights initialise the model (warm start, e.g. the previous iteration's)")
    tr.add_argument("--mirror", metavar="CATEGORY", default=None,
                    help="mirror samples left-right about CATEGORY's sagittal plane (its rig must be symmetric; "
                         "train.mirror_probability, 0.5 when the preset has none)")
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
    ev.add_argument("--run", type=Path, default=None, help="run folder (<storage>/<category>/<run name>)")
    ev.add_argument("--category", default=None, help="with --run-name: the run of this category in the catalog's "
                                                     "storage root (instead of --run)")
    ev.add_argument("--run-name", default=None, help="the run's name, with --category")
    _catalog_option(ev)
    ev.set_defaults(func=_cmd_evaluate)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
