"""The null sink: receives everything and does nothing (``--no-rerun --quiet``, benchmarks)."""

from __future__ import annotations

from lcv_replay.sinks.base import BaseSink


class NullSink(BaseSink):
    """A sink that ignores every call, so the replay loop never branches on what is enabled."""
