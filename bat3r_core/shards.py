"""Shard I/O: one Parquet table (+ an optional npz of dense arrays) per shard, written atomically.

A stage folder holds ``part-NNNNN.parquet`` and, for dense arrays, ``part-NNNNN.npz`` whose first axis follows
the Parquet row order. Both files are written under temporary names and renamed; the Parquet file is renamed
last, so its presence marks a complete shard and a crash never leaves a half-written shard that looks complete.
"""
from __future__ import annotations

import hashlib
import os
import re
import tempfile
import threading
from collections import Counter, OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

STATUS_OK = "ok"
_SHARD_RE = re.compile(r"^part-(\d{5})\.parquet$")


def shard_name(index: int) -> str:
    """``part-NNNNN`` for a non-negative shard index."""
    if index < 0:
        raise ValueError(f"shard index must be >= 0, got {index}")
    return f"part-{index:05d}"


@dataclass(frozen=True)
class ShardPaths:
    """Where a shard lives. ``npz`` may not exist for shards without dense arrays."""

    parquet: Path
    npz: Path

    @property
    def complete(self) -> bool:
        return self.parquet.is_file()


def shard_paths(folder: str | os.PathLike, index: int) -> ShardPaths:
    folder = Path(folder)
    name = shard_name(index)
    return ShardPaths(folder / f"{name}.parquet", folder / f"{name}.npz")


def atomic_write(path: str | os.PathLike, write_fn) -> Path:
    """Write ``path`` atomically: ``write_fn(tmp_path)`` writes a temporary file in the same folder, which is
    fsynced and renamed over ``path``; on any error the temporary file is removed and ``path`` is untouched."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        write_fn(tmp)
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Atomically replace ``path`` with ``data``."""
    def _write(tmp: str) -> None:
        with open(tmp, "wb") as f:
            f.write(data)
    return atomic_write(path, _write)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Atomically replace ``path`` with UTF-8 ``text``."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def _rows_to_table(rows: Sequence[Mapping[str, Any]] | pa.Table) -> pa.Table:
    if isinstance(rows, pa.Table):
        table = rows
    else:
        rows = list(rows)
        if rows:
            keys = list(rows[0].keys())
            for i, r in enumerate(rows):
                if list(r.keys()) != keys:
                    raise ValueError(f"row {i} has keys {sorted(r.keys())}, expected {sorted(keys)}")
            cols = {k: [_to_py(r[k]) for r in rows] for k in keys}
            table = pa.table(cols)
        else:
            table = pa.table({"sample_id": pa.array([], pa.string()), "status": pa.array([], pa.string()),
                              "reason": pa.array([], pa.string())})
    for required in ("sample_id", "status", "reason"):
        if required not in table.column_names:
            raise ValueError(f"shard rows must have a '{required}' column; got columns {table.column_names}")
    return table


def _to_py(v: Any) -> Any:
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    return v


def write_shard(folder: str | os.PathLike, index: int, rows: Sequence[Mapping[str, Any]] | pa.Table,
                arrays: Mapping[str, np.ndarray] | None = None) -> ShardPaths:
    """Write shard ``index`` of ``folder`` atomically.

    Args:
        rows: one mapping per sample (or a ``pyarrow.Table``) with at least ``sample_id``, ``status``, ``reason``.
        arrays: dense arrays whose first axis has one entry per row, saved to ``part-NNNNN.npz`` (uncompressed).
    """
    table = _rows_to_table(rows)
    paths = shard_paths(folder, index)
    if arrays:
        for k, a in arrays.items():
            a = np.asarray(a)
            if a.dtype == object:
                raise TypeError(f"array '{k}' has dtype object; shards store numeric/bool/str arrays only")
            if a.ndim == 0 or a.shape[0] != table.num_rows:
                raise ValueError(f"array '{k}' has shape {a.shape}; its first axis must equal the "
                                 f"{table.num_rows} rows of the shard")
        atomic_write(paths.npz, lambda tmp: _save_npz(tmp, arrays))
    atomic_write(paths.parquet, lambda tmp: pq.write_table(table, tmp))
    return paths


def _save_npz(tmp: str, arrays: Mapping[str, np.ndarray]) -> None:
    with open(tmp, "wb") as f:
        np.savez(f, **{k: np.asarray(v) for k, v in arrays.items()})


