"""The progress sink: a rich progress bar with frames/s, × real time, constraints and top score."""

from __future__ import annotations

import logging
import sys
from typing import Any

from lcv_replay.sinks.base import BaseSink, FrameUpdate, RunStart, RunSummary, StepUpdate

REFRESH_PER_SECOND = 4


class ProgressSink(BaseSink):
    """Draws one progress bar on ``console`` (a ``rich.console.Console``, stderr by default).

    The figures come from the replay's records (its injectable clock), not from a clock of its own.
    """

    def __init__(self, console: Any | None = None):
        from rich.console import Console

        self.console = console if console is not None else Console(stderr=True)
        self._progress = None
        self._task = None
        self._swapped: list[tuple[logging.StreamHandler, Any]] = []

    def on_start(self, start: RunStart) -> None:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        self._progress = Progress(
            TextColumn("[bold]{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("{task.fields[fps]} fr/s"),
            TextColumn("{task.fields[realtime]}× real time"),
            TextColumn("{task.fields[constraints]} constraints"),
            TextColumn("top score {task.fields[top]}"),
            TimeElapsedColumn(),
            console=self.console,
            refresh_per_second=REFRESH_PER_SECOND,
            transient=False,
            redirect_stderr=False,
            redirect_stdout=False,
        )
        self._task = self._progress.add_task(
            f"{start.log_path.name} · {start.method}", total=start.frames or None,
            fps="—", realtime="—", constraints=0, top="—",
        )
        self._progress.start()
        self._route_logging_above_the_bar()

    def _route_logging_above_the_bar(self) -> None:
        """Log lines on stderr are printed above the bar instead of through it (restored on close)."""
        self._swapped.extend(route_logging_to(self.console))

    def on_frame(self, update: FrameUpdate) -> None:
        if self._progress is None:
            return
        wall = update.wall_elapsed_s
        frames_done = update.frame.index + 1
        self._progress.update(
            self._task,
            completed=frames_done,
            fps=f"{frames_done / wall:.1f}" if wall > 0 else "—",
            realtime=f"{update.log_elapsed_s / wall:.2f}" if wall > 0 else "—",
            constraints=update.constraints_total,
            top="—" if update.top_score is None else update.top_score,
        )

    def on_step(self, update: StepUpdate) -> None:
        if self._progress is not None and update.step.ranking:
            self._progress.update(self._task, top=update.step.ranking[0].score)

    def on_finish(self, summary: RunSummary) -> None:
        self.close()

    def close(self) -> None:
        for handler, stream in self._swapped:
            handler.setStream(stream)
        self._swapped.clear()
        if self._progress is not None:
            self._progress.stop()
            self._progress = None


def route_logging_to(console: Any) -> list[tuple[logging.StreamHandler, Any]]:
    """Point the root logger's stderr handlers at ``console`` (so log lines print above a live
    progress bar); returns ``(handler, previous stream)`` pairs to restore with ``setStream``."""
    swapped = []
    for handler in logging.getLogger().handlers:
        if isinstance(handler, logging.StreamHandler) and handler.stream in (sys.stderr, sys.__stderr__):
            swapped.append((handler, handler.setStream(_ConsoleStream(console))))
    return swapped


class _ConsoleStream:
    """A text stream that prints through a rich console (above a live progress bar)."""

    def __init__(self, console: Any):
        self.console = console

    def write(self, text: str) -> int:
        if text.strip():
            self.console.print(text.rstrip("\n"), markup=False, highlight=False, soft_wrap=True)
        return len(text)

    def flush(self) -> None:
        pass
