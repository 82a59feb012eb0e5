"""``--follow``: a log read while it is written gives the results of the finished log.

The logs are the real KITTI 07 pose graph (robustslam_kitti, alpha 0.25: 1,101 frames, DLoopDetector
candidates, labels, ground truth), appended chunk by chunk on a timer while the follower replays it:

* rechunked by size (chunk boundaries inside frames: the follower waits for a later message), and
* written by the live recorder (``record g2o --live``: one chunk per frame, ``chunking = frame``).
"""

from __future__ import annotations

import functools
import logging
import os
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from lcv_replay.cli import app
from lcv_replay.config import load_config
from lcv_replay.log.follow import FollowReader, follow_log
from lcv_replay.log.reader import open_log
from lcv_replay.replay import ReplayOptions, replay
from lcv_replay.sinks.base import BaseSink
from lcv_replay.sinks.config import RerunOutputs
from lcv_replay.sinks.rerun_sink import RerunSink
from tests.shared_data import shared_path
from tests.log.growing import ChunkAppender, rechunk, unchunked
from tests.replay.helpers import read_rrd, write_config

SEED = 7
CONFIG = "[verification]\nwindow_frames = 300\n"
SUMMARY_FIELDS = ("frames", "constraints", "accepted", "accepted_constraint_ids", "true_positives", "false_positives",
                  "precision", "recall", "ate_rmse_m", "hypotheses", "truth_source", "constraint_source")


@pytest.fixture(scope="module")
def kitti07(tmp_path_factory):
    from recorders.g2o import record_g2o

    folder = tmp_path_factory.mktemp("follow")
    graph = shared_path("robustslam_kitti", "07", "kitti_07_alpha_0.25.g2o")
    finished = folder / "k07.mcap"
    record_g2o(graph, finished)
    live = folder / "k07-live.mcap"
    record_g2o(graph, live, live=True)
    config = load_config(write_config(folder / "c.toml", CONFIG))
    offline = replay(ReplayOptions(log_path=finished, config=config, seed=SEED), [], handle_sigint=False)
    return {"graph": graph, "finished": finished, "live": live, "sized": rechunk(finished, folder / "k07-sized.mcap"),
            "unchunked": unchunked(finished, folder / "k07-unchunked.mcap"), "config": config, "offline": offline,
            "folder": folder}


class FrameTimes(BaseSink):
    """When each frame reached the sinks (after the Rerun sink, which comes first)."""

    def __init__(self) -> None:
        self.at: dict[int, float] = {}

    def on_frame(self, update) -> None:
        self.at[update.frame.index] = time.monotonic()


def _follow(dest: Path, appender: ChunkAppender, config, *, idle_timeout_s: float = 10.0, rrd: Path | None = None):
    appender.start()
    while not dest.exists():
        time.sleep(0.001)
    times = FrameTimes()
    sinks = ([RerunSink(config.rerun, RerunOutputs(save=rrd))] if rrd else []) + [times]
    opener = functools.partial(follow_log, idle_timeout_s=idle_timeout_s, poll_s=0.005)
    summary = replay(ReplayOptions(log_path=dest, config=config, seed=SEED, open_reader=opener), sinks, handle_sigint=False)
    appender.join()
    assert appender.error is None
    return summary, times


def _same(a, b) -> None:
    for name in SUMMARY_FIELDS:
        assert getattr(a, name) == getattr(b, name), name


