"""pose_graph and measurements: numpy chi-square against GTSAM, the odometry chain, LM and GNC-TLS solves."""

from __future__ import annotations

import numpy as np
import pytest

from lcv_replay.errors import VerificationError
from lcv_replay.records import LoopCandidate, Pose2D
from lcv_replay import se2
from lcv_replay.verification import measurements as ms
from lcv_replay.verification import pose_graph as pg
from lcv_replay.verification.base import Constraint
from tests.verification.ilv_synthetic import ODOM_INFORMATION, as_constraints, circle_world

gtsam = pytest.importorskip("gtsam")


def test_numpy_chi2_equals_gtsam_factor_error():
    world = circle_world(frames_per_lap=60, laps=1.5)
    cons = as_constraints(world.candidates)
    graph = pg.build_graph(world.odom, ODOM_INFORMATION, cons, loop_default_information=ODOM_INFORMATION)
    n = len(world.odom)
    assert graph.size() == n + len(cons)
    poses = world.truth  # any poses other than the odometry give non-zero residuals
    values = pg.initial_values(poses)
    odo = ms.odometry_chi2(poses, world.odom, ODOM_INFORMATION)
    np.testing.assert_allclose(odo, [2 * graph.at(k + 1).error(values) for k in range(n - 1)], rtol=1e-9, atol=1e-12)
    for pos, c in enumerate(cons):
        expected = 2 * graph.at(pg.loop_factor_index(n, pos)).error(values)
        assert ms.loop_chi2(poses, c, ODOM_INFORMATION) == pytest.approx(expected, rel=1e-9)


def test_odometry_between_and_extend_by_odometry_chain_the_steps():
    world = circle_world(frames_per_lap=50, laps=1.0)
    steps = ms.odometry_between(world.odom)
    assert steps.shape == (49, 3)
    start = np.array([[5.0, -2.0, 0.7]])
    extended = ms.extend_by_odometry(start, world.odom)
    chained = [start[0]]
    for step in steps:
        chained.append(se2.compose(chained[-1], step))
    np.testing.assert_allclose(extended, np.array(chained), atol=1e-9)
    partial = ms.extend_by_odometry(world.truth[:20], world.odom)
    np.testing.assert_array_equal(partial[:20], world.truth[:20])
    with pytest.raises(VerificationError):
        ms.extend_by_odometry(world.truth, world.odom[:10])


def test_singular_information_names_the_constraint():
    bad = Constraint(7, LoopCandidate(30, 4, information=(1.0, 0.0, 0.0, 0.0, 0.0, 1.0)), 30)
    with pytest.raises(VerificationError, match=r"loop constraint 7 \(query 30, match 4\).*singular"):
        ms.loop_measurement(bad, ODOM_INFORMATION)
    world = circle_world(frames_per_lap=40, laps=1.0)
    with pytest.raises(VerificationError, match="loop constraint 7"):
        pg.build_graph(world.odom, ODOM_INFORMATION, [bad], loop_default_information=ODOM_INFORMATION)
    with pytest.raises(VerificationError, match="odometry"):
        pg.information_to_noise(np.zeros((3, 3)), what="odometry")
    with pytest.raises(VerificationError, match="shape"):
        ms.as_information_matrix(np.eye(2), what="x")


def test_identity_measurement_and_default_information_for_bare_candidates():
    c = Constraint(0, LoopCandidate(9, 2), 9)
    z, info = ms.loop_measurement(c, ODOM_INFORMATION)
    assert z == Pose2D(0.0, 0.0, 0.0)
    np.testing.assert_array_equal(info, ODOM_INFORMATION)
    c2 = Constraint(1, LoopCandidate(9, 2, T_match_query=Pose2D(1.0, 0.0, 0.1), information=(2, 0, 0, 3, 0, 4)), 9)
    z2, info2 = ms.loop_measurement(c2, ODOM_INFORMATION)
    assert z2 == Pose2D(1.0, 0.0, 0.1)
    np.testing.assert_array_equal(np.diag(info2), [2, 3, 4])


