"""The replay engine: a log's frames through retrieval and incremental verification, into sinks.

``replay(options, sinks, clock)`` wires the stages and owns only three things of its own:

* **routing**: left images go to retrieval, the log's ``/loop_candidates`` go straight to the
  verifier, or both (``--constraints images|log|both``; the default follows what the log has);
  odometry always goes to the verifier, which runs its window steps as frames arrive;
* **pacing**, as ``ros2 bag play``: ``rate`` 1.0 is real time by the log's timestamps, ``None`` as
  fast as possible (the :class:`~lcv_replay.pacing.Pacer`, against an injectable clock); falling
  behind is reported (achieved versus requested rate), never silent;
* **shutdown**: Ctrl-C (SIGINT) or SIGTERM stops after the current frame; the sinks still get the
  summary (as of the last completed window) and are closed, so the .rrd is finalised and the JSON
  written. A second signal aborts at once and the sinks remove their temp files
  (:mod:`lcv_replay.shutdown`).

Frame indices inside a replay are *replay-local*: with ``--start-offset`` the first replayed frame
is 0, and candidates that point before it are dropped. The reader computes the time window once
(a :class:`~lcv_replay.records.FrameWindow`) and every rebase goes through it. Everything else
lives in its stage module: truth in :mod:`lcv_replay.evaluation.truth`, the retrieval stage in
:mod:`lcv_replay.retrieval.stage`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Iterator, Literal, Sequence

import numpy as np

from lcv_replay.config import ReplayConfig, to_dict
from lcv_replay.errors import ConfigError, ReplayError, VerificationError, require_seed
from lcv_replay.evaluation.metrics import ate_rmse_m, detection_metrics, top_trajectory
from lcv_replay.evaluation.revisits import RevisitRecall, revisit_recall
from lcv_replay.evaluation.truth import ConstraintTruth, choose_truth_source, provide_truth
from lcv_replay.pacing import Clock, Pacer, PacingReport, SystemClock
from lcv_replay.records import Frame, FrameWindow, LoopCandidate
from lcv_replay.shutdown import StopToken, stop_on_signals
from lcv_replay.sinks.base import FrameUpdate, RunStart, RunSummary, Sink, SinkGroup, StepMetrics, StepUpdate
from lcv_replay.verification.base import Constraint, Verifier, VerifierStep, result_step
from lcv_replay.verification.config import VerificationConfig

if TYPE_CHECKING:  # pragma: no cover
    from lcv_replay.log.reader import LogReader
    from lcv_replay.retrieval.stage import RetrievalStage

logger = logging.getLogger(__name__)

#: The verifier used when neither ``--method`` nor the config names one: the config's default.
DEFAULT_METHOD: str = VerificationConfig.__dataclass_fields__["method"].default

ConstraintSource = Literal["images", "log", "both"]
CONSTRAINT_SOURCES: tuple[str, ...] = ("images", "log", "both")

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
        open_reader: how to open the log, ``open_reader(path, recover=...)``; ``None`` is
            :func:`lcv_replay.log.reader.open_log`. A reader mode such as the follower of a log
            still being written (:func:`lcv_replay.log.follow.follow_log`) plugs in here; the
            replay cannot tell the difference.
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
    open_reader: Any = None

    def __post_init__(self) -> None:
        if self.rate is not None:
            _check_option(math.isfinite(self.rate) and self.rate > 0, "--rate", self.rate, "a number > 0, or max")
        _check_option(math.isfinite(self.start_offset_s) and self.start_offset_s >= 0, "--start-offset", self.start_offset_s, "seconds >= 0")
        if self.duration_s is not None:
            _check_option(math.isfinite(self.duration_s) and self.duration_s > 0, "--duration", self.duration_s, "seconds > 0")
        if self.seed is not None:
            require_seed(self.seed, "--seed")
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


# --------------------------------------------------------------------------------------- shutdown
#: The first SIGINT *or SIGTERM* sets the token; a second aborts (:func:`lcv_replay.shutdown.stop_on_signals`).
sigint_requests_stop = stop_on_signals


# --------------------------------------------------------------------------------------- the replay
@dataclass
class _Setup:
    """Everything opened and checked before the first frame (see :func:`_prepare`)."""

    reader: LogReader
    config: ReplayConfig
    source: str
    window: FrameWindow
    verifier: Verifier
    retrieval: RetrievalStage | None
    truth: ConstraintTruth
    start: RunStart

    def pairs(self) -> Iterator[tuple[Frame, np.ndarray | None]]:
        """``(frame, descriptor | None)`` of the window, rebased to replay-local indices (the
        descriptor cache is keyed by log index, so frames are described before the rebase)."""

        def frames() -> Iterator[Frame]:
            return self.reader.frames(window=self.window)

        described = self.retrieval.described(frames) if self.retrieval is not None else ((f, None) for f in frames())
        return ((self.window.frame(frame), descriptor) for frame, descriptor in described)


def _prepare(options: ReplayOptions) -> _Setup:
    """Open the log, refuse what cannot be replayed, build the verifier, retrieval and truth."""
    from lcv_replay.log.reader import open_log
    from lcv_replay.retrieval.stage import RetrievalStage
    from lcv_replay.verification.config import with_loop_kind
    from lcv_replay.verification.registry import make_verifier

    path = Path(options.log_path)
    reader = (options.open_reader or open_log)(path, recover=options.recover)
    info = reader.info
    if info.recorder_warnings:
        from lcv_replay.log.format import describe_warnings

        logger.warning("%s was recorded with warnings: %s", path, describe_warnings(info.recorder_warnings))
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
    # ilv+ verifies our retrieval's same-place loops and a log's measured loops with different verifiers
    config = dataclasses.replace(config, verification=with_loop_kind(config.verification, same_place=source in ("images", "both")))
    window = reader.window(options.start_offset_s, options.duration_s)
    if window.frames == 0:
        raise ReplayError(
            f"no frames in the requested time range (start offset {options.start_offset_s} s, "
            f"duration {options.duration_s} s; the log lasts {info.duration_s:.1f} s)",
            path=path,
            fix="choose --start-offset/--duration inside the log",
        )
    verifier = make_verifier(config.verification.method, config.verification, odometry_information=info.odometry_information)
    if info.growing and config.retrieval.fit == "whole-log":
        raise ReplayError(
            "retrieval.fit = 'whole-log' needs the whole log before the first frame, but the log is still being written",
            path=path,
            fix="use retrieval.fit = 'online' (the paper's) to follow a log",
        )
    # A file still being written has no content hash yet: no descriptor cache.
    retrieval = RetrievalStage(config.retrieval, path, cache=not info.growing) if source in ("images", "both") else None

    ground_truth = window.rows(reader.ground_truth()) if info.has_ground_truth else None
    if ground_truth is not None and not np.any(np.isfinite(ground_truth[:, 0])):
        ground_truth = None
    truth_source = choose_truth_source(source, has_labels=info.has_labels, has_ground_truth=ground_truth is not None)
    # Labels and ground truth reach the truth with their frames (_Run.frame): a log still being
    # written is judged like a finished one.
    truth = ConstraintTruth(truth_source, None, None, config.verification.consistency_radius_m)
    provide_truth(verifier, truth, method=config.verification.method, path=path)  # the oracle, or refused here
    stamps = window.rows(reader.frame_stamps_ns)
    start = RunStart(
        log_path=path, method=config.verification.method, constraint_source=source, rate=options.rate,
        seed=config.verification.seed, config=to_dict(config), frames=window.frames, first_log_frame=window.first,
        start_ns=int(stamps[0]), log_duration_s=float(stamps[-1] - stamps[0]) / 1e9, log_metadata=dict(info.metadata),
        has_images=info.has_images, has_ground_truth=ground_truth is not None, truth_source=truth_source.value,
        ground_truth=ground_truth, code_bits=config.retrieval.active_code_bits if retrieval is not None else None,
    )
    return _Setup(reader, config, source, window, verifier, retrieval, truth, start)


def replay(
    options: ReplayOptions,
    sinks: Sequence[Sink],
    clock: Clock | None = None,
    *,
    stop: StopToken | None = None,
    handle_sigint: bool = True,
) -> RunSummary:
    """Replay ``options.log_path`` into ``sinks``; returns the run summary (also given to the sinks).

    ``clock`` paces the frames (default: the wall clock); ``stop`` (or Ctrl-C or SIGTERM when
    ``handle_sigint``) ends the replay after the current frame with a summary as of the last
    completed window; ``stop.exit_code`` then says which signal it was. A second signal raises
    :class:`~lcv_replay.shutdown.Interrupted`. Every sink is closed on the way out, whatever
    happens.

    Raises:
        LogFormatError: the log is missing or malformed.
        ReplayError: no odometry; neither images nor candidates; a frame without odometry.
        ConfigError: an unknown method or bad option.
    """
    clock = clock or SystemClock()
    stop = stop or StopToken()
    group = SinkGroup(sinks)
    # The handlers stay until the sinks are closed: a first signal while the outputs are finalised
    # still lets them finish; a second aborts (Interrupted) and the sinks drop their temp files.
    guard = stop_on_signals(stop) if handle_sigint else contextlib.nullcontext()
    with guard, group.opened():
        setup_started = clock.now()
        setup = _prepare(options)
        start = setup.start
        group.on_start(start)
        logger.info(
            "replaying %s: %d frames (%.1f s of log), method %s, constraints from %s, rate %s",
            start.log_path, start.frames, start.log_duration_s, start.method, start.constraint_source,
            "max" if options.rate is None else f"{options.rate:g}×",
        )
        run = _Run(setup, group, clock)
        pairs = setup.pairs()
        setup_s = clock.now() - setup_started
        run.loop_started = clock.now()
        interrupted, pacing = _drive(pairs, run, Pacer(options.rate, clock), stop)
        wall_s = clock.now() - run.loop_started
        if setup.retrieval is not None and not interrupted and setup.retrieval.warmup_message():
            logger.warning("%s", setup.retrieval.warmup_message())
        if interrupted:
            logger.warning("interrupted after %d frames: summarising the last completed window", run.frames)
        pacing.warn_if_slow()
        summary = run.summary(wall_time_s=wall_s, setup_time_s=setup_s, interrupted=interrupted, rrd=group.recording_path)
        group.on_finish(summary)
    return summary


def _drive(pairs: Iterable[tuple[Frame, np.ndarray | None]], run: _Run, pacer: Pacer, stop: StopToken) -> tuple[bool, PacingReport]:
    """The frame loop, then the verifier's final window; returns (interrupted, pacing report).

    A numerical breakdown of the verifier (degenerate odometry or constraints in the log) is one
    :class:`VerificationError` naming the frame, not a traceback.
    """
    try:
        for frame, descriptor in pairs:
            if stop.requested:
                return True, pacer.report()
            pacer.wait(frame.stamp_ns)
            run.frame(frame, descriptor)
            if stop.requested:
                return True, pacer.report()
        if stop.requested:  # the frames ended because of the stop (a follower waiting for data)
            return True, pacer.report()
        pacing = pacer.report()
        run.finish()
        return False, pacing
    except np.linalg.LinAlgError as exc:
        raise VerificationError(
            f"the verifier failed numerically after {run.frames} frames ({exc}): the log's odometry or loop "
            "constraints are degenerate",
            path=run.setup.start.log_path,
            fix="check them with 'lcv-replay info', or try another --method",
        ) from None


class _Run:
    """The per-run state of the loop: constraints, the last step, and the final answer."""

    def __init__(self, setup: _Setup, sinks: SinkGroup, clock: Clock):
        self.setup = setup
        self.verifier: Verifier = setup.verifier
        self.truth = setup.truth
        self.sinks = sinks
        self.clock = clock
        self.loop_started = clock.now()
        self.constraints: list[Constraint] = []
        self.frames = 0
        self.first_stamp: int | None = None
        self.last_stamp: int | None = None
        self.last_step: VerifierStep | None = None
        self.last_metrics: StepMetrics | None = None

    def frame(self, local: Frame, descriptor: np.ndarray | None) -> None:
        """Feed one replay-local frame: odometry, candidates (retrieval and/or the log), a step."""
        started = self.clock.now()
        if local.odom is None:
            raise ReplayError(
                f"frame {local.index} (log_time {local.stamp_ns} ns) has no odometry",
                fix="re-record the log so that every frame has /odom",
            )
        if self.first_stamp is None:
            self.first_stamp = local.stamp_ns
        self.last_stamp = local.stamp_ns
        self.truth.observe(local)
        self.verifier.add_frame(local.index, local.odom)
        candidates: list[LoopCandidate] = []
        retrieval_update = None
        if self.setup.retrieval is not None:
            retrieved, retrieval_update = self.setup.retrieval.query(local, descriptor)
            candidates.extend(retrieved)
        if self.setup.source in ("log", "both"):
            candidates.extend(local.candidates)
        new = list(self.verifier.add_candidates(candidates)) if candidates else []
        self.constraints.extend(new)
        new_truth = self.truth.add(new)
        step = self.verifier.step()
        self.frames += 1
        now = self.clock.now()
        self.sinks.on_frame(
            FrameUpdate(
                frame=local,
                new_constraints=tuple(new),
                new_constraint_truth=new_truth,
                constraints_total=len(self.constraints),
                wall_elapsed_s=now - self.loop_started,
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
        return self._metrics(step.frame_index, arrived, step.accepted_constraint_ids, top_trajectory(step), step.ranking)

    def _metrics(self, frame_index: int, arrived: int, accepted_ids: Sequence[int], trajectory: np.ndarray | None,
                 ranking: Sequence[object]) -> StepMetrics:
        """Metrics over the first ``arrived`` constraints (those arrived by ``frame_index``)."""
        return StepMetrics(
            frame_index=frame_index,
            constraints=arrived,
            detection=detection_metrics(accepted_ids, self.truth.as_loop_truth(arrived)),
            ate_rmse_m=ate_rmse_m(trajectory, self.truth.ground_truth),
            hypotheses=len(ranking) if ranking else None,
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
        final = result.last_step
        if final is None or set(final.accepted_constraint_ids) != set(result.accepted_constraint_ids) or top_trajectory(final) is None:
            final = result_step(result, self.last_step)
        metrics = self._metrics(final.frame_index, len(result.constraints), result.accepted_constraint_ids, result.trajectory, result.ranking)
        if final is self.last_step and metrics == self.last_metrics:
            return  # the last window end was the end of the log: already with the sinks
        self._emit_step(final, metrics, final=True)

    def summary(self, *, wall_time_s: float, setup_time_s: float, interrupted: bool, rrd: Path | None) -> RunSummary:
        start = self.setup.start
        metrics = self.last_metrics
        if metrics is None:  # interrupted before the first step: nothing accepted yet
            metrics = self._metrics(max(self.frames - 1, 0), len(self.constraints), (), None, ())
        accepted_ids = tuple(sorted(self.last_step.accepted_constraint_ids)) if self.last_step else ()
        d = metrics.detection
        duration = 0.0 if self.first_stamp is None else (self.last_stamp - self.first_stamp) / 1e9
        revisits = self._revisits(accepted_ids)
        return RunSummary(  # the stable keys (docs/summary-json.md), then the context
            frames=self.frames, wall_time_s=wall_time_s, log_duration_s=duration, method=start.method,
            constraints=len(self.constraints), accepted=d.accepted, true_positives=d.true_positives,
            false_positives=d.false_positives, false_negatives=d.false_negatives, precision=d.precision,
            recall=d.recall, ate_rmse_m=metrics.ate_rmse_m, hypotheses=metrics.hypotheses,
            log=str(start.log_path), constraint_source=start.constraint_source, truth_source=self.truth.source.value,
            seed=start.seed, rate_requested=start.rate, setup_time_s=setup_time_s, interrupted=interrupted,
            accepted_constraint_ids=accepted_ids, rrd=None if rrd is None else str(rrd), config=dict(start.config),
            revisits=None if revisits is None else revisits.revisits,
            revisits_proposed=None if revisits is None else revisits.proposed,
            revisits_closed=None if revisits is None else revisits.closed,
            revisit_recall=None if revisits is None else revisits.recall,
        )

    def _revisits(self, accepted_ids: Sequence[int]) -> RevisitRecall | None:
        """Recall against every ground-truth revisit of the frames replayed (None without ground truth)."""
        if self.truth.ground_truth is None or self.frames == 0:
            return None
        config = self.setup.config
        return revisit_recall(
            np.asarray(self.truth.ground_truth)[: self.frames, :2],
            [c.query_frame for c in self.constraints],
            self.truth.flags[: len(self.constraints)],
            accepted_ids,
            radius_m=config.verification.consistency_radius_m,
            exclusion_frames=config.retrieval.exclusion_frames,
        )
