"""`lcv-replay info`: ros2-bag-info style text and the stable --json keys."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from lcv_replay.cli import app
from tests.log.helpers import write_synthetic_log

runner = CliRunner()
STABLE_KEYS = {"frames", "duration_s", "start_ns", "end_ns", "has_ground_truth", "has_candidates", "has_labels", "topics"}


def test_json_has_the_stable_keys_with_values_from_the_log(tmp_path):
    path = tmp_path / "log.mcap"
    exp = write_synthetic_log(path, frames=6)
    result = runner.invoke(app, ["info", str(path), "--json"])
    assert result.exit_code == 0, result.output
    info = json.loads(result.stdout)
    assert STABLE_KEYS <= info.keys()
    assert info["frames"] == 6
    assert info["start_ns"] == exp.stamps_ns[0] and info["end_ns"] == exp.stamps_ns[-1]
    assert info["duration_s"] == (exp.stamps_ns[-1] - exp.stamps_ns[0]) / 1e9
    assert (info["has_ground_truth"], info["has_candidates"], info["has_labels"]) == (True, True, True)
    assert info["candidate_count"] == len(exp.candidates) and info["true_loop_count"] == len(exp.true_loops)
    topics = {t["topic"]: t for t in info["topics"]}
    assert topics["/stereo/left/image"]["schema"] == "foxglove.CompressedImage"
    assert topics["/stereo/left/image"]["count"] == 6
    assert topics["/odom"]["count"] == topics["/tf"]["count"] == 6
    assert topics["/loop_candidates"] == {"topic": "/loop_candidates", "schema": "lcv.LoopCandidate", "count": 3, "rate_hz": topics["/loop_candidates"]["rate_hz"]}
    assert abs(topics["/odom"]["rate_hz"] - 10.0) < 0.01
    assert info["dataset"] == "synthetic-test" and info["recorder_config"] == {"frames": 6, "seed": 0}
    assert all(set(t) == {"topic", "schema", "count", "rate_hz"} for t in info["topics"])


def test_text_form_shows_size_times_topics_and_contents(tmp_path):
    path = tmp_path / "odom_only.mcap"
    write_synthetic_log(path, frames=5, images=False)
    result = runner.invoke(app, ["info", str(path)])
    assert result.exit_code == 0, result.output
    text = result.stdout
    for needle in ("Files:             odom_only.mcap", "Bag size:", "Duration:          0.400s", "Start:", "End:"):
        assert needle in text
    assert "Topic: /odom" in text and "Type: foxglove.PoseInFrame" in text and "Count:      5" in text and "Rate:   10.000 Hz" in text
    assert "Frames:            5 at 10 Hz nominal: odometry" in text
    assert "Ground truth:      yes" in text
    assert "Loop candidates:   2" in text
    assert "Loop labels:       yes (1 true pairs)" in text
