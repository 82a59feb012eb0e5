"""evaluation.truth: the judge of a growing constraint history, and the truth given to the oracle."""

from __future__ import annotations

import numpy as np
import pytest

from lcv_replay.errors import VerificationError
from lcv_replay.evaluation.truth import ConstraintTruth, TruthSource, provide_truth
from lcv_replay.records import LoopCandidate
from lcv_replay.verification.base import Constraint
from lcv_replay.verification.config import VerificationConfig
from lcv_replay.verification.registry import make_verifier


def _constraints(pairs):
    return [Constraint(i, LoopCandidate(q, m), q) for i, (q, m) in enumerate(pairs)]


def test_ground_truth_judges_by_distance_and_is_unknown_on_a_missing_pose():
    gt = np.zeros((6, 3))
    gt[:, 0] = [0.0, 50.0, 3.0, 100.0, np.nan, 9.0]
    truth = ConstraintTruth(TruthSource.GROUND_TRUTH, None, gt, radius_m=10.0)
    assert truth.add(_constraints([(2, 0), (3, 1)])) == (True, False)
    assert truth.add(_constraints([(4, 0), (5, 2)])) == (None, True)
    assert truth.flags == [True, False, None, True]
    assert truth.as_loop_truth(2).is_true == (True, False) and truth.as_loop_truth().radius_m == 10.0
    assert truth.is_true(5, 0) and not truth.is_true(4, 0)  # unknown is not true


def test_labels_judge_either_orientation_and_none_knows_nothing():
    labels = ConstraintTruth(TruthSource.LABELS, {(7, 2)}, None, radius_m=10.0)
    assert labels.judge([(7, 2), (2, 7), (7, 3)]) == (True, True, False)
    unknown = ConstraintTruth(TruthSource.NONE, None, None, radius_m=10.0)
    assert unknown.judge([(7, 2)]) == (None,) and unknown.as_loop_truth().known is False


def test_the_oracle_gets_the_runs_judge_and_other_methods_nothing():
    config = VerificationConfig()
    oracle = make_verifier("oracle", config)
    judge = ConstraintTruth(TruthSource.LABELS, {(30, 4)}, None, radius_m=10.0)
    provide_truth(oracle, judge, method="oracle")
    for k in range(31):
        oracle.add_frame(k, (float(k), 0.0, 0.0))
    oracle.add_candidates([LoopCandidate(30, 4), LoopCandidate(30, 9)])
    assert oracle.result().accepted_constraint_ids == (0,)
    provide_truth(make_verifier("dcs", config), ConstraintTruth(TruthSource.NONE, None, None, 10.0), method="dcs")
    with pytest.raises(VerificationError, match="method 'oracle' needs the log's true loops"):
        provide_truth(make_verifier("oracle", config), ConstraintTruth(TruthSource.NONE, None, None, 10.0), method="oracle")
