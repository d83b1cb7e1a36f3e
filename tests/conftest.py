"""Shared fixtures: the toy rig is built once per session (deterministic, ~1 s)."""
from __future__ import annotations

import os

import pytest

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")


@pytest.fixture(scope="session")
def toy_rig():
    from bat3r_core.toy import build_toy_rig

    return build_toy_rig()
