"""Benchmark: Blender (Cycles, CPU) render throughput of the toy, and one process per shard vs per image.

Figures (written to benchmarks/results/render.json and benchmarks/RESULTS.md):

* ``images_per_s_128``, ``images_per_s_160``, ``images_per_s_128_denoise``: images per second of one warm worker
  process (16 spp; denoising off, off, on), i.e. the steady state of a shard: the first image of the process
  (kernel and scene setup) is left out. Each image includes posing, camera, world, the Cycles render with the
  Object Index pass, and writing/reading RGB and mask.
* ``*_from_cpu_time``: the same from the worker's CPU time per image (``2 / cpu_s``): what two free cores would
  deliver; on a shared machine other jobs inflate wall time but not CPU time.
* ``first_image_s``, ``process_start_s``: the one-off costs a process pays (start + asset load, first render).
* ``per_shard_s``, ``per_image_s``, ``per_shard_speedup``: the same 32 jobs (128 x 128, 16 spp) rendered by one
  worker process versus one process per image, measured one after the other in this run (wall time, process
  start included); ``per_shard_speedup_from_cpu_time``: the same ratio of the workers' total CPU time.

Usage: ``python benchmarks/bench_render.py [--jobs 32]`` (about 2-3 minutes on 2 shared cores).
"""
from __future__ import annotations

import argparse
import os
import resource
import shutil
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _results import record  # noqa: E402

from bat3r_core.datasets import canonical_jobs  # noqa: E402
from bat3r_core.render.config import RenderConfig, SceneAssets  # noqa: E402
from bat3r_core.labels import posed_vertices  # noqa: E402
from bat3r_core.render.runner import _render_images  # noqa: E402
from bat3r_core.rig_io import save_rig_glb  # noqa: E402
from bat3r_core.toy import TOY_BODY_FRAME, TOY_COATS, build_toy_rig  # noqa: E402


def _children_cpu() -> float:
    u = resource.getrusage(resource.RUSAGE_CHILDREN)
    return u.ru_utime + u.ru_stime


def _render(rig, jobs, assets, config, root: Path) -> tuple[list[dict], float, int, float]:
    """Render in worker processes (the skinned vertices computed first, as ``render_shard`` does, outside the
    timing); returns (records, wall s, processes, CPU s of the finished workers)."""
    work = Path(tempfile.mkdtemp(dir=root))
    posed = [posed_vertices(rig, job) for job in jobs]
    t0, c0 = time.perf_counter(), _children_cpu()
    results, processes, crashes = _render_images(jobs, posed, assets, config, work, False, None, None, progress=None)
    wall, cpu = time.perf_counter() - t0, _children_cpu() - c0
    if crashes or any(results[i]["status"] != "ok" for i in range(len(jobs))):
        raise RuntimeError(f"benchmark renders failed: {[results[i] for i in range(len(jobs))][:3]}")
    shutil.rmtree(work)
    return [results[i] for i in range(len(jobs))], wall, processes, cpu


def _throughput(recs: list[dict]) -> tuple[float, float]:
    steady = recs[1:]
    wall = sum(r["seconds"] for r in steady)
    cpu = sum(r["cpu_seconds"] for r in steady)
    return len(steady) / wall, 2.0 * len(steady) / cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=32, help="jobs for the per-shard vs per-image comparison")
    ap.add_argument("--throughput-jobs", type=int, default=9, help="images per throughput measurement")
    args = ap.parse_args()
    rig = build_toy_rig()
    root = Path(tempfile.mkdtemp(prefix="bat3r_bench_render_"))
    try:
        asset = save_rig_glb(rig, root / "toy.glb")
        assets = SceneAssets(asset=str(asset), textures=tuple(f"toy:{c}" for c in TOY_COATS))
        figures: dict[str, float] = {}
        for key, size, denoise in (("128", 128, False), ("160", 160, False), ("128_denoise", 128, True)):
            jobs = canonical_jobs(rig, args.throughput_jobs, seed=1, body_frame_spec=TOY_BODY_FRAME,
                                  resolution=size, num_textures=len(TOY_COATS))
            cfg = RenderConfig(resolution=size, samples=16, denoise=denoise)
            recs, wall, _, _ = _render(rig, jobs, assets, cfg, root)
            ips, ips_cpu = _throughput(recs)
            figures[f"images_per_s_{key}"] = round(ips, 3)
            figures[f"images_per_s_{key}_from_cpu_time"] = round(ips_cpu, 3)
            if key == "128":
                figures["first_image_s"] = round(recs[0]["seconds"], 3)
                figures["process_start_s"] = round(wall - sum(r["seconds"] for r in recs), 3)
            print(f"{size}x{size} 16 spp denoise={denoise}: {ips:.2f} images/s (wall), {ips_cpu:.2f} from CPU time")
        jobs = canonical_jobs(rig, args.jobs, seed=2, body_frame_spec=TOY_BODY_FRAME, resolution=128,
                              num_textures=len(TOY_COATS))
        cfg = RenderConfig(resolution=128, samples=16)
        _, shard_s, p1, shard_cpu = _render(rig, jobs, assets, replace(cfg, recycle_every=args.jobs), root)
        _, image_s, p2, image_cpu = _render(rig, jobs, assets, replace(cfg, recycle_every=1), root)
        if (p1, p2) != (1, args.jobs):
            raise RuntimeError(f"expected 1 and {args.jobs} worker processes, got {p1} and {p2}")
        figures.update(per_shard_s=round(shard_s, 2), per_image_s=round(image_s, 2),
                       per_shard_speedup=round(image_s / shard_s, 2),
                       per_shard_speedup_from_cpu_time=round(image_cpu / shard_cpu, 2))
        print(f"{args.jobs} jobs: one process {shard_s:.1f} s, one process per image {image_s:.1f} s "
              f"-> {image_s / shard_s:.1f}x")
        load = os.getloadavg()[0]
        notes = (f"Toy quadruped (4.8K vertices), canonical views, procedural sky + sun, Cycles CPU, 16 spp. "
                 f"Goals on 2 cores: >= 4 images/s at 128x128 without denoising; per-shard >= 5x. "
                 f"Load average during the run: {load:.1f} (shared machine).")
        record("render", figures, notes=notes)
        print(figures)
    finally:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
