"""The summary sink: prints the run summary and writes ``--summary-json`` (atomically).

The JSON keys are documented in ``docs/summary-json.md``; the stable ones are
:data:`lcv_replay.sinks.base.SUMMARY_KEYS`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from lcv_replay.fileio import check_output_path, write_text_atomic
from lcv_replay.sinks.base import BaseSink, RunSummary

if TYPE_CHECKING:
    from lcv_replay.sinks.run_record import RunRecord


def _truth_words(summary: RunSummary) -> str:
    radius = dict(summary.config).get("verification", {}).get("consistency_radius_m", 10.0)
    return {
        "labels": "the log's loop labels",
        "ground_truth": f"true when the two frames lie within T_p = {radius:g} m in the ground truth",
    }.get(summary.truth_source, summary.truth_source)


def _constraint_words(summary: RunSummary, queries: int | None) -> str:
    top_k = dict(summary.config).get("retrieval", {}).get("top_k")
    retrieval = (f"our retrieval: {queries} query frames × up to N_r = {top_k} matches" if queries is not None
                 else f"our retrieval (up to N_r = {top_k} matches per query frame)")
    return {
        "log": "loop candidates recorded in the log (/loop_candidates)",
        "images": retrieval,
        "both": f"the log's /loop_candidates plus {retrieval}",
    }.get(summary.constraint_source, f"from {summary.constraint_source}")


def _hypotheses_bound(summary: RunSummary) -> int | None:
    verification = dict(summary.config).get("verification", {})
    if summary.method == "ilv+":
        return verification.get("ilv_plus", {}).get("max_hypotheses")
    return verification.get("max_hypotheses")


def format_summary(summary: RunSummary, record: "RunRecord | None" = None) -> str:
    """The human-readable summary: one figure per line, each with what it counts.

    With the run ``record`` it also names the first wrong acceptance and the command that opens
    the recording there.
    """

    def num(value: float | None, fmt: str) -> str:
        return "n/a" if value is None else format(value, fmt)

    rt = summary.realtime_factor
    queries = None if record is None else record.queries
    lines = [
        f"lcv-replay summary: {summary.log} · {summary.method}"
        + ("  (INTERRUPTED: figures as of the last completed window)" if summary.interrupted else ""),
        f"  frames            {summary.frames} replayed ({summary.log_duration_s:.1f} s of log)",
        f"  wall time         {summary.wall_time_s:.1f} s = {num(rt, '.2f')} × real time"
        + ("" if summary.rate_requested is None else f" (requested {summary.rate_requested:g} ×)")
        + f"; set-up before the first frame {summary.setup_time_s:.1f} s",
        f"  constraints       {summary.constraints}: {_constraint_words(summary, queries)}",
        f"  accepted loops    {summary.accepted}: the constraints the final rank-1 hypothesis holds",
    ]
    flagged = "" if record is None else record.flagged_words()
    if flagged:
        lines.append(f"  ambiguous         {record.counts()['ambiguous']} {flagged}")
    if summary.true_positives is not None:
        if summary.precision is None:
            lines.append(f"  precision         n/a: nothing accepted; truth: {_truth_words(summary)}")
        else:
            lines.append(
                f"  precision         {num(summary.precision, '.3f')} = {summary.true_positives} true of "
                f"{summary.true_positives + summary.false_positives} judged accepted ({summary.false_positives} false); "
                f"truth: {_truth_words(summary)}"
            )
        true_total = summary.true_positives + (summary.false_negatives or 0)
        if summary.recall is None:
            lines.append("  recall            n/a: no true loop among the constraints")
        else:
            lines.append(f"  recall            {num(summary.recall, '.3f')} = {summary.true_positives} of {true_total} true "
                         f"constraints accepted ({summary.false_negatives} missed)")
        if summary.revisits is not None:
            lines.append(
                f"  revisit recall    {num(summary.revisit_recall, '.3f')} = {summary.revisits_closed} of {summary.revisits} "
                f"revisits closed ({summary.revisits_proposed} proposed); a revisit: within T_p of a frame > Δt earlier"
            )
    else:
        lines.append("  precision/recall  n/a: the log has neither loop labels nor ground truth")
    lines.append(
        f"  ATE RMSE          {num(summary.ate_rmse_m, '.2f')} m"
        + (": final estimate vs ground truth after SE(2) alignment" if summary.ate_rmse_m is not None else " (no ground truth)")
    )
    bound = _hypotheses_bound(summary)
    if summary.hypotheses is None:
        lines.append(f"  hypotheses        n/a: {summary.method} keeps no hypotheses")
    else:
        lines.append(f"  hypotheses        {summary.hypotheses} kept at the end" + ("" if bound is None else f" (at most {bound})"))
    if summary.rrd:
        lines.append(f"  recording         {summary.rrd}   (open it with: rerun {summary.rrd})")
    if record is not None:
        first = record.first_wrong_acceptance()
        if first is not None:
            where = f"lcv-replay open {summary.rrd} --frame {first.first_accepted_frame}" if summary.rrd else "(no recording saved)"
            later = f" ({first.later})" if first.later else ""
            lines.append(f"  first wrong loop  frame {first.first_accepted_frame}: constraint {first.constraint_id} "
                         f"({first.query_frame}↔{first.match_frame}) accepted although false{later}; open there: {where}")
    return "\n".join(lines)


def summary_json(summary: RunSummary) -> str:
    """The ``--summary-json`` document (sorted as :meth:`RunSummary.to_json_dict`)."""
    return json.dumps(summary.to_json_dict(), indent=2, allow_nan=False) + "\n"


class SummarySink(BaseSink):
    """Prints the summary to ``stream`` (if given) and writes it as JSON to ``json_path`` (if given).

    The JSON path is checked when the sink is built, before any work starts.
    """

    def __init__(self, *, stream: TextIO | None = None, json_path: str | Path | None = None, recorder=None):
        self.stream = stream
        self.recorder = recorder  # a RunRecorder earlier in the sink list: names the first wrong loop
        self.json_path = None if json_path is None else check_output_path(json_path, force=True)
        self.summary: RunSummary | None = None

    def on_finish(self, summary: RunSummary) -> None:
        self.summary = summary
        if self.stream is not None:  # first: a JSON that cannot be written (a full disk) loses no figure
            record = None if self.recorder is None else self.recorder.record
            print(format_summary(summary, record), file=self.stream, flush=True)
        if self.json_path is not None:
            write_text_atomic(self.json_path, summary_json(summary))


def read_summary_json(path: str | Path) -> dict[str, Any]:
    """Read a ``--summary-json`` file back (tests, scripts)."""
    return json.loads(Path(path).read_text(encoding="utf-8"))
