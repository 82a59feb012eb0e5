"""Stereo VO on real KITTI frames: sequence 06, frames 12 (stereo) -> 13 (left only).

3-D points come from the stereo pair of frame 12; their 2-D positions in the left image of frame 13
give the relative pose by PnP, compared with the ground truth in ``06.txt``.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from lcv_replay.errors import OdometryError
from lcv_replay.records import StereoCalibration
from lcv_replay.vo import stereo_vo as sv
from lcv_replay.vo.config import VoConfig
from tests.shared_data import shared_path

# KITTI odometry calibration of sequences 04-12 (shared/data/README.md).
KITTI_04_12 = StereoCalibration(
    width_px=1226, height_px=370, fx_px=707.0912, fy_px=707.0912, cx_px=601.8873, cy_px=183.1104,
    baseline_m=379.8145 / 707.0912,
)


def _load(name: str) -> np.ndarray:
    image = cv2.imread(str(shared_path("kitti06_frames", name)), cv2.IMREAD_GRAYSCALE)
    assert image is not None, name
    return image


def _gt_relative(first: int, second: int) -> np.ndarray:
    poses = np.loadtxt(shared_path("kitti06_frames", "06.txt")).reshape(-1, 3, 4)
    T = np.tile(np.eye(4), (2, 1, 1))
    T[0, :3], T[1, :3] = poses[first], poses[second]
    return np.linalg.inv(T[0]) @ T[1]


@pytest.fixture(scope="module")
def kitti_12_13():
    left12, right12, left13 = _load("kitti06-12.png"), _load("kitti06-12-R.png"), _load("kitti06-13.png")
    config = VoConfig()
    keyframe = sv.make_keyframe(12, left12, right12, KITTI_04_12, config)
    pnp, n_tracked = sv.track_keyframe(keyframe, left13, KITTI_04_12, config, None)
    return keyframe, pnp, n_tracked


def test_stereo_points_are_triangulated_along_rows(kitti_12_13):
    keyframe, _, _ = kitti_12_13
    assert keyframe.size >= 300
    z = keyframe.points_m[:, 2]
    assert np.all(z > 0)
    # A street scene seen from a car: most points within a few to ~100 m.
    assert 3.0 < float(np.median(z)) < 60.0
    # Points below the horizon (v > cy) are below the camera (y down > 0) and vice versa.
    below = keyframe.pixels_px[:, 1] > KITTI_04_12.cy_px + 5
    assert np.all(keyframe.points_m[below, 1] > 0)


def test_relative_pose_12_to_13_matches_ground_truth(kitti_12_13):
    _, pnp, n_tracked = kitti_12_13
    assert pnp is not None
    assert n_tracked >= 200 and len(pnp.inliers) >= 150
    assert pnp.rmse_px < 1.0
    T_12_13 = sv.invert_se3(pnp.T_cur_ref)
    T_gt = _gt_relative(12, 13)
    step_m = float(np.linalg.norm(T_gt[:3, 3]))
    assert step_m > 1.0  # the car moves ~1.19 m between the frames
    error = np.linalg.inv(T_12_13) @ T_gt
    # Tolerances: 5 % of the step in translation, 0.1 deg in rotation (measured: ~2 %, ~0.03 deg).
    assert np.linalg.norm(error[:3, 3]) < 0.05 * step_m
    assert math.degrees(sv.rotation_angle_rad(error[:3, :3])) < 0.1


def test_planar_projection_of_kitti_step_is_forward(kitti_12_13):
    _, pnp, _ = kitti_12_13
    T_body = sv.body_pose_from_camera(sv.invert_se3(pnp.T_cur_ref), sv.camera_mount())
    step = sv.planar_from_se3(T_body)
    assert 1.1 < step.x_m < 1.3  # forward (body x) along the camera's optical axis
    assert abs(step.y_m) < 0.05
    assert abs(step.yaw_rad) < math.radians(0.5)


def test_wrong_calibration_size_names_the_mismatch():
    left, right = _load("kitti06-12.png"), _load("kitti06-12-R.png")
    small = StereoCalibration(640, 480, 500.0, 500.0, 320.0, 240.0, 0.5)
    tracker = sv.StereoVoTracker(small)
    with pytest.raises(OdometryError, match=r"1226x370 px but the calibration is for 640x480"):
        tracker.process(left, right)
