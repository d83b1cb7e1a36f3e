"""A stopped flow run ends in seconds, not when its longest task would have, and takes its temporary Prefect server
with it: SIGTERM (what a batch scheduler and a Prefect worker's cancellation send) to a real local flow run whose
task is training on the local task runner (``flows._runners.StoppableThreadPoolTaskRunner``,
``bat3r_core.stopping``, ``bat3r_core.cli.exit_on_sigterm``)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]

SCRIPT = textwrap.dedent("""
    import sys
    sys.path.insert(0, {root!r})
    from bat3r_core.cli import local_server_environment

    local_server_environment()
    from prefect import flow, task

    from bat3r_core.predictor.config import ModelConfig, TrainConfig
    from bat3r_core.predictor.data import ShardDataset
    from bat3r_core.predictor.synthetic import write_synthetic_shards
    from bat3r_core.predictor.train import Trainer
    from flows._runners import make_task_runner

    @task
    def train(shards: str, out: str) -> str:
        model = ModelConfig(resolution=16, layers=4, in_channels=3, base_channels=8, depth=2)
        config = TrainConfig(steps=10_000_000, batch_size=2, checkpoint_every=1_000_000, log_every=1, seed=0)
        return str(Trainer(ShardDataset(shards), model, config, out).train())

    @flow
    def stage(shards: str, out: str) -> str:
        return train.submit(shards, out).result()

    @flow
    def run(shards: str, out: str) -> str:
        return stage.with_options(task_runner=make_task_runner("local"))(shards, out)

    if __name__ == "__main__":
        write_synthetic_shards({shards!r}, 8, 16, shard_size=4, seed=0)
        run({shards!r}, {out!r})
""")


def _log_lines(path: Path) -> int:
    return len(path.read_text().splitlines()) if path.is_file() else 0


def _children(pid: int) -> list[int]:
    """Processes whose parent is ``pid`` (from /proc)."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def test_sigterm_stops_a_training_task_within_seconds_and_keeps_its_step(tmp_path):
    out = tmp_path / "train"
    script = tmp_path / "run.py"
    script.write_text(SCRIPT.format(root=str(ROOT), shards=str(tmp_path / "shards"), out=str(out)))
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_API")}
    env.update(PREFECT_HOME=str(tmp_path / "prefect-home"), PREFECT_SERVER_ANALYTICS_ENABLED="false")
    with open(tmp_path / "run.log", "w") as log:
        proc = subprocess.Popen([sys.executable, str(script)], stdout=log, stderr=subprocess.STDOUT, env=env,
                                cwd=str(ROOT))
    try:
        deadline = time.monotonic() + 400  # the temporary server's first start migrates its database
        while _log_lines(out / "train_log.jsonl") < 20:
            assert proc.poll() is None, (tmp_path / "run.log").read_text()[-3000:]
            assert time.monotonic() < deadline, "training never started: " + (tmp_path / "run.log").read_text()[-3000:]
            time.sleep(0.5)
        server = [c for c in _children(proc.pid)
                  if "uvicorn" in Path(f"/proc/{c}/cmdline").read_bytes().decode(errors="replace")]
        assert server, "no temporary Prefect server among the run's child processes"
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=60)  # ten million steps would take days
        except subprocess.TimeoutExpired:
            pytest.fail("SIGTERM did not stop the flow run within 60 s: " + (tmp_path / "run.log").read_text()[-3000:])
        stopped_after = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    log = (tmp_path / "run.log").read_text()
    assert proc.returncode == 143 and stopped_after < 60  # SystemExit(128 + SIGTERM): atexit ran
    deadline = time.monotonic() + 20
    while any(_alive(c) for c in server) and time.monotonic() < deadline:
        time.sleep(0.2)
    orphans = [c for c in server if _alive(c)]
    for c in orphans:
        os.kill(c, signal.SIGKILL)
    assert not orphans, "the temporary Prefect server outlived the stopped run"
    assert "checkpoint.pt written" in log, log[-3000:]
    steps_logged = [json.loads(line)["step"] for line in (out / "train_log.jsonl").read_text().splitlines()]
    checkpoint = torch.load(out / "checkpoint.pt", map_location="cpu", weights_only=True)
    assert checkpoint["step"] >= 20 and checkpoint["step"] == steps_logged[-1]  # the step it reached
    assert not (out / "predictor.pt").exists()
