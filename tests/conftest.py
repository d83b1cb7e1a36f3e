"""Shared fixtures: the toy rig is built once per session (deterministic, ~1 s); a Prefect test harness (temporary
server and database, PREFECT_HOME in a tmp dir) for the flow and task tests; a per-module copy of the data catalog."""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

_HOME = tempfile.mkdtemp(prefix="bat3r-prefect-home-")
os.environ["PREFECT_HOME"] = _HOME
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")


@pytest.fixture(scope="session")
def prefect_harness():
    from prefect.settings import PREFECT_HOME, temporary_settings
    from prefect.testing.utilities import prefect_test_harness

    with temporary_settings(updates={PREFECT_HOME: _HOME}):
        with prefect_test_harness(server_startup_timeout=60):
            yield _HOME


@pytest.fixture(scope="module")
def catalog(tmp_path_factory):
    """A copy of the data catalog in a tmp folder, per test module: runs, collections and the toy asset all land
    there (``$BAT3R_CATALOG`` points at it for the module; ``$BAT3R_STORAGE_ROOT`` is unset)."""
    folder = tmp_path_factory.mktemp("catalog")
    shutil.copy(ROOT / "data_catalog.yaml", folder / "data_catalog.yaml")
    old = {k: os.environ.get(k) for k in ("BAT3R_CATALOG", "BAT3R_STORAGE_ROOT")}
    os.environ["BAT3R_CATALOG"] = str(folder / "data_catalog.yaml")
    os.environ.pop("BAT3R_STORAGE_ROOT", None)
    yield folder
    for k, v in old.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


@pytest.fixture(scope="session")
def toy_rig():
    from bat3r_core.toy import build_toy_rig

    return build_toy_rig()


@pytest.fixture()
def torch_single_thread():
    """One torch thread for the test, restored afterwards (faster and steadier on 2 shared cores)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
