"""g2o recorder round trips: record real graphs, read them back with the one reader, compare."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from lcv_replay.cli import app
from lcv_replay.errors import OutputError
from lcv_replay.log.reader import open_log
from recorders.g2o import G2oOptions, load_g2o, load_ground_truth, record_g2o
from tests.shared_data import shared_path


def assert_poses_equal(actual: np.ndarray, expected: np.ndarray, atol: float = 1e-9) -> None:
    """``(N, 3)`` poses equal, with yaw compared on the circle."""
    assert actual.shape == expected.shape
    assert np.allclose(actual[:, :2], expected[:, :2], atol=atol)
    assert np.allclose(np.cos(actual[:, 2] - expected[:, 2]), 1.0, atol=atol)


@pytest.mark.parametrize("alpha", ["0.00", "0.25", "0.50", "0.75", "1.00"])
def test_robustslam_sequence_06_round_trip(tmp_path: Path, alpha: str) -> None:
    graph_path = shared_path("robustslam_kitti", "06", f"kitti_06_alpha_{alpha}.g2o")
    out = tmp_path / "log.mcap"
    stats = record_g2o(graph_path, out, G2oOptions())
    graph = load_g2o(graph_path)
    labels = [ln.split() for ln in graph_path.with_name(f"kitti_06_alpha_{alpha}_GT_LC.txt").read_text().splitlines() if ln.strip()]

    with open_log(out) as log:
        assert log.info.frames == graph.num_poses == stats.frames == 1101
        assert log.info.has_candidates and log.info.has_labels and log.info.has_ground_truth
        assert not log.info.has_images
        stamps = log.frame_stamps_ns
        assert np.array_equal(np.diff(stamps), np.full(1100, 100_000_000))  # 10 Hz
        assert_poses_equal(log.odometry(), graph.odometry_poses())
        assert_poses_equal(log.ground_truth(), load_ground_truth(graph_path.with_name("kitti_06_GT.g2o"), 1101))
        candidates = log.loop_candidates()
        assert len(candidates) == len(graph.loops) == stats.candidates
        assert {c.pair for c in candidates} == {(max(e.from_id, e.to_id), min(e.from_id, e.to_id)) for e in graph.loops}
        assert all(c.source == "DLoopDetector" for c in candidates)
        assert log.true_loops() == {(int(i), int(j)) for i, j in labels}
        assert log.info.metadata["recorder"] == "g2o"
        assert log.info.metadata["dataset"] == f"robustslam_kitti/06/alpha_{alpha}"
        assert np.allclose(log.info.odometry_information, graph.odometry_information_matrix())
        # Candidates and labels arrive with their query frame.
        frame = next(f for f in log.frames() if f.candidates)
        assert all(c.query_frame == frame.index for c in frame.candidates)


def test_manhattan_with_group_outliers_round_trip(tmp_path: Path) -> None:
    graph_path = shared_path("vertigo", "manhattan", "originalDataset", "g2o", "manhattanOlson3500.g2o")
    gt_path = shared_path("vertigo", "manhattan", "groundTruth", "manhattanOlson3500_nodes_groundTruth.dat")
    out = tmp_path / "manhattan.mcap"
    options = G2oOptions(ground_truth=gt_path, outliers=100, outlier_mode="group", group_size=10, seed=5)
    stats = record_g2o(graph_path, out, options)
    assert stats.candidates == 2099 + 100
    with open_log(out) as log:
        candidates = log.loop_candidates()
        injected = [c for c in candidates if c.source == "injected"]
        assert len(candidates) == 2199 and len(injected) == 100
        truth = log.true_loops()
        assert len(truth) == 1954  # the distinct pairs of the original loops
        assert not truth & {c.pair for c in injected}
        assert_poses_equal(log.ground_truth(), np.loadtxt(gt_path))
        assert log.info.recorder_config["outliers"] == 100
        assert log.info.recorder_config["outlier_mode"] == "group"


def test_existing_output_needs_force(tmp_path: Path) -> None:
    graph_path = shared_path("robustslam_kitti", "07", "kitti_07_alpha_0.50.g2o")
    out = tmp_path / "log.mcap"
    out.write_bytes(b"keep me")
    with pytest.raises(OutputError, match="already exists"):
        record_g2o(graph_path, out)
    assert out.read_bytes() == b"keep me"
    record_g2o(graph_path, out, force=True)
    with open_log(out) as log:
        assert log.info.frames == 1101


def test_cli_record_g2o_and_errors(tmp_path: Path) -> None:
    runner = CliRunner()
    graph_path = shared_path("robustslam_kitti", "07", "kitti_07_alpha_0.25.g2o")
    out = tmp_path / "cli.mcap"
    result = runner.invoke(app, ["record", "g2o", str(graph_path), "-o", str(out), "--outliers", "20", "--outlier-mode", "local", "--no-auto-siblings"])
    assert result.exit_code == 0, result.output
    # DLoopDetector's loops are not all true: without labels the log has none, injected or not.
    assert f"wrote {out}: 1101 frames, 144 candidates, " in result.output and "true loops" not in result.output
    with open_log(out) as log:
        assert log.info.metadata["dataset"] == "robustslam_kitti/07/alpha_0.25"
        assert not log.info.has_ground_truth  # --no-auto-siblings
        assert len(log.loop_candidates()) == 144 and not log.info.has_labels

    bad = tmp_path / "bad.g2o"
    bad.write_text("EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE3:QUAT 1 2 0 0 0 0 0 0 1\n")
    result = runner.invoke(app, ["record", "g2o", str(bad), "-o", str(tmp_path / "x.mcap")])
    assert result.exit_code == 2
    assert "error:" in result.output and "line 2: EDGE_SE3:QUAT is a 3-D pose graph" in result.output
    assert "Traceback" not in result.output
    assert not (tmp_path / "x.mcap").exists()
    assert list(tmp_path.glob(".x.mcap*")) == []
