"""The terminal: a progress bar that fits 80 columns, progress lines when not on a terminal, and a
summary whose every figure says what it counts."""

from __future__ import annotations

import io
import re

from rich.console import Console

from lcv_replay.sinks.progress import ProgressSink
from lcv_replay.sinks.run_record import RunRecorder
from lcv_replay.sinks.summary import format_summary
from tests.sinks.scripted import N, script

ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


def test_the_bar_fits_80_columns(tmp_path):
    out = io.StringIO()
    console = Console(file=out, force_terminal=True, width=80, color_system=None)
    script(ProgressSink(console), tmp_path)
    lines = [ANSI.sub("", line).rstrip() for line in out.getvalue().replace("\r", "\n").splitlines()]
    bars = [line for line in lines if f"/{N}" in line]
    assert bars, lines
    assert max(len(line) for line in bars) <= 80, bars
    assert f"{N}/{N}" in bars[-1] and "ilv" in bars[-1] and "fake.mcap" not in bars[-1]  # no path in the bar


def test_without_a_terminal_progress_lines_are_printed_every_few_seconds(tmp_path):
    out = io.StringIO()
    console = Console(file=out, force_terminal=False, width=200)
    script(ProgressSink(console, line_every_s=0.1), tmp_path)  # the scripted frames are 0.01 s apart
    lines = [line for line in out.getvalue().splitlines() if line]
    assert all(line.startswith("progress: frame ") for line in lines), lines
    assert 3 <= len(lines) <= 5  # at 0.1, 0.2 s ... of wall clock, plus the last frame once
    assert lines[-1].startswith(f"progress: frame {N}/{N} (100 %)")
    assert "\x1b" not in out.getvalue()  # no control codes in a log file


def test_every_summary_figure_is_explained(tmp_path):
    recorder = RunRecorder()
    script(recorder, tmp_path)
    summary = recorder.record
    from lcv_replay.sinks.base import RunSummary

    s = RunSummary(frames=30, wall_time_s=0.3, log_duration_s=2.9, method="ilv", constraints=3, accepted=2,
                   true_positives=2, false_positives=0, false_negatives=0, precision=1.0, recall=1.0, ate_rmse_m=0.5,
                   hypotheses=3, constraint_source="images", truth_source="ground_truth", rrd="run.rrd",
                   config={"retrieval": {"top_k": 10}, "verification": {"consistency_radius_m": 10.0, "max_hypotheses": 200}})
    text = format_summary(s, summary)
    lines = text.splitlines()
    assert "constraints       3: our retrieval: 1 query frames × up to N_r = 10 matches" in text
    assert "true when the two frames lie within T_p = 10 m in the ground truth" in text
    assert "hypotheses        3 kept at the end (at most 200)" in text
    assert ("first wrong loop  frame 19: constraint 1 (15↔8) accepted although false (refused from frame 29); "
            "open there: lcv-replay open run.rrd --frame 19") in text  # and what became of it
    assert all(len(line) > 20 for line in lines[1:])  # each figure comes with its meaning
    assert text.count("rerun run.rrd") == 1
