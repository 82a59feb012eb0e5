"""ilv and ilv+: behaviour on synthetic worlds, the ilv+ statistics, and robustslam_kitti 06 alpha 0.50."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lcv_replay import se2
from lcv_replay.records import LoopCandidate, Pose2D
from lcv_replay.verification.base import ConstraintHistory, default_informations
from lcv_replay.verification.config import VerificationConfig
from lcv_replay.verification.hypotheses import Hypothesis
from lcv_replay.verification.ilv import PlusModel
from lcv_replay.verification.measurements import OdometryChain, loop_measurement
from lcv_replay.verification.registry import available_methods, make_verifier
from tests.shared_data import shared_path
from tests.verification.helpers import SMALL, TABLE, candidates_by_query, feed, feed_frames
from tests.verification.ilv_synthetic import ODOM_INFORMATION, circle_world

#: A measured loop (relative pose from geometric verification): sigma 10 cm, 10 cm, 0.01 rad.
MEASURED_INFORMATION = (100.0, 0.0, 0.0, 100.0, 0.0, 10000.0)


def _measured(world, query: int, match: int) -> LoopCandidate:
    """A candidate carrying the true relative pose, as robustslam_kitti's true loops do."""
    rel = se2.between(world.truth[match], world.truth[query])
    return LoopCandidate(query, match, T_match_query=Pose2D(*rel), information=MEASURED_INFORMATION, source="synthetic")


def _plus_model(world, loops: list[LoopCandidate]):
    """The ilv+ model over the whole odometry with ``loops`` admitted (ids in list order), its
    closure rounds off so that member sets stay as given; returns ``(model, constraints)``."""
    config = dataclasses.replace(SMALL, ilv_plus=dataclasses.replace(SMALL.ilv_plus, closure_rounds=0))
    chain = OdometryChain(ODOM_INFORMATION)
    chain.extend(world.odom)
    history = ConstraintHistory(default_informations(config, ODOM_INFORMATION)[1])
    history.admit(loops, len(world.odom))
    return PlusModel(chain, history, config), history.constraints


def _ate(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a[:, :2] - b[:, :2]) ** 2, axis=1))))


def test_both_methods_are_registered():
    methods = available_methods()
    assert {"ilv", "ilv+"} <= set(methods)
    assert make_verifier("ilv", VerificationConfig()).name == "ilv"
    assert make_verifier("ilv+", VerificationConfig()).name == "ilv+"


@pytest.fixture(scope="module")
def near_false_world():
    """True loops one lap apart with measured relative poses, plus false loops that claim "same
    pose" between places 7-9 m apart: inside the paper's 10 m radius, far outside 10 cm."""
    world = circle_world(num_false=0)
    true = tuple(_measured(world, q, q - world.frames_per_lap) for q in range(world.frames_per_lap + 5, len(world.odom), 10))
    near = tuple(
        LoopCandidate(q, q - world.frames_per_lap + 4, T_match_query=Pose2D(0.0, 0.0, 0.0), information=MEASURED_INFORMATION)
        for q in range(world.frames_per_lap + 12, len(world.odom), 40)
    )
    return dataclasses.replace(world, true_candidates=true, false_candidates=near)


def _run(method: str, world):
    verifier = make_verifier(method, SMALL, odometry_information=ODOM_INFORMATION)
    feed(verifier, world)
    result = verifier.result()
    true = {c.id for c in result.constraints if world.is_true(c.candidate)}
    return verifier, result, set(result.accepted_constraint_ids), true


def test_paper_radius_accepts_near_false_loops_and_ilv_plus_rejects_them(near_false_world):
    world = near_false_world
    distances = [np.linalg.norm(world.truth[c.query_frame, :2] - world.truth[c.match_frame, :2]) for c in world.false_candidates]
    assert all(5.0 < d < 10.0 for d in distances)
    _, _, accepted, true = _run("ilv", world)
    assert accepted & true == true
    assert accepted - true, "the 10 m test cannot reject loops between places 7-9 m apart"
    _, result, accepted_plus, _ = _run("ilv+", world)
    assert accepted_plus == true
    assert _ate(result.trajectory, world.truth) < 0.25 * _ate(world.odom, world.truth)


