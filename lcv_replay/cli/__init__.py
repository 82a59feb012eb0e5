"""Command-line entry point ``lcv-replay`` (see :mod:`lcv_replay.cli.app`)."""

from __future__ import annotations

from lcv_replay.cli.app import app

# Each module registers its commands on ``app``, ``record_app`` or ``bench_app``.
from lcv_replay.cli import (  # noqa: E402,F401
    bench_field,
    bench_hardening,
    bench_retrieval,
    bench_verify,
    bench_vo,
    demo,
    fleet,
    info,
    record,
    record_synthetic,
    replay,
    report,
    vo,
)


def main() -> None:
    app()
