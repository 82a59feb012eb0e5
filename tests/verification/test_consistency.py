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


# --------------------------------------------------------------------------- pairwise cycles (ilv+)
@pytest.mark.parametrize("ends", [(2, 5, 30, 33), (5, 2, 30, 33), (2, 5, 33, 30), (3, 3, 30, 31)])
def test_cycle_d2_is_the_innovation_of_one_loop_under_the_other_and_the_odometry(ends):
    """The pairwise statistic equals GTSAM's innovation of loop 2 under {loop 1, the odometry
    between the two ends}, whatever the order of the ends."""
    import gtsam

    from lcv_replay.verification.consistency import cycle_d2
    from lcv_replay.se2 import between as se2_between, compose as se2_compose, logmap as se2_logmap
    from lcv_replay.verification.measurements import OdometryChain
    from lcv_replay.verification.pose_graph import optimise_lm, relative_covariances

    rng = np.random.default_rng(1)
    steps = np.column_stack([np.full(39, 1.0), rng.normal(0, 0.05, 39), rng.normal(0, 0.1, 39)])
    odo = np.zeros((40, 3))
    for k in range(39):
        odo[k + 1] = se2_compose(odo[k], steps[k])
    chain = OdometryChain(np.diag([100.0, 400.0, 1000.0]))
    chain.extend(odo)
    m1, m2, q1, q2 = ends
    r1, r2 = np.diag([0.01, 0.02, 0.003]), np.diag([0.02, 0.01, 0.004])
    z1 = se2_compose(se2_between(odo[m1], odo[q1]), [0.3, -0.2, 0.05])
    z2 = se2_compose(se2_between(odo[m2], odo[q2]), [-0.1, 0.25, -0.03])
    d2 = cycle_d2(chain, (np.array([m1]), np.array([m2])), (np.array([q1]), np.array([q2])), (z1[None], z2[None]), (r1[None], r2[None]))[0]

    graph = gtsam.NonlinearFactorGraph()
    keys = sorted({m1, m2, q1, q2})
    graph.add(gtsam.PriorFactorPose2(m1, gtsam.Pose2(*odo[m1]), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
    for a, b in ((m1, m2), (q1, q2)):
        lo, hi = min(a, b), max(a, b)
        if lo < hi:
            cov = chain.segment_covariance(np.array([lo]), np.array([hi]))[0]
            graph.add(gtsam.BetweenFactorPose2(lo, hi, gtsam.Pose2(*se2_between(odo[lo], odo[hi])), gtsam.noiseModel.Gaussian.Covariance(cov)))
    graph.add(gtsam.BetweenFactorPose2(m1, q1, gtsam.Pose2(*z1), gtsam.noiseModel.Gaussian.Covariance(r1)))
    solution = optimise_lm(graph, np.array([odo[k] for k in keys]), keys=keys)
    sigma = relative_covariances(graph, solution.poses, keys, np.array([m2]), np.array([q2]))[0]
    x = dict(zip(keys, solution.poses))
    r = se2_logmap(se2_between(z2, se2_between(x[m2], x[q2])))
    assert d2 == pytest.approx(mahalanobis_d2(r[None], (r2 + sigma)[None])[0], rel=1e-6)


def test_neighbour_pairs_and_connected_labels():
    from lcv_replay.verification.consistency import connected_labels, neighbour_pairs

    match = np.array([10, 11, 12, 40, 13, 300])
    query = np.array([100, 101, 102, 103, 104, 105])
    pairs = neighbour_pairs(match, query, 3)
    assert pairs.tolist() == [[0, 1], [0, 2], [1, 2], [1, 4], [2, 4]]  # 40 and 300 are far in match frames
    assert connected_labels(6, pairs).tolist() == [0, 0, 0, 1, 0, 2]
    assert connected_labels(3, np.zeros((0, 2), dtype=np.int64)).tolist() == [0, 1, 2]


def test_shared_end_pairs_are_loops_of_two_passes_over_one_place():
    from lcv_replay.verification.consistency import shared_end_pairs

    # loops 0-2 revisit frames 268-271 from 1233-1237, loop 3 from two laps later; loop 4 revisits
    # frame 500 from the query stretch of loop 0; loop 5 lies near nothing; loop 6 joins frames two
    # apart beside the others (no other pass)
    match = np.array([268, 270, 271, 270, 500, 900, 266])
    query = np.array([1233, 1235, 1237, 3417, 1234, 2000, 268])
    pairs, shared_is_query = shared_end_pairs(match, query, 10)
    found = {(min(i, j), max(i, j)): bool(shared_is_query[k, 0]) for k, (i, j) in enumerate(pairs.tolist())}
    # loops of one pass (both ends near) are not pairs; loop 4 shares the query stretch of 0-2
    assert found == {(0, 3): False, (1, 3): False, (2, 3): False, (0, 4): True, (1, 4): True, (2, 4): True}
    assert np.all(shared_is_query[:, 0] == shared_is_query[:, 1])  # here match with match, query with query
    # a match frame near another loop's query frame is a shared end too (a place passed three times)
    pairs, shared_is_query = shared_end_pairs(np.array([100, 1000]), np.array([1000 - 5 + 900, 105]), 10)
    assert pairs.tolist() == [[0, 1]] or pairs.tolist() == [[1, 0]]
    assert sorted(shared_is_query[0].tolist()) == [False, True]
    empty, flags = shared_end_pairs(np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), 10)
    assert empty.shape == (0, 2) and flags.shape == (0, 2)


def _ring_revisit(rng, *, queries, false_run=(), slips=()):
    """Two laps of a ring of 100 frames 1 m apart, and loops of the second lap to the first:
    true ones (measured with 5 cm noise) for ``queries``, and for ``false_run`` loops that claim
    the frame two along the road with the true one's measurement (a group two metres off,
    consistent among itself). ``slips``: ``(frame, metres)``, the odometry slips sideways from there."""
    from lcv_replay.se2 import between as se2_between, compose as se2_compose
    from lcv_replay.verification.measurements import OdometryChain

    angle = np.arange(200) * (2 * np.pi / 100)
    radius = 100 / (2 * np.pi)
    truth = np.column_stack([radius * np.sin(angle), radius * (1 - np.cos(angle)), angle])
    odometry = truth.copy()
    for frame, sideways_m in slips:
        odometry[frame:] = se2_compose(np.array([0.0, sideways_m, 0.0]), odometry[frame:])  # in the world frame
    chain = OdometryChain(np.diag([100.0, 100.0, 1000.0]))
    chain.extend(odometry)
    loops = [(q - 100, q) for q in queries] + [(q - 100 + 2, q) for q in false_run]
    measured = [se2_between(truth[q - 100], truth[q]) + rng.normal(0, [0.05, 0.05, 0.005]) for _, q in loops]
    match, query = (np.array(v) for v in zip(*loops))
    return chain, match, query, np.array(measured)


def test_short_cycle_runs_part_a_group_two_frames_off_the_road_from_the_revisit_around_it():
    """On the loops' own scale a false group two frames along the road inside a true revisit of
    the same stretch (ring s13587's case) is a run of its own, apart from the true loops on both
    sides, which the declared loop noise would join with it; an odometry slip parts a true
    revisit once; a loose bound joins everything."""
    from lcv_replay.verification.consistency import Cycles, short_cycle_runs

    rng = np.random.default_rng(3)
    chain, m, q, z = _ring_revisit(rng, queries=[*range(130, 140), *range(148, 161)], false_run=range(140, 148))
    labels, pairs, agree, bound = short_cycle_runs(chain, m, q, z, span_frames=4, gap_factor=4.0)
    assert 0.1 < bound < 0.5  # four times the median gap of loops measured to 5 cm
    runs = {tuple(sorted(q[labels == label].tolist())) for label in np.unique(labels)}
    assert runs == {tuple(range(130, 140)), tuple(range(140, 148)), tuple(range(148, 161))}
    assert np.all(m[np.isin(q, range(140, 148))] == np.arange(140, 148) - 98)
    # under a declared loop noise of 2 m the group's cycles with the true loops pass a 3-dof gate
    across = pairs[~agree]
    cycles = Cycles(chain, (m[across[:, 0]], m[across[:, 1]]), (q[across[:, 0]], q[across[:, 1]]), (z[across[:, 0]], z[across[:, 1]]))
    loose = np.broadcast_to(np.diag([4.0, 4.0, 0.04]), (len(across), 3, 3))
    assert len(across) > 0 and np.all(cycles.d2((loose, loose)) < 11.34)

    chain, m, q, z = _ring_revisit(rng, queries=range(130, 161), slips=[(145, 1.5)])
    labels, *_ = short_cycle_runs(chain, m, q, z, span_frames=4, gap_factor=4.0)
    assert {tuple(sorted(q[labels == label].tolist())) for label in np.unique(labels)} == {tuple(range(130, 145)), tuple(range(145, 161))}
    labels, *_ = short_cycle_runs(chain, m, q, z, span_frames=4, gap_factor=1e3)
    assert len(np.unique(labels)) == 1
    assert short_cycle_runs(chain, m[:5], q[:5], z[:5], span_frames=4, gap_factor=4.0) is None  # too few cycles for a scale
