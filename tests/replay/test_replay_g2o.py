"""End to end on real components: a g2o log (real recorder) replayed with the default verifier.

The .rrd is read back with ``rerun.chunk.RrdReader`` and checked against the summary: the entities
exist, rank 1 has the largest bar, the constraints coloured accepted at the last frame are the
summary's accepted set, and the metrics series end at the summary's figures. A second identical
run gives an equal .rrd (``rerun rrd compare``) and an equal summary.
"""

from __future__ import annotations

import math
import subprocess
from pathlib import Path

import pytest

from lcv_replay.config import load_config
from lcv_replay.replay import DEFAULT_METHOD, ReplayOptions, StopToken, replay
from lcv_replay.sinks import blueprint as bp
from lcv_replay.sinks.base import SUMMARY_KEYS, BaseSink
from lcv_replay.sinks.layout import ConstraintState
from lcv_replay.sinks.config import RerunOutputs
from lcv_replay.sinks.rerun_sink import RerunSink
from lcv_replay.sinks.summary import SummarySink, read_summary_json
from tests.replay.helpers import (
    FAST_CONFIG_TOML,
    column,
    last_row,
    last_verdicts,
    read_rrd,
    record_square_route,
    series,
    write_config,
)

SEED = 7


def _run(log: Path, out_dir: Path, name: str, config_path: Path, **option_overrides):
    config = load_config(config_path)
    rrd = out_dir / f"{name}.rrd"
    js = out_dir / f"{name}.json"
    sinks = [RerunSink(config.rerun, RerunOutputs(save=rrd)), SummarySink(json_path=js)]
    options = ReplayOptions(log_path=log, config=config, seed=SEED, **option_overrides)
    summary = replay(options, sinks, handle_sigint=False)
    return summary, rrd, js


@pytest.fixture(scope="module")
def square(tmp_path_factory):
    folder = tmp_path_factory.mktemp("square")
    log, route = record_square_route(folder)
    config = write_config(folder / "fast.toml", FAST_CONFIG_TOML)
    summary, rrd, js = _run(log, folder, "run1", config)
    return {"folder": folder, "log": log, "route": route, "config": config, "summary": summary, "rrd": rrd,
            "json": js, "tables": read_rrd(rrd)}


def test_summary_json_has_the_stable_keys(square):
    data = read_summary_json(square["json"])
    assert list(data)[: len(SUMMARY_KEYS)] == list(SUMMARY_KEYS)
    s = square["summary"]
    assert data["frames"] == square["route"].frames == s.frames
    assert data["method"] == DEFAULT_METHOD
    assert data["constraints"] == len(square["route"].true_pairs) + len(square["route"].false_pairs)
    assert data["true_positives"] + data["false_negatives"] == len(square["route"].true_pairs)
    assert data["accepted"] == data["true_positives"] + data["false_positives"] == len(data["accepted_constraint_ids"])
    assert data["log_duration_s"] == pytest.approx((square["route"].frames - 1) / 10.0)
    assert data["ate_rmse_m"] is not None and data["hypotheses"] >= 1
    assert data["interrupted"] is False and data["truth_source"] == "labels"
    assert data["config"]["verification"]["window_frames"] == 100
    # the log's candidates carry relative poses: ilv+ verifies them by cluster consensus
    assert data["config"]["verification"]["ilv_plus"]["loops"] == "measured"


def test_recording_has_the_entities_of_a_g2o_replay(square):
    tables = square["tables"]
    for path in (*bp.CONSTRAINT_ENTITIES[:4], bp.LEGEND, bp.HYPOTHESES_TRAJECTORIES, bp.HYPOTHESES_RANKS, bp.HYPOTHESES_CONSISTENCY,
                 bp.HYPOTHESES_TREE, bp.HYPOTHESES_SEQUENCES, bp.TRAJ_ODOMETRY, bp.TRAJ_GROUND_TRUTH, bp.TRAJ_BEST,
                 bp.TRAJ_CURRENT, bp.EVENTS, bp.REPORT, bp.metric_path("precision"), bp.metric_path("recall"),
                 bp.metric_path("ate_rmse_m"), bp.metric_path("constraints"), bp.metric_path("hypotheses"),
                 bp.metric_path("accepted"), bp.metric_path("gate_chi2")):
        assert path in tables, f"{path} missing"
    assert bp.CAMERA_LEFT not in tables  # a g2o log has no images
    steps = tables[bp.HYPOTHESES_RANKS]
    assert sorted(set(steps.column("window").to_pylist())) == list(range(5))  # 480 frames / W = 100
    tree = tables[bp.HYPOTHESES_TREE]
    assert any(v for v in tree.column(column(tree, "GraphEdges:edges")).to_pylist() if v)


def _bars(ranks) -> list[tuple[list[float], list[int]]]:
    """(bar heights, scores) of every logged ranking."""
    values = ranks.column(column(ranks, "BarChart:values")).to_pylist()
    scores = ranks.column(column(ranks, "score")).to_pylist()
    out = []
    for bars, score in zip(values, scores):
        if bars:
            buffer = bars[0]["buffer"]
            heights = next(v for v in buffer.values() if v is not None) if isinstance(buffer, dict) else buffer
            out.append((list(heights), list(score)))
    return out


def test_rank1_is_the_maximum_of_the_bar_chart(square):
    rankings = _bars(square["tables"][bp.HYPOTHESES_RANKS])
    assert len(rankings) >= 5
    for heights, scores in rankings:
        assert heights[0] == max(heights)  # rank 1 has the largest ranking key...
        assert heights == sorted(heights, reverse=True)  # ... and the bars are in rank order
        assert len(scores) == len(heights)


