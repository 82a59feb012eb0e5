"""Accepted-loop precision/recall, ATE with SE(2) alignment, latency, per-window metrics.

Pure functions over ids, arrays and the verifier's records. ``None`` marks a figure that is
undefined (precision with nothing accepted, recall with no true candidate, anything needing truth
that the log does not carry), so that JSON reports write ``null`` rather than a made-up 0 or 1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Collection, Mapping, Sequence

import numpy as np

from lcv_replay import se2
from lcv_replay.errors import VerificationError
from lcv_replay.evaluation.truth import LoopTruth, TruthSource
from lcv_replay.records import Pose2D
from lcv_replay.verification.base import VerificationResult, VerifierStep


# --------------------------------------------------------------------------- precision / recall
@dataclass(frozen=True)
class DetectionMetrics:
    """Precision and recall of a set of accepted constraints against their truth.

    ``true_positives``/``false_positives``/``false_negatives`` are ``None`` when the truth is
    unknown; ``precision`` is ``None`` when nothing is accepted, ``recall`` when no candidate is
    true, ``f1`` (see :func:`f1_score`) only when both are.
    """

    accepted: int
    true_candidates: int | None
    true_positives: int | None
    false_positives: int | None
    false_negatives: int | None
    precision: float | None
    recall: float | None
    f1: float | None


def f1_score(true_positives: int, false_positives: int, false_negatives: int) -> float | None:
    """``2 TP / (2 TP + FP + FN)``, the harmonic mean of precision and recall where both exist.

    It stays defined when only one of them is: nothing accepted while some candidate is true gives
    0 (not a perfect score), accepting a false loop where no candidate is true gives 0. It is
    ``None`` only when nothing is accepted and nothing is true.
    """
    denominator = 2 * true_positives + false_positives + false_negatives
    return 2.0 * true_positives / denominator if denominator else None


def detection_metrics(accepted_ids: Collection[int], truth: LoopTruth) -> DetectionMetrics:
    """Precision = TP / (TP + FP) over ``accepted_ids``; recall = TP / (number of true candidates).

    Args:
        accepted_ids: accepted constraint ids (duplicates are counted once).
        truth: the truth of every constraint in the history (ids ``0..len(truth)-1``).
    """
    accepted = {int(i) for i in accepted_ids}
    unknown_ids = [i for i in accepted if i < 0 or i >= len(truth)]
    if unknown_ids:
        raise VerificationError(
            f"accepted constraint id {unknown_ids[0]} is not in the history of {len(truth)} constraints",
            fix="evaluate a result against the truth of its own constraint history",
        )
    if truth.source is TruthSource.NONE:
        return DetectionMetrics(len(accepted), None, None, None, None, None, None, None)
    true_ids = truth.true_ids
    tp = len(accepted & true_ids)
    fp = len(accepted & truth.false_ids)  # accepted constraints of unknown truth count as neither
    fn = len(true_ids) - tp
    precision = tp / (tp + fp) if tp + fp else None
    recall = tp / len(true_ids) if true_ids else None
    return DetectionMetrics(len(accepted), len(true_ids), tp, fp, fn, precision, recall, f1_score(tp, fp, fn))


# --------------------------------------------------------------------------- ATE
@dataclass(frozen=True)
class AteResult:
    """Absolute trajectory error of the positions.

    Attributes:
        rmse_m: RMSE after the best SE(2) alignment of the estimate onto the reference.
        unaligned_rmse_m: RMSE in the estimate's own frame (both start at the log's origin).
        T_reference_estimate: the aligning transform (applied to the estimate).
        frames: number of poses compared (frames with a ground-truth pose).
    """

    rmse_m: float
    unaligned_rmse_m: float
    T_reference_estimate: Pose2D
    frames: int


def _positions(name: str, array: np.ndarray) -> np.ndarray:
    array = np.asarray(array, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] not in (2, 3):
        raise VerificationError(
            f"{name} must be an (N, 2) or (N, 3) array, got shape {array.shape}",
            fix="pass one [x_m, y_m(, yaw_rad)] row per frame",
        )
    if not np.all(np.isfinite(array[:, :2])):
        raise VerificationError(f"{name} contains NaN or inf positions", fix="check the trajectory")
    return array[:, :2]


def align_se2(estimate_xy: np.ndarray, reference_xy: np.ndarray) -> Pose2D:
    """Closed-form least-squares rigid alignment in 2-D (Kabsch/Umeyama without scale).

    Finds ``T = (R(θ), t)`` minimising ``Σ ||R e_i + t − r_i||²``.

    Args:
        estimate_xy: ``(N, 2)`` positions to move.
        reference_xy: ``(N, 2)`` target positions.

    Returns:
        ``T_reference_estimate`` as a :class:`Pose2D` (``x_m, y_m`` = t, ``yaw_rad`` = θ).
    """
    e = _positions("estimate", estimate_xy)
    r = _positions("reference", reference_xy)
    if len(e) != len(r) or len(e) == 0:
        raise VerificationError(
            f"cannot align {len(e)} estimated poses with {len(r)} reference poses",
            fix="compare trajectories of the same, non-zero length",
        )
    e_mean, r_mean = e.mean(axis=0), r.mean(axis=0)
    ec, rc = e - e_mean, r - r_mean
    # θ maximises Σ r_c · R e_c = cosθ Σ(ex rx + ey ry) + sinθ Σ(ex ry − ey rx).
    theta = math.atan2(float(np.sum(ec[:, 0] * rc[:, 1] - ec[:, 1] * rc[:, 0])), float(np.sum(ec * rc)))
    t = r_mean - se2.transform_points((0.0, 0.0, theta), e_mean[None, :])[0]
    return Pose2D(float(t[0]), float(t[1]), theta)


def absolute_trajectory_error(estimate: np.ndarray, reference: np.ndarray) -> AteResult:
    """ATE RMSE of the positions after SE(2) alignment, plus the un-aligned figure.

    Args:
        estimate: ``(N, 2|3)`` estimated poses.
        reference: ``(N, 2|3)`` ground-truth poses; the first ``N`` rows are used if it is longer
            (the estimate of a replay cut short); rows that are NaN (frames without ground
            truth) are skipped.
    """
    e = _positions("estimate", estimate)
    r = np.asarray(reference, dtype=np.float64)
    if r.ndim != 2 or r.shape[1] not in (2, 3):
        raise VerificationError(f"reference must be an (N, 2) or (N, 3) array, got shape {r.shape}")
    if len(r) < len(e):
        raise VerificationError(
            f"the estimate has {len(e)} poses but the ground truth only {len(r)}",
            fix="pass the ground truth of the whole log",
        )
    r = r[: len(e), :2]
    known = np.all(np.isfinite(r), axis=1)  # frames without a ground-truth pose are skipped
    if not known.any():
        raise VerificationError("the ground truth has no finite pose to compare with", fix="check the log's ground truth")
    e, r = e[known], r[known]
    T = align_se2(e, r)
    aligned = se2.transform_points(T, e)
    rmse = float(np.sqrt(np.mean(np.sum((aligned - r) ** 2, axis=1))))
    unaligned = float(np.sqrt(np.mean(np.sum((e - r) ** 2, axis=1))))
    return AteResult(rmse, unaligned, T, len(e))


# --------------------------------------------------------------------------- latency
@dataclass(frozen=True)
class LoopLatency:
    """When one true loop arrived and when it was first accepted (``None``: never)."""

    constraint_id: int
    arrival_frame: int
    accepted_frame: int | None

    @property
    def latency_frames(self) -> int | None:
        return None if self.accepted_frame is None else self.accepted_frame - self.arrival_frame


@dataclass(frozen=True)
class LatencyStats:
    """Frames between each true loop's arrival and its first acceptance.

    ``mean_frames``/``median_frames``/``max_frames`` are over the loops that were accepted
    (``None`` if none was); ``never_accepted`` counts the others.
    """

    loops: tuple[LoopLatency, ...]
    mean_frames: float | None
    median_frames: float | None
    max_frames: int | None
    never_accepted: int


def acceptance_latency(
    arrival_frames: Mapping[int, int],
    true_ids: Collection[int],
    accepted_history: Sequence[tuple[int, Collection[int]]],
) -> LatencyStats:
    """Latency of each true loop, from the accepted set after each verifier step.

    Args:
        arrival_frames: constraint id -> frame at which it arrived.
        true_ids: ids of the true constraints.
        accepted_history: ``(frame_index, accepted_ids)`` per step, in frame order.
    """
    first_accepted: dict[int, int] = {}
    for frame_index, accepted in accepted_history:
        for cid in accepted:
            first_accepted.setdefault(int(cid), int(frame_index))
    loops = tuple(
        LoopLatency(cid, int(arrival_frames[cid]), first_accepted.get(cid))
        for cid in sorted(int(i) for i in true_ids)
    )
    latencies = [lp.latency_frames for lp in loops if lp.latency_frames is not None]
    never = sum(1 for lp in loops if lp.accepted_frame is None)
    if not latencies:
        return LatencyStats(loops, None, None, None, never)
    return LatencyStats(loops, float(np.mean(latencies)), float(np.median(latencies)), int(max(latencies)), never)


# --------------------------------------------------------------------------- per window
@dataclass(frozen=True)
class WindowMetrics:
    """Metrics after one verifier step, over the constraints that had arrived by then.

    ``ate_rmse_m`` is over the frames so far, of the top hypothesis's trajectory, when the step
    carries it and the ground truth exists.
    """

    window_index: int
    frame_index: int
    constraints: int
    detection: DetectionMetrics
    ate_rmse_m: float | None


def ate_rmse_m(trajectory: np.ndarray | None, ground_truth: np.ndarray | None) -> float | None:
    """SE(2)-aligned ATE RMSE over the frames that have ground truth; ``None`` without a trajectory,
    without ground truth, or with fewer than two frames that have both.

    Args:
        trajectory: ``(M, 3)`` estimate of frames ``0..M-1``.
        ground_truth: ``(N >= M, 3)`` ground truth, NaN rows where a frame has none.
    """
    if trajectory is None or ground_truth is None or len(trajectory) == 0:
        return None
    reference = ground_truth[: len(trajectory)]
    mask = np.all(np.isfinite(reference[:, :2]), axis=1)
    if mask.sum() < 2:
        return None
    return absolute_trajectory_error(np.asarray(trajectory)[mask], reference[mask]).rmse_m


def top_trajectory(step: VerifierStep) -> np.ndarray | None:
    """The rank-1 hypothesis's ``(N, 3)`` trajectory from a step, if the step carries it."""
    if step.ranking and step.ranking[0].id in step.trajectories:
        return step.trajectories[step.ranking[0].id]
    if len(step.trajectories) == 1:
        return next(iter(step.trajectories.values()))
    return None


