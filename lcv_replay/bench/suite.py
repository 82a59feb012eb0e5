"""Run a benchmark suite: build its logs with the g2o recorder (cached), run every method on each,
and report rows, a per-method summary and markdown tables (``lcv-replay bench suite``).

Logs are built from the shared data folder (``--data``, else ``$LCV_SHARED_DATA``, else
``../shared/data`` from the current folder or from the repository) into a work folder, one file per
case named by a hash of everything that determines its content (source files' sizes and mtimes, the
recorder options, the format version), so a later run reuses them and a changed source rebuilds.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from lcv_replay.bench.suites import DEFAULT_METHODS, Suite, SuiteCase
from lcv_replay.bench.verify import LogInputs, VerifyRow, load_inputs, verify_inputs
from lcv_replay.errors import LcvError, RecorderError
from lcv_replay.fileio import make_folder
from lcv_replay.verification.config import VerificationConfig

log = logging.getLogger(__name__)

DATA_ENV = "LCV_SHARED_DATA"


# ---------------------------------------------------------------------------------------------
# Paths
# ---------------------------------------------------------------------------------------------


def resolve_data_dir(explicit: str | Path | None = None, *, cwd: Path | None = None) -> Path:
    """The shared data folder: ``explicit``, else ``$LCV_SHARED_DATA``, else ``../shared/data``
    relative to the current folder, else relative to the repository.

    Raises:
        RecorderError: the folder does not exist (naming every place looked at).
    """
    if explicit is not None:
        candidates = [Path(explicit)]
    elif os.environ.get(DATA_ENV):
        candidates = [Path(os.environ[DATA_ENV])]
    else:
        repo = Path(__file__).resolve().parents[2]
        candidates = [(cwd or Path.cwd()) / ".." / "shared" / "data", repo.parent / "shared" / "data"]
    for path in candidates:
        if path.is_dir():
            return path.resolve()
    raise RecorderError(
        f"shared data folder not found (looked in {', '.join(str(p) for p in candidates)})",
        fix=f"pass --data DIR or set {DATA_ENV} to the folder holding robustslam_kitti/ and vertigo/",
    )


def default_workdir() -> Path:
    """Where suite logs are cached: ``$XDG_CACHE_HOME/lcv-replay/suite`` (``~/.cache/...``)."""
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "lcv-replay" / "suite"


# ---------------------------------------------------------------------------------------------
# Building the logs
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BuiltLog:
    """A case's log: where it is, whether it was reused from the work folder, build seconds."""

    case: str
    path: Path
    reused: bool
    build_s: float


def _recorder_inputs(case: SuiteCase, data_dir: Path, workdir: Path | None = None):
    """``(graph path, G2oOptions)`` of a case; a generated world is written into
    ``workdir/worlds`` first (when ``workdir`` is given; else only its paths are named)."""
    from recorders.g2o import G2oOptions

    if case.world is not None:
        folder = (workdir or default_workdir()) / "worlds"
        if workdir is not None:
            from lcv_replay.bench.worlds import generate_world, write_world

            graph, ground_truth = write_world(generate_world(case.world), folder)
        else:
            graph, ground_truth = folder / f"{case.world.name}.g2o", folder / f"{case.world.name}_gt.g2o"
        true_loops = None
    else:
        graph = case.resolve(data_dir, case.graph)
        ground_truth = case.resolve(data_dir, case.ground_truth)
        true_loops = case.resolve(data_dir, case.true_loops)
    for what, path in (("graph", graph), ("ground truth", ground_truth), ("true-loop labels", true_loops)):
        if path is not None and not path.is_file() and case.world is None:
            raise RecorderError(
                f"suite case '{case.name}': {what} file not found",
                path=path,
                fix="check the data folder (--data) or the suite file",
            )
    options = G2oOptions(
        ground_truth=ground_truth,
        true_loops=true_loops,
        auto_siblings=False,
        outliers=case.outliers,
        outlier_mode=case.outlier_mode,  # type: ignore[arg-type]
        group_size=case.group_size,
        seed=case.seed,
        loop_measurements=case.loop_measurements,
        original_loops_true=True if case.world is not None else None,  # a world's revisits are all true
        # in a world that revisits its places densely, a random pair can be a real revisit: its
        # outliers keep out of the revisit radius (a world's unlabelled revisits are not false loops)
        outlier_min_distance_m=case.world.revisit_radius_m if case.world is not None else 0.0,
        dataset=f"world/{case.world.name}" if case.world is not None else None,
    )
    return graph, options


