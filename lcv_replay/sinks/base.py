"""The ``Sink`` protocol and the records the replay hands to every sink.

The replay loop calls every sink the same way, in this order::

    sink.on_start(RunStart)                    # once, before the first frame
    for each frame:
        sink.on_frame(FrameUpdate)             # odometry, images, constraints admitted now
        sink.on_retrieval(RetrievalUpdate)     # only when the frame went through retrieval
        sink.on_step(StepUpdate)               # only at a verifier window end
    sink.on_finish(RunSummary)                 # once, also after Ctrl-C
    sink.close()                               # always, also after an error

The loop never asks which sinks are present (``if rerun_enabled:``); a sink ignores what it does
not need by inheriting the no-op methods of :class:`BaseSink`.

Frame indices in these records are *replay-local*: 0 is the first replayed frame (``--start-offset``
shifts it; :attr:`RunStart.first_log_frame` gives the log's index of local frame 0).
"""

from __future__ import annotations

import contextlib
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping, Protocol, Sequence

import numpy as np

from lcv_replay.evaluation.metrics import DetectionMetrics
from lcv_replay.records import Frame
from lcv_replay.verification.base import Constraint, VerifierStep

logger = logging.getLogger(__name__)

# The stable keys of ``--summary-json`` (docs/summary-json.md); unknown values are ``null``.
SUMMARY_KEYS: tuple[str, ...] = (
    "frames",
    "wall_time_s",
    "log_duration_s",
    "method",
    "constraints",
    "accepted",
    "true_positives",
    "false_positives",
    "false_negatives",
    "precision",
    "recall",
    "ate_rmse_m",
    "hypotheses",
)


@dataclass(frozen=True)
class RunStart:
    """What a sink needs to know before the first frame.

    Attributes:
        log_path: the replayed MCAP log.
        method: the verification method (``ilv``, ``ilv+``, ``gnc``, ...).
        constraint_source: where constraints come from: ``"images"``, ``"log"`` or ``"both"``.
        rate: requested replay rate (1.0 = real time), ``None`` for as fast as possible.
        seed: the seed of the run.
        config: the whole configuration as plain dicts (``lcv_replay.config.to_dict``).
        frames: number of frames in the replayed time range.
        first_log_frame: the log's index of replay-local frame 0.
        start_ns: ``log_time`` of the first replayed frame.
        log_duration_s: time span of the replayed frames by their timestamps.
        log_metadata: the log's ``lcv`` metadata record.
        has_images, has_ground_truth: what the log carries.
        truth_source: ``"labels"``, ``"ground_truth"`` or ``"none"`` (how constraints are judged).
        ground_truth: ``(frames, 3)`` ``[x_m, y_m, yaw_rad]`` of the replayed frames, or ``None``.
        code_bits: binary code length of retrieval (for the code image), if retrieval runs.
    """

    log_path: Path
    method: str
    constraint_source: str
    rate: float | None
    seed: int
    config: Mapping[str, Any]
    frames: int
    first_log_frame: int
    start_ns: int
    log_duration_s: float
    log_metadata: Mapping[str, Any] = field(default_factory=dict)
    has_images: bool = False
    has_ground_truth: bool = False
    truth_source: str = "none"
    ground_truth: np.ndarray | None = None
    code_bits: int | None = None


@dataclass(frozen=True)
class FrameUpdate:
    """One replayed frame.

    Attributes:
        frame: the frame (replay-local index; candidates shifted accordingly).
        new_constraints: constraints admitted into the history at this frame.
        new_constraint_truth: per new constraint, ``True``/``False`` by labels or ground truth,
            ``None`` when unknown.
        constraints_total: constraints in the history after this frame.
        wall_elapsed_s: wall-clock seconds since the first frame (from the replay's clock).
        log_elapsed_s: log seconds since the first frame.
        frame_time_s: wall-clock seconds spent on this frame (retrieval + verification).
        top_score: score of the rank-1 hypothesis after the latest step, if any.
    """

    frame: Frame
    new_constraints: tuple[Constraint, ...]
    new_constraint_truth: tuple[bool | None, ...]
    constraints_total: int
    wall_elapsed_s: float
    log_elapsed_s: float
    frame_time_s: float = 0.0
    top_score: int | None = None


@dataclass(frozen=True)
class RetrievalUpdate:
    """The place-recognition output for one query frame.

    Attributes:
        frame: the query frame (replay-local index).
        candidates: the retrieved candidates, best first (replay-local indices).
        code: ``(code_bits,)`` bool binary code of the query, or ``None`` (warm-up, no descriptor).
        prefilter_size: frames that passed the Hamming prefilter, or ``None``.
        top_frames: ``(K,)`` retrieved frame indices in re-rank order (replay-local).
        l2_distances: ``(K,)`` L2 distances of the re-rank, aligned with ``top_frames``.
        hamming: ``(K,)`` Hamming distances, aligned with ``top_frames``, or ``None``.
    """

    frame: Frame
    candidates: tuple[Any, ...]
    code: np.ndarray | None = None
    prefilter_size: int | None = None
    top_frames: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    l2_distances: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.float64))
    hamming: np.ndarray | None = None


@dataclass(frozen=True)
class StepMetrics:
    """Metrics after a verifier step, over the constraints arrived so far.

    ``detection`` and ``ate_rmse_m`` come from :mod:`lcv_replay.evaluation`; at the final step they
    are the run's final figures (equal to the summary's).
    """

    frame_index: int
    constraints: int
    detection: DetectionMetrics
    ate_rmse_m: float | None
    hypotheses: int | None


