"""A full disk or an unwritable output: one ``error:`` line naming the path and the free space, exit 2,
no temp file left behind (record, --save, --summary-json, bench outputs).

The outputs go to a 2 MB tmpfs mounted for the test (root only: skipped with the reason otherwise),
filled up with a filler file, and unmounted at teardown.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from lcv_replay.cli.inprocess import run_cli
from tests.replay.helpers import record_square_route

TMPFS_BYTES = 2 * 1024 * 1024


@pytest.fixture
def tiny_disk(tmp_path):
    """A 2 MB tmpfs at ``tmp_path/tiny``."""
    mount_point = tmp_path / "tiny"
    mount_point.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={TMPFS_BYTES}", "tmpfs", str(mount_point)], capture_output=True, text=True)
    if proc.returncode != 0:
        pytest.skip(f"mounting a tmpfs is not permitted here: {proc.stderr.strip()}")
    try:
        yield mount_point
    finally:
        subprocess.run(["umount", "-l", str(mount_point)], check=False)


def fill(folder: Path, leave_bytes: int = 0) -> None:
    """Fill ``folder``'s file system up to ``leave_bytes`` free (a ``.filler`` file)."""
    free = os.statvfs(folder).f_bavail * os.statvfs(folder).f_frsize
    with open(folder / ".filler", "wb") as f:
        try:
            f.write(bytes(max(free - leave_bytes, 0)))
        except OSError:
            pass


def assert_full_disk_error(run, path: Path, folder: Path) -> str:
    assert run.traceback is None, run.traceback
    assert "Traceback" not in run.stderr, run.stderr
    assert run.exit_code == 2, run.stderr
    lines = run.error_lines()
    assert len(lines) == 1, run.stderr
    assert lines[0].startswith(f"error: {path}: cannot write"), lines[0]
    assert "the disk is full" in lines[0] and f"free of 2.1 MB on {folder}" in lines[0], lines[0]
    assert sorted(p.name for p in folder.iterdir()) == [".filler"], "temp files left behind"
    return lines[0]


@pytest.fixture(scope="module")
def square_log(tmp_path_factory):
    log, route = record_square_route(tmp_path_factory.mktemp("disk"), laps=2, side_poses=25)
    return log, route


def test_record_synthetic_on_a_full_disk(tiny_disk):
    fill(tiny_disk, leave_bytes=100_000)
    out = tiny_disk / "s.mcap"
    run = run_cli(["record", "synthetic", "-o", str(out), "--frames", "40", "--resolution", "160x120", "-q"])
    assert_full_disk_error(run, out, tiny_disk)


def test_record_g2o_on_a_full_disk(tiny_disk, square_log):
    _log, route = square_log
    fill(tiny_disk, leave_bytes=8_000)
    out = tiny_disk / "g.mcap"
    run = run_cli(["record", "g2o", str(route.graph), "-o", str(out), "--ground-truth", str(route.ground_truth), "-q"])
    assert_full_disk_error(run, out, tiny_disk)


def test_replay_save_on_a_full_disk(tiny_disk, square_log):
    log, _route = square_log
    fill(tiny_disk, leave_bytes=60_000)
    rrd = tiny_disk / "out.rrd"
    run = run_cli([str(log), "--save", str(rrd), "--quiet", "--image-every", "0"])
    assert_full_disk_error(run, rrd, tiny_disk)
    assert "File-writer thread" not in run.stderr  # Rerun's own lines are silenced; ours says it


def test_summary_json_on_a_full_disk(tiny_disk, square_log):
    log, _route = square_log
    fill(tiny_disk)
    js = tiny_disk / "summary.json"
    run = run_cli([str(log), "--no-rerun", "--quiet", "--summary-json", str(js)])
    assert_full_disk_error(run, js, tiny_disk)
    assert "lcv-replay summary" in run.stdout  # the run itself finished and was reported


def test_bench_output_on_a_full_disk(tiny_disk, square_log):
    log, _route = square_log
    fill(tiny_disk)
    js = tiny_disk / "bench.json"
    run = run_cli(["bench", "verify", str(log), "--method", "none", "--json", str(js)])
    assert_full_disk_error(run, js, tiny_disk)


def test_a_bench_folder_that_cannot_be_created(tiny_disk):
    subprocess.run(["mount", "-o", "remount,ro", str(tiny_disk)], check=True)
    out = tiny_disk / "deep" / "log.json"
    run = run_cli(["bench", "log", "--frames", "2", "--source", "synthetic", "--repeats", "1", "-o", str(out)])
    assert run.exit_code == 2 and len(run.error_lines()) == 1, run.stderr
    line = run.error_lines()[0]
    assert line.startswith(f"error: {tiny_disk / 'deep'}: cannot write there: the file system is read-only, "), line
    assert "free of 2.1 MB" in line


def test_a_read_only_output_folder(tiny_disk, square_log):
    _log, route = square_log
    subprocess.run(["mount", "-o", "remount,ro", str(tiny_disk)], check=True)
    out = tiny_disk / "g.mcap"
    run = run_cli(["record", "g2o", str(route.graph), "-o", str(out), "-q"])
    assert run.exit_code == 2 and len(run.error_lines()) == 1, run.stderr
    assert "not writable" in run.error_lines()[0] and "free of" in run.error_lines()[0]


def test_a_real_process_on_a_full_disk(tiny_disk, square_log):
    _log, route = square_log
    fill(tiny_disk, leave_bytes=8_000)
    out = tiny_disk / "g.mcap"
    proc = subprocess.run(
        [sys.executable, "-c", "from lcv_replay.cli import main; main()", "record", "g2o", str(route.graph), "-o", str(out), "-q"],
        capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 2, proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert errors[0].startswith(f"error: {out}: cannot write the file: the disk is full, ")
    assert sorted(p.name for p in tiny_disk.iterdir()) == [".filler"]
