"""The raw-image baseline's training shards: the collection's own crops labelled by ray casting their fitted meshes
through the recovered cameras, without re-rendering (the paper's "raw images" row)."""
from __future__ import annotations

import os

import numpy as np

from bat3r_core.render.jobs import RenderJob
from bat3r_core.rig import Rig


__all__ = ["raw_image_shard"]


def raw_image_shard(rig: Rig, fit_dir: str | os.PathLike, collection_dir: str | os.PathLike, index: int,
                    out_dir: str | os.PathLike, num_layers: int = 4):
    """The raw-image baseline's training shard: the collection's own crops (RGB, mask) of collection shard
    ``index`` with pseudo-labels ray-cast from their fits (fit shard ``index``: θ and the recovered camera of the
    crop), without re-rendering. Rows that were not fitted, or whose fit has no camera, get status ``no_fit``.

    Writes shard ``index`` of ``out_dir`` in the training-shard format (docs/CONVENTIONS.md) and returns its
    :class:`~bat3r_core.shards.ShardPaths`.
    """
    from bat3r_core.fitting.io import camera_from_row
    from bat3r_core.pointmaps import encode_float16, storage_dtype
    from bat3r_core.labels import label_job
    from bat3r_core.shards import read_shard, write_shard

    fits = {r["sample_id"]: r for r in read_shard(fit_dir, index, with_arrays=False)[0].to_pylist()}
    table, arrays = read_shard(collection_dir, index)
    rows_in = table.to_pylist()
    n, res = len(rows_in), arrays["rgb"].shape[1]
    dtype = storage_dtype(rig.rest_vertices)
    out = {"rgb": arrays["rgb"].copy(), "mask": arrays["mask"].astype(bool).copy(),
           "P": np.zeros((n, res, res, num_layers, 3), dtype), "Q": np.zeros((n, res, res, num_layers, 3), dtype),
           "occupancy": np.zeros((n, res, res, num_layers), bool), "object_depth": np.zeros(n, np.float32),
           "K_intrinsics": np.zeros((n, 3, 3), np.float32)}
    rows = []
    for i, src in enumerate(rows_in):
        row = {"sample_id": src["sample_id"], "source_id": src["sample_id"], "view_kind": "raw_image",
               "status": src["status"], "reason": src["reason"]}
        fit = fits.get(src["sample_id"])
        camera = None if fit is None else camera_from_row(fit)
        if row["status"] == "ok" and camera is None:
            row["status"], row["reason"] = "no_fit", "no fitted mesh with a recovered camera for this image"
        if row["status"] == "ok":
            theta = np.asarray(fit["excess_rotations"], dtype=np.float64).reshape(-1, 3)
            _, maps = label_job(rig, RenderJob(sample_id=src["sample_id"], excess_rotations=theta, camera=camera),
                                num_layers)
            if maps.status != "ok":
                row["status"], row["reason"] = maps.status, maps.reason
            else:
                out["P"][i], out["Q"][i] = encode_float16(maps.P, maps.Q, maps.occupancy,
                                                          np.float64(maps.object_depth), dtype)
                out["occupancy"][i] = maps.occupancy
                out["object_depth"][i] = maps.object_depth
                out["K_intrinsics"][i] = camera.K
        rows.append(row)
    return write_shard(out_dir, index, rows, out)
