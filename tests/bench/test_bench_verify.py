"""bench verify / bench suite: rows and JSON (keys, nulls), suite TOML machinery, CLI errors."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from lcv_replay.bench.suite import build_case_log, case_log_name, resolve_data_dir, run_suite, summarise
from lcv_replay.bench.suites import BUILTIN_SUITES, SuiteCase, get_suite, load_suite_file
from lcv_replay.bench.verify import load_inputs, run_verification
from lcv_replay.cli import app
from lcv_replay.errors import ConfigError, LogFormatError, RecorderError
from lcv_replay.verification.config import BaselineConfig, VerificationConfig
from tests.shared_data import SHARED_DATA, shared_path

REQUIRED_KEYS = {
    "log", "method", "frames", "log_duration_s", "wall_time_s", "candidates", "accepted", "true_positives",
    "false_positives", "false_negatives", "precision", "recall", "f1", "ate_rmse_m",
}
FAST = VerificationConfig(baselines=BaselineConfig(solve_every="end"))


@pytest.fixture(scope="module")
def kitti06(tmp_path_factory) -> Path:
    from recorders.g2o import G2oOptions, record_g2o

    out = tmp_path_factory.mktemp("bench") / "kitti06.mcap"
    record_g2o(shared_path("robustslam_kitti", "06", "kitti_06_alpha_0.50.g2o"), out, G2oOptions())
    return out


@pytest.fixture(scope="module")
def no_candidates(tmp_path_factory) -> Path:
    from recorders.g2o import G2oOptions, record_g2o

    out = tmp_path_factory.mktemp("bench") / "odom_only.mcap"
    record_g2o(shared_path("robustslam_kitti", "06", "kitti_06_odom.g2o"), out, G2oOptions())
    return out


@pytest.fixture(scope="module")
def no_truth(tmp_path_factory) -> Path:
    from recorders.g2o import G2oOptions, record_g2o

    out = tmp_path_factory.mktemp("bench") / "no_truth.mcap"
    graph = shared_path("robustslam_kitti", "06", "kitti_06_alpha_0.50.g2o")
    record_g2o(graph, out, G2oOptions(auto_siblings=False))  # neither labels nor ground truth
    return out


def _toml(tmp_path: Path, text: str, name: str = "mini.toml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


# --------------------------------------------------------------------------- bench verify
def test_run_verification_row_has_the_keys_and_nulls_where_undefined(kitti06):
    row = run_verification(kitti06, "none", FAST).as_dict()
    assert REQUIRED_KEYS <= set(row)
    assert row["frames"] == 1101 and row["candidates"] == 126
    assert row["log_duration_s"] == pytest.approx(110.0)
    assert row["accepted"] == 0
    assert row["precision"] is None  # nothing accepted: undefined
    assert row["f1"] == 0.0  # but 45 true loops missed
    assert row["recall"] == 0.0 and row["false_negatives"] == 45
    assert row["ate_rmse_m"] > 3.0  # odometry only (measured 3.56 m)
    assert row["gate_chi2"] is None  # no chi-square gate in the odometry-only method
    assert row["ambiguous"] == 0 and row["ambiguous_true"] == 0  # no ambiguous verdict either
    json.dumps(row)


def test_a_log_without_truth_gives_nulls_and_the_oracle_refuses_it(no_truth):
    from lcv_replay.bench.verify import verify_inputs
    from lcv_replay.errors import VerificationError

    inputs = load_inputs(no_truth)
    row = verify_inputs(inputs, "dcs", FAST).row.as_dict()
    assert row["truth_source"] == "none" and row["accepted"] > 0
    for key in ("true_positives", "false_positives", "false_negatives", "precision", "recall", "f1", "ate_rmse_m"):
        assert row[key] is None, key
    with pytest.raises(VerificationError, match="needs the log's true loops"):
        verify_inputs(inputs, "oracle", FAST)


def test_cli_bench_verify_writes_json_rows(kitti06, tmp_path):
    out = tmp_path / "rows.json"
    result = CliRunner().invoke(app, ["bench", "verify", str(kitti06), "-m", "none", "-m", "oracle", "--json", str(out)])
    assert result.exit_code == 0, result.output
    assert "| kitti06.mcap | oracle | 1.000 | 1.000 |" in result.output
    rows = json.loads(out.read_text())
    assert [r["method"] for r in rows] == ["none", "oracle"]
    for r in rows:
        assert REQUIRED_KEYS <= set(r)
    oracle = rows[1]
    assert (oracle["true_positives"], oracle["false_positives"], oracle["false_negatives"]) == (45, 0, 0)
    assert oracle["ate_rmse_m"] < rows[0]["ate_rmse_m"]


def test_cli_bench_verify_errors_are_one_line_with_exit_2(kitti06, no_candidates, tmp_path):
    runner = CliRunner()
    result = runner.invoke(app, ["bench", "verify", str(no_candidates), "-m", "none"])
    assert result.exit_code == 2
    assert "has no loop candidates" in result.output and "Traceback" not in result.output
    result = runner.invoke(app, ["bench", "verify", str(kitti06), "-m", "no-such-method"])
    assert result.exit_code == 2 and "unknown verification method 'no-such-method'" in result.output
    with pytest.raises(LogFormatError):
        load_inputs(no_candidates)
    assert load_inputs(no_candidates, require_candidates=False).candidates == ()


# --------------------------------------------------------------------------- suites
def test_builtin_suites_cover_the_standard_cases():
    standard = BUILTIN_SUITES["standard"]
    names = {c.name for c in standard.cases}
    assert len(standard.cases) == 25 + 6
    assert {"kitti00-a0.00", "kitti07-a1.00", "manhattan-group-1000", "manhattan-local-100"} <= names
    assert {c.name for c in BUILTIN_SUITES["quick"].cases} == {"kitti06-a0.50", "kitti07-a0.00"}


def test_suite_toml_expands_and_includes(tmp_path):
    _toml(tmp_path, 'include = ["quick"]\nmethods = ["dcs"]\n', "base.toml")
    path = _toml(
        tmp_path,
        """
