"""`lcv-replay info` on foreign logs: ROS 1 bags, ROS 2 bag folders and db3, ROS 2 MCAP, any MCAP."""

from __future__ import annotations

import json
import shlex
from pathlib import Path

import pytest
from typer.testing import CliRunner

from lcv_replay.cli import app
from tests.shared_data import shared_path

runner = CliRunner()


def _info(*args: str) -> str:
    result = runner.invoke(app, ["info", *args])
    assert result.exit_code == 0, result.output
    return result.stdout


def test_ros1_bag_info_lists_topics_and_the_import_command() -> None:
    bag = shared_path("ros1", "ROS_example.bag")
    text = _info(str(bag))
    assert "Storage id:        rosbag1" in text and "Messages:          26566" in text
    assert "Duration:          889.018944740s" in text
    assert "Topic: groundtruth | Type: geometry_msgs/msg/PoseStamped | Count: 12765 | Rate:   14.357 Hz" in text
    assert "lcv-replay could use: odometry on ORB-SLAM, ground truth on groundtruth" in text
    assert "several odometry candidates: ORB-SLAM" in text  # the choice is the user's
    data = json.loads(_info("--json", str(bag)))
    assert data["format"] == "ros1" and data["message_count"] == 26566
    assert {t["topic"]: t["count"] for t in data["topics"]} == {"ORB-SLAM": 8362, "S-PTAM": 5439, "groundtruth": 12765}
    assert data["start_ns"] == 1502792570283404827 and data["duration_s"] == pytest.approx(889.0189447)
    assert data["record_command"].startswith(f"lcv-replay record rosbag {bag} --odom-topic ORB-SLAM --ground-truth-topic groundtruth -o ")


@pytest.mark.parametrize("parts", [("ros1", "tf_example.bag"), ("ros2", "tf_example"), ("ros2", "tf_example", "metadata.yaml"),
                                   ("ros2", "tf_example", "tf_example.db3")])
def test_tf_only_bags_suggest_odometry_from_tf(parts: tuple[str, ...], tmp_path: Path) -> None:
    path = shared_path(*parts)
    text = _info(str(path))
    assert "Topic: /tf        | Type: tf2_msgs/msg/TFMessage | Count: 517 | Rate:   10.000 Hz" in text
    assert "TF frames:         base_footprint, base_link, odom" in text and "TF moving:         odom -> base_footprint (517)" in text
    assert "lcv-replay could use: odometry from TF odom -> base_link" in text
    command = json.loads(_info("--json", str(path)))["record_command"]
    assert "--odom-from-tf odom:base_link" in command
    # The suggested command works as it is.
    args = shlex.split(command)[1:]
    args[args.index("-o") + 1] = str(tmp_path / "out.mcap")
    result = runner.invoke(app, args + ["--quiet"])
    assert result.exit_code == 0, result.output
    assert json.loads(_info("--json", str(tmp_path / "out.mcap")))["frames"] == 517


def test_ros2_mcap_bag_info() -> None:
    text = _info(str(shared_path("ros2", "nav2_turtlebot.mcap")))
    assert "Storage id:        mcap" in text and "Messages:          8197" in text
    assert "Topic: /odom      | Type: nav_msgs/msg/Odometry" in text and "Count: 2639 | Rate:   27.097 Hz" in text
    assert "TF moving:         odom -> base_link" in text
    assert "lcv-replay could use: odometry on /odom" in text
    assert "or replay it:    lcv-replay " in text


def test_any_other_mcap_is_listed(tmp_path: Path) -> None:
    from mcap.writer import Writer

    path = tmp_path / "other.mcap"
    with path.open("wb") as f:
        writer = Writer(f)
        writer.start(profile="x-custom", library="someone else")
        channel = writer.register_channel("/imu", "json", writer.register_schema("my.Imu", "jsonschema", b"{}"))
        for k in range(11):
            writer.add_message(channel, log_time=k * 10_000_000, data=b"{}", publish_time=k * 10_000_000)
        writer.finish()
    text = _info(str(path))
    assert "Topic: /imu | Type: my.Imu | Count: 11 | Rate:  100.000 Hz | Serialization Format: json" in text
    assert "lcv-replay could use: nothing: not an lcv-replay log (missing required topics" in text
    assert json.loads(_info("--json", str(path)))["record_command"] is None
