"""Batch inputs: files, folders and globs to unique log names; the log hash; address parsing."""

from __future__ import annotations

from pathlib import Path

import pytest

from lcv_replay.errors import ConfigError, FleetError
from lcv_replay.fleet.engine import ClusterSpec, check_reachable, parse_address
from lcv_replay.fleet.inputs import discover_logs, expand_inputs, name_logs


def _touch(path: Path, data: bytes = b"x") -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path


def test_files_folders_and_globs_in_order_each_once(tmp_path):
    a = _touch(tmp_path / "day1" / "robotA" / "a.mcap")
    b = _touch(tmp_path / "day1" / "robotB" / "b.mcap")
    c = _touch(tmp_path / "day2" / "c.mcap")
    _touch(tmp_path / "day1" / "notes.txt")
    _touch(tmp_path / "day1" / ".a.mcap.123.tmp")  # a recorder's temp file is not a log
    found = expand_inputs([str(c), str(tmp_path / "day1"), str(tmp_path / "**" / "*.mcap")])
    assert found == [c.resolve(), a.resolve(), b.resolve()]


def test_a_run_folder_inside_an_input_folder_is_not_searched(tmp_path):
    log = _touch(tmp_path / "a.mcap")
    _touch(tmp_path / "run" / "logs" / "a" / "x.mcap")
    assert expand_inputs([str(tmp_path)], exclude=tmp_path / "run") == [log.resolve()]


def test_colliding_stems_get_a_stable_path_hash():
    logs = name_logs([Path("/x/a/run.mcap"), Path("/x/b/run.mcap"), Path("/x/c/other.mcap")])
    names = [log.name for log in logs]
    assert names[2] == "other" and names[0] != names[1] and all(n.startswith("run-") for n in names[:2])
    assert name_logs([Path("/x/a/run.mcap"), Path("/y/z.mcap"), Path("/x/b/run.mcap")])[0].name == names[0]


@pytest.mark.parametrize("pattern", ["nothing/*.mcap", "empty_folder"])
def test_no_logs_matched(tmp_path, pattern):
    (tmp_path / "empty_folder").mkdir()
    with pytest.raises(FleetError, match="no logs matched"):
        expand_inputs([str(tmp_path / pattern)])


def test_a_missing_path_is_named(tmp_path):
    with pytest.raises(FleetError, match="no such file or folder") as info:
        discover_logs([str(tmp_path / "typo.mcap")])
    assert "typo.mcap" in info.value.format()


@pytest.mark.parametrize("address,expected", [
    ("auto", ("auto", None, None)),
    ("10.0.0.5:6379", ("gcs", "10.0.0.5", 6379)),
    ("ray://head.example:10001", ("client", "head.example", 10001)),
    ("ray://[::1]:10001", ("client", "::1", 10001)),
])
def test_addresses(address, expected):
    assert parse_address(address) == expected


@pytest.mark.parametrize("address", ["head", "ray://head", "head:0", "head:port", "http://head:80:x"])
def test_bad_addresses_are_refused(address):
    with pytest.raises(ConfigError, match="not a Ray address"):
        ClusterSpec(address=address)


def test_an_unreachable_address_fails_fast():
    import socket
    import time

    with socket.socket() as s:  # a port that was free a moment ago: nothing listens there
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    started = time.perf_counter()
    with pytest.raises(FleetError, match="unreachable"):
        check_reachable("127.0.0.1", port, address=f"ray://127.0.0.1:{port}")
    assert time.perf_counter() - started < 4.0
