"""One log of a batch: the body of its Ray task, a thin wrapper around :func:`lcv_replay.replay.replay`.

The wrapper runs the same replay as ``lcv-replay LOG.mcap --rate max`` (a ROS 2 MCAP or a bag is
converted first, with the default topics, as that command does) with these sinks: the Rerun
recording (``recording.rrd``), the oracle reference (:mod:`lcv_replay.fleet.oracle`) and, when asked,
the export and the HTML report. It adds only what a fleet needs around the call:

* the log's hash and the config hash, written into ``summary.json`` (the ``batch`` key) so that a
  resumed run can skip the log;
* the order of writes: ``summary.json`` is removed first and written last (atomically), so its
  presence means the log is done, whatever happened to the process in between; stale temp files
  of a killed earlier attempt are removed;
* an ``.attempts`` file, one line per attempt (host and pid), by which a retried task counts its
  attempts and a test finds the worker to kill;
* threads capped to the task's CPUs;
* every error becomes a :class:`LogOutcome` with one line (``failed``): failures are data.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import time
import traceback
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

from lcv_replay.errors import LcvError
from lcv_replay.fleet.inputs import FileStat, FleetLog

logger = logging.getLogger(__name__)

RECORDING = "recording.rrd"
SUMMARY = "summary.json"
REPORT = "report.html"
EXPORT = "export"
ERROR = "error.txt"
ATTEMPTS = ".attempts"
#: The ``summary.json`` key that holds the batch's bookkeeping (outside docs/summary-json.md's keys).
BATCH_KEY = "batch"

Status = Literal["ok", "failed", "interrupted"]


@dataclass(frozen=True)
class LogJob:
    """Everything one task needs (picklable; paths absolute, readable on every node).

    Attributes:
        log: the log and its folder name.
        out_dir: ``RUN_DIR/logs/<name>``.
        options: the replay options (``log_path`` is ``log.path``, ``rate`` is ``None``: max).
        config_hash: :func:`lcv_replay.fleet.batch.config_hash` of the run.
        cpus: the task's CPUs; thread pools are capped to this.
        export, report: also write ``export/`` and ``report.html``.
    """

    log: FleetLog
    out_dir: Path
    options: Any  # lcv_replay.replay.ReplayOptions (imported lazily: Ray workers unpickle it)
    config_hash: str
    cpus: int = 1
    export: bool = False
    report: bool = False


@dataclass(frozen=True)
class LogOutcome:
    """What a task returns.

    Attributes:
        status: ``ok``; ``failed`` (``error`` says why, in one line); ``interrupted`` (cancelled
            mid-replay: nothing kept, the log is still to do).
        summary: the ``summary.json`` document (``ok`` only).
        attempts: attempts of this task so far, this one included (Ray retries after a worker died).
        seconds: wall time of this attempt, hashing and writing included.
        cpu_s: CPU time of this attempt in the worker process (what it costs on a dedicated core).
        host, pid: where it ran.
        threads: the thread caps applied.
    """

    status: Status
    error: str | None = None
    summary: dict[str, Any] | None = None
    attempts: int = 1
    seconds: float = 0.0
    cpu_s: float = 0.0
    host: str = ""
    pid: int = 0
    threads: dict[str, Any] = field(default_factory=dict)


def attempts_so_far(out_dir: Path) -> int:
    """Attempts recorded in ``out_dir/.attempts`` (0 when none)."""
    try:
        return len((out_dir / ATTEMPTS).read_text(encoding="utf-8").splitlines())
    except FileNotFoundError:
        return 0


def attempt_pids(out_dir: Path) -> list[int]:
    """The worker pids of the recorded attempts, oldest first."""
    try:
        lines = (out_dir / ATTEMPTS).read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        return []
    return [int(line.split()[1]) for line in lines if len(line.split()) >= 2 and line.split()[1].isdigit()]


def clear_outputs(out_dir: Path) -> None:
    """Remove what an unfinished attempt may have left: the done marker first, then the rest.

    Used by a task before it starts and by the driver for a cancelled task.
    """
    import shutil

    for name in (SUMMARY, RECORDING, REPORT, ERROR):
        (out_dir / name).unlink(missing_ok=True)
    shutil.rmtree(out_dir / EXPORT, ignore_errors=True)
    if out_dir.is_dir():
        for stale in out_dir.glob(".*.tmp"):
            stale.unlink(missing_ok=True)


def run_log(job: LogJob) -> LogOutcome:
    """Replay one log into ``job.out_dir`` (the Ray task body; also callable in-process)."""
    from lcv_replay.fleet.engine import cap_threads, first_line

    started, started_cpu = time.perf_counter(), time.process_time()
    host, pid = socket.gethostname(), os.getpid()
    threads = cap_threads(job.cpus)
    out = job.out_dir
    try:
        out.mkdir(parents=True, exist_ok=True)
        with open(out / ATTEMPTS, "a", encoding="utf-8") as handle:
            handle.write(f"{host} {pid} {time.time():.3f}\n")
        attempts = attempts_so_far(out)
        clear_outputs(out)
    except OSError as exc:
        return LogOutcome("failed", f"{out}: cannot write the log's output folder ({exc.strerror or exc}); "
                          "RUN_DIR must be writable from every node", host=host, pid=pid, threads=threads)

    def outcome(status: Status, error: str | None = None, summary: dict | None = None) -> LogOutcome:
        return LogOutcome(status, error, summary, attempts, time.perf_counter() - started,
                          time.process_time() - started_cpu, host, pid, threads)

    try:
        summary = _replay_into(job, host=host, pid=pid, attempts=attempts, threads=threads, started_cpu=started_cpu)
    except LcvError as exc:
        clear_outputs(out)
        return outcome("failed", exc.format())
    except KeyboardInterrupt:  # ray.cancel: nothing of this attempt is kept
        clear_outputs(out)
        return outcome("interrupted")
    except Exception as exc:  # noqa: BLE001 - failures are data; the traceback goes to error.txt
        clear_outputs(out)
        from lcv_replay.fileio import write_text_atomic

        line = f"internal error: {type(exc).__name__}: {first_line(str(exc))}"
        write_text_atomic(out / ERROR, line + "\n\n" + traceback.format_exc())
        return outcome("failed", f"{line} (traceback in {out / ERROR})")
    if summary is None:
        clear_outputs(out)
        return outcome("interrupted")
    (out / ATTEMPTS).unlink(missing_ok=True)
    return outcome("ok", summary=summary)


def _replay_into(job: LogJob, *, host: str, pid: int, attempts: int, threads: dict[str, Any], started_cpu: float) -> dict[str, Any] | None:
    """The replay with the fleet's sinks; writes ``summary.json`` last. ``None`` if interrupted."""
    from lcv_replay.errors import LogFormatError
    from lcv_replay.fileio import write_text_atomic
    from lcv_replay.fleet.oracle import OracleReference
    from lcv_replay.replay import StopToken, replay
    from lcv_replay.retrieval.cache import log_cache_key
    from lcv_replay.sinks.config import RerunOutputs
    from lcv_replay.sinks.rerun_sink import RerunSink
    from lcv_replay.sinks.summary import summary_json
    from recorders.bags import is_foreign_log

    path = job.log.path
    if not path.is_file():
        raise LogFormatError(f"file not found on {host}", path=path,
                             fix="put the logs on storage that every node mounts at the same path")
    stat = FileStat.of(path)
    log_hash = log_cache_key(path)
    options = job.options
    if is_foreign_log(path):  # a ROS 2 MCAP or a bag: converted first, as 'lcv-replay LOG' does (cached per node)
        from recorders.convert import converted_log
        from recorders.rosbag import RosbagOptions

        options = replace(options, log_path=converted_log([path], RosbagOptions()).path)
    config = options.resolved_config()
    oracle = OracleReference()
    sinks: list = [RerunSink(config.rerun, RerunOutputs(save=job.out_dir / RECORDING)), oracle]
    sinks += _post_mortem_sinks(job)
    summary = replay(options, sinks, stop=StopToken(), handle_sigint=False)
    if summary.interrupted:
        return None
    document = json.loads(summary_json(summary))
    ate, reference = document.get("ate_rmse_m"), oracle.ate_rmse_m
    document[BATCH_KEY] = {
        "config_hash": job.config_hash,
        "log_hash": log_hash,
        "log_size_bytes": stat.size_bytes,
        "log_mtime_ns": stat.mtime_ns,
        "oracle_ate_rmse_m": reference,
        "ate_over_oracle": ate / reference if ate is not None and reference else None,
        "attempts": attempts,
        "cpu_time_s": time.process_time() - started_cpu,
        "host": host,
        "pid": pid,
        "threads": threads,
    }
    write_text_atomic(job.out_dir / SUMMARY, json.dumps(document, indent=2, allow_nan=False) + "\n")
    return document


def _post_mortem_sinks(job: LogJob) -> list:
    """The run recorder with the export and report sinks (``logs/<name>/export/``, ``report.html``),
    as ``lcv-replay LOG --export --report`` builds them."""
    if not (job.export or job.report):
        return []
    from lcv_replay.export.sink import ExportSink
    from lcv_replay.report.sink import ReportSink
    from lcv_replay.sinks.run_record import RunRecorder

    recorder = RunRecorder()
    sinks: list = [recorder]
    if job.export:
        sinks.append(ExportSink(recorder, job.out_dir / EXPORT))
    if job.report:
        sinks.append(ReportSink(recorder, job.out_dir / REPORT))
    return sinks
