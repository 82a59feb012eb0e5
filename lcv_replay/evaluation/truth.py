"""Truth of loop-closure constraints: from labels, else from ground-truth poses, else unknown.

The rule of :func:`loop_truth`:

1. if the log carries true-loop labels (``/ground_truth/loops``), a constraint is true exactly when
   its ``(query_frame, match_frame)`` pair is labelled;
2. otherwise, where ground-truth poses exist, it is true when its endpoints are closer than
   ``radius_m`` (the paper's T_p = 10 m, sec. II-A) in the ground truth (unknown where a frame
   has no ground-truth pose, a NaN row);
3. otherwise its truth is unknown, and every metric that needs it is ``None``.

A replay judges its constraints as they arrive (:class:`ConstraintTruth`), with the source that
:func:`choose_truth_source` picks for where the constraints come from. Pure functions over pairs
and arrays; nothing here reads a file.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Iterable, Sequence

import numpy as np

from lcv_replay.errors import VerificationError
from lcv_replay.verification.base import needs_truth

if TYPE_CHECKING:  # pragma: no cover
    from lcv_replay.records import Frame
    from lcv_replay.verification.base import Constraint


class TruthSource(str, Enum):
    """Where the truth of the constraints came from."""

    LABELS = "labels"
    GROUND_TRUTH = "ground_truth"
    NONE = "none"


@dataclass(frozen=True)
class LoopTruth:
    """Truth of every constraint of a history, indexed by constraint id (0..C-1).

    Attributes:
        source: labels, ground-truth distance, or none (every entry unknown).
        is_true: per constraint id, ``True``/``False``, or ``None`` when unknown.
        radius_m: the distance threshold used with ``source == GROUND_TRUTH``.
    """

    source: TruthSource
    is_true: tuple[bool | None, ...]
    radius_m: float | None = None

    @property
    def known(self) -> bool:
        """Whether the truth of every constraint is known (labels or ground truth)."""
        return self.source is not TruthSource.NONE

    @property
    def true_ids(self) -> frozenset[int]:
        """Ids of the constraints known to be true."""
        return frozenset(i for i, t in enumerate(self.is_true) if t is True)

    @property
    def false_ids(self) -> frozenset[int]:
        """Ids of the constraints known to be false."""
        return frozenset(i for i, t in enumerate(self.is_true) if t is False)

    def __len__(self) -> int:
        return len(self.is_true)

    def restricted(self, count: int) -> "LoopTruth":
        """The truth of the first ``count`` constraints (those arrived by some frame)."""
        return LoopTruth(self.source, self.is_true[:count], self.radius_m)


def normalise_pair(a: int, b: int) -> tuple[int, int]:
    """``(later, earlier)``: the orientation of :attr:`LoopCandidate.pair`."""
    return (int(a), int(b)) if a >= b else (int(b), int(a))


def endpoint_distances_m(pairs: Sequence[tuple[int, int]], ground_truth: np.ndarray) -> np.ndarray:
    """Ground-truth distance between the two frames of each pair.

    Args:
        pairs: ``C`` frame index pairs.
        ground_truth: ``(N, 2)`` or ``(N, 3)`` ground-truth poses ``[x_m, y_m(, yaw_rad)]``.

    Returns:
        ``(C,)`` float64 distances in metres.
    """
    ground_truth = np.asarray(ground_truth, dtype=np.float64)
    if ground_truth.ndim != 2 or ground_truth.shape[1] < 2:
        raise VerificationError(
            f"ground truth must be an (N, 2) or (N, 3) array, got shape {ground_truth.shape}",
            fix="pass one [x_m, y_m, yaw_rad] row per frame",
        )
    index = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if index.size and (index.min() < 0 or index.max() >= len(ground_truth)):
        raise VerificationError(
            f"a constraint references frame {int(index.max())} but the ground truth has "
            f"{len(ground_truth)} poses",
            fix="pass the ground truth of the whole log",
        )
    xy = ground_truth[:, :2]
    return np.linalg.norm(xy[index[:, 0]] - xy[index[:, 1]], axis=1)


def loop_truth(
    pairs: Sequence[tuple[int, int]],
    *,
    true_pairs: Iterable[tuple[int, int]] | None = None,
    ground_truth: np.ndarray | None = None,
    radius_m: float = 10.0,
) -> LoopTruth:
    """Truth of each constraint ``pairs[i]`` (constraint id ``i``).

    Args:
        pairs: ``C`` ``(query_frame, match_frame)`` pairs, in constraint-id order.
        true_pairs: the labelled true pairs, or ``None`` when the log has no labels. An empty
            collection means "labelled, and no candidate is true".
        ground_truth: ``(N, 2|3)`` ground-truth poses, or ``None``.
        radius_m: T_p, the ground-truth distance below which an unlabelled pair is true.
    """
    if true_pairs is not None:
        labelled = {normalise_pair(a, b) for a, b in true_pairs}
        return LoopTruth(
            TruthSource.LABELS, tuple(normalise_pair(a, b) in labelled for a, b in pairs)
        )
    if ground_truth is not None:
        distances = endpoint_distances_m(pairs, ground_truth)
        return LoopTruth(
            TruthSource.GROUND_TRUTH,
            tuple(None if not np.isfinite(d) else bool(d < radius_m) for d in distances),
            radius_m,
        )
    return LoopTruth(TruthSource.NONE, (None,) * len(pairs))


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


class ConstraintTruth:
    """Truth of a constraint history, grown as the constraints arrive.

    Args:
        source: how constraints are judged (see :func:`choose_truth_source`).
        true_pairs: the labelled true pairs (used with ``LABELS``).
        ground_truth: ``(N, 3)`` ground-truth poses, NaN rows where a frame has none (used with
            ``GROUND_TRUTH``); a pair touching a NaN row is unknown.
        radius_m: T_p, the ground-truth distance below which a pair is true.

    The labels and poses may also arrive frame by frame (:meth:`observe`, in frame order, after
    what was given): the replay feeds them so, and a log still being written is judged like a
    finished one.
    """

    def __init__(self, source: TruthSource, true_pairs: Iterable[tuple[int, int]] | None, ground_truth: np.ndarray | None, radius_m: float):
        self.source = source
        self._pairs = set(true_pairs or ())
        given = np.zeros((0, 3)) if ground_truth is None else np.asarray(ground_truth, dtype=np.float64).reshape(-1, 3)
        self._gt = np.concatenate([given, np.full((max(1024, len(given)), 3), np.nan)])  # NaN beyond; capacity doubles
        self._frames = len(given)
        self._any_gt = bool(np.isfinite(given[:, 0]).any())
        self._radius_m = radius_m
        self.flags: list[bool | None] = []

    def observe(self, frame: "Frame") -> None:
        """Take the labels and the ground-truth pose of the next frame (its index is the next row)."""
        self._pairs.update(frame.true_loops)
        if self._frames == len(self._gt):
            self._gt = np.concatenate([self._gt, np.full_like(self._gt, np.nan)])
        gt = frame.ground_truth
        if gt is not None and np.isfinite(gt.x_m):
            self._gt[self._frames] = (gt.x_m, gt.y_m, gt.yaw_rad)
            self._any_gt = True
        self._frames += 1

    @property
    def ground_truth(self) -> np.ndarray | None:
        """``(frames, 3)`` ground truth so far (NaN rows where unknown), or ``None`` when none is known."""
        return self._gt[: self._frames] if self._any_gt else None

    def judge(self, pairs: Sequence[tuple[int, int]]) -> tuple[bool | None, ...]:
        """Truth of ``(query_frame, match_frame)`` pairs, ``None`` where unknown (no state change)."""
        if not pairs:
            return ()
        if self.source is TruthSource.LABELS:
            return loop_truth(pairs, true_pairs=self._pairs).is_true
        if self.source is TruthSource.GROUND_TRUTH:
            index = np.asarray(pairs, dtype=np.int64)
            gt = self._gt  # rows beyond the frames seen are NaN: unknown
            if index.max() >= len(gt):
                gt = np.concatenate([gt, np.full((int(index.max()) + 1 - len(gt), 3), np.nan)])
            finite = np.all(np.isfinite(gt[index.reshape(-1), :2]).reshape(-1, 4), axis=1)
            judged = loop_truth(pairs, ground_truth=np.nan_to_num(gt), radius_m=self._radius_m).is_true
            return tuple(t if ok else None for t, ok in zip(judged, finite))
        return (None,) * len(pairs)

    def is_true(self, query_frame: int, match_frame: int) -> bool:
        """Whether one pair is known to be true."""
        return self.judge([(query_frame, match_frame)])[0] is True

    def add(self, constraints: Sequence["Constraint"]) -> tuple[bool | None, ...]:
        """Judge the constraints that just arrived (in id order) and keep their flags."""
        new = self.judge([(c.query_frame, c.match_frame) for c in constraints])
        self.flags.extend(new)
        return new

    def as_loop_truth(self, count: int | None = None) -> LoopTruth:
        """The flags so far (or of the first ``count`` constraints) as a :class:`LoopTruth`."""
        flags = tuple(self.flags if count is None else self.flags[:count])
        return LoopTruth(self.source, flags, self._radius_m if self.source is TruthSource.GROUND_TRUTH else None)


def provide_truth(verifier: object, truth: ConstraintTruth, *, method: str, path: Path | None = None) -> None:
    """Give a verifier that needs the truth (:class:`~lcv_replay.verification.base.NeedsTruth`,
    the oracle) the truth that judges the run; nothing for any other verifier.

    Raises:
        VerificationError: the verifier needs the truth but the run has none (no labels, no
            ground truth); raised before the first frame.
    """
    if not needs_truth(verifier):
        return
    if truth.source is TruthSource.NONE:
        raise VerificationError(
            f"method '{method}' needs the log's true loops, but the log has neither labels nor ground truth",
            path=path,
            fix="record the log with --true-loops or --ground-truth, or choose another method",
        )
    verifier.set_truth(truth.is_true)  # type: ignore[attr-defined]
