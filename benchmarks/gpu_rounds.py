"""The training half of a fidelity benchmark on a GPU machine that has torch but not Blender, open3d or Prefect.

``make bench-fidelity`` trains every model on the machine that renders. On a 2-core machine that caps the benchmark
at 32×32 and 5,000 steps, where the benchmark has no headroom (``README.md``). This tool splits a run in two: the
data (canonical renders, the collection, the oracle's true labels, the loop's renders of its fits) is made where
Blender and open3d run, and the models are trained on a GPU machine that only needs torch, numpy, pyarrow and this
repository:

    # here: the data, through the flow (Φ₀'s CPU training is a placeholder: --set train.steps=10)
    python flows/bootstrap.py --category toy --preset bench --iterations 0 --run-name gpu64 --set run.image_size=64 ...
    python benchmarks/gpu_rounds.py pack --run-name gpu64 --out .gpu           # compact copy + plan.json
    # there:
    python benchmarks/gpu_rounds.py train --pack .gpu --out OUT --budget-s 420  # Φ₀, then control and oracle rounds
    # here again:
    python benchmarks/gpu_rounds.py evaluate --run-name gpu64 --predictors OUT  # test metrics of every predictor

A pack holds each training set's shards with the point maps reduced to their occupied entries in float16 (the
storage precision of ``pointmaps.encode_float16``: P relative to the object depth, ≤ 0.5 mm), the background pixels
of ``rgb`` set to 0 (``rgb`` features zero them too; other extractors are refused) and compressed, about 10 KB per
64×64 sample instead of 425 KB, so thousands of samples travel in a few tens of MB. ``train`` unpacks them
into ordinary shards and trains with ``bat3r_core.predictor.train.Trainer`` exactly as the flow would, on CUDA.

Equal compute: the control (canonical renders), the oracle (the collection's images with their hidden true labels)
and, once its renders are packed (``pack --loop-iteration 1`` after the flow ran that iteration's data stages), the
loop round are each trained for the same number of warm-started steps from the same Φ₀. ``train`` measures the
machine's step rate first and sizes Φ₀'s and the rounds' steps to ``--budget-s`` unless ``--phi0-steps`` and
``--round-steps`` fix them; the steps used are recorded in ``timings.json`` beside the predictors. A run with
``train.canonical_replay`` > 0 packs iteration 0's canonical renders beside the loop's (set ``replay``), and the
loop round trains on both mixed at that ratio, as the flow's iteration does. ``--category`` (default ``toy``) names
the run's category, e.g. ``toy_wide``, the category of ``make bench-fidelity``.
"""
from __future__ import annotations

import argparse
import dataclasses
import io
import json
import math
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _results import RESULTS_DIR, record, record_name  # noqa: E402
from bat3r_core import shards  # noqa: E402

PACK_FORMAT = 1
MAX_STORAGE_ERROR_M = 1e-3
"""A packed coordinate may differ from the shard's by at most this much (float16 of values below 2 m: ≤ 0.5 mm)."""
_MAPS = ("P", "Q")
REPLAY = "replay"
"""The packed set of a loop pack that holds iteration 0's canonical renders, when the run's ``train.canonical_replay``
is > 0: the loop round trains on its renders mixed with these, as the flow does; it is no round of its own."""


# ------------------------------------------------------------------------------------------------------ the codec
def pack_arrays(arrays: dict[str, np.ndarray], source: str = "arrays") -> dict[str, np.ndarray]:
    """A training shard's arrays with ``P`` and ``Q`` kept on occupied entries only, as float16, and the boolean
    maps bit-packed. Raises ValueError naming ``source`` when a coordinate would lose more than
    :data:`MAX_STORAGE_ERROR_M` (P must be stored relative to the object depth, as training shards store it)."""
    missing = [k for k in ("occupancy", "mask", *_MAPS) if k not in arrays]
    if missing:
        raise ValueError(f"{source}: not a training shard (missing arrays {missing})")
    occ = np.asarray(arrays["occupancy"], dtype=bool)
    out: dict[str, np.ndarray] = {}
    for k, a in arrays.items():
        a = np.asarray(a)
        if k == "rgb":  # the background does not reach `rgb` features (zeroed there too) and compresses badly
            a = a * np.asarray(arrays["mask"], dtype=bool)[..., None].astype(a.dtype)
        if k in _MAPS:
            values = a[occ]
            half = values.astype(np.float16)
            err = float(np.abs(half.astype(np.float64) - values).max()) if values.size else 0.0
            if not err <= MAX_STORAGE_ERROR_M:
                raise ValueError(f"{source}: array {k!r} loses {err * 1000:.2f} mm in float16 (max |value| "
                                 f"{float(np.abs(values).max()):.2f} m); expected P relative to the object depth")
            out[f"{k}__occupied"] = half
        elif a.dtype == bool:
            out[f"{k}__bits"] = np.packbits(a.reshape(-1))
            out[f"{k}__shape"] = np.asarray(a.shape, dtype=np.int64)
        else:
            out[k] = a
    return out


