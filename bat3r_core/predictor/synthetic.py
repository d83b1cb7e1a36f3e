"""Analytic training samples for tests and benchmarks: an articulated two-sphere "snowman" ray cast exactly.

The canonical object is a body sphere (centre 0, radius 0.35 m) and a head sphere (centre (0, 0.3, 0.6) m,
radius 0.2 m) in the canonical frame of ``docs/CONVENTIONS.md`` (+Y up, +Z forward). A sample nods the head about
the body centre (the articulation), turns the whole object about the vertical axis and places it 2.5-3 m in front
of an OpenCV pinhole camera (focal length 2 x resolution). Every pixel-centre ray is intersected with both spheres; all hits, sorted front to
back, fill the K layers (at most 4 exist). Pixels are coloured by the layer-0 canonical coordinates with Lambert
shading, so the canonical map is observable. The arrays follow the "Training samples" shard format (P stored
relative to the object depth as float16, via ``pointmaps.encode_float16``).
"""
from __future__ import annotations

import os

import numpy as np

from bat3r_core.pointmaps import encode_float16
from bat3r_core.shards import ShardPaths, write_shard

_BODY = (np.zeros(3), 0.35)
_HEAD = (np.array([0.0, 0.3, 0.6]), 0.2)
_BACKGROUND = np.array([40, 70, 100], dtype=np.uint8)


def _rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _sample(rng: np.random.Generator, resolution: int, layers: int, with_head: bool) -> dict[str, np.ndarray]:
    f = 2.0 * resolution
    intr = np.array([[f, 0, resolution / 2], [0, f, resolution / 2], [0, 0, 1]])
    # canonical +Y up -> camera -y (up in the image): a half turn about x, then a small tilt and any turn about Y
    rot = _rot_x(np.pi) @ _rot_x(rng.uniform(-0.2, 0.2)) @ _rot_y(rng.uniform(-np.pi, np.pi))
    nod = _rot_x(rng.uniform(-0.6, 0.6))
    # put the object's middle (between body and head) near the optical axis
    trans = np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), rng.uniform(2.6, 3.0)])
    trans -= rot @ (0.5 * (_BODY[0] + _HEAD[0]))
    # (posed centre, radius, canonical centre, rotation canonical -> camera) per sphere
    spheres = [(rot @ _BODY[0] + trans, _BODY[1], _BODY[0], rot),
               (rot @ nod @ _HEAD[0] + trans, _HEAD[1], _HEAD[0], rot @ nod)][:2 if with_head else 1]

    jj, ii = np.meshgrid(np.arange(resolution) + 0.5, np.arange(resolution) + 0.5)
    dirs = np.stack([(jj - intr[0, 2]) / f, (ii - intr[1, 2]) / f, np.ones_like(jj)], -1)  # (H, W, 3), z = 1
    hits_t, hits_q = [], []
    for centre, radius, canon_centre, r_cs in spheres:
        a = (dirs ** 2).sum(-1)
        b = dirs @ centre
        disc = b ** 2 - a * (centre @ centre - radius ** 2)
        ok = disc > 0
        root = np.sqrt(np.where(ok, disc, 0.0))
        for sign in (-1.0, 1.0):
            t = np.where(ok, (b + sign * root) / a, np.inf)
            p = dirs * np.where(ok, t, 0.0)[..., None]
            hits_t.append(t)
            hits_q.append(canon_centre + (p - centre) @ r_cs)  # r_cs^T (p - c), row-vector form
    t_all = np.stack(hits_t, -1)  # (H, W, 4)
    q_all = np.stack(hits_q, -2)  # (H, W, 4, 3)
    order = np.argsort(t_all, axis=-1, kind="stable")[..., :layers]
    t_k = np.take_along_axis(t_all, order, -1)
    q_k = np.take_along_axis(q_all, order[..., None], -2)
    if layers > t_all.shape[-1]:
        pad = layers - t_all.shape[-1]
        t_k = np.concatenate([t_k, np.full(t_k.shape[:-1] + (pad,), np.inf)], -1)
        q_k = np.concatenate([q_k, np.zeros(q_k.shape[:-2] + (pad, 3))], -2)
    occ = np.isfinite(t_k)
    p_k = np.where(occ[..., None], dirs[..., None, :] * np.where(occ, t_k, 0.0)[..., None], 0.0)
    q_k = np.where(occ[..., None], q_k, 0.0)

    lo = np.min([c - r for c, r, _, _ in spheres], axis=0)
    hi = np.max([c + r for c, r, _, _ in spheres], axis=0)
    mask = occ[..., 0]
    # colour = canonical coordinates of the visible point, shaded by the angle to the viewing ray
    normal_dot = np.abs(np.sum(dirs * _layer0_normals(p_k[..., 0, :], spheres, t_k[..., 0]), -1))
    normal_dot /= np.linalg.norm(dirs, axis=-1)
    colour = np.clip(0.5 + q_k[..., 0, :] / 1.2, 0, 1) * (0.4 + 0.6 * normal_dot[..., None])
    rgb = np.where(mask[..., None], (colour * 255).round().astype(np.uint8), _BACKGROUND)
    depth = 0.5 * (lo[2] + hi[2])  # centre of the object's camera-z range
    p16, q16 = encode_float16(p_k, q_k, occ, depth)
    return {"rgb": rgb.astype(np.uint8), "mask": mask, "P": p16, "Q": q16, "occupancy": occ,
            "object_depth": np.float32(depth),
            "K_intrinsics": intr.astype(np.float32)}


