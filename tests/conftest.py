"""Shared fixtures: the toy rig is built once per session (deterministic, ~1 s)."""
from __future__ import annotations

import os

import pytest

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")


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
