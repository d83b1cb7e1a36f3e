"""Render a shard of jobs in worker subprocesses and assemble the training shard (no bpy here).

:func:`render_shard` spawns ``python -m bat3r_core.render.worker`` (never forks a process that imported bpy),
streams the shard's jobs to it on stdin, starts a fresh process every ``RenderConfig.recycle_every`` images, kills
a process that makes no progress for ``timeout_s``, and when a process dies retries the jobs it had not finished
(at most ``RenderConfig.retries`` restarts per shard; a job that was being rendered during two crashes is recorded
as ``failed`` and skipped). Before rendering it skins the rig with each job's θ and global similarity
(:mod:`bat3r_core.skinning`) and hands the worker those vertices to render; afterwards
:mod:`bat3r_core.pointmaps` ray-casts the same vertices through the job's camera, so labels and pixels agree by
construction. The shard is written with :func:`bat3r_core.shards.write_shard` in the "Training samples" format of
docs/CONVENTIONS.md.
"""
from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np

from bat3r_core.config_utils import to_mapping
from bat3r_core.labels import label_job, posed_vertices
from bat3r_core.metrics import mask_iou
from bat3r_core.render.config import RenderConfig, SceneAssets, render_config
from bat3r_core.render.jobs import RenderJob, job_to_dict, read_jobs
from bat3r_core.rig import Rig
from bat3r_core.stopping import raise_if_stop_requested, stop_requested

__all__ = ["ShardResult", "render_shard", "render_jobs", "render_command", "convert_to_glb"]

_PROJECT_ROOT = Path(__file__).resolve().parents[2]
PROGRESS_INTERVAL_S = 30.0
"""Seconds between two progress reports of a shard being rendered (images done, images per second)."""

_logger = logging.getLogger(__name__)


def _log_progress(progress: dict) -> None:
    _logger.info("rendering %s: %d/%d images done (%.1f images/s)", progress["shard"], progress["done"],
                 progress["total"], progress["images_per_s"])


@dataclass(frozen=True)
class ShardResult:
    """What :func:`render_shard` wrote.

    Attributes:
        parquet, npz: the shard's files. num_ok / num_failed: rows with status ok / not ok.
        processes: worker processes started (recycling and retries included). crashes: processes that died
        or were killed before finishing their jobs. seconds: wall time.
    """

    parquet: Path
    npz: Path
    num_ok: int
    num_failed: int
    processes: int
    crashes: int
    seconds: float


def convert_to_glb(asset: str | os.PathLike, out_dir: str | os.PathLike) -> Path:
    """``asset`` itself if it is glTF/GLB, else its conversion (FBX/.blend, through Blender) in ``out_dir``."""
    asset = Path(asset)
    if not asset.is_file():
        raise FileNotFoundError(f"asset {asset} does not exist")
    if asset.suffix.lower() in (".glb", ".gltf"):
        return asset
    if asset.suffix.lower() not in (".fbx", ".blend"):
        raise ValueError(f"asset must be .glb, .gltf, .fbx or .blend, got {asset.name}")
    out = Path(out_dir) / f"{asset.stem}.converted.glb"
    out.parent.mkdir(parents=True, exist_ok=True)
    proc = subprocess.run([sys.executable, "-m", "bat3r_core.render.blender_convert", str(asset), str(out)],
                          capture_output=True, text=True, env=_worker_env(None), timeout=600)
    if proc.returncode != 0 or not out.is_file():
        raise RuntimeError(f"converting {asset} to GLB failed (exit {proc.returncode}): "
                           f"{(proc.stderr or proc.stdout)[-2000:]}")
    return out


def _worker_env(gpu_index: int | None) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(_PROJECT_ROOT)] + [p for p in [env.get("PYTHONPATH")] if p])
    if gpu_index is not None:
        env["CUDA_VISIBLE_DEVICES"] = str(gpu_index)
    return env


def _read_results(path: Path) -> dict[int, dict]:
    out: dict[int, dict] = {}
    if path.is_file():
        for line in path.read_text(encoding="utf-8").splitlines():
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:  # a line cut short by a crash
                continue
            out[int(rec["index"])] = rec
    return out


def _tail(path: Path, n: int = 1500) -> str:
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return ""
    return text[-n:].strip()


