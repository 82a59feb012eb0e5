"""consistency: the paper's T_p test, Mahalanobis distances, and the append-only lookup table."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lcv_replay.errors import VerificationError
from lcv_replay.verification.consistency import ConsistencyTable, mahalanobis_d2, position_consistent


def test_position_test_on_a_hand_built_trajectory():
    # A 40 m x 40 m square driven once: frame k at the corners, T_p = 10 m.
    traj = np.array([[0, 0, 0], [40, 0, 0], [40, 40, 0], [0, 40, 0], [3, 4, 0], [0, 9.999, 0], [0, 10.0, 0]], float)
    pairs = np.array([[4, 0], [3, 0], [5, 0], [6, 0], [2, 1]])  # (query, match)
    ok = position_consistent(traj[pairs[:, 0]], traj[pairs[:, 1]], 10.0)
    # 5 m apart, 40 m, 9.999 m, exactly 10 m (not < T_p), 40 m
    assert ok.tolist() == [True, False, True, False, False]
    # the score of this "hypothesis" is the number of consistent constraints
    assert int(ok.sum()) == 2


def test_position_test_rejects_bad_shapes():
    with pytest.raises(VerificationError, match="query and match poses"):
        position_consistent(np.zeros((3, 3)), np.zeros((2, 3)), 10.0)


def test_mahalanobis_matches_explicit_inverse():
    rng = np.random.default_rng(1)
    r = rng.normal(size=(20, 3))
    a = rng.normal(size=(20, 3, 3))
    cov = a @ np.swapaxes(a, -1, -2) + 0.1 * np.eye(3)
    expected = [ri @ np.linalg.inv(ci) @ ri for ri, ci in zip(r, cov)]
    np.testing.assert_allclose(mahalanobis_d2(r, cov), expected, rtol=1e-10)
    assert mahalanobis_d2(np.zeros((0, 3)), np.zeros((0, 3, 3))).shape == (0,)


def _truth(h: int, c: int) -> bool:
    """A fixed consistency function of (hypothesis id, constraint id) for the property test."""
    return ((h * 7919 + c * 104729) % 13) < 5


operations = st.lists(
    st.one_of(
        st.tuples(st.just("hyp")),
        st.tuples(st.just("cons"), st.integers(1, 7)),
        st.tuples(st.just("prune"), st.integers(0, 50)),
    ),
    min_size=1,
    max_size=40,
)


@settings(max_examples=80, deadline=None)
@given(operations)
def test_incremental_table_equals_full_recomputation(ops):
    table = ConsistencyTable()
    next_id = 0
    computed = 0
    for op in ops:
        if op[0] == "hyp":
            c = table.num_constraints
            table.add_hypothesis(next_id, np.array([_truth(next_id, j) for j in range(c)], dtype=bool),
                                 support=np.array([float(_truth(next_id, j)) * j for j in range(c)]))
            computed += c
            next_id += 1
        elif op[0] == "cons":
            k = op[1]
            ids = table.hypothesis_ids
            first = table.num_constraints
            block = np.array([[_truth(h, first + j) for j in range(k)] for h in ids], dtype=bool).reshape(len(ids), k)
            support = block * np.arange(first, first + k)[None, :]
            table.add_constraints(ids, block, support)
            computed += len(ids) * k
        elif table.hypothesis_ids:
            ids = table.hypothesis_ids
            table.remove([ids[op[1] % len(ids)]])
    ids = table.hypothesis_ids
    full = np.array([[_truth(h, j) for j in range(table.num_constraints)] for h in ids], dtype=bool)
    full = full.reshape(len(ids), table.num_constraints)
    np.testing.assert_array_equal(table.matrix(ids), full)
    for h, row in zip(ids, full):
        assert table.score(h) == int(row.sum())
        assert table.support(h) == pytest.approx(float((row * np.arange(len(row))).sum()))
        np.testing.assert_array_equal(table.row(h), row)
    # every entry was computed exactly once, when its row or its column appeared
    assert table.entries_computed == computed


def test_table_rejects_inconsistent_updates():
    table = ConsistencyTable()
    table.add_hypothesis(0, np.zeros(0, dtype=bool))
    table.add_constraints([0], np.ones((1, 3), dtype=bool))
    with pytest.raises(VerificationError, match="already"):
        table.add_hypothesis(0, np.zeros(3, dtype=bool))
    with pytest.raises(VerificationError, match="expected"):
        table.add_hypothesis(1, np.zeros(2, dtype=bool))
    with pytest.raises(VerificationError, match="exactly the kept hypotheses"):
        table.add_constraints([0, 5], np.ones((2, 1), dtype=bool))
    with pytest.raises(VerificationError, match="not in the consistency table"):
        table.row(9)
    table.remove([0])
    assert len(table) == 0 and 0 not in table
