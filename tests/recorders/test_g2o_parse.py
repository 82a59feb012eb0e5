"""g2o recorder, pure part: parsing every real graph, labels, orientation, outlier injection, errors."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from lcv_replay.errors import RecorderError
from lcv_replay.records import Pose2D
from lcv_replay.se2 import information_matrix, relative_steps
from recorders.common import project_to_planar, read_pose_file
from recorders.g2o import (
    LOCAL_OUTLIER_SPAN,
    G2oOptions,
    inject_outliers,
    load_g2o,
    load_ground_truth,
    load_true_loops,
    prepare_g2o,
)
from tests.shared_data import SHARED_DATA, shared_path

ROBUSTSLAM_GRAPHS = sorted(SHARED_DATA.glob("robustslam_kitti/*/*.g2o"))
VERTIGO_GRAPHS = sorted(p for p in SHARED_DATA.glob("vertigo/**/*") if p.suffix in (".g2o", ".dat"))


def _independent_count(path: Path) -> tuple[int, int]:
    """(number of poses, number of non-chain edges) counted without the parser under test."""
    ids, loops, rows = set(), 0, 0
    for line in path.read_text().splitlines():
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        rows += 1
        if tokens[0] == "VERTEX_SE2":
            ids.add(int(tokens[1]))
        elif tokens[0] == "EDGE_SE2" or len(tokens) == 14:
            i, j = int(tokens[1 if tokens[0] == "EDGE_SE2" else 0]), int(tokens[2 if tokens[0] == "EDGE_SE2" else 1])
            ids.update((i, j))
            loops += abs(i - j) != 1
    return (len(ids) or rows), loops


@pytest.mark.parametrize("path", ROBUSTSLAM_GRAPHS + VERTIGO_GRAPHS, ids=lambda p: str(p.relative_to(SHARED_DATA)))
def test_every_shared_graph_loads(path: Path) -> None:
    graph = load_g2o(path)
    num_poses, num_loops = _independent_count(path)
    assert graph.num_poses == num_poses
    assert len(graph.loops) == num_loops
    odom = graph.odometry_poses()
    assert odom.shape == (num_poses, 3) and np.isfinite(odom).all()
    candidates = graph.loop_candidates()
    assert all(c.query_frame > c.match_frame >= 0 and c.query_frame < num_poses for c in candidates)
    assert all(c.T_match_query is not None and c.information is not None for c in candidates)


def test_shared_graph_list_is_complete() -> None:
    shared_path("robustslam_kitti")
    shared_path("vertigo")
    # 5 sequences x (5 alphas + odom + GT); Manhattan (2 graphs + 2 ground-truth files), Intel,
    # ring and ringCity (graph + ground truth each) and city10000.
    assert len(ROBUSTSLAM_GRAPHS) == 35
    assert len(VERTIGO_GRAPHS) == 10


@pytest.mark.parametrize("path", [p for p in ROBUSTSLAM_GRAPHS if "_alpha_" in p.name], ids=lambda p: p.name)
def test_robustslam_labels_are_candidates_and_ground_truth_matches(path: Path) -> None:
    rec = prepare_g2o(path)  # auto siblings: _GT_LC.txt labels and kitti_SS_GT.g2o
    labels_file = path.with_name(path.stem + "_GT_LC.txt")
    lines = [ln for ln in labels_file.read_text().splitlines() if ln.strip()]
    assert rec.true_loops is not None and len(rec.true_loops) == len(lines)
    assert rec.true_loops <= {c.pair for c in rec.candidates}
    assert rec.source == "DLoopDetector" and all(c.source == "DLoopDetector" for c in rec.candidates)
    assert rec.ground_truth is not None and rec.ground_truth.shape == rec.odometry.shape
    assert len(rec.candidates) == len(rec.graph.loops)


def test_robustslam_edges_are_inverted_into_match_frame() -> None:
    path = shared_path("robustslam_kitti", "00", "kitti_00_alpha_0.50.g2o")
    graph = load_g2o(path)
    # "EDGE_SE2  1590 145 -0.188678 -0.484661 0.053756 ..." is written (later, earlier): T_1590_145.
    edge = next(e for e in graph.loops if (e.from_id, e.to_id) == (1590, 145))
    assert edge.T_from_to == Pose2D(-0.188678, -0.484661, 0.053756)
    cand = edge.as_candidate("DLoopDetector")
    assert cand.pair == (1590, 145)
    assert cand.T_match_query == pytest.approx(tuple(Pose2D(-0.188678, -0.484661, 0.053756).inverse()))
    assert Pose2D(*edge.T_from_to).compose(cand.T_match_query) == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)


def test_manhattan_edges_written_forward_are_kept() -> None:
    graph = load_g2o(shared_path("vertigo", "manhattan", "originalDataset", "g2o", "manhattanOlson3500.g2o"))
    edge = graph.loops[0]
    assert edge.to_id > edge.from_id
    cand = edge.as_candidate("g2o")
    assert cand.pair == (edge.to_id, edge.from_id)
    assert cand.T_match_query == edge.T_from_to and cand.information == edge.information


def test_manhattan_ground_truth_files_agree() -> None:
    nodes = shared_path("vertigo", "manhattan", "groundTruth", "manhattanOlson3500_nodes_groundTruth.dat")
    edges = nodes.with_name("manhattanOlson3500_edges_groundTruth.dat")
    from_nodes = load_ground_truth(nodes, 3500)
    from_edges = load_ground_truth(edges, 3500)  # noise-free chain composed from the origin
    assert np.abs(from_nodes[:, :2] - from_edges[:, :2]).max() < 1e-2
    # The edges file carries a covariance of 0.0005 on the diagonal: information 2000.
    info = information_matrix(load_g2o(edges).odometry_information[0])
    assert np.allclose(info, np.diag([2000.0, 2000.0, 2000.0]))


def test_robustslam_ground_truth_matches_kitti_poses_projected() -> None:
    """Our 3-D -> planar projection (body x = camera z, y = -camera x) reproduces robustslam's GT."""
    kitti = read_pose_file(shared_path("trajectories", "KITTI_00_gt.txt"))
    planar = project_to_planar(kitti.T_world_sensor)
    chain = load_g2o(shared_path("robustslam_kitti", "00", "kitti_00_GT.g2o"))
    steps_error = np.abs(relative_steps(planar) - chain.odometry_steps)
    assert steps_error[:, :2].max() < 0.2 and steps_error[:, 2].max() < 0.01
    end_error = np.hypot(*(planar[-1, :2] - chain.trajectory()[-1, :2]))
    assert end_error < 3.0  # after 3.7 km


