"""``lcv-replay bench scale``: how a verifier's cost grows with the history (issue 16).

Generated worlds (:mod:`lcv_replay.bench.worlds`) of increasing length are built into logs the way
the suite builds them (cached in its work folder), every method runs on each, and the report gives

* per world: the total verification time of each method side by side, its ratio to each
  reference (GNC-TLS, DCS), and precision/recall;
* per window of the incremental method: the time of that window against the number of
  constraints verified before it (the history), so a curve that stays flat after warm-up shows a
  cost per window that does not grow with the history;
* per window, side by side, the cost of the back end alone (:func:`backend_window_times`): iSAM2
  absorbing that window's frames and the loops the method accepted in it, once, to convergence.
  Its time grows with the graph (a loop into old frames re-eliminates the Bayes tree between
  them); the ratio of the two is what the verification costs on top of the smoother the robot
  runs anyway.

With ``repeat`` (``--repeat N``), each log is verified in ``N`` rounds, every method once a round,
the order reversed every other round so that a machine that slows down or speeds up during a run
weighs on both sides alike. A round's ratio is taken between runs that ran one after the other;
the report gives the median over the rounds and their range, which is what a shared, noisy
machine can honestly claim. Logs built elsewhere (``logs``, ``--log``: a Vertigo case that
``bench suite`` built, any log ``record g2o`` wrote) are timed the same way.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np

from lcv_replay.bench.suites import SuiteCase, world_cases
from lcv_replay.verification.config import VerificationConfig

if TYPE_CHECKING:
    from lcv_replay.verification.base import Constraint, VerifierStep


@dataclass(frozen=True)
class WindowTime:
    """One window of an incremental run: constraints admitted before it, its wall time, and the
    wall time of the back end alone on the same window (:func:`backend_window_times`)."""

    window: int
    history_constraints: int
    new_constraints: int
    time_s: float
    backend_time_s: float | None = None


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
    round_times_s: tuple[float, ...] = ()
    """The wall time of each round (``wall_time_s`` is their median); the windows are the first
    round's."""


