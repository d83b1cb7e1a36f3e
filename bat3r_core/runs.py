"""Run folders: their layout, manifest, code versions, shard records and the failed-shard policy. No Prefect.

A run lives in ``<storage root>/<category>/<run name>/`` (``DESIGN.md``, "Storage contract")::

    manifest.json            resolved config, code version, per-stage code versions (``write_manifest``)
    metrics.parquet          one row per (iteration, split)  (bat3r_core.evaluation)
    report.html              the run report                  (bat3r_core.report)
    collection/ test/        run-level stage folders (shards of the image collection and the test split)
    iter-00/<stage>/         one folder per stage of an iteration: part-NNNNN.parquet (+ .npz) shards
    iter-01/<stage>/ ...
    .prefect/results/        results of the orchestration's tasks (Prefect result storage; not needed to read a run)

Stage folders of an iteration, in data-flow order: ``infer, fit, plan, render, features, train, evaluate``.
Iteration 0 has no ``infer``/``fit``: its ``plan`` holds render jobs sampled around the rest-pose mesh.

``stage_code_version`` hashes the source of the ``bat3r_core`` modules a stage's module reaches through its imports
(statically, without importing them), so a cache keyed by it is invalidated exactly when that code changes.
"""
from __future__ import annotations

import ast
import hashlib
import json
import math
import os
import re
import subprocess
import time
import types
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping

import pyarrow.parquet as pq

from bat3r_core import shards, stages

__all__ = ["ITERATION_STAGES", "RUN_STAGES", "RunLayout", "code_version", "stage_code_version", "write_manifest",
           "read_manifest", "shard_record", "ShardFailure", "FailureSummary", "TooManyFailedShards",
           "apply_failure_policy", "prune_shards", "folder_record", "DROP_WARN_FRACTION", "DROP_HINTS",
           "STAGE_NOUNS", "pseudo_label_filter_notes", "DropReason", "SampleDrops", "summarize_drops", "SampleNeed",
           "training_need",
           "TooFewSamples", "require_samples"]

ITERATION_STAGES = stages.iteration_folders()
"""Stage folders inside ``iter-NN/``, in the order of their first writer in the stage table (``bat3r_core.stages``)."""
RUN_STAGES = stages.run_folders()
"""Run-level stage folders (not tied to an iteration; from the stage table)."""

MANIFEST_FILE = "manifest.json"
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
_PACKAGE_DIR = Path(__file__).resolve().parent
_PACKAGE = "bat3r_core"
_MAX_LISTED_FAILURES = 20


def _check_name(what: str, value: Any) -> str:
    if not isinstance(value, str) or not _NAME_RE.match(value):
        raise ValueError(f"{what} must be a folder name of letters, digits, '.', '_' or '-' (not starting with "
                         f"'.', '_' or '-'), got {value!r}")
    return value


