"""Task runners chosen by configuration: local threads, a Dask LocalCluster, dask-cuda, or SLURM (dask-jobqueue).

A runner config is a mapping (``TaskRunnerConfig``); named presets live in ``deploy/task_runners.yaml``, and the
``bootstrap`` flow's ``task_runner`` parameter is a preset name or the path of a YAML file holding one config.

* ``local``: ``StoppableThreadPoolTaskRunner(max_workers=workers)`` — a laptop; render shards still run Blender in
  their own processes. A Prefect ``ThreadPoolTaskRunner`` whose running tasks stop within seconds when the flow is
  stopped (SIGTERM, a cancel from the dashboard, Ctrl-C; ``bat3r_core.stopping``) instead of holding the process
  up until they finish.
* ``dask``: ``DaskTaskRunner`` over a ``distributed.LocalCluster`` of ``workers`` workers × ``threads_per_worker``.
* ``dask-cuda``: ``dask_cuda.LocalCUDACluster`` — one worker process per visible GPU, each pinned to its GPU
  (install the ``gpu`` extra).
* ``slurm``: ``dask_jobqueue.SLURMCluster`` with ``cluster`` passed through (queue, cores, memory, walltime,
  job_extra_directives, ...) and scaled to ``workers`` jobs, or adaptively with ``adapt`` (``slurm`` extra).
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Mapping

import yaml

from prefect.exceptions import ExternalSignal
from prefect.task_runners import ThreadPoolTaskRunner

from bat3r_core.config_utils import ConfigError, from_mapping
from bat3r_core.stopping import clear_stop_request, request_stop

__all__ = ["TaskRunnerConfig", "load_task_runner_config", "make_task_runner", "PRESETS_FILE",
           "StoppableThreadPoolTaskRunner"]

PRESETS_FILE = Path(__file__).resolve().parent.parent / "deploy" / "task_runners.yaml"


_STOPPING_SIGNALS = (ExternalSignal, KeyboardInterrupt, SystemExit)
"""What a flow unwinds with when its process is being stopped: Prefect's ``TerminationSignal`` (SIGTERM, including
a worker's cancellation), Ctrl-C, ``sys.exit``."""


class StoppableThreadPoolTaskRunner(ThreadPoolTaskRunner):
    """Prefect's thread-pool task runner, plus: when the flow leaves it on a stopping signal (``_STOPPING_SIGNALS``),
    the tasks still running in its threads are asked to stop (``bat3r_core.stopping.request_stop``) before the
    runner waits for them, so that a stopped run ends in seconds, not when its longest task would have finished.
    Entering a runner withdraws an earlier request (a new flow run in the same process)."""

    def __enter__(self):
        clear_stop_request()
        return super().__enter__()

    def __exit__(self, exc_type: Any, exc_value: Any, traceback: Any) -> None:
        if exc_type is not None and issubclass(exc_type, _STOPPING_SIGNALS):
            request_stop(f"the flow run was interrupted by {exc_type.__name__}")
        super().__exit__(exc_type, exc_value, traceback)


@dataclass(frozen=True)
class TaskRunnerConfig:
    """How a flow's tasks are executed.

    Attributes:
        kind: ``local``, ``dask``, ``dask-cuda`` or ``slurm``.
        workers: threads (local), worker processes (dask), or SLURM jobs to start (slurm); ignored by dask-cuda,
            which starts one worker per GPU.
        threads_per_worker: threads of each Dask worker (keep 1 for GPU stages: one task per device).
        processes: Dask LocalCluster workers as processes (True) or threads of this process (False).
        local_directory: Dask scratch folder (default: ``dask-scratch-space`` in the working directory).
        cluster: extra keyword arguments for the cluster class (e.g. SLURM ``queue``, ``cores``, ``memory``).
        adapt: ``{"minimum": m, "maximum": n}`` for adaptive scaling (Dask and SLURM); empty: fixed size.
    """

    kind: Literal["local", "dask", "dask-cuda", "slurm"] = "local"
    workers: int = 2
    threads_per_worker: int = 1
    processes: bool = True
    local_directory: str | None = None
    cluster: dict[str, Any] = field(default_factory=dict)
    adapt: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.workers < 1 or self.threads_per_worker < 1:
            raise ValueError(f"workers and threads_per_worker must be >= 1, got {self.workers}, "
                             f"{self.threads_per_worker}")
        unknown = sorted(set(self.adapt) - {"minimum", "maximum"})
        if unknown:
            raise ValueError(f"adapt: unknown key(s) {unknown}; allowed: ['maximum', 'minimum']")


