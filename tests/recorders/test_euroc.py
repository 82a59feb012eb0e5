"""EuRoC recorder: an ASL tree built from the real euroc_loop_pairs, rectified, read back."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from lcv_replay.errors import RecorderError
from lcv_replay.log.reader import open_log
from recorders.common import read_image
from recorders.euroc import EurocOptions, load_euroc_sequence, pair_stamps, read_camera_yaml, record_euroc
from tests.recorders.trees import build_euroc_tree


def _row_offsets(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """|dy| in pixels of cross-checked ORB matches between a stereo pair."""
    import cv2

    orb = cv2.ORB_create(1500)
    kl, dl = orb.detectAndCompute(left, None)
    kr, dr = orb.detectAndCompute(right, None)
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(dl, dr)
    good = [m for m in matches if m.distance < 40]
    return np.array([abs(kl[m.queryIdx].pt[1] - kr[m.trainIdx].pt[1]) for m in good])


def test_euroc_round_trip_rectified(tmp_path: Path) -> None:
    tree = build_euroc_tree(tmp_path / "MH_01_easy")
    out = tmp_path / "euroc.mcap"
    stats = record_euroc(tree["root"], out)
    assert stats.frames == 4 and stats.has_images and stats.has_ground_truth and not stats.has_odometry
    with open_log(out) as log:
        assert log.info.frames == 4 and log.info.has_right_images
        assert np.array_equal(log.frame_stamps_ns, tree["stamps_ns"])
        calib = log.calibration
        # EuRoC's VI-sensor baseline is about 11 cm; rectified images keep their size, no distortion.
        assert calib.baseline_m == pytest.approx(0.110, abs=0.002)
        assert (calib.width_px, calib.height_px) == (752, 480) and calib.distortion == (0.0,) * 5
        assert log.info.metadata["dataset"] == "euroc/MH_01_easy"
        frames = list(log.frames())
        rectified = [(f.left.decode(), f.right.decode()) for f in frames]

    raw_dy = np.concatenate([_row_offsets(read_image(l), read_image(r)) for l, r in zip(tree["left"], tree["right"])])
    rect_dy = np.concatenate([_row_offsets(l, r) for l, r in rectified])
    # Rectification puts matches on the same row: sub-pixel, and far better than the raw pairs.
    assert len(rect_dy) > 200
    assert np.median(rect_dy) < 0.75 and np.mean(rect_dy < 2.0) > 0.8
    assert np.median(raw_dy) > 2.0 * np.median(rect_dy)

    gt = log.ground_truth()
    T = tree["T_world_body"]
    left_cam = read_camera_yaml(tree["root"] / "mav0" / "cam0" / "sensor.yaml")
    T_world_cam = T @ left_cam.T_body_camera
    # Position: the left camera centre; heading: its optical axis on the ground plane (within the
    # small rotation of the rectification).
    assert np.allclose(gt[:, :2], T_world_cam[:, :2, 3], atol=1e-9)
    heading = np.arctan2(T_world_cam[:, 1, 2], T_world_cam[:, 0, 2])
    assert np.all(np.abs(np.angle(np.exp(1j * (gt[:, 2] - heading)))) < math.radians(3.0))


def test_euroc_raw_images_and_no_ground_truth(tmp_path: Path) -> None:
    tree = build_euroc_tree(tmp_path / "V1", ground_truth=False)
    out = tmp_path / "raw.mcap"
    record_euroc(tree["root"] / "mav0", out, EurocOptions(rectify=False))
    with open_log(out) as log:
        assert not log.info.has_ground_truth
        calib = log.calibration
        assert calib.fx_px == pytest.approx(458.654) and calib.distortion[0] == pytest.approx(-0.28340811)
        for frame, left, right in zip(log.frames(), tree["left"], tree["right"]):
            assert np.array_equal(frame.left.decode(), read_image(left))
            assert np.array_equal(frame.right.decode(), read_image(right))


def test_euroc_tum_odometry_and_unpaired_images(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    tree = build_euroc_tree(tmp_path / "MH")
    cam1 = tree["root"] / "mav0" / "cam1" / "data.csv"
    lines = cam1.read_text().splitlines()
    cam1.write_text("\n".join(lines[:-1]) + "\n")  # the right camera lost its last image
    tum = tmp_path / "vo.txt"
    tum.write_text("".join(f"{s / 1e9:.9f} {0.1 * k} 0 {k} 0 0 0 1\n" for k, s in enumerate(tree["stamps_ns"])))
    with caplog.at_level("WARNING"):
        seq = load_euroc_sequence(tree["root"], EurocOptions(odometry=tum))
    assert "dropped 1 images without a stereo partner" in caplog.text
    assert len(seq.stamps_ns) == 3
    # Camera z forward -> body x; camera x right -> body -y.
    assert np.allclose(seq.odometry, [[0, 0, 0], [1, -0.1, 0], [2, -0.2, 0]])


def test_pair_stamps_tolerance() -> None:
    left = np.array([0, 100, 200, 300])
    right = np.array([1, 150, 299])
    li, ri = pair_stamps(left, right, 5)
    assert li.tolist() == [0, 3] and ri.tolist() == [0, 2]


def test_euroc_errors(tmp_path: Path) -> None:
    with pytest.raises(RecorderError, match="no mav0/cam0 folder"):
        load_euroc_sequence(tmp_path)
    tree = build_euroc_tree(tmp_path / "MH")
    yaml = tree["root"] / "mav0" / "cam1" / "sensor.yaml"
    yaml.write_text(yaml.read_text().replace("radial-tangential", "equidistant"))
    with pytest.raises(RecorderError, match="distortion model 'equidistant' is not supported"):
        load_euroc_sequence(tree["root"])
    yaml.write_text("%YAML:1.0\nintrinsics: [1, 2]\n")
    with pytest.raises(RecorderError, match="'T_BS' must list 16 numbers"):
        load_euroc_sequence(tree["root"])
    (tree["root"] / "mav0" / "cam0" / "data.csv").write_text("#timestamp [ns],filename\nabc,def\n")
    with pytest.raises(RecorderError, match="line 2: expected 'timestamp_ns,filename'"):
        load_euroc_sequence(tree["root"])
