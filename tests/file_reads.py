"""Count the files a piece of code reads under a folder, whichever process or library reads them (Python's
``open``, pyarrow's C++ reader, numpy, a Blender subprocess): Linux inotify through ctypes, one watch per folder.

A read is a file opened without write access and closed again (``IN_CLOSE_NOWRITE``); ``stat`` and directory
listings are not reads. Used by the tests that check a cached rerun reads each run file at most once and that the
report's declared inputs cover what it opens::

    with FileReads(run_dir) as reads:
        ...
    assert max(reads.counts.values(), default=0) <= 1
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import select
import struct
import threading
from collections import Counter
from pathlib import Path

__all__ = ["FileReads"]

IN_CLOSE_NOWRITE = 0x00000010
IN_MOVED_TO = 0x00000080
IN_CREATE = 0x00000100
IN_Q_OVERFLOW = 0x00004000
IN_ISDIR = 0x40000000
_MASK = IN_CLOSE_NOWRITE | IN_CREATE | IN_MOVED_TO
_EVENT = struct.Struct("iIII")


class FileReads:
    """Read-only opens of every file under ``root`` while the context is open (``counts``: path → reads)."""

    def __init__(self, root: str | os.PathLike) -> None:
        self.root = Path(root).resolve()
        self.counts: Counter[Path] = Counter()
        self.overflowed = False
        self._libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        self._fd = -1
        self._folders: dict[int, Path] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _watch(self, folder: Path) -> None:
        for d, _, _ in os.walk(folder):
            wd = self._libc.inotify_add_watch(self._fd, os.fsencode(d), _MASK)
            if wd < 0:
                raise OSError(ctypes.get_errno(), f"inotify_add_watch({d}) failed")
            self._folders[wd] = Path(d)

    def _drain(self) -> None:
        while True:
            try:
                data = os.read(self._fd, 1 << 16)
            except BlockingIOError:
                return
            offset = 0
            while offset < len(data):
                wd, mask, _, size = _EVENT.unpack_from(data, offset)
                name = data[offset + _EVENT.size: offset + _EVENT.size + size].rstrip(b"\0").decode()
                offset += _EVENT.size + size
                if mask & IN_Q_OVERFLOW:
                    self.overflowed = True
                    continue
                folder = self._folders.get(wd)
                if folder is None or not name:
                    continue
                if mask & IN_ISDIR:
                    if mask & (IN_CREATE | IN_MOVED_TO):
                        self._watch(folder / name)
                elif mask & IN_CLOSE_NOWRITE:
                    self.counts[folder / name] += 1

    def _loop(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self._fd], [], [], 0.05)
            if ready:
                self._drain()

    def __enter__(self) -> "FileReads":
        self._fd = self._libc.inotify_init1(os.O_NONBLOCK | os.O_CLOEXEC)
        if self._fd < 0:
            raise OSError(ctypes.get_errno(), "inotify_init1 failed")
        self._watch(self.root)
        self._thread = threading.Thread(target=self._loop, name="file-reads", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self._drain()  # the events queued before the context closed
        os.close(self._fd)
        if self.overflowed:
            raise RuntimeError(f"inotify queue overflowed while watching {self.root}: counts are incomplete")

    def read_more_than_once(self) -> dict[str, int]:
        """``{path relative to root: reads}`` of the files read more than once."""
        return {str(p.relative_to(self.root)): n for p, n in sorted(self.counts.items()) if n > 1}
