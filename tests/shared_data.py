"""The real data in ../shared/data, used by path and never copied (the fixture is in conftest.py)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

SHARED_DATA = Path(os.environ.get("LCV_SHARED_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))


def shared_path(*parts: str) -> Path:
    """Path to ``../shared/data/<parts>``; skips the calling test with a reason if it is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"shared data not found: {path} (set LCV_SHARED_DATA or check out shared/ beside the repo)")
    return path
