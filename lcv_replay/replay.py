"""The replay engine: a log's frames through retrieval and incremental verification, into sinks.

``replay(options, sinks, clock)`` wires the stages and owns only three things of its own:

* **routing**: left images go to retrieval, the log's ``/loop_candidates`` go straight to the
  verifier, or both (``--constraints images|log|both``; the default follows what the log has);
  odometry always goes to the verifier, which runs its window steps as frames arrive;
* **pacing**, as ``ros2 bag play``: ``rate`` 1.0 is real time by the log's timestamps, ``None`` as
  fast as possible; an injectable :class:`Clock`; falling behind is reported (achieved versus
  requested rate), never silent;
* **shutdown**: Ctrl-C (SIGINT) stops after the current frame; the sinks still get the summary (as
  of the last completed window) and are closed, so the .rrd is finalised and the JSON written.

Frame indices inside a replay are *replay-local*: with ``--start-offset`` the first replayed frame
is 0, and candidates that point before it are dropped. Everything else lives in its stage module.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, Literal, Protocol, Sequence

import numpy as np

from lcv_replay.config import ReplayConfig, to_dict
from lcv_replay.errors import ConfigError, ReplayError
from lcv_replay.evaluation.metrics import absolute_trajectory_error, detection_metrics, top_trajectory
from lcv_replay.evaluation.truth import LoopTruth, TruthSource, loop_truth
from lcv_replay.records import Frame, LoopCandidate
from lcv_replay.sinks.base import (
    FrameUpdate,
    RetrievalUpdate,
    RunStart,
    RunSummary,
    Sink,
    SinkGroup,
    StepMetrics,
    StepUpdate,
)
from lcv_replay.verification.base import Constraint, VerificationResult, VerifierStep
from lcv_replay.verification.config import VerificationConfig

logger = logging.getLogger(__name__)

#: The verifier used when neither ``--method`` nor the config names one: the config's default.
DEFAULT_METHOD: str = VerificationConfig.__dataclass_fields__["method"].default

ConstraintSource = Literal["images", "log", "both"]
CONSTRAINT_SOURCES: tuple[str, ...] = ("images", "log", "both")

#: Falling behind the requested rate by more than this is reported.
PACING_LAG_WARN_S = 0.5
#: While behind, the report is repeated at most this often (wall seconds).
PACING_REPORT_EVERY_S = 30.0


# --------------------------------------------------------------------------------------- options
@dataclass(frozen=True)
class ReplayOptions:
    """Everything a replay needs besides its sinks and clock.

    Attributes:
        log_path: the MCAP log.
        config: the whole configuration (``--config FILE.toml`` over the paper defaults).
        method: verifier name; ``None`` takes ``config.verification.method``.
        constraints: ``images``, ``log`` or ``both``; ``None`` follows what the log has.
        rate: 1.0 = real time by the log's timestamps; ``None`` = as fast as possible.
        start_offset_s, duration_s: the time range to replay (``None`` duration: to the end).
        seed: overrides the retrieval and verification seeds when given.
        recover: read a truncated log's complete chunks.
    """

    log_path: Path
    config: ReplayConfig = field(default_factory=ReplayConfig)
    method: str | None = None
    constraints: ConstraintSource | None = None
    rate: float | None = None
    start_offset_s: float = 0.0
    duration_s: float | None = None
    seed: int | None = None
    recover: bool = False

    def __post_init__(self) -> None:
        if self.rate is not None:
            _check_option(math.isfinite(self.rate) and self.rate > 0, "--rate", self.rate, "a number > 0, or max")
        _check_option(math.isfinite(self.start_offset_s) and self.start_offset_s >= 0, "--start-offset", self.start_offset_s, "seconds >= 0")
        if self.duration_s is not None:
            _check_option(math.isfinite(self.duration_s) and self.duration_s > 0, "--duration", self.duration_s, "seconds > 0")
        if self.constraints is not None and self.constraints not in CONSTRAINT_SOURCES:
            raise ConfigError(f"--constraints {self.constraints!r} is not allowed", fix="use images, log or both")

    def resolved_config(self) -> ReplayConfig:
        """The config with ``method`` and ``seed`` applied."""
        config = self.config
        verification = config.verification
        if self.method is not None:
            verification = dataclasses.replace(verification, method=self.method)
        retrieval = config.retrieval
        if self.seed is not None:
            verification = dataclasses.replace(verification, seed=self.seed)
            retrieval = dataclasses.replace(retrieval, seed=self.seed)
        return dataclasses.replace(config, verification=verification, retrieval=retrieval)


def _check_option(condition: bool, option: str, value: Any, expected: str) -> None:
    if not condition:
        raise ConfigError(f"{option} {value} is out of range", fix=f"pass {expected}")


def parse_rate(text: str) -> float | None:
    """``"max"`` -> ``None``; otherwise a positive number (1.0 = real time)."""
    if text.strip().lower() == "max":
        return None
    try:
        value = float(text)
    except ValueError:
        raise ConfigError(f"--rate {text!r} is not a number", fix="pass e.g. --rate 1.0, --rate 2 or --rate max") from None
    _check_option(math.isfinite(value) and value > 0, "--rate", text, "a number > 0, e.g. 1.0 for real time, or max")
    return value


def resolve_constraint_source(requested: str | None, *, has_images: bool, has_candidates: bool, path: Path) -> str:
    """Where constraints come from; refuses a request the log cannot serve.

    The default is ``log`` when the log carries ``/loop_candidates`` (a recorded place recogniser,
    e.g. g2o logs), else ``images`` (our retrieval on the left images).
    """
    if requested is None:
        if has_candidates:
            return "log"
        if has_images:
            return "images"
        raise ReplayError(
            "the log has neither images nor /loop_candidates: nothing can propose loop closures",
            path=path,
            fix="record it with images (e.g. 'lcv-replay record kitti') or with loop candidates (g2o)",
        )
    if requested in ("images", "both") and not has_images:
        raise ReplayError(
            f"--constraints {requested} needs images, but the log has none",
            path=path,
            fix="use --constraints log" if has_candidates else "record the log with images",
        )
    if requested in ("log", "both") and not has_candidates:
        raise ReplayError(
            f"--constraints {requested} needs /loop_candidates, but the log has none",
            path=path,
            fix="use --constraints images" if has_images else "record the log with loop candidates",
        )
    return requested


# --------------------------------------------------------------------------------------- clock, pacing, stop
class Clock(Protocol):
    """Monotonic time in seconds and a way to wait (a fake in tests: no real sleeps)."""

    def now(self) -> float: ...

    def sleep(self, seconds: float) -> None: ...


class SystemClock:
    """The wall clock: ``time.monotonic`` and ``time.sleep``."""

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)


@dataclass(frozen=True)
class PacingReport:
    """How a paced replay kept up: requested and achieved rate (log seconds per wall second)."""

    requested: float | None
    achieved: float | None
    max_lag_s: float
    behind_reports: int


class Pacer:
    """Paces frames to ``rate`` × their log timestamps, like ``ros2 bag play --rate``.

    Frame ``k`` is due at ``t0 + (stamp_k − stamp_0) / rate`` on the clock, where ``t0`` is when the
    first frame was released. Early frames wait; late frames are released at once and the lag is
    measured. When the lag exceeds :data:`PACING_LAG_WARN_S` a warning names the achieved and the
    requested rate (repeated every :data:`PACING_REPORT_EVERY_S` while behind).
    """

    def __init__(self, rate: float | None, clock: Clock):
        self.rate = rate
        self.clock = clock
        self._t0: float | None = None
        self._stamp0: int | None = None
        self._last_stamp: int | None = None
        self._max_lag_s = 0.0
        self._last_report: float | None = None
        self.behind_reports = 0

    def wait(self, stamp_ns: int) -> float:
        """Block until the frame stamped ``stamp_ns`` is due; returns its lag in seconds (>= 0)."""
        now = self.clock.now()
        if self._t0 is None:
            self._t0, self._stamp0 = now, int(stamp_ns)
        self._last_stamp = int(stamp_ns)
        if self.rate is None:
            return 0.0
        due = self._t0 + (int(stamp_ns) - self._stamp0) / 1e9 / self.rate
        if due > now:
            self.clock.sleep(due - now)
            return 0.0
        lag = now - due
        self._max_lag_s = max(self._max_lag_s, lag)
        if lag > PACING_LAG_WARN_S and (self._last_report is None or now - self._last_report >= PACING_REPORT_EVERY_S):
            self._last_report = now
            self.behind_reports += 1
            achieved = self.achieved_rate(now)
            logger.warning(
                "pacing cannot keep up: achieved %.2f× real time, requested %g× (%.1f s behind); "
                "lower --rate or use --rate max",
                achieved if achieved is not None else float("nan"), self.rate, lag,
            )
        return lag

    def achieved_rate(self, now: float | None = None) -> float | None:
        """Log seconds released per clock second so far."""
        if self._t0 is None or self._last_stamp is None:
            return None
        now = self.clock.now() if now is None else now
        wall = now - self._t0
        log_s = (self._last_stamp - self._stamp0) / 1e9
        return log_s / wall if wall > 0 else None

    def report(self) -> PacingReport:
        return PacingReport(self.rate, self.achieved_rate(), self._max_lag_s, self.behind_reports)


class StopToken:
    """Set by Ctrl-C (or a test) to stop the replay after the current frame."""

    def __init__(self) -> None:
        self._event = threading.Event()

    def request(self) -> None:
        self._event.set()

    @property
    def requested(self) -> bool:
        return self._event.is_set()


@contextlib.contextmanager
def sigint_requests_stop(token: StopToken) -> Iterator[None]:
    """While active, the first SIGINT sets ``token``; a second one raises ``KeyboardInterrupt``.

    Only possible in the main thread; elsewhere this does nothing (the caller's token still works).
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):  # noqa: ARG001 - signal handler signature
        if token.requested:
            raise KeyboardInterrupt
        token.request()
        logger.warning("Ctrl-C: stopping after this frame and finalising the outputs (Ctrl-C again to hurry)")

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


