"""Cache keys, retry settings and result storage shared by the stage tasks.

A stage task's cache key is a SHA-256 over

* the content of its input files (``bat3r_core.shards.content_hash``: names and bytes, in order),
* its stage config (``config_utils.to_mapping`` → canonical JSON),
* the code version of the ``bat3r_core`` module the stage table names for it (``bat3r_core.stages.STAGES``,
  ``bat3r_core.runs.stage_code_version``),
* the resolved OUTPUT location: a cache hit does not re-create files, so the same inputs written to another run or
  shard index must recompute.

Tasks return small JSON records (paths, content hashes, counts; ``bat3r_core.runs.shard_record``) and never arrays,
so results persist as JSON under the run folder (``RunLayout.results_dir``). Every record also carries the writer's
per-file digests (``file_digests``, with each file's inode, size and ns times): the flow seeds its digest memo with
them (``remember_record_digests``), so the cache keys of the stages that read those files, and the intact checks,
hash nothing again, in a fresh process on a cached rerun too. A cached record whose files were
deleted or changed since is detected by ``record_is_intact`` and recomputed by the flows (``refresh_cache``).
"""
from __future__ import annotations

import functools
import hashlib
import json
import os
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

from prefect import Task, task
from prefect.tasks import exponential_backoff

from bat3r_core import shards, stages
from bat3r_core.config_utils import to_mapping
from bat3r_core.runs import RunLayout, stage_code_version
from bat3r_core.specs import as_spec

__all__ = ["stage_cache_key", "shard_input_files", "record_files", "record_is_intact", "remember_record_digests",
           "stage_task", "with_file_digests", "for_run", "GPU_TAG", "RETRY_BACKOFF_FACTOR"]

GPU_TAG = "bat3r-gpu"
"""Tag of tasks that occupy a GPU (a Prefect tag concurrency limit on it caps them server-wide)."""
RETRY_BACKOFF_FACTOR = 2.0
"""Seconds before the first retry; doubled for every further retry (``prefect.tasks.exponential_backoff``)."""

_MISSING = "<missing>"


def _config_json(config: Any) -> str:
    try:
        return json.dumps(to_mapping(config), sort_keys=True, separators=(",", ":"), allow_nan=False)
    except (TypeError, ValueError) as e:
        raise ValueError(f"config must be JSON-serialisable to be part of a cache key: {e}") from e


def stage_cache_key(stage: str, code_version: str, input_files: Iterable[str | os.PathLike], config: Any,
                    output: str | os.PathLike) -> str:
    """``"<stage>-<32 hex>"``: the cache key of one stage task (see the module docstring).

    input_files: files whose bytes the task reads, in a fixed order; a missing file contributes its path and a
    marker (the task then runs and reports the missing input itself). config: a config dataclass tree or plain
    JSON-able data. output: the shard or folder the task writes (resolved to an absolute path).
    """
    if not isinstance(stage, str) or not stage:
        raise ValueError(f"stage must be a non-empty string, got {stage!r}")
    if not isinstance(code_version, str) or not code_version:
        raise ValueError(f"code_version must be a non-empty string, got {code_version!r}")
    h = hashlib.sha256()
    for name, value in (("stage", stage), ("code", code_version)):
        h.update(f"{name}={value}\0".encode())
    for f in input_files:
        p = Path(f)
        digest = shards.content_hash([p]) if p.is_file() else _MISSING
        h.update(f"input={p.resolve()}:{digest}\0".encode())
    h.update(f"config={_config_json(config)}\0".encode())
    h.update(f"output={Path(output).resolve()}\0".encode())
    return f"{stage}-{h.hexdigest()[:32]}"


def shard_input_files(folder: str | os.PathLike, index: int) -> list[Path]:
    """The files of shard ``index`` of ``folder``: its Parquet file and, when it exists, its npz."""
    p = shards.shard_paths(folder, index)
    return [p.parquet] + ([p.npz] if p.npz.is_file() else [])


def record_files(record: Mapping[str, Any]) -> list[Path]:
    """The files a task record names (``files``, ``parquet``, ``npz``, ``clouds``, ``predictor``) that exist, each
    once, in that order."""
    names = list(record.get("files") or ()) + [record.get(k) or "" for k in ("parquet", "npz", "clouds", "predictor")]
    out = []
    for name in dict.fromkeys(n for n in names if isinstance(n, str) and n):
        if Path(name).is_file():
            out.append(Path(name))
    return out


