"""`lcv-replay batch` on a local Ray (2 CPUs): a corrupt log among good ones, resume, Ctrl-C,
a worker killed mid-run, and the per-log result equal to `lcv-replay LOG.mcap`."""

from __future__ import annotations

import csv
import json
import os
import signal
import threading
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from lcv_replay.cli import app
from lcv_replay.fleet.batch import BatchSpec, run_batch
from lcv_replay.fleet.engine import Cluster, ClusterSpec
from lcv_replay.fleet.inputs import discover_logs
from lcv_replay.fleet.task import ATTEMPTS
from lcv_replay.config import load_config
from lcv_replay.replay import ReplayOptions, StopToken

#: summary.json keys that measure time or name this run's files (they differ between two runs).
VOLATILE = {"wall_time_s", "x_real_time", "setup_time_s", "rrd", "batch"}


def _cli(args: list[str]):
    result = CliRunner().invoke(app, [str(a) for a in args])
    return result.exit_code, result.output


def _temp_files(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if p.name.endswith(".tmp") or p.name == ATTEMPTS]


def _spec(fleet_logs, run_dir: Path, *, logs=None, seed=None) -> BatchSpec:
    options = ReplayOptions(log_path=Path("."), config=load_config(fleet_logs.config), seed=seed)
    return BatchSpec(discover_logs([str(p) for p in (logs or fleet_logs.logs)]), run_dir, options)


def test_batch_of_four_logs_one_corrupt_then_resume(ray_cluster, fleet_logs, tmp_path):
    run_dir = tmp_path / "run"
    code, out = _cli(["batch", fleet_logs.folder, "--out", run_dir, "--config", fleet_logs.config])
    assert code == 2, out  # one log failed
    assert out.count("error:") == 1 and "1 of 4 logs failed" in out and "Traceback" not in out
    run = json.loads((run_dir / "run.json").read_text())
    by_name = {e["name"]: e for e in run["logs"]}
    assert set(by_name) == {"corrupt", "route0", "route1", "route2"}
    assert run["complete"] and not run["interrupted"] and run["pending"] == []
    assert run["counts"] == {"ok": 3, "failed": 1, "skipped": 0, "pending": 0}
    bad = by_name["corrupt"]
    assert bad["status"] == "failed" and bad["summary"] is None
    assert "corrupt.mcap" in bad["error"] and "\n" not in bad["error"]
    assert not (run_dir / "logs" / "corrupt").exists()  # nothing half-written for a failed log
    for name in ("route0", "route1", "route2"):
        entry = by_name[name]
        assert entry["status"] == "ok" and entry["error"] is None and entry["attempts"] == 1
        assert entry["summary"]["frames"] == 200 and entry["summary"]["recall"] is not None
        folder = run_dir / "logs" / name
        assert (folder / "recording.rrd").stat().st_size > 0
        summary = json.loads((folder / "summary.json").read_text())
        assert summary["batch"]["config_hash"] == run["config_hash"]
        assert summary["batch"]["oracle_ate_rmse_m"] > 0
        assert summary["rrd"] == str(folder / "recording.rrd")
    assert _temp_files(run_dir) == []
    # The fleet table, worst first (the failed log on top), in every format.
    rows = list(csv.DictReader((run_dir / "fleet.csv").open()))
    assert [r["name"] for r in rows][0] == "corrupt" and len(rows) == 4
    import pyarrow.parquet as pq

    table = pq.read_table(run_dir / "fleet.parquet")
    assert table.num_rows == 4 and table.schema.field("recall").type == "double"
    md = (run_dir / "fleet.md").read_text()
    assert "| 1 | corrupt | failed |" in md and "logs/route0/recording.rrd" in md
    html = (run_dir / "fleet.html").read_text()
    assert html.count("<img") == 3 and "corrupt" in html

    # Resume: the done logs are skipped (a touched but identical log too), the failed one runs again.
    os.utime(fleet_logs.logs[0])
    code, out = _cli(["batch", fleet_logs.folder, "--out", run_dir, "--config", fleet_logs.config])
    assert code == 2, out
    run2 = json.loads((run_dir / "run.json").read_text())
    status = {e["name"]: e["status"] for e in run2["logs"]}
    assert status == {"corrupt": "failed", "route0": "skipped", "route1": "skipped", "route2": "skipped"}
    skipped = {e["name"]: e for e in run2["logs"]}["route1"]
    assert skipped["summary"] == by_name["route1"]["summary"]  # the summary it already had
    # Another seed is another config: everything runs again.
    code, out = _cli(["batch", *fleet_logs.logs, "--out", run_dir, "--config", fleet_logs.config, "--seed", "5"])
    assert code == 0, out
    run3 = json.loads((run_dir / "run.json").read_text())
    assert [e["status"] for e in run3["logs"]] == ["ok", "ok", "ok"] and run3["config_hash"] != run["config_hash"]


def test_batch_equals_the_per_log_replay(ray_cluster, fleet_logs, tmp_path):
    log = fleet_logs.logs[1]
    code, out = _cli(["batch", log, "--out", tmp_path / "run", "--config", fleet_logs.config, "--seed", "7", "--quiet"])
    assert code == 0, out
    batch = json.loads((tmp_path / "run" / "logs" / "route1" / "summary.json").read_text())
    code, out = _cli([log, "--config", fleet_logs.config, "--seed", "7", "--rate", "max", "--quiet",
                      "--save", tmp_path / "single.rrd", "--summary-json", tmp_path / "single.json"])
    assert code == 0, out
    single = json.loads((tmp_path / "single.json").read_text())
    assert batch["seed"] == single["seed"] == 7
    assert {k: v for k, v in batch.items() if k not in VOLATILE} == {k: v for k, v in single.items() if k not in VOLATILE}


