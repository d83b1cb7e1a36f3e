"""Heavy assets: does ``bat3r asset check`` hold on the mesh sizes users bring, and what does it cost?

Sketchfab and game exports are often 50k–500k vertices; the toy has a few thousand. This benchmark subdivides a
real rigged asset in Blender (Catmull–Clark, ``--levels``; shape keys cleared first, since Blender cannot apply a
modifier to a mesh with shape keys; the skin weights are interpolated by the subdivision) and runs the whole
preflight (``bat3r_core.asset_check.check_asset``: load, weld, labels against Blender's mask, exact-cloud fits) on
each level in a fresh process, timing it and reading its peak memory (the process and everything it waited for,
Blender workers included, from ``os.wait4``). Level 0 is Blender's own export of the asset, not the original file,
so every level went through the same exporter.

    python benchmarks/bench_assets.py [--asset ../shared/assets/dog_puppy/scene.gltf] [--scale 1]
                                      [--levels 0 1 2] [--record-as assets]

Figures per level ``L``: ``vertices_L``, ``triangles_L``, ``check_s_L`` (wall seconds), ``peak_rss_gb_L``,
``checks_passed_L`` (1 when every check passed), ``fit_cm_L`` and ``rest_cm_L`` (mean exact-cloud fit and rest-pose
vertex errors), ``mask_iou_min_L``. About 5 minutes on 2 CPU cores for the shared dog at levels 0–2.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _results import record, record_name  # noqa: E402

from bat3r_core.rig_io import read_any_asset  # noqa: E402

DEFAULT_ASSET = ROOT.parent / "shared" / "assets" / "dog_puppy" / "scene.gltf"

VARIANTS_SCRIPT = ROOT / "tests" / "assets" / "make_variants.py"  # the Blender variants of the asset tests

_CHECK = r"""
import json, sys
from bat3r_core.asset_check import check_asset
path, out, scale = sys.argv[1], sys.argv[2], float(sys.argv[3])
report = check_asset(path, out, scale=scale, resolution=64)
f = report.figures
print(json.dumps({"failed": report.failed, "fit": f.get("fit_vertex_error_cm"),
                  "rest": f.get("rest_vertex_error_cm"), "mask_iou": f.get("mask_iou")}))
"""


def subdivide(src: Path, dst_dir: Path, levels: int) -> Path:
    """``src`` through Blender's glTF importer, shape keys cleared, ``levels`` of Catmull–Clark applied, as the GLB
    ``dst_dir/subdivided_<levels>.glb`` (the ``subdivided_<N>`` variant of ``tests/assets/make_variants.py``)."""
    name = f"subdivided_{levels}"
    proc = subprocess.run([sys.executable, str(VARIANTS_SCRIPT), str(src), str(dst_dir), name],
                          capture_output=True, text=True, timeout=1800)
    dst = dst_dir / f"{name}.glb"
    if proc.returncode != 0 or not dst.is_file():
        raise RuntimeError(f"subdividing {src} ({levels} levels) failed:\n{proc.stderr[-3000:]}")
    return dst


def timed_check(path: Path, out: Path, scale: float) -> dict:
    """The asset check of ``path`` in a fresh process: its summary, wall seconds and peak RSS (GB)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "stdout.txt", "w+") as so, open(out / "stderr.txt", "w+") as se:
        start = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-c", _CHECK, str(path), str(out), str(scale)], stdout=so,
                                stderr=se, text=True, env=env)
        _, status, usage = os.wait4(proc.pid, 0)  # reaped here, not by Popen, to read its resource usage
        proc.returncode = os.waitstatus_to_exitcode(status)
        seconds = time.perf_counter() - start
        so.seek(0)
        se.seek(0)
        stdout, stderr = so.read(), se.read()
    if proc.returncode != 0:
        raise RuntimeError(f"asset check of {path} failed:\n{stderr[-3000:]}")
    summary = json.loads(stdout.strip().splitlines()[-1])
    summary.update(seconds=seconds, peak_rss_gb=usage.ru_maxrss / 2 ** 20)  # Linux: kilobytes
    return summary


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--asset", type=Path, default=DEFAULT_ASSET, help="the rigged asset (.glb/.gltf)")
    p.add_argument("--scale", type=float, default=1.0, help="its asset_scale (0.01 for a file in centimetres)")
    p.add_argument("--levels", type=int, nargs="+", default=[0, 1, 2], help="subdivision levels to check")
    p.add_argument("--record-as", type=record_name, default="assets", help="name of results/<name>.json")
    p.add_argument("--results-dir", type=Path, default=None,
                   help="write <record-as>.json here instead of benchmarks/results (RESULTS.md is left alone)")
    args = p.parse_args(argv)
    if not args.asset.is_file():
        p.error(f"--asset: {args.asset} does not exist")
    if any(level < 0 for level in args.levels):
        p.error(f"--levels: expected levels >= 0, got {args.levels}")
    figures: dict[str, float] = {}
    lines = []
    with tempfile.TemporaryDirectory(prefix="bat3r_bench_assets_") as tmp:
        for level in sorted(set(args.levels)):
            glb = subdivide(args.asset, Path(tmp), level)
            s = timed_check(glb, Path(tmp) / f"check{level}", args.scale)
            rig, _ = read_any_asset(glb, args.scale)  # the sizes, read outside the timed check
            s.update(vertices=rig.num_vertices, triangles=len(rig.faces))
            # the check's figures are per view / per pose: report the worst IoU and the mean errors
            ious, fit, rest = s["mask_iou"] or [], s["fit"] or [], s["rest"] or []
            figures.update({f"vertices_{level}": s["vertices"], f"triangles_{level}": s["triangles"],
                            f"check_s_{level}": round(s["seconds"], 1),
                            f"peak_rss_gb_{level}": round(s["peak_rss_gb"], 2),
                            f"checks_passed_{level}": int(not s["failed"])})
            if ious:
                figures[f"mask_iou_min_{level}"] = round(min(ious), 4)
            if fit and rest:
                figures[f"fit_cm_{level}"] = round(sum(fit) / len(fit), 2)
                figures[f"rest_cm_{level}"] = round(sum(rest) / len(rest), 2)
            line = (f"level {level}: {s['vertices']} vertices, {s['triangles']} triangles: check "
                    f"{s['seconds']:.0f} s, peak {s['peak_rss_gb']:.2f} GB, "
                    + ("all checks passed" if not s["failed"] else f"FAILED {', '.join(s['failed'])}"))
            print(line, flush=True)
            lines.append(line)
    notes = (f"{args.asset.name} (asset_scale {args.scale}) through Blender's glTF importer and exporter, subdivided "
             f"(Catmull-Clark) {sorted(set(args.levels))} levels, each checked by bat3r_core.asset_check.check_asset "
             f"(64 px renders, 8 views, 8 exact-cloud fits) in a fresh process; peak memory includes the Blender "
             f"workers. " + "; ".join(lines))
    record(args.record_as, figures, notes=notes, results_dir=args.results_dir)
    return figures


if __name__ == "__main__":
    main()
