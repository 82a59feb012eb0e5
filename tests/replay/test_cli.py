"""`lcv-replay LOG.mcap`: bad input gets one ``error:`` line and exit code 2 (signals: tests/test_signals.py)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from lcv_replay.cli import app
from lcv_replay.records import Pose2D
from tests.replay.helpers import FAST_CONFIG_TOML, record_square_route, write_config


@pytest.fixture(scope="module")
def square(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cli")
    log, route = record_square_route(folder, laps=2, side_poses=25)
    return folder, log, write_config(folder / "fast.toml", FAST_CONFIG_TOML)


def _write_log(path: Path, *, odom: bool, images: bool) -> Path:
    from recorders.common import LogHeader, SourceFrame, write_log

    image = np.zeros((16, 24), dtype=np.uint8)
    frames = [
        SourceFrame(
            stamp_ns=k * 100_000_000,
            left=(lambda: image) if images else None,
            odom=Pose2D(float(k), 0.0, 0.0) if odom else None,
        )
        for k in range(5)
    ]
    write_log(path, LogHeader(dataset="bad", recorder="test", nominal_rate_hz=10.0, config={}), frames, force=True)
    return path


def _cli(args: list[str]):
    result = CliRunner().invoke(app, args)
    return result.exit_code, result.output


def _assert_one_line_error(code: int, output: str, *needles: str) -> None:
    lines = [line for line in output.splitlines() if line.startswith("error:")]
    assert code == 2, output
    assert len(lines) == 1, output
    assert "Traceback" not in output
    for needle in needles:
        assert needle in lines[0], lines[0]


def test_missing_file(tmp_path):
    code, out = _cli([str(tmp_path / "nope.mcap"), "--quiet"])
    _assert_one_line_error(code, out, "nope.mcap", "file not found")
    assert not (tmp_path / "nope.rrd").exists()


def test_log_without_odometry(tmp_path):
    log = _write_log(tmp_path / "noodom.mcap", odom=False, images=True)
    code, out = _cli([str(log), "--quiet"])
    _assert_one_line_error(code, out, "noodom.mcap", "no odometry", "lcv-replay vo")
    assert not (tmp_path / "noodom.rrd").exists()


def test_log_with_neither_images_nor_candidates(tmp_path):
    log = _write_log(tmp_path / "bare.mcap", odom=True, images=False)
    code, out = _cli([str(log), "--quiet"])
    _assert_one_line_error(code, out, "bare.mcap", "neither images nor /loop_candidates")


def test_constraints_that_the_log_cannot_serve(square):
    _, log, config = square
    code, out = _cli([str(log), "--quiet", "--constraints", "images", "--config", str(config)])
    _assert_one_line_error(code, out, "--constraints images needs images", "use --constraints log")


@pytest.mark.parametrize("where", ["missing-folder", "is-a-folder"])
def test_unwritable_outputs(square, tmp_path, where):
    _, log, config = square
    target = tmp_path / "missing" / "out.rrd" if where == "missing-folder" else tmp_path
    code, out = _cli([str(log), "--quiet", "--config", str(config), "--save", str(target)])
    _assert_one_line_error(code, out, str(target))
    code, out = _cli([str(log), "--quiet", "--config", str(config), "--no-rerun", "--summary-json", str(target)])
    _assert_one_line_error(code, out, str(target))


@pytest.mark.parametrize(
    "toml, needles",
    [
        ("[verification]\nwindw_frames = 10\n", ("unknown config key 'verification.windw_frames'", "window_frames")),
        ("[verification]\nwindow_frames = 0\n", ("verification.window_frames", "out of range")),
        ("[rerun]\nimage_every = -1\n", ("rerun.image_every",)),
        ("[verification\n", ("not valid TOML",)),
    ],
)
def test_bad_config_names_the_key(square, tmp_path, toml, needles):
    _, log, _ = square
    config = write_config(tmp_path / "bad.toml", toml)
    code, out = _cli([str(log), "--quiet", "--config", str(config)])
    _assert_one_line_error(code, out, "bad.toml", *needles)


def test_unknown_method_and_bad_rate(square):
    _, log, config = square
    code, out = _cli([str(log), "--quiet", "--config", str(config), "--method", "magic"])
    _assert_one_line_error(code, out, "unknown verification method 'magic'", "ilv")
    code, out = _cli([str(log), "--quiet", "--rate", "0"])
    _assert_one_line_error(code, out, "--rate")


def test_replay_writes_the_default_rrd_next_to_the_log_and_prints_the_summary(square):
    folder, log, config = square
    code, out = _cli([str(log), "--quiet", "--config", str(config), "--summary-json", str(folder / "cli.json")])
    assert code == 0, out
    assert (folder / "square.rrd").is_file()
    assert "lcv-replay summary" in out and f"rerun {folder / 'square.rrd'}" in out
    assert json.loads((folder / "cli.json").read_text())["frames"] == 200


def test_the_oracle_on_a_log_without_truth_is_refused_before_the_first_frame(square, tmp_path):
    from recorders.g2o import G2oOptions, record_g2o

    folder, _, config = square
    log = tmp_path / "no_truth.mcap"
    record_g2o(folder / "src" / "square.g2o", log, G2oOptions(auto_siblings=False), force=True)
    code, out = _cli([str(log), "--method", "oracle", "-c", str(config), "--no-rerun", "--quiet"])
    _assert_one_line_error(code, out, "no_truth.mcap", "method 'oracle' needs the log's true loops", "--true-loops")
    assert "accepted" not in out  # refused up front: no summary


def test_an_existing_output_is_refused_without_force_and_replaced_with_it(square, tmp_path):
    _, log, config = square
    out = tmp_path / "kept.rrd"
    out.write_bytes(b"an earlier recording")
    code, text = _cli([str(log), "-c", str(config), "--save", str(out), "--quiet"])
    _assert_one_line_error(code, text, "kept.rrd", "already exists", "--force")
    assert out.read_bytes() == b"an earlier recording"  # refused before the replay touched anything
    code, text = _cli([str(log), "-c", str(config), "--save", str(out), "--quiet", "-f"])
    assert code == 0, text
    assert out.stat().st_size > 1000 and out.read_bytes()[:4] != b"an e"


def test_the_default_recording_beside_the_log_is_replaced_by_each_run(square, tmp_path):
    """Only files the user names need --force: replaying twice into the default LOG.rrd works."""
    _, log, config = square
    default = log.with_suffix(".rrd")
    for _ in range(2):
        code, text = _cli([str(log), "-c", str(config), "--quiet"])
        assert code == 0, text
        assert default.stat().st_size > 1000
