"""``lcv-replay bench scale``: how a verifier's cost grows with the history (issue 16).

Generated worlds (:mod:`lcv_replay.bench.worlds`) of increasing length are built into logs the way
the suite builds them (cached in its work folder), every method runs on each, and the report gives

* per world: the total verification time of each method side by side, its ratio to each
  reference (GNC-TLS, DCS), and precision/recall;
* per window of the incremental method: the time of that window against the number of
  constraints verified before it (the history), so a curve that stays flat after warm-up shows a
  cost per window that does not grow with the history.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from lcv_replay.bench.suites import SuiteCase, world_cases
from lcv_replay.verification.config import VerificationConfig


@dataclass(frozen=True)
class WindowTime:
    """One window of an incremental run: constraints admitted before it, its wall time."""

    window: int
    history_constraints: int
    new_constraints: int
    time_s: float


@dataclass(frozen=True)
class ScaleRun:
    """One method on one world."""

    case: str
    poses: int
    method: str
    constraints: int
    wall_time_s: float
    precision: float | None
    recall: float | None
    false_positives: int | None
    windows: tuple[WindowTime, ...] = ()


@dataclass(frozen=True)
class ScaleReport:
    """Everything ``bench scale`` measured (``as_dict`` is the JSON)."""

    method: str
    references: tuple[str, ...]
    runs: tuple[ScaleRun, ...]
    config: dict[str, Any] = field(default_factory=dict)
    load_average: tuple[float, float, float] | None = None

    def as_dict(self) -> dict[str, Any]:
        return {
            "method": self.method,
            "references": list(self.references),
            "load_average": list(self.load_average) if self.load_average else None,
            "config": self.config,
            "runs": [_json_ready(asdict(r)) for r in self.runs],
        }


def _json_ready(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_ready(v) for v in value]
    return value


def scale_cases(poses: Sequence[int], *, layout: str, noise: str, mode: str, outliers_per_1000: int, seed: int) -> tuple[SuiteCase, ...]:
    """One generated world per length, with ``outliers_per_1000`` outliers per 1,000 poses."""
    cases: list[SuiteCase] = []
    for n in poses:
        cases.extend(world_cases([layout], [int(n)], [noise], [mode], [max(1, int(n) * outliers_per_1000 // 1000)], [seed]))
    return tuple(cases)


def window_times(steps, window_times_s: Sequence[float]) -> tuple[WindowTime, ...]:
    """Pair each step's wall time (from :func:`~lcv_replay.bench.verify.feed`) with the history it
    started from (constraints admitted before its window)."""
    out = []
    history = 0
    for k, (step, seconds) in enumerate(zip(steps, window_times_s)):
        new = len(step.new_constraint_ids)
        out.append(WindowTime(k, history, new, float(seconds)))
        history += new
    return tuple(out)


def run_scale(
    cases: Sequence[SuiteCase],
    *,
    method: str,
    references: Sequence[str],
    data_dir: Path,
    workdir: Path,
    config: VerificationConfig | None = None,
    on_run: Callable[[ScaleRun], None] | None = None,
) -> ScaleReport:
    """Build each case's log (cached) and run ``method`` and the ``references`` on it."""
    import os

    from lcv_replay.bench.suite import build_case_log
    from lcv_replay.bench.verify import load_inputs, verify_inputs
    from lcv_replay.config import to_dict

    config = config or VerificationConfig()
    runs: list[ScaleRun] = []
    for case in cases:
        built = build_case_log(case, data_dir, workdir)
        inputs = load_inputs(built.path, require_candidates=False)
        for name in (method, *references):
            verified = verify_inputs(inputs, name, config, case=case.name)
            row = verified.row
            steps = list(verified.steps)
            last = verified.result.last_step
            if last is not None and (not steps or steps[-1] is not last):
                steps.append(last)
            run = ScaleRun(
                case=case.name,
                poses=inputs.frames,
                method=name,
                constraints=row.constraints,
                wall_time_s=row.wall_time_s,
                precision=row.precision,
                recall=row.recall,
                false_positives=row.false_positives,
                windows=window_times(steps, verified.window_times_s) if name == method else (),
            )
            runs.append(run)
            if on_run is not None:
                on_run(run)
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    return ScaleReport(method, tuple(references), tuple(runs), to_dict(config), load)


def _fmt(value: float | None, digits: int = 2) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def markdown_totals(report: ScaleReport) -> str:
    """One line per world: the method's total time, each reference's, the ratios, P/R."""
    refs = report.references
    head = f"| world | poses | constraints | {report.method} s | " + " | ".join(f"{r} s | {report.method}/{r}" for r in refs)
    head += f" | {report.method} P / R / FP |"
    lines = [head, "|---|---:|---:|---:|" + "---:|---:|" * len(refs) + "---|"]
    by_case: dict[str, dict[str, ScaleRun]] = {}
    for run in report.runs:
        by_case.setdefault(run.case, {})[run.method] = run
    for case, runs in by_case.items():
        mine = runs.get(report.method)
        if mine is None:
            continue
        cells = []
        for r in refs:
            other = runs.get(r)
            ratio = mine.wall_time_s / other.wall_time_s if other and other.wall_time_s > 0 else None
            cells.append(f"{_fmt(other.wall_time_s if other else None, 1)} | {_fmt(ratio)}")
        lines.append(
            f"| {case} | {mine.poses} | {mine.constraints} | {mine.wall_time_s:.1f} | " + " | ".join(cells)
            + f" | {_fmt(mine.precision, 3)} / {_fmt(mine.recall, 3)} / {mine.false_positives} |"
        )
    return "\n".join(lines)


def markdown_windows(report: ScaleReport, *, bins: int = 10) -> str:
    """Time per window against the history, per world: the windows grouped into ``bins`` by
    history size, with the mean and maximum window time of each group."""
    lines = ["| world | history (constraints) | windows | time per window, mean s | max s |", "|---|---|---:|---:|---:|"]
    for run in report.runs:
        if run.method != report.method or not run.windows:
            continue
        windows = list(run.windows)
        groups = np.array_split(np.arange(len(windows)), min(bins, len(windows)))
        for group in groups:
            if len(group) == 0:
                continue
            part = [windows[i] for i in group]
            times = [w.time_s for w in part]
            lines.append(
                f"| {run.case} | {part[0].history_constraints}-{part[-1].history_constraints} | {len(part)} | "
                f"{np.mean(times):.2f} | {np.max(times):.2f} |"
            )
    return "\n".join(lines)