@dataclass(frozen=True)
class RunLayout:
    """Paths of one run folder. Constructing it touches no file; ``create`` makes the folder.

    Attributes:
        storage_root: the catalog's storage root (absolute or relative to the working directory).
        category: category name (a folder name).
        run_name: run name (a folder name).
    """

    storage_root: Path
    category: str
    run_name: str

    def __post_init__(self) -> None:
        if not isinstance(self.storage_root, (str, os.PathLike)):
            raise TypeError(f"storage_root must be a path, got {type(self.storage_root).__name__}")
        object.__setattr__(self, "storage_root", Path(self.storage_root))
        _check_name("category", self.category)
        _check_name("run_name", self.run_name)

    @property
    def root(self) -> Path:
        """``<storage root>/<category>/<run name>``."""
        return self.storage_root / self.category / self.run_name

    @property
    def manifest(self) -> Path:
        return self.root / MANIFEST_FILE

    @property
    def metrics(self) -> Path:
        return self.root / "metrics.parquet"

    @property
    def report(self) -> Path:
        return self.root / "report.html"

    @property
    def results_dir(self) -> Path:
        """Where the orchestration persists task results (Prefect result storage)."""
        return self.root / ".prefect" / "results"

    def iteration_dir(self, iteration: int) -> Path:
        """``iter-NN`` (two digits at least) for iteration ``iteration >= 0``."""
        if isinstance(iteration, bool) or not isinstance(iteration, int) or iteration < 0:
            raise ValueError(f"iteration must be an integer >= 0, got {iteration!r}")
        return self.root / f"iter-{iteration:02d}"

    def stage_dir(self, iteration: int, stage: str) -> Path:
        """``iter-NN/<stage>``; ``stage`` is one of ``ITERATION_STAGES``."""
        if stage not in ITERATION_STAGES:
            raise ValueError(f"stage must be one of {list(ITERATION_STAGES)}, got {stage!r}")
        return self.iteration_dir(iteration) / stage

    def run_stage_dir(self, stage: str) -> Path:
        """A run-level stage folder; ``stage`` is one of ``RUN_STAGES``."""
        if stage not in RUN_STAGES:
            raise ValueError(f"run-level stage must be one of {list(RUN_STAGES)}, got {stage!r}")
        return self.root / stage

    def create(self) -> "RunLayout":
        """Create the run folder (and its parents); returns ``self``."""
        self.root.mkdir(parents=True, exist_ok=True)
        return self


# ------------------------------------------------------------------------------------------------ code versions

def code_version() -> str:
    """``git describe --always --dirty`` of the checkout holding bat3r_core (``"git:<describe>"``), else the
    installed package version (``"bat3r <version>"``), else ``"bat3r <bat3r_core.__version__>"``."""
    repo = _PACKAGE_DIR.parent
    if (repo / ".git").exists():
        try:
            out = subprocess.run(["git", "describe", "--always", "--dirty"], cwd=repo, capture_output=True,
                                 text=True, timeout=10, check=True)
            if out.stdout.strip():
                return f"git:{out.stdout.strip()}"
        except (OSError, subprocess.SubprocessError):
            pass
    try:
        from importlib.metadata import PackageNotFoundError, version

        return f"bat3r {version('bat3r')}"
    except PackageNotFoundError:
        from bat3r_core import __version__

        return f"bat3r {__version__}"


def _module_file(name: str) -> Path | None:
    """Source file of a ``bat3r_core`` module name, resolved by path (nothing is imported); None if none."""
    if name != _PACKAGE and not name.startswith(_PACKAGE + "."):
        return None
    rel = name.split(".")[1:]
    base = _PACKAGE_DIR.joinpath(*rel)
    if base.with_suffix(".py").is_file() and rel:
        return base.with_suffix(".py")
    if (base / "__init__.py").is_file():
        return base / "__init__.py"
    return None


def _parse(path: Path) -> ast.Module:
    """``ast.parse`` of a source file, retried on CPython 3.11.7's spurious "AST constructor recursion depth
    mismatch" SystemError: the depth counter is interpreter-wide, so a parse in another thread at the same moment
    (Prefect parses flow sources for parameter schemas) can trip it (python/cpython gh-106905, fixed in later
    releases). Each parse resets the counter, so a retry succeeds."""
    source = path.read_text(encoding="utf-8")
    for attempt in range(4):
        try:
            return ast.parse(source, filename=str(path))
        except SystemError as e:
            if "recursion depth mismatch" not in str(e):
                raise
            time.sleep(0.01 * (attempt + 1))
    return ast.parse(source, filename=str(path))  # the last try: its error propagates


