"""ilv+ (lcv_replay.verification.consensus): clusters, contests, the ambiguous verdict, and the
generated world with grouped outliers that the previous ilv+ failed."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest

from lcv_replay import se2
from lcv_replay.records import LoopCandidate, Pose2D
from lcv_replay.verification.config import VerificationConfig
from lcv_replay.verification.consensus import ConsensusVerifier, Fate
from lcv_replay.se2 import between as se2_between, compose as se2_compose
from lcv_replay.verification.registry import make_verifier
from tests.verification.ilv_synthetic import ODOM_INFORMATION, circle_world
from tests.verification.helpers import SMALL, candidates_by_query, feed, feed_frames

MEASURED = (100.0, 0.0, 0.0, 100.0, 0.0, 10000.0)  # sigma 10 cm, 10 cm, 0.01 rad
CONFIG = VerificationConfig(window_frames=100)


def _loop(world, query: int, match: int, *, T_match_query=None) -> LoopCandidate:
    """A loop measured with the noise it declares (``MEASURED``), seeded by its frames."""
    rel = se2_between(world.truth[match], world.truth[query]) if T_match_query is None else np.asarray(T_match_query)
    noise = np.random.default_rng([query, match]).normal(0.0, [0.1, 0.1, 0.01])
    return LoopCandidate(query, match, T_match_query=Pose2D(*se2_compose(rel, noise)), information=MEASURED, source="synthetic")


def _run(world, candidates, config=CONFIG):
    verifier = make_verifier("ilv+", config, odometry_information=ODOM_INFORMATION)
    assert isinstance(verifier, ConsensusVerifier)
    steps = feed_frames(verifier, world.odom, candidates_by_query(candidates))
    return verifier, steps, verifier.result()


def test_a_group_of_false_loops_is_refused_and_every_true_loop_accepted():
    """Ten mutually consistent false loops (a Vertigo group) against a lap of true loops."""
    world = circle_world(frames_per_lap=200, laps=2.0, true_every=2, num_false=0, yaw_bias_rad=0.0002)
    true = [_loop(world, q, q - 200) for q in range(205, 400, 2)]
    group = [_loop(world, q, q - 150, T_match_query=(0.05, -0.02, 0.01)) for q in range(300, 310)]
    verifier, steps, result = _run(world, true + group)
    constraints = result.constraints
    accepted = {constraints[i].candidate.pair for i in result.accepted_constraint_ids}
    assert accepted == {c.pair for c in true}
    assert not result.ambiguous_constraint_ids
    for step in steps:
        assert not set(step.accepted_constraint_ids) & set(step.ambiguous_constraint_ids)


def test_the_bound_queries_no_marginal_for_loops_that_cannot_prove_a_cluster_implausible(monkeypatch):
    """The window's bound (``_implausible_now``) queries iSAM2's marginals (milliseconds each on a
    city-scale graph) only for members that some marginal could make fail: no marginal raises a
    member's statistic above its value under the loop's own covariance, so a cluster that fits
    is let through with no query (grouped city10000: 527 queries -> 96 for the clusters that
    were not proven), and a false loop is still proven implausible."""
    world = circle_world(frames_per_lap=200, laps=2.0, true_every=2, num_false=0, yaw_bias_rad=0.0002)
    true = [_loop(world, q, q - 200) for q in range(205, 400, 2)]
    verifier, _, result = _run(world, true)
    accepted = np.asarray(result.accepted_constraint_ids)
    assert len(accepted) == len(true)

    def no_query(frame):
        raise AssertionError(f"marginal of frame {frame} queried")

    monkeypatch.setattr(verifier.graph, "marginal_covariance", no_query)
    verifier._fresh_marginals = set()  # as at a new window: no marginal queried yet
    for cluster in {int(verifier._cluster_of[c]) for c in accepted}:
        members = verifier.clusters[cluster].members
        assert not verifier._implausible_now(members)  # a cluster that fits: no query
    monkeypatch.undo()
    # a loop 40 m off: proven, under the remembered marginals or the current ones
    m, q = int(verifier._m[accepted[0]]), int(verifier._q[accepted[0]])
    verifier._z = verifier._z.copy()
    verifier._z[accepted[0]] = se2_compose(verifier._z[accepted[0]], np.array([40.0, 0.0, 0.0]))
    assert verifier._implausible_now(accepted[:1])
    assert (m, q) == (int(verifier._m[accepted[0]]), int(verifier._q[accepted[0]]))


def test_the_leave_out_statistic_of_a_revisit_is_the_rise_its_loops_cause_together():
    """The audit's leave-out statistic (``left_out_d2``), taken over a loop's revisit as over the
    loop alone, is the rise of the chi-square that the loops cause together (linear-Gaussian):
    each loop of a consistent false group fits once the group has bent the map and, left out
    alone, is still held by the others; only the group left out shows it. Checked against GTSAM
    solves of the map with and without them."""
    from scipy.stats import chi2

    from lcv_replay.verification.consistency import left_out_d2
    from lcv_replay.verification.pose_graph import IncrementalGraph, LoopFactor, add_loop_factors, build_graph, optimise_lm

    world = circle_world(frames_per_lap=200, laps=2.0, true_every=2, num_false=0, yaw_bias_rad=0.0002)
    info = np.diag([100.0, 100.0, 10000.0])
    true = [LoopFactor(q - 200, q, se2_between(world.truth[q - 200], world.truth[q]), info) for q in range(205, 400, 6) if not 310 < q < 370]
    group = [LoopFactor(q - 200, q, se2_compose(se2_between(world.truth[q - 200], world.truth[q]), np.array([1.5, 0.75, 0.03])), info) for q in (340, 342, 344)]
    graph = IncrementalGraph(ODOM_INFORMATION)
    graph.extend(world.odom)
    graph.update(add=list(enumerate(true + group)))
    x = graph.estimate()

    def solved_chi2(loops):
        batch = build_graph(world.odom, ODOM_INFORMATION, [], loop_default_information=info)
        add_loop_factors(batch, loops)
        return optimise_lm(batch, x, relative_error_tol=1e-10).chi2

    def left_out(loops):
        m, q = np.array([f.match_frame for f in loops]), np.array([f.query_frame for f in loops])
        r = se2.between_residuals(x, m, q, np.array([f.measured for f in loops]))
        return left_out_d2(r, np.array([np.linalg.inv(f.information) for f in loops]), graph.joint_relative_covariance(m, q))

    stacked = graph.joint_relative_covariance(np.array([f.match_frame for f in group]), np.array([f.query_frame for f in group]))
    for k, loop in enumerate(group):  # its diagonal blocks: each loop's own
        np.testing.assert_allclose(stacked[3 * k : 3 * k + 3, 3 * k : 3 * k + 3], graph.relative_covariance(loop.match_frame, loop.query_frame), rtol=1e-9, atol=1e-12)
    together = left_out(group)
    assert together == pytest.approx(solved_chi2(true + group) - solved_chi2(true), rel=0.05)
    alone = [left_out([f]) for f in group]
    assert max(alone) < chi2.ppf(0.99, 3) < chi2.ppf(0.99, 9) < together  # alone, each hides behind the others
    # the only evidence for its relative pose: nothing to test it against
    lone = LoopFactor(20, 180, se2_between(world.truth[20], world.truth[180]), np.diag([1e12, 1e12, 1e14]))
    graph.update(add=[(999, lone)])
    assert left_out([lone]) is None


def test_the_solved_credit_counts_a_gate_a_loop_less_the_rise_and_solves_nothing_it_cannot_use(monkeypatch):
    """``_solved_credit``: true loops left out of the map and solved back with it save about a
    gate each (less the chi-square they raise); where the loops left could not reach the credit
    asked for even at a gate each, no batch solve is made (each is a solve of the whole map,
    1 to 3 s on a 2,000-pose graph), and a false group solved with the map earns nothing. Each
    solve is made loose first, and converged only where every loop fits and the credit is within
    reach with half the loose rise."""
    world = circle_world(frames_per_lap=200, laps=2.0, true_every=2, num_false=0, yaw_bias_rad=0.0002)
    true = [_loop(world, q, q - 200) for q in range(205, 400, 2)]
    group = [_loop(world, q, q - 150, T_match_query=(0.05, -0.02, 0.01)) for q in range(300, 310)]
    verifier, _, result = _run(world, true + group)
    pairs = [c.candidate.pair for c in result.constraints]
    accepted = np.asarray(result.accepted_constraint_ids)
    assert {pairs[i] for i in accepted} == {c.pair for c in true}
    left_out = accepted[10:20]
    rest = accepted[~np.isin(accepted, left_out)]
    x = verifier.graph.estimate()
    without = verifier._batch_solution(rest, x)
    solves = []
    batch = ConsensusVerifier._batch_solution
    monkeypatch.setattr(ConsensusVerifier, "_batch_solution", lambda v, loops, initial, **kw: solves.append((len(loops), kw.get("relative_error_tol"))) or batch(v, loops, initial, **kw))
    gate, loose = verifier.gate_chi2, ConsensusVerifier.CREDIT_TOLERANCE
    credit, loops = verifier._solved_credit(rest, left_out, without, needed=gate)
    assert loops == 10 and 0.75 * 10 * gate < credit < 10 * gate  # true loops raise the chi-square by about their noise
    assert solves == [(len(accepted), loose), (len(accepted), None)]  # every one fits the loose solve, which is then converged
    converged = without.chi2 + 10 * gate - credit
    rise = batch(verifier, accepted, without.poses, relative_error_tol=loose).chi2 - without.chi2
    assert rise >= converged - without.chi2 - 1e-6  # the loose solve stopped at an earlier iterate of the same run
    solves.clear()
    assert verifier._solved_credit(rest, left_out, without, needed=10 * gate + 1) == (0.0, 0)
    assert solves == []  # ten loops cannot save more than ten gates
    assert verifier._solved_credit(rest, left_out, without, needed=10 * gate - ConsensusVerifier.CREDIT_RISE_SLACK * rise + 1e-3) == (0.0, 0)
    assert solves == [(len(accepted), loose)]  # out of reach even with half the loose rise: not converged
    false = np.array([i for i, pair in enumerate(pairs) if pair in {c.pair for c in group}])
    assert len(false) == 10 and not np.isin(false, accepted).any()
    final = verifier._batch_solution(accepted, x)
    solves.clear()
    assert verifier._solved_credit(accepted, false, final, needed=gate) == (0.0, 0)
    assert 1 <= len(solves) <= ConsensusVerifier.CREDIT_SOLVES
    assert all(tol == loose for _, tol in solves)  # it never fitted: no solve converged


def test_the_audit_reuses_earlier_marginals_for_its_passes_and_queries_current_ones_for_its_failures(monkeypatch):
    """The audit's leave-out tests first use a revisit's joint marginal queried at an earlier
    window (it bounds the current one: a pass under it is a pass now), and a test that fails
    under one queries the current marginal, which decides: the verdicts are those of current
    marginals, with fewer queries of iSAM2's Bayes tree."""
    from lcv_replay.verification import pose_graph

    world = circle_world(frames_per_lap=200, laps=3.0, true_every=2, num_false=0, yaw_bias_rad=0.0002)
    true = [_loop(world, q, q - 200) for q in range(205, 600, 2)]
    group = [_loop(world, q, q - 150, T_match_query=(0.05, -0.02, 0.01)) for q in range(300, 310)]
    queries = []
    joint_marginal = pose_graph.IncrementalGraph.joint_marginal
    monkeypatch.setattr(pose_graph.IncrementalGraph, "joint_marginal", lambda graph, frames: queries.append(frames) or joint_marginal(graph, frames))
    verifier, _, result = _run(world, true + group)
    with_earlier = len(queries)
    assert {result.constraints[i].candidate.pair for i in result.accepted_constraint_ids} == {c.pair for c in true}

    covariance = ConsensusVerifier._audit_covariance
    monkeypatch.setattr(ConsensusVerifier, "_audit_covariance", lambda v, members, *, earlier: covariance(v, members, earlier=False))
    queries.clear()
    _, _, current = _run(world, true + group)
    assert current.accepted_constraint_ids == result.accepted_constraint_ids
    assert with_earlier < len(queries)
    monkeypatch.undo()

    # a loop of a revisit whose marginal is remembered, moved 2 m: it fails under the earlier
    # marginal, so the current one is queried, and the loop leaves the hypothesis
    accepted = verifier._ids(Fate.ACCEPTED)
    c = int(accepted[len(accepted) // 2])
    revisit = verifier._revisit_of(np.array([c]), accepted)
    tested = revisit if 1 < len(revisit) <= verifier.AUDIT_REVISIT_LOOPS else np.array([c])  # a long revisit: the loop alone
    verifier._audit_covariance(tested, earlier=True)
    assert verifier._audit_covariance(tested, earlier=True)[1]  # remembered
    verifier._z = verifier._z.copy()
    verifier._z[c] = se2_compose(verifier._z[c], np.array([2.0, 0.0, 0.0]))
    queries.clear()
    monkeypatch.setattr(pose_graph.IncrementalGraph, "joint_marginal", lambda graph, frames: queries.append(frames) or joint_marginal(graph, frames))
    assert verifier._audit_suspects(verifier.graph.estimate(), accepted, np.array([c])) == [c]
    assert len(queries) == 1  # the current marginal, queried once the earlier one had failed it
    verifier._audit()
    assert verifier._fate[c] != Fate.ACCEPTED and c not in verifier.graph.loop_ids


def test_the_revisit_of_a_loop_is_the_transitive_closure_of_nearness():
    """``_revisit_of`` grows a set of loops by the accepted loops near any of them (both ends
    within a cluster span), round by round, testing only what the last round added: the same set
    as the closure computed by brute force, on random loops that chain across several spans."""
    verifier = make_verifier("ilv+", CONFIG, odometry_information=ODOM_INFORMATION)
    span = verifier.plus.cluster_span_frames
    rng = np.random.default_rng(7)
    chained = 0  # draws whose closure took three rounds or more
    for _ in range(30):
        n = 120
        verifier._q = np.sort(rng.integers(0, 40 * span, n))
        verifier._m = np.clip(verifier._q // 3 + rng.integers(-span, span, n), 0, None)
        accepted = np.sort(rng.choice(n, 90, replace=False))
        members = rng.choice(n, 2, replace=False)
        near = (np.abs(verifier._q[:, None] - verifier._q[None, :]) <= span) & (np.abs(verifier._m[:, None] - verifier._m[None, :]) <= span)
        closure, rounds = set(members.tolist()), 0
        while True:
            grown = closure | {int(a) for a in accepted if any(near[a, b] for b in closure)}
            if grown == closure:
                break
            closure, rounds = grown, rounds + 1
        chained += rounds >= 3
        revisit = verifier._revisit_of(members, accepted)
        assert revisit.tolist() == sorted(closure)
    assert chained >= 10


def test_no_hypothesis_is_built_largest_first_where_every_refused_part_is_proven_implausible(monkeypatch):
    """At the end of the log the hypothesis built largest first tries the refused parts that its
    graph does not prove implausible; where none is left, it could hold only the working
    hypothesis' loops, and the run of those is not tried again (grouped city10000: about 2 s)."""
    world = circle_world(frames_per_lap=200, laps=2.0, true_every=2, num_false=0, yaw_bias_rad=0.0002)
    # a dense revisit, and a sparse one whose loops are parts smaller than the refused group
    true = [_loop(world, q, q - 200) for q in [*range(205, 330, 2), *range(355, 400, 15)]]
    # a group 5 frames off the sparse revisit, its relative poses 0.3 rad off: the screen lets
    # it through, its trial refuses it, and the final map proves it implausible
    group = [_loop(world, q, q - 195, T_match_query=se2_compose(se2_between(world.truth[q - 195], world.truth[q]), np.array([0.0, 0.0, 0.3]))) for q in range(340, 350)]
    built, tried = [], []
    build, try_again = ConsensusVerifier._build_largest_first, ConsensusVerifier._try_again

    def recorded_build(verifier, held, order, universe, *, solve_runs):
        built.append(sum(len(o[3]) for o in order if o[1]))  # refused loops offered to the build
        tried_before = len(tried)
        out = build(verifier, held, order, universe, solve_runs=solve_runs)
        built.append(len(tried) - tried_before)
        return out

    monkeypatch.setattr(ConsensusVerifier, "_build_largest_first", recorded_build)
    monkeypatch.setattr(ConsensusVerifier, "_try_again", lambda v, members, *, solve=False: tried.append(len(members)) or try_again(v, members, solve=solve))
    verifier, _, result = _run(world, true + group)
    assert built == [6, 0]  # one build, offered the refused parts (6 of the group's loops), tried nothing
    constraints = result.constraints
    assert all(verifier._fate[i] == Fate.REJECTED for i, c in enumerate(constraints) if c.candidate.pair in {g.pair for g in group})
    assert {result.constraints[i].candidate.pair for i in result.accepted_constraint_ids} == {c.pair for c in true}


def test_two_groups_that_explain_a_free_end_equally_well_are_flagged_ambiguous():
    """After a long open traverse (the odometry alone holds 130 frames, several metres of
    uncertainty), two groups of five loops place the end of the trajectory three frames (6 m)
    apart; each fits the odometry about as well as the other. Neither is accepted: both are
    reported ambiguous, and the loops before them are accepted."""
    world = circle_world(frames_per_lap=200, laps=2.0, true_every=4, num_false=0, yaw_bias_rad=0.0002)
    n = len(world.odom)
    true = [_loop(world, q, q - 200) for q in range(205, 262, 4)]
    last = list(range(n - 10, n - 5))
    here = [_loop(world, q, q - 200) for q in last]
    there = [_loop(world, q, q - 197, T_match_query=se2_between(world.truth[q - 200], world.truth[q])) for q in last]
    verifier, steps, result = _run(world, true + here + there)
    constraints = result.constraints
    ambiguous = {constraints[i].candidate.pair for i in result.ambiguous_constraint_ids}
    accepted = {constraints[i].candidate.pair for i in result.accepted_constraint_ids}
    assert ambiguous == {c.pair for c in here} | {c.pair for c in there}
    assert accepted == {c.pair for c in true}
    assert result.last_step.ambiguous_constraint_ids == result.ambiguous_constraint_ids
    assert any("ambiguous" in reason for _, reason in result.last_step.dropped)


def test_two_passes_that_agree_on_a_place_beside_a_slip_join_under_heavy_tailed_odometry():
    """Three laps of a circle of 200 frames; the odometry slips 3 m sideways at the step from
    frame 119 to 120, at the end of a stretch of the first lap that no loop revisits (frames
    70-115). Its last frames, 116-119, are revisited from both later laps (8 loops): the map
    spreads the slip over the stretch, and every test refused them, one lap's loops and the
    other's (before this retry: all 8 refused, ATE 0.51 m). Each pass fits where the other
    puts the place, and together they fit under heavy-tailed odometry with the one slip at step
    119. Two false groups of the two later laps that agree on a place 12 frames back along the
    road (frames 118-127, 16 loops) pass the same cross test, and are refused under
    heavy-tailed odometry; two lone false groups claiming frames 150-159 agree with nothing."""
    period = 200
    world = circle_world(frames_per_lap=period, laps=3.0, true_every=2, num_false=0, yaw_bias_rad=0.0002)
    odom = world.odom.copy()
    odom[120:] = se2_compose(np.array([0.0, 3.0, 0.0]), odom[120:])  # in the world frame
    world = dataclasses.replace(world, odom=odom)
    true: dict[tuple[int, int], LoopCandidate] = {}
    for query in range(period + 5, 3 * period, 2):
        place = query % period
        if 70 <= place < 116:
            continue  # the stretch no loop revisits
        if query >= 2 * period:
            true[(query, query - period)] = _loop(world, query, query - period)  # the third lap to the second
        if query < 2 * period or place % 4 == 0:
            true[(query, place)] = _loop(world, query, place)
    beside = [(place + lap * period, place) for place in range(116, 120) for lap in (1, 2)]
    for query, match in beside:
        true[(query, match)] = _loop(world, query, match)
    agreeing_false = [_loop(world, q, q % period - 12, T_match_query=(0.0, 0.0, 0.0)) for q in [*range(330, 340), *range(530, 540)]]
    lone_false = [_loop(world, q, q - 150, T_match_query=(0.05, -0.02, 0.01)) for q in range(300, 310)] + [
        _loop(world, q, q - 330, T_match_query=(0.0, 0.1, 0.0)) for q in range(480, 490)]
    verifier, steps, result = _run(world, list(true.values()) + agreeing_false + lone_false)
    accepted = {result.constraints[i].candidate.pair for i in result.accepted_constraint_ids}
    assert set(beside) <= accepted
    assert accepted == set(true)  # no false loop, every true one
    assert any("8 refused loops accepted across odometry slips, where two passes over one place agree" in note for note in result.last_step.notes)
    from lcv_replay.evaluation.metrics import ate_rmse_m

    assert ate_rmse_m(result.trajectory, world.truth) < 0.2


def test_the_schedule_and_the_records():
    world = circle_world(frames_per_lap=200, laps=2.0, true_every=5, num_false=8, seed=2, yaw_bias_rad=0.0002)
    true = [_loop(world, c.query_frame, c.match_frame) for c in world.true_candidates]
    world = dataclasses.replace(world, true_candidates=tuple(true))
    verifier, steps, result = _run(world, list(world.candidates))
    assert [s.window_index for s in steps] == list(range(len(steps)))
    assert all(s.frame_index == 100 * (k + 1) - 1 for k, s in enumerate(steps))
    for step in steps:
        assert step.ranking[0].rank == 1 and step.ranking[0].constraint_ids == step.accepted_constraint_ids
        assert step.consistency.shape == (1, step.new_constraint_ids[-1] + 1 if step.new_constraint_ids else step.consistency.shape[1])
        assert step.gate_chi2 > 0 and "total" in step.timings_s
        top = step.ranking[0].id
        assert step.trajectories[top].shape == (step.frame_index + 1, 3)
    assert result.trajectory.shape == (len(world.odom), 3)
    truth = {c.pair for c in world.true_candidates}
    accepted = {result.constraints[i].candidate.pair for i in result.accepted_constraint_ids}
    assert accepted <= truth and len(accepted) >= 0.9 * len(truth)
    fates = verifier._fate
    assert set(np.flatnonzero(fates == Fate.ACCEPTED).tolist()) == set(result.accepted_constraint_ids)


@pytest.mark.slow
def test_a_generated_world_with_grouped_outliers_that_the_previous_ilv_plus_failed(tmp_path):
    """A ring city of 2,000 poses, 500 grouped outliers (Vertigo protocol), its declared
    covariances off by a different factor on each axis (``anisotropic``, as ringCity's are).
    Measured on this seed: the previous ilv+ accepted 9 false loops (P 0.986, R 0.887, ATE
    11.96 m); DCS P 1.000, R 0.980, ATE 1.05 m; the oracle's ATE is 0.26 m."""
    from pathlib import Path

    from lcv_replay.bench.suite import build_case_log
    from lcv_replay.bench.suites import world_cases
    from lcv_replay.bench.verify import load_inputs, verify_inputs

    case = world_cases(["ring"], [2000], ["anisotropic"], ["group"], [500], [CI_WORLD_SEED])[0]
    inputs = load_inputs(build_case_log(case, Path("/nonexistent"), tmp_path).path)
    row = verify_inputs(inputs, "ilv+").row
    assert row.false_positives == 0 and row.precision == 1.0
    assert row.recall >= 0.98
    oracle = verify_inputs(inputs, "oracle").row
    assert row.ate_rmse_m <= 1.1 * oracle.ate_rmse_m


CI_WORLD_SEED = 305


@pytest.mark.slow
def test_a_true_cluster_blocked_by_a_false_loop_wins_its_contest_on_ringcity(tmp_path):
    """Vertigo ringCity with 500 grouped outliers, seed 9001 (drawn fresh, not in the suite): a
    false group placed early bends a loosely held stretch, and true clusters of 26 and 50 loops are
    refused against it. The alternative with the false cluster out and every earlier loser in
    sinks under the false groups among those losers (2 to 10 loops each); the refused cluster alone
    wins; at the end of the log, the true clusters that lost to the false group (or were deposed
    while it bent the map) are tried again. Measured before: 4 false loops, R 0.902, ATE 3.14 m;
    with the first change: none, R 0.974, ATE 1.03 m; with both: none, R 1.000, ATE 0.95 m (the
    oracle's)."""
    from lcv_replay.bench.suite import build_case_log
    from lcv_replay.bench.suites import vertigo_cases
    from lcv_replay.bench.verify import load_inputs, verify_inputs
    from tests.shared_data import shared_path

    data = shared_path("vertigo", "ringCity").parents[1]
    case = vertigo_cases("ringCity", [500], ["group"])[0].with_seed(9001)
    row = verify_inputs(load_inputs(build_case_log(case, data, tmp_path).path), "ilv+").row
    assert row.false_positives == 0
    assert row.recall >= 0.99
    assert row.ate_rmse_m <= 1.1 * 0.95

def test_a_contest_lost_at_the_end_of_the_log_leaves_the_map_where_it_was(tmp_path):
    """Vertigo ring with 100 grouped outliers (the extended suite's case): its 434 poses are one
    window, so every contest is at the end of the log and solved to convergence. One such solve,
    lost and undone, settled the ring in another minimum 150 m from where it had been, its
    chi-square higher by only 13.7 (11.2 → 24.9), less than the gate (16.3) that a restart from
    the solution before needed: ATE 78 m with every true loop accepted and no false one. The
    restart now needs the chi-square back within 1 (or a ten-thousandth of it): ATE 1.43 m, the
    oracle's."""
    from lcv_replay.bench.suite import build_case_log
    from lcv_replay.bench.suites import vertigo_cases
    from lcv_replay.bench.verify import load_inputs, verify_inputs
    from tests.shared_data import shared_path

    data = shared_path("vertigo", "ring").parents[1]
    inputs = load_inputs(build_case_log(vertigo_cases("ring", [100], ["group"])[0], data, tmp_path).path)
    run, oracle = verify_inputs(inputs, "ilv+"), verify_inputs(inputs, "oracle").row
    assert any(reason.startswith("lost") for _, reason in run.result.last_step.dropped)  # the contests ran
    assert run.row.false_positives == 0
    assert run.row.recall == 1.0
    assert run.row.ate_rmse_m <= 1.01 * oracle.ate_rmse_m


def test_a_loop_noise_shape_that_leaves_ringcity_heavy_tailed_lets_no_loop_in(tmp_path):
    """Vertigo ringCity with 500 local outliers (the extended suite's case). The accepted loops'
    cycles reject the declared shape of its loop noise (variance factors x 97, y and yaw 0.10),
    but stay heavy-tailed under the fitted shape (tail dof 4.8): one more shape does not describe
    them. Retried under that shape at the end of the log, 2 local false loops joined (ATE 0.95 ->
    1.30 m). Now the retry needs the cycles to look like a chi-square under the shape, as the
    loops' scale does, and the note says why nothing was retried."""
    from lcv_replay.bench.suite import build_case_log
    from lcv_replay.bench.suites import vertigo_cases
    from lcv_replay.bench.verify import load_inputs, verify_inputs
    from tests.shared_data import shared_path

    data = shared_path("vertigo", "ringCity").parents[1]
    run = verify_inputs(load_inputs(build_case_log(vertigo_cases("ringCity", [500], ["local"])[0], data, tmp_path).path), "ilv+")
    assert run.row.false_positives == 0
    assert run.row.recall == 1.0
    assert run.row.ate_rmse_m <= 1.01 * 0.95
    note = next(note for note in run.result.last_step.notes if "reject the declared shape of the loop noise" in note)
    assert "stay heavy-tailed" in note and "no loop was retried" in note


@pytest.mark.parametrize("seed", [0, 9001, 9002])
def test_false_loops_between_parallel_streets_of_ringcity_are_refused(tmp_path, seed):
    """Vertigo ringCity with 500 random outliers: its odometry is declared about 50 times looser
    (in variance) than the long cycles between its revisits show, and false loops between two
    parallel streets 5 to 10 m apart fit under the declared noise. Measured before the odometry's
    level was fitted on the long cycles: 2 false loops, ATE 2.73 m (seed 0, the extended suite's),
    1, ATE 3.66 m (seed 9001) and 1, ATE 3.27 m (seed 9002; both drawn fresh); now none, and the
    oracle's ATE, 0.95 m. Seed 9001 also needs the stiffer odometry's true clusters judged
    soundly: with the level alone, two true clusters (31 and 51 loops) were refused by a bound
    and a one-step solve that do not hold for clusters (recall 0.908, ATE 1.06 m)."""
    from lcv_replay.bench.suite import build_case_log
    from lcv_replay.bench.suites import vertigo_cases
    from lcv_replay.bench.verify import load_inputs, verify_inputs
    from tests.shared_data import shared_path

    data = shared_path("vertigo", "ringCity").parents[1]
    case = vertigo_cases("ringCity", [500], ["random"])[0].with_seed(seed)
    row = verify_inputs(load_inputs(build_case_log(case, data, tmp_path).path), "ilv+").row
    assert row.false_positives == 0
    assert row.recall >= 0.99
    assert row.ate_rmse_m <= 1.1 * 0.95


@pytest.mark.parametrize("mode", ["random", "group"])
def test_true_loops_across_an_odometry_slip_on_intel_are_accepted_at_the_end(tmp_path, mode):
    """Vertigo Intel with 100 outliers: the long cycles put its odometry at 0.08 of the declared
    variance, and the level is tightened. Two true loops from frame 898 (to frames 74 and 549)
    cross a stretch the odometry got worse than its bulk: their innovations under the fitted level
    are 19 and 23 against a gate of 16.3. At the end of the log they fit the final map under the
    log's declared noise (the looser level), and are accepted. Three from frame 698 (to 75, 194
    and 559, three revisits) are at 17 to 23 even under the declared noise (GNC-TLS refuses them
    too); under heavy-tailed (Cauchy) odometry the accepted loops put the map where they fit, at
    0.25 to 0.4 gates, and they are accepted too: recall 1.000, as DCS's. No false loop is.
    Before the first retry: recall 0.994; before the second: 0.997."""
    from lcv_replay.bench.suite import build_case_log
    from lcv_replay.bench.suites import vertigo_cases
    from lcv_replay.bench.verify import load_inputs, verify_inputs
    from tests.shared_data import shared_path

    data = shared_path("vertigo", "intel").parents[1]
    case = vertigo_cases("intel", [100], [mode])[0]
    inputs = load_inputs(build_case_log(case, data, tmp_path).path)
    out = verify_inputs(inputs, "ilv+")
    accepted = {out.result.constraints[i].candidate.pair for i in out.result.accepted_constraint_ids}
    assert {(898, 74), (898, 549)} <= accepted
    assert {(698, 75), (698, 194), (698, 559)} <= accepted
    assert out.row.false_positives == 0
    assert out.row.recall == 1.0
    # the recording says which second opinion took them
    notes = out.result.last_step.notes
    slips = next(n for n in notes if "across odometry slips" in n)
    assert all(f"(698↔{m})" in slips for m in (75, 194, 559))
    assert any("under the looser odometry level" in n and "(898↔74)" in n for n in notes)


def test_a_refused_loop_places_a_slip_that_the_accepted_loops_leave_anywhere_between_them():
    """Between two accepted loops a slip costs heavy-tailed odometry about as much on one step as
    on another, so where the map puts it they do not say. A circle of two laps whose odometry
    slips 1 m sideways at the step from frame 298 to 299, with the accepted loops of frames 297
    and 303 around it: in a map that puts the slip at step 302 instead (frames 298-302 on the
    odometry from frame 297), the true loop of frame 300 lies 143 against a gate of 16; with
    the slip moved across its end it fits, and ``_slip_movers`` names it with its stretch. A
    false loop of frame 301 fits neither side of the slip (719, and from the truth 1,026), and
    the true loop is no mover in the true map, where it fits as it is (6.1): the retry across
    slips tries those already (ring-5k-heavy-local-1000-s13338, where three such loops of an end
    revisit placed a 5.7 m slip, is in the ``regressions`` bench suite)."""
    world = circle_world(frames_per_lap=200, laps=2.0, true_every=2, num_false=0, yaw_bias_rad=0.0002)
    steps = se2.between(world.odom[:-1], world.odom[1:])
    steps[298] = se2_compose(steps[298], np.array([0.0, 1.0, 0.0]))
    world = dataclasses.replace(world, odom=se2.compose_chain(steps, world.odom[0]))
    queries = [*range(205, 296, 2), 297, 300, 303, 305, *range(307, 400, 2)]
    false = se2_compose(se2_between(world.truth[101], world.truth[301]), np.array([-1.5, 2.0, 0.2]))
    verifier, _, result = _run(world, [_loop(world, q, q - 200) for q in queries] + [_loop(world, 301, 101, T_match_query=false)])
    pairs = [c.candidate.pair for c in result.constraints]
    true_id, false_id = pairs.index((300, 100)), pairs.index((301, 101))
    accepted = np.array([k for k, pair in enumerate(pairs) if pair not in ((300, 100), (301, 101))])
    refused = np.array([true_id, false_id])
    misplaced = world.truth.copy()
    for k in range(298, 303):
        misplaced[k] = se2_compose(world.truth[297], se2_between(world.odom[297], world.odom[k]))
    assert verifier._slipped_steps(misplaced).tolist() == [302]
    assert np.all(verifier._residual_chi2(misplaced, refused) > 5 * verifier.gate_chi2)
    movers = verifier._slip_movers(misplaced, accepted, refused)
    assert list(movers) == [(297, 303)]
    assert movers[(297, 303)].tolist() == [true_id]
    # in the true map the slip is where the loop puts it: it fits as it is, and moves nothing
    assert verifier._slipped_steps(world.truth).tolist() == [298]
    assert verifier._residual_chi2(world.truth, refused)[0] < verifier.gate_chi2
    assert verifier._slip_movers(world.truth, accepted, refused) == {}


def test_the_accepted_loops_under_heavy_tailed_odometry_are_solved_from_a_solution_of_a_subset_where_it_costs_less():
    """The accepted loops' solution under heavy-tailed odometry (``_slip_base``) starts from the
    latest such solution of a subset of its loops where that one costs less than the working
    map: from there it needs fewer iterations, and ends at the same cost. A solution that holds
    a loop the solve leaves out is no start (a slip only that loop needs could stay), nor one on
    other frames, nor one that costs more. The circle of the test above, whose odometry slips
    1 m sideways at frame 298."""
    world = circle_world(frames_per_lap=200, laps=2.0, true_every=2, num_false=0, yaw_bias_rad=0.0002)
    steps = se2.between(world.odom[:-1], world.odom[1:])
    steps[298] = se2_compose(steps[298], np.array([0.0, 1.0, 0.0]))
    world = dataclasses.replace(world, odom=se2.compose_chain(steps, world.odom[0]))
    verifier, _, result = _run(world, [_loop(world, q, q - 200) for q in range(205, 400, 2)])
    accepted = verifier.graph.loop_id_array().copy()
    assert len(accepted) > 10
    x, n = verifier.graph.estimate(), len(world.odom)
    verifier._slip_solutions = []
    assert verifier._slip_start(accepted, n) is None  # nothing solved yet
    cold = verifier._solve_with_slips(accepted[1:], x)
    assert verifier._slip_start(accepted, n) is cold.poses  # a subset of the loops
    assert verifier._slip_start(accepted[2:], n) is None  # it holds a loop left out
    assert verifier._slip_start(accepted, n - 1) is None  # other frames
    warm = verifier._solve_with_slips(accepted[1:], x, warm=True)
    assert verifier._slip_start(accepted, n) is warm.poses  # the latest
    assert cold.iterations > 2 and warm.iterations < cold.iterations
    assert warm.chi2 == pytest.approx(cold.chi2, abs=0.5)
    # a start that costs more than the working map is not taken
    verifier._slip_solutions = [(frozenset(), x + np.array([0.0, 3.0, 0.0]))]
    again = verifier._solve_with_slips(accepted[1:], x, warm=True)
    assert again.iterations == cold.iterations and np.allclose(again.poses, cold.poses)


@pytest.mark.slow
def test_a_slip_that_the_final_map_shows_switches_on_the_retry_across_slips(tmp_path):
    """A heavy-tailed grid of 2,000 poses with 400 grouped outliers, seed 13520 (drawn at the
    twenty-eighth stop). The innovations of the accepted clusters fit a Gaussian (no tail: the
    loops a slip strains are refused, so they are not in the sample), which kept the retry
    across slips off, while three odometry steps of the final map stand at 29 to 58 against a
    threshold of 27.3. Under heavy-tailed odometry 9 refused true loops (frames 851-1376 to
    649-656, and 1553 to 881) fit the accepted loops' solution and join. Measured: recall 0.938
    -> 0.949, ATE 0.473 -> 0.345 m (1.85 -> 1.35 times the oracle's 0.255; GNC-TLS 0.390, DCS
    0.259), no false loop either way.

    Since the thirty-eighth stop the reported map loosens the odometry at the steps of the
    working map beyond the slip threshold (six here: frames 154, 424-426, 655 and 1552): ATE
    0.331 -> 0.215 m, 0.84 times the oracle's, from the same loops."""
    from lcv_replay.bench.verify import verify_inputs

    inputs = _world_inputs(tmp_path, "grid", 2000, 400, 13520)
    run, oracle = verify_inputs(inputs, "ilv+"), verify_inputs(inputs, "oracle").row
    accepted = _accepted_pairs(run)
    assert {(1161, 649), (1373, 653), (851, 653)} <= accepted
    assert all(pair in inputs.true_pairs for pair in accepted)
    assert any("across odometry slips" in n and "(1161↔649)" in n for n in run.result.last_step.notes)
    assert run.row.ate_rmse_m <= 1.1 * oracle.ate_rmse_m
    # the true revisit 1543-1577 to 872-904, split by a slip into parts that contradict each
    # other, stays whole (its union judged first): before, its parts of 7 and 12 were flagged
    assert run.row.ambiguous == 0
    assert run.row.recall >= 0.97


@pytest.mark.slow
def test_parts_of_a_true_revisit_split_by_a_slip_are_judged_together_first(tmp_path):
    """A heavy-tailed ring of 2,000 poses with 400 grouped outliers (groups of 10), seed 13503
    (drawn at the twenty-fifth stop). The true revisit of frames 872-912 to 16-56 stays when
    judged whole at the end of the log, but a slip splits it into two parts that contradict each
    other (872-898 to 30-56, 13 loops, and 900-912 to 16-28, 7), each held only on the count;
    judged alone they saved 8.7 and 4.4 gates, under the margin, and both were flagged: recall
    0.944, ATE 1.89 m, 2.6 times the oracle's 0.739 (GNC-TLS 0.828, 0.752 m; DCS 0.835, 0.740
    m). Their union is judged first now and stays: measured recall 0.978, ATE 0.719 m, nothing
    flagged, no false loop."""
    from lcv_replay.bench.verify import verify_inputs

    inputs = _world_inputs(tmp_path, "ring", 2000, 400, 13503)
    run, oracle = verify_inputs(inputs, "ilv+"), verify_inputs(inputs, "oracle").row
    accepted = _accepted_pairs(run)
    revisit = _true_revisit(inputs, (872, 912), (16, 56))
    assert len(revisit) >= 20 and revisit <= accepted
    assert run.row.false_positives == 0 and run.row.ambiguous == 0
    assert run.row.recall >= 0.97
    assert run.row.ate_rmse_m <= 1.1 * oracle.ate_rmse_m


@pytest.mark.slow
def test_a_true_revisit_that_fits_the_map_without_it_is_not_flagged_on_the_count(tmp_path):
    """A heavy-tailed grid of 2,000 poses with 400 grouped outliers (groups of 10), seed 13559
    (drawn at the thirtieth stop). At the end of the log the true revisit of frames 1193-1209 to
    297-312 (14 loops) was held only on the count (without it the map's chi-square is 160 lower,
    above its cluster gate) and saved 9.7 gates against the margin of 10: flagged ambiguous,
    recall 0.963, ATE 0.199 m, 1.11 times the oracle's 0.179 (GNC-TLS 0.842, 0.198 m; DCS
    0.846, 0.180 m). Most of its loops fit the map without it, each under the gate (the median
    at 0.49 of it): no other hypothesis of that stretch, so it is not flagged. Measured: recall
    0.983, ATE 0.186 m, nothing flagged, no false loop."""
    from lcv_replay.bench.verify import verify_inputs

    inputs = _world_inputs(tmp_path, "grid", 2000, 400, 13559)
    run, oracle = verify_inputs(inputs, "ilv+"), verify_inputs(inputs, "oracle").row
    accepted = _accepted_pairs(run)
    revisit = _true_revisit(inputs, (1193, 1209), (297, 312))
    assert len(revisit) >= 14 and revisit <= accepted
    assert run.row.false_positives == 0 and run.row.ambiguous == 0
    assert run.row.recall >= 0.98
    assert run.row.ate_rmse_m <= 1.1 * oracle.ate_rmse_m


@pytest.mark.slow
def test_clusters_refused_on_a_bound_are_tried_under_the_looser_odometry_level(tmp_path):
    """A heavy-tailed grid of 2,000 poses with 400 grouped outliers (groups of 10), seed 13565
    (drawn at the thirty-first stop). At the last window, under the odometry level then in force,
    five true revisits of frames 1545-1568 (of five places, 18 loops) were refused on a bound,
    without a solve, 28 to 74 gates off the map. At the end of the log the looser level (4.8
    times) lets single loops in, but not clusters that far off: recall 0.961, ATE 0.388 m, 1.72
    times the oracle's 0.225 (GNC-TLS 0.828, 0.361 m; DCS 0.833, 0.223 m). Under that level the
    bound no longer refuses them; solved, the revisit of 1553-1559 to 153-159 (7 loops) raises
    the chi-square by 4.0 gates, and joins. Measured: recall 0.972, ATE 0.236 m, no false loop."""
    from lcv_replay.bench.verify import verify_inputs

    inputs = _world_inputs(tmp_path, "grid", 2000, 400, 13565)
    run, oracle = verify_inputs(inputs, "ilv+"), verify_inputs(inputs, "oracle").row
    revisit = _true_revisit(inputs, (1553, 1559), (153, 159))
    assert len(revisit) >= 7 and revisit <= _accepted_pairs(run)
    assert run.row.false_positives == 0
    assert run.row.recall >= 0.97
    assert run.row.ate_rmse_m <= 1.1 * oracle.ate_rmse_m


@pytest.mark.slow
def test_a_small_false_cluster_does_not_hide_in_the_sum_of_a_joint_try(tmp_path):
    """A heavy-tailed grid of 2,000 poses with 400 outliers in groups of 20, seed 14043 (drawn at
    the forty-third stop). At the second window two loops of a false group (frames 1070-1071 to
    128-129, 2.2 m off) joined inside a joint try, under the gate of all its loops together, and
    bent frames 121-142, which only the odometry held; they then fitted the map they bent and,
    with 2 loops, were never judged on the count: 2 false loops, ATE 1.27 times the oracle's
    (GNC-TLS and DCS none). Their leave-out statistic in the try is 97.8, against the 53.9 two
    loops may add alone: now they are set aside and tried alone, and refused. Measured: no false
    loop, recall 0.982 (GNC-TLS 0.845), ATE 0.207 m (the oracle's 0.203)."""
    from lcv_replay.bench.verify import verify_inputs

    inputs = _world_inputs(tmp_path, "grid", 2000, 400, 14043, group_size=20)
    run, oracle = verify_inputs(inputs, "ilv+"), verify_inputs(inputs, "oracle").row
    pair = {i for i, c in enumerate(inputs.candidates) if (c.query_frame, c.match_frame) in ((1070, 128), (1071, 129))}
    assert len(pair) == 2 and not {inputs.candidates[i].pair for i in pair} & inputs.true_pairs
    assert not pair & set(run.result.accepted_constraint_ids)
    assert run.row.false_positives == 0
    assert run.row.recall >= 0.97
    assert run.row.ate_rmse_m <= 1.1 * oracle.ate_rmse_m


@pytest.mark.slow
def test_no_loop_is_left_pending_at_the_end_of_the_log(tmp_path, monkeypatch):
    """A heavy-tailed ring of 2,000 poses with 400 outliers in groups of 20, seed 14204 (drawn at
    the forty-fifth stop), as it was judged before a window's contests were solved in full where
    the challenger outnumbers the incumbent (test_a_revisit_that_outnumbers_its_opponents_is_
    solved_in_full_at_a_window_end; switched back here), when false groups won: 40 false loops.
    At the end
    of the log the hypothesis built largest first sent 273 loops back to be verified; the trial
    of their largest cluster (233 true loops) failed and released 230 of them to the pool, which
    only a next window verifies: they stayed pending, neither accepted nor refused, and no retry
    of the end of the log looked at them (recall 0.628). Now the pool is verified again at once:
    none is left pending, recall 0.740."""
    from lcv_replay.bench.verify import verify_inputs

    verifiers: list[ConsensusVerifier] = []
    result = ConsensusVerifier.result

    def recording(self):
        verifiers.append(self)
        return result(self)

    monkeypatch.setattr(ConsensusVerifier, "result", recording)
    monkeypatch.setattr(
        ConsensusVerifier, "_solved_in_full",
        lambda self, inside, outside, *, searched, whole_side: self._finished and (not searched or (outside > inside and whole_side)),
    )
    inputs = _world_inputs(tmp_path, "ring", 2000, 400, 14204, group_size=20)
    run = verify_inputs(inputs, "ilv+")
    assert verifiers and not np.any(verifiers[-1]._fate == Fate.PENDING)
    assert run.row.recall >= 0.7


@pytest.mark.slow
def test_true_loops_refused_under_odometry_declared_too_tight_are_tried_under_the_fitted_level(tmp_path):
    """A generated grid city of 2,000 poses with heavy-tailed noise and 500 grouped outliers (the
    extended suite's seed 2): its long cycles show the odometry 2.2 times looser than declared, a
    level that is not applied (only tighter ones are). At the end of the log the refused loops
    inside the innovations' heavy tail are tried under it. Measured: recall 0.988 before, 0.993
    now (GNC-TLS 0.874, DCS 0.855), no false loop."""
    (row,) = _world_rows(tmp_path, "grid", 2000, 500, 2)
    assert row.false_positives == 0
    assert row.recall >= 0.992


@pytest.mark.slow
def test_a_revisit_that_outnumbers_its_opponents_is_solved_in_full_at_a_window_end(tmp_path):
    """A heavy-tailed ring of 2,000 poses with 400 outliers in groups of 20, seed 14204 (drawn at
    the forty-fifth stop). False groups that only the odometry held joined at the third window,
    ahead of the second lap's revisit of 238 loops (frames 1027-1498 to 676-1146), and the
    revisits of the second and third laps lost every contest against them on one Gauss-Newton
    step, far off from the map they bent: 40 false loops, recall 0.740, ATE 18.5 m (the oracle's
    2.73 m). Now a contest whose challenger outnumbers the incumbent is solved in full at a
    window end too; at the fourth window the revisits depose the false groups. Measured: no false
    loop, recall 0.985, ATE 2.70 m."""
    from lcv_replay.bench.verify import verify_inputs

    inputs = _world_inputs(tmp_path, "ring", 2000, 400, 14204, group_size=20)
    run, oracle = verify_inputs(inputs, "ilv+"), verify_inputs(inputs, "oracle").row
    revisit = _true_revisit(inputs, (1027, 1498), (676, 1146))
    assert len(revisit) >= 230 and len(revisit & _accepted_pairs(run)) >= 0.95 * len(revisit)
    assert run.row.false_positives == 0
    assert run.row.recall >= 0.97
    assert run.row.ate_rmse_m <= 1.1 * oracle.ate_rmse_m


@pytest.mark.slow
def test_the_free_end_is_claimed_again_after_the_retry_across_slips_in_the_claimed_map(tmp_path):
    """A heavy-tailed grid of 2,000 poses with 400 outliers in groups of 20, seed 13712 (drawn at
    the thirty-fifth stop; its odometry steps 29.9 m at frame 1718). At the end of the log the
    claim of the free end took 27 loops of frames 1816-1880 and nothing was tried after it: the
    true revisits of frames 1814-1999 stayed refused, recall 0.833, ATE 1.73 m (the oracle's
    1.07; GNC-TLS 6.51 m, DCS 17.2 m). Now the retry across slips runs again in the claimed map,
    and the new free end is claimed again, round after round. Measured: no false loop, recall
    0.910, ATE 1.41 m."""
    from lcv_replay.bench.verify import verify_inputs

    inputs = _world_inputs(tmp_path, "grid", 2000, 400, 13712, group_size=20)
    run, oracle = verify_inputs(inputs, "ilv+"), verify_inputs(inputs, "oracle").row
    accepted = _accepted_pairs(run)
    assert len(_true_revisit(inputs, (1928, 1999), (0, 1999)) & accepted) >= 10  # past the first claim's new free end
    assert run.row.false_positives == 0
    assert run.row.recall >= 0.9
    assert run.row.ate_rmse_m <= 1.35 * oracle.ate_rmse_m


@pytest.mark.slow
def test_a_refused_revisit_that_an_odometry_slip_explains_joins_at_the_end_of_the_log(tmp_path):
    """A heavy-tailed ring of 2,000 poses with 400 outliers in groups of 20, seed 13633 (drawn at
    the thirty-fifth stop). The revisit of frames 1079-1110 to 727-758 (17 true loops), between
    two accepted runs of the same revisit, was refused: 55 gates off the final map, and 1.4
    (median) to 3.1 gates off under heavy-tailed odometry, so no retry took it; recall 0.963,
    ATE 2.66 m, 1.11 times the oracle's 2.40 (GNC-TLS 2.35 m, DCS 2.46 m). Now a refused
    cluster near the solution under heavy-tailed odometry joins where an odometry slip explains
    it (the judgement on the count's test). Measured: no false loop, recall 0.992, ATE 1.28 m."""
    from lcv_replay.bench.verify import verify_inputs

    inputs = _world_inputs(tmp_path, "ring", 2000, 400, 13633, group_size=20)
    run, oracle = verify_inputs(inputs, "ilv+"), verify_inputs(inputs, "oracle").row
    revisit = _true_revisit(inputs, (1079, 1110), (727, 758))
    assert len(revisit) >= 17 and revisit <= _accepted_pairs(run)
    assert run.row.false_positives == 0
    assert run.row.recall >= 0.98
    assert run.row.ate_rmse_m <= 1.1 * oracle.ate_rmse_m


@pytest.mark.slow
def test_the_next_loops_of_a_revisit_split_by_a_slip_join_where_one_slip_explains_them(tmp_path):
    """A heavy-tailed ring of 2,000 poses with 400 grouped outliers (groups of 10), seed 14355
    (drawn at the forty-eighth stop). The first pass of the reverse revisit of frames 1144-1174
    to 699-728 slips at step 726 (chi-square 11,435 in the ground truth). The revisit's loops of
    frames 1149-1174 joined; its last 3 (1144-1146 to 727-728) lay 7.9 gates (median) from the
    accepted loops' solution under heavy-tailed odometry, beyond the reach of the refused
    clusters' retry, and were refused: ATE 1.17 m, 1.43 times the oracle's 0.819 (GNC-TLS 1.15
    times, DCS 1.36). They continue the revisit that joined and need one slip, so they are judged
    however far they lie. Measured: no false loop, ATE 0.520 m (0.63 times the oracle's)."""
    from lcv_replay.bench.verify import verify_inputs

    inputs = _world_inputs(tmp_path, "ring", 2000, 400, 14355)
    run, oracle = verify_inputs(inputs, "ilv+"), verify_inputs(inputs, "oracle").row
    continuation = _true_revisit(inputs, (1144, 1146), (727, 728))
    assert len(continuation) >= 3 and continuation <= _accepted_pairs(run)
    assert run.row.false_positives == 0
    assert run.row.ate_rmse_m <= 1.1 * oracle.ate_rmse_m


@pytest.mark.parametrize(
    ("query", "match", "direction"),
    [([500, 501, 503], [280, 281, 283], 1), ([1144, 1145, 1146], [728, 727, 727], -1), ([10, 12], [90, 88], -1)],
)
def test_the_direction_of_a_pass_is_that_of_its_match_frames_against_its_query_frames(query, match, direction):
    from lcv_replay.verification.consensus import _pass_direction

    assert _pass_direction(np.array(query), np.array(match)) == direction


def test_the_large_slips_of_a_continuation_lie_in_one_place_when_they_lie_on_neighbouring_steps():
    verifier = make_verifier("ilv+", CONFIG, odometry_information=ODOM_INFORMATION)
    gate = verifier.cluster_gate(5)
    assert verifier._one_slip([], 5)
    assert verifier._one_slip([(519, 3 * gate), (520, 2 * gate)], 5)  # one slip spread over two steps
    assert verifier._one_slip([(2, 9 * gate), (3, gate), (4, 1.5 * gate)], 5)
    assert not verifier._one_slip([(628, 9 * gate), (623, 8 * gate)], 5)  # both ends of a stretch
    assert verifier._one_slip([(628, 9 * gate), (623, 0.5 * gate)], 5)  # a slip under the cluster gate is not a place


def _world_inputs(tmp_path, layout: str, poses: int, outliers: int, seed: int, group_size: int = 10, noise: str = "heavy"):
    """``bench verify``'s inputs of a generated world with grouped outliers and (by default)
    heavy-tailed odometry."""
    from lcv_replay.bench.suite import build_case_log
    from lcv_replay.bench.suites import world_cases
    from lcv_replay.bench.verify import load_inputs

    case = world_cases([layout], [poses], [noise], ["group"], [outliers], [seed], group_size=group_size)[0]
    return load_inputs(build_case_log(case, Path("/nonexistent"), tmp_path).path)


def _accepted_pairs(run) -> set[tuple[int, int]]:
    """The ``(query, match)`` pairs that ``run`` (``bench verify``'s) accepted."""
    return {run.result.constraints[i].candidate.pair for i in run.result.accepted_constraint_ids}


def _true_revisit(inputs, queries: tuple[int, int], matches: tuple[int, int]) -> set[tuple[int, int]]:
    """The true candidate pairs of ``inputs`` with a query frame in ``queries`` and a match frame
    in ``matches`` (both inclusive)."""
    return {c.pair for c in inputs.candidates if queries[0] <= c.query_frame <= queries[1] and matches[0] <= c.match_frame <= matches[1] and c.pair in inputs.true_pairs}


def _world_runs(tmp_path, layout: str, poses: int, outliers: int, seed: int, methods=("ilv+",), group_size: int = 10, noise: str = "heavy"):
    """Runs (``bench verify``'s) of ``methods`` on a generated world (:func:`_world_inputs`)."""
    from lcv_replay.bench.verify import verify_inputs

    inputs = _world_inputs(tmp_path, layout, poses, outliers, seed, group_size, noise)
    return [verify_inputs(inputs, method) for method in methods]


def _world_rows(tmp_path, layout: str, poses: int, outliers: int, seed: int, methods=("ilv+",), group_size: int = 10):
    """Rows of ``methods`` on a generated world with heavy-tailed odometry and grouped outliers."""
    return [run.row for run in _world_runs(tmp_path, layout, poses, outliers, seed, methods, group_size)]


def _assert_fixed(run, oracle, *, recall: float, note: tuple[str, ...], ate_factor: float = 1.1) -> None:
    """``run`` (``ilv+``) accepts no false loop, keeps ``recall`` and an ATE within ``ate_factor``
    of the ``oracle`` run's, and the last step has a note that says each part of ``note``."""
    assert run.row.false_positives == 0
    assert run.row.recall >= recall
    assert run.row.ate_rmse_m <= ate_factor * oracle.row.ate_rmse_m
    assert any(all(part in text for part in note) for text in run.result.last_step.notes)


@pytest.mark.slow
def test_refused_revisits_that_fit_once_others_joined_at_the_end_are_tried_again(tmp_path):
    """A heavy-tailed ring of 2,000 poses with 400 grouped outliers, seed 13514 (drawn at the
    twenty-sixth stop). At the end of the log a false group of 10 loops (frames 877-886 to 37-46)
    is refused, judged again on the count, and the near misses are tried once more in the relieved
    map: 19 true loops join. Two true revisits refused at the last window (frames 1618-1620 to
    306-308 and 1624-1632 to 72-64, 9 loops) lay 19 to 32 gates off the relieved map when the
    clusters to try were chosen, but fit it once the 19 had joined (0.2 to 1.3 gates a loop), and
    nothing tried them again: recall 0.971, ATE 1.24 m (1.16 times the oracle's 1.06; GNC-TLS
    none, 0.837, 1.09 m). Now the clusters are chosen again after each round that let some in:
    measured no false loop, recall 0.985, ATE 1.07 m."""
    from lcv_replay.bench.verify import verify_inputs

    inputs = _world_inputs(tmp_path, "ring", 2000, 400, 13514)
    run, oracle = verify_inputs(inputs, "ilv+"), verify_inputs(inputs, "oracle").row
    revisits = [i for i, c in enumerate(inputs.candidates) if 1618 <= c.query_frame <= 1632 and c.pair in inputs.true_pairs]
    assert len(revisits) >= 9
    assert set(revisits) <= set(run.result.accepted_constraint_ids)
    assert run.row.false_positives == 0
    assert run.row.recall >= 0.98
    assert run.row.ate_rmse_m <= 1.1 * oracle.ate_rmse_m


@pytest.mark.slow
def test_true_revisits_kept_out_without_a_solve_by_a_flagged_group_are_solved_in_the_relieved_map(tmp_path):
    """A heavy-tailed ring of 2,000 poses with 400 outliers in groups of 20, seed 13518 (drawn at
    the twenty-seventh stop). A false group of 15 loops (frames 1920-1934 to 153-167) accepted at
    the last window kept 12 true clusters of frames 1592-1855 out without a solve; at the end of
    the log it was flagged ambiguous and left the map, but the clusters lay hundreds of gates off
    the relieved map (a few hundredths of a gate under the odometry alone) and were not tried: no
    false loop, but recall 0.869 and ATE 6.37 m, 10.3 times the oracle's 0.62 m (GNC-TLS none,
    0.802, 0.83 m). Now they are tried with a solve: measured recall 0.970, ATE 0.88 m (1.43 times
    the oracle's: still short of the bar). Since the thirty-third stop the group is refused, not
    flagged: it claims query frames of a refused true revisit (1893-1995 to 661-763, 53 loops)
    for another place, and at the end of the log that revisit, which outnumbers the side it is
    contested against (the group and two clusters, 52 loops), is solved in full and wins (J lower
    by 679)."""
    from lcv_replay.bench.verify import verify_inputs

    inputs = _world_inputs(tmp_path, "ring", 2000, 400, 13518, group_size=20)
    run, oracle = verify_inputs(inputs, "ilv+"), verify_inputs(inputs, "oracle").row
    group = [i for i, c in enumerate(inputs.candidates) if 1920 <= c.query_frame <= 1934 and 153 <= c.match_frame <= 167]
    assert len(group) == 15 and not {inputs.candidates[i].pair for i in group} & inputs.true_pairs
    assert not set(group) & (set(run.result.accepted_constraint_ids) | set(run.result.ambiguous_constraint_ids))
    assert run.row.false_positives == 0
    revisits = [i for i, c in enumerate(inputs.candidates) if 1679 <= c.query_frame <= 1697 and c.pair in inputs.true_pairs]
    assert len(revisits) >= 10
    assert set(revisits) <= set(run.result.accepted_constraint_ids)
    assert run.row.recall >= 0.95
    assert run.row.ate_rmse_m <= 1.5 * oracle.ate_rmse_m


@pytest.mark.slow
def test_a_revisit_cut_short_by_the_window_end_does_not_lose_to_a_false_group_on_the_count(tmp_path):
    """A ring of 2,000 poses with heavy-tailed odometry and 400 grouped outliers, seed 9102 (drawn
    fresh). At the first window, with nothing accepted yet, a false group of 10 loops and a true
    revisit claim the same place; the revisit is cut to 8 loops by the window's end and loses on
    the count alone (its chi-square is the lower). Before, that contest was final: the group bent
    the map and the revisit's next 35 loops were judged from it (one Gauss-Newton step 595,000
    off): 10 false loops, recall 0.740, ATE 11.6 m. Now it is left undecided until the next
    window, when the revisit joins and the group is refused: measured no false loop, recall
    0.979, ATE 0.51 m (the oracle's 0.52; GNC-TLS none, 0.55 m)."""
    from lcv_replay.bench.suite import build_case_log
    from lcv_replay.bench.suites import world_cases
    from lcv_replay.bench.verify import load_inputs, verify_inputs

    case = world_cases(["ring"], [2000], ["heavy"], ["group"], [400], [9102])[0]
    inputs = load_inputs(build_case_log(case, Path("/nonexistent"), tmp_path).path)
    run, oracle = verify_inputs(inputs, "ilv+"), verify_inputs(inputs, "oracle").row
    assert run.row.false_positives == 0
    assert run.row.recall >= 0.97
    assert run.row.ate_rmse_m <= 1.1 * oracle.ate_rmse_m
    first = run.steps[0]
    assert any("runs on past the window's end" in reason for _, reason in first.dropped)
    assert first.ambiguous_constraint_ids  # the undecided sides are shown as such meanwhile
    assert not set(first.ambiguous_constraint_ids) & set(run.result.ambiguous_constraint_ids)  # and decided by the end


@pytest.mark.slow
@pytest.mark.parametrize(("seed", "group_size"), [(9104, 10), (9421, 10), (9308, 10), (9852, 20), (9404, 10), (10301, 10), (10407, 5), (11008, 10), (11804, 10), (11803, 10), (12008, 10), (13728, 20), (14034, 10)])
def test_fresh_heavy_tailed_rings_where_a_verdict_went_wrong(tmp_path, seed, group_size):
    """Rings of 2,000 poses with heavy-tailed odometry and 400 grouped outliers (in groups of 10,
    or of 5 or 20), on seeds drawn fresh; before each fix (measured; GNC-TLS accepts no false loop on
    any of them):

    * 9104: a false group of 8 loops bent the map at the second window and a true cluster of 6
      then did not fit it; the contest was skipped because the false loops' residuals were small
      (the map had been bent to meet them). 28 false loops, recall 0.711, ATE 21.0 m. Now every
      contest runs: none, 0.987, 0.79 m (the oracle's 0.79).
    * 9207: a false group of 10 joined at the third window; every contest against it, the last
      one too (302 loops, one step 731,000 off), was lost on one Gauss-Newton step from the bent
      map. 10 false loops, recall 0.548, ATE 20.7 m. Now the contests at the end of the log are
      solved: none, 0.972, 1.06 m (the oracle's 1.04).
    * 9300: a true revisit of 93 loops lost on one step at the second window to 8 true loops and
      was never contested again. No false loop, but recall 0.842, ATE 1.70 m (1.77 times the
      oracle's). Now every standing conflict is contested once more at the end, solved: 0.984,
      0.98 m (the oracle's 0.96).
    * 9420: a false group of 10 loops, the only cluster of the first window, joined on the
      truncated cost; the true clusters that contradict it were refused later as implausible in
      the map it bent, and an eighth loop of the group came back on its own at the end. 8 false
      loops, recall 0.911, ATE 8.28 m. Now the clusters accepted on the count are judged again
      at the end, with the accepted loops of their revisit, in a batch solve: none, 0.979,
      0.52 m (the oracle's 0.50).
    * 9421: a true revisit of 186 refused loops named two false groups of 10 and true clusters
      of 202 and 41 loops; together they held more loops than it, so it was not contested at
      the end: 20 false loops, recall 0.675, ATE 11.2 m. Now a standing conflict whose
      opponents outweigh the refused cluster is searched for a side it outweighs (smallest
      first: the 41 and the two groups), and it wins: none, 0.980, 0.53 m (the oracle's 0.55).
    * 9308: a true revisit of 155 loops was refused without naming an opponent; a false group
      inside its revisit and one accepted on the count 400 frames away held the map: 10 false
      loops, recall 0.750, ATE 1.72 m. Now the side is searched among those suspects too: none,
      0.984, 0.46 m (the oracle's 0.46).
    * 9804 (groups of 20): the same, a true revisit of 102 loops against false loops of its
      revisit: 20 false loops; now none, recall 0.961, ATE 0.93 m (the oracle's 0.92).
    * 9302: a false group of 5 loops joined at the third window in a joint try with true
      clusters, and nothing contested it: 5 false loops, ATE 9.27 m (the oracle's 1.06).
    * 9755 (groups of 5): three false groups of 5 held the map against a true revisit of 118
      loops and its neighbours: 15 false loops, recall 0.725, ATE 9.48 m.
    * 9852 (groups of 20): a false group of 10 loops joined on the count (true revisits
      refused after it named no opponent): 10 false loops, ATE 4.84 m.

      These three: now a second hypothesis is built at the end of the log, the clusters tried
      largest first (:meth:`ConsensusVerifier._largest_first`), and it has the lower ``J``: none,
      recall 0.979, 0.985, 0.995, ATE 1.03, 1.37, 0.60 m (the oracle's 1.06, 1.36, 0.60). It
      guards 9804 too: a first version of it, which tried each cluster whole and broke ties of
      size by cluster id, took 20 false loops there.
    * 9404: false groups of 10 joined on the truncated-cost rule and bent the map; the true
      revisits that contradict them were screened out in it, never clustered. The second
      hypothesis drops the three accepted groups but takes another: 10 false loops, recall 0.643,
      ATE 13.1 m (30, 0.618 before it).
    * 9805 (groups of 20): a false group of 19 is tried in the second hypothesis before the true
      clusters of 15 and 14 that keep it out of the working one, which it wins on the true
      revisits of 48 and 47 loops it also takes in: 19 false loops, recall 0.895, ATE 4.25 m.
      Now, once the second hypothesis has replaced the working one, the loops it left out and
      those the screen set aside are verified in its map, and the conflicts they name are
      contested as at a window. On 9805 the true clusters the group displaced depose it: none,
      recall 0.985, ATE 0.74 m (the oracle's 0.73); on 9404 a true revisit of 214 loops, screened
      out until then, deposes the group the second hypothesis took and a true cluster of 42:
      none, 0.971, 1.21 m (the oracle's 1.16).
    * 10301 (drawn after): the largest refused part, a true revisit of 444 loops, was the first
      part the second hypothesis tried, against the odometry alone; its one Gauss-Newton step
      from there was far off, so it was refused on that step and only the 61 loops that fitted
      the step joined (it fits whole, solved: a rise of 7 per loop against a gate of 40). 30
      false loops, recall 0.359, ATE 22.9 m. Now the part tried against the odometry alone is
      solved in full: none, 0.978, 0.71 m (the oracle's 0.70).
    * 10407 (groups of 5, drawn after): three loops of a false group joined at the fourth
      window as one cluster, in a stretch no true loop held yet; left out alone in the audit,
      each was 15.8 to 30.0 off the map (gate 36.5), held by the other two. 3 false loops,
      recall 0.982. Now the audit tests a loop's revisit with it: together they are 114.6 off
      (bound 73.1), leave, and are refused when verified again: none, 0.984, 1.02 m (the
      oracle's 1.02).
    * 11008: a false group of 10 that the final map holds only on the count was flagged ambiguous
      at the end, and another false group of 10 joined when the refused loops were tried once
      more: 10 false loops, ATE 13.5 m. Now what joins then is judged by the same rule, once: it
      holds only on the count too (by 2.1 gates) and is flagged: none, recall 0.981, ATE 2.59 m.
    * 11804 (drawn at the fifteenth stop): a false group of 10 loops after every other accepted
      loop (frames 1965-1974 to 537-546) joined in a joint try at the fourth window; at the end
      the final map holds it only on the count (by 4.7 gates), but nothing else holds the
      relative poses it claims, so its leave-out statistic cannot be computed and it was never
      judged; and the true revisit of 16 loops it displaced had been refused as implausible in
      the map it bent. 10 false loops, recall 0.939, ATE 2.80 m. Now such a revisit is judged by
      the batch solve and flagged, and the refused clusters of the stretch it held are tried
      again: none, 0.980, 0.76 m (the oracle's 0.74; GNC-TLS none, 0.834, 0.78 m). Since the
      thirty-second stop the retry of clusters refused on a bound makes the statistic computable,
      0.94 of the group's cluster gate: a lone revisit at half its gate or more is judged where
      the batch solve confirms the fall (200, gate 121); before, at the gate only, 10 false loops.
    * 11803 (drawn at the fifteenth stop): at the third window a true revisit of 439 loops
      (frames 617-1499) failed its trial in the map a false group of 10 had bent at the second;
      the 66 of its loops that fitted won a contest against the group, but the other 373 had gone
      back to the pool until the next window, and meanwhile two false groups of 10 joined where
      they would have held the trajectory. 20 false loops, recall 0.652, ATE 2.62 m.
      Now the loops sent back are verified in the map a contest of their window changed: none,
      0.991, 1.02 m (the oracle's 1.00; GNC-TLS none, 0.844).
    * 12008 (drawn at the sixteenth stop): a true revisit of 200 loops (frames 1589-1998) lost
      its contest against a false group of 10 on one Gauss-Newton step at the fourth window, and
      at the end of the log the contests of the last window's new clusters (of 9, 3 and 1 loops)
      spent the budget before the standing conflicts were contested again: 20 false loops,
      recall 0.654, ATE 9.43 m. Now the standing conflicts have a budget of their own: none,
      0.980, 0.46 m (the oracle's 0.46; GNC-TLS none, 0.877).
    * 10612 (a known failure from the ninth stop): a false group of 10 (1381-1390 to 323-332)
      displaced two true loops at its match end: 10 false loops, recall 0.983. From the
      twenty-third stop it was judged on the count, credited with the loops it displaced, and
      flagged (none, 0.985, 1.19 m). Since the thirty-seventh stop (the large part of a refused
      revisit tried in its window) it no longer joins: the hypothesis built afresh leaves it
      out (none, 0.983, 1.19 m; the oracle's 1.21).
    * 13728 (groups of 20, drawn at the thirty-eighth stop): no false loop, but a lone true loop
      (frames 1471 to 1407) across a stretch that drifted beyond the declared odometry noise lay
      2.4 gates off the final map once added (inside the innovations' fitted tail, 2.6 gates)
      and was refused, as were four more lone true loops: recall 0.985, ATE 0.844 m (1.15 times
      the oracle's). Now the lone refused loops inside that tail are tried together at the end
      (:meth:`ConsensusVerifier._retry_lone_in_tail`): none, 0.992, 0.731 m (the oracle's 0.733).
    * 14034 (drawn at the forty-third stop, after the first version of
      :meth:`ConsensusVerifier._slip_explains`): a false group of 10 (frames 1795-1804 to 58-67)
      that the final map holds only on the count displaced no refused loop that fitted the map
      without it, and fitted the map under heavy-tailed odometry once it slipped at 14 places
      far from it (the largest at frame 800): kept, 10 false loops, ATE 12.9 m. Now the slips
      beyond its cluster gate must lie in one place: flagged, none, 0.997, 1.21 m (the oracle's
      1.66; GNC-TLS none, 0.814).

    GNC-TLS's recall on these rings is 0.80 to 0.87 (measured on thirteen of the first fourteen).

    Eight of them are not run here: 9207 (the contests solved at the end, as 9104's), 9300 (the
    standing conflicts contested at the end, as 12008's), 9420 (the clusters accepted on the
    count judged again at the end in a batch solve, as 11804's), 9804 (as 9308), 9302 and 9755
    (as 9852), 9805 (as 9404) and 10612 (whose group no longer joins). They
    guard fixes that another seed here guards too, and the suite has a time budget; all 20, and
    every other generated world in this file where a verdict went wrong, are in the built-in
    ``regressions`` bench suite (``lcv-replay bench suite --suite regressions``), run at each
    development stop."""
    row, oracle = _world_rows(tmp_path, "ring", 2000, 400, seed, methods=("ilv+", "oracle"), group_size=group_size)
    assert row.false_positives == 0
    assert row.recall >= 0.95
    assert row.ate_rmse_m <= 1.1 * oracle.ate_rmse_m


@pytest.mark.slow
def test_a_small_revisit_that_only_the_count_accepts_is_flagged_ambiguous(tmp_path):
    """A heavy-tailed ring of 2,000 poses with 400 grouped outliers, seed 10712 (drawn fresh). A
    false group of 10 short loops (frames 1471-1479 to 1421-1429) joined at the third window on the
    truncated cost (its rise 1.44 cluster gates), and no accepted loop contradicts it: at the end
    the hypothesis with it is cheaper by 3.8 gates, and 8 of its loops were accepted (GNC-TLS
    accepts 4 of them). Now a revisit that only the count accepts, by fewer than
    ``count_ambiguity_margin`` gates, is flagged ambiguous at the end of the log: no false loop
    (measured: recall 0.976 -> 0.977, ATE 1.00 -> 1.29 m, the oracle's 1.29)."""
    from lcv_replay.bench.suite import build_case_log
    from lcv_replay.bench.suites import world_cases
    from lcv_replay.bench.verify import load_inputs, verify_inputs

    case = world_cases(["ring"], [2000], ["heavy"], ["group"], [400], [10712])[0]
    inputs = load_inputs(build_case_log(case, Path("/nonexistent"), tmp_path).path)
    run, oracle = verify_inputs(inputs, "ilv+"), verify_inputs(inputs, "oracle").row
    assert run.row.false_positives == 0
    assert run.row.ambiguous - run.row.ambiguous_true >= 7  # the group is shown, not dropped
    assert any("flagged ambiguous" in note for note in run.result.last_step.notes)
    assert run.row.recall >= 0.95
    assert run.row.ate_rmse_m <= 1.1 * oracle.ate_rmse_m


@pytest.mark.slow
def test_a_false_group_that_took_the_free_end_loses_to_the_clusters_refused_in_the_map_it_bent(tmp_path):
    """A heavy-tailed grid city of 2,000 poses with 400 grouped outliers, seed 11911 (drawn at the
    fifteenth stop). At the second window's free end a false group of 10 loops (frames 947-956 to
    54-63) was the largest cluster, so it was tried first and accepted; the true clusters of 5, 3,
    6 and 6 loops after it (frames 952-983) were then refused on a bound in the map it bent, naming
    no opponent, and the group fitted the final map: 10 false loops, recall 0.932, ATE 1.28 m (5.6
    times the oracle's). Now, at the end of the log, such a hold is contested against those
    clusters together: no false loop, recall 0.961, ATE 0.25 m (1.08 times the oracle's; GNC-TLS
    none)."""
    run, oracle = _world_runs(tmp_path, "grid", 2000, 400, 11911, methods=("ilv+", "oracle"))
    _assert_fixed(run, oracle, recall=0.95, note=("took the free end of the trajectory refused",))


@pytest.mark.slow
def test_a_false_group_that_took_the_free_end_also_answers_to_the_revisits_refused_before_its_start(tmp_path):
    """A heavy-tailed ring of 2,000 poses with 400 outliers in groups of 20, seed 12708 (drawn at
    the twenty-first stop). With nothing accepted yet, the first window's largest cluster was a
    false group of 10 loops (frames 407-416 to 19-28); it was tried first and joined. The true
    revisits it contradicts, of 6 loops (357-368 to 0-11: before its start) and 8 (434-448 to
    16-30), were refused on a bound in the map it bent. Only the 8 counted as its rivals, fewer
    than its 10, so it was never contested: 10 false loops, ATE 2.98 m (4.9 times the oracle's;
    GNC-TLS and DCS accept none). Now every cluster so refused beyond the frontier it took is a
    rival, and against the 14 together it is refused: no false loop, recall 0.990, ATE 0.59 m."""
    run, oracle = _world_runs(tmp_path, "ring", 2000, 400, 12708, methods=("ilv+", "oracle"), group_size=20)
    _assert_fixed(run, oracle, recall=0.98, note=("407-416↔19-28) that took the free end of the trajectory refused",))


@pytest.mark.slow
def test_a_false_group_beside_a_true_revisit_that_contradicts_it_is_flagged_ambiguous(tmp_path):
    """Heavy-tailed rings of 2,000 poses with 400 grouped outliers (groups of 10) where a false
    group runs beside a true revisit of the same road, a frame or two off it, and clustered with
    it (the pairwise test passes across a few odometry steps through the true loops):

    * 12805 (drawn at the twenty-second stop): the false group of frames 1615-1624 to 557-566
      lies 1.4 m along the road from the true loops of frames 1597-1612 to 541-556. The final
      map bends at an odometry slip between the two; the true loops beside the group fail the
      pairwise gate with its loops by 1.3 to 3.5 times. Its revisit, grown to a fixed point, is
      the whole true drive (196 loops), so it was never judged as a lone revisit: 10 false loops,
      recall 0.932. Left out of the final map alone, its chi-square falls by 238, above its
      cluster gate, and the hypothesis with it is cheaper by only 4.1 gates: flagged ambiguous.
    * 9900 (the fifth stop's known failure): 9 false loops and 2 true ones in one part (frames
      1133-1148 to 189-202), beside true loops they contradict; left out, the chi-square falls by
      225, and they save 4.4 gates: flagged ambiguous. 9 false loops -> none, recall 0.971 ->
      0.974, ATE 1.02 times the oracle's.

    Now the parts of accepted revisits that contradict an accepted loop beside them (a pair
    across the part's edge fails) are judged on the count alone. 9900 is run by the
    ``regressions`` bench suite, not here (the suite's time budget).

    On 12805 the ATE stayed 1.42 times the oracle's (0.97 m against 0.68; GNC-TLS 1.29 m): the
    true revisit of frames 864-904 to 16-56 (17 loops), beside an odometry slip (frames 879-881)
    that the final map spreads, was flagged ambiguous on the count too (27 loops flagged). Now
    such a revisit stays where it fits the map under heavy-tailed odometry and displaces no
    refused loop that fits the map without it (:meth:`ConsensusVerifier._slip_explains`); the
    false group still leaves a refused loop off that map, and stays flagged: recall 0.936 ->
    0.963, ATE 1.01 times the oracle's."""
    run, oracle = _world_runs(tmp_path, "ring", 2000, 400, 12805, methods=("ilv+", "oracle"))
    _assert_fixed(run, oracle, recall=0.96, note=("10 loops (1615-1624↔557-566) flagged ambiguous",))
    assert any("17 loops (864-904↔16-56) kept" in note for note in run.result.last_step.notes)
    assert run.row.ambiguous - run.row.ambiguous_true >= 9  # the group is shown, not dropped


@pytest.mark.slow
def test_a_true_revisit_whose_slips_lie_inside_its_own_stretches_stays(tmp_path):
    """A heavy-tailed grid of 2,000 poses with 400 local outliers, seed 14099 (drawn at the
    forty-fourth stop). The true revisit of frames 617-636 to 217-236 (12 loops) strains the
    final map, which spreads the odometry's slips at steps 617 and 216 (chi-square 1,355 and
    9,984 in truth), and the count saves only 4.8 gates: it was flagged ambiguous, although under
    heavy-tailed odometry it fits with slips at steps 234, 617 and 635, all inside its own two
    stretches; those counted as three places (recall 0.981, ATE 1.20 times the oracle's; GNC-TLS
    and DCS recall 0.81). Now only the slips away from its stretches count: it stays, with a
    note. Measured: no false loop, recall 0.997, ATE 0.84 times the oracle's."""
    from lcv_replay.bench.suite import build_case_log
    from lcv_replay.bench.suites import world_cases
    from lcv_replay.bench.verify import load_inputs, verify_inputs

    case = world_cases(["grid"], [2000], ["heavy"], ["local"], [400], [14099])[0]
    inputs = load_inputs(build_case_log(case, Path("/nonexistent"), tmp_path).path)
    run, oracle = verify_inputs(inputs, "ilv+"), verify_inputs(inputs, "oracle").row
    revisit = _true_revisit(inputs, (617, 636), (217, 236))
    assert len(revisit) >= 12 and revisit <= _accepted_pairs(run)
    assert any("(617-636↔217-236) kept" in note for note in run.result.last_step.notes)
    assert run.row.false_positives == 0
    assert run.row.recall >= 0.99
    assert run.row.ate_rmse_m <= 1.1 * oracle.ate_rmse_m


@pytest.mark.slow
@pytest.mark.parametrize(
    ("layout", "seed", "group_size", "where", "fitting", "recall"),
    [
        ("grid", 12905, 20, "20 loops (1835-1854↔1485-1504)", "loops of their stretches, refused or screened out, fit it", 0.94),
    ],
)
def test_a_false_group_judged_on_the_count_answers_to_the_true_loops_it_displaced(tmp_path, layout, seed, group_size, where, fitting, recall):
    """Heavy-tailed worlds of 2,000 poses with 400 grouped outliers where a false group, a couple
    of metres along the road from where the robot was, displaced true loops of its stretches and
    was judged on the count at the end of the log against the map without it alone:

    * grid 12905 (groups of 20, drawn at the twenty-third stop): the group of frames 1835-1854 to
      1485-1504 joined at the fourth window against 13 true loops of two revisits of its query
      stretch. The hypothesis with it was cheaper by 14.7 gates, above the margin of 10: 20 false
      loops, recall 0.940, ATE 1.24 times the oracle's (GNC-TLS none, recall 0.826). The 13 fit
      the map without it; credited with them, it saves 5.5 gates: flagged ambiguous, and the
      true loops of its stretch join when tried again. Measured: none, recall 0.951, ATE 0.194 m
      (the oracle's 0.192). Since the thirty-sixth stop (a refused solve is undone to the state
      before it exactly) four of the 13 join earlier, across odometry slips, and 8 are credited
      (6.8 gates saved): none, recall 0.973, ATE 0.191 m.

    Ring 10612 (groups of 10) was judged so from the twenty-third to the thirty-sixth stop (a
    group of 10 credited with the two true loops it displaced: flagged, recall 0.985); since the
    thirty-seventh its group no longer joins, and the ring is checked with
    :func:`test_fresh_heavy_tailed_rings_where_a_verdict_went_wrong`."""
    run, oracle = _world_runs(tmp_path, layout, 2000, 400, seed, methods=("ilv+", "oracle"), group_size=group_size)
    _assert_fixed(run, oracle, recall=recall, note=(f"{where} flagged ambiguous", fitting))
    assert run.row.ambiguous - run.row.ambiguous_true >= group_size  # the group is shown, not dropped


@pytest.mark.slow
def test_a_false_group_holding_the_free_end_answers_to_the_true_revisit_it_screened_out(tmp_path):
    """A heavy-tailed ring of 2,000 poses with 400 grouped outliers in groups of 20, seed 13201
    (drawn at the twenty-fourth stop). A false group (frames 1846-1865 to 818-837) joined at the
    last window and held the free end of the trajectory where it claims; the true revisit of the
    280 frames around it (1716-1999 to 1364-1647, 152 loops) was screened out in the map it bent,
    neither clustered nor refused, so judged on the count at the end of the log the group was
    credited with nothing it displaced and stayed, cheaper by 10.4 gates: 20 false loops, recall
    0.753, ATE 10 times the oracle's. Now the loops of its stretches, screened out or refused, are
    solved with the map without it; 19 of the 26 that could fit do, the group is refused and the
    revisit joins in the relieved map. Measured: none, recall 0.978, ATE 0.85 m (the oracle's
    0.88; GNC-TLS none, recall 0.834). Since the thirty-seventh stop the large part of a refused
    revisit is tried in its window, and the group no longer joins (none, recall 0.975, 0.85 m):
    the judgement is no longer reached here, and the test holds the outcome. Judged on the count
    and credited with the loops it displaced: grid s12905
    (:func:`test_a_false_group_judged_on_the_count_answers_to_the_true_loops_it_displaced`) and
    rings s13587 and s13687."""
    row, oracle = _world_rows(tmp_path, "ring", 2000, 400, 13201, methods=("ilv+", "oracle"), group_size=20)
    assert row.false_positives == 0
    assert row.recall >= 0.97
    assert row.ate_rmse_m <= 1.1 * oracle.ate_rmse_m


@pytest.mark.slow
def test_revisits_of_several_places_past_the_last_accepted_loop_join_across_an_odometry_slip(tmp_path):
    """A heavy-tailed ring of 2,000 poses with 400 grouped outliers, seed 12219 (drawn at the
    seventeenth stop). Nothing was accepted past frame 1922; the true revisits of frames 1948-1999
    (of five places, with false clusters among them) were each refused on a bound in the map the
    odometry extended there, and the last 60 frames drifted: no false loop, but recall 0.928 and
    ATE 5.07 m, 6.9 times the oracle's (GNC-TLS 5.01 m, DCS 4.73 m). Now, at the end of the log,
    a refused cluster past the last accepted loop that revisits of other places agree with under
    heavy-tailed odometry joins with them: no false loop, recall 0.943, ATE 0.76 m (1.04 times
    the oracle's)."""
    run, oracle = _world_runs(tmp_path, "ring", 2000, 400, 12219, methods=("ilv+", "oracle"))
    oracle = oracle.row
    assert run.row.false_positives == 0
    assert run.row.recall >= 0.94
    assert run.row.ate_rmse_m <= 1.1 * oracle.ate_rmse_m
    assert any("past the last accepted loop" in note for note in run.result.last_step.notes)


@pytest.mark.slow
def test_small_clusters_refused_on_a_bound_that_fit_the_final_map_are_tried_again(tmp_path):
    """A ring of 2,000 poses whose declared noise is off by a factor (``misdeclared``) with 400
    grouped outliers, seed 12400 (drawn at the eighteenth stop). At the third window a true pair
    (frames 1647 and 1649 to 568) and a true single loop (1704 to 464) were refused on a bound, in
    a map that later loops moved; they fit the final map at 0.2 gates or less, but only refused
    clusters of ``frontier_min_loops`` loops or more, or refused by a solve, were tried again:
    recall 0.995 (GNC-TLS and DCS 1.000), ATE 0.269 m (the oracle's 0.261). Now a refused cluster
    of any size whose loops fit the final map, the test that the window applies to new ones, is
    tried once more: no false loop, recall 1.000, the oracle's ATE."""
    run, oracle = _world_runs(tmp_path, "ring", 2000, 400, 12400, methods=("ilv+", "oracle"), noise="misdeclared")
    oracle = oracle.row
    assert run.row.false_positives == 0
    assert run.row.recall == 1.0
    assert run.row.ate_rmse_m <= 1.01 * oracle.ate_rmse_m
    retried = next(note for note in run.result.last_step.notes if "tried once more against the final map" in note)
    assert "(1704↔464)" in retried and "(1647↔568)" in retried


@pytest.mark.slow
def test_a_local_outlier_between_frames_two_apart_is_not_tried_as_a_loop_across_a_drift(tmp_path, caplog):
    """A heavy-tailed grid of 2,000 poses with 400 local outliers (each between frames two
    apart), seed 13830 (drawn at the thirty-ninth stop). At the end of the log the lone refused
    loops inside the innovations' fitted tail are tried together
    (:meth:`ConsensusVerifier._retry_lone_in_tail`); under its first version a local outlier
    (frames 1822 to 1820, 1.4 gates off the final map, inside the tail's 2.3) joined with three
    true loops: 1 false loop. The odometry between frames two apart is tighter than the loop
    itself (the smallest generalised eigenvalue of the two covariances 0.30), so no drift of it
    explains the innovation, and the loop is not tried: none, and the three true loops (spanning
    340 to 896 frames) still join.

    Since the fortieth stop the retry under the looser odometry level
    (:meth:`ConsensusVerifier._retry_under_looser_level`) asks the same. It tried this loop here
    (refused); on grid-10k-heavy-local-1000-s12603 such a loop joined under it, that world's one
    false loop. Now only the true loops across long stretches are tried (340 frames or more
    here), and three join.

    Since the forty-first stop the retry of the near misses (:meth:`ConsensusVerifier._retry_near_misses`)
    asks it too of the clusters refused by their own solve: 15 local outliers were tried there,
    and refused (on grid-5k-heavy-local-1000-s13323 one joined). Now only loops across 50
    frames or more are."""
    import logging

    from lcv_replay.bench.suite import build_case_log
    from lcv_replay.bench.suites import world_cases
    from lcv_replay.bench.verify import load_inputs, verify_inputs

    case = world_cases(["grid"], [2000], ["heavy"], ["local"], [400], [13830])[0]
    with caplog.at_level(logging.DEBUG, logger="lcv_replay.verification.consensus"):
        run = verify_inputs(load_inputs(build_case_log(case, Path("/nonexistent"), tmp_path).path), "ilv+")
    assert run.row.false_positives == 0
    lone = next(note for note in run.result.last_step.notes if "lone loops inside the innovations' fitted tail" in note)
    assert all(pair in lone for pair in ("(378↔38)", "(1299↔509)", "(1372↔476)"))
    assert "(1822↔1820)" not in lone
    looser = next(note for note in run.result.last_step.notes if "under the looser odometry level" in note)
    assert all(pair in looser for pair in ("(1518↔130)", "(1568↔1024)", "(1618↔962)"))
    tried = [tuple(map(int, re.search(r"loop \d+ \((\d+)↔(\d+)\)", r.getMessage()).groups())) for r in caplog.records if "under the odometry level" in r.getMessage()]
    assert len(tried) == 5 and min(query - match for query, match in tried) > 300  # the local outliers (two frames) are not tried
    # nor by the retry of the near misses, which had refused them by their own solve
    near = [tuple(map(int, pair)) for r in caplog.records if "near miss tried again" in r.getMessage()
            for pair in re.findall(r"\((\d+)↔(\d+)\)", r.getMessage())]
    assert near and min(query - match for query, match in near) > 50
    passed_over = " ".join(r.getMessage() for r in caplog.records if "near miss not tried again" in r.getMessage())
    assert "(1822↔1820)" in passed_over and "(222↔220)" in passed_over


@pytest.mark.slow
def test_true_loops_refused_under_a_wrongly_shaped_loop_noise_are_tried_under_the_fitted_shape(tmp_path):
    """A grid of 2,000 poses with 400 grouped outliers whose declared covariances are off by their
    own factor on each axis (``anisotropic``), seed 12464 (drawn at the eighteenth stop): the loops
    are declared four times too tight along x and four times too loose along y and yaw. The one
    scale fitted to all three (0.11) leaves them 36 times too tight along x, and three true single
    loops with errors of about 3σ along x were refused, 7 to 12 gates off the final map: recall
    0.996 (GNC-TLS and DCS lower), ATE 0.154 m against the oracle's 0.159. Now the loops' shape
    is fitted axis by axis to the accepted clusters' cycles at the end of the log, and the refused
    loops near the final map are tried once more under it: no false loop, recall 1.000."""
    run, oracle = _world_runs(tmp_path, "grid", 2000, 400, 12464, methods=("ilv+", "oracle"), noise="anisotropic")
    assert run.row.false_positives == 0
    assert run.row.recall == 1.0
    assert run.row.ate_rmse_m <= 1.01 * oracle.row.ate_rmse_m
    retried = next(note for note in run.result.last_step.notes if "noise shape fitted axis by axis" in note)
    assert all(pair in retried for pair in ("(433↔287)", "(1169↔257)", "(1475↔115)"))


@pytest.mark.slow
def test_a_window_audit_takes_a_loop_out_once_when_its_revisit_failed_first(tmp_path, monkeypatch):
    """A grid of 2,000 poses with 400 grouped outliers and anisotropic mis-declared noise, seed
    12465, verified with iSAM2 relinearising positions at 0.2 m (tried at the twentieth stop, not
    kept): a window's audit failed a revisit and then one of its loops alone, named the loop twice,
    and removing it the second time raised "loop 43 is not in the graph". A loop already out is
    not tested again. (Under the default thresholds the audit does not meet this; the run equals
    the default's verdict: no false loop, recall 1.000.)"""
    import functools

    from lcv_replay.verification.pose_graph import IncrementalGraph

    monkeypatch.setattr(IncrementalGraph, "__init__", functools.partialmethod(IncrementalGraph.__init__, relinearize_position_m=0.2))
    (run,) = _world_runs(tmp_path, "grid", 2000, 400, 12465, noise="anisotropic")
    assert run.row.false_positives == 0
    assert run.row.recall == 1.0


@pytest.mark.slow
def test_a_map_in_a_wrong_minimum_gives_way_to_the_hypothesis_built_with_its_runs_solved(tmp_path):
    """A heavy-tailed ring of 2,000 poses with 400 grouped outliers, seed 9903 (drawn fresh).
    False groups bent the map early and true revisits were refused in it; the hypothesis built
    at the end, largest first, on one Gauss-Newton step per trial, held only 229 loops, as runs
    of accepted parts were refused on their one step, and its ``J`` was the higher (24,303
    against 19,548): 10 false loops, recall 0.487, ATE 23.2 m at the start of the ninth stop.
    Now a second build solves the accepted runs in full, and its ``J`` (16,310) is the lowest:
    measured no false loop, recall 0.870, ATE 4.72 m (the oracle's 4.33; GNC-TLS: 3 false loops,
    recall 0.857, 15.9 m)."""
    row, oracle = _world_rows(tmp_path, "ring", 2000, 400, 9903, methods=("ilv+", "oracle"))
    assert row.false_positives == 0
    assert row.recall >= 0.86  # above GNC-TLS's 0.857 here (DCS: lower)
    assert row.ate_rmse_m <= 1.1 * oracle.ate_rmse_m


@pytest.mark.slow
@pytest.mark.xfail(strict=True, raises=AssertionError, reason="known failure (issue 16): a false group still wins; see docs/verification-bench.md, 'Fifth stop' and 'Fifteenth stop'")
def test_a_fresh_heavy_tailed_ring_where_a_false_group_still_wins(tmp_path):
    """A heavy-tailed ring of 2,000 poses with 400 grouped outliers (groups of 20), seed 11604
    (drawn at the fourteenth stop), on which ``ilv+`` still accepts a false group (9900, listed
    here until the twenty-third stop, is now
    ``test_a_false_group_beside_a_true_revisit_that_contradicts_it_is_flagged_ambiguous``; 13511
    until the twenty-ninth, now
    ``test_a_false_group_contradicted_by_a_true_revisit_that_fits_without_it_is_flagged``): the last
    12 loops of a false group (frames 1977-1988 to 977-988) lie after every other accepted loop,
    at the free end of the trajectory, and join in a joint try at the fourth window; left out of
    the final map they lower its chi-square by 114 against their cluster gate of 129, as true
    revisits at the end of a log do (recall 0.97, ATE 4.1 times the oracle's). GNC-TLS accepts
    the same 12 (recall 0.83), DCS 32 false loops.

    Strict: when a change fixes it, this test fails until the mark is removed."""
    (row,) = _world_rows(tmp_path, "ring", 2000, 400, 11604, group_size=20)
    assert row.false_positives == 0


@pytest.mark.slow
@pytest.mark.xfail(strict=True, raises=AssertionError, reason="known failure (issue 16): a false group still wins; see docs/verification-bench.md, 'Forty-eighth stop'")
def test_a_fresh_heavy_tailed_ring_where_a_false_group_of_20_still_wins_at_the_forty_eighth_stop(tmp_path):
    """A heavy-tailed ring of 2,000 poses with 400 grouped outliers (groups of 20), seed 14416,
    drawn at the forty-eighth stop, on which ``ilv+`` accepts a false group (GNC-TLS none): after
    a false group of 8 accepted under the looser odometry level is flagged on the count, the 20
    loops that join in the map relieved of it are a false group (1947-1966 to 167-186); judged
    again, they hold on their cluster gate (the chi-square falls by 213.9 without them, against
    215.6), so they stay (ATE 9.9 times the oracle's). Their match frames lie in the stretch
    before the first lap (frames 0-331), which no other accepted loop ties to the rest of the
    map: only the odometry checks them. (s14390, listed here until the forty-ninth stop, is now
    ``test_small_true_clusters_a_false_group_blocks_contest_it_together``.)

    Strict: when a change fixes it, this test fails until the mark is removed."""
    (row,) = _world_rows(tmp_path, "ring", 2000, 400, 14416, group_size=20)
    assert row.false_positives == 0


@pytest.mark.slow
def test_small_true_clusters_a_false_group_blocks_contest_it_together(tmp_path):
    """A heavy-tailed ring of 2,000 poses with 400 grouped outliers, seed 14390 (drawn at the
    forty-eighth stop). Around frame 1030 the robot crosses three earlier stretches in 30 frames,
    and the true loops there form small clusters, one per stretch: 1003-1008 to 379-384 (3
    loops), 1015-1017 to 280 (2), 1023-1033 to 256-264 (4) and one more of 2. A false group of 8
    (1025-1032 to 369-376), larger than each, joined first at the third window; the small ones
    were then refused as implausible, named no opponent and were never contested, and the group
    was kept to the end: 8 false loops, ATE 7.17 m (13.7 times the oracle's; GNC-TLS accepts
    none). Now, at the end of the log, the refused clusters that a cluster accepted on the count
    blocks contest it together where only together they outnumber it: they win, measured no
    false loop, recall 0.986, ATE 0.53 m (the oracle's 0.52). A strict known failure at the
    forty-eighth stop."""
    from lcv_replay.bench.verify import verify_inputs

    inputs = _world_inputs(tmp_path, "ring", 2000, 400, 14390)
    run, oracle = verify_inputs(inputs, "ilv+"), verify_inputs(inputs, "oracle").row
    group = {c.pair for c in inputs.candidates if 1025 <= c.query_frame <= 1032 and 369 <= c.match_frame <= 376}
    accepted = _accepted_pairs(run)
    assert len(group) == 8 and not group & inputs.true_pairs and not group & accepted
    assert {(1023, 256), (1003, 379)} <= accepted & inputs.true_pairs
    assert run.row.false_positives == 0
    assert run.row.ate_rmse_m <= 1.1 * oracle.ate_rmse_m


@pytest.mark.slow
def test_a_refused_revisit_is_contested_against_a_group_that_claims_its_query_frames_elsewhere(tmp_path):
    """A heavy-tailed ring of 2,000 poses with 400 grouped outliers (groups of 20), seed 13597
    (drawn at the thirty-second stop). At the last window the true revisit of frames 1501-1998 to
    1149-1700 (261 loops, after 500 frames without an accepted loop) was refused on one
    Gauss-Newton step, and a false group of 20 (1790-1809 to 1007-1026) took the free end in a
    trial. The revisit named two accepted true revisits as opponents and lost to them, and its
    end-of-log search against the group was lost on one step: 20 false loops, recall 0.594, ATE
    27.8 m (the oracle's 1.79; GNC-TLS and DCS none, recall 0.834 and 0.832). Now a refused
    cluster is also contested against the accepted clusters that claim other places for its
    query frames, and at the end of the log a search whose challenger outnumbers its side is
    solved in full: measured none, recall 0.982, ATE 1.89 m. A strict known failure at the
    thirty-second stop."""
    from lcv_replay.bench.verify import verify_inputs

    inputs = _world_inputs(tmp_path, "ring", 2000, 400, 13597, group_size=20)
    run, oracle = verify_inputs(inputs, "ilv+"), verify_inputs(inputs, "oracle").row
    group = {c.pair for c in inputs.candidates if 1790 <= c.query_frame <= 1809 and 1007 <= c.match_frame <= 1026}
    revisit = _true_revisit(inputs, (1501, 1998), (1149, 1700))
    assert len(group) == 20 and not group & inputs.true_pairs and len(revisit) == 261
    accepted = _accepted_pairs(run)
    assert not accepted & group
    assert len(accepted & revisit) >= 250
    assert run.row.false_positives == 0
    assert run.row.recall >= 0.95
    assert run.row.ate_rmse_m <= 1.1 * oracle.ate_rmse_m


@pytest.mark.slow
def test_the_large_part_of_a_refused_revisit_is_tried_in_its_window_before_a_group_takes_the_free_end(tmp_path):
    """A heavy-tailed ring of 2,000 poses with 400 grouped outliers (groups of 20), seed 13609,
    drawn at the thirty-third stop. At the last window a cluster of 230 loops (the revisit of
    frames 1550-1998 to 1198-1646) fails its trial; its 78 loops up to frame 1769 join, and the
    other 152 went back to the pool until the end of the log. A false group of 20 (1923-1942 to
    1536-1555), which claims their query frames for a place 35 frames back along the road, then
    took the free end on the count, and at the end of the log the revisit's loops were judged in
    the map it bent: 20 false loops, recall 0.763, ATE 9.30 m (the oracle's 0.709; GNC-TLS and
    DCS none, recall 0.851); a strict known failure from the thirty-third to the thirty-sixth
    stop. Now the released loops are clustered again, and the cluster of 131 takes its turn in
    the same window, before the group (measured: none, recall 0.988, ATE 0.673 m)."""
    from lcv_replay.bench.verify import verify_inputs

    inputs = _world_inputs(tmp_path, "ring", 2000, 400, 13609, group_size=20)
    group = {c.pair for c in inputs.candidates if 1923 <= c.query_frame <= 1942 and 1536 <= c.match_frame <= 1555}
    if len(group) != 20 or group & inputs.true_pairs:  # the world itself changed: fail, do not pass on another world
        pytest.fail(f"ring s13609 no longer holds the false group of 20 at 1923-1942 to 1536-1555 ({len(group)} pairs)")
    run = verify_inputs(inputs, "ilv+")
    assert not _accepted_pairs(run) & group
    assert run.row.false_positives == 0
    assert run.row.recall > 0.98
    assert run.row.ate_rmse_m < 1.1 * 0.709  # the oracle's


@pytest.mark.slow
@pytest.mark.parametrize(
    ("seed", "note", "recall"),
    [
        (13687, ("10 loops (1413-1422", "flagged ambiguous: the final map holds them only on the count", "6 loops of their stretches"), 0.98),
    ],
)
def test_a_false_group_two_frames_off_a_true_revisit_of_the_same_stretch_is_flagged(tmp_path, seed, note, recall):
    """Heavy-tailed rings of 2,000 poses with 400 grouped outliers (groups of 10) where a false
    group lies two frames along the road from the true revisit of the same stretch, and joins
    with it in one cluster (under the declared loop noise, 2 m, the two metres between them pass
    the pairwise gate).

    * s13587 (drawn at the thirty-second stop): the group (1255-1264 to 140-149) held 3 true loops
      of its query frames out; 8 false loops, recall 0.988, ATE 0.486 m (the oracle's 0.512), a
      strict known failure from the thirty-second to the thirty-sixth stop. Its 8 loops form a
      run (its short cycles 0.18 m off at the median, those with the true loops beside it 1.65 to
      2.00 m) that displaced refused loops of its query frames, so it is judged on the count,
      credited with the 4 of them that fit the map without it: flagged ambiguous, and the true
      loops join (measured: none accepted, recall 0.999, ATE 0.511 m).
    * s13687 (drawn at the thirty-seventh stop): the group (1413-1422 to 1063-1072) held 6 true
      loops out where the revisit's loops are sparse; no short cycle reaches it from before, so
      it is seamed on one side only: 10 false loops, recall 0.976, ATE 0.973 m (the oracle's
      1.006). It displaced the refused loops of its query frames, so it is judged on the count,
      credited with them: flagged ambiguous (measured: none accepted, recall 0.984, 0.983 m).

    s13587 is run by the ``regressions`` bench suite, not here (the suite's time budget)."""
    run, oracle = _world_runs(tmp_path, "ring", 2000, 400, seed, methods=("ilv+", "oracle"), group_size=10)
    _assert_fixed(run, oracle, recall=recall, note=note)
    assert run.row.ambiguous_true == 0


@pytest.mark.slow
def test_a_false_group_contradicted_by_a_true_revisit_that_fits_without_it_is_flagged(tmp_path):
    """A heavy-tailed ring of 2,000 poses with 400 grouped outliers (groups of 10), seed 13511
    (drawn at the twenty-sixth stop). A false group of 10 (frames 618-627 to 55-64) joins at the
    second window beside the true revisit of the start there (614-626 to 16-27, driven the other
    way, refused), and the start's later true revisits are refused in the map it bent. Judged
    again at the end it stayed (left out, 126 lower, under its cluster gate of 128): the loops
    its stretches displaced were solved together, 9 true ones with 20 of other false groups that
    claim the start (a rise of 1,741 gates), and nothing was credited: 10 false loops, recall
    0.889, ATE 9.46 m (the oracle's 0.555; GNC-TLS and DCS none, recall 0.850 and 0.843). Now
    the revisits among them that contradict the group are solved each alone: the true one fits
    the map without it, the two hypotheses' truncated costs differ by 0.5 gates, so the group is
    flagged ambiguous, leaves the map, and the start's true revisits join (measured: none
    accepted, 10 flagged, recall 0.980, 0.553 m). A strict known failure before the twenty-ninth
    stop."""
    run, oracle = _world_runs(tmp_path, "ring", 2000, 400, 13511, methods=("ilv+", "oracle"))
    _assert_fixed(run, oracle, recall=0.95, note=("10 loops (618-627↔55-64) flagged ambiguous", "a revisit of their stretches that contradicts them"))


# ----------------------------------------------------------------------------------------------
# The calibration: declared covariances far looser than the data (as in Vertigo Manhattan)
# ----------------------------------------------------------------------------------------------

LOOSE_ODOMETRY = np.diag([4.0, 4.0, 400.0])  # declared 0.5 m, 0.5 m, 0.05 rad per step; real: 2 cm, 0
LOOP_INFORMATION = (100.0, 0.0, 0.0, 100.0, 0.0, 10000.0)  # declared 10 cm, 10 cm, 0.01 rad; real: exact


def _loose_world(*, revisits: int | None = None):
    """True loops with exact relative poses up to 60 frames before the end; one false "same
    place" loop from the last frame to a place 15 m away. Under the declared covariances the open
    end is loose enough for the false loop to fit.

    ``revisits=None``: 2.5 laps, a loop every 5 frames (one long run of loops a lap: a few
    clusters). Otherwise that many short revisits of two loops (3 frames apart, 15 frames between
    revisits: each its own cluster), over as many laps as they need."""
    laps = 2.5 if revisits is None else 1.0 + (revisits * 15 + 70) / 200
    world = circle_world(num_false=0, laps=laps, yaw_bias_rad=0.0)
    n = len(world.odom)

    def measured(query: int, match: int) -> LoopCandidate:
        rel = se2.between(world.truth[match], world.truth[query])
        return LoopCandidate(query, match, T_match_query=Pose2D(*rel), information=LOOP_INFORMATION)

    lap = world.frames_per_lap
    if revisits is None:
        queries = list(range(lap + 5, n - 60, 5))
    else:
        queries = [q for start in range(lap + 5, n - 60, 15)[:revisits] for q in (start, start + 3)]
    true = tuple(measured(q, q - lap) for q in queries)
    false = LoopCandidate(n - 1, n - 1 - lap + 8, T_match_query=Pose2D(0.0, 0.0, 0.0), information=LOOP_INFORMATION)
    assert np.linalg.norm(world.truth[false.query_frame, :2] - world.truth[false.match_frame, :2]) > 14.0
    return dataclasses.replace(world, true_candidates=true, false_candidates=(false,)), false


def _run_loose(world, calibrate: bool):
    config = dataclasses.replace(SMALL, ilv_plus=dataclasses.replace(SMALL.ilv_plus, loops="measured", calibrate_gate=calibrate))
    verifier = make_verifier("ilv+", config, odometry_information=LOOSE_ODOMETRY)
    steps = feed(verifier, world)
    result = verifier.result()
    accepted = {result.constraints[i].candidate.pair for i in result.accepted_constraint_ids}
    return config, [s.gate_chi2 for s in steps] + [result.last_step.gate_chi2], accepted


@pytest.mark.parametrize("calibrate", [False, True])
def test_the_gate_calibrated_on_35_revisits_rejects_a_false_loop_at_the_loose_open_end(calibrate):
    """Thirty-five revisits: enough independent evidence to tighten the gate."""
    world, false = _loose_world(revisits=35)
    config, gates, accepted = _run_loose(world, calibrate)
    true = {c.pair for c in world.true_candidates}
    assert accepted & true == true
    if calibrate:
        assert gates[0] == config.ilv_plus.gate_chi2  # no loop yet in the first window
        assert gates[-1] < 0.1 * config.ilv_plus.gate_chi2  # calibrated on the pairwise cycles
        assert false.pair not in accepted
    else:
        assert set(gates) == {config.ilv_plus.gate_chi2}
        assert false.pair in accepted  # the failure the calibration fixes


def test_the_cycles_of_a_few_revisits_do_not_tighten_the_gate():
    """One long run of loops a lap gives a hundred pairwise cycles but a few clusters: their
    spread may widen the gate, never tighten it below the prior (KITTI 02 at alpha 1.00 fitted
    4.2 on three revisits and refused 13 of its 41 true loops)."""
    world, _ = _loose_world()
    config, gates, accepted = _run_loose(world, True)
    assert min(gates) >= config.ilv_plus.gate_chi2
    assert {c.pair for c in world.true_candidates} <= accepted


def test_ilv_plus_verifies_each_kind_of_loop_with_its_verifier():
    """``ilv+`` is the cluster-consensus verifier for measured loops and the hypothesis table for
    same-place loops; ``auto`` is decided by whoever knows the loops (replay, bench)."""
    from lcv_replay.verification.config import with_loop_kind
    from lcv_replay.verification.incremental import IncrementalVerifier

    auto = VerificationConfig()
    assert auto.ilv_plus.loops == "auto"
    assert isinstance(make_verifier("ilv+", auto), ConsensusVerifier)
    same_place = with_loop_kind(auto, same_place=True)
    assert same_place.ilv_plus.loops == "same-place"
    assert isinstance(make_verifier("ilv+", same_place), IncrementalVerifier)
    assert with_loop_kind(auto, same_place=False).ilv_plus.loops == "measured"
    assert with_loop_kind(same_place, same_place=False) is same_place  # a configured kind stays


def test_the_scale_fit_costs_match_a_solve_per_covariance():
    from lcv_replay.verification.consensus import student_t_scale_costs
    from lcv_replay.verification.consistency import mahalanobis_d2

    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(2, 200, 3, 3))
    loop, odometry = a @ np.swapaxes(a, 1, 2) * 1e-3, b @ np.swapaxes(b, 1, 2) * 1e-2
    error = rng.normal(size=(200, 3)) * 0.1
    log_loop, log_odometry = (g.ravel() for g in np.meshgrid(np.arange(-3, 3.01, 0.5), np.arange(-3, 3.01, 0.5), indexing="ij"))
    reference = []
    for sl, so in zip(log_loop, log_odometry):
        cov = 10.0**sl * loop + 10.0**so * odometry + 1e-12 * np.eye(3)
        d2 = mahalanobis_d2(error, cov)
        reference.append(np.sum(0.5 * np.linalg.slogdet(cov)[1] + 3.5 * np.log1p(d2 / 4.0)) + 0.5 * (sl - so) ** 2)
    costs = student_t_scale_costs(error, loop, odometry, log_loop, log_odometry)
    np.testing.assert_allclose(costs, reference, rtol=1e-9)
    assert int(np.argmin(costs)) == int(np.argmin(reference))



def _banked(verifier, ratio: float, count: int, seed: int) -> np.ndarray:
    """Bank ``count`` synthetic pairwise cycles whose errors have covariance
    ``ratio * L + O`` (random positive-definite parts, the loops' comparable to the odometry's)."""
    rng = np.random.default_rng(seed)
    a, b = rng.normal(size=(2, count, 3, 3))
    loop, odometry = a @ np.swapaxes(a, 1, 2) * 1e-2, b @ np.swapaxes(b, 1, 2) * 1e-2
    error = np.einsum("kij,kj->ki", np.linalg.cholesky(ratio * loop + odometry), rng.normal(size=(count, 3)))
    verifier._pair_ids = np.zeros((count, 2), dtype=np.int64)
    verifier._pair_error, verifier._pair_loop, verifier._pair_odometry = error, loop, odometry
    return np.arange(count)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_loops_weight_changes_only_where_the_cycles_reject_the_one_in_force(monkeypatch, seed):
    verifier = make_verifier("ilv+", CONFIG, odometry_information=ODOM_INFORMATION)
    applied = []
    monkeypatch.setattr(verifier, "_apply_scales", lambda sl, so: applied.append((sl, so)))
    # the weight in force (1) is 1.6 times the truth: beyond SCALE_CHANGE, but 40 cycles cannot
    # tell them apart
    verifier._fit_scales(_banked(verifier, 1.0 / 1.6, 40, seed), independent=40)
    assert applied == []
    # 2,000 cycles at a tenth of it reject it
    verifier._scales_fitted_on = 0
    verifier._fit_scales(_banked(verifier, 0.1, 2000, seed), independent=2000)
    assert len(applied) == 1
    assert 0.05 < applied[0][0] < 0.2 and applied[0][1] == 1.0


def test_noise_scales_that_gtsam_cannot_solve_leave_the_verifier_as_it_was(monkeypatch):
    """A rebuild under new noise scales that GTSAM fails (the end-of-log retry at the looser level
    runs one on the whole graph) changes nothing: the scales, the graph and its solution stay, and
    the run goes on."""
    from lcv_replay.verification import pose_graph

    world = circle_world(frames_per_lap=200, laps=2.0, true_every=4, num_false=0, yaw_bias_rad=0.0002)
    true = [_loop(world, q, q - 200) for q in range(205, 400, 4)]
    verifier, _, result = _run(world, true)
    graph, x = verifier.graph, verifier.graph.estimate().copy()
    scales = (verifier.loop_scale, verifier.odometry_scale)

    def fail(self, initial, loops=None):
        raise pose_graph.OptimisationFailed("iSAM2 update failed: Indeterminant linear system")

    monkeypatch.setattr(pose_graph.IncrementalGraph, "restart", fail)
    assert verifier._apply_scales(0.5, 0.5) is False
    assert (verifier.loop_scale, verifier.odometry_scale) == scales
    assert verifier.graph is graph
    np.testing.assert_array_equal(verifier.graph.estimate(), x)
    assert len(result.accepted_constraint_ids) == len(true)


def test_the_reported_map_is_the_working_one_where_no_odometry_step_slips():
    """The reported map loosens the odometry only at a step beyond the slip threshold; a Gaussian
    chain has none, so (the noise scales not moved) the trajectory is the working solution of the
    accepted loops and the odometry under the declared noise, unchanged."""
    world = circle_world(frames_per_lap=200, laps=2.0, true_every=2, num_false=0, yaw_bias_rad=0.0002)
    verifier, _, result = _run(world, [_loop(world, q, q - 200) for q in range(205, 400, 2)])
    assert len(result.accepted_constraint_ids) >= 95 and verifier.loop_scale == verifier.odometry_scale == 1.0
    assert verifier._odometry_chi2(result.trajectory, len(result.trajectory)).max() < verifier._slip_threshold(len(result.trajectory))
    assert verifier._slip_factors(result.trajectory) == {}
    assert np.array_equal(result.trajectory, verifier.graph.estimate())
