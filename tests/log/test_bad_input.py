"""Malformed logs, built on purpose byte by byte or with the low-level mcap writer.

Each case must give one ``error:`` line naming the file, the problem and the fix, exit code 2 and no
traceback (``lcv-replay info``), and the same :class:`LogFormatError` from :func:`open_log`.
"""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.stream_reader import StreamReader
from mcap.records import Message
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_protobuf.schema import register_schema
from typer.testing import CliRunner

from lcv_replay.cli import app
from lcv_replay.errors import LogFormatError, RecorderError
from lcv_replay.log import format as fmt
from lcv_replay.log import messages
from lcv_replay.log.container import load_container
from lcv_replay.log.reader import open_log
from lcv_replay.records import Pose2D
from tests.log.helpers import write_synthetic_log

runner = CliRunner()


def _raw_log(path: Path, records: list[tuple[str, object, int]], *, extra_channels: dict[str, tuple[str, str, str]] = {}) -> Path:
    """Write ``(topic, protobuf message, log_time)`` records with the plain mcap writer (no checks)."""
    with open(path, "wb") as f:
        writer = McapWriter(f, compression=CompressionType.NONE)
        writer.start()
        schemas: dict[str, int] = {}
        channels: dict[str, int] = {}
        for topic, (schema_name, schema_encoding, message_encoding) in extra_channels.items():
            sid = writer.register_schema(schema_name, schema_encoding, b"")
            channels[topic] = writer.register_channel(topic, message_encoding, sid)
        for seq, (topic, message, log_time) in enumerate(records):
            if topic not in channels:
                name = type(message).DESCRIPTOR.full_name
                if name not in schemas:
                    schemas[name] = register_schema(writer, type(message))
                channels[topic] = writer.register_channel(topic, "protobuf", schemas[name])
            data = message if isinstance(message, bytes) else message.SerializeToString()
            writer.add_message(channels[topic], log_time=log_time, data=data, publish_time=log_time, sequence=seq)
        writer.finish()
    return path


def _odom(i: int, x: float = 0.0) -> tuple[str, object, int]:
    return (fmt.ODOM_TOPIC, messages.pose_in_frame(Pose2D(x, 0.0, 0.0), i, fmt.ODOM_FRAME_ID), i)


def _image(topic: str, t: int) -> tuple[str, object, int]:
    return (topic, messages.CompressedImage(frame_id="cam", format="png", data=b"\x89PNG"), t)


def _assert_cli_error(path: Path, *needles: str, args: tuple[str, ...] = ()) -> str:
    result = runner.invoke(app, ["info", str(path), *args])
    assert result.exit_code == 2, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    line = lines[0]
    assert line.startswith(f"error: {path}: ")
    assert "Traceback" not in result.output
    assert "(" in line and line.endswith(")")  # the fix, in parentheses
    for needle in needles:
        assert needle in line, line
    return line


def test_not_an_mcap_file(tmp_path):
    path = tmp_path / "picture.mcap"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    _assert_cli_error(path, "not an MCAP file")
    empty = tmp_path / "zero.mcap"
    empty.write_bytes(b"")
    _assert_cli_error(empty, "the file is empty")
    _assert_cli_error(tmp_path / "absent.mcap", "file not found")


def _messages_in_complete_chunks(data: bytes) -> int:
    """Reference count with the mcap library: messages it yields before hitting the cut."""
    import io

    count = 0
    try:
        for record in StreamReader(io.BytesIO(data), skip_magic=False).records:
            count += isinstance(record, Message)
    except Exception:
        pass
    return count


def test_truncated_file_says_recover_and_recover_salvages_complete_chunks(tmp_path):
    full = tmp_path / "full.mcap"
    write_synthetic_log(full, frames=20, chunk_size_bytes=8 * 1024)
    data = full.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    _assert_cli_error(cut, "truncated", "--recover")

    expected = _messages_in_complete_chunks(cut.read_bytes())
    assert expected > 0
    result = runner.invoke(app, ["info", str(cut), "--recover", "--json"])
    assert result.exit_code == 0, result.output
    assert f"recovered {expected} messages" in result.stderr
    with open_log(cut, recover=True) as reader:
        assert reader.info.recovered_messages == expected
        assert 5 <= reader.info.frames < 20
        frames = list(reader.frames())
        assert frames[-1].left.decode().shape == (30, 40, 3)


