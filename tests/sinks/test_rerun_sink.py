"""The Rerun sink in isolation: scripted records in, the .rrd read back with RrdReader.

The records are built by hand here (a verifier's steps, a retrieval query) so that every entity and
timeline can be checked against known values; tests/replay checks the same sink fed by the real
pipeline.
"""

from __future__ import annotations


import pytest

from lcv_replay.config import RerunConfig
from lcv_replay.sinks import blueprint as bp
from lcv_replay.sinks.config import RerunOutputs
from lcv_replay.sinks.layout import ConstraintState
from lcv_replay.sinks.rerun_sink import RerunSink, web_viewer_url
from tests.replay.helpers import by_frame, column, last_row, last_verdicts, read_rrd, series
from tests.sinks.scripted import N, T0, script, start

@pytest.fixture(scope="module")
def scripted(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("sink")
    out = tmp / "out.rrd"
    script(RerunSink(RerunConfig(image_every=10), RerunOutputs(save=out)), tmp)
    return out, read_rrd(out)


def test_every_listed_entity_is_written(scripted):
    _, tables = scripted
    for path in (bp.CAMERA_LEFT, bp.RETRIEVAL_CODE, bp.RETRIEVAL_DISTANCES, bp.RETRIEVAL_MATCHES, bp.RETRIEVAL_LINES,
                 bp.CONSTRAINTS_ACCEPTED, bp.CONSTRAINTS_WRONG, bp.CONSTRAINTS_REJECTED, bp.CONSTRAINTS_PENDING,
                 bp.TRUTH_WRONG, bp.LEGEND, f"{bp.POSTMORTEM}/meta", bp.HYPOTHESES_TRAJECTORIES, bp.HYPOTHESES_RANKS,
                 bp.HYPOTHESES_CONSISTENCY, bp.HYPOTHESES_TREE, bp.HYPOTHESES_SEQUENCES, bp.TRAJ_ODOMETRY,
                 bp.TRAJ_GROUND_TRUTH, bp.TRAJ_BEST, bp.TRAJ_CURRENT, bp.EVENTS, bp.REPORT,
                 bp.metric_path("precision"), bp.metric_path("recall"), bp.metric_path("ate_rmse_m"),
                 bp.metric_path("constraints"), bp.metric_path("hypotheses"), bp.STAGE_TIMES, bp.FRAME_TIME, bp.REPORT_TIMING):
        assert path in tables, f"{path} missing; have {sorted(tables)}"


def test_timelines_are_exact_and_window_only_on_steps(scripted):
    _, tables = scripted
    current = tables[bp.TRAJ_CURRENT]
    assert [f for f in current.column("frame").to_pylist() if f is not None] == list(range(N))  # + one static style row
    stamps = [t for t in current.column("log_time").cast("int64").to_pylist() if t is not None]
    assert stamps == [T0 + i * 100_000_000 for i in range(N)]  # exact nanoseconds
    ranks = tables[bp.HYPOTHESES_RANKS]
    assert ranks.column("window").to_pylist() == [0, 1]
    assert "window" not in tables[bp.TRAJ_CURRENT].column_names
    images = tables[bp.CAMERA_LEFT]
    assert images.column("frame").to_pylist() == [0, 10, 20]  # image_every = 10


def test_ranks_constraints_consistency_and_events(scripted):
    _, tables = scripted
    ranks = tables[bp.HYPOTHESES_RANKS]
    assert last_row(ranks, "hypothesis_id") == [5, 3, 0]
    assert last_verdicts(tables) == {0: ConstraintState.ACCEPTED, 1: ConstraintState.REJECTED_FALSE, 2: ConstraintState.ACCEPTED}
    assert last_row(tables[bp.CONSTRAINTS_REJECTED], "state") == ["rejected, truly false"]
    # First step: constraint 1 (labelled false) was accepted: drawn as a wrong loop closure, on
    # the estimate and between its true places.
    assert by_frame(tables[bp.CONSTRAINTS_WRONG], "constraint_id") == {19: [1], 29: []}
    strips = by_frame(tables[bp.TRUTH_WRONG], "LineStrips2D:strips")
    assert strips[19] == [[[15.0, 0.0], [8.0, 0.0]]] and strips[29] == []  # the ground truth (y = 0.5) anchored at the first odometry pose (0, 0)
    # Consistency: the top hypotheses (rows) × the constraints, as an image with its ids.
    assert last_row(tables[bp.HYPOTHESES_CONSISTENCY], "rows_hypothesis_id") == [5, 3, 0]
    assert sorted(last_row(tables[bp.HYPOTHESES_CONSISTENCY], "columns_constraint_id")) == [0, 1, 2]
    texts = [t[0] for t in tables[bp.EVENTS].column(column(tables[bp.EVENTS], "TextLog:text")).to_pylist()]
    levels = [t[0] for t in tables[bp.EVENTS].column(column(tables[bp.EVENTS], "TextLog:level")).to_pylist()]
    assert "frame 19: FIRST wrong acceptance: constraint 1 (15↔8) accepted, but it is false" in texts
    assert "frame 29: 1 no longer accepted: 1 (15↔8)" in texts
    assert "frame 29: rank 1 H3 (score 2) → H5 (score 3)" in texts
    assert levels.count("WINDOW") == 1 and levels.count("FINAL") == 1 and levels.count("WRONG") == 1
    # the verifier's notes (ilv+: what an end-of-log second opinion accepted) are events too
    assert levels.count("NOTE") == 1
    assert "frame 29: end of the log: 1 refused loop accepted across odometry slips (under heavy-tailed odometry): 2 (25↔3)" in texts
    window = next(t for t, level in zip(texts, levels) if level == "WINDOW")
    assert window.startswith("frame 19: window 0 ends, 2 accepted (+2), 1 false, 0 missed, P 0.500 R 1.000")
    legend = last_row(tables[bp.LEGEND], "TextDocument:text")[0]
    assert "**green**: 2 accepted true" in legend and "**red (thickest)**: 0 accepted but false" in legend
    code = last_row(tables[bp.RETRIEVAL_CODE], "Image:buffer")
    assert code[0] == [255 if k % 3 == 0 else 0 for k in range(20)]  # a 1 x 20 image, MSB first
    assert series(tables[bp.metric_path("constraints")])[-1] == (29, 3.0)
    assert series(tables[bp.metric_path("precision")]) == [(19, 0.5), (29, 1.0)]


def test_the_blueprint_opens_on_the_answer(scripted):
    """Time panel expanded and following (a finished file opens at its end), P/R on a fixed 0..1."""
    from rerun.chunk import RrdReader

    out, _ = scripted
    (blueprint,) = RrdReader(out).blueprints()
    cells = {}
    for chunk in RrdReader(out).stream(store=blueprint):
        batch = chunk.to_record_batch()
        for name in batch.schema.names:
            cells.setdefault((chunk.entity_path, name), []).extend(batch.column(name).to_pylist())
    from rerun.blueprint.components import PanelState, PlayState

    time_panel = {name.rsplit(":", 1)[-1]: values[-1] for (entity, name), values in cells.items() if entity == "/time_panel"}
    assert time_panel["play_state"] == [PlayState.Following.value]
    assert time_panel["state"] == [PanelState.Expanded.value]
    assert time_panel["timeline"] == ["frame"]
    ranges = [values[-1] for (entity, name), values in cells.items() if name == "ScalarAxis:range"]
    assert ranges == [[[-0.02, 1.05]]]  # precision / recall only, on a fixed 0..1


def test_report_and_blueprint_are_stored(scripted):
    from rerun.chunk import RrdReader

    out, tables = scripted
    report = tables[bp.REPORT].column(column(tables[bp.REPORT], "TextDocument:text")).to_pylist()[-1][0]
    assert "| `accepted` | 2 |" in report and "verification.window_frames" in report
    assert len(RrdReader(out).blueprints()) == 1


def test_the_run_record_is_stored_and_read_back(scripted):
    """The recording holds the same run record as a recorder fed the same calls (report from a
    recording = report at the end of the replay)."""
    from lcv_replay.report.rrd import read_run_record
    from lcv_replay.sinks.run_record import RunRecorder

    out, _ = scripted
    live = RunRecorder()
    script(live, out.parent)
    back = read_run_record(out)
    assert back == live.record
    assert [loop.state for loop in back.loops] == ["accepted", "rejected", "accepted"]
    assert back.loops[1].first_accepted_frame == 19 and back.loops[1].dropped_frame == 29
    assert back.first_wrong_acceptance().constraint_id == 1


def test_an_error_leaves_no_recording(tmp_path):
    out = tmp_path / "broken.rrd"
    script(RerunSink(RerunConfig(), RerunOutputs(save=out)), tmp_path, finish=False)
    assert not out.exists()
    assert list(tmp_path.glob(".broken.rrd.*")) == []


def test_outputs_are_checked_before_any_work(tmp_path):
    from lcv_replay.errors import OutputError

    with pytest.raises(OutputError, match="output folder does not exist"):
        RerunSink(RerunConfig(), RerunOutputs(save=tmp_path / "missing" / "x.rrd"))
    with pytest.raises(OutputError, match="no output"):
        RerunSink(RerunConfig(), RerunOutputs())
    assert web_viewer_url(9090, "rerun+http://127.0.0.1:9876/proxy") == (
        "http://127.0.0.1:9090/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A9876%2Fproxy"
    )


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _accepts(host: str, port: int) -> bool:
    import socket

    with socket.socket() as s:
        s.settimeout(0.5)
        return s.connect_ex((host, port)) == 0


def test_serve_binds_to_loopback_only_and_tees_with_the_file(tmp_path):
    import socket

    grpc, web = _free_port(), _free_port()
    out = tmp_path / "served.rrd"
    sink = RerunSink(RerunConfig(), RerunOutputs(save=out, serve=True, grpc_port=grpc, web_port=web, memory_limit="256MB"))
    sink.on_start(start(tmp_path))
    try:
        assert _accepts("127.0.0.1", grpc) and _accepts("127.0.0.1", web)
        assert sink.served_url == web_viewer_url(web, f"rerun+http://127.0.0.1:{grpc}/proxy")
        try:
            outside = [a for a in socket.gethostbyname_ex(socket.gethostname())[2] if not a.startswith("127.")]
        except OSError:
            outside = []
        for address in outside:  # not reachable from another interface
            assert not _accepts(address, grpc) and not _accepts(address, web)
    finally:
        sink.close()  # without on_finish: an aborted run; the server must go away all the same
    assert not _accepts("127.0.0.1", grpc) and not _accepts("127.0.0.1", web)
    assert not out.exists()


def test_a_constraint_flagged_ambiguous_gets_its_own_entity(tmp_path):
    import dataclasses

    class FlagLast(RerunSink):
        def on_step(self, update):
            if update.final:
                update = dataclasses.replace(update, step=dataclasses.replace(update.step, ambiguous_constraint_ids=(1,)))
            super().on_step(update)

    out = tmp_path / "ambiguous.rrd"
    script(FlagLast(RerunConfig(image_every=0), RerunOutputs(save=out)), tmp_path)
    tables = read_rrd(out)
    assert by_frame(tables[bp.CONSTRAINTS_AMBIGUOUS], "constraint_id") == {19: [], 29: [1]}
    assert by_frame(tables[bp.CONSTRAINTS_REJECTED], "constraint_id")[29] == []
    assert "1 ambiguous (flagged)" in last_row(tables[bp.LEGEND], "TextDocument:text")[0]