# --------------------------------------------------------------------------------------- frames
def frame_range(stamps_ns: np.ndarray, start_offset_s: float, duration_s: float | None) -> tuple[int, int]:
    """``[first, last)`` frame indices of ``[stamp_0 + offset, + duration)``, as the reader's window."""
    if len(stamps_ns) == 0:
        return 0, 0
    t0 = int(stamps_ns[0]) + round(start_offset_s * 1e9)
    first = int(np.searchsorted(stamps_ns, t0, "left"))
    if duration_s is None:
        return first, len(stamps_ns)
    return first, int(np.searchsorted(stamps_ns, t0 + round(duration_s * 1e9), "left"))


def rebase_candidates(candidates: Iterable[LoopCandidate], first: int) -> list[LoopCandidate]:
    """Shift candidates to replay-local indices; drops those whose match precedes the replay."""
    out = []
    for c in candidates:
        if c.match_frame < first or c.query_frame < first:
            continue
        out.append(dataclasses.replace(c, query_frame=c.query_frame - first, match_frame=c.match_frame - first))
    return out


def rebase_frame(frame: Frame, first: int) -> Frame:
    """The frame with a replay-local index and candidates (``first`` = log index of local 0)."""
    if first == 0:
        return frame
    return dataclasses.replace(
        frame,
        index=frame.index - first,
        candidates=tuple(rebase_candidates(frame.candidates, first)),
        true_loops=tuple((q - first, m - first) for q, m in frame.true_loops if m >= first),
    )


