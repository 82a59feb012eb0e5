"""Stereo VO on rendered pairs with known motion (the synthetic street world at 320x240)."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest

from lcv_replay.errors import ConfigError, OdometryError
from lcv_replay.records import Pose2D, StereoCalibration
from lcv_replay.vo import stereo_vo as sv
from lcv_replay.vo.config import VoConfig
from tests.vo import rendered

MOTIONS = {
    "forward_1m": Pose2D(1.0, 0.0, 0.0),
    "forward_2m": Pose2D(2.0, 0.0, 0.0),
    "curve": Pose2D(0.8, 0.05, math.radians(5.0)),
    "sideways": Pose2D(0.0, 0.3, 0.0),
    "turn_in_place": Pose2D(0.2, 0.0, math.radians(-8.0)),
}


def estimate_motion(first: Pose2D, motion: Pose2D, config: VoConfig | None = None, *, calib=None, images=None) -> tuple[Pose2D, sv.PnpResult]:
    """Planar motion estimated from the stereo pair at ``first`` and the left image at ``first ∘ motion``."""
    config = config or VoConfig()
    calib = calib or rendered.calibration()
    (l0, r0), (l1, _) = images or (rendered.render_grey(first), rendered.render_grey(first.compose(motion)))
    keyframe = sv.make_keyframe(0, l0, r0, calib, config)
    pnp, _ = sv.track_keyframe(keyframe, l1, calib, config, None)
    assert pnp is not None
    T_body = sv.body_pose_from_camera(sv.invert_se3(pnp.T_cur_ref), sv.camera_mount())
    return sv.planar_from_se3(T_body), pnp


@pytest.fixture(scope="module")
def start_pose() -> Pose2D:
    return Pose2D(*rendered.route(12)[10])


@pytest.mark.parametrize("name", sorted(MOTIONS))
def test_relative_pose_of_rendered_pair(start_pose, name):
    motion = MOTIONS[name]
    estimate, pnp = estimate_motion(start_pose, motion)
    error = motion.between(estimate)
    step_m = math.hypot(motion.x_m, motion.y_m)
    # Tolerances at 320x240 (fx = 192 px): 3 % of the step + 1 cm, 0.1 deg (measured: <= 1.6 cm, 0.013 deg).
    assert math.hypot(error.x_m, error.y_m) < 0.03 * step_m + 0.01, (name, estimate)
    assert abs(math.degrees(error.yaw_rad)) < 0.1, (name, estimate)
    assert pnp.rmse_px < 1.0 and len(pnp.inliers) >= 100


def test_sequence_with_blank_dark_and_duplicate_frames(start_pose):
    truth = rendered.route(40)
    pairs = [rendered.render_grey(Pose2D(*p)) for p in truth]
    blank = np.full_like(pairs[0][0], 128)
    dark = np.full_like(pairs[0][0], 3)
    dark[::7, ::5] = 12  # a few bright dots do not make a dark image usable
    pairs[12] = (blank, pairs[12][1])
    pairs[20] = (dark, dark)
    pairs[30] = pairs[29]  # the camera driver sent the same frame twice
    result = sv.run_vo(pairs, rendered.calibration())

    statuses = {s.index: s.quality.status for s in result.steps}
    assert statuses[0] == sv.TrackStatus.FIRST
    assert statuses[12] == sv.TrackStatus.BLANK
    assert statuses[20] == sv.TrackStatus.DARK
    assert statuses[30] == sv.TrackStatus.DUPLICATE
    assert result.fallback_frames == [12, 20, 30]
    assert result.summary()["status_counts"] == {"first": 1, "ok": 36, "blank": 1, "dark": 1, "duplicate": 1}
    # The frame after a gap is tracked against the last good keyframe (bridging).
    assert result.steps[13].quality.keyframe_index == 11
    assert result.steps[21].quality.keyframe_index == 19

    origin = Pose2D(*truth[0])
    true_odom = np.array([origin.between(Pose2D(*p)) for p in truth])
    # Fallback frames hold a constant-velocity guess; frames after them are measured again.
    for step in result.steps:
        error = np.hypot(*(step.T_odom_base.as_array()[:2] - true_odom[step.index, :2]))
        if not step.quality.fallback:
            assert error < 0.02 * (step.index + 1) + 0.05, step
    final = Pose2D(*true_odom[-1]).between(result.steps[-1].T_odom_base)
    distance_m = float(np.sum(np.hypot(*np.diff(true_odom[:, :2], axis=0).T)))
    assert distance_m > 30
    assert math.hypot(final.x_m, final.y_m) < 0.01 * distance_m
    assert abs(math.degrees(final.yaw_rad)) < 0.5


def test_long_gap_reanchors_and_continues():
    truth = rendered.route(16)
    pairs = [rendered.render_grey(Pose2D(*p)) for p in truth]
    blank = np.zeros_like(pairs[0][0])
    for k in range(4, 11):  # 7 dark frames > max_bridge_frames = 5
        pairs[k] = (blank, blank)
    result = sv.run_vo(pairs, rendered.calibration(), VoConfig(max_bridge_frames=5))
    assert result.fallback_frames == list(range(4, 11))
    # After the gap the tracker re-anchors on frame 11 and tracks 12.. against it.
    assert result.steps[12].quality.status == sv.TrackStatus.OK
    assert result.steps[12].quality.keyframe_index == 11
    assert all(np.isfinite(result.poses).ravel())


def test_first_frame_blank_then_starts():
    truth = rendered.route(4)
    pairs = [rendered.render_grey(Pose2D(*p)) for p in truth]
    pairs[0] = (np.full_like(pairs[0][0], 90), pairs[0][1])
    result = sv.run_vo(pairs, rendered.calibration())
    assert [s.quality.status for s in result.steps] == [
        sv.TrackStatus.BLANK, sv.TrackStatus.NO_REFERENCE, sv.TrackStatus.OK, sv.TrackStatus.OK,
    ]


def test_distortion_is_applied_with_a_warning(start_pose, caplog):
    calib = rendered.calibration()
    coefficients = (-0.25, 0.06, 0.0, 0.0, 0.0)
    distorted_calib = StereoCalibration(**{**calib.__dict__, "distortion": coefficients})
    motion = Pose2D(1.0, 0.0, math.radians(3.0))
    pinhole = (rendered.render_grey(start_pose), rendered.render_grey(start_pose.compose(motion)))
    images = tuple(tuple(rendered.distort(im, calib, coefficients) for im in pair) for pair in pinhole)

    with caplog.at_level(logging.WARNING, logger="lcv_replay.vo.stereo_vo"):
        sv.StereoVoTracker(distorted_calib)
    assert "lens distortion" in caplog.text and "cv2.undistortPoints" in caplog.text

    corrected, _ = estimate_motion(start_pose, motion, calib=distorted_calib, images=images)
    ignored, _ = estimate_motion(start_pose, motion, calib=calib, images=images)
    error = motion.between(corrected)
    error_ignored = motion.between(ignored)
    # Measured: 1.9 cm / 0.06 deg with the distortion applied, 3.6 cm / 0.20 deg without.
    assert math.hypot(error.x_m, error.y_m) < 0.03 and abs(math.degrees(error.yaw_rad)) < 0.1
    assert abs(error_ignored.yaw_rad) > 2 * abs(error.yaw_rad)
    assert math.hypot(error_ignored.x_m, error_ignored.y_m) > math.hypot(error.x_m, error.y_m)


def test_image_and_calibration_checks():
    calib = rendered.calibration()
    tracker = sv.StereoVoTracker(calib)
    left = np.zeros((calib.height_px, calib.width_px), np.uint8)
    with pytest.raises(OdometryError, match=r"right image is 160x120 px but the calibration is for 320x240"):
        tracker.process(left, np.zeros((120, 160), np.uint8))
    with pytest.raises(OdometryError, match="8-bit"):
        sv.to_grey(np.zeros((4, 4), np.float32))
    with pytest.raises(OdometryError, match="baseline"):
        sv.StereoVoTracker(StereoCalibration(320, 240, 192.0, 192.0, 160.0, 120.0, 0.0))
    with pytest.raises(OdometryError, match="missing"):
        sv.check_calibration(None)
    with pytest.raises(ConfigError, match="vo.klt_window_px"):
        VoConfig(klt_window_px=10)


def test_bucketing_keeps_strongest_per_cell():
    pixels = np.array([[1, 1], [2, 2], [3, 3], [50, 1], [51, 2]], np.float32)
    response = np.array([1.0, 5.0, 3.0, 2.0, 4.0])
    keep = sv.bucket_strongest(pixels, response, bucket_px=10, per_bucket=2, max_total=10)
    assert keep.tolist() == [1, 4, 2, 3]  # cell (0,0): 1 and 2; cell (5,0): 4 and 3; strongest first
    assert sv.bucket_strongest(pixels, response, 10, 2, 3).tolist() == [1, 4, 2]
    assert sv.bucket_strongest(np.zeros((0, 2), np.float32), np.zeros(0), 10, 2, 3).shape == (0,)


def test_planar_projection_round_trip():
    rng = np.random.default_rng(3)
    for _ in range(20):
        pose = Pose2D(*rng.uniform(-50, 50, 2), rng.uniform(-math.pi, math.pi))
        T = np.eye(4)
        c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
        T[:2, :2] = [[c, -s], [s, c]]
        T[:2, 3] = pose.x_m, pose.y_m
        T[2, 3] = rng.uniform(-1, 1)  # height is dropped
        mount = sv.camera_mount((0.3, -0.1, 1.6))
        T_cam = sv.invert_se3(mount) @ T @ mount  # the same motion seen by the camera
        back = sv.planar_from_se3(sv.body_pose_from_camera(T_cam, mount))
        assert np.allclose(back.as_array(), pose.as_array(), atol=1e-9)
        assert np.allclose(sv.invert_se3(T) @ T, np.eye(4), atol=1e-12)