def test_constraint_to_unknown_frame_is_refused():
    world = circle_world(frames_per_lap=40, laps=1.0)
    c = Constraint(3, LoopCandidate(40, 2), 40)
    with pytest.raises(VerificationError, match=r"outside 0\.\.39"):
        pg.build_graph(world.odom, ODOM_INFORMATION, [c], loop_default_information=ODOM_INFORMATION)


def _ate(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a[:, :2] - b[:, :2]) ** 2, axis=1))))


def test_lm_with_true_loops_removes_drift_and_warm_start_converges_at_once():
    world = circle_world()
    cons = as_constraints(world.true_candidates)
    graph = pg.build_graph(world.odom, ODOM_INFORMATION, cons, loop_default_information=ODOM_INFORMATION)
    sol = pg.optimise_lm(graph, world.odom)
    assert sol.poses.shape == world.odom.shape
    assert _ate(sol.poses, world.truth) < 0.25 * _ate(world.odom, world.truth)
    assert sol.chi2 == pytest.approx(2 * graph.error(pg.initial_values(sol.poses)))
    again = pg.optimise_lm(graph, sol.poses)
    assert again.iterations <= 1
    np.testing.assert_allclose(again.poses, sol.poses, atol=1e-6)


def test_robust_kernel_reduces_the_pull_of_a_false_loop():
    world = circle_world(num_false=3)
    cons = as_constraints(world.candidates)
    plain = pg.optimise_lm(pg.build_graph(world.odom, ODOM_INFORMATION, cons, loop_default_information=ODOM_INFORMATION), world.odom)
    robust_graph = pg.build_graph(
        world.odom, ODOM_INFORMATION, cons, loop_default_information=ODOM_INFORMATION, robust=pg.RobustKernel("cauchy", 1.0)
    )
    robust = pg.optimise_lm(robust_graph, world.odom)
    assert _ate(robust.poses, world.truth) < _ate(plain.poses, world.truth)
    with pytest.raises(VerificationError, match="unknown robust kernel"):
        pg.RobustKernel("l1", 1.0)  # type: ignore[arg-type]


def test_a_robust_odometry_kernel_bends_the_map_at_a_slip_instead_of_around_it():
    """A wheel slip of 1.5 m sideways in one odometry step of the second lap, with a true loop
    at every frame: Gaussian odometry spreads the correction over the steps around the slip; with
    a Cauchy kernel on the odometry, the slipped step takes it."""
    world = circle_world(yaw_bias_rad=0.0, num_false=0, true_every=1)
    slip = 305
    steps = se2.between(world.odom[:-1], world.odom[1:])
    steps[slip, 1] += 1.5
    odom = np.zeros_like(world.odom)
    for k, step in enumerate(steps):
        odom[k + 1] = se2.compose(odom[k], step)
    cons = as_constraints(world.true_candidates)

    def solve(kernel):
        graph = pg.build_graph(odom, ODOM_INFORMATION, cons, loop_default_information=ODOM_INFORMATION, odometry_robust=kernel)
        return pg.optimise_lm(graph, odom).poses

    plain, robust = solve(None), solve(pg.RobustKernel("cauchy", 1.0))
    bent = {name: np.linalg.norm(se2.between(x[:-1], x[1:])[:, :2] - steps[:, :2], axis=1) for name, x in (("plain", plain), ("robust", robust))}
    assert int(np.argmax(bent["robust"])) == slip and bent["robust"][slip] > 1.2
    assert bent["plain"][slip] < 0.5
    around = slice(slip - 10, slip + 11)
    assert _ate(robust[around], world.truth[around]) < 0.5 * _ate(plain[around], world.truth[around])