def test_ilv_plus_keeps_precision_with_far_false_loops():
    world = circle_world(num_false=15, seed=3)
    _, result, accepted, true = _run("ilv+", world)
    assert accepted <= true
    assert len(accepted) >= 0.9 * len(true)
    # the paper's own figure: constraints within T_p of the reported trajectory
    assert set(result.paper_consistent_ids) >= accepted


def test_innovation_covariance_matches_gtsam_marginals():
    """ilv+'s innovation (marginals of its reduced graph) equals the one from GTSAM's marginal
    covariances of the full graph, and shows an error that the solution including the loop hides."""
    import gtsam

    from lcv_replay.verification import pose_graph as pg

    world = circle_world(num_false=0, yaw_bias_rad=0.0005)
    loops = [_measured(world, q, q - world.frames_per_lap) for q in range(world.frames_per_lap + 5, len(world.odom), 10)]
    bad = loops[14]
    loops[14] = dataclasses.replace(bad, T_match_query=Pose2D(bad.T_match_query.x_m + 1.5, bad.T_match_query.y_m - 1.0, bad.T_match_query.yaw_rad))
    model, cons = _plus_model(world, loops)
    root = Hypothesis(0, None, (), 0, np.zeros(1, dtype=np.int64), world.odom[:1].copy())
    members = (2, 6, 10, 12, 13)
    without = model.solve(root, members, hypothesis_id=1, window=0, added=13)
    with_bad = model.solve(root, members + (14,), hypothesis_id=2, window=0, added=14)
    innovation = model.mahalanobis(without, np.array([14]))[0][0]
    in_sample = model.mahalanobis(with_bad, np.array([14]))[1][0]
    # the same innovation from GTSAM: full graph, marginal covariance of (x_m, x_q)
    graph = pg.build_graph(world.odom, ODOM_INFORMATION, [cons[c] for c in members], loop_default_information=ODOM_INFORMATION)
    full = pg.optimise_lm(graph, world.odom).poses
    c14 = cons[14]
    joint = gtsam.Marginals(graph, pg.initial_values(full)).jointMarginalCovariance(
        gtsam.KeyVector([c14.match_frame, c14.query_frame])
    ).fullMatrix()
    rel = gtsam.Pose2(*full[c14.match_frame]).between(gtsam.Pose2(*full[c14.query_frame]))
    jac = np.hstack([-rel.inverse().AdjointMap(), np.eye(3)])
    z, info = loop_measurement(c14, ODOM_INFORMATION)
    r = gtsam.Pose2.Logmap(gtsam.Pose2(*z).between(rel))
    expected = r @ np.linalg.solve(np.linalg.inv(info) + jac @ joint @ jac.T, r)
    assert innovation == pytest.approx(expected, rel=0.05)
    assert innovation > 10.0  # the 1.8 m error is visible before the loop is added ...
    assert in_sample < 0.5 * innovation  # ... and partly hidden by a solution that includes it


def test_leave_one_out_equals_the_chi2_drop_of_removing_the_loop():
    """The leave-one-out statistic of a member is what removing it saves in chi-square (two GTSAM
    solves), and flags a false loop at the open end of the trajectory that fits its own solution."""
    from lcv_replay.verification import pose_graph as pg

    world = circle_world(num_false=0, yaw_bias_rad=0.0005)
    n = len(world.odom)
    loops = [_measured(world, q, q - world.frames_per_lap) for q in range(world.frames_per_lap + 5, n - 40, 10)]
    # a false "same place" loop from the last frame to a place 7.5 m away along the lap
    loops.append(LoopCandidate(n - 1, n - 1 - world.frames_per_lap + 4, T_match_query=Pose2D(0.0, 0.0, 0.0), information=MEASURED_INFORMATION))
    model, cons = _plus_model(world, loops)
    root = Hypothesis(0, None, (), 0, np.zeros(1, dtype=np.int64), world.odom[:1].copy())
    true_ids = tuple(range(len(loops) - 1))

    def chi2_drop(members, c):
        def solve(ids):
            graph = pg.build_graph(world.odom, ODOM_INFORMATION, [cons[i] for i in ids], loop_default_information=ODOM_INFORMATION)
            return pg.optimise_lm(graph, world.odom).chi2

        return solve(members) - solve([i for i in members if i != c])

    true_only = model.solve(root, true_ids, hypothesis_id=1, window=0, added=None)
    for c, statistic in zip((0, 3, len(true_ids) - 1), model.leave_one_out(true_only, np.array([0, 3, len(true_ids) - 1]))):
        assert statistic == pytest.approx(chi2_drop(true_ids, c), rel=0.05, abs=0.2)
    everything = model.solve(root, true_ids + (len(loops) - 1,), hypothesis_id=2, window=0, added=None)
    false_id = np.array([len(loops) - 1])
    loo = model.leave_one_out(everything, false_id)[0]
    gate = model.plus.gate_chi2
    assert loo > gate and chi2_drop(true_ids + (len(loops) - 1,), len(loops) - 1) > gate
    assert model.mahalanobis(everything, false_id)[1][0] < gate  # it fits its own solution