def _imported_modules(name: str, path: Path) -> set[str]:
    """``bat3r_core`` module names imported anywhere in ``path`` (module level or inside functions)."""
    is_package = path.name == "__init__.py"
    package = name if is_package else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(_parse(path)):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                parts = parts[: len(parts) - (node.level - 1)]
                base = ".".join(parts + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            for alias in node.names:  # "from pkg import submodule" reads the submodule, not pkg/__init__
                sub = f"{base}.{alias.name}"
                found.add(sub if _module_file(sub) is not None else base)
    return {m for m in found if _module_file(m) is not None}


def _module_closure(root: str) -> dict[str, Path]:
    todo, seen = [root], {}
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        path = _module_file(name)
        if path is None:
            continue
        seen[name] = path
        todo.extend(_imported_modules(name, path) - set(seen))
    return seen


def stage_code_version(stage_module: str | types.ModuleType) -> str:
    """16-hex SHA-256 over the source of ``stage_module`` and every ``bat3r_core`` module it reaches by imports.

    stage_module: a ``bat3r_core`` module or its dotted name (``"bat3r_core.predictor.features"``). Imports are
    found statically (``ast``), including imports inside functions; a package's ``__init__`` counts only when it
    is imported itself (``from bat3r_core import shards`` reads ``bat3r_core/shards.py``, not the re-exports).
    Modules are hashed in name order, each as its name and its bytes.
    """
    name = stage_module.__name__ if isinstance(stage_module, types.ModuleType) else stage_module
    if not isinstance(name, str):
        raise TypeError(f"stage_module must be a module or a dotted name, got {type(stage_module).__name__}")
    if _module_file(name) is None:
        raise ValueError(f"stage_module must name a bat3r_core module with a source file, got {name!r}")
    h = hashlib.sha256()
    for mod, path in sorted(_module_closure(name).items()):
        h.update(mod.encode() + b"\0")
        h.update(path.read_bytes())
        h.update(b"\0")
    return h.hexdigest()[:16]


# -------------------------------------------------------------------------------------------------- manifest

def read_manifest(layout: RunLayout) -> dict[str, Any]:
    """The run's ``manifest.json`` as a dict (``{}`` when it does not exist yet)."""
    if not layout.manifest.is_file():
        return {}
    return json.loads(shards.read_bytes(layout.manifest).decode("utf-8"))  # read once: its digest is kept too


def write_manifest(layout: RunLayout, config: Mapping[str, Any], stage_modules: Mapping[str, str]
                   ) -> dict[str, Any]:
    """Write ``manifest.json`` atomically and return its content.

    config: the resolved run configuration (JSON-serialisable; e.g. ``config_utils.to_mapping`` of the stage
    configs, plus the run parameters). stage_modules: stage name → the ``bat3r_core`` module it runs; each gets
    its ``stage_code_version``. Keys: ``category, run_name, config, code_version, stage_code_versions, created,
    updated`` (UTC ISO-8601; ``created`` is kept from an earlier manifest of the same run). A manifest whose
    content would not change but for ``updated`` is left as it is (a cached rerun writes nothing, so the report's
    cache key, which holds the manifest, stays the same).
    """
    if not isinstance(config, Mapping):
        raise TypeError(f"config must be a mapping, got {type(config).__name__}")
    try:
        json.dumps(config, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise ValueError(f"config must be JSON-serialisable (no NaN): {e}") from e
    now = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    previous = read_manifest(layout)
    manifest = {
        "category": layout.category,
        "run_name": layout.run_name,
        "config": dict(config),
        "code_version": code_version(),
        "stage_code_versions": {stage: stage_code_version(mod) for stage, mod in sorted(stage_modules.items())},
        "created": previous.get("created", now),
        "updated": now,
    }
    if previous and {**previous, "updated": now} == json.loads(json.dumps(manifest)):
        return previous
    shards.atomic_write_text(layout.manifest, json.dumps(manifest, indent=2, sort_keys=True) + "\n")
    return manifest


# ------------------------------------------------------------------------------------------------ shard records

def shard_record(stage: str, index: int, paths: shards.ShardPaths) -> dict[str, Any]:
    """The small record a task returns for a shard it wrote (JSON-serialisable; no arrays).

    Keys: ``stage, index, parquet, npz`` (``""`` when the shard has no npz), ``content_hash``
    (``shards.content_hash`` of its files), ``n_rows``, ``n_ok``, ``n_failed``, ``failed_samples`` (at most
    20 ``[sample_id, status, reason]`` of the rows whose status is not ``"ok"``), ``status_counts``
    (``{status: rows}`` of those rows) and ``status_examples`` (``{status: [sample_id, reason]}``, the first row
    of each status) — what :func:`summarize_drops` reads.
    """
    if not paths.complete:
        raise FileNotFoundError(f"shard {paths.parquet} does not exist or is incomplete")
    files = [paths.parquet] + ([paths.npz] if paths.npz.is_file() else [])
    table = pq.read_table(paths.parquet, columns=["sample_id", "status", "reason"])
    ok = shards.ok_mask(table)
    bad = [[r["sample_id"], r["status"], r["reason"]] for r, good in zip(table.to_pylist(), ok) if not good]
    return {
        "stage": stage, "index": int(index), "parquet": str(paths.parquet),
        "npz": str(paths.npz) if paths.npz.is_file() else "",
        "content_hash": shards.content_hash(files), "n_rows": table.num_rows, "n_ok": int(ok.sum()),
        "n_failed": len(bad), "failed_samples": bad[:_MAX_LISTED_FAILURES], **_status_details(bad),
    }


def _status_details(bad: list[list]) -> dict[str, Any]:
    """``status_counts`` ({status: rows}) and ``status_examples`` ({status: [sample_id, reason]}, the first row of
    each status) of the not-ok rows ``[[sample_id, status, reason, ...], ...]``."""
    counts: dict[str, int] = {}
    examples: dict[str, list] = {}
    for row in bad:
        counts[row[1]] = counts.get(row[1], 0) + 1
        examples.setdefault(row[1], [row[0], row[2]] + list(row[3:4]))
    return {"status_counts": counts, "status_examples": examples}


def folder_record(stage: str, folder: str | os.PathLike) -> dict[str, Any]:
    """One record for all complete shards of ``folder`` (e.g. the hidden render shards of a generated collection):
    like :func:`shard_record`, with ``parquet`` the first shard, ``files`` every shard file, ``n_shards`` and
    ``failed_samples`` entries ``[sample_id, status, reason, shard parquet]``. Raises FileNotFoundError when the
    folder has no complete shard."""
    indices = shards.list_shards(folder)
    if not indices:
        raise FileNotFoundError(f"{folder}: no complete shard (part-NNNNN.parquet)")
    records = [shard_record(stage, i, shards.shard_paths(folder, i)) for i in indices]
    bad = []
    for rec in records:
        table = pq.read_table(rec["parquet"], columns=["sample_id", "status", "reason"])
        bad += [[r["sample_id"], r["status"], r["reason"], rec["parquet"]]
                for r, good in zip(table.to_pylist(), shards.ok_mask(table)) if not good]
    files = [f for rec in records for f in [rec["parquet"]] + ([rec["npz"]] if rec["npz"] else [])]
    return {"stage": stage, "parquet": records[0]["parquet"], "files": files,
            "content_hash": shards.content_hash(files), "n_shards": len(records),
            "n_rows": sum(r["n_rows"] for r in records), "n_ok": sum(r["n_ok"] for r in records),
            "n_failed": len(bad), "failed_samples": bad[:_MAX_LISTED_FAILURES], **_status_details(bad)}


def prune_shards(folder: str | os.PathLike, keep: Iterable[int]) -> list[int]:
    """Delete the shards of ``folder`` whose index is not in ``keep`` (left by an earlier, larger plan of the same
    run); the Parquet file goes first, so a shard never looks complete without its npz. Returns the indices
    removed."""
    keep = {int(k) for k in keep}
    removed = []
    for index in shards.list_shards(folder):
        if index in keep:
            continue
        paths = shards.shard_paths(folder, index)
        paths.parquet.unlink()
        if paths.npz.is_file():
            paths.npz.unlink()
        removed.append(index)
    return removed


# --------------------------------------------------------------------------------------- failed-shard policy

@dataclass(frozen=True)
class ShardFailure:
    """A shard whose task failed after its retries: ``label`` (e.g. ``part-00003``) and the error text."""

    label: str
    reason: str


@dataclass(frozen=True)
class FailureSummary:
    """Outcome of one stage's fan-out: ``n_total`` shards, the ``failures``, and the limit they were held to."""

    stage: str
    n_total: int
    failures: tuple[ShardFailure, ...]
    max_failed_fraction: float

    @property
    def failed_fraction(self) -> float:
        return len(self.failures) / self.n_total if self.n_total else 0.0

    def describe(self) -> str:
        """One line per failure after a header, e.g. ``render: 1 of 4 shards failed (25.0%, limit 50.0%)``."""
        head = (f"{self.stage}: {len(self.failures)} of {self.n_total} shards failed "
                f"({100 * self.failed_fraction:.1f}%, limit {100 * self.max_failed_fraction:.1f}%)")
        return "\n".join([head] + [f"  {f.label}: {f.reason}" for f in self.failures])


class TooManyFailedShards(RuntimeError):
    """More shards of a stage failed than the run allows; the message lists them."""

    def __init__(self, summary: FailureSummary | str) -> None:
        if isinstance(summary, str):  # unpickled (Prefect states, Dask): args == (message,)
            super().__init__(summary)
            self.summary = None
            return
        super().__init__(f"stage {summary.describe()}\nThe failed fraction exceeds the limit "
                         f"(max_failed_fraction={summary.max_failed_fraction}); fix the cause and rerun with the "
                         f"same run name (completed shards are reused), or raise the limit.")
        self.summary = summary


def apply_failure_policy(stage: str, n_total: int, failures: Iterable[ShardFailure | tuple[str, str]],
                         max_failed_fraction: float) -> FailureSummary:
    """Decide whether a stage may continue with some shards failed.

    n_total: shards the stage fanned out over (>= 0). failures: the shards that failed after retries, as
    ``ShardFailure`` or ``(label, reason)``. max_failed_fraction: in [0, 1]; the stage continues when
    ``failed / n_total <= max_failed_fraction`` (0 tolerates no failure, 1 tolerates all).
    Returns the summary; raises ``TooManyFailedShards`` (listing every failed shard) otherwise.
    """
    if isinstance(n_total, bool) or not isinstance(n_total, int) or n_total < 0:
        raise ValueError(f"n_total must be an integer >= 0, got {n_total!r}")
    if not isinstance(max_failed_fraction, (int, float)) or isinstance(max_failed_fraction, bool) \
            or not math.isfinite(max_failed_fraction) or not 0.0 <= max_failed_fraction <= 1.0:
        raise ValueError(f"max_failed_fraction must be a number in [0, 1], got {max_failed_fraction!r}")
    items = tuple(f if isinstance(f, ShardFailure) else ShardFailure(str(f[0]), str(f[1])) for f in failures)
    if len(items) > n_total:
        raise ValueError(f"{len(items)} failures reported for stage {stage!r} but only n_total={n_total} shards")
    summary = FailureSummary(stage, n_total, items, float(max_failed_fraction))
    if summary.failed_fraction > summary.max_failed_fraction:
        raise TooManyFailedShards(summary)
    return summary


# ------------------------------------------------------------------------------------------- dropped samples

DROP_WARN_FRACTION = 0.05
"""A stage that marks more than this fraction of its samples not ok is reported: a warning in the flow log, a
markdown artifact ``…-<stage>-drops`` and a section of the iteration summary (docs/orchestration.md)."""
_TOP_REASONS = 3

DROP_HINTS = {
    "mask_mismatch": "run `bat3r asset check {asset} --category {category}{catalog}` (the asset Blender renders and "
                     "the rig bat3r ray-casts disagree: scale, up axis, skin)",
    "bad_texture": "check categories.{category}.textures in the data catalog",
    "bad_envmap": "check categories.{category}.environment_maps in the data catalog",
    "bad_job": "the render jobs hold non-finite poses or cameras (see the plan stage)",
    "failed": "the render worker failed on these jobs (the reason quotes its log)",
    "empty": "the object is not in view: check the camera prior and the asset's scale",
    "bad_image": "fix or remove these files of the collection (docs/collections.md, \"Bad files\")",
    "missing_mask": "give every image a mask (docs/collections.md, \"Bad files\")",
    "bad_mask": "fix these masks (docs/collections.md, \"Bad files\")",
    "empty_mask": "these masks have no foreground pixel (docs/collections.md, \"Bad files\")",
    "size_mismatch": "mask and image sizes differ (docs/collections.md, \"Bad files\")",
}
"""What to do about the most frequent drop status; ``{category}``, ``{asset}`` (the category's asset file) and
``{catalog}`` (`` --catalog PATH`` or empty) are filled in by :func:`require_samples`."""

STAGE_NOUNS = {s.name: s.noun for s in stages.STAGES}
"""What a stage's samples are called in reports (the stage table's ``Stage.noun``; default ``samples``)."""


@dataclass(frozen=True)
class DropReason:
    """One status of the samples a stage dropped: how many rows, and one of them (its reason, sample and shard)."""

    status: str
    count: int
    reason: str
    sample_id: str
    shard: str


@dataclass(frozen=True)
class SampleDrops:
    """How many samples a stage kept and dropped, by status (most frequent first).

    Attributes:
        label: where, e.g. ``iteration 0 render`` or ``collection``. stage: the stage name. noun: what the samples
        are (``renders``). n_total / n_ok: samples the stage wrote / with status ok. reasons: the drop statuses.
    """

    label: str
    stage: str
    noun: str
    n_total: int
    n_ok: int
    reasons: tuple[DropReason, ...] = ()

    @property
    def n_dropped(self) -> int:
        return self.n_total - self.n_ok

    @property
    def fraction(self) -> float:
        return self.n_dropped / self.n_total if self.n_total else 0.0

    def exceeds(self, threshold: float = DROP_WARN_FRACTION) -> bool:
        """True when more than ``threshold`` of the samples were dropped."""
        return self.n_dropped > 0 and self.fraction > threshold

    def headline(self) -> str:
        """``iteration 0 render: 25 of 32 renders dropped (78.1 %)``."""
        return (f"{self.label}: {self.n_dropped} of {self.n_total} {self.noun} dropped "
                f"({100 * self.fraction:.1f} %)")

    def reasons_text(self, top: int = _TOP_REASONS) -> str:
        """``mask_mismatch ×25 (Blender mask and … IoU 0.512 < 0.8)`` for the ``top`` statuses, ``; ``-joined."""
        parts = [f"{r.status} ×{r.count} ({r.reason})" if r.reason else f"{r.status} ×{r.count}"
                 for r in self.reasons[:top]]
        more = len(self.reasons) - top
        return "; ".join(parts + ([f"{more} other status(es)"] if more > 0 else []))

    def example(self) -> str:
        """``e.g. sample canonical-000003 in …/part-00000.parquet`` (the most frequent status), or ``""``."""
        r = self.reasons[0] if self.reasons else None
        if r is None or not (r.sample_id or r.shard):
            return ""
        return f"e.g. sample {r.sample_id} in {r.shard}" if r.sample_id else f"e.g. in {r.shard}"

    def describe(self) -> str:
        """One line: headline, the top reasons and an example file."""
        if not self.n_dropped:
            return f"{self.label}: {self.n_ok} {self.noun}, none dropped"
        example = self.example()
        return f"{self.headline()}: {self.reasons_text()}" + (f" — {example}" if example else "")

    def markdown(self, heading: bool = True) -> str:
        """A markdown table (status, count, share, representative reason, example sample and shard) after a bold
        headline (``heading``)."""
        lines = [f"**{self.headline()}**; {self.n_ok} kept.", ""] if heading else []
        lines += ["| status | samples | share | representative reason | example sample | shard |",
                  "|---|---|---|---|---|---|"]
        for r in self.reasons:
            share = 100.0 * r.count / self.n_total if self.n_total else 0.0
            cell = r.reason.replace("|", "\\|").replace("\n", " ")
            lines.append(f"| {r.status} | {r.count} | {share:.1f} % | {cell} | `{r.sample_id}` | `{r.shard}` |")
        return "\n".join(lines)

    def to_mapping(self) -> dict[str, Any]:
        """JSON form (flow parameters, records); :meth:`from_mapping` reads it back."""
        return {"label": self.label, "stage": self.stage, "noun": self.noun, "n_total": self.n_total,
                "n_ok": self.n_ok, "reasons": [dict(vars(r)) for r in self.reasons]}

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any]) -> "SampleDrops":
        return cls(str(data["label"]), str(data["stage"]), str(data["noun"]), int(data["n_total"]),
                   int(data["n_ok"]), tuple(DropReason(**r) for r in data.get("reasons", ())))