def test_gnc_tls_keeps_true_and_drops_false_loops():
    world = circle_world(num_false=4)
    cons = as_constraints(world.candidates)
    n = len(world.odom)
    graph = pg.build_graph(world.odom, ODOM_INFORMATION, cons, loop_default_information=ODOM_INFORMATION)
    sol, weights = pg.optimise_gnc_tls(graph, world.odom, pg.odometry_factor_indices(n))
    assert weights.shape == (n + len(cons),)
    loop_w = weights[n:]
    truth = np.array([world.is_true(c.candidate) for c in cons])
    assert np.all(loop_w[truth] > 0.5)
    assert np.all(loop_w[~truth] < 0.5)
    assert _ate(sol.poses, world.truth) < 0.25 * _ate(world.odom, world.truth)


def test_optimiser_failure_is_reported_not_returned():
    world = circle_world(frames_per_lap=30, laps=1.0)
    graph = pg.build_graph(world.odom, ODOM_INFORMATION, [], loop_default_information=ODOM_INFORMATION)
    initial = world.odom.copy()
    initial[12, 1] = np.nan  # a NaN start: GTSAM returns NaNs silently
    with pytest.raises(pg.OptimisationFailed, match="non-finite"):
        pg.optimise_lm(graph, initial)
    unknown = np.vstack([world.odom, [[0.0, 0.0, 0.0]]])
    graph.add(gtsam.BetweenFactorPose2(30, 31, gtsam.Pose2(1.0, 0.0, 0.0), gtsam.noiseModel.Unit.Create(3)))
    with pytest.raises(pg.OptimisationFailed, match="Levenberg-Marquardt failed"):
        pg.optimise_lm(graph, unknown)  # key 31 has no initial value


def test_chain_segment_covariance_equals_gtsam_marginals():
    world = circle_world(frames_per_lap=60, laps=1.0)
    chain = ms.OdometryChain(ODOM_INFORMATION)
    chain.extend(world.odom[:25])  # grows in pieces like a replay
    chain.extend(world.odom[25:])
    graph = pg.build_graph(world.odom, ODOM_INFORMATION, [], loop_default_information=ODOM_INFORMATION)
    marginals = gtsam.Marginals(graph, pg.initial_values(world.odom))
    for a, b in [(0, 59), (10, 40), (33, 34)]:
        joint = marginals.jointMarginalCovariance(gtsam.KeyVector([a, b])).fullMatrix()
        rel = gtsam.Pose2(*world.odom[a]).between(gtsam.Pose2(*world.odom[b]))
        jac = np.hstack([-rel.inverse().AdjointMap(), np.eye(3)])  # d(x_a⁻¹ x_b), right perturbation at b
        np.testing.assert_allclose(chain.segment_covariance(np.array([a]), np.array([b]))[0], jac @ joint @ jac.T, rtol=1e-6, atol=1e-12)


def test_the_odometry_alone_bounds_the_marginals_of_a_graph_with_loops():
    """``ilv+``'s hypothesis built largest first proves refused parts implausible with marginals
    that must bound the new graph's from above: those of the odometry alone (from frame 0), since
    loops only shrink them. A loose bound is useless, so it is tight where no loop holds yet."""
    from lcv_replay.se2 import between as se2_between
    from lcv_replay.verification.pose_graph import IncrementalGraph, LoopFactor

    world = circle_world(num_false=0)
    chain = ms.OdometryChain(ODOM_INFORMATION)
    chain.extend(world.odom)
    frames = np.arange(len(world.odom))
    bound = chain.segment_covariance(np.zeros_like(frames), frames)
    loops = [c for c in world.true_candidates if c.query_frame < 300][::3]
    info = np.diag([25.0, 25.0, 400.0])
    graph = IncrementalGraph(ODOM_INFORMATION)
    graph.extend(world.odom)
    graph.update(add=[(k, LoopFactor(c.match_frame, c.query_frame, se2_between(world.truth[c.match_frame], world.truth[c.query_frame]), info)) for k, c in enumerate(loops)])
    held = max(c.query_frame for c in loops)
    shrunk = []
    for k in (5, 100, held, held + 40, len(frames) - 1):
        marginal = graph.marginal_covariance(k)
        gap = np.linalg.eigvalsh(bound[k] - marginal)
        assert gap.min() > -1e-6 * np.abs(bound[k]).max()  # an upper bound (up to the prior and the linearisation point)
        shrunk.append(np.trace(marginal) / np.trace(bound[k]))
    assert shrunk[2] < 0.5  # the loops hold the frame they reach
    assert shrunk[0] > 0.9  # and the first frames were held by the prior all along


