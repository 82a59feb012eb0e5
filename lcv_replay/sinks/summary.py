"""The summary sink: prints the run summary and writes ``--summary-json`` (atomically).

The JSON keys are documented in ``docs/summary-json.md``; the stable ones are
:data:`lcv_replay.sinks.base.SUMMARY_KEYS`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, TextIO

from lcv_replay.fileio import check_output_path, write_text_atomic
from lcv_replay.sinks.base import BaseSink, RunSummary


def format_summary(summary: RunSummary) -> str:
    """The human-readable summary (plain text, one figure per line)."""

    def num(value: float | None, fmt: str) -> str:
        return "n/a" if value is None else format(value, fmt)

    rt = summary.realtime_factor
    lines = [
        f"lcv-replay summary: {summary.log}" + ("  (INTERRUPTED: figures as of the last completed window)" if summary.interrupted else ""),
        f"  frames            {summary.frames} ({summary.log_duration_s:.1f} s of log)",
        f"  wall time         {summary.wall_time_s:.1f} s ({num(rt, '.2f')} × real time"
        + ("" if summary.rate_requested is None else f", requested {summary.rate_requested:g} ×")
        + f"; set-up {summary.setup_time_s:.1f} s)",
        f"  method            {summary.method}",
        f"  constraints       {summary.constraints} (from {summary.constraint_source})",
        f"  accepted loops    {summary.accepted}",
    ]
    if summary.true_positives is not None:
        lines.append(
            f"  precision         {num(summary.precision, '.3f')} "
            f"({summary.true_positives} true / {summary.false_positives} false accepted; truth from {summary.truth_source})"
        )
        lines.append(f"  recall            {num(summary.recall, '.3f')} ({summary.false_negatives} true loops missed)")
        if summary.revisits is not None:
            lines.append(
                f"  revisit recall    {num(summary.revisit_recall, '.3f')} (closed {summary.revisits_closed} of the "
                f"{summary.revisits} revisits in the ground truth; {summary.revisits_proposed} were proposed)"
            )
    else:
        lines.append("  precision/recall  n/a (the log has neither loop labels nor ground truth)")
    lines.append(
        f"  ATE RMSE          {num(summary.ate_rmse_m, '.2f')} m"
        + (" (SE(2)-aligned to the ground truth)" if summary.ate_rmse_m is not None else " (no ground truth)")
    )
    lines.append(f"  hypotheses        {'n/a' if summary.hypotheses is None else summary.hypotheses}")
    if summary.rrd:
        lines.append(f"  recording         {summary.rrd}   (open it with: rerun {summary.rrd})")
    return "\n".join(lines)


def summary_json(summary: RunSummary) -> str:
    """The ``--summary-json`` document (sorted as :meth:`RunSummary.to_json_dict`)."""
    return json.dumps(summary.to_json_dict(), indent=2, allow_nan=False) + "\n"


class SummarySink(BaseSink):
    """Prints the summary to ``stream`` (if given) and writes it as JSON to ``json_path`` (if given).

    The JSON path is checked when the sink is built, before any work starts.
    """

    def __init__(self, *, stream: TextIO | None = None, json_path: str | Path | None = None):
        self.stream = stream
        self.json_path = None if json_path is None else check_output_path(json_path, force=True)
        self.summary: RunSummary | None = None

    def on_finish(self, summary: RunSummary) -> None:
        self.summary = summary
        if self.json_path is not None:
            write_text_atomic(self.json_path, summary_json(summary))
        if self.stream is not None:
            print(format_summary(summary), file=self.stream, flush=True)


def read_summary_json(path: str | Path) -> dict[str, Any]:
    """Read a ``--summary-json`` file back (tests, scripts)."""
    return json.loads(Path(path).read_text(encoding="utf-8"))
