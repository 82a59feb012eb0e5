"""SIGTERM is handled like Ctrl-C: stop after the current frame, finalise the outputs, exit 143; a second
signal aborts at once and leaves no temp file (real processes, real signals)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from lcv_replay.log.reader import open_log
from tests.replay.helpers import FAST_CONFIG_TOML, record_square_route, write_config

REPO = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-c", "from lcv_replay.cli import main; main()"]

pytestmark = pytest.mark.slow


def _start(args: list[str], cwd: Path = REPO) -> subprocess.Popen:
    return subprocess.Popen([*CLI, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=cwd)


def _wait_for(predicate, proc: subprocess.Popen, timeout_s: float = 90.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


def _temp_files(folder: Path) -> list[Path]:
    return [p for p in folder.iterdir() if p.name.startswith(".") and p.name.endswith(".tmp")]


@pytest.fixture(scope="module")
def square(tmp_path_factory):
    folder = tmp_path_factory.mktemp("signals")
    log, _route = record_square_route(folder, laps=2, side_poses=25)
    return log, write_config(folder / "fast.toml", FAST_CONFIG_TOML)


def _record(out: Path) -> subprocess.Popen:
    proc = _start(["record", "synthetic", "-o", str(out), "--frames", "400", "--resolution", "160x120", "-q"])
    _wait_for(lambda: any(p.stat().st_size > 0 for p in _temp_files(out.parent)), proc)
    return proc


def test_sigterm_stops_a_recording_after_the_current_frame_and_closes_a_valid_log(tmp_path):
    out = tmp_path / "s.mcap"
    proc = _record(out)
    time.sleep(1.0)
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 143, stderr
    assert "Traceback" not in stderr and "SIGTERM: stopping after this frame and closing the log" in stderr
    assert "INTERRUPTED: the first" in stdout and "of 400 frames" in stdout
    with open_log(out) as reader:
        reader.check()
        assert 0 < reader.info.frames < 400
        assert len(reader.odometry()) == reader.info.frames
    assert not _temp_files(tmp_path)


def test_a_second_signal_aborts_a_recording_and_removes_the_temp_file(tmp_path):
    out = tmp_path / "s.mcap"
    proc = _record(out)
    proc.send_signal(signal.SIGINT)  # two different signals are not merged by the kernel:
    proc.send_signal(signal.SIGTERM)  # the first asks for a stop, the second aborts
    _stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 143, stderr
    assert "interrupted by SIGTERM: stopped at once" in stderr and "Traceback" not in stderr
    assert not out.exists() and not _temp_files(tmp_path)


def _replay(square, tmp_path: Path) -> tuple[subprocess.Popen, Path, Path]:
    log, config = square
    rrd, js = tmp_path / "r.rrd", tmp_path / "r.json"
    proc = _start([str(log), "--rate", "2", "--quiet", "-c", str(config), "--save", str(rrd), "--summary-json", str(js)])
    _wait_for(lambda: bool(_temp_files(tmp_path)), proc)
    return proc, rrd, js


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_mid_replay_finalises_the_recording_and_the_summary(square, tmp_path, signum):
    proc, rrd, js = _replay(square, tmp_path)
    time.sleep(2.0)  # 200 frames at 2x real time take 10 s
    proc.send_signal(signum)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signum, stderr
    summary = json.loads(js.read_text())
    assert summary["interrupted"] is True and 0 < summary["frames"] < 200
    assert "INTERRUPTED" in stdout and "Traceback" not in stderr
    verify = subprocess.run(["rerun", "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=120)
    assert verify.returncode == 0, verify.stdout + verify.stderr
    assert not _temp_files(tmp_path)


def test_a_second_signal_aborts_a_replay_and_removes_the_temp_files(square, tmp_path):
    proc, rrd, js = _replay(square, tmp_path)
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    proc.send_signal(signal.SIGTERM)
    _stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 143, stderr
    assert "Traceback" not in stderr
    assert not rrd.exists() and not js.exists() and not _temp_files(tmp_path)


def test_sigterm_stops_the_fuzz_benchmark_with_a_partial_report(tmp_path):
    out, work = tmp_path / "fuzz.json", tmp_path / "work"
    golden = REPO / "tests" / "data" / "golden.mcap"
    proc = _start(["bench", "fuzz", "--files", "5000", "--log", str(golden), "--workdir", str(work), "-o", str(out), "-q"])
    _wait_for(lambda: (work / "mutant.mcap").exists(), proc)
    time.sleep(1.0)
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 143, stderr
    report = json.loads(out.read_text())
    assert report["complete"] is False and 0 < report["files"] < 5000
    assert "(INTERRUPTED)" in stdout and "Traceback" not in stderr


def test_vo_stops_after_the_current_frame_and_writes_the_log_so_far(tmp_path):
    from lcv_replay.shutdown import StopToken, stop_on_signals
    from lcv_replay.vo.log_vo import add_vo_odometry
    from recorders.synthetic import SyntheticOptions, record_synthetic

    source = tmp_path / "src.mcap"
    record_synthetic(source, SyntheticOptions(frames=30, width_px=160, height_px=120))
    stop = StopToken()

    def on_step(step) -> None:
        if step.index == 9:
            stop.request(signal.SIGTERM)

    with stop_on_signals(stop):
        stats = add_vo_odometry(source, tmp_path / "vo.mcap", replace_odometry=True, on_step=on_step)
    assert stats.interrupted and stats.frames_planned == 30 and len(stats.result.steps) == 10
    assert stop.exit_code == 143
    with open_log(tmp_path / "vo.mcap") as reader:
        assert reader.info.frames == 10 and reader.odometry().shape == (10, 3)
