"""hypotheses: sequential selection, ranking, pruning, and hypothesis trajectories."""

from __future__ import annotations

import numpy as np
import pytest

from lcv_replay.verification.hypotheses import (
    Hypothesis,
    draw_constraint,
    odometry_root,
    prune,
    rank_order,
    selectable_constraints,
)
from lcv_replay.verification.measurements import OdometryChain, extend_by_odometry
from tests.verification.ilv_synthetic import ODOM_INFORMATION, circle_world


def _hyp(hid: int, constraints: tuple[int, ...], parent: int | None = 0) -> Hypothesis:
    return Hypothesis(hid, parent, constraints, 0, np.zeros(1, dtype=np.int64), np.zeros((1, 3)))


def test_root_may_draw_any_eligible_constraint():
    root = _hyp(0, (), parent=None)
    consistent = np.array([True, False, True, False, True])
    eligible = np.array([True, True, True, True, False])
    assert selectable_constraints(root, consistent, eligible=eligible).tolist() == [0, 1, 2, 3]


def test_child_draws_only_inconsistent_non_member_constraints():
    parent = _hyp(4, (1,))
    consistent = np.array([True, False, True, False, False, True])
    ids = selectable_constraints(parent, consistent)
    assert ids.tolist() == [3, 4]  # 1 is a member, 0/2/5 are consistent with the parent
    # never recreate a constraint set that is already kept
    ids = selectable_constraints(parent, consistent, existing_sets={frozenset({1, 3})})
    assert ids.tolist() == [4]


def test_draws_are_deterministic_for_a_seed_and_only_from_the_candidates():
    rng_a, rng_b = np.random.default_rng(7), np.random.default_rng(7)
    candidates = np.array([2, 5, 9, 11])
    draws_a = [draw_constraint(rng_a, candidates) for _ in range(50)]
    draws_b = [draw_constraint(rng_b, candidates) for _ in range(50)]
    assert draws_a == draws_b
    assert set(draws_a) <= set(candidates.tolist())
    assert len(set(draws_a)) > 1
    assert draw_constraint(rng_a, np.zeros(0, dtype=np.int64)) is None


def test_rank_order_breaks_ties_deterministically():
    keys = {0: 5.0, 1: 7.0, 2: 7.0, 3: 1.0}
    assert rank_order([3, 2, 1, 0], keys) == [1, 2, 0, 3]  # equal keys: older id first
    assert rank_order([3, 2, 1, 0], keys, {1: 2.0, 2: 1.0}) == [2, 1, 0, 3]  # then the tie key


def test_prune_keeps_the_top_ranked_and_the_root():
    ranked = [5, 3, 8, 1, 0, 7]
    kept, pruned = prune(ranked, 3)
    assert kept == [5, 3, 8] and pruned == [1, 0, 7]
    kept, pruned = prune(ranked, 3, keep={0})
    assert kept == [5, 3, 0] and pruned == [8, 1, 7]  # the root counts towards the bound
    kept, pruned = prune(ranked, 10)
    assert kept == ranked and pruned == []


def test_hypothesis_trajectory_extends_by_odometry_and_is_immutable():
    world = circle_world(frames_per_lap=50, laps=1.0)
    chain = OdometryChain(ODOM_INFORMATION)
    chain.extend(world.odom[:30])
    dense = Hypothesis(3, 0, (), 0, np.arange(30, dtype=np.int64), world.truth[:30].copy())
    chain.extend(world.odom[30:])
    np.testing.assert_allclose(dense.trajectory(chain), extend_by_odometry(world.truth[:30], world.odom), atol=1e-9)
    with pytest.raises(ValueError):
        dense.node_poses[0, 0] = 1.0
    root = odometry_root(chain)
    np.testing.assert_allclose(root.trajectory(chain), world.odom, atol=1e-9)
    assert root.is_root and root.constraint_set == frozenset()