def load_task_runner_config(spec: str | os.PathLike | Mapping[str, Any] | TaskRunnerConfig = "local",
                            presets: str | os.PathLike = PRESETS_FILE) -> TaskRunnerConfig:
    """A ``TaskRunnerConfig`` from a config, a mapping, a YAML file path, or a preset name of ``presets``."""
    if isinstance(spec, TaskRunnerConfig):
        return spec
    if isinstance(spec, Mapping):
        return _build(spec, "task_runner")
    if not isinstance(spec, (str, os.PathLike)):
        raise TypeError(f"task runner spec must be a preset name, a YAML path or a mapping, got "
                        f"{type(spec).__name__}")
    path = Path(spec)
    if path.suffix in (".yaml", ".yml"):
        if not path.is_file():
            raise FileNotFoundError(f"task runner config {path} does not exist")
        return _build(yaml.safe_load(path.read_text(encoding="utf-8")), str(path))
    with open(presets, encoding="utf-8") as f:
        table = yaml.safe_load(f) or {}
    if str(spec) not in table:
        raise ConfigError(f"unknown task runner preset {str(spec)!r} in {presets}; available: {sorted(table)}")
    return _build(table[str(spec)], f"{presets}:{spec}")


def _build(data: Any, path: str) -> TaskRunnerConfig:
    try:
        return from_mapping(TaskRunnerConfig, data, path)
    except ConfigError:
        raise
    except ValueError as e:
        raise ConfigError(f"{path}: {e}") from e


def make_task_runner(spec: str | os.PathLike | Mapping[str, Any] | TaskRunnerConfig = "local"):
    """The Prefect task runner for ``spec`` (see ``load_task_runner_config`` and the module docstring)."""
    cfg = load_task_runner_config(spec)
    if cfg.kind == "local":
        return StoppableThreadPoolTaskRunner(max_workers=cfg.workers)
    from prefect_dask import DaskTaskRunner

    kwargs: dict[str, Any] = {}
    if cfg.local_directory:
        kwargs["local_directory"] = cfg.local_directory
    if cfg.kind == "dask":
        cluster_class = "distributed.LocalCluster"
        kwargs.update(n_workers=cfg.workers, threads_per_worker=cfg.threads_per_worker, processes=cfg.processes,
                      dashboard_address=None)
    elif cfg.kind == "dask-cuda":
        _require("dask_cuda", "gpu")
        cluster_class = "dask_cuda.LocalCUDACluster"
        kwargs.update(threads_per_worker=cfg.threads_per_worker)
    else:
        _require("dask_jobqueue", "slurm")
        cluster_class = "dask_jobqueue.SLURMCluster"
    kwargs.update(cfg.cluster)
    adapt = dict(cfg.adapt) or None
    if cfg.kind == "slurm" and adapt is None:
        adapt = {"minimum": cfg.workers, "maximum": cfg.workers}
    return DaskTaskRunner(cluster_class=cluster_class, cluster_kwargs=kwargs, adapt_kwargs=adapt)


def _require(module: str, extra: str) -> None:
    try:
        __import__(module)
    except ImportError as e:
        raise ImportError(f"this task runner needs the '{module}' package: pip install -e '.[{extra}]'") from e