def test_with_the_paper_method_the_bars_are_the_scores(square, tmp_path):
    summary, rrd, _ = _run(square["log"], tmp_path, "ilv", square["config"], method="ilv")
    rankings = _bars(read_rrd(rrd)[bp.HYPOTHESES_RANKS])
    assert rankings and summary.method == "ilv"
    for heights, scores in rankings:
        assert heights == [float(s) for s in scores] and scores[0] == max(scores)


def test_accepted_in_summary_are_those_coloured_accepted_at_the_last_frame(square):
    verdicts = last_verdicts(square["tables"])
    assert len(verdicts) == square["summary"].constraints  # every judged constraint is drawn once
    coloured = {i for i, c in verdicts.items() if ConstraintState(c).accepted}
    assert coloured == set(square["summary"].accepted_constraint_ids)
    assert len(coloured) == square["summary"].accepted
    wrong = {i for i, c in verdicts.items() if c == ConstraintState.ACCEPTED_FALSE}
    assert len(wrong) == square["summary"].false_positives
    assert set(last_row(square["tables"][bp.CONSTRAINTS_WRONG], "constraint_id")) == wrong


def test_metrics_series_end_at_the_summary(square):
    tables, s = square["tables"], square["summary"]
    last_frame = s.frames - 1
    for name, expected in (("precision", s.precision), ("recall", s.recall), ("ate_rmse_m", s.ate_rmse_m),
                           ("accepted", s.accepted), ("hypotheses", s.hypotheses)):
        points = series(tables[bp.metric_path(name)])
        assert points[-1][0] == last_frame
        assert points[-1][1] == pytest.approx(expected), name
    assert series(tables[bp.metric_path("constraints")])[-1] == (last_frame, float(s.constraints))


def test_same_log_config_and_seed_give_an_equal_recording_and_summary(square):
    summary, rrd, _ = _run(square["log"], square["folder"], "run2", square["config"])
    # Wall-clock measurements live in bp.WALL_CLOCK_ENTITIES only; everything else must be equal.
    drop = [arg for entity in bp.WALL_CLOCK_ENTITIES for arg in ("--drop-entity", entity)]
    filtered = []
    for path in (square["rrd"], rrd):
        out = path.with_suffix(".filtered.rrd")
        subprocess.run(["rerun", "rrd", "filter", *drop, str(path), "-o", str(out)], check=True, capture_output=True, timeout=120)
        filtered.append(str(out))
    done = subprocess.run(["rerun", "rrd", "compare", *filtered], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    # ... and the comparison is not vacuous: the unfiltered recordings differ in their timings.
    assert subprocess.run(["rerun", "rrd", "compare", "--unordered", str(square["rrd"]), str(rrd)],
                          capture_output=True, timeout=120).returncode != 0
    first = square["summary"].to_json_dict()
    second = summary.to_json_dict()
    for volatile in ("wall_time_s", "setup_time_s", "x_real_time", "rrd"):
        first.pop(volatile), second.pop(volatile)
    assert first == second


def test_start_offset_and_duration_select_frames_and_drop_earlier_candidates(square, tmp_path):
    summary, rrd, _ = _run(square["log"], tmp_path, "window", square["config"], start_offset_s=20.0, duration_s=21.0)
    assert summary.frames == 210
    assert summary.log_duration_s == pytest.approx(20.9)
    route = square["route"]
    inside = [p for p in route.true_pairs | route.false_pairs if 200 <= p[1] and p[0] < 410]
    assert summary.constraints == len(inside)
    current = read_rrd(rrd)[bp.TRAJ_CURRENT]
    assert current.column("frame").to_pylist()[0] == 0  # replay-local frame numbers
    assert current.column("log_time").cast("int64").to_pylist()[0] == 200 * 100_000_000


def test_stop_token_summarises_the_last_completed_window(square, tmp_path):
    config = load_config(square["config"])
    stop = StopToken()

    class StopAt(BaseSink):
        def on_frame(self, update):
            if update.frame.index == 250:
                stop.request()

    rrd = tmp_path / "stopped.rrd"
    summary = replay(ReplayOptions(log_path=square["log"], config=config, seed=SEED),
                     [RerunSink(config.rerun, RerunOutputs(save=rrd)), StopAt()], stop=stop, handle_sigint=False)
    assert summary.interrupted and summary.frames == 251 and summary.rrd == str(rrd)
    tables = read_rrd(rrd)
    assert max(f for f in tables[bp.CONSTRAINTS_ACCEPTED].column("frame").to_pylist() if f is not None) == 199  # the last completed window
    assert sum(ConstraintState(c).accepted for c in last_verdicts(tables).values()) == summary.accepted
    assert math.isfinite(summary.wall_time_s)


def test_the_oracle_replays_with_the_truth_that_judges_the_run(square, tmp_path):
    """``--method oracle`` in a replay is given the log's labels (the NeedsTruth capability), as in
    ``bench verify``: it accepts exactly the labelled true loops."""
    summary, _, _ = _run(square["log"], tmp_path, "oracle", square["config"], method="oracle")
    route = square["route"]
    assert summary.method == "oracle" and summary.truth_source == "labels"
    assert (summary.accepted, summary.true_positives, summary.false_positives, summary.false_negatives) == (
        len(route.true_pairs), len(route.true_pairs), 0, 0)
    assert summary.precision == summary.recall == 1.0