def _run_process(rows: list[dict], spec_path: Path, results_path: Path, workdir: Path, log_path: Path,
                 config: RenderConfig, env: dict, on_worker_start: Callable[[subprocess.Popen], None] | None,
                 on_results: Callable[[int], None] | None = None) -> tuple[int, bool, bool]:
    """One worker process over ``rows``; returns (exit code, killed for lack of progress, start-up succeeded)."""
    cmd = [sys.executable, "-m", "bat3r_core.render.worker", "--spec", str(spec_path), "--results",
           str(results_path), "--out", str(workdir)]
    with open(log_path, "a", encoding="utf-8") as log:
        proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=log, stderr=subprocess.STDOUT, env=env,
                                text=True, cwd=str(_PROJECT_ROOT))

        def feed() -> None:
            try:
                for row in rows:
                    proc.stdin.write(json.dumps(row) + "\n")
                proc.stdin.close()
            except (BrokenPipeError, OSError, ValueError):
                pass  # the process died; the runner notices

        feeder = threading.Thread(target=feed, daemon=True)
        feeder.start()
        if on_worker_start is not None:
            on_worker_start(proc)
        wanted = {r["index"] for r in rows}
        done = len(wanted & set(_read_results(results_path)))
        ready_file = workdir / f"ready-{proc.pid}"
        last_progress = time.monotonic()
        ready = False
        killed = False
        while proc.poll() is None:
            time.sleep(0.05)
            if stop_requested():  # a rerun renders the shard again (the work folder is scratch)
                proc.kill()
                proc.wait()
                feeder.join(timeout=5)
                raise_if_stop_requested(f"rendering {spec_path.parent} ({done} of {len(wanted)} images done)")
            if not ready and ready_file.exists():
                ready, last_progress = True, time.monotonic()
            results = _read_results(results_path)
            now_done = len(wanted & set(results))
            if now_done != done:
                done, last_progress = now_done, time.monotonic()
                if on_results is not None:
                    on_results(len(results))
            limit = config.timeout_s if ready else config.startup_timeout_s
            if time.monotonic() - last_progress > limit:
                proc.kill()
                killed = True
                proc.wait()
        feeder.join(timeout=5)
        return proc.returncode, killed, ready or ready_file.exists()


def _render_images(jobs: Sequence[RenderJob], posed: Sequence[np.ndarray | None], assets: SceneAssets,
                   config: RenderConfig, workdir: Path, debug_vertices: bool, gpu_index: int | None,
                   on_worker_start: Callable[[subprocess.Popen], None] | None,
                   progress: Callable[[dict], None] | None = None, progress_interval_s: float = PROGRESS_INTERVAL_S,
                   shard: str = "") -> tuple[dict[int, dict], int, int]:
    """Render all jobs into ``workdir`` (``posed[i]``: job i's skinned vertices, None when it cannot be posed);
    returns (results by job index, processes started, crashes). ``progress`` is called every
    ``progress_interval_s`` seconds while images finish, and once all are done, with ``{"shard", "done", "total",
    "images_per_s"}``."""
    t_start = time.monotonic()
    last_report = [t_start]

    def on_results(n_done: int) -> None:
        now = time.monotonic()
        if progress is not None and (now - last_report[0] >= progress_interval_s or n_done == len(jobs)):
            last_report[0] = now
            progress({"shard": shard, "done": n_done, "total": len(jobs),
                      "images_per_s": n_done / max(now - t_start, 1e-9)})

    spec_path = workdir / "spec.json"
    spec_path.write_text(json.dumps({"asset": str(assets.asset), "textures": list(assets.textures),
                                     "envmaps": list(assets.envmaps), "config": to_mapping(config),
                                     "debug_vertices": bool(debug_vertices)}))
    results_path = workdir / "results.jsonl"
    log_path = workdir / "worker.log"
    env = _worker_env(gpu_index)
    rows = []
    for i, job in enumerate(jobs):
        row = job_to_dict(job)
        row["index"] = i
        if posed[i] is not None:  # the worker renders exactly these vertices
            row["vertices_file"] = str(workdir / f"pose-{i:06d}.npy")
            np.save(row["vertices_file"], posed[i].astype(np.float32))
        rows.append(row)
    pending = list(range(len(jobs)))
    failed: dict[int, dict] = {}
    blame: dict[int, int] = {}
    processes = crashes = 0
    while pending:
        batch = pending[:config.recycle_every]
        processes += 1
        rc, killed, ready = _run_process([rows[i] for i in batch], spec_path, results_path, workdir, log_path, config,
                                         env, on_worker_start, on_results)
        results = _read_results(results_path)
        pending = [i for i in pending if i not in results and i not in failed]
        unfinished = [i for i in batch if i not in results and i not in failed]
        if not unfinished:
            continue
        crashes += 1
        why = ("killed after no progress for its timeout" if killed else f"exited with code {rc}")
        if not ready:
            why += " before its scene was ready"
        suspect = unfinished[0]
        blame[suspect] = blame.get(suspect, 0) + int(ready)  # a start-up failure is no job's fault
        if blame[suspect] >= 2:
            failed[suspect] = {"status": "failed", "reason": f"the render worker crashed twice on this job "
                                                             f"({why}); log: {_tail(log_path, 300)}"}
            pending.remove(suspect)
        if crashes > config.retries:
            for i in pending:
                failed[i] = {"status": "failed", "reason": f"render worker {why}; gave up after {crashes} crashes "
                                                           f"({config.retries} retries); log: {_tail(log_path)}"}
            pending = []
    results = _read_results(results_path)
    results.update(failed)
    return results, processes, crashes