def test_reduced_graph_and_bridge_match_the_full_graph():
    world = circle_world(num_false=0)
    cons = as_constraints(world.true_candidates)
    full = pg.optimise_lm(pg.build_graph(world.odom, ODOM_INFORMATION, cons, loop_default_information=ODOM_INFORMATION), world.odom)
    chain = ms.OdometryChain(ODOM_INFORMATION)
    chain.extend(world.odom)
    loops = [pg.loop_factor(c, ODOM_INFORMATION) for c in cons]
    nodes = np.unique(np.concatenate([[0], [c.match_frame for c in cons], [c.query_frame for c in cons]]))
    graph = pg.build_reduced_graph(chain, nodes, loops)
    assert graph.size() == len(nodes) + len(loops)
    reduced = pg.optimise_lm(graph, world.odom[nodes], keys=nodes)
    interpolated = chain.interpolate(nodes, reduced.poses, np.arange(len(world.odom)))
    np.testing.assert_allclose(interpolated[nodes], reduced.poses, atol=1e-9)
    assert np.abs(interpolated[:, :2] - full.poses[:, :2]).max() < 0.05  # first order: cm on a 60 m circle
    assert _ate(interpolated, world.truth) < 0.25 * _ate(world.odom, world.truth)
    with pytest.raises(VerificationError, match="not a node"):
        pg.build_reduced_graph(chain, nodes[nodes != nodes[3]], loops)


# --------------------------------------------------------------------------- iSAM2 working graph (ilv+)
def test_incremental_graph_matches_a_batch_solve_and_undoes_a_step_exactly():
    from lcv_replay.se2 import between as se2_between
    from lcv_replay.verification.pose_graph import IncrementalGraph, LoopFactor, build_graph, optimise_lm
    world = circle_world(num_false=0)
    loops = world.true_candidates[::3]
    info = np.diag([25.0, 25.0, 400.0])
    factors = [LoopFactor(c.match_frame, c.query_frame, se2_between(world.truth[c.match_frame], world.truth[c.query_frame]), info) for c in loops]
    graph = IncrementalGraph(ODOM_INFORMATION)
    graph.extend(world.odom[:300])
    graph.update()
    graph.extend(world.odom)
    graph.update(add=list(enumerate(factors)))
    assert graph.loop_ids == frozenset(range(len(factors))) and len(graph) == len(world.odom)
    batch = build_graph(world.odom, ODOM_INFORMATION, [], loop_default_information=info)
    from lcv_replay.verification.pose_graph import add_loop_factors

    add_loop_factors(batch, factors)
    reference = optimise_lm(batch, world.odom, relative_error_tol=1e-10).poses
    np.testing.assert_allclose(graph.estimate(), reference, atol=2e-3)

    before = graph.estimate().copy()
    wrong = LoopFactor(10, 390, np.array([0.0, 0.0, 0.0]), info)  # opposite sides of the circle
    graph.update(add=[(99, wrong)], relinearize=False)
    assert np.max(np.abs(graph.estimate() - before)) > 1.0
    graph.update(remove=[99], relinearize=False)  # one Gauss-Newton step, undone (to iSAM2's wildfire threshold)
    np.testing.assert_allclose(graph.estimate(), before, atol=1e-4)
    rebuilt = IncrementalGraph(ODOM_INFORMATION)  # the same loops given to the restart: the same state
    rebuilt.extend(world.odom)
    rebuilt.restart(before, loops=list(enumerate(factors)))
    graph.restart(before)  # relinearised at `before`: one more Gauss-Newton step from it
    np.testing.assert_array_equal(rebuilt.estimate(), graph.estimate())
    assert rebuilt.loop_ids == graph.loop_ids and rebuilt.updates == 1
    with pytest.raises(VerificationError, match="outside"):
        rebuilt.restart(before, loops=[(0, LoopFactor(0, len(world.odom), factors[0].measured, info))])
    np.testing.assert_allclose(graph.estimate(), before, atol=5e-3)
    sigma = graph.relative_covariance(factors[0].match_frame, factors[0].query_frame)
    assert np.all(np.linalg.eigvalsh(sigma) > 0) and np.all(np.linalg.eigvalsh(np.linalg.inv(info) - sigma) > 0)
    with pytest.raises(VerificationError, match="already in the graph"):
        graph.update(add=[(0, factors[0])])
    with pytest.raises(VerificationError, match="not in the graph"):
        graph.update(remove=[12345])


