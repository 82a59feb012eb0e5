"""Time-window reads go through the MCAP index: chunks outside the window are never decompressed."""

from __future__ import annotations

import numpy as np
import pytest

from lcv_replay.errors import ConfigError
from lcv_replay.log.reader import open_log
from lcv_replay.records import FrameWindow
from tests.log.helpers import PERIOD_NS, write_synthetic_log


@pytest.fixture(scope="module")
def small_chunk_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("window") / "log.mcap"
    # ~2 frames per 8 KiB chunk: each frame holds two 40x30 RGB PNGs of ~3.5 KiB.
    exp = write_synthetic_log(path, frames=40, chunk_size_bytes=8 * 1024)
    return path, exp


def _chunks_overlapping(path, t_first_ns, t_last_ns):
    """Chunks whose time range meets ``[t_first_ns, t_last_ns]``, from the official mcap reader's index."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    return sum(1 for c in chunks if c.message_start_time <= t_last_ns and c.message_end_time >= t_first_ns)


def test_window_selects_frames_by_offset_and_duration(small_chunk_log):
    path, exp = small_chunk_log
    with open_log(path) as reader:
        frames = list(reader.frames(start_offset_s=0.9999, duration_s=0.5))
        # stamps are i * 100 ms + < 1 us jitter: frames 10..14 lie in [0.9999 s, 1.4999 s)
        assert [f.index for f in frames] == [10, 11, 12, 13, 14]
        for f in frames:
            np.testing.assert_array_equal(f.left.decode(), exp.left[f.index])
            assert [c.pair for c in f.candidates] == [(f.index, f.index - 3)]
        assert list(reader.frames(start_offset_s=100.0)) == []
        assert [f.index for f in reader.frames(start_offset_s=3.85)] == [39]
        # The window is computed once, by the reader, and the replay reads through it.
        window = reader.window(0.9999, 0.5)
        assert window == FrameWindow(10, 15) and window.frames == 5
        assert [f.index for f in reader.frames(window=window)] == [f.index for f in frames]
        assert reader.window() == FrameWindow(0, 40) and reader.window(100.0) == FrameWindow(40, 40)


def test_chunks_outside_the_window_are_not_decoded(small_chunk_log):
    path, exp = small_chunk_log
    with open_log(path) as reader:
        total = reader.info.chunk_count
        assert total >= 15
        assert reader.chunks_decoded == 0  # opening reads only the summary and message indexes
        frames = list(reader.frames(start_offset_s=1.9999, duration_s=0.35))
        assert [f.index for f in frames] == [20, 21, 22, 23]
        t_first, t_last = exp.stamps_ns[20], exp.stamps_ns[23]
        assert reader.chunks_decoded == _chunks_overlapping(path, t_first, t_last)
        assert reader.chunks_decoded <= 4 < total
        before = reader.chunks_decoded
        list(reader.frames())
        assert reader.chunks_decoded - before >= total - 1  # a full read does touch (almost) every chunk


def test_invalid_windows_are_refused(small_chunk_log):
    path, _ = small_chunk_log
    with open_log(path) as reader:
        with pytest.raises(ConfigError, match="start offset"):
            reader.frames(start_offset_s=-1.0)
        with pytest.raises(ConfigError, match="duration"):
            reader.frames(duration_s=0.0)


def test_window_duration_shorter_than_a_frame_period_can_be_empty(small_chunk_log):
    path, _ = small_chunk_log
    with open_log(path) as reader:
        assert list(reader.frames(start_offset_s=0.5005, duration_s=PERIOD_NS / 2e9)) == []