def summarize_drops(stage: str, records: Iterable[Mapping[str, Any]], label: str | None = None,
                    noun: str | None = None) -> SampleDrops:
    """Add up the samples a stage's task records kept and dropped.

    records: task records; shard records (:func:`shard_record`, :func:`folder_record`) count their rows
    (``n_rows``, ``n_ok``, ``status_counts``, ``status_examples``; records without the last two fall back on
    ``failed_samples``); job-planning records without rows count their ``n_jobs`` as kept samples; other records
    (training, metrics) count nothing. label: where (default: ``stage``); noun: default ``STAGE_NOUNS``.
    Reasons are sorted by count (then status); each keeps the first example met, in record order.
    """
    n_total = n_ok = 0
    counts: dict[str, int] = {}
    examples: dict[str, DropReason] = {}
    for rec in records:
        if "n_rows" not in rec:
            jobs = int(rec.get("n_jobs", 0))
            n_total, n_ok = n_total + jobs, n_ok + jobs
            continue
        n_total += int(rec["n_rows"])
        n_ok += int(rec["n_ok"])
        failed = [list(f) for f in rec.get("failed_samples", ())]
        rec_counts = rec.get("status_counts")
        if rec_counts is None:
            rec_counts = {}
            for f in failed:
                rec_counts[f[1]] = rec_counts.get(f[1], 0) + 1
        rec_examples = {k: list(v) for k, v in (rec.get("status_examples") or {}).items()}
        for f in failed:
            rec_examples.setdefault(f[1], [f[0], f[2]] + f[3:4])
        for status, count in rec_counts.items():
            counts[status] = counts.get(status, 0) + int(count)
            if status not in examples:
                ex = rec_examples.get(status, ["", ""])
                shard = ex[2] if len(ex) > 2 else str(rec.get("parquet", ""))
                examples[status] = DropReason(status, 0, str(ex[1]), str(ex[0]), shard)
    reasons = tuple(DropReason(s, c, examples[s].reason, examples[s].sample_id, examples[s].shard)
                    for s, c in sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))
    return SampleDrops(label or stage, stage, noun or STAGE_NOUNS.get(stage, "samples"), n_total, n_ok, reasons)


