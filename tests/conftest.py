"""Shared fixtures. Helpers live in helper modules (tests/shared_data.py, <folder>/helpers.py), never here."""

from __future__ import annotations

import os
from pathlib import Path

if "PYTEST_XDIST_WORKER_COUNT" in os.environ:  # a worker of `-n N`, before numpy loads its BLAS
    from lcv_replay.fleet.engine import thread_env

    # N workers share the cores, so each caps its native thread pools as a fleet task does: with
    # OpenBLAS's default of a thread per core, two workers on two cores took 703 s for the suite;
    # capped, 593 s (one run after the other; docs/verification-bench.md, thirty-fifth stop).
    os.environ.update(thread_env(max(1, (os.cpu_count() or 1) // int(os.environ["PYTEST_XDIST_WORKER_COUNT"]))))

import pytest

from tests.shared_data import shared_path


@pytest.fixture
def shared_data() -> Path:
    """The ``../shared/data`` folder; skips the test when it is absent."""
    return shared_path()
