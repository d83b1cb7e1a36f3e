"""A cooperative stop for long loops: one process-wide request that training, fitting, rendering, feature
extraction and inference honour between two steps.

Python runs signal handlers in the main thread only. When a flow run is stopped (SIGTERM from a batch scheduler, a
Prefect worker cancelling the run from the dashboard, Ctrl-C), the flow's main thread unwinds at once, but a task
running in a worker thread of the thread-pool task runner keeps computing, and the process waits for it before it
exits: a training task could hold a "stopped" run up for an hour, past a scheduler's grace period. The local task
runner (``flows._runners.StoppableThreadPoolTaskRunner``) calls ``request_stop`` when its flow unwinds on such a
signal; the loops call ``raise_if_stop_requested`` and end with ``StopRequested`` — the trainer after writing a
checkpoint of the step it reached, the render runner after killing its Blender workers — so the process exits in
seconds and a rerun resumes every completed shard (and the training from that step).

``StopRequested`` derives from ``BaseException``, not ``Exception``: no per-sample or per-shard handler that records
bad input and moves on may take a stop for a bad sample.

A library user can stop the loops of their own threads the same way (``request_stop()`` from a signal handler);
``clear_stop_request()`` re-arms them. Tasks on Dask workers run in other processes and do not see this request
(their cluster is shut down instead).
"""
from __future__ import annotations

import threading

__all__ = ["StopRequested", "request_stop", "clear_stop_request", "stop_requested", "raise_if_stop_requested"]


class StopRequested(BaseException):
    """A loop ended early because a stop was requested (``request_stop``); the work it finished is kept."""


_REQUEST = threading.Event()
_REASON: list[str] = [""]


def request_stop(reason: str = "stop requested") -> None:
    """Ask every loop of this process to end at its next step with ``StopRequested`` (``reason`` is in its message)."""
    _REASON[0] = reason
    _REQUEST.set()


def clear_stop_request() -> None:
    """Withdraw a stop request: loops run to completion again."""
    _REQUEST.clear()
    _REASON[0] = ""


def stop_requested() -> bool:
    """Whether a stop has been requested and not withdrawn."""
    return _REQUEST.is_set()


def raise_if_stop_requested(where: str) -> None:
    """Raise ``StopRequested`` naming ``where`` (e.g. ``training at step 1200``) when a stop has been requested."""
    if _REQUEST.is_set():
        raise StopRequested(f"{where}: stopped ({_REASON[0] or 'stop requested'})")