def window_metrics(
    step: VerifierStep,
    truth: LoopTruth,
    arrival_frames: Sequence[int],
    ground_truth: np.ndarray | None = None,
) -> WindowMetrics:
    """Metrics of one :class:`VerifierStep`.

    Args:
        step: the step.
        truth: truth of the whole constraint history (ids in arrival order).
        arrival_frames: ``(C,)`` arrival frame of each constraint id.
        ground_truth: ``(N, 2|3)`` ground truth of the whole log, or ``None``.
    """
    arrived = int(np.searchsorted(np.asarray(arrival_frames), step.frame_index, side="right"))
    detection = detection_metrics(step.accepted_constraint_ids, truth.restricted(arrived))
    ate = None
    trajectory = top_trajectory(step)
    if ground_truth is not None and trajectory is not None and len(trajectory) > 0:
        ate = absolute_trajectory_error(trajectory, ground_truth).rmse_m
    return WindowMetrics(step.window_index, step.frame_index, arrived, detection, ate)


# --------------------------------------------------------------------------- whole run
@dataclass(frozen=True)
class Metrics:
    """Every figure of one verification run.

    Attributes:
        truth_source: labels, ground truth or none.
        candidates: constraints in the history.
        accepted: the metrics of the accepted loops.
        paper: the paper's own precision/recall over the constraints consistent with the top
            hypothesis under the T_p test (sec. II-A), ``result.paper_consistent_ids``.
        ate: ``None`` without ground truth.
        latency: ``None`` without truth or without per-step accepted sets.
        windows: per-step metrics, in frame order.
    """

    truth_source: TruthSource
    candidates: int
    accepted: DetectionMetrics
    paper: DetectionMetrics
    ate: AteResult | None
    latency: LatencyStats | None
    windows: tuple[WindowMetrics, ...] = ()