def read_shard(folder: str | os.PathLike, index: int, with_arrays: bool = True
               ) -> tuple[pa.Table, dict[str, np.ndarray]]:
    """Read a complete shard; raise ``FileNotFoundError`` naming the path if it is missing."""
    paths = shard_paths(folder, index)
    if not paths.complete:
        raise FileNotFoundError(f"shard {paths.parquet} does not exist or is incomplete")
    table = pq.read_table(paths.parquet)
    arrays: dict[str, np.ndarray] = {}
    if with_arrays and paths.npz.is_file():
        with np.load(paths.npz, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    return table, arrays


def list_shards(folder: str | os.PathLike) -> list[int]:
    """Indices of the complete shards in ``folder``, sorted."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    out = []
    for p in folder.iterdir():
        m = _SHARD_RE.match(p.name)
        if m:
            out.append(int(m.group(1)))
    return sorted(out)


def read_table(folder: str | os.PathLike) -> pa.Table:
    """Concatenate the Parquet rows of every complete shard in ``folder`` (empty table if none)."""
    tables = [pq.read_table(shard_paths(folder, i).parquet) for i in list_shards(folder)]
    if not tables:
        return _rows_to_table([])
    return pa.concat_tables(tables, promote_options="default")


_DIGESTS: "OrderedDict[tuple, bytes]" = OrderedDict()
_DIGEST_READS: Counter = Counter()
_DIGEST_LOCK = threading.Lock()
_MAX_DIGESTS = 200_000


def _version_key(p: Path) -> tuple:
    """A file version's identity: resolved path, inode, size, modification and change times in ns."""
    st = p.stat()
    return (str(p.resolve()), st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


def file_digest(path: str | os.PathLike) -> bytes:
    """SHA-256 of a file's bytes, read once per version of the file in this process: memoised by the file's
    identity and state (resolved path, inode, size, modification and change times in ns), so the several cache
    keys and record checks of a run that name one shard hash it once, and a file rewritten since (a new inode
    after an atomic write, or new times) is read again. A digest carried in a task record
    (:func:`file_digests`, :func:`remember_file_digests`) counts as read. Raises FileNotFoundError for a missing
    file."""
    p = Path(path)
    key = _version_key(p)
    with _DIGEST_LOCK:
        if key in _DIGESTS:
            _DIGESTS.move_to_end(key)
            return _DIGESTS[key]
    h = hashlib.sha256()
    with open(p, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    digest = h.digest()
    with _DIGEST_LOCK:
        _DIGESTS[key] = digest
        _DIGEST_READS[key[0]] += 1
        while len(_DIGESTS) > _MAX_DIGESTS:
            _DIGESTS.popitem(last=False)
    return digest


def read_bytes(path: str | os.PathLike) -> bytes:
    """A file's bytes, whose SHA-256 also enters the digest memo (keyed by the version of the file that was read,
    from ``fstat`` of the open file): a file read for its content is not read again to hash it."""
    p = Path(path)
    with open(p, "rb") as f:
        st = os.fstat(f.fileno())
        data = f.read()
    key = (str(p.resolve()), st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)
    with _DIGEST_LOCK:
        _DIGESTS[key] = hashlib.sha256(data).digest()
        while len(_DIGESTS) > _MAX_DIGESTS:
            _DIGESTS.popitem(last=False)
    return data


def file_digests(paths: Iterable[str | os.PathLike]) -> dict[str, list]:
    """``{resolved path: [sha256 hex, inode, size, mtime_ns, ctime_ns]}`` of the given files (hashed through the
    memo, so a file just hashed for its record is not read again): what a task record carries
    (``file_digests``) so that downstream cache keys and intact checks, in whichever process reads the record,
    reuse the writer's hash instead of reading the file (:func:`remember_file_digests`)."""
    out = {}
    for p in paths:
        p = Path(p)
        digest = file_digest(p)
        key = _version_key(p)
        out[key[0]] = [digest.hex(), *key[1:]]
    return out


def remember_file_digests(digests: Mapping[str, Sequence] | None) -> int:
    """Seed this process's digest memo with a record's ``file_digests`` (:func:`file_digests`): an entry is taken
    only while the file on disk is still that version (same inode, size and ns times, checked with ``stat``,
    not read); a file changed or gone since is skipped and is hashed from its bytes when next asked for.
    Returns the number of entries taken."""
    taken = 0
    for path, entry in (digests or {}).items():
        try:
            sha, *version = entry
            key = _version_key(Path(path))
            digest = bytes.fromhex(sha)
        except (OSError, ValueError, TypeError):
            continue
        if list(key[1:]) != [int(v) for v in version] or key[0] != path:
            continue
        with _DIGEST_LOCK:
            _DIGESTS[key] = digest
            while len(_DIGESTS) > _MAX_DIGESTS:
                _DIGESTS.popitem(last=False)
        taken += 1
    return taken


def file_digest_reads() -> dict[str, int]:
    """How many times each file (resolved path) was read by :func:`file_digest` since the last
    :func:`forget_file_digests` (for tests and diagnostics)."""
    with _DIGEST_LOCK:
        return dict(_DIGEST_READS)


def forget_file_digests() -> None:
    """Drop the memoised digests and the read counts (what a fresh process starts with)."""
    with _DIGEST_LOCK:
        _DIGESTS.clear()
        _DIGEST_READS.clear()


def content_hash(paths: Iterable[str | os.PathLike], extra: bytes | str = b"") -> str:
    """SHA-256 (hex, 16 chars) over the names and contents (:func:`file_digest`) of the given files, in order,
    plus ``extra``."""
    h = hashlib.sha256()
    for p in paths:
        p = Path(p)
        h.update(p.name.encode())
        h.update(file_digest(p))
    h.update(extra.encode() if isinstance(extra, str) else extra)
    return h.hexdigest()[:16]


def ok_mask(table: pa.Table) -> np.ndarray:
    """Boolean mask of rows whose status is ``"ok"``."""
    return np.asarray(table.column("status").to_pylist(), dtype=object) == STATUS_OK
