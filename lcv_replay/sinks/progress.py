"""The progress sink: a progress bar on a terminal, periodic progress lines elsewhere.

On a terminal the bar fits 80 columns: ``ilv+ ━━━━ 2314/4541 636 fr/s 63.6× 337 cand. top 120
0:00:05`` (method, frames, frames per second, × real time, constraints so far, rank-1 score,
elapsed); log lines are printed above it, never through it. When the console is not a terminal (a CI
log, a file), one plain line is printed every :data:`LINE_EVERY_S` seconds of wall clock instead.
"""

from __future__ import annotations

import logging
import sys
from typing import Any

from lcv_replay.sinks.base import BaseSink, FrameUpdate, RunStart, RunSummary, StepUpdate

REFRESH_PER_SECOND = 4
LINE_EVERY_S = 5.0  # wall-clock seconds between progress lines when not on a terminal
BAR_WIDTH = 16


class ProgressSink(BaseSink):
    """Draws one progress bar on ``console`` (a ``rich.console.Console``, stderr by default).

    The figures come from the replay's records (its injectable clock), not from a clock of its own.
    """

    def __init__(self, console: Any | None = None, *, line_every_s: float = LINE_EVERY_S):
        from rich.console import Console

        self.console = console if console is not None else Console(stderr=True)
        self.line_every_s = line_every_s
        self._progress = None
        self._task = None
        self._swapped: list[tuple[logging.StreamHandler, Any]] = []
        self._lines = False  # plain progress lines instead of a bar (not a terminal)
        self._total: int | None = None
        self._next_line_s = 0.0
        self._top: Any = "—"
        self._last: FrameUpdate | None = None

    def on_start(self, start: RunStart) -> None:
        self._total = start.frames or None
        if not self.console.is_terminal:
            self._lines = True
            self._next_line_s = self.line_every_s
            return
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        self._progress = Progress(
            TextColumn("[bold]{task.description}"),
            BarColumn(bar_width=BAR_WIDTH),
            MofNCompleteColumn(),
            TextColumn("{task.fields[fps]} fr/s"),
            TextColumn("{task.fields[realtime]}×"),
            TextColumn("{task.fields[constraints]} cand."),
            TextColumn("top {task.fields[top]}"),
            TimeElapsedColumn(),
            console=self.console,
            refresh_per_second=REFRESH_PER_SECOND,
            transient=False,
            redirect_stderr=False,
            redirect_stdout=False,
            expand=False,
        )
        self._task = self._progress.add_task(
            start.method, total=self._total, fps="—", realtime="—", constraints=0, top="—",
        )
        self._progress.start()
        self._route_logging_above_the_bar()

    def _route_logging_above_the_bar(self) -> None:
        """Log lines on stderr are printed above the bar instead of through it (restored on close)."""
        self._swapped.extend(route_logging_to(self.console))

    def on_frame(self, update: FrameUpdate) -> None:
        if update.top_score is not None:
            self._top = update.top_score
        if self._lines:
            self._last = update
            if update.wall_elapsed_s >= self._next_line_s:
                self._print_line(update)
                self._next_line_s = update.wall_elapsed_s + self.line_every_s
                self._last = None  # printed
            return
        if self._progress is None:
            return
        wall = update.wall_elapsed_s
        frames_done = update.frame.index + 1
        self._progress.update(
            self._task,
            completed=frames_done,
            fps=f"{frames_done / wall:.0f}" if wall > 0 else "—",
            realtime=f"{update.log_elapsed_s / wall:.1f}" if wall > 0 else "—",
            constraints=update.constraints_total,
            top="—" if update.top_score is None else update.top_score,
        )

    def on_step(self, update: StepUpdate) -> None:
        if update.step.ranking:
            self._top = update.step.ranking[0].score
            if self._progress is not None:
                self._progress.update(self._task, top=self._top)

    def _print_line(self, update: FrameUpdate) -> None:
        """One plain progress line (no terminal): frames, rate, constraints, rank-1 score, time."""
        done = update.frame.index + 1
        wall = update.wall_elapsed_s
        of = f"/{self._total} ({100.0 * done / self._total:.0f} %)" if self._total else ""
        rate = f", {done / wall:.0f} fr/s, {update.log_elapsed_s / wall:.1f}× real time" if wall > 0 else ""
        self.console.print(
            f"progress: frame {done}{of}{rate}, {update.constraints_total} constraints, top score {self._top}, "
            f"{wall:.0f} s elapsed", markup=False, highlight=False, soft_wrap=True,
        )

    def on_finish(self, summary: RunSummary) -> None:
        if self._lines and self._last is not None:
            self._print_line(self._last)  # where the run ended
            self._last = None
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
