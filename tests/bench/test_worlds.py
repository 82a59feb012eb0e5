"""Generated pose-graph worlds (lcv_replay.bench.worlds) and their place in the suites."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lcv_replay.bench.suites import BUILTIN_SUITES, SuiteCase, load_suite_file, with_seeds, world_cases
from lcv_replay.bench.worlds import MISDECLARED_RANGE, WorldSpec, generate_world, write_world
from lcv_replay.errors import ConfigError
from lcv_replay.se2 import between as se2_between, logmap as se2_logmap


@pytest.mark.parametrize("layout", ["grid", "ring"])
def test_a_world_is_a_pure_function_of_its_spec(layout):
    spec = WorldSpec(layout=layout, poses=600, seed=3)
    a, b = generate_world(spec), generate_world(spec)
    assert np.array_equal(a.truth, b.truth) and np.array_equal(a.odometry, b.odometry) and np.array_equal(a.loops, b.loops)
    other = generate_world(WorldSpec(layout=layout, poses=600, seed=4))
    assert not np.array_equal(a.truth, other.truth)


@pytest.mark.parametrize("layout", ["grid", "ring"])
def test_worlds_drive_one_metre_steps_and_revisit_places(layout):
    world = generate_world(WorldSpec(layout=layout, poses=1500, seed=1))
    steps = np.linalg.norm(np.diff(world.truth[:, :2], axis=0), axis=1)
    # one metre along the road; a step across a corner cuts it (chord of at least 1/sqrt(2))
    assert np.all(steps <= 1.0 + 1e-9) and np.all(steps > 0.7) and np.median(steps) == pytest.approx(1.0)
    q, m = world.loops[:, 0], world.loops[:, 1]
    assert len(world.loops) > 0.15 * 1500
    assert np.all(q - m >= 50)
    assert np.all(np.linalg.norm(world.truth[q, :2] - world.truth[m, :2], axis=1) < 1.5)
    # the measurements are the true relative poses plus loop noise (sigmas 0.1 m, 0.1 m, 0.02 rad)
    error = se2_logmap(se2_between(se2_between(world.truth[m], world.truth[q]), world.loop_measurements))
    assert np.all(np.abs(error[:, :2]) < 0.6) and np.all(np.abs(error[:, 2]) < 0.12)
    # the odometry drifts away from the truth
    assert np.linalg.norm(world.odometry[-1, :2] - world.truth[-1, :2]) > 1.0


def test_noise_models():
    gaussian = generate_world(WorldSpec(poses=3000, noise="gaussian", seed=2))
    heavy = generate_world(WorldSpec(poses=3000, noise="heavy", seed=2))

    def odometry_errors(world):
        truth = se2_between(world.truth[:-1], world.truth[1:])
        odometry = se2_between(world.odometry[:-1], world.odometry[1:])
        return se2_logmap(se2_between(truth, odometry))[:, 0] / world.spec.odometry_sigmas[0]

    g, h = odometry_errors(gaussian), odometry_errors(heavy)
    assert 0.9 < np.std(g) < 1.1 and np.max(np.abs(g)) < 6.0  # as declared
    assert np.max(np.abs(h)) > 10.0  # Student-t (3 dof): a tail no Gaussian has
    assert gaussian.declared_factors == heavy.declared_factors == (1.0, 1.0)
    np.testing.assert_allclose(np.linalg.inv(gaussian.odometry_information), np.diag(np.square(gaussian.spec.odometry_sigmas)))
    for seed in range(5):
        world = generate_world(WorldSpec(poses=300, noise="misdeclared", seed=seed))
        for factor in world.declared_factors:
            assert MISDECLARED_RANGE[0] <= factor <= MISDECLARED_RANGE[1]
        declared = np.linalg.inv(world.odometry_information)
        np.testing.assert_allclose(declared, world.declared_factors[0] * np.diag(np.square(world.spec.odometry_sigmas)))
        world = generate_world(WorldSpec(poses=300, noise="anisotropic", seed=seed))
        per_axis = np.diag(np.linalg.inv(world.loop_information)) / np.square(world.spec.loop_sigmas)
        assert np.all((per_axis >= MISDECLARED_RANGE[0]) & (per_axis <= MISDECLARED_RANGE[1]))
        assert np.ptp(np.log(per_axis)) > 0  # each axis off by its own factor


def test_a_written_world_reads_back_through_the_g2o_recorder(tmp_path):
    from recorders.g2o import load_g2o, prepare_g2o, G2oOptions

    world = generate_world(WorldSpec(layout="ring", poses=400, seed=5))
    graph_path, truth_path = write_world(world, tmp_path)
    graph = load_g2o(graph_path)
    assert graph.num_poses == 400 and len(graph.loops) == len(world.loops)
    np.testing.assert_allclose(graph.odometry_poses(), world.odometry, atol=1e-6)
    np.testing.assert_allclose(load_g2o(truth_path).trajectory(), world.truth, atol=1e-6)
    np.testing.assert_allclose(graph.odometry_information_matrix(), world.odometry_information, rtol=1e-6)
    # the suite's recorder labels the revisits true and injects outliers the Vertigo way
    rec = prepare_g2o(graph_path, G2oOptions(ground_truth=truth_path, outliers=30, outlier_mode="group", seed=1))
    assert len(rec.candidates) == len(world.loops) + 30
    assert rec.true_loops == frozenset((int(q), int(m)) for q, m in world.loops)


def test_world_specs_are_checked():
    with pytest.raises(ConfigError, match="layout"):
        WorldSpec(layout="maze")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="noise"):
        WorldSpec(noise="pink")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="poses"):
        WorldSpec(poses=10)


def test_suites_of_generated_worlds_and_fresh_seeds(tmp_path):
    generated = BUILTIN_SUITES["generated"]
    assert len(generated.cases) >= 60 and all(c.world is not None and c.seeded for c in generated.cases)
    assert {c.world.layout for c in generated.cases} == {"grid", "ring"}
    assert {c.world.noise for c in generated.cases} == {"gaussian", "heavy", "misdeclared"}
    assert {c.outlier_mode for c in generated.cases} == {"random", "local", "group"}
    assert {c.world.poses for c in generated.cases} >= {1000, 2000, 10000}
    names = {c.name for c in BUILTIN_SUITES["vertigo"].cases}
    assert {"ring-group-100", "ringCity-group-500", "intel-local-200", "city10000-random-1000"} <= names
    assert len(BUILTIN_SUITES["extended"].cases) == 31 + len(BUILTIN_SUITES["vertigo"].cases) + len(generated.cases)

    redrawn = with_seeds(BUILTIN_SUITES["quick"], [7, 8])  # robustslam_kitti cases have no seed
    assert redrawn.cases == BUILTIN_SUITES["quick"].cases
    case = world_cases(["grid"], [1000], ["heavy"], ["group"], [100], [1])[0]
    assert case.name == "grid-1k-heavy-group-100-s1"
    again = with_seeds(type(generated)("x", (case,)), [7, 8]).cases
    assert [c.name for c in again] == ["grid-1k-heavy-group-100-s7", "grid-1k-heavy-group-100-s8"]
    assert [c.world.seed for c in again] == [7, 8] and [c.seed for c in again] == [7, 8]
    twenty = world_cases(["ring"], [2000], ["heavy"], ["group"], [400], [9804], group_size=20)[0]
    assert twenty.name == "ring-2k-heavy-group20-400-s9804" and twenty.with_seed(1).name == "ring-2k-heavy-group20-400-s1"

    path = tmp_path / "w.toml"
    path.write_text('[[world]]\nlayouts = ["ring"]\nposes = [1500]\nnoise = ["misdeclared"]\nmodes = ["local", "group"]\noutliers = [50]\nseeds = [4]\n')
    suite = load_suite_file(path)
    assert [c.name for c in suite.cases] == ["ring-1500-misdeclared-local-50-s4", "ring-1500-misdeclared-group-50-s4"]
    path.write_text('[[world]]\nlayouts = ["maze"]\n')
    with pytest.raises(ConfigError, match="layout") as refused:
        load_suite_file(path)
    assert refused.value.path == path  # the error line names the file
    for bad in ('noise = ["bogus"]', 'modes = ["bogus"]', "poses = [5]"):
        path.write_text(f"[[world]]\n{bad}\n")
        with pytest.raises(ConfigError) as refused:
            load_suite_file(path)
        assert str(refused.value).startswith(f"{path}: ")
    including = tmp_path / "top.toml"
    including.write_text('include = ["w.toml"]\n')
    with pytest.raises(ConfigError) as refused:
        load_suite_file(including)
    assert refused.value.path == path  # the file the bad table is in, not the one including it
    with pytest.raises(ConfigError, match="exactly one"):
        SuiteCase("both", graph="x.g2o", world=WorldSpec())


def test_the_regressions_suite_names_each_world_once_with_its_group_size():
    """Rows are keyed by case name (the oracle's ATE too), so worlds that differ in group size only
    must not share one."""
    suite = BUILTIN_SUITES["regressions"]
    names = [c.name for c in suite.cases]
    assert len(names) == len(set(names)) and set(suite.methods) == {"ilv+", "gnc", "dcs", "oracle"}
    by_name = {c.name: c for c in suite.cases}
    assert by_name["ring-2k-heavy-group20-400-s9804"].group_size == 20
    assert by_name["ring-2k-heavy-group5-400-s9755"].group_size == 5
    assert by_name["ring-2k-heavy-group-400-s11008"].group_size == 10
    assert by_name["ring-5k-heavy-group-1000-s9007"].world.poses == 5000
    assert by_name["ring-5k-heavy-local-1000-s13338"].outlier_mode == "local"
    assert by_name["ring-2k-heavy-local-400-s13923"].outlier_mode == "local"
    moved = {"ring-2k-heavy-group-400-s9207", "ring-2k-heavy-group20-400-s9804", "ring-2k-heavy-group-400-s9302", "ring-2k-heavy-group5-400-s9755",
             "ring-2k-heavy-group20-400-s9805", "ring-2k-heavy-group-400-s10612", "ring-2k-heavy-group-400-s9900", "ring-2k-heavy-group-400-s13587",
             "ring-2k-heavy-group-400-s9300", "ring-2k-heavy-group-400-s9420",
             "ring-5k-heavy-group-1000-s9007"}
    assert moved <= set(names)  # the worlds that left tests/verification/test_consensus.py for it


def test_a_world_case_builds_once_into_the_work_folder(tmp_path):
    from lcv_replay.bench.suite import build_case_log
    from lcv_replay.bench.verify import load_inputs

    case = world_cases(["grid"], [500], ["gaussian"], ["random"], [20], [3])[0]
    first = build_case_log(case, Path("/nonexistent"), tmp_path)
    again = build_case_log(case, Path("/nonexistent"), tmp_path)
    assert not first.reused and again.reused
    inputs = load_inputs(first.path)
    assert inputs.frames == 500 and inputs.ground_truth is not None and inputs.true_pairs
    assert len(inputs.candidates) == len(inputs.true_pairs) + 20


def test_bench_scale_prints_both_tables_and_writes_json(tmp_path):
    """``lcv-replay bench scale`` end to end on two small worlds: the totals side by side, the time
    per window against the history, and the JSON with every window."""
    import json

    from typer.testing import CliRunner

    from lcv_replay.cli import app

    out = tmp_path / "scale.json"
    args = ["bench", "scale", "--poses", "600,1200", "--outliers-per-1000", "50", "-m", "ilv+", "-r", "dcs", "--workdir", str(tmp_path / "work"), "--json", str(out)]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "ilv+" in result.output and "dcs" in result.output
    report = json.loads(out.read_text())
    runs = {(r["case"], r["method"]) for r in report["runs"]}
    assert len(runs) == 4
    for run in report["runs"]:
        if run["method"] == "ilv+":
            assert run["windows"] and all(w["time_s"] >= 0 for w in run["windows"])
            assert [w["history_constraints"] for w in run["windows"]] == sorted(w["history_constraints"] for w in run["windows"])
            # the back end alone, timed on the same windows
            assert all(w["backend_time_s"] > 0 for w in run["windows"])
    assert "ilv+ / back end" in result.output and "end of the log" in result.output
    again = CliRunner().invoke(app, args)
    assert again.exit_code == 2 and "--force" in again.output  # the one overwrite rule


def test_the_back_end_reference_absorbs_each_windows_change_of_the_accepted_loops(tmp_path, monkeypatch):
    """``backend_window_times`` replays a run's accepted set window by window through iSAM2: one
    time per step, loops leaving the set are removed (a loop added twice or removed while absent
    would raise), and what it holds at the end is what the run accepted."""
    import dataclasses

    from lcv_replay.bench.scale import backend_window_times
    from lcv_replay.bench.suite import build_case_log
    from lcv_replay.bench.verify import load_inputs, verify_inputs
    from lcv_replay.verification.base import default_informations
    from lcv_replay.verification.config import VerificationConfig
    from lcv_replay.verification.pose_graph import IncrementalGraph

    case = world_cases(["grid"], [600], ["gaussian"], ["group"], [30], [3])[0]
    inputs = load_inputs(build_case_log(case, Path("/nonexistent"), tmp_path).path)
    run = verify_inputs(inputs, "ilv+")
    steps = list(run.steps)
    if steps[-1] is not run.result.last_step:
        steps.append(run.result.last_step)
    accepted = [s.accepted_constraint_ids for s in steps]
    assert len(accepted[-1]) > 20
    # a loop that leaves the set in one window and comes back in the next
    leaving = accepted[-2][0]
    steps[-2] = dataclasses.replace(steps[-2], accepted_constraint_ids=tuple(c for c in accepted[-2] if c != leaving))
    odometry_information, loop_information = default_informations(VerificationConfig(), inputs.odometry_information)

    held: list[frozenset[int]] = []
    original_update = IncrementalGraph.update

    def update(self, add=(), remove=(), **kwargs):
        original_update(self, add=add, remove=remove, **kwargs)
        held.append(self.loop_ids)

    monkeypatch.setattr(IncrementalGraph, "update", update)
    times = backend_window_times(inputs.odometry, odometry_information, loop_information, run.result.constraints, steps)
    assert len(times) == len(steps) and all(t > 0 for t in times)
    assert held[-2] == frozenset(steps[-2].accepted_constraint_ids) and leaving not in held[-2]
    assert held[-1] == frozenset(accepted[-1])


def test_bench_scale_times_a_given_log_in_rounds_that_alternate_the_order(tmp_path, monkeypatch):
    """``bench scale --log L --repeat 3``: every method runs once a round, the order reversed every
    other round; the time reported is the median of the rounds, each ratio is taken within a round,
    and the table and the JSON give the medians with their ranges. A missing log is one error line."""
    import json

    from typer.testing import CliRunner

    import lcv_replay.bench.verify as bench_verify
    from lcv_replay.bench.suite import build_case_log
    from lcv_replay.cli import app

    log = build_case_log(world_cases(["grid"], [500], ["gaussian"], ["group"], [20], [4])[0], Path("/nonexistent"), tmp_path).path
    order: list[str] = []
    original = bench_verify.verify_inputs

    def verify_inputs(inputs, method, *args, **kwargs):
        order.append(method)
        return original(inputs, method, *args, **kwargs)

    monkeypatch.setattr(bench_verify, "verify_inputs", verify_inputs)
    out = tmp_path / "scale.json"
    result = CliRunner().invoke(app, ["bench", "scale", "--log", str(log), "--repeat", "3", "-m", "ilv+", "-r", "dcs", "--json", str(out)])
    assert result.exit_code == 0, result.output
    assert order == ["ilv+", "dcs", "dcs", "ilv+", "ilv+", "dcs"]  # no generated world: only the log
    report = json.loads(out.read_text())
    assert report["repeat"] == 3
    runs = {r["method"]: r for r in report["runs"]}
    assert set(runs) == {"ilv+", "dcs"} and all(r["case"] == log.stem for r in runs.values())
    mine, other = runs["ilv+"]["round_times_s"], runs["dcs"]["round_times_s"]
    assert len(mine) == len(other) == 3
    assert runs["ilv+"]["wall_time_s"] == sorted(mine)[1]
    assert report["ratios"][log.stem]["dcs"] == pytest.approx([a / b for a, b in zip(mine, other)])
    assert runs["ilv+"]["windows"] and runs["ilv+"]["precision"] == 1.0
    ratios = report["ratios"][log.stem]["dcs"]
    assert f"{sorted(ratios)[1]:.2f} ({min(ratios):.2f}–{max(ratios):.2f})" in result.output
    assert "3 rounds per log" in result.output

    missing = CliRunner().invoke(app, ["bench", "scale", "--log", str(tmp_path / "absent.mcap")])
    assert missing.exit_code == 2 and "Traceback" not in missing.output
    assert f"error: {tmp_path / 'absent.mcap'}: no such log" in missing.output


@pytest.mark.parametrize("command", [["bench", "scale", "--poses", "500", "-r", "dcs"], ["bench", "suite", "--suite", "standard", "-m", "none"]])
def test_a_work_folder_that_cannot_be_created_is_one_error_line(tmp_path, command):
    """``--workdir`` under a file: exit 2 with one ``error:`` line naming the folder, no traceback."""
    from typer.testing import CliRunner

    from lcv_replay.cli import app

    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    data = tmp_path / "data"  # the shared data is not needed: the folder is refused first
    data.mkdir()
    extra = ["--data", str(data)] if command[1] == "suite" else []
    result = CliRunner().invoke(app, [*command, *extra, "--workdir", str(blocker / "work")])
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output
    assert f"error: {blocker / 'work'}: cannot create the work folder" in result.output


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs /proc (Linux): a folder that passes os.access but holds no file")
def test_a_json_report_that_cannot_be_written_is_refused_before_the_suite_runs(tmp_path):
    """``--json`` in a folder where no file can be created though ``os.access`` says it can (/proc,
    as root): exit 2 with one ``error:`` line naming the file, before any case runs (the report
    was written at the end, and its failure was a traceback after the whole suite)."""
    from typer.testing import CliRunner

    from lcv_replay.cli import app

    data, work = tmp_path / "data", tmp_path / "work"  # the shared data is not needed: the report is refused first
    data.mkdir()
    work.mkdir()
    result = CliRunner().invoke(app, ["bench", "suite", "--suite", "standard", "-m", "none", "--data", str(data), "--workdir", str(work), "--json", "/proc/lcv-report.json"])
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output
    assert "error: /proc/lcv-report.json: cannot write the file" in result.output
    assert not list(work.iterdir())  # no case log was built
