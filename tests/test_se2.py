"""se2: the numpy SE(2) algebra against gtsam.Pose2, its identities, and the one-pose variants."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from lcv_replay import se2
from lcv_replay.records import Pose2D

gtsam = pytest.importorskip("gtsam")

pose = st.tuples(
    st.floats(-100, 100), st.floats(-100, 100), st.floats(-np.pi + 1e-9, np.pi - 1e-9)
)


def _random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.column_stack([rng.normal(0, 50, n), rng.normal(0, 50, n), rng.uniform(-np.pi, np.pi, n)])


@settings(max_examples=60, deadline=None)
@given(pose, pose, pose)
@example((0.0, 0.0, 1.1415926525897926), (0.0, 0.0, 2.000000001), (0.0, 0.0, 0.0))  # a heading of pi: GTSAM says pi, we say -pi
def test_se2_ops_match_gtsam(a, b, z):
    pa, pb, pz = gtsam.Pose2(*a), gtsam.Pose2(*b), gtsam.Pose2(*z)
    comp = pa.compose(pb)
    got = se2.compose(np.array(a), np.array(b))
    np.testing.assert_allclose(got[:2], [comp.x(), comp.y()], atol=1e-9)
    assert abs(se2.wrap_angles(got[2] - comp.theta())) < 1e-9  # -pi and pi are one heading
    betw = pa.between(pb)
    got = se2.between(np.array(a), np.array(b))
    np.testing.assert_allclose(got[:2], [betw.x(), betw.y()], atol=1e-9)
    assert abs(se2.wrap_angles(got[2] - betw.theta())) < 1e-9
    inv = pa.inverse()
    np.testing.assert_allclose(se2.inverse(np.array(a)), [inv.x(), inv.y(), inv.theta()], atol=1e-9)
    err = pz.inverse().compose(betw)
    # GTSAM's closed form loses digits for |theta| < ~1e-4 (cancellation); ours switches to a series.
    tol = 1e-7 if abs(err.theta()) > 1e-4 else 1e-4
    np.testing.assert_allclose(se2.logmap(np.array([err.x(), err.y(), err.theta()])), gtsam.Pose2.Logmap(err), atol=tol)


def test_compose_with_inverse_is_identity():
    rng = np.random.default_rng(3)
    a, b = _random_poses(rng, 100), _random_poses(rng, 100)
    np.testing.assert_allclose(se2.between(a, a), 0.0, atol=1e-9)
    np.testing.assert_allclose(se2.compose(a, se2.inverse(a)), 0.0, atol=1e-9)
    np.testing.assert_allclose(se2.compose(a, se2.between(a, b))[:, :2], b[:, :2], atol=1e-9)
    np.testing.assert_allclose(se2.between(a, b), se2.compose(se2.inverse(a), b), atol=1e-9)


def test_expmap_and_adjoint_match_gtsam():
    rng = np.random.default_rng(5)
    for _ in range(20):
        xi = rng.normal(size=3) * [3.0, 3.0, 1.0]
        T = rng.normal(size=3) * [30.0, 30.0, 1.0]
        e = gtsam.Pose2.Expmap(xi)
        np.testing.assert_allclose(se2.expmap(xi), [e.x(), e.y(), e.theta()], atol=1e-9)
        np.testing.assert_allclose(se2.adjoint(T), gtsam.Pose2(*T).AdjointMap(), atol=1e-12)
        np.testing.assert_allclose(se2.adjoint_inverse(T) @ se2.adjoint(T), np.eye(3), atol=1e-9)
        np.testing.assert_allclose(se2.logmap(se2.expmap(xi)), xi, atol=1e-9)


def test_one_pose_variants_equal_the_array_functions_exactly():
    """Pose2D and the per-frame hot paths use the float variants: same arithmetic, same bits."""
    rng = np.random.default_rng(11)
    a, b = _random_poses(rng, 200), _random_poses(rng, 200)
    for pa, pb, ca, bw, inv in zip(a, b, se2.compose(a, b), se2.between(a, b), se2.inverse(a)):
        assert Pose2D(*pa).compose(Pose2D(*pb)) == tuple(ca)
        assert Pose2D(*pa).between(Pose2D(*pb)) == tuple(bw)
        assert Pose2D(*pa).inverse() == tuple(inv)
    assert se2.wrap_angle(3 * math.pi) == float(se2.wrap_angles(3 * math.pi)) == -math.pi


def test_matrices_and_transform_points_agree_with_compose():
    rng = np.random.default_rng(2)
    a, b = _random_poses(rng, 50), _random_poses(rng, 50)
    product = se2.matrices(a) @ se2.matrices(b)
    expected = se2.matrices(se2.compose(a, b))
    np.testing.assert_allclose(product, expected, atol=1e-9)
    moved = np.stack([se2.transform_points(T, b[k : k + 1])[0] for k, T in enumerate(a)])
    np.testing.assert_allclose(moved, se2.compose(a, b)[:, :2], atol=1e-9)


poses = st.tuples(
    st.floats(-50, 50), st.floats(-50, 50), st.floats(-math.pi, math.pi - 1e-9)
).map(lambda t: Pose2D(*t))


@settings(max_examples=50, deadline=None)
@given(st.lists(poses, min_size=1, max_size=30))
def test_compose_chain_matches_pose2d_and_inverts(steps: list[Pose2D]) -> None:
    chain = se2.compose_chain(np.array(steps))
    expected = Pose2D(0.0, 0.0, 0.0)
    for k, step in enumerate(steps):
        expected = expected.compose(step)
        assert chain[k + 1, :2] == pytest.approx(expected[:2], abs=1e-6)
        assert math.cos(chain[k + 1, 2] - expected.yaw_rad) == pytest.approx(1.0)
    back = se2.relative_steps(chain)
    assert np.allclose(back[:, :2], np.array(steps)[:, :2], atol=1e-6)
    assert np.allclose(np.cos(back[:, 2] - np.array(steps)[:, 2]), 1.0)


@settings(max_examples=30, deadline=None)
@given(poses)
def test_invert_measurement_transforms_the_information_by_the_adjoint(T: Pose2D) -> None:
    info = se2.information_matrix((554.2, -35.9, -388.4, 388.0, 525.4, 294517.3))
    T_inv, info_inv = se2.invert_measurement(T, info)
    # Covariances transform as Σ' = Ad Σ Adᵀ.
    ad = gtsam.Pose2(*T).AdjointMap()
    assert np.allclose(np.linalg.inv(info_inv), ad @ np.linalg.inv(info) @ ad.T, rtol=1e-6, atol=1e-12)
    T_back, info_back = se2.invert_measurement(T_inv, info_inv)
    assert tuple(T_back)[:2] == pytest.approx(tuple(T)[:2], abs=1e-9)
    assert np.allclose(info_back, info, rtol=1e-6, atol=1e-6)
    assert se2.upper_triangle(info) == pytest.approx((554.2, -35.9, -388.4, 388.0, 525.4, 294517.3))


def test_between_chi2_is_the_whitened_residual():
    rng = np.random.default_rng(4)
    poses = _random_poses(rng, 10)
    i, j = np.array([0, 3, 5]), np.array([2, 7, 9])
    measured = se2.between(poses[i], poses[j])
    np.testing.assert_allclose(se2.between_chi2(poses, i, j, measured, np.eye(3)), 0.0, atol=1e-18)
    shifted = se2.compose(measured, np.array([0.1, 0.0, 0.0]))  # z = rel ∘ (0.1, 0, 0): r = -(0.1, 0, 0)
    np.testing.assert_allclose(se2.between_chi2(poses, i, j, shifted, 4.0 * np.eye(3)), 4.0 * 0.01, rtol=1e-9)
