"""Mesh-fitting throughput on CPU: instances per second for batches of 64 and 256 (200 steps, 200 control
points, the synthetic preset, the 4.8K-vertex toy), and the speed-up over fitting the same instances one at a time,
measured side by side in one run.

Inputs are ray-cast dual point clouds (96x96, 4 layers) of the toy in natural poses. One-at-a-time fitting is timed
on a subset (``ONE_AT_A_TIME`` instances of the 64-batch) and extrapolated per instance, which the notes say.
Writes benchmarks/results/fitting.json via benchmarks/_results.py.
"""
from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _results import record  # noqa: E402

from bat3r_core.fitting import FittingAsset, PointCloudInstance, fit_batch, preset  # noqa: E402
from bat3r_core.pointmaps import dual_point_cloud, dual_point_maps  # noqa: E402
from bat3r_core.poses import sample_toy_natural_poses  # noqa: E402
from bat3r_core.skinning import skin  # noqa: E402
from bat3r_core.toy import TOY_BODY_FRAME, build_toy_rig  # noqa: E402
from bat3r_core.viewpoints import CameraPriorConfig, body_frame, sample_viewpoints  # noqa: E402

DISTINCT = 64
ONE_AT_A_TIME = 4


def make_instances(rig, n: int, seed: int) -> list[PointCloudInstance]:
    theta, _ = sample_toy_natural_poses(n, seed=seed)
    out = skin(rig.tensors(dtype=torch.float64), torch.as_tensor(theta))
    idx = {k: i for i, k in enumerate(rig.joint_names)}
    rng = np.random.default_rng(seed)
    insts = []
    for i in range(n):
        frame = body_frame(out.joints[i].numpy(), idx[TOY_BODY_FRAME["origin"]],
                           tuple(idx[k] for k in TOY_BODY_FRAME["forward"]),
                           tuple(idx[k] for k in TOY_BODY_FRAME["horizontal"]))
        cam = sample_viewpoints(out.vertices[i].numpy(), frame, 1, CameraPriorConfig(), 96, 96, rng)[0].camera
        m = dual_point_maps(out.vertices[i].numpy(), rig.rest_vertices, rig.faces, cam)
        pc = dual_point_cloud(m.P, m.Q, m.occupancy)
        p = pc.posed_points.astype(np.float64)
        p[:, 2] -= m.object_depth
        insts.append(PointCloudInstance(f"b{i}", p, pc.canonical_points.astype(np.float64), None, pc.pixels,
                                        pc.layers, cam.K, (96, 96)))
    return insts


def main() -> dict:
    # all cores by default (2 threads on the 2-core machine: 10.8 inst/s, 11x batched when it is otherwise idle);
    # BAT3R_BENCH_THREADS=1 when other jobs share the cores (two OpenMP threads then spin against them)
    threads = int(os.environ.get("BAT3R_BENCH_THREADS", str(torch.get_num_threads())))
    torch.set_num_threads(threads)
    rig = build_toy_rig()
    config = preset("synthetic")
    with tempfile.TemporaryDirectory() as cache:
        asset = FittingAsset.prepare(rig, config, cache_dir=cache)
    base = make_instances(rig, DISTINCT, seed=31_337)
    # 256 instances: the 64 point clouds four times under different ids (different control points)
    many = [PointCloudInstance(f"{i.sample_id}-{r}", i.posed_points, i.canonical_points, None, i.pixels, i.layers,
                               i.intrinsics, i.image_size) for r in range(4) for i in base]
    fit_batch(asset, base[:2], preset("synthetic", {"steps": 3}))  # warm-up (imports, allocator)
    figures = {}
    for b, insts in ((64, base), (256, many)):
        t0 = time.perf_counter()
        res = fit_batch(asset, insts, config)
        dt = time.perf_counter() - t0
        assert all(s == "ok" for s in res.status)
        figures[f"instances_per_s_b{b}"] = round(b / dt, 2)
        figures[f"seconds_b{b}"] = round(dt, 1)
    t0 = time.perf_counter()
    for inst in base[:ONE_AT_A_TIME]:
        fit_batch(asset, [inst], config)
    single = ONE_AT_A_TIME / (time.perf_counter() - t0)
    figures["instances_per_s_one_at_a_time"] = round(single, 3)
    figures["batched_speedup"] = round(figures["instances_per_s_b256"] / single, 1)
    figures["batched_speedup_b64"] = round(figures["instances_per_s_b64"] / single, 1)
    notes = (f"toy rig {rig.num_vertices} vertices / {rig.num_joints} joints, synthetic preset ({config.steps} steps, "
             f"{config.num_control_points} control points, regularisers on a {len(asset.reg_mesh.rest_vertices)}-"
             f"vertex proxy, repulsion pairs refreshed every {config.repulsion_refresh_steps} steps), torch threads "
             f"{threads}. "
             f"One-at-a-time rate measured on {ONE_AT_A_TIME} instances and compared per instance; "
             "times include correspondences, FPS, camera recovery and output Chamfer.")
    record("fitting", figures, notes)
    print(figures)
    return figures


if __name__ == "__main__":
    main()
