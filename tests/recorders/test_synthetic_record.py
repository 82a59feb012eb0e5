"""``record synthetic``: the log round trip, determinism, atomicity, VO odometry and the CLI."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
from typer.testing import CliRunner

from lcv_replay.cli import app
from lcv_replay.errors import ConfigError, OutputError
from lcv_replay.log.reader import open_log
from lcv_replay.records import Pose2D
from recorders.synthetic import DEFAULT_START_STAMP_NS, DriftConfig, SyntheticOptions, record_synthetic, simulate_odometry
from recorders.synthetic_world import SyntheticWorld, WorldConfig, make_route

SMALL = WorldConfig(texture_px_per_m=16.0, ground_px_per_m=12.0)
OPTIONS = SyntheticOptions(frames=12, seed=2, width_px=160, height_px=120, world=SMALL)


def _digest(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    path = tmp_path_factory.mktemp("synthetic") / "street.mcap"
    calls = []
    stats = record_synthetic(path, OPTIONS, progress=lambda done, total: calls.append((done, total)))
    return path, stats, calls


def test_round_trip_through_the_log_reader(recorded):
    path, stats, calls = recorded
    assert stats.frames == 12 and stats.has_images and stats.has_odometry and stats.has_ground_truth
    assert calls[-1] == (12, 12) and len(calls) == 12
    world = SyntheticWorld.from_seed(OPTIONS.seed, SMALL)
    truth = make_route(world, OPTIONS.frames)
    odometry = simulate_odometry(truth, OPTIONS.drift, OPTIONS.seed)
    reader = open_log(path)
    info = reader.info
    assert info.frames == 12 and info.has_right_images and info.has_ground_truth and info.has_odometry
    assert info.start_ns == DEFAULT_START_STAMP_NS and info.end_ns == DEFAULT_START_STAMP_NS + 11 * 100_000_000
    assert info.metadata["dataset"] == "synthetic-street" and info.metadata["recorder"] == "synthetic"
    np.testing.assert_allclose(np.array(json.loads(info.metadata["T_body_camera"])).reshape(4, 4)[:3, 3], [0, 0, 1.6])
    assert info.recorder_config["frames"] == 12 and info.recorder_config["drift"]["translation_noise_pct"] == 1.0
    np.testing.assert_allclose(info.odometry_information, DriftConfig().step_information(1.0))
    assert reader.calibration == world.calibration(160, 120)
    frames = list(reader.frames())
    assert [f.index for f in frames] == list(range(12))
    np.testing.assert_allclose([f.ground_truth for f in frames], truth, atol=1e-6)
    np.testing.assert_allclose([f.odom for f in frames], odometry, atol=1e-6)
    for k in (0, 11):  # PNG is lossless: the decoded images are the rendered ones
        left, right = world.render_stereo(Pose2D(*truth[k]), width_px=160, height_px=120)
        np.testing.assert_array_equal(frames[k].left.decode(), left)
        np.testing.assert_array_equal(frames[k].right.decode(), right)


def test_recording_is_deterministic(recorded, tmp_path):
    path, _, _ = recorded
    again = tmp_path / "again.mcap"
    record_synthetic(again, OPTIONS)
    assert _digest(again) == _digest(path)
    other = tmp_path / "other.mcap"
    record_synthetic(other, SyntheticOptions(frames=3, seed=3, width_px=160, height_px=120, world=SMALL))
    assert _digest(other) != _digest(path)


def test_interrupted_recording_leaves_nothing(tmp_path):
    out = tmp_path / "cut.mcap"

    def interrupt(done: int, total: int) -> None:
        if done == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        record_synthetic(out, OPTIONS, progress=interrupt)
    assert list(tmp_path.iterdir()) == []


def test_existing_output_is_kept_without_force(recorded, tmp_path):
    out = tmp_path / "keep.mcap"
    out.write_bytes(b"precious")
    with pytest.raises(OutputError):
        record_synthetic(out, OPTIONS)
    assert out.read_bytes() == b"precious"
    record_synthetic(out, SyntheticOptions(frames=2, width_px=96, height_px=72, world=SMALL), force=True)
    assert open_log(out).info.frames == 2


def test_vo_odometry_follows_the_true_motion(tmp_path):
    out = tmp_path / "vo.mcap"
    record_synthetic(out, SyntheticOptions(frames=25, width_px=320, height_px=240, odometry="vo", world=SMALL))
    reader = open_log(out)
    assert reader.info.metadata["odometry_source"] == "stereo VO on the rendered images"
    assert reader.info.odometry_information is None
    frames = list(reader.frames())
    start = frames[0].ground_truth
    truth = np.array([start.between(f.ground_truth).as_array() for f in frames])
    odom = np.array([f.odom for f in frames])
    travelled = np.hypot(*np.diff(truth[:, :2], axis=0).T).sum()
    assert travelled > 15.0
    assert np.hypot(*(odom[-1, :2] - truth[-1, :2])) < 0.03 * travelled
    assert abs(np.degrees(odom[-1, 2] - truth[-1, 2])) < 1.0


def test_bad_options_are_refused():
    for kwargs in (dict(frames=0), dict(seed=-1), dict(width_px=8), dict(odometry="lidar"), dict(image_format="bmp"), dict(rate_hz=0.0)):
        with pytest.raises(ConfigError):
            SyntheticOptions(**kwargs)


def test_cli_records_and_reports(tmp_path):
    runner = CliRunner()
    out = tmp_path / "cli.mcap"
    result = runner.invoke(app, ["record", "synthetic", "-o", str(out), "--frames", "3", "--resolution", "96x72", "--seed", "1"])
    assert result.exit_code == 0, result.output
    assert "3 frames" in result.output
    assert open_log(out).info.frames == 3
    again = runner.invoke(app, ["record", "synthetic", "-o", str(out), "--frames", "3"])
    assert again.exit_code == 2 and "already exists" in again.output and "Traceback" not in again.output
    bad = runner.invoke(app, ["record", "synthetic", "-o", str(tmp_path / "x.mcap"), "--resolution", "96by72"])
    assert bad.exit_code == 2 and "error: --resolution '96by72' is not WIDTHxHEIGHT" in bad.output
    assert not (tmp_path / "x.mcap").exists()