@dataclass(frozen=True)
class SampleNeed:
    """What the next stage needs: at least ``n`` samples for ``consumer`` (``training``), because ``why``."""

    n: int
    consumer: str
    why: str


def training_need(batch_size: int, world_size: int | None = None) -> SampleNeed:
    """Training needs one full batch per process: ``batch_size × world_size`` samples. world_size: default the
    torchrun environment's ``WORLD_SIZE`` (1 without it), as the trainer reads it."""
    world = int(os.environ.get("WORLD_SIZE", "1")) if world_size is None else int(world_size)
    if batch_size < 1 or world < 1:
        raise ValueError(f"batch_size and world_size must be >= 1, got {batch_size}, {world}")
    return SampleNeed(batch_size * world, "training",
                      f"batch_size × world_size = {batch_size} × {world}" if world > 1 else "batch_size × world_size")


class TooFewSamples(RuntimeError):
    """A stage ended with fewer samples than the next stage needs; the message says where they were lost."""

    def __init__(self, message: str, drops: SampleDrops | None = None, need: SampleNeed | None = None) -> None:
        super().__init__(message)  # args == (message,): pickles and unpickles (Prefect states, Dask)
        self.drops, self.need = drops, need


def require_samples(drops: SampleDrops, need: SampleNeed, upstream: Iterable[SampleDrops] = (),
                    category: str = "", asset: str = "", catalog: str = "") -> SampleDrops:
    """Stop the run unless the stage kept at least ``need.n`` samples.

    The message names the stage, how many of its samples it dropped and why (the top statuses with a
    representative reason and an example file), what to do about the most frequent status (``DROP_HINTS``), what
    the next stage needs, and the upstream stages (``upstream``) that dropped samples, e.g. ``iteration 0 render:
    25 of 32 renders dropped (78.1 %): mask_mismatch ×25 (…) — run `bat3r asset check assets/horse/horse.glb
    --category horse` …; training needs at least 8 (batch_size × world_size), 7 left (e.g. sample … in …)``.
    category, asset, catalog: fill the hint (``catalog``: the catalog file, when not the default one).
    Returns ``drops`` when there are enough; raises :class:`TooFewSamples` otherwise.
    """
    if drops.n_ok >= need.n:
        return drops
    if drops.n_dropped:
        head = f"{drops.headline()}: {drops.reasons_text()}"
        top = drops.reasons[0].status if drops.reasons else ""
        if top in DROP_HINTS:
            head += " — " + DROP_HINTS[top].format(category=category or "<category>", asset=asset or "<asset>",
                                                    catalog=f" --catalog {catalog}" if catalog else "")
    else:
        head = f"{drops.label}: {drops.n_ok} {drops.noun}, none dropped"
    msg = f"{head}; {need.consumer} needs at least {need.n} ({need.why}), {drops.n_ok} left"
    example = drops.example()
    if example:
        msg += f" ({example})"
    lost = [u for u in upstream if u.n_dropped]
    if lost:
        msg += ". Dropped before: " + "; ".join(u.describe() for u in lost)
    raise TooFewSamples(msg, drops, need)