def with_file_digests(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn`` whose returned record also carries ``file_digests`` (``shards.file_digests`` of ``record_files``):
    the writer's hashes, taken from the digest memo its ``content_hash`` just filled, so downstream cache keys and
    intact checks in any process that reads the record (``remember_record_digests``) need not read the files."""
    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        record = fn(*args, **kwargs)
        if isinstance(record, dict):
            record["file_digests"] = shards.file_digests(record_files(record))
        return record

    return wrapper


def remember_record_digests(record: Mapping[str, Any]) -> int:
    """Seed this process's digest memo from a record's ``file_digests`` (``shards.remember_file_digests``:
    entries whose file changed since are ignored). Returns the number taken."""
    return shards.remember_file_digests(record.get("file_digests"))


def record_is_intact(record: Mapping[str, Any]) -> bool:
    """True when the files a task record names still exist with the content hash the task saw.

    Records carry ``parquet``/``npz`` (shards; hashed with ``shards.content_hash``) or ``files`` (a list of
    paths, e.g. a checkpoint) together with ``content_hash``.
    """
    if "files" in record:
        files = [Path(p) for p in record["files"]]
    else:
        files = [Path(record["parquet"])] + ([Path(record["npz"])] if record.get("npz") else [])
    if not all(p.is_file() for p in files):
        return False
    return shards.content_hash(files) == record.get("content_hash")


def stage_task(stage: str, *, inputs: Callable[[Mapping[str, Any]], Sequence[os.PathLike]],
               output: Callable[[Mapping[str, Any]], os.PathLike], spec: type | None = None,
               config_param: str = "config", retries: int = 0, gpu: bool = False,
               **task_kwargs: Any) -> Callable[[Callable], Task]:
    """Decorator: the Prefect task of stage ``stage`` of ``bat3r_core.stages.STAGES``, cached by
    ``stage_cache_key`` with the code version of the module the table names for it. A name that is not a stage of
    the table, or one that runs another stage's task (``Stage.task_stage``), is refused at import.

    inputs / output: map the task's bound parameters to its input files and its output location.
    spec: the typed spec (``bat3r_core.specs``) the task's config parameter holds; the key hashes the spec's
    mapping form, so the spec and a mapping of it (a deployment parameter, a test's dict) share one key.
    config_param: the parameter holding the stage config. retries: retried with exponential back-off
    (``RETRY_BACKOFF_FACTOR``·2^k seconds, 20 % jitter) — for rendering, I/O and inference. gpu: tag the task
    ``GPU_TAG``. Results persist as JSON (``result_serializer="json"``).
    """
    entry = stages.stage(stage)
    if entry.own_task != stage:
        raise ValueError(f"stage {stage!r} runs the task of stage {entry.own_task!r} (bat3r_core.stages.STAGES): "
                         "it has no task of its own")
    version = stage_code_version(entry.module)

    def key_fn(context: Any, parameters: Mapping[str, Any]) -> str:
        config = parameters.get(config_param)
        if spec is not None:  # a bad config raises here; Prefect logs it and the task reports it when it runs
            config = as_spec(spec, config, f"{stage} {config_param}")
        return stage_cache_key(stage, version, inputs(parameters), config, output(parameters))

    def decorate(fn: Callable) -> Task:
        options: dict[str, Any] = dict(name=f"{stage}", cache_key_fn=key_fn, persist_result=True,
                                       result_serializer="json", tags=[stage] + ([GPU_TAG] if gpu else []),
                                       retries=retries)
        if retries:
            options.update(retry_delay_seconds=exponential_backoff(RETRY_BACKOFF_FACTOR), retry_jitter_factor=0.2)
        options.update(task_kwargs)
        return task(**options)(with_file_digests(fn))

    return decorate


def for_run(stage_task_: Task, layout: RunLayout, **options: Any) -> Task:
    """``stage_task_`` with its results persisted under ``layout.results_dir`` (plus any other task options)."""
    return stage_task_.with_options(result_storage=Path(layout.results_dir).resolve(), **options)