# ---------------------------------------------------------------------------------------------
# Outlier injection (Vertigo protocol)
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("mode", ["random", "local", "group"])
def test_inject_outliers_protocol(mode: str) -> None:
    info = (1.0, 0.0, 0.0, 2.0, 0.0, 3.0)
    existing = {(500, 10), (900, 40)}
    out = inject_outliers(1000, 400, mode=mode, group_size=10, information=info, seed=3, existing_pairs=existing)
    assert len(out) == 400
    pairs = [c.pair for c in out]
    assert len(set(pairs)) == 400 and not set(pairs) & existing
    assert all(c.query_frame - c.match_frame >= 2 for c in out)  # never an odometry edge
    assert all(0 <= c.match_frame < c.query_frame < 1000 for c in out)
    assert all(c.information == info and c.source == "injected" for c in out)
    if mode == "local":
        assert all(c.query_frame - c.match_frame <= LOCAL_OUTLIER_SPAN for c in out)
    measurements = np.array([c.T_match_query for c in out])
    if mode == "group":
        for g in range(40):
            run = out[10 * g : 10 * (g + 1)]
            assert len({c.T_match_query for c in run}) == 1  # one measurement per run: mutually consistent
            assert [c.pair for c in run] == [(run[0].query_frame + k, run[0].match_frame + k) for k in range(10)]
        measurements = measurements[::10]
    else:
        assert len({c.T_match_query for c in out}) == 400
    assert np.std(measurements[:, :2]) == pytest.approx(0.3, rel=0.25)
    assert np.std(measurements[:, 2]) == pytest.approx(math.radians(10.0), rel=0.25)


def test_inject_outliers_is_deterministic_and_group_remainder() -> None:
    a = inject_outliers(300, 25, mode="group", group_size=10, seed=7)
    assert a == inject_outliers(300, 25, mode="group", group_size=10, seed=7)
    assert a != inject_outliers(300, 25, mode="group", group_size=10, seed=8)
    assert len(a) == 25 and len({c.T_match_query for c in a}) == 3  # runs of 10, 10 and 5


@pytest.mark.parametrize("mode", ["random", "local", "group"])
def test_inject_outliers_keeps_out_of_real_revisits(mode: str) -> None:
    """A route driven twice over the same 50 m: with the ground truth and a minimum distance, no
    injected pair joins two poses at the same place (without it, many would)."""
    lap = np.stack([np.arange(50.0), np.zeros(50), np.zeros(50)], axis=1)
    truth = np.concatenate([lap, lap[::-1], lap])  # 150 poses, every place visited three times
    near = lambda out: sum(np.hypot(*(truth[c.query_frame, :2] - truth[c.match_frame, :2])) < 1.5 for c in out)
    kept = inject_outliers(len(truth), 20, mode=mode, seed=3, ground_truth=truth, min_distance_m=1.5)
    assert len(kept) == 20 and near(kept) == 0
    if mode == "random":
        assert near(inject_outliers(len(truth), 200, mode=mode, seed=3)) > 0  # the draw the rule redraws
    with pytest.raises(RecorderError, match="ground truth"):
        inject_outliers(len(truth), 5, mode=mode, min_distance_m=1.5)


