"""Skinning forward + backward time for B x V x J = 256 x 4000 x 30 on CPU (float32).

Writes benchmarks/results/skinning.json (key `fwd_bwd_s`: median seconds of one forward+backward pass over
excess rotations, bone scales and the global similarity) and refreshes benchmarks/RESULTS.md.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bat3r_core.rig import Rig  # noqa: E402
from bat3r_core.skinning import axis_angle_to_matrix, skin  # noqa: E402

B, V, J = 256, 4000, 30


def synthetic_rig(seed: int = 0) -> Rig:
    """A random tree of J joints and V vertices with 4 influences each (skinning cost does not depend on shape)."""
    rng = np.random.default_rng(seed)
    parents = np.array([-1] + [int(rng.integers(0, j)) for j in range(1, J)])
    rest = np.tile(np.eye(4), (J, 1, 1))
    rest[:, :3, 3] = rng.normal(size=(J, 3))
    verts = rng.normal(size=(V, 3))
    w = np.zeros((V, J))
    for v in range(V):
        idx = rng.choice(J, 4, replace=False)
        w[v, idx] = rng.random(4)
    w /= w.sum(1, keepdims=True)
    faces = np.stack([np.arange(V - 2), np.arange(1, V - 1), np.arange(2, V)], 1)
    return Rig("bench", verts, faces, tuple(f"j{i}" for i in range(J)), parents, rest, w)


def main() -> dict:
    torch.manual_seed(0)
    rt = synthetic_rig().tensors(torch.float32)
    theta = (0.3 * torch.randn(B, J, 3)).requires_grad_()
    scales = torch.ones(B, J, requires_grad=True)
    gs = torch.ones(B, requires_grad=True)
    gr = torch.zeros(B, 3, requires_grad=True)
    gt = torch.zeros(B, 3, requires_grad=True)

    def step():
        out = skin(rt, theta, scales, gs, axis_angle_to_matrix(gr), gt)
        loss = out.vertices.square().mean() + out.joints.square().mean()
        loss.backward()

    step()  # warm-up
    times = []
    for _ in range(7):
        t0 = time.perf_counter()
        step()
        times.append(time.perf_counter() - t0)
    figures = {"fwd_bwd_s": round(float(np.median(times)), 4), "batch": B, "vertices": V, "joints": J,
               "threads": torch.get_num_threads()}
    print(figures)
    from _results import record

    record("skinning", figures, notes=f"linear blend skinning forward+backward, float32 CPU, B x V x J = "
                                      f"{B} x {V} x {J}, median of 7 after a warm-up")
    return figures


if __name__ == "__main__":
    main()
