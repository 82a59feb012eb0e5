"""Shared fixtures. Helpers live in helper modules (tests/shared_data.py, <folder>/helpers.py), never here."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.shared_data import shared_path


@pytest.fixture
def shared_data() -> Path:
    """The ``../shared/data`` folder; skips the test when it is absent."""
    return shared_path()