name = "mine"
include = ["base.toml"]
[[robustslam_kitti]]
sequences = ["02"]
alphas = ["0.00", "1.00"]
loop_measurements = "same-place"
[[vertigo]]
outliers = [10]
modes = ["group"]
[[case]]
name = "custom"
graph = "/abs/graph.g2o"
outliers = 5
""",
    )
    suite = load_suite_file(path)
    assert suite.name == "mine" and suite.methods == ("dcs",)
    assert [c.name for c in suite.cases] == [
        "kitti06-a0.50", "kitti07-a0.00", "kitti02-a0.00-same-place", "kitti02-a1.00-same-place",
        "manhattan-group-10", "custom",
    ]
    assert suite.cases[2].loop_measurements == "same-place"
    assert suite.cases[-1].resolve(Path("/data"), suite.cases[-1].graph) == Path("/abs/graph.g2o")


@pytest.mark.parametrize(
    "text, message",
    [
        ("[[case]]\nname = 'a'\ngraf = 'x.g2o'\n", "unknown suite key 'case.graf'.*did you mean 'graph'"),
        ("[[robustslam_kitti]]\nalphas = [0.5]\n", "must be a str"),
        ("name = 'empty'\n", "the suite has no cases"),
        ("include = ['nope']\n", "unknown suite 'nope'"),
        ("include = ['self.toml']\n", "cycle"),
        ("[[case]]\nname = 'a'\ngraph = 'x'\n[[case]]\nname = 'a'\ngraph = 'y'\n", "'a' is used twice"),
        ("[[robustslam_kitti]]\nloop_measurements = 'exact'\n", "not allowed"),
        ("this is = not toml", "not valid TOML"),
        ("[[world]]\nlayouts = ['ring']\ngroup_size = 0\n", "'world.group_size' = 0 must be >= 1"),
    ],
)
def test_suite_toml_errors_name_the_problem(tmp_path, text, message):
    with pytest.raises(ConfigError, match=message):
        load_suite_file(_toml(tmp_path, text, "self.toml"))


def test_unknown_suite_name_lists_the_builtins():
    with pytest.raises(ConfigError, match="standard, vertigo, generated, extended, regressions, quick"):
        get_suite("standrd")


def test_data_dir_resolution(tmp_path, monkeypatch):
    monkeypatch.delenv("LCV_SHARED_DATA", raising=False)
    assert resolve_data_dir(tmp_path) == tmp_path.resolve()
    monkeypatch.setenv("LCV_SHARED_DATA", str(tmp_path))
    assert resolve_data_dir() == tmp_path.resolve()
    with pytest.raises(RecorderError, match="shared data folder not found.*--data DIR"):
        resolve_data_dir(tmp_path / "absent")


def test_suite_runs_builds_once_and_reuses_the_logs(tmp_path):
    shared_path("robustslam_kitti", "06")
    case = SuiteCase(
        "k06", "robustslam_kitti/06/kitti_06_alpha_0.50.g2o",
        ground_truth="robustslam_kitti/06/kitti_06_GT.g2o",
        true_loops="robustslam_kitti/06/kitti_06_alpha_0.50_GT_LC.txt",
    )
    work = tmp_path / "work"
    first = build_case_log(case, SHARED_DATA, work)
    again = build_case_log(case, SHARED_DATA, work)
    assert not first.reused and again.reused and first.path == again.path
    assert case_log_name(case, SHARED_DATA) != case_log_name(SuiteCase(**{**case.__dict__, "seed": 1}), SHARED_DATA)
    first.path.write_bytes(b"not an mcap")  # a damaged cache entry is rebuilt
    assert not build_case_log(case, SHARED_DATA, work).reused

    from lcv_replay.bench.suites import Suite

    events = []
    report = run_suite(Suite("t", (case,)), data_dir=SHARED_DATA, workdir=work, config=FAST,
                       methods=["none", "oracle"], progress=events.append)
    assert [r.method for r in report.rows] == ["none", "oracle"]
    assert events[-1].done == events[-1].total == 2
    oracle = next(s for s in summarise(report.rows, report.methods) if s.method == "oracle")
    assert (oracle.mean_precision, oracle.mean_recall, oracle.max_ate_over_oracle) == (1.0, 1.0, 1.0)
    assert (oracle.pooled_precision, oracle.pooled_recall) == (1.0, 1.0)
    none = next(s for s in summarise(report.rows, report.methods) if s.method == "none")
    assert (none.pooled_precision, none.pooled_recall, none.no_false_positive_cases) == (None, 0.0, 1)
    json.dumps(report.as_dict())


def test_cli_bench_suite_from_a_toml_file(tmp_path):
    shared_path("robustslam_kitti", "07")
    suite_file = _toml(
        tmp_path,
        '[[robustslam_kitti]]\nsequences = ["07"]\nalphas = ["0.50", "1.00"]\n',
    )
    config = _toml(tmp_path, '[verification.baselines]\nsolve_every = "end"\n', "config.toml")
    out = tmp_path / "suite.json"
    args = ["bench", "suite", "--suite", str(suite_file), "-m", "dcs", "-m", "oracle", "--config", str(config),
            "--workdir", str(tmp_path / "work"), "--data", str(SHARED_DATA), "--json", str(out)]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "| kitti07-a0.50 | oracle | 1.000 | 1.000 |" in result.output
    assert "| method | cases | P pooled | R pooled |" in result.output
    report = json.loads(out.read_text())
    assert report["complete"] and report["methods"] == ["dcs", "oracle"]
    assert report["config"]["baselines"]["solve_every"] == "end"
    rows = {(r["case"], r["method"]): r for r in report["rows"]}
    empty = rows[("kitti07-a1.00", "dcs")]  # a graph without any loop candidate
    assert empty["candidates"] == 0
    assert (empty["precision"], empty["recall"], empty["f1"]) == (None, None, None)
    assert REQUIRED_KEYS <= set(empty)


def test_cli_bench_suite_errors(tmp_path):
    runner = CliRunner()
    result = runner.invoke(app, ["bench", "suite", "--quick", "--data", str(tmp_path / "absent")])
    assert result.exit_code == 2 and "shared data folder not found" in result.output
    result = runner.invoke(app, ["bench", "suite", "--quick", "--suite", "standard"])
    assert result.exit_code == 2 and "exclusive" in result.output
