"""What the silhouette term (``FittingConfig.weight_silhouette``) costs in fitting throughput, on CPU.

The toy (4.8K vertices), a batch of 64 ray-cast dual point clouds (96x96, 4 layers; ``bench_fitting.make_instances``)
fitted with the synthetic preset with the term off (weight 0: only its final value is computed, for the
``loss_silhouette`` column), on (weight 16), and on with the coverage's nearest-vertex search every 5 steps
(``silhouette_refresh_steps``), in A B C C B A order in one process; the figures are ratios of the rates measured
side by side. Also the time of the term alone (forward + backward of ``silhouette_terms`` for the
batch, best of 5), as a share of one optimisation step.

    python benchmarks/bench_silhouette.py        # BAT3R_BENCH_THREADS=1 when other jobs share the cores

Writes benchmarks/results/silhouette.json via benchmarks/_results.py.
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
from bench_fitting import make_instances  # noqa: E402

from bat3r_core.catalog import fitting_preset as preset  # noqa: E402
from bat3r_core.fitting import FittingAsset, fit_batch  # noqa: E402
from bat3r_core.fitting.silhouette import SilhouetteBatch, silhouette_target, silhouette_terms  # noqa: E402
from bat3r_core.toy import build_toy_rig  # noqa: E402

BATCH = 64
WEIGHT = 16.0
REFRESH = 5


def _rate(asset, insts, config) -> float:
    t0 = time.perf_counter()
    res = fit_batch(asset, insts, config)
    dt = time.perf_counter() - t0
    if not all(s == "ok" for s in res.status):
        raise RuntimeError(f"not every instance was fitted: {sorted(set(res.reason))}")
    return len(insts) / dt


def _term_s(insts, config) -> float:
    """Seconds of one forward + backward of the term for the batch (600 vertices, 400 mask pixels), best of 5."""
    rng = np.random.default_rng(0)
    targets = [silhouette_target(i.posed_points, i.pixels, i.layers, np.ones(len(i.layers), bool), None,
                                 i.intrinsics, i.image_size, config.silhouette_mask_samples, rng) for i in insts]
    batch = SilhouetteBatch.stack(targets, torch.float32, torch.device("cpu"))
    points = torch.as_tensor(np.stack([i.posed_points[rng.choice(len(i.posed_points), config.silhouette_vertices)]
                                       for i in insts]), dtype=torch.float32).requires_grad_(True)
    best = np.inf
    for _ in range(5):
        t0 = time.perf_counter()
        outside, coverage = silhouette_terms(points, batch, 1.0, config.huber_delta)
        (outside + coverage).sum().backward()
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> dict:
    threads = int(os.environ.get("BAT3R_BENCH_THREADS", str(torch.get_num_threads())))
    torch.set_num_threads(threads)
    rig = build_toy_rig()
    insts = make_instances(rig, BATCH, seed=20_261_205)
    configs = {"off": preset("synthetic"), "on": preset("synthetic", {"weight_silhouette": WEIGHT, "silhouette_refresh_steps": 1}),
               "refresh": preset("synthetic", {"weight_silhouette": WEIGHT, "silhouette_refresh_steps": REFRESH})}
    with tempfile.TemporaryDirectory() as cache:
        asset = FittingAsset.prepare(rig, configs["off"], cache_dir=cache)
        fit_batch(asset, insts[:2], preset("synthetic", {"steps": 3}))  # warm-up
        rates: dict[str, list[float]] = {k: [] for k in configs}
        for which in ("off", "on", "refresh", "refresh", "on", "off"):
            rates[which].append(_rate(asset, insts, configs[which]))
    rate_off, rate_on, rate_refresh = (float(np.mean(rates[k])) for k in ("off", "on", "refresh"))
    on = configs["on"]
    term = _term_s(insts, on)
    figures = {"instances_per_s_b64": round(rate_off, 2), "instances_per_s_b64_silhouette": round(rate_on, 2),
               "silhouette_rate_ratio": round(rate_on / rate_off, 3),
               f"instances_per_s_b64_silhouette_refresh{REFRESH}": round(rate_refresh, 2),
               f"silhouette_refresh{REFRESH}_rate_ratio": round(rate_refresh / rate_off, 3),
               "silhouette_term_ms_b64": round(1e3 * term, 1),
               "silhouette_term_share_of_step": round(term / (BATCH / rate_on / on.steps), 3),
               "threads": threads}
    for k, v in figures.items():
        print(f"{k}: {v}")
    record("silhouette", figures, notes=(
        f"toy, batch of {BATCH} ray-cast clouds (96x96), synthetic preset ({on.steps} steps), weight_silhouette 0 vs "
        f"{WEIGHT:g} (the coverage's nearest vertices searched every step, and every {REFRESH} steps: refresh) in "
        "A B C C B A order in one process (rates averaged); the term alone: forward + backward for the batch with "
        "the search, best of 5; share_of_step: its time over the mean step time with the term on."))
    return figures


if __name__ == "__main__":
    main()
