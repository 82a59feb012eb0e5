"""`lcv-replay info --json` on the output of every recorder (CLI end to end)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from lcv_replay.cli import app
from tests.shared_data import shared_path
from tests.recorders.trees import build_folder_tree
from tests.recorders.trees import build_euroc_tree, build_kitti_tree


def _record_args(name: str, tmp_path: Path) -> list[str]:
    if name == "g2o":
        return [str(shared_path("robustslam_kitti", "07", "kitti_07_alpha_0.25.g2o"))]
    if name == "kitti":
        return [str(build_kitti_tree(tmp_path / "kitti", frames=(12, 13))["sequence"]), "--odometry", str(tmp_path / "kitti" / "poses" / "06.txt")]
    if name == "euroc":
        return [str(build_euroc_tree(tmp_path / "euroc")["root"])]
    if name == "folder":
        build_folder_tree(tmp_path / "folder", named_by_stamp=True)
        return [str(tmp_path / "folder")]
    return [str(shared_path("ros2", "nav2_turtlebot.mcap")), "--max-frames", "300"]  # rosbag (and its alias ros2)


# name -> (frames, has_images, has_odometry, has_ground_truth, has_candidates, has_labels)
EXPECTED = {
    "g2o": (1101, False, True, True, True, True),
    "kitti": (2, True, True, True, False, False),
    "euroc": (4, True, False, True, False, False),
    "folder": (5, True, True, False, False, False),
    "rosbag": (300, False, True, False, False, False),
}


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_info_json_on_recorder_output(tmp_path: Path, name: str) -> None:
    runner = CliRunner()
    out = tmp_path / f"{name}.mcap"
    result = runner.invoke(app, ["record", name, *_record_args(name, tmp_path), "-o", str(out), "--quiet"])
    assert result.exit_code == 0, result.output
    result = runner.invoke(app, ["info", "--json", str(out)])
    assert result.exit_code == 0, result.output
    info = json.loads(result.stdout)
    frames, images, odometry, truth, candidates, labels = EXPECTED[name]
    assert info["frames"] == frames
    assert (info["has_images"], info["has_odometry"], info["has_ground_truth"]) == (images, odometry, truth)
    assert (info["has_candidates"], info["has_labels"]) == (candidates, labels)
    topics = {t["topic"]: t["count"] for t in info["topics"]}
    if odometry:
        assert topics["/odom"] == topics["/tf"] == frames
    if images:
        assert topics["/stereo/left/image"] == topics["/stereo/right/image"] == frames
        assert topics["/stereo/left/calibration"] == 1