def render_shard(jobs: Sequence[RenderJob], assets: SceneAssets, out_dir: str | os.PathLike, shard_index: int = 0,
                 config: RenderConfig | str | None = None, rig: Rig | None = None, debug_vertices: bool = False,
                 gpu_index: int | None = None, min_mask_iou: float = 0.8,
                 on_worker_start: Callable[[subprocess.Popen], None] | None = None,
                 progress: Callable[[dict], None] | None = _log_progress,
                 progress_interval_s: float = PROGRESS_INTERVAL_S) -> ShardResult:
    """Render ``jobs`` and write training shard ``part-<shard_index>`` into ``out_dir``.

    Args:
        jobs: render jobs (one image each); all must share one image size.
        assets: the category's rigged asset (GLB; FBX/.blend are converted), textures and environment maps.
        config: a :class:`RenderConfig` or a mapping of its fields (default: its defaults).
        rig: the rig of ``assets.asset`` (loaded when None).
        debug_vertices: also store the depsgraph-evaluated posed vertices Blender rendered
            (``blender_vertices (N, V, 3) float32``, bat3r world frame) for checking against skinning.
        gpu_index: pins the worker to this GPU (``CUDA_VISIBLE_DEVICES``) when the device is a GPU.
        min_mask_iou: rows whose Blender mask and ray-cast layer-0 occupancy agree less than this (IoU, for masks
            of at least 50 pixels) get status ``mask_mismatch``.
        on_worker_start: called with each worker ``Popen`` right after it starts (monitoring, fault injection).
        progress: called every ``progress_interval_s`` seconds while images finish and once when the last one
            has, with ``{"shard", "done", "total", "images_per_s"}`` (default: an INFO line on this module's
            logger); None reports nothing.

    Returns:
        :class:`ShardResult`. The npz holds ``rgb (N, H, W, 3) uint8``, ``mask (N, H, W) bool``,
        ``P``/``Q (N, H, W, K, 3) float16`` (P relative to the object depth, see :mod:`bat3r_core.pointmaps`),
        ``occupancy (N, H, W, K) bool``, ``object_depth (N,) float32``, ``K_intrinsics (N, 3, 3) float32``; rows
        that failed hold zeros. Parquet rows: the job's columns plus ``status``, ``reason``, ``mask_iou``. The
        same jobs give the same bytes (Cycles is seeded per job; no time is stored), so a re-rendered shard keeps
        the cache keys of every stage that reads it; the timings are in the result and the progress lines.
    """
    from bat3r_core.pointmaps import encode_float16, storage_dtype
    from bat3r_core.rig_io import load_rig
    from bat3r_core.shards import shard_name, write_shard

    t0 = time.perf_counter()
    config = render_config(config)
    jobs = list(jobs)
    if not jobs:
        raise ValueError("jobs must not be empty")
    bad = [type(j).__name__ for j in jobs if not isinstance(j, RenderJob)]
    if bad:
        raise TypeError(f"jobs must be RenderJob objects, got {bad[0]}")
    sizes = {(int(j.camera_numbers().get("width", 0)), int(j.camera_numbers().get("height", 0))) for j in jobs}
    if len(sizes) != 1:
        raise ValueError(f"all jobs of a shard must share one image size, got {sorted(sizes)}")
    width, height = sizes.pop()
    if width <= 0 or height <= 0:
        raise ValueError(f"jobs must have a positive image size, got {width}x{height}")
    out_dir = Path(out_dir)
    workdir = out_dir / f".work-{shard_name(shard_index)}"
    if workdir.exists():
        import shutil

        shutil.rmtree(workdir)
    workdir.mkdir(parents=True)
    glb = convert_to_glb(assets.asset, workdir)
    assets = SceneAssets(asset=str(glb), textures=assets.textures, envmaps=assets.envmaps)
    rig = rig if rig is not None else load_rig(glb)
    posed = []
    for job in jobs:
        ok = not job.problems(rig.num_joints)
        posed.append(posed_vertices(rig, job) if ok else None)  # a bad job is reported by the worker
    results, processes, crashes = _render_images(jobs, posed, assets, config, workdir, debug_vertices, gpu_index,
                                                 on_worker_start, progress, progress_interval_s,
                                                 shard=str(out_dir / shard_name(shard_index)))
    n, k = len(jobs), config.num_layers
    # float16 labels when the rig is small enough for sub-millimetre round trips, float32 otherwise
    label_dtype = storage_dtype(rig.rest_vertices, max((abs(j.global_scale) for j in jobs), default=1.0))
    arrays = {
        "rgb": np.zeros((n, height, width, 3), np.uint8), "mask": np.zeros((n, height, width), bool),
        "P": np.zeros((n, height, width, k, 3), label_dtype), "Q": np.zeros((n, height, width, k, 3), label_dtype),
        "occupancy": np.zeros((n, height, width, k), bool), "object_depth": np.zeros(n, np.float32),
        "K_intrinsics": np.zeros((n, 3, 3), np.float32),
    }
    if debug_vertices:
        arrays["blender_vertices"] = np.zeros((n, rig.num_vertices, 3), np.float32)
    rows = []
    for i, job in enumerate(jobs):
        rec = results.get(i, {"status": "failed", "reason": "no result from the render worker"})
        status, reason, iou = rec["status"], rec["reason"], float("nan")
        if status == "ok":
            try:
                with np.load(workdir / f"job-{i:06d}.npz", allow_pickle=False) as z:
                    arrays["rgb"][i] = z["rgb"]
                    arrays["mask"][i] = z["mask"]
                    if debug_vertices:
                        arrays["blender_vertices"][i] = z["posed_vertices"]
                _, maps = label_job(rig, job, k, posed[i])
                iou = mask_iou(arrays["mask"][i], maps.mask)
                if maps.status != "ok":
                    status, reason = maps.status, maps.reason
                elif iou < min_mask_iou and arrays["mask"][i].sum() >= 50:
                    status, reason = "mask_mismatch", (f"Blender mask and ray-cast occupancy disagree "
                                                       f"(IoU {iou:.3f} < {min_mask_iou})")
                p16, q16 = encode_float16(maps.P, maps.Q, maps.occupancy, np.float64(maps.object_depth),
                                          label_dtype)
                arrays["P"][i], arrays["Q"][i] = p16, q16
                arrays["occupancy"][i] = maps.occupancy
                arrays["object_depth"][i] = maps.object_depth
                arrays["K_intrinsics"][i] = job.camera.K
            except (OSError, ValueError, KeyError) as e:
                status, reason = "failed", f"labelling failed: {type(e).__name__}: {e}"
        row = job_to_dict(job)
        row.update(status=status, reason=reason, mask_iou=iou)  # no wall times: the shard's bytes are its content
        rows.append(row)
    paths = write_shard(out_dir, shard_index, rows, arrays)
    import shutil

    shutil.rmtree(workdir, ignore_errors=True)
    n_ok = sum(r["status"] == "ok" for r in rows)
    return ShardResult(parquet=paths.parquet, npz=paths.npz, num_ok=n_ok, num_failed=n - n_ok, processes=processes,
                       crashes=crashes, seconds=time.perf_counter() - t0)


