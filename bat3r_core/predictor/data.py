"""Training data of the predictor: a dataset over a folder of rendered training shards.

A shard's npz holds the arrays of ``docs/CONVENTIONS.md`` ("Training samples"); rows whose Parquet ``status`` is
not ``"ok"`` are skipped. Features come either from the features stage's shards (``features_dir``: shard ``i`` holds
the feature ``grid (N, C, h, w)`` of training shard ``i``, row for row, ``bat3r_core.predictor.features
.extract_feature_shard``; ``features.grid_features`` brings a batch to the crop resolution), streamed like the
training shards so each sample's features are computed once per iteration, or per batch from a pluggable ``feature_fn(rgb, mask)``: ``rgb (N, H, W, 3) uint8``, ``mask (N, H, W)
bool`` -> ``(N, C, H, W) float32``. The default, ``rgb_features``, is the masked crop scaled to [0, 1] with the
background set to 0.

Targets are ``canonical_points`` Q, ``posed_points`` P relative to the object depth (``P - (0, 0, object_depth)``
on occupied entries, 0 elsewhere; this is how shards store P, see ``pointmaps.encode_float16``) and
``occupancy``; float32/bool tensors.
"""
from __future__ import annotations

import os
from collections import OrderedDict
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np
import torch

from bat3r_core.shards import list_shards, ok_mask, read_shard

FeatureFn = Callable[[np.ndarray, np.ndarray], np.ndarray]
_REQUIRED = ("rgb", "mask", "P", "Q", "occupancy", "object_depth")


