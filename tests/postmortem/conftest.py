"""Runs shared by the post-mortem tests (export, report, viewer screenshots): each replays once per
session through the real CLI, with ``--save``, ``--export`` and ``--report`` together."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest
from typer.testing import CliRunner

from lcv_replay.cli import app
from tests.shared_data import shared_path
from tests.replay.helpers import FAST_CONFIG_TOML, record_square_route, write_config


@dataclass(frozen=True)
class Run:
    """One replay's outputs."""

    folder: Path
    log: Path
    rrd: Path
    export: Path
    report: Path
    summary: dict
    output: str
    config: Path | None = None


def replay_with_outputs(folder: Path, log: Path, *extra: str, config: Path | None = None) -> Run:
    rrd, export, report, js = folder / "run.rrd", folder / "export", folder / "report.html", folder / "summary.json"
    args = [str(log), "--save", str(rrd), "--export", str(export), "--report", str(report), "--summary-json", str(js),
            "--quiet", *extra]
    if config is not None:
        args += ["--config", str(config)]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    import json

    return Run(folder, log, rrd, export, report, json.loads(js.read_text()), result.output, config)


def one_error(args: list[str], *needles: str) -> None:
    """``lcv-replay ARGS`` ends in exactly one ``error:`` line holding ``needles``, exit code 2."""
    result = CliRunner().invoke(app, args)
    lines = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert result.exit_code == 2, result.output
    assert len(lines) == 1 and "Traceback" not in result.output, result.output
    for needle in needles:
        assert needle in lines[0], lines[0]


@pytest.fixture(scope="session")
def square_run(tmp_path_factory) -> Run:
    """The synthetic square route (real g2o recorder, labels and ground truth) with the paper's ``ilv``."""
    folder = tmp_path_factory.mktemp("postmortem_square")
    log, _ = record_square_route(folder)
    config = write_config(folder / "fast.toml", FAST_CONFIG_TOML)
    return replay_with_outputs(folder, log, "--method", "ilv", "--seed", "7", config=config)


@pytest.fixture(scope="session")
def kitti_run(tmp_path_factory) -> Run:
    """KITTI 00 (robustslam, alpha 0.50: real VO, real place-recognition candidates) with ``ilv+``."""
    graph = shared_path("robustslam_kitti", "00", "kitti_00_alpha_0.50.g2o")

    folder = tmp_path_factory.mktemp("postmortem_kitti00")
    log = folder / "kitti00.mcap"
    result = CliRunner().invoke(app, ["record", "g2o", str(graph), "-o", str(log)])
    assert result.exit_code == 0, result.output
    return replay_with_outputs(folder, log)
