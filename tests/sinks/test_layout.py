"""Pure sink helpers: constraint states, the best-map estimate, anchoring, markdown, tensor rows."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lcv_replay.records import LoopCandidate
from lcv_replay.sinks.layout import (
    ancestry,
    compress_chains,
    deciding_constraints,
    tree_layout,
    ConstraintState,
    MapEstimate,
    anchor_to_first,
    constraint_states,
    flatten,
    hypotheses_markdown,
    retrieval_markdown,
    segments,
)
from lcv_replay.verification.base import Constraint, HypothesisSummary
from lcv_replay import se2


def test_constraint_states_cover_every_combination():
    truth = [True, False, None, True, False, None, True]
    states = constraint_states(7, accepted_ids=[0, 1, 2], truth=truth)
    assert states.tolist() == [
        ConstraintState.ACCEPTED,
        ConstraintState.ACCEPTED_FALSE,
        ConstraintState.ACCEPTED,
        ConstraintState.REJECTED_TRUE,
        ConstraintState.REJECTED_FALSE,
        ConstraintState.REJECTED,
        ConstraintState.REJECTED_TRUE,
    ]
    assert [ConstraintState(s).accepted for s in states] == [True, True, True, False, False, False, False]


def test_constraint_states_pending_and_short_truth():
    states = constraint_states(4, accepted_ids=[0, 3], truth=[False], judged=2)
    assert states.tolist() == [ConstraintState.ACCEPTED_FALSE, ConstraintState.REJECTED, ConstraintState.PENDING, ConstraintState.PENDING]
    assert constraint_states(0, [], []).shape == (0,)


def _odometry(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = [np.zeros(3)]
    for _ in range(n - 1):
        poses.append(se2.compose(poses[-1], np.array([1.0, rng.normal(0, 0.1), rng.normal(0, 0.1)])))
    return np.array(poses)


def test_map_estimate_before_and_after_a_step():
    odom = _odometry(30)
    est = MapEstimate()
    for pose in odom[:20]:
        est.add_odometry(pose)
    assert est.frames == 20 and est.optimised_frames == 0
    np.testing.assert_allclose(est.poses(), odom[:20])
    np.testing.assert_allclose(est.positions_of(np.array([3, 19])), odom[[3, 19], :2])

    # A step moves the first 20 frames rigidly by 5 m in x: later frames follow by odometry.
    best = odom[:20].copy()
    best[:, 0] += 5.0
    est.set_best(best)
    for pose in odom[20:]:
        est.add_odometry(pose)
    poses = est.poses()
    np.testing.assert_allclose(poses[:20], best)
    np.testing.assert_allclose(poses[20:, :2], odom[20:, :2] + [5.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(est.positions_of(np.array([25, 2])), poses[[25, 2], :2])


def test_map_estimate_grows_past_its_initial_capacity():
    est = MapEstimate()
    for k in range(3000):
        est.add_odometry((float(k), 0.0, 0.0))
    assert est.frames == 3000
    assert est.odometry[-1, 0] == 2999.0


@settings(max_examples=30, deadline=None)
@given(st.floats(-50, 50), st.floats(-50, 50), st.floats(-math.pi, math.pi))
def test_anchor_to_first_moves_the_first_pose_and_keeps_shape(x, y, yaw):
    reference = _odometry(15, seed=3)
    reference = se2.compose(np.array([10.0, -4.0, 0.7]), reference)
    anchored = anchor_to_first(reference, np.array([x, y, yaw]))
    np.testing.assert_allclose(anchored[0, :2], [x, y], atol=1e-9)
    assert math.isclose(math.remainder(anchored[0, 2] - yaw, 2 * math.pi), 0.0, abs_tol=1e-9)
    # Rigid: pairwise distances unchanged.
    d_ref = np.linalg.norm(np.diff(reference[:, :2], axis=0), axis=1)
    d_new = np.linalg.norm(np.diff(anchored[:, :2], axis=0), axis=1)
    np.testing.assert_allclose(d_new, d_ref, atol=1e-9)


def test_segments():
    positions = np.arange(20, dtype=float).reshape(10, 2)
    seg = segments(positions, np.array([[5, 1], [9, 0]]))
    assert seg.shape == (2, 2, 2)
    np.testing.assert_array_equal(seg[0], [positions[5], positions[1]])


def test_deciding_constraints_keep_what_separates_the_top_hypotheses():
    rng = np.random.default_rng(3)
    m = np.ones((4, 300), dtype=bool)  # every hypothesis holds most constraints ...
    m[:, 250:] = False  # ... none holds the last 50
    m[1, [10, 20]] = False  # rank 2 differs from rank 1 on two ...
    m[3, rng.choice(200, 30, replace=False)] = False  # ... rank 4 on thirty
    deciding = int((m != m[:1]).any(axis=0).sum())  # 32
    cols = deciding_constraints(m, rows=4, max_columns=12, context=2)
    assert len(cols) == 12 and len(set(cols.tolist())) == 12
    assert {10, 20} <= set(cols.tolist())  # what separates rank 1 from rank 2 comes first
    assert sum(m[:, c].all() for c in cols) == 0  # no room left for context
    cols = deciding_constraints(m, rows=4, max_columns=40, context=2)
    assert len(cols) == deciding + 2 and sum(m[:, c].all() for c in cols) == 2  # every deciding one, two for reference
    patterns = [tuple(m[:, c]) for c in cols]
    assert patterns == sorted(patterns, reverse=True)  # sorted by pattern, rank 1 most significant
    small = np.array([[True, False, True], [False, True, True]])
    assert sorted(deciding_constraints(small, rows=2, max_columns=10).tolist()) == [0, 1, 2]  # all fit
    assert deciding_constraints(np.zeros((0, 0), bool), rows=3, max_columns=5).size == 0


def test_ancestry_layout_and_chain_compression():
    # 0 -> 1 -> 2 -> 3 -> {4, 5}; 0 -> 6; 7 has a parent that was never reported.
    tree = {0: (None, None, 0), 1: (0, 10, 1), 2: (1, 11, 1), 3: (2, -1, 2), 4: (3, 12, 2), 5: (3, 13, 2), 6: (0, 14, 1),
            7: (99, 15, 2)}
    assert ancestry(tree, [4, 5]) == [0, 1, 2, 3, 4, 5]
    assert ancestry(tree, [7]) == [7]
    nodes = ancestry(tree, [5, 4, 6])
    parents = {n: tree[n][0] for n in nodes}
    pos = tree_layout(nodes, parents, leaves=[5, 4, 6], dx=1.0, dy=1.0)
    assert pos[0][0] == 0 and pos[5][0] == 4  # depth on x
    assert pos[5][1] < pos[4][1] < pos[6][1]  # leaves stacked in the given (rank) order
    assert pos[3][1] == (pos[4][1] + pos[5][1]) / 2  # a parent at the mean height of its children
    new_parents, chains = compress_chains(parents, {n: tree[n][1] for n in nodes}, keep=[4, 5, 6])
    assert new_parents == {0: None, 3: 0, 4: 3, 5: 3, 6: 0}  # 1 and 2 (single child, not kept) folded
    assert chains[3] == (10, 11, -1) and chains[4] == (12,) and chains[6] == (14,)


def test_markdown_tables_name_ranks_and_constraints():
    constraints = [Constraint(i, LoopCandidate(100 + i, i), 100 + i) for i in range(3)]
    ranking = (
        HypothesisSummary(id=7, parent_id=2, constraint_ids=(0, 2), score=5, rank=1, window=1, chi2=12.5),
        HypothesisSummary(id=0, parent_id=None, constraint_ids=(), score=1, rank=2, window=0),
    )
    text = hypotheses_markdown(ranking, constraints, top=10, truth=[True, True, False])
    assert "| 1 | #7 | #2 | 5 | 12.5 | 1 | 0: 100↔0, 2: 102↔2 ✗ |" in text  # ✗: labelled false
    assert "(odometry only)" in text
    keyed = (HypothesisSummary(id=7, parent_id=2, constraint_ids=(0,), score=5, rank=1, window=1, rank_key=40.25),
             HypothesisSummary(id=3, parent_id=0, constraint_ids=(1,), score=6, rank=2, window=1, rank_key=12.0))
    text = hypotheses_markdown(keyed, constraints, top=10, key_name="TLS key")
    assert "| rank | TLS key | hypothesis |" in text and "| 1 | 40.2 | #7 |" in text  # the key that ranks, shown
    table = retrieval_markdown(50, [3, 9], [0.1, 0.25], [1, 2], admitted={9})
    assert "| 2 | 9 | 0.2500 | 2 | — | yes |" in table and "| 1 | 3 | 0.1000 | 1 | — | no |" in table
    table = retrieval_markdown(50, [3, 9], [0.1, 0.25], [1, 2], admitted={9}, similarity=[0.91, None])
    assert "| 1 | 3 | 0.1000 | 1 | 0.910 | no |" in table and "| 2 | 9 | 0.2500 | 2 | — | yes |" in table
    assert flatten({"a": {"b": 1, "c": {"d": 2}}, "e": 3}) == {"a.b": 1, "a.c.d": 2, "e": 3}


@pytest.mark.parametrize("bits", [1, 20, 64, 128])
def test_code_bits_msb_first(bits):
    from lcv_replay.retrieval.stage import code_bits_msb_first

    code = (1 << (bits - 1)) | 1
    out = code_bits_msb_first(code, bits)
    assert out.shape == (bits,) and out[0] and out[-1] and out.sum() == (1 if bits == 1 else 2)


def test_position_of_matches_positions_of():
    odom = _odometry(40, seed=5)
    est = MapEstimate()
    for pose in odom[:25]:
        est.add_odometry(pose)
    assert est.position_of(7) == pytest.approx(tuple(odom[7, :2]))
    best = se2.compose(np.array([3.0, -2.0, 0.4]), odom[:25])
    est.set_best(best)
    for pose in odom[25:]:
        est.add_odometry(pose)
    for k in (0, 24, 25, 39):
        assert est.position_of(k) == pytest.approx(tuple(est.positions_of(np.array([k]))[0]), abs=1e-9)
