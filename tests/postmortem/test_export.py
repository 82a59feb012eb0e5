"""``--export DIR``: evo reads the trajectories and agrees with our ATE; the g2o graph and the TOML
config come back in; loops.csv matches the summary; bad export folders get one ``error:`` line."""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from lcv_replay.cli import app
from tests.postmortem.conftest import one_error
from lcv_replay.export.formats import LOOP_COLUMNS, stamp_seconds
from lcv_replay.export.sink import EXPORT_FILES
from lcv_replay.report.rrd import read_run_record

evo = pytest.importorskip("evo", reason="evo (the test extra) is not installed")


def _evo_ape_rmse(reference: Path, estimate: Path) -> float:
    """``evo_ape tum REF EST -a``: translation APE RMSE after SE(3) Umeyama alignment, no scale."""
    from evo.core import metrics, sync
    from evo.tools import file_interface

    ref = file_interface.read_tum_trajectory_file(str(reference))
    est = file_interface.read_tum_trajectory_file(str(estimate))
    ref, est = sync.associate_trajectories(ref, est)
    est.align(ref, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    return float(ape.get_statistic(metrics.StatisticsType.rmse))


def _loops(run) -> list[dict[str, str]]:
    with open(run.export / "loops.csv", newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def test_every_file_is_written_and_named(square_run):
    assert sorted(p.name for p in square_run.export.iterdir()) == sorted(EXPORT_FILES)
    assert f"export            {square_run.export}" in square_run.output
    assert not list(square_run.export.glob(".*"))  # no temp file left behind
    assert json.loads((square_run.export / "summary.json").read_text()) == square_run.summary


def test_evo_reads_tum_and_kitti_and_agrees_with_our_ate(square_run):
    from evo.tools import file_interface

    tum = file_interface.read_tum_trajectory_file(str(square_run.export / "trajectory.tum"))
    kitti = file_interface.read_kitti_poses_file(str(square_run.export / "trajectory.kitti"))
    assert tum.num_poses == kitti.num_poses == square_run.summary["frames"]
    np.testing.assert_allclose(kitti.positions_xyz, tum.positions_xyz, atol=1e-6)
    np.testing.assert_allclose(tum.positions_xyz[:, 2], 0.0)  # planar
    record = read_run_record(square_run.rrd)
    np.testing.assert_allclose(tum.positions_xyz[:, :2], record.estimate[:, :2], atol=1e-6)
    rotations = np.asarray(kitti.poses_se3)
    yaw = np.arctan2(rotations[:, 1, 0], rotations[:, 0, 0])
    np.testing.assert_allclose(np.angle(np.exp(1j * (yaw - record.estimate[:, 2]))), 0.0, atol=1e-9)
    odometry = file_interface.read_tum_trajectory_file(str(square_run.export / "odometry.tum"))
    np.testing.assert_allclose(odometry.positions_xyz[:, :2], record.odometry[:, :2], atol=1e-6)
    rmse = _evo_ape_rmse(square_run.export / "ground_truth.tum", square_run.export / "trajectory.tum")
    assert rmse == pytest.approx(square_run.summary["ate_rmse_m"], rel=0.01)


def test_loops_csv_is_the_fate_of_every_constraint(square_run):
    rows = _loops(square_run)
    s = square_run.summary
    assert list(rows[0]) == list(LOOP_COLUMNS)
    assert [int(r["constraint_id"]) for r in rows] == list(range(s["constraints"]))
    accepted = [r for r in rows if r["state"] == "accepted"]
    assert sorted(int(r["constraint_id"]) for r in accepted) == s["accepted_constraint_ids"]
    assert sum(r["truth"] == "false" for r in accepted) == s["false_positives"]
    assert sum(r["truth"] == "true" and r["state"] != "accepted" for r in rows) == s["false_negatives"]
    assert {r["state"] for r in rows} <= {"accepted", "rejected", "pending", "ambiguous"}
    for r in rows:
        assert int(r["query_frame"]) > int(r["match_frame"])
        assert int(r["query_stamp_ns"]) == int(r["query_frame"]) * 100_000_000  # 10 Hz from 0
        if r["state"] == "accepted":
            assert r["first_accepted_frame"] != ""
        if r["dropped_frame"]:
            assert r["first_accepted_frame"] and int(r["dropped_frame"]) > int(r["first_accepted_frame"])
        assert float(r["d2"]) >= 0.0
    # d² is the loop's whitened residual under the final estimate: accepted ones are small.
    assert np.median([float(r["d2"]) for r in accepted]) < 11.34


def test_accepted_g2o_comes_back_through_record_g2o(square_run, tmp_path):
    from recorders.g2o import load_g2o

    graph = load_g2o(square_run.export / "accepted.g2o")
    record = read_run_record(square_run.rrd)
    assert graph.num_poses == record.frames
    np.testing.assert_allclose(graph.odometry_poses(), record.odometry, atol=1e-6)
    loops = graph.loop_candidates()
    assert sorted((c.query_frame, c.match_frame) for c in loops) == sorted(
        (l.query_frame, l.match_frame) for l in record.loops if l.state == "accepted")
    assert len(loops) == square_run.summary["accepted"]
    # ... and the lcv-replay recorder records it into a log that replays.
    log = tmp_path / "verified.mcap"
    result = CliRunner().invoke(app, ["record", "g2o", str(square_run.export / "accepted.g2o"), "-o", str(log)])
    assert result.exit_code == 0, result.output
    from lcv_replay.log.reader import open_log

    info = open_log(log).info
    assert info.frames == record.frames and info.candidate_count == square_run.summary["accepted"]


def test_config_toml_loads_back_with_config(square_run):
    from lcv_replay.config import load_config, to_dict

    back = load_config(square_run.export / "config.toml")
    assert to_dict(back) == square_run.summary["config"]
    assert back.verification.method == "ilv" and back.verification.seed == 7 and back.verification.window_frames == 100


def test_tum_stamps_are_exact():
    assert stamp_seconds(1_700_000_000_123_456_789) == "1700000000.123456789"
    assert stamp_seconds(5) == "0.000000005"


@pytest.mark.slow
def test_kitti00_export_agrees_with_evo_on_real_data(kitti_run):
    rmse = _evo_ape_rmse(kitti_run.export / "ground_truth.tum", kitti_run.export / "trajectory.tum")
    assert rmse == pytest.approx(kitti_run.summary["ate_rmse_m"], rel=0.01)
    rows = _loops(kitti_run)
    assert len(rows) == 337 and sum(r["state"] == "accepted" for r in rows) == kitti_run.summary["accepted"]


def test_export_into_a_file_or_an_unwritable_folder_is_refused_before_any_work(square_run, tmp_path):
    a_file = tmp_path / "taken"
    a_file.write_text("x")
    one_error([str(square_run.log), "--export", str(a_file), "--quiet", "--no-rerun"], "taken", "needs a folder")
    one_error([str(square_run.log), "--export", str(tmp_path / "no" / "such" / "dir"), "--quiet", "--no-rerun"],
               "parent does not exist")
    one_error([str(square_run.log), "--export", "/proc/lcv-replay-export", "--quiet", "--no-rerun"], "/proc/lcv-replay-export")
    if os.geteuid() != 0:  # root writes anywhere; the /proc case above covers it
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o500)
        one_error([str(square_run.log), "--export", str(locked), "--quiet", "--no-rerun"], "not writable")
    one_error(["demo", "--export", str(a_file), "--quiet"], "needs a folder")