def test_batch_export_and_report_equal_the_per_log_ones(ray_cluster, fleet_logs, tmp_path):
    log = fleet_logs.logs[2]
    args = ["--config", fleet_logs.config, "--seed", "7", "--quiet"]
    code, out = _cli(["batch", log, "--out", tmp_path / "run", "--export", "--report", *args])
    assert code == 0, out
    per_log = tmp_path / "run" / "logs" / "route2"
    code, out = _cli([log, *args, "--save", tmp_path / "single.rrd", "--export", tmp_path / "single", "--report",
                      tmp_path / "single.html"])
    assert code == 0, out
    for name in ("loops.csv", "trajectory.tum", "accepted.g2o", "config.toml"):
        assert (per_log / "export" / name).read_text() == (tmp_path / "single" / name).read_text(), name
    assert "Fig. X" in (per_log / "report.html").read_text(encoding="utf-8")


def test_ctrl_c_stops_scheduling_and_a_rerun_finishes(ray_cluster, fleet_logs, tmp_path):
    run_dir = tmp_path / "run"
    spec = _spec(fleet_logs, run_dir)
    stop = StopToken()

    def on_event(event):
        if event.kind == "finished":
            stop.request()  # what the first Ctrl-C does

    state = run_batch(spec, ray_cluster, stop=stop, on_event=on_event)
    run = json.loads((run_dir / "run.json").read_text())
    assert state.interrupted and run["interrupted"] and not run["complete"]
    done = {e["name"] for e in run["logs"]}
    assert len(done) == 2  # the first to finish, and the one running beside it
    assert len(run["pending"]) == 1 and run["counts"]["pending"] == 1
    for name in done:  # consistent with the folders: done logs have their summary, the rest nothing
        assert (run_dir / "logs" / name / "summary.json").is_file()
    pending = Path(run["pending"][0]).stem
    assert not (run_dir / "logs" / pending).exists()
    assert _temp_files(run_dir) == []
    state = run_batch(spec, ray_cluster)
    run = json.loads((run_dir / "run.json").read_text())
    assert run["complete"] and sorted(e["status"] for e in run["logs"]) == ["ok", "skipped", "skipped"]


def _kill_first_attempt(folder: Path, killed: list[int]) -> None:
    """Wait for the task to start in ``folder``, then SIGKILL its worker process (a real kill)."""
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            line = (folder / ATTEMPTS).read_text().splitlines()[0]
        except (FileNotFoundError, IndexError):
            time.sleep(0.01)
            continue
        pid = int(line.split()[1])
        os.kill(pid, signal.SIGKILL)
        killed.append(pid)
        return


@pytest.fixture(scope="module")
def slow_log(tmp_path_factory):
    from tests.replay.helpers import record_square_route

    log, _ = record_square_route(tmp_path_factory.mktemp("slow"), laps=3, side_poses=60, name="slow.mcap")
    return log  # 720 frames: 1-2 s of replay, time enough to be killed mid-run


@pytest.fixture(scope="module")
def long_log(tmp_path_factory):
    from tests.replay.helpers import record_square_route

    log, _ = record_square_route(tmp_path_factory.mktemp("long"), laps=20, side_poses=60, name="slow.mcap")
    return log  # 4,800 frames: longer to replay than the engine's grace for a cancelled task


@pytest.mark.parametrize("retries", [1, 0])
def test_a_killed_worker_is_retried_or_reported(ray_cluster, fleet_logs, slow_log, tmp_path, retries):
    run_dir = tmp_path / "run"
    spec = _spec(fleet_logs, run_dir, logs=[slow_log])
    killed: list[int] = []
    killer = threading.Thread(target=_kill_first_attempt, args=(run_dir / "logs" / "slow", killed), daemon=True)
    killer.start()
    with Cluster(ClusterSpec(max_retries=retries)) as cluster:  # the session's Ray, these task options
        run_batch(spec, cluster)
    killer.join(timeout=5)
    assert len(killed) == 1
    entry = json.loads((run_dir / "run.json").read_text())["logs"][0]
    if retries:
        assert entry["status"] == "ok" and entry["attempts"] == 2, entry
        assert (run_dir / "logs" / "slow" / "summary.json").is_file()
    else:
        assert entry["status"] == "failed" and "worker process died" in entry["error"], entry
        assert not (run_dir / "logs" / "slow").exists()
    assert _temp_files(run_dir) == []


def test_a_second_ctrl_c_cancels_the_running_logs_cleanly(ray_cluster, fleet_logs, long_log, tmp_path):
    """The interrupt lands while the long log replays (the grace the engine gives a cancelled task
    is shorter than its replay: with ``slow_log``, 1 to 2 s, the replay could end in the grace and
    be recorded whole, as CI on a clean clone saw)."""
    run_dir = tmp_path / "run"
    spec = _spec(fleet_logs, run_dir, logs=[long_log, fleet_logs.logs[0]])  # the larger (slow) one goes first

    def on_event(event):
        if event.kind == "started" and event.log.name == "slow":
            deadline = time.monotonic() + 60
            while not (run_dir / "logs" / "slow" / ATTEMPTS).exists() and time.monotonic() < deadline:
                time.sleep(0.01)  # until the replay runs in its worker
            raise KeyboardInterrupt  # what the second Ctrl-C raises in the driver

    state = run_batch(spec, ray_cluster, on_event=on_event)
    run = json.loads((run_dir / "run.json").read_text())
    assert state.interrupted and run["interrupted"] and run["logs"] == []
    assert sorted(Path(p).name for p in run["pending"]) == ["route0.mcap", "slow.mcap"]
    assert not (run_dir / "logs" / "slow").exists()  # cancelled: nothing half-written, not even its folder
    assert (run_dir / "fleet.md").is_file() and _temp_files(run_dir) == []