@dataclass(frozen=True)
class ScaleReport:
    """Everything ``bench scale`` measured (``as_dict`` is the JSON)."""

    method: str
    references: tuple[str, ...]
    runs: tuple[ScaleRun, ...]
    config: dict[str, Any] = field(default_factory=dict)
    load_average: tuple[float, float, float] | None = None
    repeat: int = 1

    def ratios(self, case: str, reference: str) -> tuple[float, ...]:
        """The method's time over ``reference``'s on ``case``, round by round (empty if either
        is missing or a reference time is zero)."""
        runs = {r.method: r for r in self.runs if r.case == case}
        mine, other = runs.get(self.method), runs.get(reference)
        if mine is None or other is None or not other.round_times_s or min(other.round_times_s) <= 0:
            return ()
        return tuple(a / b for a, b in zip(mine.round_times_s, other.round_times_s))

    def as_dict(self) -> dict[str, Any]:
        return {
            "method": self.method,
            "references": list(self.references),
            "repeat": self.repeat,
            "ratios": {
                case: {ref: list(self.ratios(case, ref)) for ref in self.references}
                for case in dict.fromkeys(r.case for r in self.runs)
            },
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


def window_times(steps, window_times_s: Sequence[float], backend_times_s: Sequence[float] | None = None) -> tuple[WindowTime, ...]:
    """Pair each step's wall time (from :func:`~lcv_replay.bench.verify.feed`) with the history it
    started from (constraints admitted before its window) and, if given, the back end's time on
    the same window."""
    out = []
    history = 0
    for k, (step, seconds) in enumerate(zip(steps, window_times_s)):
        new = len(step.new_constraint_ids)
        backend = None if backend_times_s is None else float(backend_times_s[k])
        out.append(WindowTime(k, history, new, float(seconds), backend))
        history += new
    return tuple(out)


def backend_window_times(
    odometry: np.ndarray,
    odometry_information: np.ndarray,
    loop_default_information: np.ndarray,
    constraints: Sequence[Constraint],
    steps: Sequence[VerifierStep],
) -> tuple[float, ...]:
    """The reference for the cost of each window: the back end alone. An iSAM2 graph
    (:class:`~lcv_replay.verification.pose_graph.IncrementalGraph`, the one ``ilv+`` keeps its
    working hypothesis in) absorbs, step by step, the frames up to the step's last one and the
    change of the accepted loops since the previous step (added and removed), in one update
    relinearised to convergence, then computes the estimate. That is what a smoother fed only the
    verified loops pays per window; it does no verification.

    Args:
        odometry: ``(N, 3)`` cumulative odometry of the log.
        odometry_information: ``(3, 3)`` information of one odometry step.
        loop_default_information: ``(3, 3)`` information of a loop that carries none.
        constraints: the run's constraints (``VerificationResult.constraints``), by id.
        steps: the run's steps, the last one included.

    Returns:
        The wall time of each step's update, in seconds.
    """
    from lcv_replay.verification.pose_graph import IncrementalGraph, loop_factor

    by_id = {c.id: c for c in constraints}
    graph = IncrementalGraph(odometry_information)
    held: set[int] = set()
    times = []
    for step in steps:
        start = time.perf_counter()
        graph.extend(odometry[: step.frame_index + 1])
        now = set(step.accepted_constraint_ids)
        add = [(c, loop_factor(by_id[c], loop_default_information)) for c in sorted(now - held)]
        graph.update(add=add, remove=sorted(held - now), relinearize=True)
        graph.estimate()
        times.append(time.perf_counter() - start)
        held = now
    return tuple(times)


def run_scale(
    cases: Sequence[SuiteCase],
    *,
    method: str,
    references: Sequence[str],
    data_dir: Path,
    workdir: Path,
    config: VerificationConfig | None = None,
    on_run: Callable[[ScaleRun], None] | None = None,
    logs: Sequence[Path] = (),
    repeat: int = 1,
) -> ScaleReport:
    """Build each case's log (cached), then run ``method`` and the ``references`` on those and
    on each of ``logs``, in ``repeat`` rounds (the order reversed every other round); ``on_run`` is
    called after each method's last round."""
    import os

    from lcv_replay.bench.suite import build_case_log
    from lcv_replay.bench.verify import load_inputs
    from lcv_replay.config import to_dict

    if repeat < 1:
        raise ValueError(f"repeat must be >= 1, got {repeat}")
    config = config or VerificationConfig()
    runs: list[ScaleRun] = []
    sources = [(c.name, build_case_log(c, data_dir, workdir).path) for c in cases] + [(Path(p).stem, Path(p)) for p in logs]
    for name, path in sources:
        inputs = load_inputs(path, require_candidates=False)
        runs.extend(_time_rounds(name, inputs, (method, *references), method, config, repeat, on_run))
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    return ScaleReport(method, tuple(references), tuple(runs), to_dict(config), load, repeat)


def _time_rounds(case: str, inputs, methods: Sequence[str], measured: str, config: VerificationConfig, repeat: int, on_run) -> list[ScaleRun]:
    """``methods`` on one log, ``repeat`` rounds (every other one in reverse order); one
    :class:`ScaleRun` per method, with the first round's verdict and windows, and the back end
    timed on ``measured``'s windows."""
    from lcv_replay.bench.verify import verify_inputs
    from lcv_replay.verification.base import default_informations

    first: dict[str, Any] = {}
    times: dict[str, list[float]] = {name: [] for name in methods}
    for k in range(repeat):
        for name in (methods if k % 2 == 0 else tuple(reversed(methods))):
            verified = verify_inputs(inputs, name, config, case=case)
            times[name].append(float(verified.row.wall_time_s))
            first.setdefault(name, verified)
    runs = []
    for name in methods:
        verified = first[name]
        row = verified.row
        steps = list(verified.steps)
        last = verified.result.last_step
        if last is not None and (not steps or steps[-1] is not last):
            steps.append(last)
        windows: tuple[WindowTime, ...] = ()
        if name == measured:
            odometry_information, loop_information = default_informations(config, inputs.odometry_information)
            backend = backend_window_times(inputs.odometry, odometry_information, loop_information, verified.result.constraints, steps)
            windows = window_times(steps, verified.window_times_s, backend)
        run = ScaleRun(
            case=case,
            poses=inputs.frames,
            method=name,
            constraints=row.constraints,
            wall_time_s=float(np.median(times[name])),
            precision=row.precision,
            recall=row.recall,
            false_positives=row.false_positives,
            windows=windows,
            round_times_s=tuple(times[name]),
        )
        runs.append(run)
        if on_run is not None:
            on_run(run)
    return runs


def _fmt(value: float | None, digits: int = 2) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def _spread(values: Sequence[float], digits: int = 2) -> str:
    """The median of ``values``, with their range where there are several."""
    if not values:
        return "–"
    median = _fmt(float(np.median(values)), digits)
    return median if len(values) == 1 else f"{median} ({_fmt(min(values), digits)}–{_fmt(max(values), digits)})"


def markdown_totals(report: ScaleReport) -> str:
    """One line per world: the method's total time, each reference's, the ratios, P/R; over
    several rounds, the medians with their ranges (a ratio's range is over the rounds' ratios,
    each between two runs one after the other)."""
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
            cells.append(f"{_spread(other.round_times_s, 1) if other else '–'} | {_spread(report.ratios(case, r))}")
        lines.append(
            f"| {case} | {mine.poses} | {mine.constraints} | {_spread(mine.round_times_s, 1)} | " + " | ".join(cells)
            + f" | {_fmt(mine.precision, 3)} / {_fmt(mine.recall, 3)} / {mine.false_positives} |"
        )
    return "\n".join(lines)


def markdown_windows(report: ScaleReport, *, bins: int = 10) -> str:
    """Time per window against the history, per world: the windows grouped into ``bins`` by
    history size, with the mean and maximum window time of each group, the back end's mean time
    on the same windows and the ratio of the two (of their sums over the group). The last window,
    the end of the log (where the method's second opinions run, which the back end has no part
    of), gets a row of its own."""
    lines = [
        f"| world | history (constraints) | windows | time per window, mean s | max s | back end alone, mean s | {report.method} / back end |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]

    def row(case: str, label: str, part: list[WindowTime]) -> str:
        times = [w.time_s for w in part]
        backend = [w.backend_time_s for w in part if w.backend_time_s is not None]
        mean_backend = float(np.mean(backend)) if backend and len(backend) == len(part) else None
        ratio = sum(times) / sum(backend) if mean_backend else None
        return f"| {case} | {label} | {len(part)} | {np.mean(times):.2f} | {np.max(times):.2f} | {_fmt(mean_backend, 3)} | {_fmt(ratio, 1)} |"

    for run in report.runs:
        if run.method != report.method or not run.windows:
            continue
        windows, last = list(run.windows[:-1]), run.windows[-1]
        for group in np.array_split(np.arange(len(windows)), min(bins, len(windows))) if windows else ():
            if len(group):
                part = [windows[i] for i in group]
                first, latest = part[0].history_constraints, part[-1].history_constraints
                lines.append(row(run.case, f"{first}" if first == latest else f"{first}-{latest}", part))
        lines.append(row(run.case, f"end of the log ({last.history_constraints + last.new_constraints})", [last]))
    return "\n".join(lines)