def _corrupt_middle_chunk(src: Path, dst: Path) -> int:
    container = load_container(src)
    chunk = container.chunks[len(container.chunks) // 2]
    data = bytearray(src.read_bytes())
    body = chunk.file_offset + 9
    data_start = body + 8 + 8 + 8 + 4 + 4 + 0 + 8  # uncompressed chunk: empty compression string
    data[data_start + (chunk.record_length - 40) // 2] ^= 0xFF
    dst.write_bytes(bytes(data))
    return len(container.chunks)


def test_chunk_crc_mismatch(tmp_path):
    good = tmp_path / "good.mcap"
    write_synthetic_log(good, frames=20, compression="none", chunk_size_bytes=8 * 1024)
    bad = tmp_path / "bad.mcap"
    n_chunks = _corrupt_middle_chunk(good, bad)
    _assert_cli_error(bad, "fails its CRC check", "re-copy")
    with open_log(bad) as reader:  # opening uses only the index; reading the chunk fails
        with pytest.raises(LogFormatError, match="CRC"):
            list(reader.frames())
    result = runner.invoke(app, ["info", str(bad), "--recover"])
    assert result.exit_code == 0, result.output
    # recover keeps the chunks before the damaged one (a prefix, so frame indices keep their meaning)
    with open_log(bad, recover=True) as reader, open_log(good) as reference:
        assert reader.info.chunk_count == n_chunks // 2
        assert reader.info.skipped_chunks == n_chunks - n_chunks // 2
        assert f"recovered {reader.info.recovered_messages} messages" in result.stderr
        assert 0 < reader.info.frames < reference.info.frames
        kept = list(reader.frames())
        np.testing.assert_array_equal(reader.odometry(), reference.odometry()[: len(kept)])
        assert reader.loop_candidates() == [c for c in reference.loop_candidates() if c.query_frame < len(kept)]


def test_missing_required_topics(tmp_path):
    tf = messages.frame_transform(Pose2D(0, 0, 0), 0, "odom", "base_link")
    path = _raw_log(tmp_path / "tf_only.mcap", [(fmt.TF_TOPIC, tf, 0), ("/diagnostics", tf, 1)])
    _assert_cli_error(path, "missing required topics", "/stereo/left/image or /odom", "/diagnostics, /tf")
    right_only = _raw_log(tmp_path / "right.mcap", [_image(fmt.RIGHT_IMAGE_TOPIC, 0)])
    _assert_cli_error(right_only, "has /stereo/right/image but no /stereo/left/image")


def test_unknown_schema_on_a_known_topic(tmp_path):
    path = _raw_log(
        tmp_path / "ros.mcap",
        [(fmt.ODOM_TOPIC, b"\x00\x01\x00\x00", 0)],
        extra_channels={fmt.ODOM_TOPIC: ("nav_msgs/msg/Odometry", "ros2msg", "cdr")},
    )
    _assert_cli_error(path, "/odom has unknown schema 'nav_msgs/msg/Odometry'", "foxglove.PoseInFrame", "record rosbag")


@pytest.mark.parametrize("bad_value, problem", [(math.nan, "not finite"), (math.inf, "not finite"), (1.3e39, "out of range")])
def test_non_finite_or_absurd_odometry_names_the_frame(tmp_path, bad_value, problem):
    records = [_odom(i * 100, x=float(i)) for i in range(6)]
    records[3] = _odom(300, x=bad_value)
    path = _raw_log(tmp_path / "nan.mcap", records)
    _assert_cli_error(path, "/odom of frame 3", problem)
    with pytest.raises(LogFormatError, match="frame 3"):
        open_log(path).odometry()


def test_an_absurd_candidate_measurement_is_refused(tmp_path):
    """A bit flip in a candidate's JSON can leave valid JSON with a value no verifier can use."""
    from lcv_replay.log.writer import LogWriter
    from lcv_replay.records import LoopCandidate

    path = tmp_path / "cand.mcap"
    with LogWriter(path, dataset="d", recorder="t", nominal_rate_hz=10, recorder_config={}, compression="none") as w:
        for i in range(5):
            w.write_frame(i, i * 100, odom=Pose2D(float(i), 0, 0))
        w.write_loop_candidate(LoopCandidate(4, 1, T_match_query=Pose2D(0.5, 0.0, 0.0), information=(100.0, 0, 0, 100.0, 0, 100.0)), 400)
    from lcv_replay.bench.fuzz import plain_copy

    data = plain_copy(path)  # no CRCs: the edit below is not caught as damage
    assert data.count(b'"x_m":0.5') == 1
    data = data.replace(b'"x_m":0.5', b'"x_m":9e9')
    bad = tmp_path / "absurd.mcap"
    bad.write_bytes(data)
    _assert_cli_error(bad, "/loop_candidates candidate (4, 1)", "T_match_query", "out of range")
    with pytest.raises(RecorderError, match="out of range"):
        with LogWriter(tmp_path / "w.mcap", dataset="d", recorder="t", nominal_rate_hz=10, recorder_config={}) as w:
            w.write_frame(0, 0, odom=Pose2D(2e8, 0.0, 0.0))


def test_timestamps_going_backwards(tmp_path):
    path = _raw_log(tmp_path / "back.mcap", [_odom(t) for t in (0, 100, 200, 150, 300)])
    _assert_cli_error(path, "timestamps go backwards on /odom: message 3", "150 ns")


def test_stereo_counts_that_cannot_be_paired(tmp_path):
    records = [_image(fmt.LEFT_IMAGE_TOPIC, i * 100_000_000) for i in range(10)]
    records += [_image(fmt.RIGHT_IMAGE_TOPIC, i * 100_000_000) for i in range(4)]
    path = _raw_log(tmp_path / "stereo.mcap", records)
    _assert_cli_error(path, "cannot be paired", "10 left and 4 right", "4 pairs")


def test_a_few_unpaired_stereo_images_are_dropped_and_reported(tmp_path, caplog):
    records = [_image(fmt.LEFT_IMAGE_TOPIC, i * 100_000_000) for i in range(30)]
    records += [_image(fmt.RIGHT_IMAGE_TOPIC, i * 100_000_000 + 1_000_000) for i in range(30) if i != 17]
    path = _raw_log(tmp_path / "stereo.mcap", records)
    with caplog.at_level("WARNING"):
        reader = open_log(path)
    assert reader.info.frames == 29 and reader.info.dropped_unpaired_images == 1
    assert 17 * 100_000_000 not in reader.frame_stamps_ns
    assert "dropped 1 stereo images" in caplog.text


def test_empty_log(tmp_path):
    path = _raw_log(tmp_path / "empty.mcap", [])
    _assert_cli_error(path, "the log is empty")
    declared = _raw_log(
        tmp_path / "declared.mcap", [], extra_channels={fmt.ODOM_TOPIC: ("foxglove.PoseInFrame", "protobuf", "protobuf")}
    )
    _assert_cli_error(declared, "the log is empty")


def test_candidate_not_at_its_query_frame(tmp_path):
    records = [_odom(i * 100) for i in range(5)]
    path = tmp_path / "cand.mcap"
    _raw_log(path, records)
    from lcv_replay.log.writer import LogWriter
    from lcv_replay.records import LoopCandidate

    ok = tmp_path / "ok.mcap"
    with LogWriter(ok, dataset="d", recorder="t", nominal_rate_hz=10, recorder_config={}) as w:
        for i in range(5):
            w.write_frame(i, i * 100, odom=Pose2D(0, 0, 0))
        w.write_loop_candidate(LoopCandidate(4, 1), 400)
    # Re-stamp the candidate at frame 2 by rewriting the file with the raw writer.
    from mcap.reader import make_reader

    with open(ok, "rb") as f:
        msgs = [(c.topic, m.data, m.log_time) for _, c, m in make_reader(f).iter_messages()]
    with open(path, "wb") as f:
        writer = McapWriter(f)
        writer.start()
        sid = register_schema(writer, messages.PoseInFrame)
        cid_odom = writer.register_channel(fmt.ODOM_TOPIC, "protobuf", sid)
        jid = writer.register_schema(messages.LOOP_CANDIDATE_SCHEMA, "jsonschema", b"{}")
        cid_cand = writer.register_channel(fmt.LOOP_CANDIDATES_TOPIC, "json", jid)
        for topic, data, t in msgs:
            if topic == fmt.ODOM_TOPIC:
                writer.add_message(cid_odom, t, data, t)
            elif topic == fmt.LOOP_CANDIDATES_TOPIC:
                writer.add_message(cid_cand, 200, data, 200)
        writer.finish()
    _assert_cli_error(path, "stamped at frame 2", "not at its query frame 4")


def test_real_process_exit_code_and_no_traceback(tmp_path):
    path = tmp_path / "junk.mcap"
    path.write_bytes(np.random.default_rng(0).bytes(4096))
    proc = subprocess.run(
        [sys.executable, "-c", "from lcv_replay.cli import main; main()", "info", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2
    assert proc.stdout == ""
    assert proc.stderr.strip() == f"error: {path}: not an MCAP file (no MCAP magic bytes at the start) (pass a log written by 'lcv-replay record' (or any MCAP file))"


# -- damage that the container must name precisely (issue 12) ----------------------------------------
def _message_index_records(path: Path, topic: str):
    """``(file offset, channel id, entries)`` of each message-index record of ``topic``."""
    import struct

    container = load_container(path)
    data = path.read_bytes()
    ids = set(container.topic_channels(topic))
    for chunk in container.chunks:
        pos = chunk.file_offset + 9 + chunk.record_length
        while data[pos] == 0x07:
            (length,) = struct.unpack_from("<Q", data, pos + 1)
            channel_id, records_len = struct.unpack_from("<HI", data, pos + 9)
            if channel_id in ids:
                yield pos, channel_id, records_len // 16
            pos += 9 + length


def test_appended_bytes_are_not_called_truncated(tmp_path):
    good = tmp_path / "good.mcap"
    write_synthetic_log(good, frames=6)
    size = good.stat().st_size
    bad = tmp_path / "appended.mcap"
    bad.write_bytes(good.read_bytes() + b"\x00garbage" * 40)
    line = _assert_cli_error(bad, f"320 bytes of unexpected data follow the end of the MCAP at byte {size}", f"truncate -s {size}")
    assert "truncated at" not in line
    result = runner.invoke(app, ["info", str(bad), "--recover", "--json"])
    assert result.exit_code == 0, result.output
    with open_log(bad, recover=True) as reader:
        assert reader.info.frames == 6


def test_damaged_closing_magic_is_named(tmp_path):
    good = tmp_path / "good.mcap"
    write_synthetic_log(good, frames=4)
    data = bytearray(good.read_bytes())
    data[-3] ^= 0x10
    bad = tmp_path / "magic.mcap"
    bad.write_bytes(bytes(data))
    _assert_cli_error(bad, f"the closing magic bytes at byte {len(data) - 8} are damaged")


def test_a_damaged_message_index_is_not_called_timestamps_going_backwards(tmp_path):
    good = tmp_path / "good.mcap"
    write_synthetic_log(good, frames=12, images=False, compression="none")
    offset, _channel, count = next(_message_index_records(good, fmt.ODOM_TOPIC))
    assert count >= 3
    data = bytearray(good.read_bytes())
    first = offset + 9 + 6 + 16  # entry 1's log_time; swap it with entry 2's (both inside the chunk's range)
    data[first : first + 8], data[first + 16 : first + 24] = data[first + 16 : first + 24], data[first : first + 8]
    bad = tmp_path / "index.mcap"
    bad.write_bytes(bytes(data))
    line = _assert_cli_error(bad, "the message index of the chunk at byte", "is damaged", "--recover, which rebuilds it")
    assert "backwards" not in line
    result = runner.invoke(app, ["info", str(bad), "--recover"])
    assert result.exit_code == 0, result.output
    with open_log(bad, recover=True) as reader, open_log(good) as reference:
        np.testing.assert_array_equal(reader.odometry(), reference.odometry())


def test_a_message_index_entry_outside_its_chunk_names_the_record(tmp_path):
    good = tmp_path / "good.mcap"
    write_synthetic_log(good, frames=12, images=False)
    offset, _channel, _count = next(_message_index_records(good, fmt.ODOM_TOPIC))
    data = bytearray(good.read_bytes())
    data[offset + 9 + 6 + 7] ^= 0x40  # the high byte of entry 0's log_time
    bad = tmp_path / "index.mcap"
    bad.write_bytes(bytes(data))
    _assert_cli_error(bad, f"the message index record at byte {offset} is damaged", "outside the time range")


def test_damaged_metadata_names_the_record_and_its_offset(tmp_path):
    """The issue's reproduction: metadata records carry no CRC (byte 54 lies in the first one)."""
    good = tmp_path / "good.mcap"
    write_synthetic_log(good, frames=4)
    data = bytearray(good.read_bytes())
    data[54] = 0xFF
    bad = tmp_path / "meta.mcap"
    bad.write_bytes(bytes(data))
    _assert_cli_error(bad, "the metadata record at byte 41 is damaged", "not valid UTF-8")


def test_the_data_section_crc_catches_damage_no_other_check_sees(tmp_path):
    good = tmp_path / "good.mcap"
    write_synthetic_log(good, frames=4)
    data = bytearray(good.read_bytes())
    at = data.index(b"synthetic-test")  # the dataset name in the 'lcv' metadata: still valid UTF-8 when changed
    data[at] = ord("S")
    bad = tmp_path / "meta.mcap"
    bad.write_bytes(bytes(data))
    assert runner.invoke(app, ["info", str(bad), "--no-check"]).exit_code == 0
    _assert_cli_error(bad, "the data section", "fails its CRC check", "outside the chunks")


def test_recover_that_salvages_nothing_says_so(tmp_path):
    good = tmp_path / "good.mcap"
    write_synthetic_log(good, frames=4)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(good.read_bytes()[:200])
    line = _assert_cli_error(cut, "--recover salvaged nothing", "the metadata record at byte 41", args=("--recover",))
    assert "recorder produced no frames" not in line
