"""Shared fixtures: one Prefect test server per test process, with a private PREFECT_HOME."""

from __future__ import annotations

import os
import tempfile

import pytest

os.environ.setdefault("PREFECT_HOME", tempfile.mkdtemp(prefix="mobileocc-test-prefect-"))
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
# commands run in subprocesses start their own temporary server: 20 s is not enough on a loaded
# machine (the harness below waits 120 s for its own)
os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "120")


@pytest.fixture(scope="session")
def prefect_harness():
    from prefect.testing.utilities import prefect_test_harness

    with prefect_test_harness(server_startup_timeout=120):
        yield


@pytest.fixture(scope="session")
def synthetic_root(tmp_path_factory):
    """Two tiny synthetic sequences (4 raw frames = 2 frames at 5 Hz each), made once per session.

    Tests that edit files copy it first (``copy_dataset``)."""
    from flows.commands.simulate import simulate

    root = tmp_path_factory.mktemp("synthetic")
    simulate(root, sequences=2, frames=4, seed=7, pedestrians=3, crowd="uncrowded", progress=False)
    return root


@pytest.fixture()
def copy_dataset(synthetic_root, tmp_path):
    import shutil

    def copy(name: str = "data"):
        dst = tmp_path / name
        shutil.copytree(synthetic_root, dst)
        return dst

    return copy
