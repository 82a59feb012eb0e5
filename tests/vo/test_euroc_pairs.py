"""Stereo matching and triangulation on real EuRoC pairs (MH/V1 Vicon room, 752x480, 11 cm baseline).

EuRoC images are raw (distorted, not rectified). Rectified with ``cv2.stereoRectify`` from the
sensor yaml files, the VO's row-constrained matching finds hundreds of stereo points at room depths;
on the raw pair the same constraint rejects almost everything.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from lcv_replay.records import StereoCalibration
from lcv_replay.vo import stereo_vo as sv
from lcv_replay.vo.config import VoConfig
from tests.shared_data import shared_path


def _sensor(name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(T_body_sensor (4, 4), K (3, 3), distortion (4,))`` from a EuRoC sensor yaml."""
    storage = cv2.FileStorage(str(shared_path("euroc_loop_pairs", name)), cv2.FILE_STORAGE_READ)
    node = storage.getNode("T_BS").getNode("data")
    T = np.array([node.at(i).real() for i in range(16)]).reshape(4, 4)
    fu, fv, cu, cv = (storage.getNode("intrinsics").at(i).real() for i in range(4))
    dist = np.array([storage.getNode("distortion_coefficients").at(i).real() for i in range(4)])
    return T, np.array([[fu, 0, cu], [0, fv, cv], [0, 0, 1.0]]), dist


@pytest.fixture(scope="module")
def rectification():
    T_left, K_left, d_left = _sensor("sensorLeft.yaml")
    T_right, K_right, d_right = _sensor("sensorRight.yaml")
    T_right_left = np.linalg.inv(T_right) @ T_left
    size = (752, 480)
    R1, R2, P1, P2, *_ = cv2.stereoRectify(
        K_left, d_left, K_right, d_right, size, T_right_left[:3, :3].copy(), T_right_left[:3, 3].reshape(3, 1).copy(),
        flags=cv2.CALIB_ZERO_DISPARITY, alpha=0,
    )
    maps = (
        cv2.initUndistortRectifyMap(K_left, d_left, R1, P1, size, cv2.CV_32FC1),
        cv2.initUndistortRectifyMap(K_right, d_right, R2, P2, size, cv2.CV_32FC1),
    )
    calib = StereoCalibration(752, 480, P1[0, 0], P1[1, 1], P1[0, 2], P1[1, 2], -P2[0, 3] / P2[0, 0])
    return maps, calib


@pytest.mark.parametrize("index", [0, 1, 2, 3])
def test_rectified_euroc_pair_triangulates_room_depths(rectification, index):
    (map_left, map_right), calib = rectification
    assert 0.10 < calib.baseline_m < 0.12  # EuRoC: 11 cm
    left = cv2.imread(str(shared_path("euroc_loop_pairs", f"left_img_{index}.png")), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(shared_path("euroc_loop_pairs", f"right_img_{index}.png")), cv2.IMREAD_GRAYSCALE)
    rect_left = cv2.remap(left, *map_left, cv2.INTER_LINEAR)
    rect_right = cv2.remap(right, *map_right, cv2.INTER_LINEAR)
    config = VoConfig()
    keyframe = sv.make_keyframe(index, rect_left, rect_right, calib, config)
    assert keyframe.size >= 250
    depth = keyframe.points_m[:, 2]
    assert 1.0 < float(np.median(depth)) < 8.0  # the Vicon room
    assert float(np.percentile(depth, 95)) < 30.0

    raw_calib = StereoCalibration(752, 480, 458.654, 457.296, 367.215, 248.375, calib.baseline_m)
    raw = sv.make_keyframe(index, left, right, raw_calib, config)
    assert raw.size < 0.2 * keyframe.size  # unrectified rows do not agree
