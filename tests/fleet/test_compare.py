"""`lcv-replay compare`: the regression rules, a real regression between two batch runs, bench JSONs."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest
from typer.testing import CliRunner

from lcv_replay.cli import app
from lcv_replay.fleet.compare import Tolerances, compare_rows
from lcv_replay.fleet.table import FleetRow

BASE = FleetRow(name="log", log="/x/log.mcap", status="ok", false_positives=0, true_positives=10, false_negatives=2,
                recall=10 / 12, ate_rmse_m=2.0, wall_time_s=10.0, accepted=10)


def _cli(args):
    result = CliRunner().invoke(app, [str(a) for a in args])
    return result.exit_code, result.output


@pytest.mark.parametrize("change,verdict,reason", [
    (dict(), "same", None),
    (dict(false_positives=1, accepted=11), "regressed", "wrong acceptances 0 → 1"),
    (dict(recall=9 / 12, true_positives=9, false_negatives=3), "regressed", "recall 0.833 → 0.750"),
    (dict(recall=11 / 12, true_positives=11, false_negatives=1), "improved", "recall 0.833 → 0.917"),
    (dict(ate_rmse_m=2.09), "changed", "within tolerance"),  # +4.5 % < 5 %
    (dict(ate_rmse_m=2.11), "regressed", "ATE 2.000 → 2.110 m"),
    (dict(ate_rmse_m=1.8), "improved", "ATE 2.000 → 1.800 m"),
    (dict(wall_time_s=30.0), "same", None),  # time is reported, not gated by default
    (dict(status="failed", error="boom"), "regressed", "failed in B: boom"),
])
def test_rules(change, verdict, reason):
    result = compare_rows(BASE, replace(BASE, **change), Tolerances())
    assert result.verdict == verdict, result
    if reason:
        assert any(reason in r for r in result.reasons), result.reasons


def test_tolerances_can_absorb_a_change_or_gate_time():
    assert compare_rows(BASE, replace(BASE, recall=0.8), Tolerances(recall_tol=0.05)).verdict == "changed"
    assert compare_rows(BASE, replace(BASE, ate_rmse_m=2.3), Tolerances(ate_tol=0.2)).verdict == "changed"
    assert compare_rows(BASE, replace(BASE, wall_time_s=16.0), Tolerances(time_tol=0.5)).verdict == "regressed"


def test_compare_flags_a_real_regression_between_two_batches(ray_cluster, fleet_logs, tmp_path):
    logs = fleet_logs.logs[:2]
    code, out = _cli(["batch", *logs, "--out", tmp_path / "base", "--config", fleet_logs.config, "-q"])
    assert code == 0, out
    # The injected regression: a change that accepts random constraints (the paper's ir-only baseline).
    code, out = _cli(["batch", *logs, "--out", tmp_path / "change", "--config", fleet_logs.config, "-m", "ir-only", "-q"])
    assert code == 0, out
    code, out = _cli(["compare", tmp_path / "base", tmp_path / "change", "--out", tmp_path])
    assert code == 1, out
    assert "2 regressed" in out and "wrong acceptances 0 →" in out and "regression: 2 log(s)" in out
    md = (tmp_path / "compare.md").read_text()
    assert "| route0 | regressed |" in md and "| route1 | regressed |" in md
    html = (tmp_path / "compare.html").read_text()
    assert '<tr class="bad">' in html and html.count("<img") == 1
    # The same run against itself: nothing changed, exit 0.
    code, out = _cli(["compare", tmp_path / "base", tmp_path / "base", "--out", tmp_path, "--force"])  # compare.md exists
    assert code == 0 and "0 regressed" in out and "2 the same" in out, out


def test_compare_two_bench_jsons(fleet_logs, tmp_path):
    log = fleet_logs.logs[0]
    for name, method in (("a", "dcs"), ("b", "ir-only")):
        code, out = _cli(["bench", "verify", log, "-m", method, "--config", fleet_logs.config, "--json", tmp_path / f"{name}.json"])
        assert code == 0, out
    rows = json.loads((tmp_path / "a.json").read_text())
    assert rows[0]["method"] == "dcs"
    code, out = _cli(["compare", tmp_path / "a.json", tmp_path / "b.json", "--out", tmp_path])
    assert code == 1 and "route0" in out and "regressed" in out, out