# --------------------------------------------------------------------------------------- truth
class _Truth:
    """Truth of the constraint history, grown as constraints arrive (labels or ground truth)."""

    def __init__(self, source: TruthSource, true_pairs: set[tuple[int, int]] | None, ground_truth: np.ndarray | None, radius_m: float):
        self.source = source
        self._pairs = true_pairs
        self._gt = ground_truth
        self._radius_m = radius_m
        self.flags: list[bool | None] = []

    def add(self, constraints: Sequence[Constraint]) -> tuple[bool | None, ...]:
        if not constraints:
            return ()
        pairs = [(c.query_frame, c.match_frame) for c in constraints]
        if self.source is TruthSource.LABELS:
            new = loop_truth(pairs, true_pairs=self._pairs).is_true
        elif self.source is TruthSource.GROUND_TRUTH:
            index = np.asarray(pairs, dtype=np.int64)
            finite = np.all(np.isfinite(self._gt[index.reshape(-1), :2]).reshape(-1, 4), axis=1)
            judged = loop_truth(pairs, ground_truth=np.nan_to_num(self._gt), radius_m=self._radius_m).is_true
            new = tuple(t if ok else None for t, ok in zip(judged, finite))
        else:
            new = (None,) * len(pairs)
        self.flags.extend(new)
        return tuple(new)

    def as_loop_truth(self, count: int | None = None) -> LoopTruth:
        flags = tuple(self.flags if count is None else self.flags[:count])
        return LoopTruth(self.source, flags, self._radius_m if self.source is TruthSource.GROUND_TRUTH else None)


