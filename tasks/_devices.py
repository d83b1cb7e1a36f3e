"""One task per GPU: a process-local pool of GPU slots for the GPU stages (render on GPU, inference, training).

Inside one process (the default thread-pool task runner, or one Dask worker) ``gpu_slot()`` hands each GPU task a
free device index and blocks while every device is busy, so at most one GPU task runs per device. With dask-cuda's
``LocalCUDACluster`` every worker process sees a single GPU and runs one thread, which gives the same guarantee
across processes. Across machines or deployments, a Prefect tag concurrency limit on ``tasks._cache.GPU_TAG``
(``prefect concurrency-limit create bat3r-gpu <number of GPUs>``) caps GPU tasks server-wide.

Devices are the indices into ``CUDA_VISIBLE_DEVICES`` (or all CUDA devices torch sees when it is unset). With
no GPU the pool is empty and ``gpu_slot()`` yields ``None`` without blocking (CPU work is not limited here).
"""
from __future__ import annotations

import contextlib
import os
import threading
from typing import Iterator, Sequence

__all__ = ["DevicePool", "gpu_slot", "visible_gpus"]


class DevicePool:
    """A fixed set of device ids, each lent to one holder at a time (thread-safe)."""

    def __init__(self, devices: Sequence[int]) -> None:
        devices = list(devices)
        if any(isinstance(d, bool) or not isinstance(d, int) or d < 0 for d in devices):
            raise ValueError(f"devices must be non-negative integers, got {devices}")
        if len(set(devices)) != len(devices):
            raise ValueError(f"devices must be distinct, got {devices}")
        self.devices = tuple(devices)
        self._free = list(devices)
        self._cond = threading.Condition()

    @contextlib.contextmanager
    def slot(self, timeout: float | None = None) -> Iterator[int | None]:
        """Hold one free device for the ``with`` block (``None`` for an empty pool); ``TimeoutError`` after
        ``timeout`` seconds without a free device."""
        if not self.devices:
            yield None
            return
        with self._cond:
            if not self._cond.wait_for(lambda: bool(self._free), timeout=timeout):
                raise TimeoutError(f"no free GPU among {list(self.devices)} after {timeout} s")
            device = self._free.pop(0)
        try:
            yield device
        finally:
            with self._cond:
                self._free.append(device)
                self._cond.notify()


def visible_gpus() -> list[int]:
    """Indices of the CUDA devices this process may use (``CUDA_VISIBLE_DEVICES`` order)."""
    env = os.environ.get("CUDA_VISIBLE_DEVICES")
    if env is not None:
        ids = [s for s in env.split(",") if s.strip() and s.strip() != "-1"]
        return list(range(len(ids)))
    try:
        import torch
    except ImportError:
        return []
    return list(range(torch.cuda.device_count())) if torch.cuda.is_available() else []


_POOL: DevicePool | None = None
_POOL_LOCK = threading.Lock()


def gpu_slot(timeout: float | None = None) -> contextlib.AbstractContextManager[int | None]:
    """The process-wide pool's ``slot`` (the pool is built on first use from ``visible_gpus``)."""
    global _POOL
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = DevicePool(visible_gpus())
    return _POOL.slot(timeout)
