"""Evaluation: truth, precision/recall edge cases, SE(2) alignment, latency, per-window metrics."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lcv_replay import se2
from lcv_replay.errors import VerificationError
from lcv_replay.evaluation.metrics import (
    absolute_trajectory_error,
    acceptance_latency,
    align_se2,
    detection_metrics,
    evaluate,
    f1_score,
    window_metrics,
)
from lcv_replay.evaluation.truth import TruthSource, endpoint_distances_m, loop_truth
from lcv_replay.records import LoopCandidate
from lcv_replay.verification.base import Constraint, HypothesisSummary, VerificationResult, VerifierStep


def _truth(flags):
    pairs = [(10 + i, i) for i in range(len(flags))]
    true_pairs = [p for p, f in zip(pairs, flags) if f]
    return loop_truth(pairs, true_pairs=true_pairs)


# --------------------------------------------------------------------------- truth
def test_labels_take_precedence_over_ground_truth_and_ignore_orientation():
    gt = np.zeros((20, 3))  # every pair is 0 m apart: ground truth alone would say "true"
    truth = loop_truth([(5, 1), (7, 2)], true_pairs=[(2, 7)], ground_truth=gt)
    assert truth.source is TruthSource.LABELS
    assert truth.is_true == (False, True)


def test_empty_label_set_means_nothing_is_true():
    truth = loop_truth([(5, 1)], true_pairs=[], ground_truth=np.zeros((10, 3)))
    assert truth.is_true == (False,)
    assert truth.true_ids == frozenset()


def test_ground_truth_distance_rule_is_strictly_below_radius():
    gt = np.array([[0.0, 0.0, 0.0], [9.999, 0.0, 0.0], [0.0, 10.0, 0.0], [3.0, 4.0, 1.0]])
    truth = loop_truth([(1, 0), (2, 0), (3, 0)], ground_truth=gt, radius_m=10.0)
    assert truth.source is TruthSource.GROUND_TRUTH
    assert truth.is_true == (True, False, True)
    np.testing.assert_allclose(endpoint_distances_m([(3, 0)], gt), [5.0])


def test_unknown_truth_without_labels_or_ground_truth():
    truth = loop_truth([(3, 1), (4, 0)])
    assert truth.source is TruthSource.NONE and not truth.known
    assert truth.is_true == (None, None)
    m = detection_metrics([0], truth)
    assert m.accepted == 1
    assert (m.true_positives, m.precision, m.recall, m.f1) == (None, None, None, None)


def test_ground_truth_too_short_is_an_error():
    with pytest.raises(VerificationError, match="ground truth has 3 poses"):
        loop_truth([(5, 0)], ground_truth=np.zeros((3, 3)))


# --------------------------------------------------------------------------- precision / recall
def test_precision_recall_counts():
    truth = _truth([True, True, False, False, True])
    m = detection_metrics([0, 2, 3], truth)
    assert (m.true_positives, m.false_positives, m.false_negatives) == (1, 2, 2)
    assert m.precision == pytest.approx(1 / 3)
    assert m.recall == pytest.approx(1 / 3)
    assert m.f1 == pytest.approx(1 / 3)


def test_nothing_accepted_gives_undefined_precision_and_zero_recall():
    m = detection_metrics([], _truth([True, False]))
    assert m.precision is None
    assert m.recall == 0.0
    assert m.f1 == 0.0  # missing every true loop is not a perfect score
    assert m.false_negatives == 1


def test_no_true_candidates_gives_undefined_recall():
    m = detection_metrics([1], _truth([False, False]))
    assert m.precision == 0.0
    assert m.recall is None and m.f1 == 0.0
    m_none = detection_metrics([], _truth([False, False]))
    assert (m_none.precision, m_none.recall, m_none.f1, m_none.true_candidates) == (None, None, None, 0)


def test_f1_is_the_harmonic_mean_where_precision_and_recall_exist():
    assert f1_score(0, 0, 0) is None
    assert f1_score(3, 1, 2) == pytest.approx(2 * 0.75 * 0.6 / (0.75 + 0.6))
    m = detection_metrics([1], _truth([True, False]))
    assert (m.precision, m.recall, m.f1) == (0.0, 0.0, 0.0)


def test_accepting_an_unknown_id_is_an_error():
    with pytest.raises(VerificationError, match="not in the history"):
        detection_metrics([7], _truth([True]))


# --------------------------------------------------------------------------- ATE
def _random_walk(n, seed):
    rng = np.random.default_rng(seed)
    xy = np.cumsum(rng.normal(size=(n, 2)), axis=0)
    return np.column_stack([xy, rng.uniform(-math.pi, math.pi, n)])


@settings(max_examples=40, deadline=None)
@given(
    theta=st.floats(-math.pi + 1e-6, math.pi - 1e-6),
    tx=st.floats(-1e3, 1e3),
    ty=st.floats(-1e3, 1e3),
    seed=st.integers(0, 1000),
)
def test_alignment_recovers_a_known_rigid_transform_exactly(theta, tx, ty, seed):
    from lcv_replay.records import Pose2D

    reference = _random_walk(50, seed)
    T = Pose2D(tx, ty, theta)
    # The estimate is the reference seen from another frame: estimate = T⁻¹ · reference.
    estimate = se2.transform_points(T.inverse(), reference[:, :2])
    found = align_se2(estimate, reference[:, :2])
    assert math.isclose(math.remainder(found.yaw_rad - theta, 2 * math.pi), 0.0, abs_tol=1e-9)
    assert found.x_m == pytest.approx(tx, abs=1e-6)
    assert found.y_m == pytest.approx(ty, abs=1e-6)
    ate = absolute_trajectory_error(estimate, reference)
    assert ate.rmse_m < 1e-6


def test_ate_aligned_and_unaligned_figures():
    reference = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [3.0, 0.0]])
    shifted = reference + np.array([0.0, 2.0])
    ate = absolute_trajectory_error(shifted, reference)
    assert ate.rmse_m == pytest.approx(0.0, abs=1e-12)
    assert ate.unaligned_rmse_m == pytest.approx(2.0)
    # A residual that no rigid motion removes: the middle points bent sideways by 1 m. The bend
    # is mirror-symmetric, so the best alignment only shifts by 0.5 m: every residual is 0.5 m.
    bent = reference + np.array([[0.0, 0.0], [0.0, 1.0], [0.0, 1.0], [0.0, 0.0]])
    ate_bent = absolute_trajectory_error(bent, reference)
    assert ate_bent.rmse_m == pytest.approx(0.5, abs=1e-12)
    assert ate_bent.T_reference_estimate.yaw_rad == pytest.approx(0.0, abs=1e-12)


def test_ate_uses_the_prefix_of_a_longer_reference_and_rejects_a_shorter_one():
    reference = _random_walk(30, 1)
    assert absolute_trajectory_error(reference[:10], reference).frames == 10
    with pytest.raises(VerificationError, match="only 10"):
        absolute_trajectory_error(reference, reference[:10])
    with pytest.raises(VerificationError, match="NaN"):
        absolute_trajectory_error(np.full((3, 3), np.nan), reference)


# --------------------------------------------------------------------------- latency
def test_latency_is_first_acceptance_minus_arrival():
    arrival = {0: 100, 1: 250, 2: 300}
    history = [(499, [0]), (999, [0, 1]), (1499, [1])]
    stats = acceptance_latency(arrival, [0, 1, 2], history)
    assert [lp.latency_frames for lp in stats.loops] == [399, 749, None]
    assert stats.never_accepted == 1
    assert stats.mean_frames == pytest.approx(574.0)
    assert stats.max_frames == 749
    empty = acceptance_latency(arrival, [2], history)
    assert empty.mean_frames is None and empty.never_accepted == 1


# --------------------------------------------------------------------------- per window / whole run
def _constraints(pairs_arrivals):
    return tuple(
        Constraint(i, LoopCandidate(q, m), arrival) for i, ((q, m), arrival) in enumerate(pairs_arrivals)
    )


def test_window_metrics_only_count_constraints_arrived_so_far():
    truth = _truth([True, False, True])
    arrival = [100, 200, 700]
    step = VerifierStep(
        frame_index=499, window_index=0, new_constraint_ids=(0, 1), new_hypotheses=(),
        generation_edges=(), ranking=(HypothesisSummary(3, 0, (0,), 1, 1, 0),),
        accepted_constraint_ids=(0,), trajectories={3: np.zeros((500, 3))},
    )
    wm = window_metrics(step, truth, arrival, ground_truth=np.zeros((1000, 3)))
    assert wm.constraints == 2
    assert (wm.detection.precision, wm.detection.recall) == (1.0, 1.0)
    assert wm.ate_rmse_m == pytest.approx(0.0)


def test_evaluate_whole_run():
    constraints = _constraints([((30, 0), 30), ((40, 5), 40), ((45, 20), 45)])
    gt = np.column_stack([np.arange(50.0), np.zeros(50), np.zeros(50)])
    truth = loop_truth([c.candidate.pair for c in constraints], true_pairs=[(30, 0), (45, 20)])
    result = VerificationResult(
        method="x", constraints=constraints, accepted_constraint_ids=(0, 1),
        trajectory=gt.copy(), paper_consistent_ids=(0,),
    )
    steps = [
        VerifierStep(34, 0, (0,), (), (), (), accepted_constraint_ids=(0,)),
        VerifierStep(49, 1, (1, 2), (), (), (), accepted_constraint_ids=(0, 1)),
    ]
    m = evaluate(result, truth, ground_truth=gt, steps=steps)
    assert (m.accepted.true_positives, m.accepted.false_positives, m.accepted.false_negatives) == (1, 1, 1)
    assert (m.paper.precision, m.paper.recall) == (1.0, 0.5)
    assert m.ate is not None and m.ate.rmse_m == pytest.approx(0.0)
    assert m.latency is not None and [lp.latency_frames for lp in m.latency.loops] == [4, None]
    assert [w.constraints for w in m.windows] == [1, 3]
    with pytest.raises(VerificationError, match="truth covers"):
        evaluate(result, truth.restricted(2))


def test_frames_without_ground_truth_are_unknown_and_skipped():
    gt = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [np.nan, np.nan, np.nan], [3.0, 0.0, 0.0]])
    truth = loop_truth([(1, 0), (2, 0), (3, 0)], ground_truth=gt, radius_m=2.0)
    assert truth.is_true == (True, None, False)
    # The unknown constraint counts neither as a true nor as a false positive.
    m = detection_metrics([0, 1], truth)
    assert (m.true_positives, m.false_positives, m.precision, m.recall) == (1, 0, 1.0, 1.0)
    ate = absolute_trajectory_error(np.nan_to_num(gt) + [5.0, 0.0, 0.0], gt)
    assert ate.frames == 3 and ate.rmse_m == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(VerificationError, match="no finite pose"):
        absolute_trajectory_error(np.zeros((2, 3)), np.full((2, 3), np.nan))
