"""``lcv-replay record kitti|euroc|folder --vo``: /odom computed from the images while recording."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
from typer.testing import CliRunner

from lcv_replay.cli import app
from lcv_replay.log.reader import open_log
from lcv_replay.records import Pose2D
from tests.recorders.trees import build_euroc_tree, build_kitti_tree
from tests.vo import rendered

runner = CliRunner()


def test_record_kitti_with_vo_matches_ground_truth_step(tmp_path):
    # Tree frames 0, 1 are sequence-06 frames 12, 13 (consecutive): frame 1 is tracked from the real
    # stereo pair of frame 0 into the real left image of frame 1.
    tree = build_kitti_tree(tmp_path / "kitti", frames=(12, 13))
    out = tmp_path / "kitti_vo.mcap"
    result = runner.invoke(app, ["record", "kitti", str(tree["sequence"]), "-o", str(out), "--vo", "--quiet"])
    assert result.exit_code == 0, result.output
    with open_log(out) as reader:
        assert reader.info.has_odometry
        assert reader.info.recorder_config["vo"] is True
        odom, truth = reader.odometry(), reader.ground_truth()
    step_true = Pose2D(*truth[0]).between(Pose2D(*truth[1]))
    step_vo = Pose2D(*odom[0]).between(Pose2D(*odom[1]))
    assert np.allclose(odom[0], 0.0)
    assert 1.1 < step_true.x_m < 1.3
    assert math.hypot(step_vo.x_m - step_true.x_m, step_vo.y_m - step_true.y_m) < 0.05  # measured ~2.3 cm
    assert abs(step_vo.yaw_rad - step_true.yaw_rad) < math.radians(0.1)


def test_record_kitti_vo_and_odometry_file_are_exclusive(tmp_path):
    tree = build_kitti_tree(tmp_path / "kitti", frames=(12, 13))
    result = runner.invoke(app, ["record", "kitti", str(tree["sequence"]), "-o", str(tmp_path / "o.mcap"), "--vo", "--odometry", str(tmp_path / "kitti" / "poses" / "06.txt")])
    assert result.exit_code == 2 and "--vo and --odometry are exclusive" in result.output


def test_record_euroc_with_vo_runs_on_rectified_real_pairs(tmp_path):
    # The 4 EuRoC pairs are two loop-closure pairs, not a sequence: 0 -> 1 turns by 38 deg, which
    # frame-to-frame tracking cannot follow. The recorder must still write /odom for every frame,
    # flagging the failures (constant-velocity fallback) instead of stopping.
    tree = build_euroc_tree(tmp_path / "euroc")
    out = tmp_path / "euroc_vo.mcap"
    result = runner.invoke(app, ["record", "euroc", str(tree["root"]), "-o", str(out), "--vo", "--quiet"])
    assert result.exit_code == 0, result.output
    with open_log(out) as reader:
        assert reader.info.frames == 4 and reader.info.has_odometry
        odom = reader.odometry()
    assert np.all(np.isfinite(odom)) and np.allclose(odom[0], 0.0)
    result = runner.invoke(app, ["record", "euroc", str(tree["root"]), "-o", str(tmp_path / "raw.mcap"), "--vo", "--no-rectify"])
    assert result.exit_code == 2 and "--vo needs rectified stereo pairs" in result.output


def _folder_tree(root, frames: int = 12):
    truth = rendered.route(frames)
    for side in ("left", "right"):
        (root / side).mkdir(parents=True)
    for k, pose in enumerate(truth):
        left, right = rendered.render_grey(Pose2D(*pose))
        cv2.imwrite(str(root / "left" / f"{k:04d}.png"), left)
        cv2.imwrite(str(root / "right" / f"{k:04d}.png"), right)
    calib = rendered.calibration()
    (root / "calibration.json").write_text(json.dumps({"fx": calib.fx_px, "fy": calib.fy_px, "cx": calib.cx_px, "cy": calib.cy_px, "baseline_m": calib.baseline_m}))
    rows = ["timestamp_ns,x_m,y_m,yaw_rad"] + [f"{k * 100_000_000},{x:.9f},{y:.9f},{yaw:.9f}" for k, (x, y, yaw) in enumerate(truth)]
    (root / "ground_truth.csv").write_text("\n".join(rows) + "\n")
    return truth


def test_record_folder_with_vo(tmp_path):
    truth = _folder_tree(tmp_path / "src")
    out = tmp_path / "folder_vo.mcap"
    result = runner.invoke(app, ["record", "folder", str(tmp_path / "src"), "-o", str(out), "--vo", "--stamps", "rate", "--rate-hz", "10", "--quiet"])
    assert result.exit_code == 0, result.output
    with open_log(out) as reader:
        odom = reader.odometry()
    origin = Pose2D(*truth[0])
    true_odom = np.array([origin.between(Pose2D(*p)) for p in truth])
    assert np.max(np.hypot(*(odom[:, :2] - true_odom[:, :2]).T)) < 0.2  # ~9 m driven
    assert np.max(np.abs(odom[:, 2] - true_odom[:, 2])) < math.radians(0.5)

    (tmp_path / "src" / "calibration.json").unlink()
    result = runner.invoke(app, ["record", "folder", str(tmp_path / "src"), "-o", str(tmp_path / "b.mcap"), "--vo", "--stamps", "rate", "--rate-hz", "10"])
    assert result.exit_code == 2 and "--calibration" in result.output
    result = runner.invoke(app, ["record", "folder", "--left", str(tmp_path / "src" / "left"), "-o", str(tmp_path / "c.mcap"), "--vo", "--stamps", "rate", "--rate-hz", "10"])
    assert result.exit_code == 2 and "stereo is required" in result.output and "--right" in result.output