def choose_truth_source(constraint_source: str, *, has_labels: bool, has_ground_truth: bool) -> TruthSource:
    """Labels judge the log's own candidates; retrieval's constraints are judged by ground truth.

    Labels (``/ground_truth/loops``) list the true pairs among the *recorded* candidates, so they
    judge ``--constraints log``; constraints from our retrieval (``images``/``both``) are judged by
    the ground-truth distance (< T_p) where ground truth exists, else by the labels.
    """
    if constraint_source == "log" and has_labels:
        return TruthSource.LABELS
    if has_ground_truth:
        return TruthSource.GROUND_TRUTH
    if has_labels:
        return TruthSource.LABELS
    return TruthSource.NONE


def _ate_rmse(trajectory: np.ndarray | None, ground_truth: np.ndarray | None) -> float | None:
    """SE(2)-aligned ATE over the frames that have ground truth (evaluation's function)."""
    if trajectory is None or ground_truth is None or len(trajectory) == 0:
        return None
    reference = ground_truth[: len(trajectory)]
    mask = np.all(np.isfinite(reference[:, :2]), axis=1)
    if mask.sum() < 2:
        return None
    return absolute_trajectory_error(np.asarray(trajectory)[mask], reference[mask]).rmse_m


# --------------------------------------------------------------------------------------- retrieval route
class _Retrieval:
    """Descriptor backend + incremental retriever, fed with (frame, descriptor) pairs.

    With ``retrieval.fit = "whole-log"`` (post-mortem) every descriptor of the replayed range is
    computed first (and cached), PCA and the codes are fitted on all of them, then the frames are
    replayed; with ``"online"`` (the paper) the retriever warms up on the first frames.
    """

    def __init__(self, config, log_path: Path):
        from lcv_replay.retrieval.descriptors import make_backend
        from lcv_replay.retrieval.retriever import Retriever

        self.config = config
        self.backend = make_backend(config.backend, config)
        self.retriever = Retriever(config, dim=self.backend.dim)
        self._log_path = log_path

    def _describe(self, frames: Iterable[Frame]) -> Iterator[tuple[Frame, Any]]:
        from lcv_replay.retrieval.cache import describe_frames, log_cache_key

        return describe_frames(
            frames,
            self.backend,
            cache_key=log_cache_key(self._log_path),
            cache_dir=Path(self.config.cache_dir) if self.config.cache_dir else None,
            batch_size=self.config.batch_size,
        )

    def described(self, frames_factory) -> Iterator[tuple[Frame, Any]]:
        """``(frame, descriptor | None)`` in frame order; ``frames_factory()`` gives a fresh iterator."""
        if self.config.fit != "whole-log":
            return self._describe(frames_factory())
        descriptors = {frame.index: d for frame, d in self._describe(frames_factory()) if d is not None}
        if descriptors:
            self.retriever.fit(np.stack([descriptors[i] for i in sorted(descriptors)]))
        return ((frame, descriptors.get(frame.index)) for frame in frames_factory())

    def query(self, local: Frame, descriptor: Any) -> tuple[list[LoopCandidate], RetrievalUpdate | None]:
        if descriptor is None:  # an unreadable image: the frame is skipped by retrieval
            return [], None
        output = self.retriever.add(local.index, descriptor)
        candidates = list(output.candidates)
        diag = output.diagnostics
        if diag is None:  # warming up
            return candidates, RetrievalUpdate(frame=local, candidates=tuple(candidates))
        top = tuple(diag.top)
        return candidates, RetrievalUpdate(
            frame=local,
            candidates=tuple(candidates),
            code=code_bits_msb_first(diag.code, diag.code_bits),
            prefilter_size=diag.prefilter_size,
            top_frames=np.array([c.match_frame for c in top], dtype=np.int64),
            l2_distances=np.asarray(diag.l2_distances, dtype=np.float64),
            hamming=np.array([-1 if c.hamming is None else c.hamming for c in top], dtype=np.int64),
        )


def code_bits_msb_first(code: int, code_bits: int) -> np.ndarray:
    """A packed code (bit ``k`` = ``1 << k``) as ``(code_bits,)`` bool, most significant bit first."""
    return np.array([(int(code) >> k) & 1 for k in range(code_bits - 1, -1, -1)], dtype=bool)


