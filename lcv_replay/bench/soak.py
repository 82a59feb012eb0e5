"""Soak benchmark: one long replay, with memory (RSS) and time per frame sampled as it runs.

``lcv-replay bench soak`` chains the real KITTI pose graphs of robustslam_kitti (sequences 00, 02,
05, 06 and 07 at one alpha, their own DLoopDetector candidates, labels and ground truth) into one
log of 20,000 frames, then replays it as a user would (``ilv+``, the Rerun recording written) with
a sink that samples the process' resident memory and the time per frame every 1,000 frames.

Chaining: each graph's odometry and ground truth are moved rigidly so that its first pose lies one
metre ahead of the previous graph's last pose; loop candidates and labels keep their measurements,
with frame indices shifted. The log never revisits a place across two graphs.

Goals (issue 12): after warm-up the RSS is flat (it grows by less than 10 % over the last 15,000
frames) and so is the time per frame.
"""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from lcv_replay import se2
from lcv_replay.sinks.base import BaseSink, FrameUpdate, RunSummary

SOAK_SEQUENCES: tuple[str, ...] = ("00", "02", "05", "06", "07")
#: One metre forward between two chained graphs (the odometry and ground truth of the joint).
JOINT_STEP = np.array([1.0, 0.0, 0.0])


def rss_bytes() -> int:
    """The resident set size of this process now (``/proc/self/statm``; peak RSS elsewhere)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


@dataclass(frozen=True)
class ChainedGraphs:
    """Several recordings as one: ``(N, 3)`` odometry and ground truth, candidates, labels, pieces."""

    odometry: np.ndarray
    ground_truth: np.ndarray
    candidates: tuple
    true_loops: frozenset[tuple[int, int]]
    pieces: tuple[tuple[str, int, int], ...]  # (dataset, first frame, frames)


def _moved(poses: np.ndarray, first_at: np.ndarray) -> np.ndarray:
    """``poses`` moved rigidly so that ``poses[0]`` lands on ``first_at``."""
    transform = se2.compose(first_at, se2.inverse(poses[0]))
    return se2.compose(transform, poses)


def chain_recordings(recordings: Sequence, frames: int) -> ChainedGraphs:
    """Chain :class:`recorders.g2o.G2oRecording` s (cycling through them) up to ``frames`` frames."""
    odometry, truth, candidates, labels, pieces = [], [], [], set(), []
    offset, k = 0, 0
    last_odom = last_truth = None
    while offset < frames:
        rec = recordings[k % len(recordings)]
        k += 1
        n = min(len(rec.odometry), frames - offset)
        odom = rec.odometry[:n]
        gt = rec.ground_truth[:n] if rec.ground_truth is not None else np.full((n, 3), np.nan)
        if last_odom is not None:
            odom = _moved(odom, se2.compose(last_odom, JOINT_STEP))
            gt = _moved(gt, se2.compose(last_truth, JOINT_STEP)) if np.isfinite(last_truth).all() else gt
        odometry.append(odom)
        truth.append(gt)
        for c in rec.candidates:
            if c.query_frame < n:
                candidates.append(dataclasses.replace(c, query_frame=c.query_frame + offset, match_frame=c.match_frame + offset))
        labels.update((q + offset, m + offset) for q, m in (rec.true_loops or ()) if q < n)
        pieces.append((rec.dataset, offset, n))
        last_odom, last_truth = odom[-1], gt[-1]
        offset += n
    return ChainedGraphs(np.concatenate(odometry), np.concatenate(truth), tuple(candidates), frozenset(labels), tuple(pieces))


def build_soak_log(data_dir: Path, out: Path, *, frames: int = 20_000, alpha: str = "0.50", force: bool = False):
    """Record the chained KITTI graphs into ``out``; returns the writer's ``RecordStats``.

    Raises:
        RecorderError: a sequence of the shared data is missing.
    """
    from recorders.common import LogHeader, make_frames, write_log
    from recorders.g2o import G2oOptions, prepare_g2o

    recordings = [
        prepare_g2o(Path(data_dir) / "robustslam_kitti" / seq / f"kitti_{seq}_alpha_{alpha}.g2o", G2oOptions())
        for seq in SOAK_SEQUENCES
    ]
    chained = chain_recordings(recordings, frames)
    rate_hz = 10.0
    stamps = np.rint(np.arange(len(chained.odometry)) * (1e9 / rate_hz)).astype(np.int64)
    header = LogHeader(
        dataset=f"soak/robustslam_kitti_alpha_{alpha}_x{len(chained.pieces)}",
        recorder="bench soak",
        nominal_rate_hz=rate_hz,
        config={"frames": frames, "alpha": alpha, "pieces": [list(p) for p in chained.pieces]},
        odometry_information=recordings[0].graph.odometry_information_matrix(),
    )
    return write_log(
        out, header, make_frames(stamps, odometry=chained.odometry, ground_truth=chained.ground_truth),
        candidates=chained.candidates, true_loops=chained.true_loops, force=force,
    )


@dataclass(frozen=True)
class SoakSample:
    """The state after ``frames`` frames: RSS, wall time so far, and the mean time per frame of the block."""

    frames: int
    rss_mb: float
    wall_s: float
    ms_per_frame: float


class SoakSampler(BaseSink):
    """Samples RSS and time every ``every`` frames (a sink, so it sees the replay as the others do)."""

    def __init__(self, every: int = 1000, on_sample=None):
        self.every = every
        self.on_sample = on_sample
        self.samples: list[SoakSample] = []
        self._t0 = self._last = time.perf_counter()
        self.rss_start_mb = rss_bytes() / 1e6

    def on_frame(self, update: FrameUpdate) -> None:
        done = update.frame.index + 1
        if done % self.every:
            return
        now = time.perf_counter()
        previous = self.samples[-1].frames if self.samples else 0
        sample = SoakSample(done, rss_bytes() / 1e6, now - self._t0, (now - self._last) / (done - previous) * 1e3)
        self._last = now
        self.samples.append(sample)
        if self.on_sample is not None:
            self.on_sample(sample)


@dataclass
class SoakReport:
    """The curve and the two goals (see the module docstring)."""

    log: str
    frames: int
    rerun: bool
    samples: list[SoakSample] = field(default_factory=list)
    rss_start_mb: float = 0.0
    summary: dict = field(default_factory=dict)
    window_frames: int = 15_000
    complete: bool = True

    def _at(self, frames: int) -> SoakSample | None:
        return next((s for s in self.samples if s.frames >= frames), None)

    def _window(self) -> list[SoakSample]:
        """The samples of the last ``window_frames`` frames (its first sample included)."""
        if not self.samples:
            return []
        start = self.samples[-1].frames - self.window_frames
        return [s for s in self.samples if s.frames >= start]

    @property
    def rss_growth(self) -> float | None:
        """Relative RSS growth over the last ``window_frames`` frames, from a least-squares line.

        RSS jumps by tens of MB between two samples (transient arrays of a verifier step), so two
        single samples would mostly measure that jitter; the line through all samples of the
        window does not.
        """
        window = self._window()
        if len(window) < 3:
            return None
        frames = np.array([s.frames for s in window], dtype=np.float64)
        rss = np.array([s.rss_mb for s in window])
        slope, intercept = np.polyfit(frames, rss, 1)
        start = slope * frames[0] + intercept
        return float(slope * (frames[-1] - frames[0]) / start)

    @property
    def rss_growth_kb_per_frame(self) -> float | None:
        """The same line's slope, in kB per frame."""
        window = self._window()
        if len(window) < 3:
            return None
        slope = np.polyfit([s.frames for s in window], [s.rss_mb for s in window], 1)[0]
        return float(slope * 1e3)

    @property
    def time_ratio(self) -> float | None:
        """Mean ms/frame of the last three samples over that of the three after warm-up (same window)."""
        if len(self.samples) < 6:
            return None
        start = self._at(self.samples[-1].frames - self.window_frames)
        k = self.samples.index(start) if start is not None else 0
        head = [s.ms_per_frame for s in self.samples[k : k + 3]]
        tail = [s.ms_per_frame for s in self.samples[-3:]]
        return float(np.mean(tail) / np.mean(head))

    def as_dict(self) -> dict:
        return {
            "log": self.log,
            "frames": self.frames,
            "rerun": self.rerun,
            "complete": self.complete,
            "rss_start_mb": self.rss_start_mb,
            "rss_growth_last_frames": self.window_frames,
            "rss_growth": self.rss_growth,
            "rss_growth_kb_per_frame": self.rss_growth_kb_per_frame,
            "time_per_frame_ratio": self.time_ratio,
            "samples": [dataclasses.asdict(s) for s in self.samples],
            "summary": self.summary,
        }


