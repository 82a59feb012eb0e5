"""``lcv-replay batch``: many logs through the replay, one Ray task each, into one run folder.

Layout of ``RUN_DIR``::

    run.json                      config, code version, machine, cluster, one entry per log
    fleet.md  fleet.html          the per-log table, worst first, with aggregates and figures
    fleet.csv fleet.parquet       the per-log figures for the user's own analysis
    logs/<name>/recording.rrd     the replay's Rerun recording
    logs/<name>/summary.json      the replay's summary (docs/summary-json.md) + the "batch" key
    logs/<name>/error.txt         an unexpected error's traceback (failed logs only)

Every file is written atomically, and ``run.json`` is rewritten as logs finish, so it is always
consistent with the folders: a log is done when its ``summary.json`` exists.

**Resume.** A log is skipped when its ``summary.json`` has the run's config hash and the log's
hash (BLAKE2b of the file's bytes, the descriptor cache's key; the size and modification time
recorded with it spare a re-hash when they have not changed) and the requested outputs exist.
Everything else is run again.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import logging
import os
import platform
import subprocess
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Literal, Sequence

from lcv_replay.errors import FleetError, LcvError
from lcv_replay.fleet.inputs import FileStat, FleetLog
from lcv_replay.fleet.task import (
    ATTEMPTS,
    BATCH_KEY,
    EXPORT,
    RECORDING,
    REPORT,
    SUMMARY,
    LogJob,
    LogOutcome,
    attempts_so_far,
    clear_outputs,
    run_log,
)

logger = logging.getLogger(__name__)

RUN_JSON = "run.json"
LOGS_DIR = "logs"
RUN_FORMAT = "lcv-replay-batch/1"
#: Seconds between two rewrites of run.json while logs finish (it is always rewritten at the end).
RUN_JSON_EVERY_S = 2.0

EntryStatus = Literal["ok", "failed", "skipped"]


# --------------------------------------------------------------------------------------- hashes
def config_hash(options: Any) -> str:
    """16 hex of SHA-256 over what decides a log's result: the resolved config (method and seed
    applied), the constraint source, the time range, ``--recover`` and the code version."""
    from lcv_replay import __version__
    from lcv_replay.config import to_dict

    key = {
        "config": to_dict(options.resolved_config()),
        "constraints": options.constraints,
        "start_offset_s": options.start_offset_s,
        "duration_s": options.duration_s,
        "recover": options.recover,
        "version": __version__,
    }
    return hashlib.sha256(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()[:16]


def code_version() -> dict[str, Any]:
    """``lcv_replay`` version, and the git commit (``+dirty``) when running from a checkout."""
    from lcv_replay import __version__

    out: dict[str, Any] = {"lcv_replay": __version__, "git": None}
    repo = Path(__file__).resolve().parents[2]
    if (repo / ".git").exists():
        try:
            commit = subprocess.run(["git", "-C", str(repo), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5).stdout.strip()
            dirty = subprocess.run(["git", "-C", str(repo), "status", "--porcelain", "--untracked-files=no"],
                                   capture_output=True, text=True, timeout=5).stdout.strip()
            out["git"] = (commit + ("+dirty" if dirty else "")) or None
        except (OSError, subprocess.SubprocessError):
            pass
    return out


def machine() -> dict[str, Any]:
    return {
        "host": platform.node(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpus": os.cpu_count(),
    }


# --------------------------------------------------------------------------------------- spec
@dataclass(frozen=True)
class BatchSpec:
    """A batch to run.

    Attributes:
        logs: the logs (absolute paths, unique names).
        run_dir: ``RUN_DIR``.
        options: the replay options shared by every log (``log_path`` is replaced per log; the rate
            is forced to max).
        export, report: also write each log's export folder and ``report.html``.
        resume: skip logs already done with the same config and log hash.
        command: the command line, for ``run.json``.
    """

    logs: tuple[FleetLog, ...]
    run_dir: Path
    options: Any  # lcv_replay.replay.ReplayOptions
    export: bool = False
    report: bool = False
    resume: bool = True
    command: tuple[str, ...] = ()

    def out_dir(self, log: FleetLog) -> Path:
        return self.run_dir / LOGS_DIR / log.name


def check_run_dir(run_dir: Path) -> Path:
    """Refuse a ``--out`` that cannot hold a batch, before anything is written.

    Raises:
        FleetError: a file; a non-empty folder without ``run.json``; a ``run.json`` that is not a
            batch's; a folder that cannot be created or written.
    """
    run_dir = Path(run_dir)
    if run_dir.exists() and not run_dir.is_dir():
        raise FleetError("--out is a file, not a folder", path=run_dir, fix="name a new folder for the run (or an earlier run's folder to resume it)")
    if run_dir.is_dir():
        marker = run_dir / RUN_JSON
        if marker.is_file():
            try:
                fmt = json.loads(marker.read_text(encoding="utf-8")).get("format")
            except (OSError, ValueError, AttributeError):
                fmt = None
            if fmt != RUN_FORMAT:
                raise FleetError(f"{RUN_JSON} is not a batch run's ({RUN_FORMAT})", path=marker, fix="choose another --out folder")
        elif any(run_dir.iterdir()):
            raise FleetError("--out is a folder with other files and no run.json: not a batch run folder",
                             path=run_dir, fix="choose a new or empty folder")
        if not os.access(run_dir, os.W_OK):
            raise FleetError("--out is not writable", path=run_dir, fix="choose another folder")
    else:
        parent = next((p for p in run_dir.absolute().parents if p.exists()), None)
        if parent is None or not parent.is_dir() or not os.access(parent, os.W_OK):
            raise FleetError("--out cannot be created here", path=run_dir, fix="choose a folder in a writable place")
    return run_dir


# --------------------------------------------------------------------------------------- entries
@dataclass(frozen=True)
class LogEntry:
    """One log's line in ``run.json``.

    Attributes:
        status: ``ok``, ``failed`` or ``skipped`` (done by an earlier run with the same config and
            log hash; ``summary`` is that run's).
        error: one line (``failed``), else ``None``.
        summary: the ``summary.json`` document (without ``config``, which ``run.json`` holds once,
            and ``batch``, whose fields are the entry's), or ``None``.
        attempts: Ray attempts this run (``> 1``: a worker died and Ray retried).
        seconds: the task's wall time, submission to result (``None`` for ``skipped``).
        cpu_s: the task's CPU time in its worker (``None`` for ``skipped`` and dead workers).
    """

    log: FleetLog
    status: EntryStatus
    error: str | None = None
    summary: dict[str, Any] | None = None
    batch: dict[str, Any] = field(default_factory=dict)
    attempts: int = 0
    seconds: float | None = None
    cpu_s: float | None = None

    def as_dict(self) -> dict[str, Any]:
        summary = None
        if self.summary is not None:
            summary = {k: v for k, v in self.summary.items() if k not in ("config", BATCH_KEY)}
        name = self.log.name
        return {
            "log": str(self.log.path),
            "name": name,
            "status": self.status,
            "error": self.error,
            "summary": summary,
            "attempts": self.attempts,
            "seconds": self.seconds,
            "cpu_s": self.cpu_s,
            "log_hash": self.batch.get("log_hash"),
            "oracle_ate_rmse_m": self.batch.get("oracle_ate_rmse_m"),
            "ate_over_oracle": self.batch.get("ate_over_oracle"),
            "folder": f"{LOGS_DIR}/{name}",
        }


def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def done_summary(spec: BatchSpec, log: FleetLog, config_hash_: str) -> dict[str, Any] | None:
    """The ``summary.json`` of a log already done with this config and these log bytes, and with the
    outputs this run asks for; else ``None``."""
    out = spec.out_dir(log)
    summary = _read_json(out / SUMMARY)
    if summary is None:
        return None
    batch = summary.get(BATCH_KEY) or {}
    if batch.get("config_hash") != config_hash_ or not log.path.is_file():
        return None
    stat = FileStat.of(log.path)
    if (batch.get("log_size_bytes"), batch.get("log_mtime_ns")) != (stat.size_bytes, stat.mtime_ns):
        from lcv_replay.retrieval.cache import log_cache_key

        try:
            if log_cache_key(log.path) != batch.get("log_hash"):
                return None
        except LcvError:  # unreadable now: run it, and let the task report why
            return None
    wanted = [out / RECORDING] + ([out / EXPORT] if spec.export else []) + ([out / REPORT] if spec.report else [])
    if not all(p.exists() for p in wanted):
        return None
    return summary


# --------------------------------------------------------------------------------------- state
@dataclass
class BatchState:
    """The run as it progresses; :meth:`as_dict` is ``run.json``."""

    spec: BatchSpec
    config_hash: str
    config: dict[str, Any]
    cluster: dict[str, Any] = field(default_factory=dict)
    entries: dict[str, LogEntry] = field(default_factory=dict)  # by log name
    running: set[str] = field(default_factory=set)
    started_at: float = field(default_factory=time.time)
    started_perf: float = field(default_factory=time.perf_counter)
    finished_at: float | None = None
    interrupted: bool = False
    code: dict[str, Any] = field(default_factory=code_version)

    @property
    def total(self) -> int:
        return len(self.spec.logs)

    def count(self, status: str) -> int:
        return sum(1 for e in self.entries.values() if e.status == status)

    @property
    def pending(self) -> list[FleetLog]:
        return [log for log in self.spec.logs if log.name not in self.entries]

    @property
    def elapsed_s(self) -> float:
        return time.perf_counter() - self.started_perf

    @property
    def replayed_log_s(self) -> float:
        """Log seconds replayed by this run (``ok`` logs, not ``skipped``)."""
        return sum((e.summary or {}).get("log_duration_s") or 0.0 for e in self.entries.values() if e.status == "ok")

    @property
    def complete(self) -> bool:
        return not self.pending

    def entry_list(self) -> list[LogEntry]:
        return [self.entries[log.name] for log in self.spec.logs if log.name in self.entries]

    def as_dict(self) -> dict[str, Any]:
        options = self.spec.options
        counts = {s: self.count(s) for s in ("ok", "failed", "skipped")}
        counts["pending"] = len(self.pending)
        return {
            "format": RUN_FORMAT,
            "command": list(self.spec.command),
            "started": _iso(self.started_at),
            "finished": None if self.finished_at is None else _iso(self.finished_at),
            "wall_time_s": self.elapsed_s if self.finished_at is None else self.finished_at - self.started_at,
            "complete": self.complete,
            "interrupted": self.interrupted,
            "counts": counts,
            "config_hash": self.config_hash,
            "method": options.resolved_config().verification.method,
            "seed": options.resolved_config().verification.seed,
            "constraints": options.constraints,
            "export": self.spec.export,
            "report": self.spec.report,
            "config": self.config,
            "code": self.code,
            "machine": machine(),
            "cluster": self.cluster,
            "logs": [e.as_dict() for e in self.entry_list()],
            "pending": [str(log.path) for log in self.pending],
        }


def _iso(t: float) -> str:
    return _dt.datetime.fromtimestamp(t, tz=_dt.timezone.utc).isoformat(timespec="seconds")


# --------------------------------------------------------------------------------------- running
@dataclass(frozen=True)
class BatchEvent:
    """Progress: ``kind`` is ``planned``, ``started`` or ``finished`` (``entry`` set)."""

    kind: str
    state: BatchState
    log: FleetLog | None = None
    entry: LogEntry | None = None


def plan(spec: BatchSpec, state: BatchState) -> list[LogJob]:
    """Fill ``state`` with the skipped logs and return the jobs to run, the largest logs first (a
    proxy for the longest replays: the long ones do not start last and run alone at the end)."""
    jobs = []
    options = replace(spec.options, rate=None)
    for log in spec.logs:
        if spec.resume:
            summary = done_summary(spec, log, state.config_hash)
            if summary is not None:
                state.entries[log.name] = LogEntry(log, "skipped", summary=summary, batch=summary.get(BATCH_KEY) or {})
                continue
        (spec.out_dir(log) / ATTEMPTS).unlink(missing_ok=True)  # a count left by a driver that died
        jobs.append(LogJob(log, spec.out_dir(log), replace(options, log_path=log.path), state.config_hash,
                           export=spec.export, report=spec.report))
    return sorted(jobs, key=lambda job: -_size(job.log.path))


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0


def entry_of(result: Any) -> LogEntry | None:
    """A finished task's entry; ``None`` when the log was not run to its end (cancelled)."""
    job: LogJob = result.job
    if result.cancelled:
        reset_log_folder(job.out_dir)
        return None
    if result.failure is not None:  # Ray gave up: the worker kept dying
        attempts = attempts_so_far(job.out_dir)
        reset_log_folder(job.out_dir)
        return LogEntry(job.log, "failed", error=f"{result.failure} [{attempts} attempt(s) started]", attempts=attempts, seconds=result.seconds)
    outcome: LogOutcome = result.value
    if outcome.status == "interrupted":
        reset_log_folder(job.out_dir)
        return None
    if outcome.status == "failed":
        reset_log_folder(job.out_dir, keep_error=True)
        return LogEntry(job.log, "failed", error=outcome.error, attempts=outcome.attempts, seconds=result.seconds, cpu_s=outcome.cpu_s)
    return LogEntry(job.log, "ok", summary=outcome.summary, batch=(outcome.summary or {}).get(BATCH_KEY) or {},
                    attempts=outcome.attempts, seconds=result.seconds, cpu_s=outcome.cpu_s)


def reset_log_folder(folder: Path, *, keep_error: bool = False) -> None:
    """After a log that did not end ``ok``: remove its partial outputs and attempt count, and the
    folder itself when nothing is left (``error.txt`` is kept with ``keep_error``)."""
    if not keep_error:
        clear_outputs(folder)
    (folder / ATTEMPTS).unlink(missing_ok=True)
    try:
        folder.rmdir()
    except OSError:  # not empty (error.txt), or gone
        pass


def run_batch(
    spec: BatchSpec,
    cluster: Any,
    *,
    stop: Any | None = None,
    on_event: Callable[[BatchEvent], None] | None = None,
) -> BatchState:
    """Run every log of ``spec`` not already done on ``cluster`` (a connected
    :class:`~lcv_replay.fleet.engine.Cluster`); write ``run.json`` as logs finish and the fleet
    tables at the end (also after Ctrl-C, with what was done).

    ``stop.requested`` (the first Ctrl-C) stops scheduling; running logs finish. A
    ``KeyboardInterrupt`` (the second) cancels them; they stay pending.
    """
    from lcv_replay.config import to_dict

    check_run_dir(spec.run_dir)
    spec.run_dir.mkdir(parents=True, exist_ok=True)
    state = BatchState(spec, config_hash(spec.options), to_dict(spec.options.resolved_config()), cluster.describe())
    emit = on_event or (lambda event: None)
    jobs = plan(spec, state)
    writer = _RunJsonWriter(spec.run_dir / RUN_JSON)
    writer.write(state, force=True)
    emit(BatchEvent("planned", state))

    def submitted(job: LogJob) -> None:
        state.running.add(job.log.name)
        emit(BatchEvent("started", state, job.log))

    def finished(result) -> None:
        state.running.discard(result.job.log.name)
        entry = entry_of(result)
        if entry is not None:
            state.entries[entry.log.name] = entry
        writer.write(state)
        emit(BatchEvent("finished", state, result.job.log, entry))

    try:
        report = cluster.run(run_log, jobs, stop=stop, on_submit=submitted, on_result=finished)
        for job in report.cancelled:
            reset_log_folder(job.out_dir)
        state.running.clear()
        state.interrupted = report.aborted or bool(state.pending)
    finally:
        state.finished_at = time.time()
        writer.write(state, force=True)
        write_fleet_outputs(state)
    return state


class _RunJsonWriter:
    """Rewrites ``run.json`` atomically, at most every :data:`RUN_JSON_EVERY_S` unless forced."""

    def __init__(self, path: Path):
        self.path = path
        self._last = 0.0

    def write(self, state: BatchState, *, force: bool = False) -> None:
        from lcv_replay.fileio import write_text_atomic

        now = time.monotonic()
        if not force and now - self._last < RUN_JSON_EVERY_S:
            return
        write_text_atomic(self.path, json.dumps(state.as_dict(), indent=2, allow_nan=False) + "\n")
        self._last = now


def write_fleet_outputs(state: BatchState) -> list[Path]:
    """``fleet.md``, ``fleet.html``, ``fleet.csv`` and ``fleet.parquet`` from the entries so far."""
    from lcv_replay.fleet import table

    run = state.as_dict()
    return table.write_fleet(state.spec.run_dir, table.rows_of_run(run), run=run)


def load_run(run_dir: str | Path) -> dict[str, Any]:
    """``RUN_DIR/run.json``.

    Raises:
        FleetError: missing or not a batch's.
    """
    path = Path(run_dir) / RUN_JSON
    data = _read_json(path)
    if data is None or data.get("format") != RUN_FORMAT:
        raise FleetError("not a batch run (no valid run.json)", path=Path(run_dir), fix="pass a folder written by 'lcv-replay batch'")
    return data


def failed_entries(state: BatchState) -> Sequence[LogEntry]:
    return [e for e in state.entry_list() if e.status == "failed"]
