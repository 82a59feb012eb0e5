"""Records and the ``Verifier`` protocol shared by ``ilv``, ``ilv+`` and every baseline.

The replay and the bench call every method the same way, frame by frame::

    verifier = make_verifier("ilv", config)
    for frame in frames:
        verifier.add_frame(frame.index, frame.odom)
        verifier.add_candidates(candidates_arriving_at(frame))
        step = verifier.step()          # a VerifierStep at a window end, else None
    result = verifier.result()          # solves the last, partial window

A verifier never sees the future: constraints only reference frames already added.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, NamedTuple, Protocol, Sequence, runtime_checkable

import numpy as np

from lcv_replay.errors import VerificationError
from lcv_replay.records import LoopCandidate, Pose2D
from lcv_replay.verification.measurements import as_information_matrix, loop_measurement

if TYPE_CHECKING:  # pragma: no cover
    from lcv_replay.verification.config import VerificationConfig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Constraint:
    """A loop candidate admitted into the history, with its id (0, 1, 2, ... in arrival order)."""

    id: int
    candidate: LoopCandidate
    arrival_frame: int

    @property
    def query_frame(self) -> int:
        return self.candidate.query_frame

    @property
    def match_frame(self) -> int:
        return self.candidate.match_frame


@dataclass(frozen=True)
class HypothesisSummary:
    """A hypothesis as reported to sinks (without its trajectory).

    Attributes:
        id: unique id, 0 is the odometry-only root.
        parent_id: the hypothesis it was extended from (``None`` for the root).
        constraint_ids: the constraints its pose graph optimises, in the order they were added.
        score: number of constraints in the history consistent with it (paper sec. II-A); for
            ``ilv+`` the ranking key may differ, see ``rank_key``.
        rank: 1 = best.
        window: the window index in which it was created.
        chi2: whitened chi-square of its pose-graph solution, if computed.
        rank_key: the value hypotheses are sorted by (``float(score)`` for ``ilv``).
    """

    id: int
    parent_id: int | None
    constraint_ids: tuple[int, ...]
    score: int
    rank: int
    window: int
    chi2: float | None = None
    rank_key: float = 0.0


@dataclass(frozen=True)
class VerifierStep:
    """What changed in one verifier step (a window end).

    Attributes:
        frame_index: the last frame included in this step.
        window_index: 0, 1, 2, ... (one per window of ``window_frames`` frames).
        new_constraint_ids: constraints admitted since the previous step.
        new_hypotheses: hypotheses created in this step.
        generation_edges: ``(parent_id, child_id, constraint_id)`` per new hypothesis.
        ranking: every kept hypothesis, best first.
        accepted_constraint_ids: constraints consistent with the rank-1 hypothesis (accepted).
        trajectories: ``{hypothesis_id: (N, 3) [x_m, y_m, yaw_rad]}`` for the top-k hypotheses,
            N = frame_index + 1 (extended by odometry past their last optimisation).
        consistency: ``(H, C)`` bool, rows for the first ``H`` of ``ranking`` (``H`` may be
            fewer), columns constraint ids 0..C-1.
        timings_s: seconds spent per stage in this step, e.g. ``{"optimise": .., "score": ..}``.
        dropped: ``(hypothesis_id, reason)`` for hypotheses dropped (optimiser failure, pruning).
        gate_chi2: the chi-square gate in force in this step, in the declared noise units
            (``ilv+`` calibrates it to the data); ``None`` for methods without one.
        ambiguous_constraint_ids: constraints the verifier can neither accept nor reject yet:
            mutually consistent loops that compete with other loops and explain the data about as
            well (``ilv+``). They are flagged, never accepted (disjoint from
            ``accepted_constraint_ids``); empty for methods without such a verdict.
        notes: what the step decided that its ranking does not show, one sentence each (``ilv+``:
            the loops accepted at the end of the log by a second opinion, and which one); the
            Rerun recording lists them among its events.
    """

    frame_index: int
    window_index: int
    new_constraint_ids: tuple[int, ...]
    new_hypotheses: tuple[HypothesisSummary, ...]
    generation_edges: tuple[tuple[int, int, int], ...]
    ranking: tuple[HypothesisSummary, ...]
    accepted_constraint_ids: tuple[int, ...]
    trajectories: dict[int, np.ndarray] = field(default_factory=dict)
    consistency: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), dtype=bool))
    timings_s: dict[str, float] = field(default_factory=dict)
    dropped: tuple[tuple[int, str], ...] = ()
    gate_chi2: float | None = None
    ambiguous_constraint_ids: tuple[int, ...] = ()
    notes: tuple[str, ...] = ()


@dataclass(frozen=True)
class VerificationResult:
    """The final answer of a verifier.

    Attributes:
        method: the verifier's name.
        constraints: the whole constraint history.
        accepted_constraint_ids: the accepted loop closures.
        trajectory: ``(N, 3)`` best trajectory estimate ``[x_m, y_m, yaw_rad]``.
        ranking: final hypothesis ranking (empty for batch baselines).
        paper_consistent_ids: constraints consistent with the top hypothesis under the paper's
            T_p test (sec. II-A), for the paper's own precision/recall.
        last_step: the last step (for sinks), if any.
        ambiguous_constraint_ids: constraints flagged ambiguous at the end (never accepted; see
            :attr:`VerifierStep.ambiguous_constraint_ids`).
    """

    method: str
    constraints: tuple[Constraint, ...]
    accepted_constraint_ids: tuple[int, ...]
    trajectory: np.ndarray
    ranking: tuple[HypothesisSummary, ...] = ()
    paper_consistent_ids: tuple[int, ...] = ()
    last_step: VerifierStep | None = None
    ambiguous_constraint_ids: tuple[int, ...] = ()


def result_step(result: VerificationResult, last: VerifierStep | None) -> VerifierStep:
    """A final :class:`VerifierStep` that carries ``result`` (for a verifier whose last step does
    not: a batch method that solves in ``result()``, or a last partial window)."""
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
        ambiguous_constraint_ids=tuple(result.ambiguous_constraint_ids),
    )


class Verifier(Protocol):
    """Incremental loop-closure verifier (``ilv``, ``ilv+`` and the baselines)."""

    name: str

    def add_frame(self, frame_index: int, odom: Pose2D) -> None:
        """Append frame ``frame_index`` (must be the next index) with its cumulative odometry."""

    def add_candidates(self, candidates: Sequence[LoopCandidate]) -> list[Constraint]:
        """Admit candidates into the history; returns the new constraints (after merging
        duplicates and self-loops and rejecting unknown frames)."""

    def step(self) -> VerifierStep | None:
        """Run scheduled work; returns a :class:`VerifierStep` at a window end, else ``None``."""

    def result(self) -> VerificationResult:
        """Finish (process the last partial window) and return the final result."""


#: Whether the loop ``(query_frame, match_frame)`` is known to be true.
PairTruth = Callable[[int, int], bool]


@runtime_checkable
class NeedsTruth(Protocol):
    """A verifier capability: it must be told which loops are true before its first frame.

    The ``oracle`` (only the true loops: the ATE reference) has it. The replay and ``bench verify``
    give it the truth that judges the run (:func:`lcv_replay.evaluation.truth.provide_truth`), and
    refuse the method up front where the log has neither labels nor ground truth.
    """

    def set_truth(self, is_true: PairTruth) -> None:
        """Which ``(query_frame, match_frame)`` pairs are true (frame indices as fed to the verifier)."""


def needs_truth(verifier: object) -> bool:
    """Whether ``verifier`` has the :class:`NeedsTruth` capability."""
    return isinstance(verifier, NeedsTruth)


# ----------------------------------------------------------------------------------------------
# Shared by every verifier: the constraint history, frame checks, default noise
# ----------------------------------------------------------------------------------------------


@dataclass
class AdmissionStats:
    """Counts of candidates not admitted as new constraints."""

    unknown_frames: int = 0
    self_loops: int = 0
    duplicates: int = 0


class LoopArrays(NamedTuple):
    """Every constraint of a :class:`ConstraintHistory` as arrays, in id order (what the verifiers
    vectorise over)."""

    match: np.ndarray  # (K,) match frames
    query: np.ndarray  # (K,) query frames
    measured: np.ndarray  # (K, 3) T_match_query
    information: np.ndarray  # (K, 3, 3)
    covariance: np.ndarray  # (K, 3, 3), the inverses


class ConstraintHistory:
    """The growing constraint history: ids in arrival order, duplicates and self-loops merged.

    A candidate is rejected (counted, with a warning) when it references a frame not yet added or
    is not oriented ``query_frame > match_frame``; a self-loop (``query == match``) or a pair
    already in the history is merged (dropped, counted). Its information matrix is validated on
    arrival, so a singular one is reported naming the constraint.
    """

    def __init__(self, loop_default_information: np.ndarray):
        self.loop_default_information = loop_default_information
        self.constraints: list[Constraint] = []
        self.stats = AdmissionStats()
        self._pairs: set[tuple[int, int]] = set()
        self._arrays = LoopArrays(np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3, 3)))
        self._measurements: list[tuple[Pose2D, np.ndarray]] = []  # per constraint: loop_measurement, validated on arrival

    def __len__(self) -> int:
        return len(self.constraints)

    def arrays(self) -> LoopArrays:
        """The constraints so far as :class:`LoopArrays` (extended by the ones admitted since the
        last call)."""
        start = len(self._arrays.match)
        if start < len(self.constraints):
            from lcv_replay.verification.measurements import measurement_arrays

            m, q, z, info = measurement_arrays(self.constraints[start:], self._measurements[start:])  # validated on arrival
            new = LoopArrays(m, q, z, info, np.linalg.inv(info))
            self._arrays = LoopArrays(*(np.concatenate([old, more]) for old, more in zip(self._arrays, new)))
        return self._arrays

    def admit(self, candidates: Sequence[LoopCandidate], num_frames: int) -> list[Constraint]:
        """Admit ``candidates`` given frames ``0..num_frames-1``; returns the new constraints."""
        new: list[Constraint] = []
        unknown = []
        arrival = num_frames - 1
        for cand in candidates:
            q, m = cand.query_frame, cand.match_frame
            if q == m:
                self.stats.self_loops += 1
                continue
            if not (0 <= m < q < num_frames):
                unknown.append((q, m))
                continue
            if cand.pair in self._pairs:
                self.stats.duplicates += 1
                continue
            constraint = Constraint(len(self.constraints), cand, arrival)
            measurement = loop_measurement(constraint, self.loop_default_information)  # validates Ω
            self._pairs.add(cand.pair)
            self.constraints.append(constraint)
            self._measurements.append(measurement)
            new.append(constraint)
        if unknown:
            self.stats.unknown_frames += len(unknown)
            log.warning(
                "rejected %d loop candidate(s) referencing frames outside 0..%d or not oriented "
                "query > match, e.g. (query %d, match %d)",
                len(unknown), num_frames - 1, *unknown[0],
            )
        return new


def checked_frame(name: str, frame_index: int, expected_index: int, odom: Pose2D, *, finished: bool = False) -> tuple[float, float, float]:
    """Validate :meth:`Verifier.add_frame` input; returns the odometry as ``(x_m, y_m, yaw_rad)``.

    Raises:
        VerificationError: after ``result()`` (``finished``), out of order, or non-finite odometry.
    """
    if finished:
        raise VerificationError(f"{name}: add_frame after result()", fix="build a new verifier")
    if frame_index != expected_index:
        raise VerificationError(
            f"{name}: frame {frame_index} added, expected frame {expected_index}",
            fix="feed frames in order, each exactly once",
        )
    values = (float(odom[0]), float(odom[1]), float(odom[2]))
    if not all(np.isfinite(values)):
        raise VerificationError(f"{name}: frame {frame_index} has non-finite odometry {values}")
    return values


def default_informations(config: VerificationConfig, odometry_information: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """``(odometry (3, 3), loop default (3, 3))`` information matrices for a run.

    The odometry information is the log's (g2o logs carry it), else the config's default; the
    loop information applies to candidates that carry none ("same place" from retrieval).
    """
    odom = config.odometry_information_matrix() if odometry_information is None else odometry_information
    return (
        as_information_matrix(odom, what="odometry"),
        as_information_matrix(config.loop_information_matrix(), what="default loop constraint"),
    )