def render_jobs(jobs: Sequence[RenderJob], assets: SceneAssets, out_dir: str | os.PathLike,
                config: RenderConfig | str | None = None, shard_size: int = 256, start_index: int = 0,
                skip_complete: bool = True, **kwargs) -> list[ShardResult | None]:
    """Split ``jobs`` into shards of ``shard_size`` and render each with :func:`render_shard` (sequentially).

    Shards already complete in ``out_dir`` are skipped when ``skip_complete`` (their entry is None).
    """
    from bat3r_core.shards import shard_paths

    if shard_size < 1:
        raise ValueError(f"shard_size must be >= 1, got {shard_size}")
    jobs = list(jobs)
    out = []
    for s, start in enumerate(range(0, len(jobs), shard_size)):
        index = start_index + s
        if skip_complete and shard_paths(out_dir, index).complete:
            out.append(None)
            continue
        out.append(render_shard(jobs[start:start + shard_size], assets, out_dir, index, config, **kwargs))
    return out


def render_command(jobs: str | os.PathLike, asset: str | os.PathLike, out: str | os.PathLike,
                   config: RenderConfig | Mapping | None = None, textures: Sequence[str] | None = None,
                   envmaps: Sequence[str] = (), shard_index: int = 0, debug_vertices: bool = False) -> ShardResult:
    """``bat3r render --jobs JOBS.parquet --asset ASSET --out DIR``: render one job file as one shard by hand.

    No ``textures``: the asset's own base-colour texture. Returns the :class:`ShardResult` (its files are
    ``DIR/part-<shard_index>.parquet/.npz``).
    """
    job_list = read_jobs(jobs)
    assets = SceneAssets(asset=str(asset), textures=tuple(textures or ()),
                         envmaps=tuple(envmaps))
    return render_shard(job_list, assets, out, shard_index, config, debug_vertices=debug_vertices)