def run_soak(log: Path, *, every: int = 1000, rerun: bool = True, workdir: Path, stop=None, on_sample=None, config=None) -> SoakReport:
    """Replay ``log`` (``ilv+`` and the defaults; the Rerun recording into ``workdir`` unless not ``rerun``)."""
    from lcv_replay.config import ReplayConfig
    from lcv_replay.replay import ReplayOptions, replay

    config = config or ReplayConfig()
    sampler = SoakSampler(every, on_sample)
    sinks: list = [sampler]
    if rerun:
        from lcv_replay.sinks.config import RerunOutputs
        from lcv_replay.sinks.rerun_sink import RerunSink

        sinks.append(RerunSink(config.rerun, RerunOutputs(save=Path(workdir) / "soak.rrd")))
    result: RunSummary = replay(ReplayOptions(log_path=Path(log), config=config), sinks, stop=stop, handle_sigint=False)
    report = SoakReport(str(log), result.frames, rerun, sampler.samples, sampler.rss_start_mb, result.to_json_dict())
    report.complete = not result.interrupted
    return report


def format_report(report: SoakReport) -> str:
    """The curve as a table, then the two goals."""
    lines = [f"{'frames':>7} {'RSS MB':>8} {'ms/frame':>9} {'wall s':>8}"]
    lines += [f"{s.frames:>7} {s.rss_mb:>8.1f} {s.ms_per_frame:>9.2f} {s.wall_s:>8.1f}" for s in report.samples]
    growth, ratio = report.rss_growth, report.time_ratio
    lines.append("")
    lines.append(
        f"RSS at start {report.rss_start_mb:.0f} MB; growth over the last {report.window_frames} frames (line fit): "
        + ("n/a" if growth is None else (
            f"{100 * growth:+.1f} %, {report.rss_growth_kb_per_frame:.2f} kB/frame "
            f"(goal < 10 %: {'met' if growth < 0.10 else 'NOT met'})"
        ))
    )
    lines.append(
        "time per frame, last 3 samples / first 3 of that window: "
        + ("n/a" if ratio is None else f"{ratio:.2f}x")
    )
    return "\n".join(lines)
