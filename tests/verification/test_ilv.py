"""ilv and ilv+: behaviour on synthetic worlds, the ilv+ statistics, and robustslam_kitti 06 alpha 0.50."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lcv_replay.records import LoopCandidate, Pose2D
from lcv_replay.verification.config import VerificationConfig
from lcv_replay import se2
from lcv_replay.verification.base import Constraint
from lcv_replay.verification.registry import available_methods, make_verifier
from tests.shared_data import shared_path
from tests.verification.ilv_synthetic import ODOM_INFORMATION, circle_world
from tests.verification.helpers import SMALL, candidates_by_query, feed, feed_frames

#: A measured loop (relative pose from geometric verification): sigma 10 cm, 10 cm, 0.01 rad.
MEASURED_INFORMATION = (100.0, 0.0, 0.0, 100.0, 0.0, 10000.0)


def _measured(world, query: int, match: int) -> LoopCandidate:
    """A candidate carrying the true relative pose, as robustslam_kitti's true loops do."""
    rel = se2.between(world.truth[match], world.truth[query])
    return LoopCandidate(query, match, T_match_query=Pose2D(*rel), information=MEASURED_INFORMATION, source="synthetic")


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


def test_leave_one_out_of_the_working_graph_equals_the_chi2_drop_of_removing_the_loop():
    """ilv+'s audit statistic of an accepted loop, ``rᵀ(R - Σ)⁻¹r`` with ``Σ`` from iSAM2's joint
    marginals, is what removing the loop saves in chi-square (two GTSAM solves); it flags a false
    loop at the open end of the trajectory that fits the solution holding it."""
    from lcv_replay.verification import pose_graph as pg
    from lcv_replay.verification.consistency import mahalanobis_d2
    from lcv_replay.verification.measurements import loop_chi2

    world = circle_world(num_false=0, yaw_bias_rad=0.0005)
    n = len(world.odom)
    loops = [_measured(world, q, q - world.frames_per_lap) for q in range(world.frames_per_lap + 5, n - 40, 10)]
    # a false "same place" loop from the last frame to a place 7.5 m away along the lap
    loops.append(LoopCandidate(n - 1, n - 1 - world.frames_per_lap + 4, T_match_query=Pose2D(0.0, 0.0, 0.0), information=MEASURED_INFORMATION))
    constraints = [Constraint(k, c, c.query_frame) for k, c in enumerate(loops)]
    factors = [pg.loop_factor(c, ODOM_INFORMATION) for c in constraints]
    graph = pg.IncrementalGraph(ODOM_INFORMATION)
    graph.extend(world.odom)
    graph.update(add=list(enumerate(factors)))

    def chi2_without(skip: int) -> float:
        batch = pg.build_graph(world.odom, ODOM_INFORMATION, [c for c in constraints if c.id != skip], loop_default_information=ODOM_INFORMATION)
        return pg.optimise_lm(batch, world.odom, relative_error_tol=1e-10).chi2

    everything = chi2_without(-1)
    x = graph.estimate()
    for c in (0, 3, len(loops) - 1):
        f = factors[c]
        r = se2.between_residuals(x, np.array([f.match_frame]), np.array([f.query_frame]), f.measured[None])
        remaining = np.linalg.inv(f.information) - graph.relative_covariance(f.match_frame, f.query_frame)
        statistic = mahalanobis_d2(r, remaining[None])[0]
        assert statistic == pytest.approx(everything - chi2_without(c), rel=0.05, abs=0.3)
    assert loop_chi2(x, constraints[-1], ODOM_INFORMATION) < 11.34  # it fits the solution holding it ...
    assert everything - chi2_without(len(loops) - 1) > 11.34  # ... but not the others


def test_robustslam_kitti_06_alpha_050():
    from recorders.g2o import load_g2o, load_ground_truth, load_true_loops

    folder = shared_path("robustslam_kitti", "06")
    graph = load_g2o(folder / "kitti_06_alpha_0.50.g2o")
    odom = graph.odometry_poses()
    truth_pairs = load_true_loops(folder / "kitti_06_alpha_0.50_GT_LC.txt", len(odom))
    ground_truth = load_ground_truth(folder / "kitti_06_GT.g2o", len(odom))
    verifier = make_verifier("ilv+", VerificationConfig(), odometry_information=graph.odometry_information_matrix())
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
    assert not result.ambiguous_constraint_ids


def test_ilv_plus_survives_a_failing_solver(monkeypatch, caplog):
    """GTSAM failing on an iSAM2 update refuses the loops it was adding and rebuilds the graph; it
    never ends the run."""
    from lcv_replay.verification import pose_graph as pg

    original = pg.IncrementalGraph.update
    calls = {"n": 0}

    def flaky(self, add=(), remove=(), *, relinearize=True):
        if add:
            calls["n"] += 1
            if calls["n"] == 1:
                raise pg.OptimisationFailed("iSAM2 update failed: indeterminant system (test)")
        return original(self, add, remove, relinearize=relinearize)

    monkeypatch.setattr(pg.IncrementalGraph, "update", flaky)
    world = circle_world(num_false=5, seed=1, yaw_bias_rad=0.0002)
    verifier = make_verifier("ilv+", SMALL, odometry_information=ODOM_INFORMATION)
    with caplog.at_level("WARNING"):
        feed(verifier, world)
        result = verifier.result()
    assert len(result.trajectory) == len(world.odom)
    assert "indeterminant system (test)" in caplog.text