@dataclass(frozen=True)
class StepUpdate:
    """A verifier step (window end) with its metrics.

    Attributes:
        step: the verifier's record (ranking, trajectories, consistency, generation tree, ...).
        metrics: precision/recall/ATE after the step.
        constraints: the whole constraint history so far, by id.
        constraint_truth: per constraint id, ``True``/``False``/``None`` (unknown).
        final: ``True`` for the last step of the run (after ``Verifier.result()``).
    """

    step: VerifierStep
    metrics: StepMetrics
    constraints: Sequence[Constraint]
    constraint_truth: Sequence[bool | None]
    final: bool = False


@dataclass(frozen=True)
class RunSummary:
    """The result of a replay: the ``--summary-json`` keys plus context.

    The first thirteen fields are the stable contract (:data:`SUMMARY_KEYS`, docs/summary-json.md);
    ``None`` means unknown (no ground truth, no labels, nothing accepted, a method without
    hypotheses).
    """

    frames: int
    wall_time_s: float
    log_duration_s: float
    method: str
    constraints: int
    accepted: int
    true_positives: int | None
    false_positives: int | None
    false_negatives: int | None
    precision: float | None
    recall: float | None
    ate_rmse_m: float | None
    hypotheses: int | None
    # Context (also written to the JSON, outside the stable contract).
    log: str = ""
    constraint_source: str = ""
    truth_source: str = "none"
    seed: int = 0
    rate_requested: float | None = None
    setup_time_s: float = 0.0
    interrupted: bool = False
    accepted_constraint_ids: tuple[int, ...] = ()
    rrd: str | None = None
    config: Mapping[str, Any] = field(default_factory=dict)
    # Recall against every true revisit (lcv_replay.evaluation.revisits), where the log has ground
    # truth: frames within T_p of a frame more than Δt earlier, and how many got a true candidate
    # (proposed) and an accepted true loop (closed); revisit_recall = closed / revisits.
    revisits: int | None = None
    revisits_proposed: int | None = None
    revisits_closed: int | None = None
    revisit_recall: float | None = None

    @property
    def realtime_factor(self) -> float | None:
        """Achieved × real time: log seconds replayed per wall-clock second."""
        if self.wall_time_s <= 0.0 or self.log_duration_s <= 0.0:
            return None
        return self.log_duration_s / self.wall_time_s

    def to_json_dict(self) -> dict[str, Any]:
        """The stable keys first, then the context keys; non-finite floats become ``null``."""
        data: dict[str, Any] = {key: _json_number(getattr(self, key)) for key in SUMMARY_KEYS}
        data.update(
            x_real_time=_json_number(self.realtime_factor),
            rate_requested=_json_number(self.rate_requested),
            setup_time_s=_json_number(self.setup_time_s),
            interrupted=self.interrupted,
            log=self.log,
            rrd=self.rrd,
            constraint_source=self.constraint_source,
            truth_source=self.truth_source,
            seed=self.seed,
            accepted_constraint_ids=list(self.accepted_constraint_ids),
            config=dict(self.config),
            revisits=self.revisits,
            revisits_proposed=self.revisits_proposed,
            revisits_closed=self.revisits_closed,
            revisit_recall=_json_number(self.revisit_recall),
        )
        return data


def _json_number(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


class Sink(Protocol):
    """Receives everything the replay produces; see the module docstring for the call order.

    ``recording_path`` is the file the sink records the run into, if any (the summary names it).
    """

    recording_path: Path | None

    def on_start(self, start: RunStart) -> None: ...

    def on_frame(self, update: FrameUpdate) -> None: ...

    def on_retrieval(self, update: RetrievalUpdate) -> None: ...

    def on_step(self, update: StepUpdate) -> None: ...

    def on_finish(self, summary: RunSummary) -> None: ...

    def close(self) -> None: ...


class BaseSink:
    """No-op implementation of every :class:`Sink` method, to inherit from."""

    recording_path: Path | None = None

    def on_start(self, start: RunStart) -> None:
        pass

    def on_frame(self, update: FrameUpdate) -> None:
        pass

    def on_retrieval(self, update: RetrievalUpdate) -> None:
        pass

    def on_step(self, update: StepUpdate) -> None:
        pass

    def on_finish(self, summary: RunSummary) -> None:
        pass

    def close(self) -> None:
        pass


class SinkGroup(BaseSink):
    """Fans every call out to several sinks; :meth:`close` closes all of them even if one fails."""

    def __init__(self, sinks: Iterable[Sink]):
        self.sinks: tuple[Sink, ...] = tuple(sinks)

    @property
    def recording_path(self) -> Path | None:  # type: ignore[override]
        """The first recording file among the sinks."""
        return next((s.recording_path for s in self.sinks if s.recording_path is not None), None)

    def on_start(self, start: RunStart) -> None:
        for sink in self.sinks:
            sink.on_start(start)

    def on_frame(self, update: FrameUpdate) -> None:
        for sink in self.sinks:
            sink.on_frame(update)

    def on_retrieval(self, update: RetrievalUpdate) -> None:
        for sink in self.sinks:
            sink.on_retrieval(update)

    def on_step(self, update: StepUpdate) -> None:
        for sink in self.sinks:
            sink.on_step(update)

    def on_finish(self, summary: RunSummary) -> None:
        for sink in self.sinks:
            sink.on_finish(summary)

    def close(self) -> None:
        errors: list[BaseException] = []
        for sink in self.sinks:
            try:
                sink.close()
            except Exception as exc:  # close the others, then re-raise the first
                logger.debug("closing %r failed", sink, exc_info=True)
                errors.append(exc)
        if errors:
            raise errors[0]

    @contextlib.contextmanager
    def opened(self):
        """``with group.opened():`` closes every sink on the way out, whatever happened."""
        try:
            yield self
        finally:
            self.close()