def test_the_incremental_estimate_is_isam2s_own_after_every_kind_of_change():
    """:meth:`IncrementalGraph.estimate` retracts iSAM2's cached linearisation point by its delta
    in numpy; it must equal GTSAM's ``calculateEstimate`` after one-step adds, relinearised
    solves (which move the linearisation point), removals, new frames and a restart, headings
    included (compared on the circle)."""
    from lcv_replay.se2 import between as se2_between
    from lcv_replay.verification.pose_graph import IncrementalGraph, LoopFactor

    world = circle_world(num_false=0)
    info = np.diag([25.0, 25.0, 400.0])

    def factor(m, q, bend=0.0):
        return LoopFactor(m, q, se2.compose(se2_between(world.truth[m], world.truth[q]), np.array([bend, 0.0, 0.0])), info)

    graph = IncrementalGraph(ODOM_INFORMATION)

    def check():
        reference = np.asarray(gtsam.utilities.extractPose2(graph._isam.calculateEstimate()))
        x = graph.estimate()
        np.testing.assert_allclose(x[:, :2], reference[:, :2], rtol=0.0, atol=1e-9)
        np.testing.assert_allclose(se2.wrap_angles(x[:, 2] - reference[:, 2]), 0.0, atol=1e-12)

    graph.extend(world.odom[:250])
    graph.update(relinearize=False)
    check()
    steps = [
        dict(add=[(1, factor(10, 210))], relinearize=False),
        dict(relinearize=True),
        dict(add=[(2, factor(40, 240, bend=3.0))], relinearize=True),  # a false loop: the map moves
        dict(remove=[2], relinearize=False),
        dict(remove=[1], relinearize=True),
    ]
    for change in steps:
        graph.update(**change)
        check()
    graph.extend(world.odom)
    graph.update(add=[(3, factor(5, 395)), (4, factor(150, 350))], relinearize=True)
    check()
    graph.restart(graph.estimate() + 0.01)
    check()
    graph.update(relinearize=True)
    check()