@pytest.mark.slow
@pytest.mark.parametrize("source", ["sized", "live", "unchunked"])
def test_following_a_growing_log_equals_replaying_the_finished_one(kitti07, tmp_path: Path, source: str) -> None:
    dest = tmp_path / "growing.mcap"
    period = {"sized": 0.02, "live": 0.001, "unchunked": 0.01}[source]
    appender = ChunkAppender(kitti07[source], dest, period_s=period, block_bytes=3001 if source == "unchunked" else None)
    rrd = tmp_path / "follow.rrd"
    summary, times = _follow(dest, appender, kitti07["config"], rrd=rrd)
    _same(summary, kitti07["offline"])
    assert summary.frames == 1101 and summary.true_positives > 0 and not summary.interrupted
    assert len(appender.landed) > 80
    assert times.at[0] < appender.landed[len(appender.landed) // 2][0]  # it ran while the file grew
    assert dest.read_bytes() == kitti07[source].read_bytes()  # the finished file, as the appender left it
    tables = read_rrd(rrd)  # a valid recording of every frame
    assert "/metrics/constraints" in tables


def test_a_writer_that_dies_mid_chunk_ends_like_recover(kitti07, tmp_path: Path, caplog) -> None:
    dest = tmp_path / "dead.mcap"
    appender = ChunkAppender(kitti07["live"], dest, period_s=0.0005, stop_in_chunk=600)
    with caplog.at_level(logging.WARNING):
        summary, _ = _follow(dest, appender, kitti07["config"], idle_timeout_s=0.5)
    assert "(--idle-timeout) and not finalised: the writer stopped; ending with the" in caplog.text
    assert not summary.interrupted and 0 < summary.frames < 1101
    recovered = replay(ReplayOptions(log_path=dest, config=kitti07["config"], seed=SEED, recover=True), [], handle_sigint=False)
    _same(summary, recovered)


def test_follow_cli_refuses_a_file_that_is_not_growing_and_not_finalised(kitti07, tmp_path: Path) -> None:
    dead = tmp_path / "dead.mcap"
    appender = ChunkAppender(kitti07["live"], dead, period_s=0.0, stop_in_chunk=50)
    appender.run()
    old = time.time() - 3600
    os.utime(dead, (old, old))
    runner = CliRunner()
    result = runner.invoke(app, [str(dead), "--follow", "--no-rerun"])
    assert result.exit_code == 2 and result.output.count("\n") == 1, result.output
    assert "--follow: the file is not finalised and not growing (last written 3600 s ago, --idle-timeout 30 s)" in result.output
    assert "replay it with --recover" in result.output
    # A finalised log is just replayed.
    result = runner.invoke(app, [str(kitti07["finished"]), "--follow", "--no-rerun", "--quiet", "-c",
                                 str(kitti07["folder"] / "c.toml"), "--seed", str(SEED)])
    assert result.exit_code == 0, result.output
    assert f"frames            {kitti07['offline'].frames}" in result.output


def test_the_follower_reader_grows(kitti07, tmp_path: Path) -> None:
    """The reader mode itself: info of what is known, frames as they land, the end at the footer."""
    dest = tmp_path / "growing.mcap"
    appender = ChunkAppender(kitti07["live"], dest, period_s=0.0005)
    appender.start()
    while not dest.exists() or dest.stat().st_size < 2000:
        time.sleep(0.001)
    reader = follow_log(dest, idle_timeout_s=10, poll_s=0.002)
    assert isinstance(reader, FollowReader) and reader.info.growing
    assert reader.info.has_candidates and reader.info.has_ground_truth and reader.info.has_labels
    assert 0 < len(reader.frame_stamps_ns) < 1101
    frames = list(reader.frames())
    appender.join()
    assert reader.end_reason == "finalised"
    with open_log(kitti07["finished"]) as finished:
        expected = list(finished.frames())
    assert [f.index for f in frames] == list(range(1101))
    assert [f.stamp_ns for f in frames] == [f.stamp_ns for f in expected]
    assert [f.odom for f in frames] == [f.odom for f in expected]
    assert [f.candidates for f in frames] == [f.candidates for f in expected]
    assert [f.true_loops for f in frames] == [f.true_loops for f in expected]


def test_an_interrupted_live_recording_is_a_valid_shorter_log(tmp_path: Path) -> None:
    from lcv_replay.log.writer import LogWriter
    from lcv_replay.records import Pose2D

    path = tmp_path / "live.mcap"
    with pytest.raises(KeyboardInterrupt):
        with LogWriter(path, dataset="t", recorder="t", nominal_rate_hz=10.0, recorder_config={}, live=True) as writer:
            for i in range(5):
                writer.write_frame(i, 1000 + i, odom=Pose2D(float(i), 0.0, 0.0))
                writer.flush()
                assert path.exists()  # the final path, written as it goes
            raise KeyboardInterrupt
    with open_log(path) as log:
        assert log.info.frames == 5 and log.info.metadata["chunking"] == "frame"
        assert log.info.chunk_count == 5  # one chunk per frame
        assert np.allclose(log.odometry()[:, 0], range(5))


def test_bench_follow_paces_its_writer_without_a_negative_sleep(kitti07, tmp_path: Path, monkeypatch) -> None:
    """The writer of ``bench follow`` waits for each frame's due time. It read the clock twice,
    to test and to sleep; on a loaded machine (CI, 2026-12-03) the due time passed between the
    two reads and ``time.sleep`` refused the negative length. A clock that moves 0.3 ms a read,
    at 1 kHz, puts the due time between the two reads of every frame."""
    import threading

    from lcv_replay.bench import follow as bench_follow

    class Clock:
        now_s = 0.0

        def monotonic(self) -> float:
            self.now_s += 0.0003
            return self.now_s

        def sleep(self, seconds: float) -> None:
            if seconds < 0:
                raise ValueError("sleep length must be non-negative")
            self.now_s += seconds

    monkeypatch.setattr(bench_follow, "time", Clock())
    landed: dict[int, float] = {}
    failure: list = []
    bench_follow._rewrite_live(kitti07["finished"], tmp_path / "live.mcap", 20, 1000.0, landed, threading.Event(), failure)
    assert failure == [] and sorted(landed) == list(range(20))


def test_bench_follow_and_bench_rosbag_print_tables(kitti07, tmp_path: Path) -> None:
    import json

    runner = CliRunner()
    out = tmp_path / "follow.json"
    result = runner.invoke(app, ["bench", "follow", "--log", str(kitti07["finished"]), "--frames", "300", "--rate-hz", "300",
                                 "--poll-s", "0.01", "--outputs", "file", "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert "p50 ms" in result.output and "goal: p99 < 1000 ms at 10 Hz" in result.output
    (row,) = json.loads(out.read_text())
    assert row["frames"] == 300 and row["summary_equals_offline"] and 0 < row["latency_p50_ms"] <= row["latency_max_ms"]
    out = tmp_path / "rosbag.json"
    result = runner.invoke(app, ["bench", "rosbag", str(shared_path("ros1", "tf_example.bag")), "--odom-from-tf", "odom:base_link",
                                 "--repeats", "1", "-o", str(out)])
    assert result.exit_code == 0, result.output
    rows = json.loads(out.read_text())
    assert [r["what"] for r in rows] == ["rosbags read", "rosbags read + deserialise", "record rosbag"]
    assert all(r["messages"] == 518 for r in rows)  # /tf and /tf_static, read by all three