# --------------------------------------------------------------------------------------- the replay
@dataclass
class _Setup:
    """Everything opened and checked before the first frame (see :func:`_prepare`)."""

    reader: Any
    config: ReplayConfig
    source: str
    first: int
    verifier: Any
    retrieval: _Retrieval | None
    truth: _Truth
    start: RunStart

    def pairs(self, options: ReplayOptions) -> Iterator[tuple[Frame, Any]]:
        """``(frame, descriptor | None)`` of the replayed range, log-indexed."""

        def frames() -> Iterator[Frame]:
            return self.reader.frames(start_offset_s=options.start_offset_s, duration_s=options.duration_s)

        if self.retrieval is not None:
            return self.retrieval.described(frames)
        return ((frame, None) for frame in frames())


def _prepare(options: ReplayOptions) -> _Setup:
    """Open the log, refuse what cannot be replayed, build the verifier, retrieval and truth."""
    from lcv_replay.log.reader import open_log
    from lcv_replay.verification.registry import make_verifier

    path = Path(options.log_path)
    reader = open_log(path, recover=options.recover)
    info = reader.info
    if not info.has_odometry:
        raise ReplayError(
            "the log has no odometry (/odom): the verifier needs it",
            path=path,
            fix="record the log with odometry, or estimate it first with 'lcv-replay vo'",
        )
    source = resolve_constraint_source(
        options.constraints, has_images=info.has_images, has_candidates=info.has_candidates, path=path
    )
    config = options.resolved_config()
    stamps = reader.frame_stamps_ns
    first, last = frame_range(stamps, options.start_offset_s, options.duration_s)
    if first >= last:
        raise ReplayError(
            f"no frames in the requested time range (start offset {options.start_offset_s} s, "
            f"duration {options.duration_s} s; the log lasts {info.duration_s:.1f} s)",
            path=path,
            fix="choose --start-offset/--duration inside the log",
        )
    verifier = make_verifier(config.verification.method, config.verification, odometry_information=info.odometry_information)
    retrieval = _Retrieval(config.retrieval, path) if source in ("images", "both") else None

    ground_truth = reader.ground_truth() if info.has_ground_truth else None
    if ground_truth is not None:
        ground_truth = ground_truth[first:last]
        if not np.any(np.isfinite(ground_truth[:, 0])):
            ground_truth = None
    true_pairs = None
    if info.has_labels:
        true_pairs = {(q - first, m - first) for q, m in reader.true_loops() if m >= first}
    truth_source = choose_truth_source(source, has_labels=info.has_labels, has_ground_truth=ground_truth is not None)
    truth = _Truth(truth_source, true_pairs, ground_truth, config.verification.consistency_radius_m)
    start = RunStart(
        log_path=path,
        method=config.verification.method,
        constraint_source=source,
        rate=options.rate,
        seed=config.verification.seed,
        config=to_dict(config),
        frames=last - first,
        first_log_frame=first,
        start_ns=int(stamps[first]),
        log_duration_s=float(stamps[last - 1] - stamps[first]) / 1e9,
        log_metadata=dict(info.metadata),
        has_images=info.has_images,
        has_ground_truth=ground_truth is not None,
        truth_source=truth_source.value,
        ground_truth=ground_truth,
        code_bits=config.retrieval.active_code_bits if retrieval is not None else None,
    )
    return _Setup(reader, config, source, first, verifier, retrieval, truth, start)


