"""Logs of the field recorders replay as they are: KITTI (real frames), the real KITTI 00 g2o log."""

from __future__ import annotations

import logging

import pytest

from lcv_replay.config import load_config
from lcv_replay.replay import ReplayOptions, replay
from lcv_replay.sinks import blueprint as bp
from lcv_replay.sinks.config import RerunOutputs
from lcv_replay.sinks.rerun_sink import RerunSink
from tests.shared_data import shared_path
from tests.replay.helpers import read_rrd, write_config


def test_a_kitti_recording_replays_and_logs_its_real_images(tmp_path, caplog):
    from recorders.kitti import KittiOptions, record_kitti
    from tests.recorders.trees import build_kitti_tree

    tree = build_kitti_tree(tmp_path / "kitti")
    log = tmp_path / "kitti06.mcap"
    record_kitti(tree["sequence"], log, KittiOptions(odometry=tmp_path / "kitti" / "poses" / "06.txt"))
    config = load_config(write_config(tmp_path / "c.toml", '[retrieval]\nbackend = "thumbnail"\n\n[rerun]\nimage_every = 1\n'))
    rrd = tmp_path / "kitti06.rrd"
    with caplog.at_level(logging.WARNING, logger="lcv_replay.replay"):
        summary = replay(ReplayOptions(log_path=log, config=config), [RerunSink(config.rerun, RerunOutputs(save=rrd))],
                         handle_sigint=False)
    assert summary.frames == 5 and summary.constraint_source == "images" and summary.constraints == 0
    assert any("retrieval never queried" in r.getMessage() for r in caplog.records)  # 5 frames < warm-up
    images = read_rrd(rrd)[bp.CAMERA_LEFT]
    assert images.column("frame").to_pylist() == [0, 1, 2, 3, 4]
    blobs = [b[0] for b in images.column([c for c in images.column_names if c.endswith("EncodedImage:blob")][0]).to_pylist()]
    assert all(bytes(b[:2]) == b"\xff\xd8" for b in blobs)  # JPEG, not the log's PNG
    assert max(len(b) for b in blobs) < 150_000  # a 1226 x 370 KITTI frame at JPEG q85


def test_kitti00_g2o_first_two_windows(tmp_path):
    """The real KITTI 00 pose graph with DLoopDetector candidates (robustslam_kitti, alpha 0.50)."""
    from recorders.g2o import record_g2o

    graph = shared_path("robustslam_kitti", "00", "kitti_00_alpha_0.50.g2o")
    log = tmp_path / "k00.mcap"
    record_g2o(graph, log)
    config = load_config(write_config(tmp_path / "c.toml", "[verification]\nwindow_frames = 500\n"))
    summary = replay(ReplayOptions(log_path=log, config=config, method="ilv+", duration_s=100.0), [], handle_sigint=False)
    from lcv_replay.log.reader import open_log

    with open_log(log) as reader:
        pairs = {c.pair for c in reader.loop_candidates() if c.query_frame < 1000}
        true_pairs = {p for p in reader.true_loops() if p in pairs}
    assert summary.frames == 1000 and summary.truth_source == "labels"
    assert summary.constraints == len(pairs) > 0  # every candidate of the range, none from beyond it
    assert summary.true_positives + summary.false_negatives == len(true_pairs)
    assert summary.ate_rmse_m is not None and summary.log_duration_s == pytest.approx(99.9)