def unpack_arrays(packed: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The inverse of :func:`pack_arrays`: dense float32 ``P``/``Q`` (0 on empty entries) and bool maps."""
    out: dict[str, np.ndarray] = {}
    for k, a in packed.items():
        if k.endswith("__bits"):
            name = k[: -len("__bits")]
            shape = tuple(int(s) for s in packed[f"{name}__shape"])
            out[name] = np.unpackbits(a, count=int(np.prod(shape))).astype(bool).reshape(shape)
    occ = out["occupancy"]
    for name in _MAPS:
        dense = np.zeros(occ.shape + (3,), dtype=np.float32)
        dense[occ] = packed[f"{name}__occupied"].astype(np.float32)
        out[name] = dense
    for k, a in packed.items():
        if not (k.endswith("__bits") or k.endswith("__shape") or k.endswith("__occupied")):
            out[k] = a
    return out


def pack_folder(src: Path, dst: Path) -> int:
    """Every complete shard of ``src`` packed into ``dst`` (``part-NNNNN.parquet`` as is, ``part-NNNNN.pack.npz``
    compressed); returns the number of samples."""
    dst.mkdir(parents=True, exist_ok=True)
    n = 0
    for i in shards.list_shards(src):
        paths = shards.shard_paths(src, i)
        table, arrays = shards.read_shard(src, i)
        packed = pack_arrays(arrays, source=str(paths.npz))
        buf = io.BytesIO()
        np.savez_compressed(buf, **packed)
        shards.atomic_write_bytes(dst / paths.npz.name.replace(".npz", ".pack.npz"), buf.getvalue())
        shutil.copyfile(paths.parquet, dst / paths.parquet.name)
        n += table.num_rows
    if n == 0:
        raise FileNotFoundError(f"{src}: no complete training shards to pack")
    return n


def unpack_folder(src: Path, dst: Path) -> int:
    """Ordinary training shards in ``dst`` from a packed folder ``src``; returns the number of samples."""
    dst.mkdir(parents=True, exist_ok=True)
    n = 0
    for packed_npz in sorted(src.glob("part-*.pack.npz")):
        stem = packed_npz.name[: -len(".pack.npz")]
        with np.load(packed_npz, allow_pickle=False) as z:
            arrays = unpack_arrays({k: z[k] for k in z.files})
        index = int(stem.split("-")[1])
        table = pq.read_table(src / f"{stem}.parquet")
        shards.write_shard(dst, index, table, arrays)
        n += table.num_rows
    if n == 0:
        raise FileNotFoundError(f"{src}: no packed shards (part-NNNNN.pack.npz)")
    return n


# --------------------------------------------------------------------------------------------------------- pack
def _pack(args: argparse.Namespace) -> None:
    from bench_demo_control import _oracle_dataset

    from bat3r_core.rig_io import load_rig
    from flows._settings import recorded_run

    settings, parameters = recorded_run(args.category, args.run_name)
    out = Path(args.out)
    sets: dict[str, Path] = {}
    if args.loop_iteration is None:
        sets["canonical"] = settings.layout.stage_dir(0, "render")
        sets["oracle"] = _oracle_dataset(settings, load_rig(settings.assets.asset),
                                         settings.layout.root / "fidelity" / "oracle")
    else:
        sets[f"loop{args.loop_iteration}"] = settings.layout.stage_dir(args.loop_iteration, "render")
        if settings.train.canonical_replay > 0:  # the loop round also trains on iteration 0's renders, as the flow
            sets[REPLAY] = settings.layout.stage_dir(0, "render")
    if out.exists():
        shutil.rmtree(out)
    counts = {}
    for name, folder in sets.items():
        counts[name] = pack_folder(Path(folder), out / name)
        print(f"packed {name}: {counts[name]} samples from {folder}", flush=True)
    plan = {"format": PACK_FORMAT, "run_name": args.run_name, "preset": settings.preset,
            "overrides": parameters["overrides"], "seed": int(parameters["seed"]), "samples": counts,
            "model": dataclasses.asdict(settings.model), "train": dataclasses.asdict(settings.train),
            "features": dataclasses.asdict(settings.features)}
    (out / "plan.json").write_text(json.dumps(plan, indent=1))
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    print(f"pack {out}: {size / 2**20:.1f} MiB", flush=True)


# -------------------------------------------------------------------------------------------------------- train
def _configs(plan: dict, steps: int, warm_start: bool):
    from bat3r_core.predictor.config import ModelConfig, TrainConfig

    model = ModelConfig(**plan["model"])
    train = {**plan["train"], **plan.get("train_overrides", {})}
    train["betas"] = tuple(train["betas"])
    return model, TrainConfig(**{**train, "steps": int(steps), "warm_start": warm_start})


def _dataset(plan: dict, folder: Path):
    """The training set of ``folder``; on a CUDA machine held on the GPU (``DeviceDataset``: a step does not wait
    for shard reads and a Python gather: 53 steps/s instead of 16.5 on an H200 at 64×64)."""
    from bat3r_core.predictor.data import ShardDataset, hold_on_device
    from bat3r_core.predictor.features import FeatureConfig, make_feature_fn

    features = dict(plan["features"])
    features.pop("dinov2", None)
    if features.get("extractor") != "rgb":
        raise ValueError(f"plan.json: gpu_rounds trains on `rgb` features only, got {features.get('extractor')!r}")
    dataset = ShardDataset(folder, make_feature_fn(FeatureConfig(**features)),
                           cache_shards=int(plan["train"]["shuffle_shards"]))
    return hold_on_device(dataset, None, float(plan["train"].get("mirror_probability", 0.0)))


def save_half(src: Path, dst: Path) -> Path:
    """``src`` (a ``predictor.pt``) with its floating-point weights stored as float16: half the bytes, so a
    64×64 depth-4 width-32 predictor (24 MB) comes back from the GPU machine within its 16 MiB per file. It loads
    as any predictor (``load_state_dict`` converts to the model's float32); the rounds start from Φ₀'s float16 copy
    too, so every arm starts from the same weights."""
    import torch

    state = torch.load(src, map_location="cpu", weights_only=True)
    state["model"] = {k: v.half() if v.is_floating_point() else v for k, v in state["model"].items()}
    torch.save(state, dst)
    return dst


def train_one(plan: dict, data: Path, out: Path, steps: int, init_from: Path | None,
              until_step: int | None = None, replay: Path | None = None) -> tuple[Path, float]:
    """Train (or resume) one model on ``data`` (mixed with ``replay``'s canonical renders at the plan's
    ``train.canonical_replay``, as the flow's refinement iterations are); returns its predictor (or checkpoint) and
    the seconds it took."""
    from bat3r_core.predictor.data import with_canonical_replay
    from bat3r_core.predictor.train import Trainer

    model, train = _configs(plan, steps, warm_start=init_from is not None)
    dataset = _dataset(plan, data)
    if replay is not None:
        dataset = with_canonical_replay(dataset, _dataset(plan, replay), train.canonical_replay)
    t0 = time.perf_counter()
    path = Trainer(dataset, model, train, out, init_from=init_from).train(until_step)
    return path, time.perf_counter() - t0


def _train(args: argparse.Namespace) -> None:
    import torch

    pack, out = Path(args.pack), Path(args.out)
    work = Path(args.work)
    plan = json.loads((pack / "plan.json").read_text())
    if plan.get("format") != PACK_FORMAT:
        raise ValueError(f"{pack / 'plan.json'}: expected pack format {PACK_FORMAT}, got {plan.get('format')}")
    _configs(plan, 1, False)  # a plan no round can train is refused before any round starts
    overrides = {k: int(v) for k, v in (("batch_size", args.batch_size), ("warmup_steps", args.warmup_steps))
                 if v is not None}
    if overrides:  # every model of the call (Φ₀ and each round) with these settings
        plan["train_overrides"] = overrides
        (work / "plan.json").parent.mkdir(parents=True, exist_ok=True)
        (work / "plan.json").write_text(json.dumps(plan))
    plan_file = work / "plan.json" if overrides else pack / "plan.json"
    t_start = time.perf_counter()
    timings: dict = {"device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu",
                     "torch": torch.__version__, "run_name": plan["run_name"], "samples": plan["samples"]}
    for name in plan["samples"]:
        n = unpack_folder(pack / name, work / name)
        print(f"unpacked {name}: {n} samples", flush=True)
    timings["unpack_s"] = round(time.perf_counter() - t_start, 1)
    out.mkdir(parents=True, exist_ok=True)
    phi0 = Path(args.phi0) if args.phi0 else None
    phi0_steps, round_steps = args.phi0_steps, args.round_steps
    if phi0 is None and (phi0_steps is None or round_steps is None):
        # probe: steps/s of this model on this machine (after 20 warm-up steps), then size Φ₀ and the (parallel)
        # rounds to what is left of the budget
        from bat3r_core.predictor.train import Trainer

        model, train = _configs(plan, 100_000, warm_start=False)
        shutil.rmtree(work / "probe", ignore_errors=True)
        probe = Trainer(_dataset(plan, work / "canonical"), model, train, work / "probe", progress=None)
        probe.train(until_step=20)
        t0 = time.perf_counter()
        probe.train(until_step=220)
        rate = 200 / max(time.perf_counter() - t0, 1e-6)
        del probe
        left = args.budget_s - (time.perf_counter() - t_start)
        phi0_steps = phi0_steps or max(1000, int(rate * 0.5 * left) // 500 * 500)
        round_steps = round_steps or max(500, phi0_steps // 2)
        timings["probe_steps_per_s"] = round(rate, 1)
        print(f"probe: {rate:.1f} steps/s; Φ₀ {phi0_steps} steps, rounds {round_steps} steps", flush=True)
    if phi0 is None:
        full, secs = train_one(plan, work / "canonical", work / "phi0", phi0_steps, None)
        timings["phi0"] = {"steps": phi0_steps, "seconds": round(secs, 1), "steps_per_s": round(phi0_steps / secs, 1)}
        phi0 = save_half(full, out / "phi0.pt")
        print(f"Φ₀: {phi0_steps} steps in {secs:.0f} s", flush=True)
    rounds = args.rounds or ["control" if name == "canonical" else name for name in plan["samples"] if name != REPLAY]
    procs = {}
    for name in rounds:
        data = work / ("canonical" if name == "control" else name)
        cmd = [sys.executable, __file__, "train-one", "--plan", str(plan_file), "--data", str(data),
               "--out", str(work / name), "--steps", str(round_steps), "--init-from", str(phi0),
               "--timing", str(out / f"{name}.timing.json")]
        if name.startswith("loop") and REPLAY in plan["samples"]:
            cmd += ["--replay", str(work / REPLAY)]
        procs[name] = subprocess.Popen(cmd)
    for name, proc in procs.items():
        if proc.wait() != 0:
            raise RuntimeError(f"round {name!r} failed (exit {proc.returncode})")
        save_half(work / name / "predictor.pt", out / f"{name}.pt")
        timings[name] = json.loads((out / f"{name}.timing.json").read_text())
        (out / f"{name}.timing.json").unlink()
    timings["round_steps"] = round_steps
    timings["batch_size"] = int(_configs(plan, 1, False)[1].batch_size)
    timings["total_s"] = round(time.perf_counter() - t_start, 1)
    (out / "timings.json").write_text(json.dumps(timings, indent=1))
    print(json.dumps(timings, indent=1), flush=True)


def _train_one_cmd(args: argparse.Namespace) -> None:
    plan = json.loads(Path(args.plan).read_text())
    path, secs = train_one(plan, Path(args.data), Path(args.out), args.steps,
                           Path(args.init_from) if args.init_from else None,
                           replay=Path(args.replay) if args.replay else None)
    Path(args.timing).write_text(json.dumps({"steps": args.steps, "seconds": round(secs, 1),
                                             "steps_per_s": round(args.steps / secs, 1)}))


# ----------------------------------------------------------------------------------------------------- evaluate
def _evaluate(args: argparse.Namespace) -> None:
    from bench_demo_control import _test_metrics

    from flows._settings import recorded_run

    settings, parameters = recorded_run(args.category, args.run_name)
    seed = int(parameters["seed"])
    folder = Path(args.predictors)
    rows = {}
    for name in args.names:
        ckpt = folder / f"{name}.pt"
        iteration = 0 if name == "phi0" else 1
        out = settings.layout.root / "gpu" / args.tag / name
        row = _test_metrics(settings, ckpt, out, iteration, seed=seed + iteration)
        rows[name] = {k: row[k] for k in ("mcd_cm", "pct_mcd_over_5cm", "rot_err_deg", "mv_mcd_cm") if k in row}
        rows[name]["test_infer"] = str(out / "test_infer")
        print(f"{name}: test mCD {row['mcd_cm']:.2f} cm, >5 cm {row['pct_mcd_over_5cm']:.1f} %, "
              f"ΔR {row['rot_err_deg']:.1f}°", flush=True)
    from bench_fidelity import map_floors

    rows["floors"] = map_floors(settings)
    print(f"map floors: {rows['floors']}", flush=True)
    Path(args.json).write_text(json.dumps(rows, indent=1))


# ------------------------------------------------------------------------------------------------------- record
ARMS = {"phi0": ("phi0", 0), "control": ("control", 1), "oracle": ("oracle", 1), "loop1": ("loop", 1)}
"""Predictor file name → (arm, iteration) in ``bench_fidelity``'s figure names."""


def read_evaluations(paths: list[str]) -> tuple[dict[str, float], dict[str, dict]]:
    """The map floors and the per-predictor test rows of ``evaluate --json`` files (later files win a name)."""
    floors: dict[str, float] = {}
    rows: dict[str, dict] = {}
    for path in paths:
        data = json.loads(Path(path).read_text())
        floors.update({k: float(v) for k, v in data.pop("floors", {}).items()})
        rows.update(data)
    return floors, rows


def _record(args: argparse.Namespace) -> dict:
    """``benchmarks/results/<record-as>.json`` and RESULTS.md from the evaluations (``evaluate --json``), the device
    timings (``timings.json``) and the loop run's fits (their pose errors against the hidden truth, the filter's
    precision), with ``bench_fidelity``'s verdict lines."""
    from bench_fidelity import gap_recovered, map_error_figures, verdict_lines
    from bench_fit_oracle import filter_figures, pose_quality

    from bat3r_core import evaluation_truth
    from bat3r_core.rig_io import load_rig
    from flows._settings import recorded_run

    settings, parameters = recorded_run(args.category, args.run_name)
    floors, tests = read_evaluations(args.evaluations)
    figures: dict[str, float] = {"iterations": 1, "crop_px": settings.model.resolution, **floors}
    for name, row in tests.items():
        arm, it = ARMS[name]
        figures[f"mcd_{arm}_iter{it}"] = round(row["mcd_cm"], 3)
        figures[f"pct_over_5cm_{arm}_iter{it}"] = round(row["pct_mcd_over_5cm"], 1)
        figures[f"rot_err_deg_{arm}_iter{it}"] = round(row["rot_err_deg"], 1)
    for arm in ("loop", "control", "oracle"):
        figures[f"mcd_{arm}_iter0"] = figures["mcd_phi0_iter0"]
        figures[f"rot_err_deg_{arm}_iter0"] = figures["rot_err_deg_phi0_iter0"]
    control, oracle, loop = (figures[f"mcd_{a}_iter1"] for a in ("control", "oracle", "loop"))
    figures["headroom"] = round(oracle / control, 3)
    c, o, lp = (figures[f"rot_err_deg_{a}_iter1"] for a in ("control", "oracle", "loop"))
    for key, share in (("loop_gap_recovered", gap_recovered(control, oracle, loop)),
                       ("loop_rot_gap_recovered", gap_recovered(c, o, lp))):
        if math.isfinite(share):  # NaN: the oracle is no better than the control, no gap to close
            figures[key] = round(share, 3)
    devices = set()
    for path in args.timings:
        t = json.loads(Path(path).read_text())
        devices.add(t["device"])
        if "phi0" in t:
            figures["phi0_steps"] = t["phi0"]["steps"]
            figures["phi0_steps_per_s"] = t["phi0"]["steps_per_s"]
        figures["round_steps"] = t["round_steps"]
        figures["batch_size"] = t["batch_size"]
        for name in ("control", "oracle", "loop1"):
            if name in t:
                figures[f"{ARMS[name][0]}_round_steps_per_s"] = t[name]["steps_per_s"]
    loop_settings, _ = recorded_run(args.category, args.loop_run)
    rows = shards.read_table(loop_settings.layout.stage_dir(1, "fit")).to_pylist()
    gt = evaluation_truth.load_ground_truth(Path(loop_settings.collection["ground_truth"]) / "ground_truth.npz")
    quality = pose_quality(rows, gt, load_rig(loop_settings.assets.asset))
    figures.update({f"fit_{k}": round(float(v), 3) for k, v in quality.items()})
    figures.update(filter_figures(loop_settings.layout, 1))
    figures.update(map_error_figures(settings, {ARMS[n][0]: Path(row["test_infer"]) for n, row in tests.items()}))
    lines = verdict_lines(figures)
    lines.insert(2, f"camera rotation error ΔR: Φ₀ {figures['rot_err_deg_phi0_iter0']:.1f}°, control {c:.1f}°, oracle "
                    f"{o:.1f}°, loop {lp:.1f}°" + (f" (the loop closes {figures['loop_rot_gap_recovered']:.0%} of the "
                                                  "control -> oracle gap in ΔR)" if "loop_rot_gap_recovered" in figures
                                                  else ""))
    lines.append(f"fits of Φ₀'s collection predictions: median vertex error {quality['median_vertex_err_cm']:.2f} cm "
                 f"against {quality['median_rest_pose_vertex_err_cm']:.2f} for the rest pose (goal: below it: "
                 f"{'met' if quality['median_vertex_err_cm'] < quality['median_rest_pose_vertex_err_cm'] else 'NOT met'}"
                 f"); {quality['pct_better_than_rest']:.1f} % beat the rest pose"
                 + (f"; the filter's kept half beats it with precision {figures['filter_precision']:.2f} (goal >= 0.8: "
                    f"{'met' if figures['filter_precision'] >= 0.8 else 'NOT met'})" if "filter_precision" in figures
                    else ""))
    notes = (f"{args.category} at {settings.model.resolution}x{settings.model.resolution}, run {args.run_name!r} (bench preset, "
             f"overrides {parameters['overrides']}); the data (canonical "
             f"renders, collection, test split, the oracle's true labels, the loop's renders of its filtered fits, "
             f"run {args.loop_run!r}) made on this machine, every model trained on {', '.join(sorted(devices))} by "
             f"benchmarks/gpu_rounds.py: Φ₀ {figures.get('phi0_steps', 0):.0f} steps, then one warm-started round of "
             f"{figures['round_steps']:.0f} steps per arm, batch {figures['batch_size']:.0f}. " + "; ".join(lines))
    record(args.record_as, figures, notes=notes, results_dir=args.results_dir)
    from bench_fidelity import plot

    arms = {arm: {0: {"mcd_cm": figures["mcd_phi0_iter0"]}, 1: {"mcd_cm": figures[f"mcd_{arm}_iter1"]}}
            for arm in ("loop", "control", "oracle")}
    plot(Path(args.results_dir or RESULTS_DIR) / f"{args.record_as}.png", arms, figures)
    print(notes, flush=True)
    return figures


def _compare(args: argparse.Namespace) -> dict:
    """``results/<record-as>.json``: the test mCD, ΔR and map errors (``bench_fidelity.map_error_figures``) of the
    predictors of ``evaluate --json`` files side by side, with ``--notes`` saying what differs between them."""
    from bench_fidelity import map_error_figures

    from flows._settings import recorded_run

    settings, _ = recorded_run(args.category, args.run_name)
    _, tests = read_evaluations(args.evaluations)
    figures: dict[str, float] = {}
    for name, row in tests.items():
        figures[f"mcd_{name}"] = round(row["mcd_cm"], 3)
        figures[f"rot_err_deg_{name}"] = round(row["rot_err_deg"], 1)
    figures.update(map_error_figures(settings, {name: Path(row["test_infer"]) for name, row in tests.items()}))
    record(args.record_as, figures, notes=args.notes, results_dir=args.results_dir)
    print(json.dumps(figures, indent=1), flush=True)
    return figures


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    pk = sub.add_parser("pack", help="compact copy of a run's training sets and plan.json (where the run is)")
    pk.add_argument("--run-name", required=True)
    pk.add_argument("--category", default="toy", help="the run's category (default: toy; e.g. toy_wide)")
    pk.add_argument("--out", required=True)
    pk.add_argument("--loop-iteration", type=int, default=None,
                    help="pack the loop's renders of this iteration instead of the canonical and oracle sets")
    pk.set_defaults(func=_pack)
    tr = sub.add_parser("train", help="unpack and train Φ₀ and the rounds (on the GPU machine)")
    tr.add_argument("--pack", required=True)
    tr.add_argument("--out", required=True)
    tr.add_argument("--work", default="/tmp/gpu_rounds")
    tr.add_argument("--budget-s", type=float, default=420.0)
    tr.add_argument("--phi0", default=None, help="a trained Φ₀ (predictor.pt): train only the rounds from it")
    tr.add_argument("--phi0-steps", type=int, default=None)
    tr.add_argument("--round-steps", type=int, default=None)
    tr.add_argument("--rounds", nargs="*", default=None, help="rounds to train (default: one per packed set)")
    tr.add_argument("--batch-size", type=int, default=None, help="override the run's batch size for every model")
    tr.add_argument("--warmup-steps", type=int, default=None, help="override the run's warm-up for every model")
    tr.set_defaults(func=_train)
    one = sub.add_parser("train-one", help=argparse.SUPPRESS)
    one.add_argument("--plan", required=True)
    one.add_argument("--data", required=True)
    one.add_argument("--out", required=True)
    one.add_argument("--steps", type=int, required=True)
    one.add_argument("--init-from", default=None)
    one.add_argument("--timing", required=True)
    one.add_argument("--replay", default=None, help="canonical renders mixed in (train.canonical_replay)")
    one.set_defaults(func=_train_one_cmd)
    ev = sub.add_parser("evaluate", help="test metrics of trained predictors (where the run is)")
    ev.add_argument("--run-name", required=True)
    ev.add_argument("--category", default="toy", help="the run's category (default: toy; e.g. toy_wide)")
    ev.add_argument("--predictors", required=True, help="folder of <name>.pt")
    ev.add_argument("--names", nargs="+", default=["phi0", "control", "oracle"])
    ev.add_argument("--tag", default="call1")
    ev.add_argument("--json", required=True)
    ev.set_defaults(func=_evaluate)
    rc = sub.add_parser("record", help="results/<record-as>.json and RESULTS.md from evaluations and timings")
    rc.add_argument("--run-name", required=True)
    rc.add_argument("--category", default="toy", help="the run's category (default: toy; e.g. toy_wide)")
    rc.add_argument("--loop-run", required=True, help="the bootstrap run whose iteration 1 made the loop's data")
    rc.add_argument("--evaluations", nargs="+", required=True, help="evaluate --json files")
    rc.add_argument("--timings", nargs="+", required=True, help="timings.json files of the train calls")
    rc.add_argument("--record-as", type=record_name, default="fidelity_gpu64")
    rc.add_argument("--results-dir", type=Path, default=None)
    rc.set_defaults(func=_record)
    cp = sub.add_parser("compare", help="results/<record-as>.json: predictors of evaluate --json files side by side")
    cp.add_argument("--run-name", required=True)
    cp.add_argument("--category", default="toy", help="the run's category (default: toy; e.g. toy_wide)")
    cp.add_argument("--evaluations", nargs="+", required=True)
    cp.add_argument("--record-as", type=record_name, required=True)
    cp.add_argument("--notes", default="")
    cp.add_argument("--results-dir", type=Path, default=None)
    cp.set_defaults(func=_compare)
    args = p.parse_args(argv)
    args.func(args)


if __name__ == "__main__":
    main()