def replay(
    options: ReplayOptions,
    sinks: Sequence[Sink],
    clock: Clock | None = None,
    *,
    stop: StopToken | None = None,
    handle_sigint: bool = True,
) -> RunSummary:
    """Replay ``options.log_path`` into ``sinks``; returns the run summary (also given to the sinks).

    ``clock`` paces the frames (default: the wall clock); ``stop`` (or Ctrl-C when
    ``handle_sigint``) ends the replay after the current frame with a summary as of the last
    completed window. Every sink is closed on the way out, whatever happens.

    Raises:
        LogFormatError: the log is missing or malformed.
        ReplayError: no odometry; neither images nor candidates; a frame without odometry.
        ConfigError: an unknown method or bad option.
    """
    clock = clock or SystemClock()
    stop = stop or StopToken()
    group = SinkGroup(sinks)
    with group.opened():
        setup_started = clock.now()
        setup = _prepare(options)
        start = setup.start
        group.on_start(start)
        logger.info(
            "replaying %s: %d frames (%.1f s of log), method %s, constraints from %s, rate %s",
            start.log_path, start.frames, start.log_duration_s, start.method, start.constraint_source,
            "max" if options.rate is None else f"{options.rate:g}×",
        )
        run = _Run(verifier=setup.verifier, truth=setup.truth, ground_truth=start.ground_truth, sinks=group)
        pairs = setup.pairs(options)
        setup_s = clock.now() - setup_started
        loop_started = clock.now()
        guard = sigint_requests_stop(stop) if handle_sigint else contextlib.nullcontext()
        with guard:
            interrupted, pacing = _drive(pairs, run, setup, Pacer(options.rate, clock), clock, stop, loop_started)
        wall_s = clock.now() - loop_started
        if setup.retrieval is not None and not interrupted and setup.retrieval.retriever.warmup_message():
            logger.warning("%s", setup.retrieval.retriever.warmup_message())
        if interrupted:
            logger.warning("interrupted after %d frames: summarising the last completed window", run.frames)
        if options.rate is not None and pacing.achieved is not None and pacing.achieved < 0.95 * options.rate:
            logger.warning(
                "replay ran at %.2f× real time, slower than the requested %g× (max lag %.1f s)",
                pacing.achieved, options.rate, pacing.max_lag_s,
            )
        summary = run.summary(
            start=start,
            wall_time_s=wall_s,
            setup_time_s=setup_s,
            interrupted=interrupted,
            rrd=group.recording_path,
        )
        group.on_finish(summary)
    return summary


def _drive(pairs, run: "_Run", setup: _Setup, pacer: Pacer, clock: Clock, stop: StopToken, loop_started: float) -> tuple[bool, PacingReport]:
    """The frame loop, then the verifier's final window; returns (interrupted, pacing report)."""
    pacing: PacingReport | None = None
    try:
        for frame, descriptor in pairs:
            if stop.requested:
                return True, pacer.report()
            pacer.wait(frame.stamp_ns)
            run.frame(rebase_frame(frame, setup.first), descriptor, setup.retrieval, setup.source, clock, loop_started)
            if stop.requested:
                return True, pacer.report()
        pacing = pacer.report()
        run.finish()
        return False, pacing
    except KeyboardInterrupt:  # a second Ctrl-C: stop at once, summarise what is there
        return True, pacing or pacer.report()


