"""Fan a stage task out over shards: progress artifact, cache-integrity check, failed-shard policy, dropped samples.

``run_stage`` submits one task per call, updates a Prefect progress artifact as tasks finish, recomputes (with
``refresh_cache``) any cached record whose files are gone or changed, collects the shards whose task failed after
its retries, and applies ``bat3r_core.runs.apply_failure_policy``: the stage continues when the failed fraction is
at most the limit (the failures are returned for the summary), else ``TooManyFailedShards`` stops the flow. When
the stage's records mark more than ``bat3r_core.runs.DROP_WARN_FRACTION`` of its samples not ok, it logs a warning
and publishes a markdown artifact ``<progress key>-drops`` (``bat3r_core.runs.summarize_drops``).
"""
from __future__ import annotations

import re
import time
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

from prefect import Task
from prefect.client.orchestration import get_client
from prefect.exceptions import ObjectNotFound
from prefect.artifacts import create_markdown_artifact, create_progress_artifact, update_progress_artifact
from prefect.futures import as_completed
from prefect.logging import get_run_logger

from bat3r_core.runs import (DROP_WARN_FRACTION, FailureSummary, SampleDrops, ShardFailure, apply_failure_policy,
                             summarize_drops)
from tasks._cache import record_is_intact, remember_record_digests

__all__ = ["StageResult", "run_stage", "report_drops", "artifact_key"]


def artifact_key(*parts: Any) -> str:
    """A Prefect artifact key (lowercase letters, digits, dashes) made of ``parts``."""
    key = "-".join(str(p) for p in parts).lower()
    return re.sub(r"-+", "-", re.sub(r"[^a-z0-9-]", "-", key)).strip("-")


@dataclass(frozen=True)
class StageResult:
    """What a stage's fan-out produced.

    records: the task records of the shards that succeeded, in call order. failures: the failed-shard summary.
    cached: how many records came from the cache (state ``Cached``) and were intact. recomputed: cached records
    whose files had changed or vanished and were recomputed. states: final state name per call (call order).
    label: where the stage ran, for reports (``iteration 0 render``; default: the stage name).
    """

    stage: str
    records: tuple[dict, ...]
    summary: FailureSummary
    cached: int
    recomputed: int
    states: tuple[str, ...] = field(default=())
    label: str = ""

    @property
    def drops(self) -> SampleDrops:
        """The samples the stage's records kept and dropped (``bat3r_core.runs.summarize_drops``)."""
        return summarize_drops(self.stage, self.records, self.label or self.stage)


def _label(call: Mapping[str, Any], position: int) -> str:
    return f"part-{call['index']:05d}" if "index" in call else f"call-{position}"


def _attempts(future: Any, wait_s: float = 30.0) -> int | None:
    """Runs of a finished task run as the API records it (task states reach the API asynchronously, so poll);
    None when the API has not recorded the final state within ``wait_s``."""
    deadline = time.monotonic() + wait_s
    with get_client(sync_client=True) as client:
        while time.monotonic() < deadline:
            try:
                run = client.read_task_run(future.task_run_id)
            except ObjectNotFound:
                run = None
            if run is not None and run.state is not None and run.state.is_final():
                return int(run.run_count)
            time.sleep(0.25)
    return None


def report_drops(result: StageResult, artifact: str) -> SampleDrops:
    """Warn (flow log) and publish the markdown artifact ``artifact`` when ``result`` dropped more than
    ``DROP_WARN_FRACTION`` of its samples. Returns the stage's ``SampleDrops``."""
    drops = result.drops
    if drops.exceeds(DROP_WARN_FRACTION):
        get_run_logger().warning("%s", drops.describe())
        create_markdown_artifact(markdown=drops.markdown(), key=artifact, description=drops.headline())
    return drops


def run_stage(stage: str, stage_task: Task, calls: Sequence[Mapping[str, Any]], *, progress_key: str,
              max_failed_fraction: float, label: str | None = None) -> StageResult:
    """Run ``stage_task(**call)`` for every call concurrently (on the flow's task runner).

    calls: keyword arguments per task (with an ``index`` for shard tasks, used in labels). progress_key: the
    artifact key of this stage's progress bar (dropped samples: ``<progress_key>-drops``). label: where the stage
    runs, for messages (``iteration 0 render``; default: ``stage``). Returns a ``StageResult``; raises
    ``TooManyFailedShards`` when the failed fraction exceeds ``max_failed_fraction``.
    """
    logger = get_run_logger()
    calls = list(calls)
    progress_id = create_progress_artifact(progress=0.0, key=progress_key,
                                           description=f"{stage}: 0 of {len(calls)} shards")
    futures = [stage_task.submit(**call) for call in calls]
    position = {id(f): i for i, f in enumerate(futures)}
    records: dict[int, dict] = {}
    states: dict[int, str] = {}
    failures: list[ShardFailure] = []
    cached = recomputed = 0
    done = 0
    for fut in as_completed(futures):
        i = position[id(fut)]
        shard = _label(calls[i], i)
        current = fut
        current.wait()
        try:
            record = current.result()
            remember_record_digests(record)  # the writer's hashes: downstream cache keys read no file again
            if current.state.name == "Cached":
                if record_is_intact(record):
                    cached += 1
                else:
                    logger.warning("%s %s: cached result's files changed or vanished; recomputing", stage, shard)
                    current = stage_task.with_options(refresh_cache=True).submit(**calls[i])
                    current.wait()
                    record = current.result()
                    remember_record_digests(record)
                    recomputed += 1
            records[i] = record
        except Exception as exc:  # the task failed after its retries: report the shard, apply the policy
            attempts = _attempts(current)
            tries = f"after {attempts} attempt(s)" if attempts is not None else "after its retries"
            failures.append(ShardFailure(shard, f"{type(exc).__name__}: {exc} ({tries})"))
            logger.error("%s %s failed (%s): %s", stage, shard, tries, exc)
        states[i] = current.state.name
        done += 1
        update_progress_artifact(progress_id, 100.0 * done / max(len(calls), 1),
                                 description=f"{stage}: {done} of {len(calls)} shards ({len(failures)} failed)")
    summary = apply_failure_policy(stage, len(calls), sorted(failures, key=lambda f: f.label), max_failed_fraction)
    if failures:
        logger.warning("%s", summary.describe())
    result = StageResult(stage, tuple(records[i] for i in sorted(records)), summary, cached, recomputed,
                         tuple(states[i] for i in range(len(calls))), label or stage)
    report_drops(result, f"{progress_key}-drops")
    return result