def test_inject_outliers_rejects_impossible_requests() -> None:
    with pytest.raises(RecorderError, match="too small"):
        inject_outliers(5, 1, mode="group", group_size=10)
    with pytest.raises(RecorderError, match="cannot place"):
        inject_outliers(8, 40, mode="random")  # only 15 pairs (b >= a + 2 in 0..6) exist


def test_outliers_label_manhattan_originals_true() -> None:
    path = shared_path("vertigo", "manhattan", "originalDataset", "g2o", "manhattanOlson3500.g2o")
    rec = prepare_g2o(path, G2oOptions(outliers=100, outlier_mode="local", seed=1))
    originals = {c.pair for c in rec.candidates if c.source == "g2o"}
    injected = [c for c in rec.candidates if c.source == "injected"]
    # 2099 loop edges over 1954 distinct pairs (Manhattan measures some pairs more than once).
    assert len(rec.candidates) - len(injected) == 2099 and len(originals) == 1954
    assert len(injected) == 100 and not originals & {c.pair for c in injected}
    assert rec.true_loops == frozenset(originals)
    # The injected loops copy the information matrix of the graph's first loop.
    first_loop_information = load_g2o(path).loops[0].information
    assert all(c.information == first_loop_information for c in injected)
    plain = prepare_g2o(path)
    assert plain.true_loops is None  # no outliers, no labels file: unlabelled


def test_same_place_drops_measurements() -> None:
    path = shared_path("robustslam_kitti", "07", "kitti_07_alpha_0.50.g2o")
    rec = prepare_g2o(path, G2oOptions(loop_measurements="same-place"))
    assert rec.candidates and all(c.T_match_query is None and c.information is None for c in rec.candidates)


# ---------------------------------------------------------------------------------------------
# Malformed inputs
# ---------------------------------------------------------------------------------------------

