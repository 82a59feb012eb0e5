"""``bench suite --workers N`` / ``--address``: the suite's (case, method) pairs as Ray tasks.

The logs are built (or reused) on the driver exactly as in a serial run; each case's
:class:`~lcv_replay.bench.verify.LogInputs` is read once and put in Ray's object store, so workers
need no shared storage; each pair runs the same function as the serial loop. The rows come back in
the serial order, equal to a serial run's apart from the time fields (a test checks it).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

#: ``VerifyRow`` fields that measure time (they differ between any two runs).
TIME_FIELDS = ("wall_time_s", "cpu_time_s", "realtime_factor", "window_time_mean_s", "window_time_max_s")


@dataclass(frozen=True)
class PairJob:
    """One (case, method) pair: ``index`` is its position in the serial order."""

    index: int
    case: str
    method: str


def run_pairs_on_cluster(
    cluster: Any,
    suite: Any,
    methods: Sequence[str],
    *,
    data_dir: Path,
    workdir: Path,
    config: Any,
    seed: int | None,
    run_one: Callable[..., Any],
    progress: Callable[[Any], None] | None = None,
    on_row: Callable[[Any], None] | None = None,
) -> tuple[list[Any], list[Any]]:
    """``(builds, rows)`` of ``suite`` with ``run_one(inputs, case, method, config, seed)`` per pair
    on ``cluster`` (a connected :class:`~lcv_replay.fleet.engine.Cluster`).

    Raises:
        KeyboardInterrupt: Ctrl-C: the running pairs were cancelled (``on_row`` has the rows done).
    """
    import ray

    from lcv_replay.bench.suite import CaseRow, SuiteEvent, build_case_log
    from lcv_replay.bench.verify import load_inputs

    total = len(suite.cases) * len(methods)
    builds, inputs = [], {}
    for case in suite.cases:
        if progress:
            progress(SuiteEvent("build", case.name, None, 0, total))
        built = build_case_log(case, data_dir, workdir)
        builds.append(built)
        inputs[case.name] = ray.put(load_inputs(built.path, require_candidates=False))
    jobs = [PairJob(k * len(methods) + j, case.name, method) for k, case in enumerate(suite.cases) for j, method in enumerate(methods)]
    rows: dict[int, Any] = {}

    def finished(result) -> None:
        job: PairJob = result.job
        row = result.value if result.failure is None else CaseRow(job.case, job.method, None, result.failure)
        rows[job.index] = row
        if on_row:
            on_row(row)
        if progress:
            progress(SuiteEvent("run", job.case, job.method, len(rows), total))

    report = cluster.run(run_one, jobs, args=lambda job: (inputs[job.case], job.case, job.method, config, seed), on_result=finished)
    if report.aborted:
        raise KeyboardInterrupt
    if progress:
        progress(SuiteEvent("done", "", None, len(rows), total))
    return builds, [rows[k] for k in sorted(rows)]


def on_cluster(cluster: Any) -> Callable[..., tuple[list[Any], list[Any]]]:
    """The ``distribute`` argument of :func:`lcv_replay.bench.suite.run_suite` for ``cluster``."""
    return functools.partial(run_pairs_on_cluster, cluster)