def test_a_rollback_puts_back_the_state_of_its_checkpoint_exactly_and_each_checkpoint_serves_once():
    """A false loop solved into the graph and refused: :meth:`IncrementalGraph.rollback` brings back
    the estimate, the loops, covariances and iSAM2's own estimate bit for bit, where taking the
    loop out and relinearising lands only near the solution before it. The versions of the undone
    branch no longer count as held (:meth:`holds_loops_of`); the graph goes on from there as one
    that never saw the loop."""
    from lcv_replay.se2 import between as se2_between
    from lcv_replay.verification.pose_graph import IncrementalGraph, LoopFactor

    world = circle_world(num_false=0)
    info = np.diag([25.0, 25.0, 400.0])
    factors = [LoopFactor(c.match_frame, c.query_frame, se2_between(world.truth[c.match_frame], world.truth[c.query_frame]), info) for c in world.true_candidates[::3]]

    def build():
        graph = IncrementalGraph(ODOM_INFORMATION)
        graph.extend(world.odom)
        graph.update(add=list(enumerate(factors[:-1])))
        return graph

    graph, twin = build(), build()
    before, version = graph.estimate().copy(), graph.version
    sigma = graph.relative_covariance(10, 390)
    point = graph.checkpoint()
    wrong = LoopFactor(10, 390, np.array([0.0, 0.0, 0.0]), info)  # opposite sides of the circle
    graph.update(add=[(99, wrong)], relinearize=True)
    assert np.max(np.abs(graph.estimate() - before)) > 1.0
    branch = graph.version
    graph.rollback(point)
    np.testing.assert_array_equal(graph.estimate(), before)
    np.testing.assert_array_equal(np.asarray(gtsam.utilities.extractPose2(graph._isam.calculateEstimate()))[:, :2], np.asarray(gtsam.utilities.extractPose2(twin._isam.calculateEstimate()))[:, :2])
    np.testing.assert_array_equal(graph.relative_covariance(10, 390), sigma)
    assert graph.loop_ids == frozenset(range(len(factors) - 1)) and graph.version > branch
    assert graph.holds_loops_of(version) and not graph.holds_loops_of(branch)
    with pytest.raises(VerificationError, match="serves one rollback"):
        graph.rollback(point)
    twin.update(add=[(99, wrong)], relinearize=True)
    twin.update(remove=[99], relinearize=True)  # the undo by removal: near, not back
    assert 0.0 < np.max(np.abs(twin.estimate() - before))
    graph.update(add=[(len(factors) - 1, factors[-1])])  # and it goes on as a graph that never held the loop
    fresh = IncrementalGraph(ODOM_INFORMATION)
    fresh.extend(world.odom)
    fresh.update(add=list(enumerate(factors)))
    np.testing.assert_allclose(graph.estimate(), fresh.estimate(), atol=2e-3)  # both converged to the threshold
    other = graph.checkpoint()
    graph.restart(graph.estimate())
    with pytest.raises(VerificationError, match="epoch"):
        graph.rollback(other)


def test_a_joint_marginal_queried_earlier_bounds_the_current_one_while_the_graph_holds_more_loops():
    """``ilv+``'s audit reuses a revisit's joint marginal queried at an earlier window, where the
    graph still holds every loop it held then: more frames and loops only add information, so
    the covariance of the revisit's relative poses under the earlier marginal bounds the current
    one from above, and the leave-out statistic under it is no smaller than the current one: a
    pass under it is a pass now (up to the relinearisation of the poses that moved, which on
    this circle leaves the relative poses' covariances ordered but not the frames' own). A
    restart relinearises everything and starts a new epoch, as does another graph."""
    from lcv_replay.se2 import between as se2_between
    from lcv_replay.verification.consistency import left_out_d2
    from lcv_replay.verification.pose_graph import IncrementalGraph, LoopFactor, pair_frames

    world = circle_world(frames_per_lap=200, laps=2.0, true_every=2, num_false=0, yaw_bias_rad=0.0002)
    info = np.diag([100.0, 100.0, 10000.0])
    rng = np.random.default_rng(3)

    def loop(q):
        z = se2.compose(se2_between(world.truth[q - 200], world.truth[q]), rng.normal(0.0, [0.1, 0.1, 0.01]))
        return LoopFactor(q - 200, q, z, info)

    graph = IncrementalGraph(ODOM_INFORMATION)
    graph.extend(world.odom[:260])
    graph.update(add=[(q, loop(q)) for q in range(205, 260, 4)])
    revisit = [q for q in range(229, 245, 4)]
    m, q = np.array([k - 200 for k in revisit]), np.array(revisit)
    frames = pair_frames(m, q)
    assert frames == sorted(set(m.tolist()) | set(q.tolist()))
    epoch, version, earlier = graph.epoch, graph.version, graph.joint_marginal(frames)
    graph.extend(world.odom)
    graph.update(add=[(k, loop(k)) for k in range(261, 400, 4)] + [(k, loop(k)) for k in range(231, 245, 4)])
    graph.update(add=[(1000, loop(300))], relinearize=False)
    graph.update(remove=[1000], relinearize=False)  # a trial undone: a loop added after, removed
    assert graph.epoch == epoch and graph.holds_loops_of(version)
    now = graph.joint_marginal(frames)
    # the relative poses' covariance, what the audit tests with, is ordered; the frames' own
    # (absolute, in the tangent space at each pose) are not quite: the map was relinearised
    held_earlier, held_now = graph.transport(m, q, frames, earlier), graph.transport(m, q, frames, now)
    assert np.linalg.eigvalsh(held_earlier - held_now).min() > 0.0
    assert np.trace(held_now) < 0.95 * np.trace(held_earlier)  # the new loops hold the revisit
    assert np.linalg.eigvalsh(earlier - now).min() < 0.0 < np.linalg.eigvalsh(earlier - now).max()
    np.testing.assert_allclose(graph.transport(m, q, frames, now), graph.joint_relative_covariance(m, q), rtol=1e-12, atol=1e-15)
    x = graph.estimate()
    factors = [loop(k) for k in revisit]
    r = se2.between_residuals(x, m, q, np.array([f.measured for f in factors]))
    covariances = np.array([np.linalg.inv(f.information) for f in factors])
    under_earlier = left_out_d2(r, covariances, graph.transport(m, q, frames, earlier))
    under_now = left_out_d2(r, covariances, graph.transport(m, q, frames, now))
    assert under_now is not None and under_earlier is not None and under_earlier > under_now
    graph.update(remove=[209])  # a loop it held then
    assert not graph.holds_loops_of(version) and graph.holds_loops_of(graph.version)
    graph.restart(x)
    assert graph.epoch != epoch
    assert IncrementalGraph(ODOM_INFORMATION).epoch not in (epoch, graph.epoch)