GOOD_CHAIN = "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 1 2 1 0 0 1 0 0 1 0 1\nEDGE_SE2 2 3 1 0 0 1 0 0 1 0 1\n"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "empty"),
        ("# only a comment\n", "empty"),
        (GOOD_CHAIN + "EDGE_SE2 3 1 0 0\n", "line 4: malformed EDGE_SE2"),
        (GOOD_CHAIN + "EDGE_SE2 3 0 0 0 nan 1 0 0 1 0 1\n", "line 4: NaN or inf"),
        (GOOD_CHAIN + "FOO 1 2\n", "line 4: unknown record type 'FOO'"),
        ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n", "3-D pose graph"),
        ("EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 2 3 1 0 0 1 0 0 1 0 1\nEDGE_SE2 3 0 1 0 0 1 0 0 1 0 1\n", "no odometry edge between vertices 1 and 2"),
        ("EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 5 6 1 0 0 1 0 0 1 0 1\n", "not contiguous: 2 is missing"),
        ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 0 1 0 0\n", "vertex 0 defined twice"),
        ("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n", "vertex 1 is used by an edge"),
        ("EDGE_SE2 0 0 1 0 0 1 0 0 1 0 1\n", "to itself"),
        ("1 2 3 4\n1 2 3\n", "untagged rows"),
        ("0 1 1 0 0 1 0 0 0 1 0 0 0 1\n1 2 1 0 0 0 0 0 0 0 0 0 0 0\n", "line 2: singular covariance"),
    ],
)
def test_malformed_graphs_name_file_and_problem(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.g2o"
    path.write_text(text)
    with pytest.raises(RecorderError) as info:
        load_g2o(path)
    assert message in str(info.value) and str(path) in str(info.value)


def test_missing_graph_file(tmp_path: Path) -> None:
    with pytest.raises(RecorderError, match="pose graph file not found"):
        load_g2o(tmp_path / "nope.g2o")


def test_toro_format_and_reverse_chain_edge(tmp_path: Path) -> None:
    path = tmp_path / "toro.graph"
    # EDGE2 order: Ixx Ixy Iyy Itt Ixt Iyt; the second chain edge is written backwards (2 -> 1).
    path.write_text("VERTEX2 0 0 0 0\nVERTEX2 1 1 0 0\nVERTEX2 2 1 1 1.5707963\n"
                    "EDGE2 0 1 1 0 0 10 1 20 30 2 3\nEDGE2 2 1 -1 0 -1.5707963 10 0 10 10 0 0\n")
    graph = load_g2o(path)
    assert graph.loops == ()
    assert graph.odometry_information[0] == pytest.approx((10, 1, 2, 20, 3, 30))
    assert graph.odometry_poses()[2] == pytest.approx([1.0, 1.0, 1.5707963], abs=1e-6)


def test_ids_starting_at_one_are_shifted(tmp_path: Path) -> None:
    path = tmp_path / "one.g2o"
    path.write_text("EDGE_SE2 1 2 1 0 0 1 0 0 1 0 1\nEDGE_SE2 2 3 1 0 0 1 0 0 1 0 1\nEDGE_SE2 3 1 0 0 0 1 0 0 1 0 1\n")
    graph = load_g2o(path)
    assert graph.num_poses == 3 and graph.id_offset == 1
    assert graph.loop_candidates()[0].pair == (2, 0)


def test_ground_truth_and_label_mismatches(tmp_path: Path) -> None:
    gt = tmp_path / "gt.txt"
    gt.write_text("0 0 0\n1 0 0\n")
    with pytest.raises(RecorderError, match="ground truth has 2 poses but the graph has 4"):
        load_ground_truth(gt, 4)
    labels = tmp_path / "labels.txt"
    labels.write_text("3 0\n7 1\n")
    with pytest.raises(RecorderError, match=r"line 2: pair \(7, 1\)"):
        load_true_loops(labels, 4)
    labels.write_text("3 x\n")
    with pytest.raises(RecorderError, match="line 1: not a number"):
        load_true_loops(labels, 4)
    labels.write_text("0 3\n2 0\n")
    assert load_true_loops(labels, 4) == {(3, 0), (2, 0)}


# -- warnings, not silence (issue 12) -------------------------------------------------------------------
_WARNED_GRAPH = """\
VERTEX_SE2 0 0 0 0
VERTEX_SE2 1 1 0 0
VERTEX_SE2 2 2 0 0
VERTEX_SE2 3 3 0 0
VERTEX_SE2 4 4 0 0
EDGE_SE2 0 1 1 0 0 0 0 0 0 0 0
EDGE_SE2 1 2 1 0 0 100 0 0 100 0 100
EDGE_SE2 2 3 1 0 0 100 0 0 100 0 100
EDGE_SE2 3 4 1 0 0 100 0 0 -100 0 100
EDGE_SE2 4 0 -4 0 0 100 0 0 100 0 100
EDGE_SE2 4 0 -4 0 0 100 0 0 100 0 100
EDGE_SE2 0 4 4 0 0 100 0 0 100 0 100
"""


def test_singular_odometry_information_and_duplicate_edges_are_warned_and_counted(tmp_path: Path, caplog) -> None:
    graph_path = tmp_path / "warned.g2o"
    graph_path.write_text(_WARNED_GRAPH)
    with caplog.at_level("WARNING"):
        rec = prepare_g2o(graph_path)
    assert rec.graph.warnings() == {"singular_odometry_information": 2, "duplicate_edges": 2}
    text = caplog.text
    assert "2 odometry edges have a singular or non-positive-definite information matrix (first: line 6" in text
    assert "2 duplicate edges join the same two vertices as an earlier edge (first: line 11 repeats line 10)" in text
    # The log's odometry information is the first usable one (edge 1 -> 2), not edge 0's zeros.
    np.testing.assert_array_equal(rec.graph.odometry_information_matrix(), np.diag([100.0, 100.0, 100.0]))
    assert len(rec.candidates) == 3  # duplicates are kept, each as its own candidate


def test_a_clean_graph_has_no_warnings(caplog) -> None:
    with caplog.at_level("WARNING"):
        rec = prepare_g2o(shared_path("robustslam_kitti/06/kitti_06_alpha_0.50.g2o"), G2oOptions())
    assert rec.graph.warnings() == {}
    assert "recorders.g2o" not in caplog.text


def test_warnings_reach_the_record_summary_and_info(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from lcv_replay.cli import app
    from lcv_replay.log.inspect import info_to_json
    from lcv_replay.log.reader import open_log

    graph_path = tmp_path / "warned.g2o"
    graph_path.write_text(_WARNED_GRAPH)
    out = tmp_path / "warned.mcap"
    result = CliRunner().invoke(app, ["record", "g2o", str(graph_path), "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert "warnings: 2 duplicate edges" in result.stdout and "2 odometry edges with a singular" in result.stdout
    with open_log(out) as reader:
        assert reader.info.recorder_warnings == {"duplicate_edges": 2, "singular_odometry_information": 2}
        assert info_to_json(reader.info)["recorder_warnings"] == {"duplicate_edges": 2, "singular_odometry_information": 2}
    info = CliRunner().invoke(app, ["info", str(out)])
    assert "Warnings:          2 duplicate edges" in info.stdout
