"""Seeded, bounded fuzzing: mutated copies of our own small logs through ``info`` and the replay.

Every command run on a mutant must end in exit 0, or exit 2 with exactly one ``error:`` line
naming the file and no traceback (``lcv-replay bench fuzz`` runs the same harness on 10,000 files).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from lcv_replay.bench.fuzz import MUTATIONS, SeedLog, classify, format_report, mutants, run_fuzz
from lcv_replay.cli.inprocess import run_cli
from tests.replay.helpers import record_square_route

GOLDEN = Path(__file__).resolve().parents[1] / "data" / "golden.mcap"


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fuzz-seeds")
    square, _route = record_square_route(folder, laps=2, side_poses=25)
    return [*SeedLog.pair(GOLDEN, "golden"), *SeedLog.pair(square, "square")]


def test_mutants_are_reproducible_and_cover_every_kind(seeds):
    first = list(mutants(seeds, 24, seed=7))
    again = list(mutants(seeds, 24, seed=7))
    assert [m.data for m in first] == [m.data for m in again]
    assert {m.mutation for m in first} == set(MUTATIONS)
    assert {m.log for m in first} == {s.name for s in seeds}
    alone = next(mutants(seeds, 1, seed=7, start=13))
    assert alone.data == first[13].data and alone.description == first[13].description
    by_index = {m.index: m for m in first}
    assert len(by_index[2].data) < len(seeds[0].data)  # truncate
    assert len(by_index[5].data) > len(seeds[0].data)  # append


@pytest.mark.slow
def test_fuzzed_logs_end_in_one_error_line_or_success(seeds, tmp_path):
    report = run_fuzz(seeds, files=96, seed=12, workdir=tmp_path, timeout_s=120)
    assert report.files == 96 and report.complete
    assert not report.bad, format_report(report)
    totals = report.totals()
    assert totals["error"] >= 48, format_report(report)  # most damage is found ...
    assert totals["ok"] >= 1, format_report(report)  # ... and some is harmless (image bytes, padding)
    assert report.by_command["info --recover"]["ok"] > report.by_command["info"]["ok"]


def test_the_classifier_sees_a_traceback(tmp_path, monkeypatch):
    import lcv_replay.log.inspect as inspect

    def broken(*args, **kwargs):
        raise KeyError("boom")

    monkeypatch.setattr(inspect, "format_info", broken)
    run = run_cli(["info", str(GOLDEN)])
    assert classify(run, GOLDEN) == "traceback" and "KeyError" in run.traceback


@pytest.mark.parametrize("index", [0, 3, 4, 5])  # a bit flip, a duplicated chunk, zeros, appended bytes
def test_real_processes_on_mutants(seeds, tmp_path, index):
    mutant = next(mutants(seeds, 1, seed=12, start=index))
    path = tmp_path / f"{mutant.mutation}.mcap"
    path.write_bytes(mutant.data)
    proc = subprocess.run(
        [sys.executable, "-c", "from lcv_replay.cli import main; main()", "info", str(path)],
        capture_output=True, text=True, timeout=120,
    )
    assert "Traceback" not in proc.stderr, proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert (proc.returncode, len(errors)) in ((0, 0), (2, 1)), proc.stderr
    if errors:
        assert errors[0].startswith(f"error: {path}: ")