class _Run:
    """The per-run state of the loop: constraints, the last step, and the final answer."""

    def __init__(self, *, verifier, truth: _Truth, ground_truth: np.ndarray | None, sinks: SinkGroup):
        self.verifier = verifier
        self.truth = truth
        self.ground_truth = ground_truth
        self.sinks = sinks
        self.constraints: list[Constraint] = []
        self.frames = 0
        self.first_stamp: int | None = None
        self.last_stamp: int | None = None
        self.last_step: VerifierStep | None = None
        self.last_metrics: StepMetrics | None = None
        self.result: VerificationResult | None = None

    def frame(self, local: Frame, descriptor, retrieval: _Retrieval | None, source: str, clock: Clock, loop_started: float) -> None:
        started = clock.now()
        if local.odom is None:
            raise ReplayError(
                f"frame {local.index} (log_time {local.stamp_ns} ns) has no odometry",
                fix="re-record the log so that every frame has /odom",
            )
        if self.first_stamp is None:
            self.first_stamp = local.stamp_ns
        self.last_stamp = local.stamp_ns
        self.verifier.add_frame(local.index, local.odom)
        candidates: list[LoopCandidate] = []
        retrieval_update = None
        if retrieval is not None:
            retrieved, retrieval_update = retrieval.query(local, descriptor)
            candidates.extend(retrieved)
        if source in ("log", "both"):
            candidates.extend(local.candidates)
        new = list(self.verifier.add_candidates(candidates)) if candidates else []
        self.constraints.extend(new)
        new_truth = self.truth.add(new)
        step = self.verifier.step()
        self.frames += 1
        now = clock.now()
        self.sinks.on_frame(
            FrameUpdate(
                frame=local,
                new_constraints=tuple(new),
                new_constraint_truth=new_truth,
                constraints_total=len(self.constraints),
                wall_elapsed_s=now - loop_started,
                log_elapsed_s=(local.stamp_ns - self.first_stamp) / 1e9,
                frame_time_s=now - started,
                top_score=self.last_step.ranking[0].score if self.last_step and self.last_step.ranking else None,
            )
        )
        if retrieval_update is not None:
            self.sinks.on_retrieval(retrieval_update)
        if step is not None:
            self._emit_step(step, self.step_metrics(step))

    def step_metrics(self, step: VerifierStep) -> StepMetrics:
        arrived = sum(1 for c in self.constraints if c.arrival_frame <= step.frame_index)
        detection = detection_metrics(step.accepted_constraint_ids, self.truth.as_loop_truth(arrived))
        return StepMetrics(
            frame_index=step.frame_index,
            constraints=arrived,
            detection=detection,
            ate_rmse_m=_ate_rmse(top_trajectory(step), self.ground_truth),
            hypotheses=len(step.ranking) if step.ranking else None,
        )

    def _emit_step(self, step: VerifierStep, metrics: StepMetrics, *, final: bool = False) -> None:
        self.last_step, self.last_metrics = step, metrics
        self.sinks.on_step(
            StepUpdate(step=step, metrics=metrics, constraints=tuple(self.constraints),
                       constraint_truth=tuple(self.truth.flags), final=final)
        )

    def finish(self) -> None:
        """``Verifier.result()`` (the last, partial window) and the final step for the sinks."""
        result = self.verifier.result()
        self.result = result
        final = result.last_step
        if final is None or set(final.accepted_constraint_ids) != set(result.accepted_constraint_ids) or top_trajectory(final) is None:
            final = _step_from_result(result, self.last_step)
        detection = detection_metrics(result.accepted_constraint_ids, self.truth.as_loop_truth(len(result.constraints)))
        metrics = StepMetrics(
            frame_index=final.frame_index,
            constraints=len(result.constraints),
            detection=detection,
            ate_rmse_m=_ate_rmse(result.trajectory, self.ground_truth),
            hypotheses=len(result.ranking) if result.ranking else None,
        )
        if final is self.last_step and metrics == self.last_metrics:
            return  # the last window end was the end of the log: already with the sinks
        self._emit_step(final, metrics, final=True)

    def summary(self, *, start: RunStart, wall_time_s: float, setup_time_s: float, interrupted: bool,
                rrd: Path | None) -> RunSummary:
        metrics = self.last_metrics
        if metrics is None:  # interrupted before the first step: nothing accepted yet
            metrics = StepMetrics(
                frame_index=max(self.frames - 1, 0),
                constraints=len(self.constraints),
                detection=detection_metrics((), self.truth.as_loop_truth()),
                ate_rmse_m=None,
                hypotheses=None,
            )
        accepted_ids = tuple(sorted(self.last_step.accepted_constraint_ids)) if self.last_step else ()
        d = metrics.detection
        duration = 0.0 if self.first_stamp is None else (self.last_stamp - self.first_stamp) / 1e9
        return RunSummary(
            frames=self.frames,
            wall_time_s=wall_time_s,
            log_duration_s=duration,
            method=start.method,
            constraints=len(self.constraints),
            accepted=d.accepted,
            true_positives=d.true_positives,
            false_positives=d.false_positives,
            false_negatives=d.false_negatives,
            precision=d.precision,
            recall=d.recall,
            ate_rmse_m=metrics.ate_rmse_m,
            hypotheses=metrics.hypotheses,
            log=str(start.log_path),
            constraint_source=start.constraint_source,
            truth_source=self.truth.source.value,
            seed=start.seed,
            rate_requested=start.rate,
            setup_time_s=setup_time_s,
            interrupted=interrupted,
            accepted_constraint_ids=accepted_ids,
            rrd=None if rrd is None else str(rrd),
            config=dict(start.config),
        )


def _step_from_result(result: VerificationResult, last: VerifierStep | None) -> VerifierStep:
    """A final :class:`VerifierStep` carrying the result (for verifiers whose last step lacks it)."""
    frame_index = len(result.trajectory) - 1
    window = (last.window_index + 1) if last is not None else 0
    top_id = result.ranking[0].id if result.ranking else -1
    return VerifierStep(
        frame_index=frame_index,
        window_index=window,
        new_constraint_ids=(),
        new_hypotheses=(),
        generation_edges=(),
        ranking=tuple(result.ranking),
        accepted_constraint_ids=tuple(result.accepted_constraint_ids),
        trajectories={top_id: np.asarray(result.trajectory)},
        consistency=last.consistency if last is not None else np.zeros((0, 0), dtype=bool),
        timings_s={},
    )
