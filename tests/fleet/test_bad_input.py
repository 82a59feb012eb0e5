"""Bad input to batch and compare: one `error:` line, exit 2, nothing written."""

from __future__ import annotations

import socket
import time

from typer.testing import CliRunner

from lcv_replay.cli import app


def _cli(args):
    result = CliRunner().invoke(app, [str(a) for a in args])
    return result.exit_code, result.output


def _one_error(code, output, *needles, exit_code=2):
    lines = [line for line in output.splitlines() if line.startswith("error:")]
    assert code == exit_code, output
    assert len(lines) == 1 and "Traceback" not in output, output
    for needle in needles:
        assert needle in lines[0], lines[0]


def test_no_logs_matched(tmp_path):
    code, out = _cli(["batch", tmp_path / "nowhere" / "*.mcap", "--out", tmp_path / "run"])
    _one_error(code, out, "no logs matched", "nowhere")
    assert not (tmp_path / "run").exists()


def test_out_is_a_file(fleet_logs, tmp_path):
    target = tmp_path / "run"
    target.write_text("mine")
    code, out = _cli(["batch", fleet_logs.logs[0], "--out", target])
    _one_error(code, out, "--out is a file", str(target))
    assert target.read_text() == "mine"


def test_out_is_someone_elses_folder(fleet_logs, tmp_path):
    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "cat.jpg").write_bytes(b"\xff\xd8")
    code, out = _cli(["batch", fleet_logs.logs[0], "--out", tmp_path / "photos"])
    _one_error(code, out, "not a batch run folder")
    assert sorted(p.name for p in (tmp_path / "photos").iterdir()) == ["cat.jpg"]


def test_unreachable_address_fails_within_seconds(fleet_logs, tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    for address in (f"ray://127.0.0.1:{port}", f"127.0.0.1:{port}"):
        started = time.perf_counter()
        code, out = _cli(["batch", fleet_logs.logs[0], "--out", tmp_path / "run", "--address", address])
        _one_error(code, out, "unreachable", address)
        assert time.perf_counter() - started < 5.0
        assert not (tmp_path / "run").exists()


def test_unknown_method_before_anything_runs(fleet_logs, tmp_path):
    code, out = _cli(["batch", fleet_logs.logs[0], "--out", tmp_path / "run", "-m", "ilv++"])
    _one_error(code, out, "unknown verification method 'ilv++'")
    assert not (tmp_path / "run").exists()


def test_compare_runs_with_no_log_in_common(tmp_path):
    import json

    for name, log in (("a", "/x/one.mcap"), ("b", "/x/two.mcap")):
        rows = [{"log": log, "method": "ilv+", "false_positives": 0, "recall": 1.0, "ate_rmse_m": 1.0}]
        (tmp_path / f"{name}.json").write_text(json.dumps(rows))
    code, out = _cli(["compare", tmp_path / "a.json", tmp_path / "b.json", "--out", tmp_path])
    _one_error(code, out, "no log in common")
    assert not (tmp_path / "compare.md").exists()


def test_compare_something_that_is_not_a_run(tmp_path):
    (tmp_path / "a").mkdir()
    code, out = _cli(["compare", tmp_path / "a", tmp_path / "a"])
    _one_error(code, out, "not a batch run")