def check_crops(rgb: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(rgb, mask)`` as arrays once they are a batch of object crops: rgb (N, H, W, 3) uint8 and mask (N, H, W)
    bool. Anything else raises (ValueError for a shape or the rgb dtype, TypeError for a mask that is not bool, e.g.
    0/255 uint8, which would scale the features). The one check every feature extractor runs."""
    rgb = np.asarray(rgb)
    mask = np.asarray(mask)
    if rgb.ndim != 4 or rgb.shape[-1] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be (N, H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    if mask.shape != rgb.shape[:3]:
        raise ValueError(f"mask must have shape {rgb.shape[:3]} (rgb's first three axes), got {mask.shape}")
    if mask.dtype != bool:
        raise TypeError(f"mask must be bool, got {mask.dtype}")
    return rgb, mask


def rgb_features(rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Reference ``rgb`` features: rgb (N, H, W, 3) uint8, mask (N, H, W) bool (:func:`check_crops`) ->
    (N, 3, H, W) float32 in [0, 1], background pixels 0."""
    rgb, mask = check_crops(rgb, mask)
    out = rgb.astype(np.float32) * np.float32(1.0 / 255.0) * mask[..., None].astype(np.float32)
    return np.ascontiguousarray(out.transpose(0, 3, 1, 2))


class TrainingTargets(NamedTuple):
    """canonical_points (B, H, W, K, 3) float32 metres, canonical frame; posed_points (B, H, W, K, 3) float32
    metres, camera frame minus the object depth; occupancy (B, H, W, K) bool."""

    canonical_points: torch.Tensor
    posed_points: torch.Tensor
    occupancy: torch.Tensor


class TrainingBatch(NamedTuple):
    """features (B, C, H, W) float32; mask (B, H, W) bool (the rendered object mask); targets."""

    features: torch.Tensor
    mask: torch.Tensor
    targets: TrainingTargets


class ShardDataset(torch.utils.data.Dataset):
    """Map-style dataset over the complete training shards of ``folder``; item i is a ``TrainingBatch`` of one
    sample without the batch axis. ``get_batch(indices)`` returns a batched ``TrainingBatch`` (one ``feature_fn``
    call, or rows of the feature shards of ``features_dir`` when given: a training shard whose feature shard is
    missing, because its features task failed and was reported, is left out and listed in
    ``shards_without_features``). At most ``cache_shards`` decoded shards (with their feature shards) are kept in
    memory."""

    def __init__(self, folder: str | os.PathLike, feature_fn: FeatureFn | None = None, cache_shards: int = 4,
                 features_dir: str | os.PathLike | None = None) -> None:
        if feature_fn is not None and features_dir is not None:
            raise ValueError("ShardDataset: give feature_fn or features_dir, not both")
        self.folder = Path(folder)
        self.features_dir = None if features_dir is None else Path(features_dir)
        self.feature_fn: FeatureFn = feature_fn or rgb_features
        self.cache_shards = max(1, int(cache_shards))
        self._cache: OrderedDict[int, dict[str, np.ndarray]] = OrderedDict()
        shards = list_shards(self.folder)
        if not shards:
            raise FileNotFoundError(f"shards_dir: no complete shards (part-NNNNN.parquet) in {self.folder}")
        self.shards: list[int] = []
        self.rows: list[np.ndarray] = []  # per shard: the ok row indices
        featured = None if self.features_dir is None else set(list_shards(self.features_dir))
        self.shards_without_features: list[int] = []  # their feature shard failed (the features stage reports it)
        for s in shards:
            if featured is not None and s not in featured:
                self.shards_without_features.append(s)
                continue
            table, _ = read_shard(self.folder, s, with_arrays=False)
            ok = np.flatnonzero(ok_mask(table))
            if len(ok):
                self.shards.append(s)
                self.rows.append(ok)
        if not self.shards:
            raise ValueError(f"shards_dir: no sample with status 'ok' in {self.folder}" + (
                f" that has a feature shard in {self.features_dir}" if self.shards_without_features else ""))
        self._starts = np.cumsum([0] + [len(r) for r in self.rows])
        first = self._arrays(0)
        missing = [k for k in _REQUIRED if k not in first]
        if missing:
            raise ValueError(f"shard {self.folder}/part-{self.shards[0]:05d}.npz: missing arrays {missing}")
        _, self.height, self.width, self.layers, _ = first["P"].shape
        probe = self._features(first["grid"][:1], first["mask"][:1].astype(bool)) \
            if self.features_dir is not None else self.feature_fn(first["rgb"][:1], first["mask"][:1].astype(bool))
        if probe.ndim != 4 or probe.shape[0] != 1 or probe.shape[2:] != (self.height, self.width):
            raise ValueError(f"feature_fn: expected (1, C, {self.height}, {self.width}) for one sample, "
                             f"got {tuple(probe.shape)}")
        self.channels = int(probe.shape[1])

    def __len__(self) -> int:
        return int(self._starts[-1])

    @property
    def shard_sizes(self) -> list[int]:
        """Number of usable samples of each shard, in ``self.shards`` order."""
        return [len(r) for r in self.rows]

    def _arrays(self, shard_pos: int) -> dict[str, np.ndarray]:
        if shard_pos in self._cache:
            self._cache.move_to_end(shard_pos)
            return self._cache[shard_pos]
        table, arrays = read_shard(self.folder, self.shards[shard_pos])
        if self.features_dir is not None:
            arrays = {**arrays, "grid": self._feature_shard(self.shards[shard_pos], table)}
        self._cache[shard_pos] = arrays
        while len(self._cache) > self.cache_shards:
            self._cache.popitem(last=False)
        return arrays

    @staticmethod
    def _features(grid: np.ndarray, mask: np.ndarray) -> np.ndarray:
        from bat3r_core.predictor.features import grid_features

        return grid_features(grid, mask)

    def _feature_shard(self, shard: int, table) -> np.ndarray:
        """The feature ``grid`` of training shard ``shard`` from its feature shard, checked row for row."""
        name = f"{self.features_dir}/part-{shard:05d}"
        try:
            ftable, farrays = read_shard(self.features_dir, shard)
        except FileNotFoundError as e:
            raise FileNotFoundError(f"features_dir: no feature shard {name} for training shard {self.folder}/"
                                    f"part-{shard:05d} (run the features stage on {self.folder})") from e
        ids, fids = table.column("sample_id").to_pylist(), ftable.column("sample_id").to_pylist()
        if ids != fids:
            raise ValueError(f"features_dir: {name} holds samples {fids[:3]}... but training shard "
                             f"{self.folder}/part-{shard:05d} holds {ids[:3]}... (a feature shard of another "
                             "render: rerun the features stage)")
        if "grid" not in farrays:
            raise ValueError(f"features_dir: {name}.npz has no 'grid' array; got {sorted(farrays)}")
        return farrays["grid"]

    def locate(self, index: int) -> tuple[int, int]:
        """Global sample index -> (position in ``self.shards``, row in that shard's npz)."""
        if not 0 <= index < len(self):
            raise IndexError(f"index: expected 0 <= index < {len(self)}, got {index}")
        pos = int(np.searchsorted(self._starts, index, side="right") - 1)
        return pos, int(self.rows[pos][index - self._starts[pos]])

    def epoch_order(self, seed: int, epoch: int, shuffle_shards: int = 4) -> np.ndarray:
        """Deterministic sample order of ``epoch``: shards are permuted, then samples are shuffled within groups
        of ``shuffle_shards`` consecutive shards (bounded memory). Depends on (seed, epoch) and the shard sizes
        only."""
        rng = np.random.default_rng([int(seed), int(epoch)])
        perm = rng.permutation(len(self.shards))
        groups = []
        for g in range(0, len(perm), shuffle_shards):
            idx = np.concatenate([np.arange(self._starts[p], self._starts[p + 1]) for p in perm[g:g + shuffle_shards]])
            groups.append(rng.permutation(idx))
        return np.concatenate(groups).astype(np.int64)

    def get_batch(self, indices) -> TrainingBatch:
        """Samples ``indices`` (global) stacked into a batch."""
        keys = _REQUIRED + (("grid",) if self.features_dir is not None else ())
        parts: dict[str, list[np.ndarray]] = {k: [] for k in keys}
        for i in indices:
            pos, row = self.locate(int(i))
            arrays = self._arrays(pos)
            for k in keys:
                parts[k].append(arrays[k][row])
        a = {k: np.stack(v) for k, v in parts.items()}
        if a["P"].shape[1:] != (self.height, self.width, self.layers, 3):
            raise ValueError(f"P: expected (N, {self.height}, {self.width}, {self.layers}, 3) in every shard, "
                             f"got {a['P'].shape}")
        mask = a["mask"].astype(bool)
        occ = a["occupancy"].astype(bool)
        features = self._features(a["grid"], mask) if self.features_dir is not None else \
            np.asarray(self.feature_fn(a["rgb"], mask), dtype=np.float32)
        # shards store P relative to the object depth already: the regression target as is
        q = np.where(occ[..., None], a["Q"].astype(np.float32), np.float32(0.0))
        p = np.where(occ[..., None], a["P"].astype(np.float32), np.float32(0.0))
        return TrainingBatch(torch.from_numpy(features), torch.from_numpy(mask),
                             TrainingTargets(torch.from_numpy(q), torch.from_numpy(p), torch.from_numpy(occ)))

    def __getitem__(self, index: int) -> TrainingBatch:
        b = self.get_batch([index])
        return TrainingBatch(b.features[0], b.mask[0], TrainingTargets(*(t[0] for t in b.targets)))


class DeviceDataset:
    """Every sample of a :class:`ShardDataset` decoded once, with its features, and held as tensors on ``device``:
    ``get_batch`` is then an index on the device instead of a shard read, a gather and a feature pass in Python per
    step — what keeps a GPU busy on small crops (on an H200 at 64×64 a step that read its batch from shards took
    ~60 ms, the network ~5 ms). Same samples, same order (``epoch_order`` is the source's), same batches as the
    source's ``get_batch``; a drop-in ``dataset`` for :class:`~bat3r_core.predictor.train.Trainer`. Needs ``len × H × W × (4 C + 25 K + 1)`` bytes
    (2.1 GB for 4,608 samples at 64×64, K = 4, rgb features).

    Args:
        source: the shard dataset to hold.
        device: where the tensors live (``cuda``, ``cuda:N`` or ``cpu``).
        chunk: samples decoded per ``source.get_batch`` call while loading.
    """

    def __init__(self, source: ShardDataset, device: str | torch.device, chunk: int = 256) -> None:
        self.source, self.device = source, torch.device(device)
        self.height, self.width, self.layers, self.channels = source.height, source.width, source.layers, \
            source.channels
        self.shards_without_features = list(source.shards_without_features)
        parts: list[TrainingBatch] = []
        for start in range(0, len(source), int(chunk)):
            b = source.get_batch(np.arange(start, min(start + int(chunk), len(source))))
            parts.append(TrainingBatch(b.features.to(self.device), b.mask.to(self.device),
                                       TrainingTargets(*(t.to(self.device) for t in b.targets))))
        self._features = torch.cat([p.features for p in parts])
        self._mask = torch.cat([p.mask for p in parts])
        self._targets = TrainingTargets(*(torch.cat([p.targets[i] for p in parts]) for i in range(3)))

    def __len__(self) -> int:
        return len(self.source)

    def epoch_order(self, seed: int, epoch: int, shuffle_shards: int = 4) -> np.ndarray:
        """The source's order (:meth:`ShardDataset.epoch_order`)."""
        return self.source.epoch_order(seed, epoch, shuffle_shards)

    def get_batch(self, indices) -> TrainingBatch:
        """Samples ``indices`` (global) as a batch on ``device``."""
        idx = torch.as_tensor(np.asarray(indices, dtype=np.int64), device=self.device)
        return TrainingBatch(self._features[idx], self._mask[idx], TrainingTargets(*(t[idx] for t in self._targets)))

    @staticmethod
    def nbytes(source: ShardDataset) -> int:
        """Bytes the tensors of ``DeviceDataset(source, ...)`` take: ``len × H × W × (4 C + 25 K + 1)``."""
        return len(source) * source.height * source.width * (4 * source.channels + 25 * source.layers + 1)


def hold_on_device(dataset: ShardDataset, device: str | torch.device | None, mirror_probability: float = 0.0,
                   max_fraction: float = 0.5) -> ShardDataset | DeviceDataset:
    """``dataset`` held on ``device`` (:class:`DeviceDataset`) when that is a CUDA device (``None``: the one the
    trainer would pick), no sample is mirrored (``predictor.mirror`` flips batches on the CPU) and its tensors take
    at most ``max_fraction`` of the device's free memory; else ``dataset`` itself (read from shards per step)."""
    if device is None:
        if not torch.cuda.is_available():
            return dataset
        device = f"cuda:{int(os.environ.get('LOCAL_RANK', 0))}"
    device = torch.device(device)
    if device.type != "cuda" or mirror_probability > 0:
        return dataset
    free, _ = torch.cuda.mem_get_info(device)
    if DeviceDataset.nbytes(dataset) > max_fraction * free:
        return dataset
    return DeviceDataset(dataset, device)


class MixedDataset:
    """Several training sets as one: every epoch takes ``takes[k]`` samples of part k, the first ones of that part's
    own :meth:`~ShardDataset.epoch_order` for the epoch (a part with more samples than it gives contributes a
    different subset each epoch), interleaved at random. What a refinement iteration with ``train.canonical_replay``
    trains on: its pseudo-label renders (all of them) and a share of iteration 0's canonical renders.

    Global sample indices number the parts one after the other (part k's local index plus the sizes of the parts
    before it); ``len`` is the number of samples per epoch (``sum(takes)``), which is what the trainer's epoch
    bookkeeping and its resume check need. The parts are :class:`ShardDataset` or :class:`DeviceDataset` of the same
    crop size, layers and feature channels.

    Args:
        parts: the training sets.
        takes: samples per epoch of each part, 1 ≤ take ≤ len(part).
    """

    def __init__(self, parts, takes) -> None:
        self.parts, self.takes = list(parts), [int(t) for t in takes]
        if not self.parts or len(self.parts) != len(self.takes):
            raise ValueError(f"MixedDataset: expected one take per part, got {len(self.parts)} parts and "
                             f"{len(self.takes)} takes")
        shape = lambda d: (d.height, d.width, d.layers, d.channels)  # noqa: E731
        for k, (part, take) in enumerate(zip(self.parts, self.takes)):
            if shape(part) != shape(self.parts[0]):
                raise ValueError(f"MixedDataset: part {k} ({_name(part)}) has (height, width, layers, channels) "
                                 f"{shape(part)}, part 0 ({_name(self.parts[0])}) {shape(self.parts[0])}: "
                                 "training sets of one run must share the crop size, layers and features")
            if not 1 <= take <= len(part):
                raise ValueError(f"MixedDataset: take of part {k} ({_name(part)}): expected 1 ≤ take ≤ {len(part)}, "
                                 f"got {take}")
        self.height, self.width, self.layers, self.channels = shape(self.parts[0])
        self._offsets = np.cumsum([0] + [len(p) for p in self.parts])
        self.shards_without_features = [s for p in self.parts for s in getattr(p, "shards_without_features", [])]

    def __len__(self) -> int:
        return int(sum(self.takes))

    def epoch_order(self, seed: int, epoch: int, shuffle_shards: int = 4) -> np.ndarray:
        """Deterministic order of epoch ``epoch``: each part's first ``take`` samples of its own epoch order (part k
        ordered with seed ``seed + k``), placed at random slots; depends on (seed, epoch) and the parts' sizes only."""
        rng = np.random.default_rng([int(seed), int(epoch), len(self.parts)])
        slots = rng.permutation(np.repeat(np.arange(len(self.parts)), self.takes))
        order = np.empty(len(slots), dtype=np.int64)
        for k, (part, take) in enumerate(zip(self.parts, self.takes)):
            order[slots == k] = part.epoch_order(int(seed) + k, epoch, shuffle_shards)[:take] + self._offsets[k]
        return order

    def get_batch(self, indices) -> TrainingBatch:
        """Samples ``indices`` (global) as one batch, in the order given."""
        idx = np.asarray(indices, dtype=np.int64)
        if idx.size and (idx.min() < 0 or idx.max() >= self._offsets[-1]):
            raise IndexError(f"indices: expected 0 <= index < {self._offsets[-1]}, got {idx.min()}..{idx.max()}")
        part_of = np.searchsorted(self._offsets, idx, side="right") - 1
        batches, positions = [], []
        for k in np.unique(part_of):
            sel = np.flatnonzero(part_of == k)
            batches.append(self.parts[k].get_batch(idx[sel] - self._offsets[k]))
            positions.append(sel)
        back = torch.as_tensor(np.argsort(np.concatenate(positions)), device=batches[0].features.device)

        def cat(tensors: list[torch.Tensor]) -> torch.Tensor:
            return torch.cat(tensors)[back]

        return TrainingBatch(cat([b.features for b in batches]), cat([b.mask for b in batches]),
                             TrainingTargets(*(cat([b.targets[i] for b in batches]) for i in range(3))))


def with_canonical_replay(data, canonical, ratio: float):
    """``data`` (an iteration's pseudo-label renders) with ``round(ratio × len(data))`` samples of ``canonical``
    (iteration 0's renders; at least 1, at most all of them) per epoch, as a :class:`MixedDataset`; ``data`` itself
    when ``canonical`` is None or ``ratio`` ≤ 0 (``TrainConfig.canonical_replay``)."""
    if canonical is None or ratio <= 0:
        return data
    return MixedDataset([data, canonical], [len(data), min(len(canonical), max(1, round(ratio * len(data))))])


def _name(dataset) -> str:
    source = getattr(dataset, "source", dataset)
    return str(getattr(source, "folder", type(dataset).__name__))