def test_covariances_from_a_fresh_elimination_equal_isam2s_and_serve_only_the_version_they_were_built_at():
    """Once iSAM2's covariance queries at one version of the graph have taken longer than a
    fresh elimination of the same linear system took (here: set to no time at all), the
    queries at that version are answered by GTSAM ``Marginals`` of the graph's factors
    linearised at iSAM2's linearisation point: the same numbers (joint and single marginals;
    a removed loop, a change without relinearisation and a relinearised one included); the
    next change brings the queries back to iSAM2."""
    from lcv_replay.se2 import between as se2_between
    from lcv_replay.verification.pose_graph import IncrementalGraph, LoopFactor

    world = circle_world(frames_per_lap=200, laps=2.0, true_every=2, num_false=0, yaw_bias_rad=0.0002)
    info = np.diag([100.0, 100.0, 10000.0])
    rng = np.random.default_rng(5)

    def loop(q, m=None):
        m = q - 200 if m is None else m
        z = se2.compose(se2_between(world.truth[m], world.truth[q]), rng.normal(0.0, [0.1, 0.1, 0.01]))
        return LoopFactor(m, q, z, info)

    graph = IncrementalGraph(ODOM_INFORMATION)
    graph.extend(world.odom)
    graph.update(add=[(q, loop(q)) for q in range(205, 400, 6)])
    graph.update(add=[(1000, loop(390, 50))], relinearize=False)  # a false loop, far off: theta and the estimate part
    graph.update(remove=[211])
    frames = [3, 50, 120, 390]
    wanted_joint, wanted_singles = graph.joint_marginal(frames), [graph.marginal_covariance(f) for f in frames]
    assert graph._covariance_source() is graph._isam
    graph._elimination_s = 0.0  # a fresh elimination costs nothing: the queries above took longer
    source = graph._covariance_source()
    assert source is not graph._isam and isinstance(source, gtsam.Marginals)
    fresh_joint, fresh_singles = graph.joint_marginal(frames), [graph.marginal_covariance(f) for f in frames]
    scale = np.abs(wanted_joint).max()
    np.testing.assert_allclose(fresh_joint, wanted_joint, rtol=0.0, atol=1e-8 * scale)
    for a, b in zip(fresh_singles, wanted_singles):
        np.testing.assert_allclose(a, b, rtol=0.0, atol=1e-8 * scale)
    assert graph._covariance_source() is source  # built once per version
    graph.update(remove=[1000])
    assert graph._covariance_source() is graph._isam  # a new version: iSAM2 first again
    np.testing.assert_allclose(graph.joint_marginal(frames)[:3, :3], graph.marginal_covariance(3), rtol=1e-9)