def case_log_name(case: SuiteCase, data_dir: Path) -> str:
    """``<case>-<hash>.mcap``: the hash covers the sources (size, mtime) and recorder options, or
    a generated world's spec and generator version."""
    from lcv_replay import __version__
    from lcv_replay.bench.worlds import WORLD_OUTLIERS_VERSION, WORLD_VERSION
    from lcv_replay.log.format import FORMAT_VERSION

    if case.world is not None:
        sources: list = [("world", WORLD_VERSION, "outliers", WORLD_OUTLIERS_VERSION)]
    else:
        graph, options = _recorder_inputs(case, data_dir)
        paths = [p for p in (graph, options.ground_truth, options.true_loops) if p is not None]
        sources = [(str(p), p.stat().st_size, p.stat().st_mtime_ns) for p in paths]
    key = {
        "case": asdict(case),
        "sources": sources,
        "format": FORMAT_VERSION,
        "version": __version__,
    }
    digest = hashlib.sha1(json.dumps(key, sort_keys=True).encode()).hexdigest()[:10]
    safe = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in case.name)
    return f"{safe}-{digest}.mcap"


def build_case_log(case: SuiteCase, data_dir: Path, workdir: Path) -> BuiltLog:
    """Record ``case`` into ``workdir`` with the g2o recorder, or reuse a valid earlier build."""
    from lcv_replay.log.reader import open_log
    from recorders.g2o import record_g2o

    make_folder(workdir)
    path = workdir / case_log_name(case, data_dir)
    if path.is_file():
        try:
            open_log(path)
            return BuiltLog(case.name, path, True, 0.0)
        except LcvError as exc:
            log.warning("rebuilding %s: %s", path, exc.format())
    started = time.perf_counter()
    graph, options = _recorder_inputs(case, data_dir, workdir)
    record_g2o(graph, path, options, force=True)
    return BuiltLog(case.name, path, False, time.perf_counter() - started)


# ---------------------------------------------------------------------------------------------
# Running
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SuiteEvent:
    """Progress of a suite run: ``phase`` is ``"build"`` or ``"run"``; ``done`` of ``total`` units."""

    phase: str
    case: str
    method: str | None
    done: int
    total: int


@dataclass(frozen=True)
class CaseRow:
    """A suite row: the :class:`VerifyRow`, or the error that stopped that method on that case."""

    case: str
    method: str
    row: VerifyRow | None
    error: str | None = None

    def as_dict(self) -> dict[str, Any]:
        out = self.row.as_dict() if self.row is not None else {"log": None, "method": self.method}
        out.pop("config", None)  # the suite report carries the config once
        out["case"] = self.case
        out["error"] = self.error
        return out


@dataclass(frozen=True)
class MethodSummary:
    """One method over all cases of a suite. Means skip undefined values (``None``).

    ``pooled_*`` are micro-averages (total TP over total accepted, over total true candidates);
    ``mean_*`` average the per-case figures.

    ``no_false_positive_cases`` counts cases with no false positive (precision 1, or nothing
    accepted where nothing was true); ``ambiguous`` the loops flagged ambiguous over all cases;
    ``ate_over_oracle`` is the mean ratio of ATE to the oracle's ATE.
    """

    method: str
    cases: int
    errors: int
    pooled_precision: float | None
    pooled_recall: float | None
    mean_precision: float | None
    min_precision: float | None
    mean_recall: float | None
    mean_f1: float | None
    no_false_positive_cases: int
    ambiguous: int
    mean_ate_m: float | None
    max_ate_over_oracle: float | None
    mean_ate_over_oracle: float | None
    total_time_s: float
    median_time_s: float | None


@dataclass(frozen=True)
class SuiteReport:
    """Everything a suite run produced (``as_dict`` is the JSON written by ``--json``)."""

    suite: str
    description: str
    data_dir: Path
    workdir: Path
    methods: tuple[str, ...]
    rows: tuple[CaseRow, ...]
    builds: tuple[BuiltLog, ...]
    wall_time_s: float
    config: dict[str, Any] = field(default_factory=dict)
    complete: bool = True

    def summary(self) -> list[MethodSummary]:
        return summarise(self.rows, self.methods)

    def as_dict(self) -> dict[str, Any]:
        return {
            "suite": self.suite,
            "description": self.description,
            "complete": self.complete,
            "data_dir": str(self.data_dir),
            "workdir": str(self.workdir),
            "methods": list(self.methods),
            "wall_time_s": self.wall_time_s,
            "config": self.config,
            "builds": [{**asdict(b), "path": str(b.path)} for b in self.builds],
            "summary": [_json_ready(asdict(s)) for s in self.summary()],
            "rows": [r.as_dict() for r in self.rows],
        }


