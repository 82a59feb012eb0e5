"""``--report FILE.html``: the report written when the replay ends (Ctrl-C included)."""

from __future__ import annotations

from pathlib import Path
from typing import TextIO

from lcv_replay.fileio import check_output_path, write_text_atomic
from lcv_replay.sinks.base import BaseSink, RunSummary
from lcv_replay.sinks.run_record import RunRecord, RunRecorder


def write_report(path: str | Path, record: RunRecord) -> Path:
    """Render the report of ``record`` into ``path`` atomically (overwriting it)."""
    from lcv_replay.report.html import render

    return write_text_atomic(path, render(record))


class ReportSink(BaseSink):
    """Writes the HTML report of ``recorder``'s record at ``on_finish``; ``recorder`` must come
    before it in the sink list. The path is checked when the sink is built."""

    def __init__(self, recorder: RunRecorder, path: str | Path, *, stream: TextIO | None = None):
        self.recorder = recorder
        self.path = check_output_path(path, force=True)
        self.stream = stream

    def on_finish(self, summary: RunSummary) -> None:
        if self.recorder.record is None:
            raise RuntimeError("ReportSink: the RunRecorder must come before it in the sink list")
        write_report(self.path, self.recorder.record)
        if self.stream is not None:
            print(f"  report            {self.path}", file=self.stream, flush=True)
