"""KITTI recorder: a tiny sequences/06 tree built from the real kitti06_frames, read back."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from lcv_replay.cli import app
from lcv_replay.errors import RecorderError
from lcv_replay.log.reader import open_log
from recorders.common import project_to_planar, read_image, read_pose_file
from recorders.kitti import KittiOptions, load_kitti_sequence, record_kitti
from tests.recorders.trees import KITTI06_FX, KITTI06_FX_BASELINE, build_kitti_tree


def _quaternion_from_matrix(R: np.ndarray) -> tuple[float, float, float, float]:
    """(qx, qy, qz, qw) of a rotation matrix (test helper, Shepperd's method is not needed here)."""
    w = math.sqrt(max(0.0, 1.0 + R[0, 0] + R[1, 1] + R[2, 2])) / 2.0
    return ((R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w), w)


def test_kitti_round_trip_with_odometry_in_both_formats(tmp_path: Path) -> None:
    tree = build_kitti_tree(tmp_path / "kitti")
    poses = tree["poses"].reshape(-1, 3, 4)
    # The same trajectory as a TUM file (stamps = times.txt), as evo or ORB-SLAM would write it.
    tum = tmp_path / "odom_tum.txt"
    tum.write_text("".join(
        f"{t:.6f} {P[0, 3]} {P[1, 3]} {P[2, 3]} " + " ".join(map(str, _quaternion_from_matrix(P[:, :3]))) + "\n"
        for t, P in zip(tree["times_s"], poses)
    ))
    T = np.tile(np.eye(4), (len(poses), 1, 1))
    T[:, :3, :] = poses
    expected = project_to_planar(T)

    for odometry in (tree["sequence"].parent.parent / "poses" / "06.txt", tum):
        out = tmp_path / f"{odometry.stem}.mcap"
        stats = record_kitti(tree["sequence"], out, KittiOptions(odometry=odometry))
        assert stats.frames == 5 and stats.has_images and stats.has_odometry and stats.has_ground_truth
        with open_log(out) as log:
            assert log.info.frames == 5 and log.info.has_right_images
            assert np.array_equal(log.frame_stamps_ns, np.rint(tree["times_s"] * 1e9).astype(np.int64))
            odom = log.odometry()
            assert np.allclose(odom[:, :2], expected[:, :2], atol=1e-6)
            assert np.allclose(np.cos(odom[:, 2] - expected[:, 2]), 1.0, atol=1e-9)
            assert np.allclose(log.ground_truth()[:, :2], expected[:, :2], atol=1e-6)
            calib = log.calibration
            assert calib.fx_px == pytest.approx(KITTI06_FX)
            assert calib.baseline_m == pytest.approx(KITTI06_FX_BASELINE / KITTI06_FX)
            assert (calib.width_px, calib.height_px) == (1226, 370)
            for frame, left, right in zip(log.frames(), tree["left"], tree["right"]):
                assert np.array_equal(frame.left.decode(), read_image(left))  # PNG: lossless
                assert np.array_equal(frame.right.decode(), read_image(right))
            assert log.info.metadata["dataset"] == "kitti/06"


def test_planar_convention_on_real_kitti_poses(tmp_path: Path) -> None:
    """KITTI 06 starts driving straight ahead: the body moves along +x, and heading follows it."""
    tree = build_kitti_tree(tmp_path / "kitti", frames=(1, 12))
    seq = load_kitti_sequence(tree["sequence"])
    gt = seq.ground_truth
    step = gt[1, :2] - gt[0, :2]
    assert step[0] > 10.0 and abs(step[1]) < 0.5  # 13 m forward in 11 frames, little sideways
    assert abs(math.atan2(step[1], step[0]) - gt[0, 2]) < 0.05


def test_kitti_without_odometry_writes_images_and_ground_truth(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    tree = build_kitti_tree(tmp_path / "kitti", frames=(12, 13))
    out = tmp_path / "no_odom.mcap"
    with caplog.at_level("WARNING"):
        stats = record_kitti(tmp_path / "kitti", out, KittiOptions(sequence="06"))
    assert "no --odometry given" in caplog.text
    assert stats.frames == 2 and not stats.has_odometry
    with open_log(out) as log:
        assert not log.info.has_odometry and log.info.has_ground_truth and log.info.has_images
    runner = CliRunner()
    result = runner.invoke(app, ["record", "kitti", str(tree["sequence"]), "-o", str(tmp_path / "cli.mcap"), "--quiet"])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "cli.mcap").exists()


def test_kitti_start_and_max_frames(tmp_path: Path) -> None:
    tree = build_kitti_tree(tmp_path / "kitti")
    seq = load_kitti_sequence(tree["sequence"], KittiOptions(start_frame=1, max_frames=2))
    assert [p.name for p in seq.left_images] == ["000001.png", "000002.png"]
    assert seq.frame_offset == 1 and len(seq.ground_truth) == 2


def _break(tree: dict, what: str) -> None:
    seq: Path = tree["sequence"]
    if what == "times":
        (seq / "times.txt").write_text("0.0\n0.1\n")
    elif what == "right":
        (seq / "image_1" / "000004.png").unlink()
    elif what == "calib":
        (seq / "calib.txt").write_text("P0: 1 2 3\n")
    elif what == "poses":
        (seq.parent.parent / "poses" / "06.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    elif what == "image":
        (seq / "image_0" / "000000.png").write_bytes(b"not a png")


@pytest.mark.parametrize(
    ("what", "message"),
    [
        ("times", "times.txt has 2 lines but image_0 has 5 images"),
        ("right", "image_0 has 5 images but image_1 has 4"),
        ("calib", "calib.txt has no P0/P1 line"),
        ("poses", "ground truth has 1 poses but the sequence has 5 frames"),
        ("image", "cannot read the image"),
    ],
)
def test_kitti_bad_trees(tmp_path: Path, what: str, message: str) -> None:
    tree = build_kitti_tree(tmp_path / "kitti")
    _break(tree, what)
    out = tmp_path / "x.mcap"
    with pytest.raises(RecorderError, match=message):
        record_kitti(tree["sequence"], out)
    assert not out.exists() and not list(tmp_path.glob(".x.mcap*"))


def test_kitti_root_without_sequence_lists_sequences(tmp_path: Path) -> None:
    build_kitti_tree(tmp_path / "kitti", frames=(12,))
    with pytest.raises(RecorderError, match=r"pass --sequence \(found: 06\)"):
        load_kitti_sequence(tmp_path / "kitti")
    with pytest.raises(RecorderError, match="KITTI source folder not found"):
        load_kitti_sequence(tmp_path / "nope")


def test_tum_odometry_must_cover_frames(tmp_path: Path) -> None:
    tree = build_kitti_tree(tmp_path / "kitti")
    tum = tmp_path / "short.txt"
    tum.write_text(f"{tree['times_s'][0]:.6f} 0 0 0 0 0 0 1\n")
    with pytest.raises(RecorderError, match="4 of 5 frames have no pose"):
        load_kitti_sequence(tree["sequence"], KittiOptions(odometry=tum))
    assert read_pose_file(tum).format == "tum"
