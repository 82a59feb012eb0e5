"""`lcv-replay` commands: record_synthetic."""

from __future__ import annotations

from lcv_replay.cli.app import app, bench_app, record_app  # noqa: F401