def _json_ready(d: dict[str, Any]) -> dict[str, Any]:
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}


def available_suite_methods(requested: Sequence[str]) -> tuple[str, ...]:
    """The methods to run: ``requested``, or :data:`DEFAULT_METHODS` that are registered."""
    from lcv_replay.verification.registry import available_methods

    registered = available_methods()
    if requested:
        return tuple(requested)
    return tuple(m for m in DEFAULT_METHODS if m in registered)


def run_suite(
    suite: Suite,
    *,
    data_dir: Path,
    workdir: Path,
    config: VerificationConfig | None = None,
    methods: Sequence[str] = (),
    seed: int | None = None,
    progress: Callable[[SuiteEvent], None] | None = None,
    on_row: Callable[[CaseRow], None] | None = None,
    distribute: Callable[..., tuple[list[BuiltLog], list[CaseRow]]] | None = None,
) -> SuiteReport:
    """Build every case's log (or reuse it) and run every method on it.

    A method that raises :class:`LcvError` on a case is recorded as an error row and the suite
    goes on. ``KeyboardInterrupt`` propagates; use ``on_row`` to keep the rows done so far.

    ``distribute`` runs the (case, method) pairs elsewhere, e.g. as Ray tasks
    (:func:`lcv_replay.fleet.suite.on_cluster`): it is called with the suite, the methods and this
    function's arguments, and returns ``(builds, rows)``: the same rows in the same order as the
    serial loop, apart from the time fields.

    Raises:
        ConfigError: an unknown method (checked before any work).
        RecorderError: a case's source files are missing.
    """
    from lcv_replay.config import to_dict
    from lcv_replay.errors import ConfigError
    from lcv_replay.verification.registry import available_methods

    config = config or VerificationConfig()
    methods = available_suite_methods(methods or suite.methods)
    registered = available_methods()
    unknown = [m for m in methods if m not in registered]
    if unknown:
        raise ConfigError(f"unknown verification method '{unknown[0]}'", fix=f"use one of {', '.join(sorted(registered))}")
    started = time.perf_counter()
    if distribute is not None:
        builds, rows = distribute(
            suite, methods, data_dir=data_dir, workdir=workdir, config=config, seed=seed,
            run_one=_run_one, progress=progress, on_row=on_row,
        )
        return SuiteReport(
            suite.name, suite.description, data_dir, workdir, methods, tuple(rows), tuple(builds),
            time.perf_counter() - started, to_dict(config),
        )
    total_runs = len(suite.cases) * len(methods)
    builds: list[BuiltLog] = []
    rows: list[CaseRow] = []
    done = 0
    for case in suite.cases:
        if progress:
            progress(SuiteEvent("build", case.name, None, done, total_runs))
        built = build_case_log(case, data_dir, workdir)
        builds.append(built)
        inputs = load_inputs(built.path, require_candidates=False)
        for method in methods:
            if progress:
                progress(SuiteEvent("run", case.name, method, done, total_runs))
            row = _run_one(inputs, case.name, method, config, seed)
            rows.append(row)
            if on_row:
                on_row(row)
            done += 1
    if progress:
        progress(SuiteEvent("done", "", None, done, total_runs))
    return SuiteReport(
        suite.name, suite.description, data_dir, workdir, methods, tuple(rows), tuple(builds),
        time.perf_counter() - started, to_dict(config),
    )


def _run_one(inputs: LogInputs, case: str, method: str, config: VerificationConfig, seed: int | None) -> CaseRow:
    try:
        return CaseRow(case, method, verify_inputs(inputs, method, config, seed=seed, case=case).row)
    except LcvError as exc:
        log.warning("%s on %s failed: %s", method, case, exc.format())
        return CaseRow(case, method, None, exc.format())


# ---------------------------------------------------------------------------------------------
# Summaries and tables
# ---------------------------------------------------------------------------------------------


def _mean(values: list[float | None]) -> float | None:
    defined = [v for v in values if v is not None]
    return float(np.mean(defined)) if defined else None