def test_robustslam_kitti_06_alpha_050():
    from recorders.g2o import load_g2o, load_ground_truth, load_true_loops

    folder = shared_path("robustslam_kitti", "06")
    graph = load_g2o(folder / "kitti_06_alpha_0.50.g2o")
    odom = graph.odometry_poses()
    truth_pairs = load_true_loops(folder / "kitti_06_alpha_0.50_GT_LC.txt", len(odom))
    ground_truth = load_ground_truth(folder / "kitti_06_GT.g2o", len(odom))
    verifier = make_verifier("ilv+", TABLE, odometry_information=graph.odometry_information_matrix())
    feed_frames(verifier, odom, candidates_by_query(graph.loop_candidates()))
    result = verifier.result()
    accepted = {result.constraints[i].candidate.pair for i in result.accepted_constraint_ids}
    true = {c.candidate.pair for c in result.constraints} & truth_pairs
    assert len(result.constraints) == 126 and len(true) == 45
    tp = len(accepted & true)
    # measured: P 1.00, R 1.00 (45/45), ATE 2.19 m (oracle 2.19 m, odometry 3.6 m)
    assert tp == len(accepted), "precision must be 1.0"
    assert tp >= 43
    from lcv_replay.evaluation.metrics import absolute_trajectory_error

    assert absolute_trajectory_error(result.trajectory, ground_truth).rmse_m < 2.45
    # KITTI's loop errors are heavy-tailed: calibrating on the final best hypothesis (45 loops)
    # fits nu of about 3, and the gate widens to its ceiling, never tighter than configured
    plus = verifier.model.plus
    assert result.last_step.gate_chi2 == plus.gate_chi2  # the last window started before 30 loops
    assert verifier.model.recalibrate(verifier.hypotheses[result.ranking[0].id])
    fit = verifier.model.noise_fit
    assert fit is not None and fit.samples >= 40 and fit.dof < 10.0
    assert fit.quantile(plus.calibration_confidence) > plus.calibrated_max_chi2
    assert verifier.model.gate_chi2 == plus.calibrated_max_chi2


def test_ilv_plus_draws_prefer_plausible_constraints(near_false_world):
    world = dataclasses.replace(near_false_world, false_candidates=circle_world(num_false=12).false_candidates)
    verifier = make_verifier("ilv+", SMALL, odometry_information=ODOM_INFORMATION)
    feed(verifier, world)
    verifier.result()
    model = verifier.model
    ids = np.arange(len(verifier.history), dtype=np.int64)
    root = verifier.hypotheses[0]
    d2 = model.mahalanobis(root, ids)[0]
    weights = model.draw_weights(root, ids)
    plus = model.plus
    assert np.all((weights > 0) == (d2 < plus.explore_chi2))
    assert (weights == 0).any() and (weights > 0).any()
    order = np.argsort(d2)
    assert np.all(np.diff(weights[order]) <= 1e-12)  # never prefers a less plausible constraint


def test_ilv_plus_survives_failing_marginals(monkeypatch, caplog):
    """GTSAM failing on a hypothesis' marginals drops that child or falls back to the paper's
    uniform draw; it never ends the run."""
    from lcv_replay.verification import pose_graph as pg

    def fail(*args, **kwargs):
        raise pg.OptimisationFailed("marginal covariances failed: indeterminant system (test)")

    monkeypatch.setattr(pg, "relative_covariances", fail)
    world = circle_world(num_false=5, seed=1)
    verifier = make_verifier("ilv+", SMALL, odometry_information=ODOM_INFORMATION)
    with caplog.at_level("WARNING"):
        feed(verifier, world)
        result = verifier.result()
    assert len(result.trajectory) == len(world.odom)
    assert "uniform draw" in caplog.text
