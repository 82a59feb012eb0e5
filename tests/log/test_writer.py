"""LogWriter: atomic output, refusal of existing files, and the checks on its inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lcv_replay.errors import OutputError, RecorderError
from lcv_replay.log.reader import open_log
from lcv_replay.log.writer import LogWriter
from lcv_replay.records import LoopCandidate, Pose2D
from tests.log.helpers import write_synthetic_log

KW = dict(dataset="d", recorder="tests", nominal_rate_hz=10.0, recorder_config={})


def _leftovers(folder):
    return sorted(p.name for p in folder.iterdir())


def test_exception_inside_the_block_leaves_no_file(tmp_path):
    path = tmp_path / "out.mcap"
    with pytest.raises(RuntimeError):
        with LogWriter(path, **KW) as writer:
            writer.write_frame(0, 10, odom=Pose2D(0, 0, 0))
            raise RuntimeError("recorder crashed")
    assert _leftovers(tmp_path) == []


def test_keyboard_interrupt_leaves_existing_output_untouched(tmp_path):
    path = tmp_path / "out.mcap"
    write_synthetic_log(path, frames=3, images=False)
    before = path.read_bytes()
    with pytest.raises(KeyboardInterrupt):
        with LogWriter(path, force=True, **KW) as writer:
            writer.write_frame(0, 10, odom=Pose2D(0, 0, 0))
            raise KeyboardInterrupt
    assert path.read_bytes() == before
    assert _leftovers(tmp_path) == ["out.mcap"]


def test_existing_file_is_refused_without_force_and_replaced_with_it(tmp_path):
    path = tmp_path / "out.mcap"
    path.write_bytes(b"precious")
    with pytest.raises(OutputError, match="already exists"):
        LogWriter(path, **KW)
    assert path.read_bytes() == b"precious"
    write_synthetic_log(path, frames=2, images=False, force=True)
    assert open_log(path).info.frames == 2


def test_a_log_without_frames_is_not_created(tmp_path):
    path = tmp_path / "out.mcap"
    with pytest.raises(RecorderError, match="no frames"):
        with LogWriter(path, **KW):
            pass
    assert _leftovers(tmp_path) == []


@pytest.mark.parametrize(
    "bad_call, message",
    [
        (lambda w: w.write_frame(1, 10, odom=Pose2D(0, 0, 0)), "out of order"),
        (lambda w: (w.write_frame(0, 10, odom=Pose2D(0, 0, 0)), w.write_frame(1, 10, odom=Pose2D(0, 0, 0))), "not after"),
        (lambda w: w.write_frame(0, 10, odom=Pose2D(math.nan, 0, 0)), "not finite"),
        (lambda w: w.write_frame(0, 10), "neither a left image nor odometry"),
        (lambda w: w.write_frame(0, 10, left=np.zeros((4, 4), np.float32)), "dtype"),
        (lambda w: w.write_frame(0, 10, left=np.zeros((4, 4, 4), np.uint8)), "shape"),
        (lambda w: w.write_frame(0, 10, left=np.zeros((4, 4), np.uint8), right=np.zeros((4, 5), np.uint8)), "shape"),
        (
            lambda w: (w.write_frame(0, 10, odom=Pose2D(0, 0, 0)), w.write_frame(1, 20, left=np.zeros((4, 4), np.uint8), odom=Pose2D(0, 0, 0))),
            "differs from frame 0 in left image",
        ),
        (lambda w: (w.write_frame(0, 10, odom=Pose2D(0, 0, 0)), w.write_loop_candidate(LoopCandidate(1, 0), 10)), "only 1 frames"),
        (
            lambda w: (w.write_frame(0, 10, odom=Pose2D(0, 0, 0)), w.write_frame(1, 20, odom=Pose2D(0, 0, 0)), w.write_loop_candidate(LoopCandidate(1, 0), 10)),
            "pass the query frame's stamp_ns",
        ),
        (lambda w: (w.write_frame(0, 10, odom=Pose2D(0, 0, 0)), w.write_true_loop(0, 0, 10)), "match_frame < query_frame"),
    ],
)
def test_invalid_records_are_refused_with_the_frame_named(tmp_path, bad_call, message):
    path = tmp_path / "out.mcap"
    with pytest.raises(RecorderError, match=message):
        with LogWriter(path, **KW) as writer:
            bad_call(writer)
    assert _leftovers(tmp_path) == []


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"image_format": "bmp"}, "image format"),
        ({"compression": "gzip"}, "compression"),
        ({"jpeg_quality": 0}, "jpeg_quality"),
        ({"nominal_rate_hz": 0.0}, "nominal_rate_hz"),
        ({"odometry_information": np.eye(2)}, "odometry_information"),
        ({"extra_metadata": {"dataset": "x"}}, "reserved"),
        ({"recorder_config": {"f": object()}}, "JSON"),
    ],
)
def test_invalid_options_are_refused_before_any_file_is_made(tmp_path, kwargs, message):
    with pytest.raises(RecorderError, match=message):
        LogWriter(tmp_path / "out.mcap", **{**KW, **kwargs})
    assert _leftovers(tmp_path) == []


def test_declared_labels_without_true_loops_read_as_labelled(tmp_path):
    path = tmp_path / "out.mcap"
    with LogWriter(path, extra_metadata={"sequence": "07"}, **KW) as writer:
        writer.write_frame(0, 10, odom=Pose2D(0, 0, 0))
        writer.declare_labels()
    info = open_log(path).info
    assert info.has_labels and info.true_loop_count == 0 and info.metadata["sequence"] == "07"


def test_interrupt_with_images_still_encoding_leaves_no_file_and_no_threads(tmp_path):
    import threading

    path = tmp_path / "out.mcap"
    image = np.random.default_rng(0).integers(0, 255, (240, 320, 3), dtype=np.uint8)
    with pytest.raises(KeyboardInterrupt):
        with LogWriter(path, **KW) as writer:
            for i in range(6):
                writer.write_frame(i, 10 + i, left=image, right=image)
            raise KeyboardInterrupt
    assert _leftovers(tmp_path) == []
    assert not any(t.name.startswith("lcv-encode") for t in threading.enumerate())


def test_images_are_copied_when_queued(tmp_path):
    """The caller may reuse its buffer right after write_frame returns (encoding is asynchronous)."""
    path = tmp_path / "out.mcap"
    buffer = np.zeros((8, 8), np.uint8)
    with LogWriter(path, **KW) as writer:
        for i in range(3):
            buffer[:] = 10 * (i + 1)
            writer.write_frame(i, 10 + i, left=buffer)
    values = [int(f.left.decode()[0, 0]) for f in open_log(path).frames()]
    assert values == [10, 20, 30]
