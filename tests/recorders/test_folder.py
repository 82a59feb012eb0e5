"""Folder recorder: image folders + planar pose CSVs + calibration file, from the real KITTI 06 frames."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from lcv_replay.cli import app
from lcv_replay.errors import RecorderError
from lcv_replay.log.reader import open_log
from recorders.common import interpolate_planar, read_image
from recorders.folder import FolderOptions, read_planar_csv, record_folder
from tests.recorders.trees import KITTI06_CX, KITTI06_CY, KITTI06_FX, KITTI06_FX_BASELINE, build_folder_tree

@pytest.mark.parametrize("named_by_stamp", [True, False])
def test_folder_round_trip(tmp_path: Path, named_by_stamp: bool) -> None:
    tree = build_folder_tree(tmp_path / "seq", named_by_stamp=named_by_stamp)
    out = tmp_path / "folder.mcap"
    stats = record_folder(tmp_path / "seq", out)
    assert stats.frames == 5 and stats.has_odometry and stats.has_images
    with open_log(out) as log:
        assert np.array_equal(log.frame_stamps_ns, tree["stamps_ns"])
        assert np.allclose(log.odometry()[:, :2], tree["planar"][:, :2], atol=1e-9)
        assert log.calibration.baseline_m == pytest.approx(KITTI06_FX_BASELINE / KITTI06_FX)
        assert log.calibration.cx_px == pytest.approx(KITTI06_CX)
        for frame, left in zip(log.frames(), tree["left"]):
            assert np.array_equal(frame.left.decode(), read_image(left))
        assert log.info.recorder_config["stamps_from"] == ("names" if named_by_stamp else "odometry")


def test_folder_json_calibration_ground_truth_and_cli(tmp_path: Path) -> None:
    tree = build_folder_tree(tmp_path / "seq", named_by_stamp=True)
    seq = tmp_path / "seq"
    (seq / "calibration.yaml").unlink()
    calib = {"fx": KITTI06_FX, "fy": KITTI06_FX, "cx": KITTI06_CX, "cy": KITTI06_CY, "baseline_m": 0.537, "width": 1226, "height": 370}
    (tmp_path / "calib.json").write_text(json.dumps(calib))
    # A denser ground truth (every 50 ms) to exercise the interpolation.
    dense = np.arange(tree["stamps_ns"][0], tree["stamps_ns"][-1] + 1, 50_000_000)
    gt = interpolate_planar(tree["stamps_ns"], tree["planar"], dense, 10**12)
    (tmp_path / "gt.csv").write_text("".join(f"{s},{float(x)!r},{float(y)!r},{float(t)!r}\n" for s, (x, y, t) in zip(dense, gt)))
    out = tmp_path / "cli.mcap"
    result = CliRunner().invoke(app, ["record", "folder", str(seq), "-o", str(out), "--calibration", str(tmp_path / "calib.json"),
                                      "--ground-truth", str(tmp_path / "gt.csv"), "--max-gap-ns", str(10**11)])
    assert result.exit_code == 0, result.output
    assert "5 frames" in result.output
    with open_log(out) as log:
        assert log.calibration.baseline_m == pytest.approx(0.537)
        truth = log.ground_truth()
        assert np.isfinite(truth).all()
        assert np.allclose(truth[:, :2], tree["planar"][:, :2], atol=0.5)  # re-interpolated from 50 ms samples


def test_interpolate_planar_on_the_short_arc() -> None:
    stamps = np.array([0, 100, 300])
    poses = np.array([[0.0, 0.0, 3.0], [1.0, 2.0, -3.0], [5.0, 2.0, -3.0]])
    out = interpolate_planar(stamps, poses, np.array([50, 100, 200, 301, 1000]), max_gap_ns=150)
    assert out[0, :2] == pytest.approx([0.5, 1.0])
    assert abs(abs(out[0, 2]) - np.pi) < 0.01  # halfway from 3.0 to -3.0 through pi, not through 0
    assert out[1] == pytest.approx(poses[1])
    assert np.isnan(out[2]).all()  # the 200 ns gap between 100 and 300 is too long
    assert out[3] == pytest.approx(poses[2])  # 1 ns past the end: nearest pose
    assert np.isnan(out[4]).all()


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda s: (s / "odometry.csv").write_text("timestamp_ns,x_m,y_m,yaw_rad\n5,0,0\n"), "line 2: expected 4 columns"),
        (lambda s: (s / "odometry.csv").write_text("10,0,0,0\n5,0,0,0\n"), "line 2: timestamp 5 does not increase"),
        (lambda s: (s / "odometry.csv").write_text("10,0,nan,0\n"), "line 1: NaN or inf"),
        (lambda s: next((s / "right").iterdir()).unlink(), "left and right folders differ"),
        (lambda s: (s / "calibration.yaml").write_text("fx: 1\nfy: 1\ncx: 1\ncy: 1\n"), "missing key 'baseline_m'"),
        (lambda s: (s / "calibration.yaml").write_text("fx: 1\nfy: 1\ncx: 1\ncy: 1\nbaseline_m: 1\nwidth: 640\n"), "calibration is for 640x370 images"),
        (lambda s: shutil.rmtree(s / "left"), "no left image folder"),
    ],
)
def test_folder_errors(tmp_path: Path, edit, message: str) -> None:
    build_folder_tree(tmp_path / "seq", named_by_stamp=False)
    edit(tmp_path / "seq")
    with pytest.raises(RecorderError, match=message):
        record_folder(tmp_path / "seq", tmp_path / "x.mcap")
    assert not (tmp_path / "x.mcap").exists()


def test_folder_odometry_must_cover_frames(tmp_path: Path) -> None:
    tree = build_folder_tree(tmp_path / "seq", named_by_stamp=True)
    rows = (tmp_path / "seq" / "odometry.csv").read_text().splitlines()
    (tmp_path / "seq" / "odometry.csv").write_text("\n".join(rows[:3]) + "\n")  # the first two poses only
    with pytest.raises(RecorderError, match="2 frames have no odometry"):
        record_folder(tmp_path / "seq", tmp_path / "x.mcap")
    stamps, poses = read_planar_csv(tmp_path / "seq" / "odometry.csv")
    assert stamps.tolist() == tree["stamps_ns"][:2].tolist()


def test_folder_needs_a_stamp_source(tmp_path: Path) -> None:
    build_folder_tree(tmp_path / "seq", named_by_stamp=False)
    (tmp_path / "seq" / "odometry.csv").unlink()
    with pytest.raises(RecorderError, match="cannot tell the frame stamps"):
        record_folder(tmp_path / "seq", tmp_path / "x.mcap")
    stats = record_folder(tmp_path / "seq", tmp_path / "x.mcap", FolderOptions(rate_hz=10.0))
    assert stats.frames == 5 and not stats.has_odometry