def test_incremental_graph_relinearises_on_headings_and_positions_by_their_own_thresholds():
    """Given the headings, a planar pose graph is linear in the positions: a loop that stretches a
    straight chain of 50 frames by 15 cm is solved exactly by one step. Under the default
    thresholds (0.05 on every axis) it relinearises 36 of the 50 frames; with 0.2 m on the
    position, at most the loop's two. A loop that turns the chain relinearises its frames either
    way and lands on the batch solution."""
    from lcv_replay.verification.pose_graph import IncrementalGraph, LoopFactor, add_loop_factors, build_graph, optimise_lm

    odom = np.column_stack([np.arange(50.0), np.zeros(50), np.zeros(50)])
    info = np.diag([1e4, 1e4, 1e4])

    def solved(loop: LoopFactor, **thresholds) -> tuple[IncrementalGraph, int]:
        graph = IncrementalGraph(ODOM_INFORMATION, **thresholds)
        graph.extend(odom)
        graph.update()
        before = graph.relinearized
        graph.update(add=[(0, loop)])
        return graph, graph.relinearized - before

    for measured, turned in (((49.15, 0.0, 0.0), False), ((49.0, 0.0, 0.1), True)):
        loop = LoopFactor(0, 49, np.array(measured), info)
        batch = build_graph(odom, ODOM_INFORMATION, [], loop_default_information=info)
        add_loop_factors(batch, [loop])
        reference = optimise_lm(batch, odom, relative_error_tol=1e-12).poses
        for position_m in (0.05, 0.2):
            graph, relinearized = solved(loop, relinearize_position_m=position_m)
            assert np.abs(graph.estimate() - odom).max() > (0.5 if turned else 0.1)  # the loop moved the chain
            if turned:
                assert relinearized > 20
                np.testing.assert_allclose(graph.estimate(), reference, atol=1e-3)
            else:
                assert (relinearized > 20) if position_m == 0.05 else (relinearized <= 2)
                np.testing.assert_allclose(graph.estimate(), reference, atol=1e-9)


def test_incremental_graph_refactors_with_qr_where_cholesky_calls_stiff_odometry_indeterminate():
    """Odometry declared far stiffer across than along the road (5 cm along, 1.6 mm across,
    0.011 rad of yaw per step): GTSAM 4.3's iSAM2 Cholesky calls a plain chain of 400 frames
    indeterminate (ringCity with such weights did too); the graph redoes the change with QR and
    keeps it, loops included."""
    from lcv_replay.verification.pose_graph import IncrementalGraph, LoopFactor

    rng = np.random.default_rng(0)
    steps = np.column_stack([np.full(400, 1.0), np.zeros(400), rng.normal(0.0, 0.02, 400)])
    odom = np.zeros((401, 3))
    for k in range(400):
        odom[k + 1] = se2.compose(odom[k : k + 1], steps[k : k + 1])[0]
    graph = IncrementalGraph(np.diag([400.0, 4e5, 7600.0]))
    graph.extend(odom[:50])
    graph.update(relinearize=False)
    assert graph.factorization == "CHOLESKY"  # 50 frames: Cholesky copes
    graph.extend(odom)
    graph.update(relinearize=False)
    assert graph.factorization == "QR"
    np.testing.assert_allclose(graph.estimate(), odom, atol=1e-9)
    info = np.diag([100.0, 100.0, 1e4])
    graph.update(add=[(7, LoopFactor(100, 390, se2.between(odom[[100]], odom[[390]])[0], info))])
    assert graph.loop_ids == frozenset({7})
    np.testing.assert_allclose(graph.estimate(), odom, atol=1e-6)  # an exact loop moves nothing