def _percent(v: float | None) -> str:
    return "n/a" if v is None else f"{100 * v:.0f} %"


def pseudo_label_filter_notes(filter_record: Mapping[str, Any], check_record: Mapping[str, Any] | None = None
                              ) -> list[str]:
    """The iteration summary's lines on the pseudo-label filter: the kept fraction and the drop reasons of its
    record (``tasks.filter.filter_pseudo_labels``) and, with ground truth, its precision and recall against it
    (``tasks.filter.filter_precision_check``)."""
    drops = ", ".join(f"{s} ×{n}" for s, n in (filter_record.get("status_counts") or {}).items()) or "none"
    lines = [f"Pseudo-label filter: {filter_record['n_ok']} of {filter_record['n_rows']} ok fits kept "
             f"({_percent(filter_record.get('kept_fraction'))}; {filter_record.get('n_rescued', 0)} kept back by "
             f"min_kept); dropped: {drops}."]
    if check_record is not None:
        c = check_record
        lines.append(f"Pseudo-label filter against the hidden truth: precision {_percent(c['precision'])} "
                     f"({c['n_kept_good']} of {c['n_kept']} kept fits beat the rest pose), recall "
                     f"{_percent(c['recall'])} (of {c['n_good']} that do); keeping every fit: "
                     f"{_percent(c['base_rate'])}.")
    return lines
