"""Every seed follows one rule with one message: an integer from 0 to 2**63 - 1 (issue 12)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lcv_replay.cli.inprocess import run_cli
from lcv_replay.errors import SEED_LIMIT, ConfigError, require_seed

GOLDEN = Path(__file__).resolve().parent / "data" / "golden.mcap"
FIX = "(a seed is an integer from 0 to 2**63 - 1)"


@pytest.mark.parametrize("value", [0, 1, SEED_LIMIT - 1, np.int64(7)])
def test_the_rule_accepts(value):
    assert require_seed(value, "--seed") == int(value)


@pytest.mark.parametrize("value", [-1, SEED_LIMIT, 2**70, True, 1.0, "3", None])
def test_the_rule_refuses_with_one_message(value):
    with pytest.raises(ConfigError) as info:
        require_seed(value, "--seed")
    assert info.value.format() == f"invalid seed {value!r} for --seed {FIX}"


def _one_error(args: list[str]) -> str:
    run = run_cli(args)
    assert run.traceback is None, run.traceback
    assert run.exit_code == 2, run.stderr
    lines = run.error_lines()
    assert len(lines) == 1, run.stderr
    return lines[0]


@pytest.mark.parametrize(
    "args, name",
    [
        ([str(GOLDEN), "--no-rerun", "--seed", "-1"], "--seed"),
        ([str(GOLDEN), "--no-rerun", "--seed", str(SEED_LIMIT)], "--seed"),
        (["record", "synthetic", "-o", "never.mcap", "--seed", "-1"], "record synthetic --seed"),
        (["bench", "verify", str(GOLDEN), "--seed", "-1"], "--seed"),
        (["bench", "fuzz", "--files", "1", "--seed", "-1"], "--seed"),
        (["demo", "--seed", "-1"], "--seed"),
    ],
)
def test_cli_seeds(args, name, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    line = _one_error(args)
    assert line == f"error: invalid seed {args[-1]} for {name} {FIX}"
    assert not list(tmp_path.iterdir())


def test_record_g2o_seed(tmp_path):
    from tests.replay.helpers import square_route_g2o

    route = square_route_g2o(tmp_path, laps=2, side_poses=25)
    line = _one_error(["record", "g2o", str(route.graph), "-o", str(tmp_path / "o.mcap"), "--outliers", "5", "--seed", "-1"])
    assert line == f"error: invalid seed -1 for record g2o --seed {FIX}"


@pytest.mark.parametrize("section", ["verification", "retrieval"])
def test_config_seeds(section, tmp_path):
    config = tmp_path / "c.toml"
    config.write_text(f"[{section}]\nseed = -1\n")
    line = _one_error([str(GOLDEN), "--no-rerun", "-c", str(config)])
    assert line == f"error: {config}: invalid seed -1 for config key '{section}.seed' {FIX}"


def test_suite_file_seeds(tmp_path):
    from lcv_replay.bench.suites import get_suite

    suite = tmp_path / "s.toml"
    suite.write_text('name = "s"\n[[case]]\nname = "c"\ngraph = "x.g2o"\nseed = -1\n')
    with pytest.raises(ConfigError) as info:
        get_suite(str(suite))
    assert info.value.format() == f"{suite}: invalid seed -1 for suite key 'case.seed' {FIX}"