def _layer0_normals(points: np.ndarray, spheres, t0: np.ndarray) -> np.ndarray:
    """Unit surface normals of the layer-0 hits (zeros where there is no hit)."""
    best = np.full(points.shape[:-1], np.inf)
    normals = np.zeros_like(points)
    for centre, radius, _, _ in spheres:
        d = np.abs(np.linalg.norm(points - centre, axis=-1) - radius)
        closer = d < best
        best = np.where(closer, d, best)
        normals = np.where(closer[..., None], (points - centre) / radius, normals)
    return np.where(np.isfinite(t0)[..., None], normals, 0.0)


def synthetic_samples(n: int, resolution: int, layers: int = 4, seed: int = 0, with_head: bool = True
                      ) -> dict[str, np.ndarray]:
    """``n`` samples as stacked arrays of the training-shard format (``rgb (n, H, W, 3) uint8``, ``mask``, ``P``,
    ``Q``, ``occupancy``, ``object_depth``, ``K_intrinsics``); H = W = ``resolution``; seeded. ``with_head=False``
    keeps the body sphere only (two layers, smooth maps)."""
    if n < 1 or resolution < 2 or layers < 1:
        raise ValueError(f"synthetic_samples: expected n >= 1, resolution >= 2, layers >= 1, "
                         f"got {n}, {resolution}, {layers}")
    rng = np.random.default_rng(seed)
    samples = [_sample(rng, resolution, layers, with_head) for _ in range(n)]
    return {k: np.stack([s[k] for s in samples]) for k in samples[0]}


def write_synthetic_shards(folder: str | os.PathLike, n: int, resolution: int, layers: int = 4,
                           shard_size: int = 16, seed: int = 0, with_head: bool = True) -> list[ShardPaths]:
    """Write ``n`` synthetic samples to training shards ``part-00000`` ... of ``folder``."""
    arrays = synthetic_samples(n, resolution, layers, seed, with_head)
    out = []
    for s, start in enumerate(range(0, n, shard_size)):
        part = {k: v[start:start + shard_size] for k, v in arrays.items()}
        rows = [{"sample_id": f"snowman-{seed}-{start + i:06d}", "status": "ok", "reason": ""}
                for i in range(len(part["rgb"]))]
        out.append(write_shard(folder, s, rows, part))
    return out


def save_random_dinov2(folder: str | os.PathLike, seed: int = 0, patch_size: int = 8, image_size: int = 32,
                       hidden_size: int = 32, layers: int = 2) -> str:
    """Save a small randomly initialised ``transformers`` DINOv2 to ``folder`` (``save_pretrained``) and return its
    path: what ``features.dinov2.model`` can name to run the ``dinov2`` feature path offline (tests, CI), where the
    real weights cannot be downloaded. Its features carry no meaning; the code path is the real one."""
    import torch
    from transformers import Dinov2Config, Dinov2Model

    torch.manual_seed(seed)
    cfg = Dinov2Config(hidden_size=hidden_size, num_hidden_layers=layers, num_attention_heads=2,
                       intermediate_size=2 * hidden_size, patch_size=patch_size, image_size=image_size)
    Dinov2Model(cfg).save_pretrained(str(folder))
    return str(folder)
