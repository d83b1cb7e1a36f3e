"""The on-disk feature cache: grids keyed by the content hash of crop and mask, one folder per extractor config."""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from bat3r_core.predictor.features.config import _save_npz


# ---------------------------------------------------------------------------------------------------------- cache
class _FeatureCache:
    """npz shards of (keys, grids) in one folder; an in-process index maps a key to its shard and row."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self._index: dict[str, tuple[Path, int]] = {}
        self._seen: set[str] = set()

    def _refresh(self) -> None:
        if not self.folder.is_dir():
            return
        for p in sorted(self.folder.glob("*.npz")):
            if p.name in self._seen:
                continue
            with np.load(p, allow_pickle=False) as z:
                keys = z["keys"]
            for row, k in enumerate(keys.tolist()):
                self._index.setdefault(k, (p, row))
            self._seen.add(p.name)

    def lookup(self, keys: list[str]) -> dict[str, np.ndarray]:
        self._refresh()
        by_file: dict[Path, list[tuple[str, int]]] = {}
        for k in keys:
            if k in self._index:
                p, row = self._index[k]
                by_file.setdefault(p, []).append((k, row))
        found = {}
        for p, items in by_file.items():
            with np.load(p, allow_pickle=False) as z:
                grids = z["grids"]
            for k, row in items:
                found[k] = grids[row]
        return found

    def store(self, keys: list[str], grids: np.ndarray) -> None:
        name = hashlib.sha256("".join(keys).encode()).hexdigest()[:16] + ".npz"
        _save_npz(self.folder / name, {"keys": np.array(keys), "grids": grids.astype(np.float32)})


_CACHES: dict[str, _FeatureCache] = {}


def _cache(folder: Path) -> _FeatureCache:
    key = str(folder.resolve())
    if key not in _CACHES:
        _CACHES[key] = _FeatureCache(folder)
    return _CACHES[key]


def sample_keys(rgb: np.ndarray, mask: np.ndarray) -> list[str]:
    """Content hash (hex, 32 chars) of each crop and its mask."""
    keys = []
    for i in range(len(rgb)):
        h = hashlib.sha256(str(rgb[i].shape).encode())
        h.update(np.ascontiguousarray(rgb[i]).tobytes())
        h.update(np.packbits(mask[i]).tobytes())
        keys.append(h.hexdigest()[:32])
    return keys
