"""The TF buffer against chains computed by hand: composition, inversion, interpolation, gaps, errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lcv_replay.errors import RecorderError
from recorders.tf_buffer import TfBuffer, interpolate_poses, parse_frame_pair, slerp


def yaw_q(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def planar(T: np.ndarray) -> tuple[float, float, float]:
    return float(T[0, 3]), float(T[1, 3]), math.atan2(T[1, 0], T[0, 0])


S = 1_000_000_000


@pytest.fixture
def robot() -> TfBuffer:
    """map -> odom (static: 1 m along x, turned 90 deg), odom -> base_link (moving), two sensors on base_link.

    odom -> base_link: t = 0 s at the origin heading 0; t = 10 s at (2, 0) heading 90 deg.
    base_link -> camera: (0.5, 0, 1.0), pitched down 90 deg about y (an optical frame looks along its z).
    base_link -> laser: (-0.2, 0.1, 0.3), no rotation.
    """
    tf = TfBuffer()
    tf.add("map", "odom", 0, (1.0, 0.0, 0.0), yaw_q(math.pi / 2), static=True)
    tf.add("odom", "base_link", 0, (0.0, 0.0, 0.0), yaw_q(0.0))
    tf.add("/odom", "/base_link", 10 * S, (2.0, 0.0, 0.0), yaw_q(math.pi / 2))  # ROS 1 style names
    s = math.sqrt(0.5)
    tf.add("base_link", "camera", 0, (0.5, 0.0, 1.0), (0.0, s, 0.0, s), static=True)
    tf.add("base_link", "laser", 0, (-0.2, 0.1, 0.3), (0.0, 0.0, 0.0, 1.0), static=True)
    return tf


def test_chain_through_a_static_and_an_interpolated_edge(robot: TfBuffer) -> None:
    # At t = 5 s, odom -> base_link is halfway: (1, 0), heading 45 deg (slerp).
    # map -> base_link = map -> odom (1, 0, 90 deg) o (1, 0, 45 deg) = (1 + 0, 0 + 1, 135 deg).
    T = robot.lookup("map", "base_link", [5 * S], max_gap_ns=20 * S)[0]
    assert planar(T) == pytest.approx((1.0, 1.0, math.radians(135)))
    # The reverse lookup is the inverse.
    T_inv = robot.lookup("base_link", "map", [5 * S], max_gap_ns=20 * S)[0]
    assert np.allclose(T_inv @ T, np.eye(4))
    # At the samples themselves, no interpolation.
    T0, T10 = robot.lookup("odom", "base_link", [0, 10 * S], max_gap_ns=20 * S)
    assert planar(T0) == pytest.approx((0.0, 0.0, 0.0)) and planar(T10) == pytest.approx((2.0, 0.0, math.pi / 2))


def test_sibling_frames_through_their_common_parent(robot: TfBuffer) -> None:
    # camera -> laser = inv(base -> camera) o (base -> laser). Camera axes in base: x_c = -z_b, y_c = y_b,
    # z_c = x_b (rotation of +90 deg about y). The laser origin relative to the camera origin in base
    # coordinates is (-0.7, 0.1, -0.7); in camera coordinates: (x_c, y_c, z_c) = (0.7, 0.1, -0.7).
    T = robot.lookup("camera", "laser", [3 * S], max_gap_ns=20 * S)[0]
    assert T[:3, 3] == pytest.approx([0.7, 0.1, -0.7])
    assert np.allclose(T[:3, :3], [[0, 0, -1], [0, 1, 0], [1, 0, 0]], atol=1e-12)
    # Same answer from a longer way round: camera -> map -> laser (map is a common ancestor too).
    T_cm = robot.lookup("camera", "map", [3 * S], max_gap_ns=20 * S)[0]
    T_ml = robot.lookup("map", "laser", [3 * S], max_gap_ns=20 * S)[0]
    assert np.allclose(T_cm @ T_ml, T)


def test_gaps_and_extrapolation_are_refused_beyond_max_gap() -> None:
    tf = TfBuffer()
    for k, x in ((0, 0.0), (1, 1.0), (5, 5.0)):
        tf.add("odom", "base", k * S, (x, 0.0, 0.0), yaw_q(0.0))
    T = tf.lookup("odom", "base", [int(0.5 * S), 3 * S, int(-0.5 * S), -2 * S, int(5.4 * S), 7 * S], max_gap_ns=S)
    x = T[:, 0, 3]
    assert x[0] == pytest.approx(0.5)  # inside a 1 s gap: interpolated
    assert np.isnan(x[1])  # inside the 4 s gap: refused
    assert x[2] == pytest.approx(0.0) and np.isnan(x[3])  # before the first sample: nearest within 1 s only
    assert x[4] == pytest.approx(5.0) and np.isnan(x[5])
    assert tf.sample_stamps("odom", "base").tolist() == [0, S, 5 * S]


def test_disconnected_frames_name_the_frames_seen(robot: TfBuffer) -> None:
    robot.add("world", "gps", 0, (0.0, 0.0, 0.0), yaw_q(0.0))
    with pytest.raises(RecorderError, match=r"no TF chain connects odom and gps.*separate trees.*tree of map: map, odom, base_link.*tree of world: world, gps.*frames seen: base_link, camera, gps, laser, map, odom, world"):
        robot.chain("odom", "gps")
    with pytest.raises(RecorderError, match=r"'base_footprint' never appears on /tf and /tf_static \(frames seen: base_link, camera"):
        robot.lookup("odom", "base_footprint", [0], max_gap_ns=S)
    with pytest.raises(RecorderError, match=r"frames of one TF tree \(e\.g\. odom:base_link\)"):  # the fix suggests the odometry pair
        robot.chain("odom", "nowhere")


def test_a_child_with_two_parents_keeps_the_busier_one(caplog) -> None:
    tf = TfBuffer()
    for k in range(3):
        tf.add("odom", "base", k * S, (float(k), 0.0, 0.0), yaw_q(0.0))
    tf.add("map", "base", 0, (9.0, 9.0, 0.0), yaw_q(0.0))
    assert tf.edges()["base"].parent == "odom"
    assert "several parents" in caplog.text


def test_slerp_and_interpolation_identities() -> None:
    rng = np.random.default_rng(1)
    q0, q1 = rng.normal(size=(50, 4)), rng.normal(size=(50, 4))
    q0 /= np.linalg.norm(q0, axis=1, keepdims=True)
    q1 /= np.linalg.norm(q1, axis=1, keepdims=True)
    same = lambda a, b: np.allclose(np.abs(np.sum(a * b, axis=1)), 1.0)  # q and -q are one rotation
    assert same(slerp(q0, q1, np.zeros(50)), q0) and same(slerp(q0, q1, np.ones(50)), q1)
    # Halfway, the angle to each end is the same.
    mid = slerp(q0, q1, np.full(50, 0.5))
    assert np.allclose(np.abs(np.sum(mid * q0, axis=1)), np.abs(np.sum(mid * q1, axis=1)))
    # Interpolating about z: yaw 0 -> 170 deg at 0.25 gives 42.5 deg (the shorter arc).
    t, q = interpolate_poses(np.array([0, 100]), np.zeros((2, 3)), np.array([yaw_q(0.0), yaw_q(math.radians(170))]), np.array([25]), 1000)
    assert 2 * math.atan2(q[0, 2], q[0, 3]) == pytest.approx(math.radians(42.5))


def test_frame_pair_parsing() -> None:
    assert parse_frame_pair("/odom:base_link", flag="--odom-from-tf") == ("odom", "base_link")
    for bad in ("odom", "odom:", "a:a", "a:b:c"):
        with pytest.raises(RecorderError, match="--odom-from-tf .* is not PARENT:CHILD"):
            parse_frame_pair(bad, flag="--odom-from-tf")
