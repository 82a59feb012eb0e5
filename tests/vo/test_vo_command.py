"""``lcv-replay vo LOG -o OUT``: VO odometry added to a copy of a log; bad inputs refused by name."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from typer.testing import CliRunner

from lcv_replay.cli import app
from lcv_replay.errors import OdometryError
from lcv_replay.log import format as fmt
from lcv_replay.log.reader import open_log
from lcv_replay.log.writer import LogWriter
from lcv_replay.records import LoopCandidate, Pose2D, StereoCalibration
from lcv_replay.vo.log_vo import VO_METADATA_NAME, add_vo_odometry
from tests.vo import rendered

runner = CliRunner()
FRAMES = 20
STAMP0_NS = 1_600_000_000_000_000_000


@pytest.fixture(scope="module")
def rendered_frames():
    truth = rendered.route(FRAMES)
    return truth, [rendered.world().render_stereo(Pose2D(*p), width_px=320, height_px=240) for p in truth]


def write_log(
    path: Path,
    rendered_frames,
    *,
    right: bool = True,
    calibration: StereoCalibration | None | str = "world",
    odometry: bool = False,
) -> Path:
    """A stereo log of the rendered frames: images, ground truth, one candidate and one label."""
    truth, pairs = rendered_frames
    calib = rendered.calibration() if calibration == "world" else calibration
    with LogWriter(path, dataset="vo-test", recorder="test", nominal_rate_hz=10.0, recorder_config={"frames": FRAMES}) as writer:
        if calib is not None:
            writer.write_calibration(calib, STAMP0_NS)
        for i, (left, right_image) in enumerate(pairs):
            stamp = STAMP0_NS + i * 100_000_000
            writer.write_frame(
                i, stamp, left=left, right=right_image if right else None,
                odom=Pose2D(0.5 * i, 0.0, 0.0) if odometry else None, ground_truth=Pose2D(*truth[i]),
            )
            if i == 15:
                writer.write_loop_candidate(LoopCandidate(15, 3, 0.7, source="test"), stamp)
                writer.write_true_loop(15, 2, stamp)
    return path


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def messages_by_topic(path: Path) -> dict[str, list[tuple[int, int, bytes]]]:
    out: dict[str, list] = {}
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=True):
            out.setdefault(channel.topic, []).append((message.log_time, message.sequence, message.data))
    return out


def test_vo_command_adds_odometry_and_copies_everything(tmp_path, rendered_frames):
    log = write_log(tmp_path / "in.mcap", rendered_frames)
    before = digest(log)
    out, report = tmp_path / "out.mcap", tmp_path / "vo.json"
    result = runner.invoke(app, ["vo", str(log), "-o", str(out), "--json", str(report), "--quiet"])
    assert result.exit_code == 0, result.output
    assert digest(log) == before  # the input is never rewritten

    original, copied = messages_by_topic(log), messages_by_topic(out)
    assert set(copied) == set(original) | {fmt.ODOM_TOPIC, fmt.TF_TOPIC}
    for topic, records in original.items():
        assert copied[topic] == records, topic  # byte-identical copies, same times and sequences

    with open_log(out) as reader:
        assert reader.info.has_odometry and reader.info.frames == FRAMES
        odom = reader.odometry()
        frames = list(reader.frames())
        assert frames[15].candidates[0].pair == (15, 3) and frames[15].true_loops == ((15, 2),)
        assert reader.info.metadata["odometry_source"].startswith("stereo visual odometry")
        assert reader.info.metadata["dataset"] == "vo-test"
    truth = rendered_frames[0]
    origin = Pose2D(*truth[0])
    true_odom = np.array([origin.between(Pose2D(*p)) for p in truth])
    assert np.allclose(odom[0], 0.0)
    end_error = np.hypot(*(odom[-1, :2] - true_odom[-1, :2]))
    assert end_error < 0.02 * np.sum(np.hypot(*np.diff(true_odom[:, :2], axis=0).T))

    # /odom and /tf carry the frame index as sequence and the frame stamp as log_time.
    stamps = [t for t, _, _ in copied[fmt.LEFT_IMAGE_TOPIC]]
    assert [(t, s) for t, s, _ in copied[fmt.ODOM_TOPIC]] == [(t, i) for i, t in enumerate(stamps)]
    assert len(copied[fmt.TF_TOPIC]) == FRAMES

    with open(out, "rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert json.loads(meta[VO_METADATA_NAME]["summary"])["frames"] == FRAMES
    assert json.loads(meta[VO_METADATA_NAME]["config"])["klt_window_px"] > 0
    assert meta["lcv.recorder_config"] == {"frames": "20"}

    summary = json.loads(report.read_text())
    assert summary["summary"]["frames"] == FRAMES and len(summary["frames"]) == FRAMES
    assert summary["frames"][1]["status"] == "ok" and summary["frames"][1]["n_inliers"] > 50


def test_vo_command_prints_drift_against_ground_truth(tmp_path, rendered_frames):
    log = write_log(tmp_path / "in.mcap", rendered_frames)
    result = runner.invoke(app, ["vo", str(log), "-o", str(tmp_path / "out.mcap")])
    assert result.exit_code == 0, result.output
    assert "stereo VO: 20 frames, 0 constant-velocity fallbacks" in result.output
    assert "translational error" in result.output and "ATE" in result.output


def test_left_images_only_says_stereo_is_required(tmp_path, rendered_frames):
    log = write_log(tmp_path / "mono.mcap", rendered_frames, right=False)
    out = tmp_path / "out.mcap"
    result = runner.invoke(app, ["vo", str(log), "-o", str(out)])
    assert result.exit_code == 2
    assert "stereo is required" in result.output and fmt.RIGHT_IMAGE_TOPIC in result.output
    assert "--right-topic" in result.output
    assert not out.exists()


def test_missing_calibration_names_the_topic(tmp_path, rendered_frames):
    log = write_log(tmp_path / "nocal.mcap", rendered_frames, calibration=None)
    result = runner.invoke(app, ["vo", str(log), "-o", str(tmp_path / "out.mcap")])
    assert result.exit_code == 2
    assert "missing calibration" in result.output and fmt.LEFT_CALIBRATION_TOPIC in result.output


def test_calibration_size_mismatch_names_topic_and_sizes(tmp_path, rendered_frames):
    wrong = rendered.world().calibration(640, 480)
    log = write_log(tmp_path / "bad.mcap", rendered_frames, calibration=wrong)
    out = tmp_path / "out.mcap"
    result = runner.invoke(app, ["vo", str(log), "-o", str(out)])
    assert result.exit_code == 2
    line = result.output.strip()
    assert f"the image on {fmt.LEFT_IMAGE_TOPIC} is 320x240 px but the calibration on {fmt.LEFT_CALIBRATION_TOPIC} is for 640x480 px" in line
    assert "Traceback" not in result.output
    assert not out.exists() and list(tmp_path.glob(".out.mcap.*")) == []  # nothing half-written


def test_existing_odometry_output_and_input_are_protected(tmp_path, rendered_frames):
    log = write_log(tmp_path / "odom.mcap", rendered_frames, odometry=True)
    out = tmp_path / "out.mcap"
    result = runner.invoke(app, ["vo", str(log), "-o", str(out)])
    assert result.exit_code == 2 and "--replace-odometry" in result.output
    result = runner.invoke(app, ["vo", str(log), "-o", str(log), "--replace-odometry", "--force"])
    assert result.exit_code == 2 and "never rewrites its input" in result.output
    out.write_bytes(b"keep me")
    result = runner.invoke(app, ["vo", str(log), "-o", str(out), "--replace-odometry"])
    assert result.exit_code == 2 and "--force" in result.output and out.read_bytes() == b"keep me"

    stats = add_vo_odometry(log, out, force=True, replace_odometry=True)
    assert stats.replaced_odometry
    with open_log(out) as reader:
        odom = reader.odometry()
    assert not np.allclose(odom[:, 0], 0.5 * np.arange(FRAMES))  # the fake odometry is gone
    assert math.isclose(float(odom[1, 0]), 1.0, abs_tol=0.1)  # ~1 m per frame forward


def test_baseline_missing_is_refused(tmp_path, rendered_frames):
    calib = rendered.calibration()
    monocular = StereoCalibration(**{**calib.__dict__, "baseline_m": 0.0})
    log = write_log(tmp_path / "nobaseline.mcap", rendered_frames, calibration=monocular)
    with pytest.raises(OdometryError, match=r"no stereo baseline: /stereo/right/calibration"):
        add_vo_odometry(log, tmp_path / "out.mcap")
