"""``lcv-replay bench follow``: latency of following a log, from a chunk on disk to its frame in the recording.

A writer thread re-records a real log (a g2o pose graph by default: odometry, ground truth,
DLoopDetector candidates, labels) with the live writer (:class:`~lcv_replay.log.writer.LogWriter`,
``live=True``: one flushed chunk per frame), paced at ``rate_hz``, while the replay follows it
(:func:`~lcv_replay.log.follow.follow_log`) into the Rerun sink. For each frame:

* ``landed``: when ``LogWriter.flush()`` returned for it (its chunk is in the file);
* ``logged``: when the Rerun sink's ``on_frame`` for it returned (the frame is in the recording
  stream; with a live viewer its buffered rows are sent within ``LIVE_REFRESH_S``).

The latency is ``logged - landed``. A frame that arrives while the verifier runs a window step waits
for the step, so the tail of the distribution is the window-step time.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lcv_replay.errors import ConfigError


@dataclass(frozen=True)
class FollowBenchResult:
    """Latencies in milliseconds over the followed frames (see the module docstring)."""

    source: str
    frames: int
    rate_hz: float
    poll_s: float
    outputs: str
    latency_p50_ms: float
    latency_p90_ms: float
    latency_p99_ms: float
    latency_max_ms: float
    frames_over_1s: int
    window_steps: int
    wall_s: float
    summary_equals_offline: bool
    load_average_1min: float


def _rewrite_live(source: Path, dest: Path, frames: int, rate_hz: float, landed: dict[int, float], started: threading.Event,
                  failure: list) -> None:
    from lcv_replay.log.reader import open_log
    from lcv_replay.log.writer import LogWriter

    try:
        with open_log(source) as reader:
            info = reader.info
            labels = reader.true_loops()
            with LogWriter(dest, force=True, dataset=f"{info.metadata.get('dataset', source.stem)} (followed)",
                           recorder="bench-follow", nominal_rate_hz=rate_hz, recorder_config={"source": str(source)},
                           odometry_information=info.odometry_information, live=True) as writer:
                if any(c.query_frame < frames for c in reader.loop_candidates()):
                    writer.declare_candidates()
                if info.has_labels:
                    writer.declare_labels()
                if info.has_ground_truth:
                    writer.declare_ground_truth()
                t0 = time.monotonic()
                for frame in reader.frames():
                    if frame.index >= frames:
                        break
                    wait_s = t0 + frame.index / rate_hz - time.monotonic()  # read once: it may pass between two reads
                    if wait_s > 0:
                        time.sleep(wait_s)
                    writer.write_frame(frame.index, frame.stamp_ns, odom=frame.odom, ground_truth=frame.ground_truth)
                    for candidate in frame.candidates:
                        writer.write_loop_candidate(candidate, frame.stamp_ns)
                    for query, match in sorted(p for p in labels if p[0] == frame.index):
                        writer.write_true_loop(query, match, frame.stamp_ns)
                    writer.flush()
                    landed[frame.index] = time.monotonic()
                    started.set()
    except BaseException as exc:  # noqa: BLE001 - reported by the caller
        failure.append(exc)
        started.set()


def run_follow_benchmark(
    source: Path,
    *,
    frames: int = 600,
    rate_hz: float = 10.0,
    poll_s: float = 0.05,
    outputs: str = "file",
    work_dir: Path | None = None,
    config=None,
) -> FollowBenchResult:
    """Follow ``source`` re-recorded live at ``rate_hz`` (see the module docstring); ``outputs`` is
    ``"file"`` (``--save`` only) or ``"serve"`` (a local gRPC server too, so rows are streamed live)."""
    from lcv_replay.config import ReplayConfig
    from lcv_replay.log.follow import follow_log
    from lcv_replay.replay import ReplayOptions, replay
    from lcv_replay.sinks.base import BaseSink
    from lcv_replay.sinks.config import RerunOutputs
    from lcv_replay.sinks.rerun_sink import RerunSink

    if frames < 2 or not rate_hz > 0:
        raise ConfigError("need frames >= 2 and rate_hz > 0")
    if outputs not in ("file", "serve"):
        raise ConfigError(f"outputs {outputs!r} is unknown", fix="use file or serve")
    config = config or ReplayConfig()

    class Logged(BaseSink):
        def __init__(self) -> None:
            self.at: dict[int, float] = {}

        def on_frame(self, update) -> None:
            self.at[update.frame.index] = time.monotonic()

    class Steps(BaseSink):
        count = 0

        def on_step(self, update) -> None:
            Steps.count += 1

    with tempfile.TemporaryDirectory(dir=work_dir) as tmp:
        dest = Path(tmp) / "followed.mcap"
        landed: dict[int, float] = {}
        started, failure = threading.Event(), []
        writer = threading.Thread(target=_rewrite_live, args=(source, dest, frames, rate_hz, landed, started, failure), daemon=True)
        writer.start()
        started.wait()
        if failure:
            raise failure[0]
        rerun_outputs = RerunOutputs(save=Path(tmp) / "followed.rrd", serve=outputs == "serve", grpc_port=_free_port(),
                                     web_port=_free_port())
        logged, steps = Logged(), Steps()
        opener = functools.partial(follow_log, idle_timeout_s=10.0, poll_s=poll_s)
        t0 = time.monotonic()
        summary = replay(ReplayOptions(log_path=dest, config=config, open_reader=opener),
                         [RerunSink(config.rerun, rerun_outputs), logged, steps], handle_sigint=False)
        wall = time.monotonic() - t0
        writer.join()
        if failure:
            raise failure[0]
        offline = replay(ReplayOptions(log_path=dest, config=config), [], handle_sigint=False)
    latency_ms = np.array([1000 * (logged.at[i] - landed[i]) for i in sorted(landed) if i in logged.at])
    fields = ("frames", "constraints", "accepted_constraint_ids", "precision", "recall", "ate_rmse_m")
    return FollowBenchResult(
        source=str(source),
        frames=len(latency_ms),
        rate_hz=rate_hz,
        poll_s=poll_s,
        outputs=outputs,
        latency_p50_ms=float(np.percentile(latency_ms, 50)),
        latency_p90_ms=float(np.percentile(latency_ms, 90)),
        latency_p99_ms=float(np.percentile(latency_ms, 99)),
        latency_max_ms=float(latency_ms.max()),
        frames_over_1s=int((latency_ms > 1000).sum()),
        window_steps=Steps.count,
        wall_s=wall,
        summary_equals_offline=all(getattr(summary, f) == getattr(offline, f) for f in fields),
        load_average_1min=os.getloadavg()[0],
    )


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def format_results(results: list[FollowBenchResult]) -> str:
    header = (f"{'outputs':<7} {'frames':>6} {'rate Hz':>7} {'poll s':>6} {'p50 ms':>7} {'p90 ms':>7} {'p99 ms':>7} "
              f"{'max ms':>7} {'>1 s':>4} {'steps':>5} {'= offline':>9} {'load':>5}")
    lines = [header, "-" * len(header)]
    for r in results:
        lines.append(
            f"{r.outputs:<7} {r.frames:>6} {r.rate_hz:>7g} {r.poll_s:>6g} {r.latency_p50_ms:>7.1f} {r.latency_p90_ms:>7.1f} "
            f"{r.latency_p99_ms:>7.1f} {r.latency_max_ms:>7.1f} {r.frames_over_1s:>4} {r.window_steps:>5} "
            f"{'yes' if r.summary_equals_offline else 'NO':>9} {r.load_average_1min:>5.1f}"
        )
    return "\n".join(lines)


def results_to_json(results: list[FollowBenchResult]) -> list[dict]:
    return [dataclasses.asdict(r) for r in results]

