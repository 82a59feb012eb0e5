"""The Rerun sink in isolation: scripted records in, the .rrd read back with RrdReader.

The records are built by hand here (a verifier's steps, a retrieval query) so that every entity and
timeline can be checked against known values; tests/replay checks the same sink fed by the real
pipeline.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lcv_replay.config import RerunConfig
from lcv_replay.evaluation.metrics import detection_metrics
from lcv_replay.evaluation.truth import LoopTruth, TruthSource
from lcv_replay.records import Frame, ImageRef, LoopCandidate, Pose2D
from lcv_replay.sinks import blueprint as bp
from lcv_replay.sinks.base import FrameUpdate, RetrievalUpdate, RunStart, RunSummary, StepMetrics, StepUpdate
from lcv_replay.sinks.layout import ConstraintState
from lcv_replay.sinks.config import RerunOutputs
from lcv_replay.sinks.rerun_sink import RerunSink, web_viewer_url
from lcv_replay.verification.base import Constraint, HypothesisSummary, VerifierStep
from tests.replay.helpers import column, last_row, read_rrd, series

N = 30
T0 = 1_700_000_000_123_456_789  # an exact ns stamp (not representable as float64 seconds)


def _frame(i: int) -> Frame:
    image = np.full((24, 32), i * 8 % 255, dtype=np.uint8)
    return Frame(
        index=i,
        stamp_ns=T0 + i * 100_000_000,
        odom=Pose2D(float(i), 0.0, 0.0),
        ground_truth=Pose2D(float(i), 0.5, 0.0),
        left=ImageRef(T0, "mono8", lambda image=image: image),
    )


def _step(frame_index, window, accepted, constraints, scores) -> VerifierStep:
    ranking = tuple(
        HypothesisSummary(id=hid, parent_id=None if hid == 0 else 0, constraint_ids=cids, score=score, rank=r, window=window,
                          rank_key=float(score))
        for r, (hid, cids, score) in enumerate(scores, start=1)
    )
    n = frame_index + 1
    trajectories = {h.id: np.column_stack([np.arange(n, dtype=float), np.full(n, 0.1 * h.id), np.zeros(n)]) for h in ranking}
    consistency = np.zeros((len(ranking), len(constraints)), dtype=bool)
    consistency[0, list(accepted)] = True
    return VerifierStep(
        frame_index=frame_index,
        window_index=window,
        new_constraint_ids=(),
        new_hypotheses=tuple(h for h in ranking if h.window == window and h.id != 0),
        generation_edges=tuple((0, h.id, h.constraint_ids[-1]) for h in ranking if h.id != 0),
        ranking=ranking,
        accepted_constraint_ids=tuple(accepted),
        trajectories=trajectories,
        consistency=consistency,
        timings_s={"optimise": 0.25, "score": 0.01},
    )


def _metrics(step, truth, constraints) -> StepMetrics:
    det = detection_metrics(step.accepted_constraint_ids, LoopTruth(TruthSource.LABELS, tuple(truth[: len(constraints)])))
    return StepMetrics(step.frame_index, len(constraints), det, ate_rmse_m=0.5, hypotheses=len(step.ranking))


def _start(tmp_path: Path) -> RunStart:
    return RunStart(
        log_path=tmp_path / "fake.mcap", method="ilv", constraint_source="both", rate=None, seed=0,
        config={"verification": {"window_frames": 20}}, frames=N, first_log_frame=0, start_ns=T0,
        log_duration_s=2.9, has_images=True, has_ground_truth=True, truth_source="labels",
        ground_truth=np.column_stack([np.arange(N, dtype=float), np.full(N, 0.5), np.zeros(N)]), code_bits=20,
    )


def _script(sink: RerunSink, tmp_path: Path, *, finish: bool = True) -> None:
    c = [Constraint(0, LoopCandidate(15, 2, 0.9, source="retrieval"), 15),
         Constraint(1, LoopCandidate(15, 8, 0.4, source="retrieval"), 15),
         Constraint(2, LoopCandidate(25, 3, 0.8, source="log"), 25)]
    truth = [True, False, True]
    sink.on_start(_start(tmp_path))
    for i in range(N):
        new = tuple(x for x in c if x.arrival_frame == i)
        frame = _frame(i)
        sink.on_frame(FrameUpdate(frame, new, tuple(truth[x.id] for x in new), sum(x.arrival_frame <= i for x in c), i * 0.01, i * 0.1))
        if i == 15:
            sink.on_retrieval(RetrievalUpdate(frame, tuple(x.candidate for x in new), code=np.arange(20) % 3 == 0,
                                              prefilter_size=7, top_frames=np.array([2, 8]), l2_distances=np.array([0.3, 0.7]),
                                              hamming=np.array([1, 3])))
        if i == 19:
            step = _step(19, 0, [0, 1], c[:2], [(3, (1,), 2), (0, (), 1)])
            sink.on_step(StepUpdate(step, _metrics(step, truth, c[:2]), c[:2], truth[:2]))
        if i == 29:
            step = _step(29, 1, [0, 2], c, [(5, (0, 2), 3), (3, (1,), 1), (0, (), 1)])
            sink.on_step(StepUpdate(step, _metrics(step, truth, c), c, truth, final=True))
    if finish:
        sink.on_finish(RunSummary(frames=N, wall_time_s=0.3, log_duration_s=2.9, method="ilv", constraints=3, accepted=2,
                                  true_positives=2, false_positives=0, false_negatives=0, precision=1.0, recall=1.0,
                                  ate_rmse_m=0.5, hypotheses=3, accepted_constraint_ids=(0, 2)))
    sink.close()


@pytest.fixture(scope="module")
def scripted(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("sink")
    out = tmp / "out.rrd"
    _script(RerunSink(RerunConfig(image_every=10), RerunOutputs(save=out)), tmp)
    return out, read_rrd(out)


def test_every_listed_entity_is_written(scripted):
    _, tables = scripted
    for path in (bp.CAMERA_LEFT, bp.RETRIEVAL_CODE, bp.RETRIEVAL_DISTANCES, bp.RETRIEVAL_MATCHES, bp.RETRIEVAL_LINES,
                 bp.CONSTRAINTS_SEGMENTS, bp.CONSTRAINTS_PENDING, bp.HYPOTHESES_TRAJECTORIES, bp.HYPOTHESES_RANKS,
                 bp.HYPOTHESES_CONSISTENCY, bp.HYPOTHESES_TREE, bp.HYPOTHESES_SEQUENCES, bp.TRAJ_ODOMETRY,
                 bp.TRAJ_GROUND_TRUTH, bp.TRAJ_BEST, bp.TRAJ_CURRENT, bp.EVENTS, bp.REPORT,
                 bp.metric_path("precision"), bp.metric_path("recall"), bp.metric_path("ate_rmse_m"),
                 bp.metric_path("constraints"), bp.metric_path("hypotheses"), bp.STAGE_TIMES, bp.FRAME_TIME, bp.REPORT_TIMING):
        assert path in tables, f"{path} missing; have {sorted(tables)}"


def test_timelines_are_exact_and_window_only_on_steps(scripted):
    _, tables = scripted
    current = tables[bp.TRAJ_CURRENT]
    assert current.column("frame").to_pylist() == list(range(N))
    stamps = current.column("log_time").cast("int64").to_pylist()
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
    segs = tables[bp.CONSTRAINTS_SEGMENTS]
    ids = last_row(segs, "constraint_id")
    by_id = dict(zip(ids, last_row(segs, "LineStrips2D:class_ids")))
    assert by_id == {0: ConstraintState.ACCEPTED, 1: ConstraintState.REJECTED_FALSE, 2: ConstraintState.ACCEPTED}
    assert dict(zip(ids, last_row(segs, "state"))) == {0: "accepted", 1: "rejected, truly false", 2: "accepted"}
    assert ids[0] == 1  # faint (correctly rejected) segments are drawn first, under the accepted ones
    # First step: constraint 1 (labelled false) was accepted: drawn as a wrong loop closure.
    first = segs.column(column(segs, "LineStrips2D:class_ids")).to_pylist()[0]
    assert first == [ConstraintState.ACCEPTED, ConstraintState.ACCEPTED_FALSE]
    tensor = last_row(tables[bp.HYPOTHESES_CONSISTENCY], "Tensor:data")
    assert tensor[0]["shape"] == [3, 3]
    texts = tables[bp.EVENTS].column(column(tables[bp.EVENTS], "TextLog:text")).to_pylist()
    flat = [t[0] for t in texts]
    assert "constraint 1 (15↔8) accepted at frame 19 — TRULY FALSE" in flat
    assert "constraint 1 (15↔8) no longer accepted at frame 29" in flat
    assert "constraint 2 (25↔3) accepted at frame 29" in flat
    assert "rank-1 hypothesis changed from #3 (score 2) to #5 (score 3) at frame 29" in flat
    code = last_row(tables[bp.RETRIEVAL_CODE], "Image:buffer")
    assert code[0] == [255 if k % 3 == 0 else 0 for k in range(20)]  # a 1 x 20 image, MSB first
    assert series(tables[bp.metric_path("constraints")])[-1] == (29, 3.0)
    assert series(tables[bp.metric_path("precision")]) == [(19, 0.5), (29, 1.0)]


def test_report_and_blueprint_are_stored(scripted):
    from rerun.chunk import RrdReader

    out, tables = scripted
    report = tables[bp.REPORT].column(column(tables[bp.REPORT], "TextDocument:text")).to_pylist()[-1][0]
    assert "| `accepted` | 2 |" in report and "verification.window_frames" in report
    assert len(RrdReader(out).blueprints()) == 1


def test_an_error_leaves_no_recording(tmp_path):
    out = tmp_path / "broken.rrd"
    _script(RerunSink(RerunConfig(), RerunOutputs(save=out)), tmp_path, finish=False)
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
    sink.on_start(_start(tmp_path))
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
