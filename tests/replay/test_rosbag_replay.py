"""A ROS bag written by rosbags' own writer from the synthetic stereo world, replayed end to end.

The world is rendered once per module (120 frames at 160 x 120): stereo ``sensor_msgs/Image`` with
their ``CameraInfo``, ``nav_msgs/Odometry`` (the recorder's simulated drift) and the true pose as
``geometry_msgs/PoseStamped`` on ``/ground_truth/pose``. ``lcv-replay BAG`` picks every topic by
itself, converts the bag into the cache and replays it through the image route; the result equals
the replay of the same frames written directly as an lcv-replay log.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from lcv_replay.cli import app
from lcv_replay.config import load_config
from lcv_replay.log.reader import open_log
from lcv_replay.log.writer import LogWriter
from lcv_replay.records import Pose2D
from lcv_replay.replay import ReplayOptions, replay
from lcv_replay.sinks import blueprint as bp
from tests.recorders.bag_writer import BagBuilder
from tests.replay.helpers import read_rrd, write_config
from tests.replay.test_synthetic_demo import IMAGE_ROUTE_TOML

FRAMES = 120
SEED = 3
WIDTH_PX, HEIGHT_PX = 160, 120
START_NS = 1_700_000_000 * 10**9
PERIOD_NS = 100_000_000


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """The rendered drive and the two bags (ROS 2 MCAP and ROS 1) that carry it."""
    from recorders.synthetic import simulate_odometry
    from recorders.synthetic_world import SyntheticWorld, make_route

    scene = SyntheticWorld.from_seed(SEED)
    truth = make_route(scene, FRAMES)
    odometry = simulate_odometry(truth, seed=SEED)
    pairs = [scene.render_stereo(Pose2D(*p), width_px=WIDTH_PX, height_px=HEIGHT_PX) for p in truth]
    calib = scene.calibration(WIDTH_PX, HEIGHT_PX)
    stamps = START_NS + PERIOD_NS * np.arange(FRAMES)
    folder = tmp_path_factory.mktemp("bags")
    bags = {}
    for kind, name in (("ros2-mcap", "drive"), ("ros1", "drive.bag")):
        b = BagBuilder(kind)
        for side, tx in (("left", 0.0), ("right", -calib.fx_px * calib.baseline_m)):
            b.add(f"/stereo/{side}/camera_info", int(stamps[0]),
                  b.camera_info(int(stamps[0]), WIDTH_PX, HEIGHT_PX, calib.fx_px, calib.cx_px, calib.cy_px, tx))
        for k, stamp in enumerate(stamps):
            stamp = int(stamp)
            left, right = pairs[k]
            b.add("/stereo/left/image_raw", stamp + 3_000_000, b.image(stamp, left, "camera_left"))  # received 3 ms later
            b.add("/stereo/right/image_raw", stamp + 4_000_000, b.image(stamp, right, "camera_right"))
            b.add("/odom", stamp + 1_000_000, b.odometry(stamp, *odometry[k]))
            b.add("/ground_truth/pose", stamp + 2_000_000, b.pose_stamped(stamp, *truth[k]))
        bags[kind] = b.write(folder / name)
    return {"truth": truth, "odometry": odometry, "pairs": pairs, "calib": calib, "stamps": stamps, "bags": bags, "folder": folder}


def _native_log(world, path: Path) -> Path:
    """The same frames written directly through the log writer (no bag)."""
    with LogWriter(path, dataset="drive", recorder="test", nominal_rate_hz=10.0, recorder_config={}) as writer:
        writer.write_calibration(world["calib"], int(world["stamps"][0]))
        for k, stamp in enumerate(world["stamps"]):
            left, right = world["pairs"][k]
            writer.write_frame(k, int(stamp), left=left, right=right, odom=Pose2D(*world["odometry"][k]),
                               ground_truth=Pose2D(*world["truth"][k]))
    return path


def test_bag_import_keeps_every_frame(world, tmp_path: Path, caplog) -> None:
    """ROS 2 MCAP and ROS 1 bag of the same drive import to the same log: pixels, poses, calibration."""
    import logging

    from recorders.rosbag import RosbagOptions, record_rosbag

    logs = {}
    for kind, bag in world["bags"].items():
        logs[kind] = tmp_path / f"{kind}.mcap"
        with caplog.at_level(logging.INFO, logger="recorders.rosbag"):
            stats = record_rosbag(bag, logs[kind], RosbagOptions())
        assert stats.frames == FRAMES and stats.has_images and stats.has_ground_truth
    assert "stereo pair: /stereo/left/image_raw / /stereo/right/image_raw (the only pair" in caplog.text
    assert "odometry: /odom (nav_msgs/msg/Odometry; the only candidate" in caplog.text
    assert "ground truth: /ground_truth/pose (geometry_msgs/msg/PoseStamped; by its name" in caplog.text
    with open_log(logs["ros2-mcap"]) as a, open_log(logs["ros1"]) as b:
        for log in (a, b):
            assert np.array_equal(log.frame_stamps_ns, world["stamps"])
            assert np.allclose(log.odometry()[:, :2], world["odometry"][:, :2])
            assert np.allclose(np.cos(log.odometry()[:, 2] - world["odometry"][:, 2]), 1.0)
            assert np.allclose(log.ground_truth()[:, :2], world["truth"][:, :2])
            assert log.calibration.baseline_m == pytest.approx(world["calib"].baseline_m)
            assert log.calibration.fx_px == pytest.approx(world["calib"].fx_px)
        for k, (fa, fb) in enumerate(zip(a.frames(), b.frames())):
            if k % 40 == 0:
                left, right = world["pairs"][k]
                assert np.array_equal(fa.left.decode(), left) and np.array_equal(fb.right.decode(), right)


@pytest.mark.slow
def test_replaying_the_bag_directly_equals_replaying_the_log(world, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("LCV_CACHE_DIR", str(tmp_path / "cache"))
    config_path = write_config(tmp_path / "images.toml", IMAGE_ROUTE_TOML)
    bag = world["bags"]["ros2-mcap"]
    runner = CliRunner()
    rrd, js = tmp_path / "bag.rrd", tmp_path / "bag.json"
    args = [str(bag), "--config", str(config_path), "--seed", str(SEED), "--save", str(rrd), "--summary-json", str(js), "--quiet"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    cached = list((tmp_path / "cache" / "converted").glob("drive-*.mcap"))
    assert len(cached) == 1 and f"converted {bag}: {cached[0]}" not in result.output  # --quiet: no note
    data = json.loads(js.read_text())
    assert data["frames"] == FRAMES and data["constraint_source"] == "images" and data["truth_source"] == "ground_truth"

    native = _native_log(world, tmp_path / "native.mcap")
    config = load_config(config_path)
    expected = replay(ReplayOptions(log_path=native, config=config, seed=SEED), [], handle_sigint=False)
    assert data["constraints"] == expected.constraints and data["accepted"] == expected.accepted
    assert data["accepted_constraint_ids"] == list(expected.accepted_constraint_ids)
    assert (data["precision"], data["recall"]) == (expected.precision, expected.recall)
    assert data["ate_rmse_m"] == pytest.approx(expected.ate_rmse_m, rel=1e-9)
    tables = read_rrd(rrd)
    assert tables[bp.CAMERA_LEFT].column("frame").to_pylist() == list(range(0, FRAMES, 10))
    assert bp.RETRIEVAL_CODE in tables

    # Again: the cached conversion is used, not rebuilt.
    before = cached[0].stat().st_mtime_ns
    result = runner.invoke(app, [a for a in args if a != "--quiet"] + ["--no-rerun", "--force"])  # bag.json exists
    assert result.exit_code == 0, result.output
    assert f"using the conversion of {bag}: {cached[0]}" in result.output and cached[0].stat().st_mtime_ns == before
    # Another option is another conversion; --keep-converted writes it beside the bag.
    result = runner.invoke(app, [str(bag), "--ground-truth-topic", "", "--keep-converted", "--config", str(config_path), "--no-rerun", "--quiet"])
    assert result.exit_code == 0, result.output
    beside = world["folder"] / "drive.lcv.mcap"
    with open_log(beside) as log:
        assert not log.info.has_ground_truth and log.info.frames == FRAMES


def test_direct_replay_names_the_missing_option(world, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("LCV_CACHE_DIR", str(tmp_path / "cache"))
    runner = CliRunner()
    result = runner.invoke(app, [str(world["bags"]["ros1"]), "--odom-topic", "/stereo/left/image_raw", "--no-rerun"])
    assert result.exit_code == 2 and result.output.count("\n") == 1
    assert "topic /stereo/left/image_raw (--odom-topic) has type sensor_msgs/msg/Image, which lcv-replay cannot use there" in result.output
    result = runner.invoke(app, [str(world["bags"]["ros1"]), "--odom-from-tf", "odom:base_link", "--no-rerun"])
    assert result.exit_code == 2 and "--odom-from-tf needs /tf or /tf_static, and the bag has neither" in result.output
    native = _native_log(world, tmp_path / "native.mcap")
    result = runner.invoke(app, [str(native), "--odom-topic", "/odom", "--no-rerun"])
    assert result.exit_code == 2 and "--odom-topic applies to bags" in result.output
    assert not any((tmp_path / "cache").rglob("*.mcap"))


@pytest.mark.slow
def test_following_a_ros2_mcap_being_recorded(world, tmp_path: Path, monkeypatch) -> None:
    """The bag's MCAP appended chunk by chunk (as 'ros2 bag record -s mcap' writes it), replayed with
    --follow through the live conversion: the results equal those of the finished recording."""
    from tests.log.growing import ChunkAppender

    monkeypatch.setenv("LCV_CACHE_DIR", str(tmp_path / "cache"))
    config_path = write_config(tmp_path / "images.toml", IMAGE_ROUTE_TOML)
    source = next(world["bags"]["ros2-mcap"].glob("*.mcap"))
    growing = tmp_path / "recording.mcap"
    appender = ChunkAppender(source, growing, period_s=0.15)
    appender.start()
    while not growing.exists() or growing.stat().st_size < 100_000:
        time.sleep(0.005)
    js = tmp_path / "follow.json"
    result = CliRunner().invoke(app, [str(growing), "--follow", "--idle-timeout", "5", "--config", str(config_path), "--seed", str(SEED),
                                      "--summary-json", str(js), "--save", str(tmp_path / "follow.rrd")])
    appender.join()
    assert result.exit_code == 0, result.output
    assert "following " in result.output and "through its live conversion" in result.output
    data = json.loads(js.read_text())
    native = _native_log(world, tmp_path / "native.mcap")
    expected = replay(ReplayOptions(log_path=native, config=load_config(config_path), seed=SEED), [], handle_sigint=False)
    assert data["frames"] == FRAMES and data["constraint_source"] == "images" and data["truth_source"] == "ground_truth"
    assert data["constraints"] == expected.constraints and data["accepted_constraint_ids"] == list(expected.accepted_constraint_ids)
    assert data["ate_rmse_m"] == pytest.approx(expected.ate_rmse_m, rel=1e-9)
    converted = list((tmp_path / "cache" / "converted").glob("recording.followed-*.lcv.mcap"))
    assert len(converted) == 1
    with open_log(converted[0]) as log:
        assert log.info.frames == FRAMES and log.info.metadata["chunking"] == "frame"
        assert np.array_equal(next(log.frames()).left.decode(), world["pairs"][0][0])
