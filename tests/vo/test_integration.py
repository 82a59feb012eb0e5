"""End to end: ``record synthetic --odometry vo`` (320x240, 300 frames) into the replay."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from lcv_replay.cli import app
from lcv_replay.log.reader import open_log
from lcv_replay.records import Pose2D
from lcv_replay.vo.drift import kitti_drift, path_length_m

runner = CliRunner()
FRAMES = 300

# A light replay: the thumbnail descriptor instead of the CNN, shorter windows (the paper's values
# need thousands of frames); the point here is that the VO log goes through the whole pipeline.
REPLAY_TOML = """
[retrieval]
backend = "thumbnail"
exclusion_frames = 50

[verification]
window_frames = 100
"""


@pytest.mark.slow
def test_record_synthetic_with_vo_then_replay(tmp_path, monkeypatch):
    monkeypatch.setenv("LCV_CACHE_DIR", str(tmp_path / "cache"))
    log = tmp_path / "demo_vo.mcap"
    result = runner.invoke(app, ["record", "synthetic", "-o", str(log), "--frames", str(FRAMES), "--resolution", "320x240", "--odometry", "vo", "--quiet"])
    assert result.exit_code == 0, result.output

    with open_log(log) as reader:
        info = reader.info
        assert info.frames == FRAMES and info.has_odometry and info.has_ground_truth
        assert "VO" in info.metadata["odometry_source"]
        odom, truth = reader.odometry(), reader.ground_truth()
    origin = Pose2D(*truth[0])
    true_odom = np.array([origin.between(Pose2D(*p)) for p in truth])
    drift = kitti_drift(odom, true_odom)
    assert path_length_m(true_odom)[-1] > 200
    assert drift.segments > 10 and drift.translation_error_pct < 2.0  # measured: ~0.5 %

    config = tmp_path / "replay.toml"
    config.write_text(REPLAY_TOML)
    summary = tmp_path / "summary.json"
    result = runner.invoke(app, [str(log), "--no-rerun", "--quiet", "--config", str(config), "--summary-json", str(summary)])
    assert result.exit_code == 0, result.output
    report = json.loads(summary.read_text())
    assert report["frames"] == FRAMES and not report["interrupted"]
    assert report["constraints"] > 0 and report["ate_rmse_m"] is not None
    assert report["truth_source"] == "ground_truth"