def summarise(rows: Sequence[CaseRow], methods: Sequence[str]) -> list[MethodSummary]:
    """Per-method aggregates over the suite's cases (see :class:`MethodSummary`)."""
    oracle_ate = {r.case: r.row.ate_rmse_m for r in rows if r.method == "oracle" and r.row is not None}
    out = []
    for method in methods:
        mine = [r for r in rows if r.method == method]
        ok = [r.row for r in mine if r.row is not None]
        ratios = [
            row.ate_rmse_m / oracle_ate[r.case]
            for r, row in ((r, r.row) for r in mine if r.row is not None)
            if row.ate_rmse_m is not None and oracle_ate.get(r.case)
        ]
        times = [row.wall_time_s for row in ok]
        precisions = [row.precision for row in ok if row.precision is not None]
        tp = sum(row.true_positives or 0 for row in ok)
        fp = sum(row.false_positives or 0 for row in ok)
        true = sum(row.true_candidates or 0 for row in ok)
        out.append(
            MethodSummary(
                method=method,
                cases=len(mine),
                errors=len(mine) - len(ok),
                pooled_precision=tp / (tp + fp) if tp + fp else None,
                pooled_recall=tp / true if true else None,
                mean_precision=_mean(precisions),
                min_precision=min(precisions) if precisions else None,
                mean_recall=_mean([row.recall for row in ok]),
                mean_f1=_mean([row.f1 for row in ok]),
                no_false_positive_cases=sum(1 for row in ok if row.false_positives == 0),
                ambiguous=sum(row.ambiguous for row in ok),
                mean_ate_m=_mean([row.ate_rmse_m for row in ok]),
                max_ate_over_oracle=max(ratios) if ratios else None,
                mean_ate_over_oracle=_mean(ratios),
                total_time_s=float(sum(times)),
                median_time_s=float(np.median(times)) if times else None,
            )
        )
    return out


def _fmt(value: float | int | None, digits: int = 2) -> str:
    if value is None:
        return "–"
    if isinstance(value, int):
        return str(value)
    return f"{value:.{digits}f}"


def markdown_rows(rows: Sequence[CaseRow]) -> str:
    """One line per case × method: P, R, F1 (3 decimals: 0.998 is not 1), TP/FP/FN, the loops
    flagged ambiguous (neither accepted nor rejected), ATE (aligned), time."""
    lines = [
        "| case | method | P | R | F1 | TP | FP | FN | amb. | ATE m | time s | ×RT |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        row = r.row
        if row is None:
            lines.append(f"| {r.case} | {r.method} | error: {r.error} ||||||||||")
            continue
        lines.append(
            f"| {r.case} | {r.method} | {_fmt(row.precision, 3)} | {_fmt(row.recall, 3)} | {_fmt(row.f1, 3)} | "
            f"{_fmt(row.true_positives)} | {_fmt(row.false_positives)} | {_fmt(row.false_negatives)} | "
            f"{_fmt(row.ambiguous)} | {_fmt(row.ate_rmse_m)} | {_fmt(row.wall_time_s)} | {_fmt(row.realtime_factor, 0)} |"
        )
    return "\n".join(lines)


def markdown_summary(summary: Sequence[MethodSummary]) -> str:
    """One line per method: pooled and mean figures, worst precision, ATE against the oracle, time."""
    lines = [
        "| method | cases | P pooled | R pooled | mean P | min P | no-FP cases | ambiguous loops | mean R | mean F1 | mean ATE m | ATE/oracle mean | ATE/oracle max | time s (total) | time s (median) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for s in summary:
        cases = f"{s.cases}" + (f" ({s.errors} errors)" if s.errors else "")
        lines.append(
            f"| {s.method} | {cases} | {_fmt(s.pooled_precision, 3)} | {_fmt(s.pooled_recall, 3)} | "
            f"{_fmt(s.mean_precision, 3)} | {_fmt(s.min_precision, 3)} | "
            f"{s.no_false_positive_cases} | {s.ambiguous} | {_fmt(s.mean_recall, 3)} | {_fmt(s.mean_f1, 3)} | {_fmt(s.mean_ate_m)} | "
            f"{_fmt(s.mean_ate_over_oracle)} | {_fmt(s.max_ate_over_oracle)} | {_fmt(s.total_time_s, 1)} | "
            f"{_fmt(s.median_time_s)} |"
        )
    return "\n".join(lines)