def evaluate(
    result: VerificationResult,
    truth: LoopTruth,
    *,
    ground_truth: np.ndarray | None = None,
    steps: Sequence[VerifierStep] = (),
) -> Metrics:
    """All metrics of a :class:`VerificationResult` (and its steps, for latency and per window)."""
    if len(truth) != len(result.constraints):
        raise VerificationError(
            f"the truth covers {len(truth)} constraints but the result has {len(result.constraints)}",
            fix="compute the truth from the result's own constraint history",
        )
    accepted = detection_metrics(result.accepted_constraint_ids, truth)
    paper = detection_metrics(result.paper_consistent_ids, truth)
    ate = None
    if ground_truth is not None and len(result.trajectory) > 0:
        ate = absolute_trajectory_error(result.trajectory, ground_truth)
    arrival = [c.arrival_frame for c in result.constraints]
    history = [(s.frame_index, s.accepted_constraint_ids) for s in steps]
    last_frame = len(result.trajectory) - 1
    if not history or history[-1][0] != last_frame or set(history[-1][1]) != set(result.accepted_constraint_ids):
        history.append((last_frame, result.accepted_constraint_ids))
    latency = None
    if truth.known:
        latency = acceptance_latency(dict(enumerate(arrival)), truth.true_ids, history)
    windows = tuple(window_metrics(s, truth, arrival, ground_truth) for s in steps)
    return Metrics(truth.source, len(truth), accepted, paper, ate, latency, windows)
