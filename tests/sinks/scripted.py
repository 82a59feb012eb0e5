"""A scripted replay for the sink tests: hand-built records (a verifier's two steps, a retrieval
query) fed to a sink in the replay's call order, so that every value can be checked."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lcv_replay.evaluation.metrics import detection_metrics
from lcv_replay.evaluation.truth import LoopTruth, TruthSource
from lcv_replay.records import Frame, ImageRef, LoopCandidate, Pose2D
from lcv_replay.sinks.base import FrameUpdate, RetrievalUpdate, RunStart, RunSummary, StepMetrics, StepUpdate
from lcv_replay.verification.base import Constraint, HypothesisSummary, VerifierStep

N = 30
T0 = 1_700_000_000_123_456_789  # an exact ns stamp (not representable as float64 seconds)


def frame(i: int) -> Frame:
    image = np.full((24, 32), i * 8 % 255, dtype=np.uint8)
    return Frame(
        index=i,
        stamp_ns=T0 + i * 100_000_000,
        odom=Pose2D(float(i), 0.0, 0.0),
        ground_truth=Pose2D(float(i), 0.5, 0.0),
        left=ImageRef(T0, "mono8", lambda image=image: image),
    )


def step(frame_index, window, accepted, constraints, scores, notes=()) -> VerifierStep:
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
        notes=tuple(notes),
    )


def metrics(verifier_step, truth, constraints) -> StepMetrics:
    det = detection_metrics(verifier_step.accepted_constraint_ids, LoopTruth(TruthSource.LABELS, tuple(truth[: len(constraints)])))
    return StepMetrics(verifier_step.frame_index, len(constraints), det, ate_rmse_m=0.5, hypotheses=len(verifier_step.ranking))


def start(tmp_path: Path) -> RunStart:
    return RunStart(
        log_path=tmp_path / "fake.mcap", method="ilv", constraint_source="both", rate=None, seed=0,
        config={"verification": {"window_frames": 20}}, frames=N, first_log_frame=0, start_ns=T0,
        log_duration_s=2.9, has_images=True, has_ground_truth=True, truth_source="labels",
        ground_truth=np.column_stack([np.arange(N, dtype=float), np.full(N, 0.5), np.zeros(N)]), code_bits=20,
    )


def script(sink, tmp_path: Path, *, finish: bool = True) -> None:
    """Feed ``sink`` a 30-frame run: constraints 0 (true) and 1 (false) arrive at frame 15, 2 (true)
    at 25; window 0 (frame 19) accepts 0 and 1, the final window (frame 29) accepts 0 and 2."""
    c = [Constraint(0, LoopCandidate(15, 2, 0.9, source="retrieval"), 15),
         Constraint(1, LoopCandidate(15, 8, 0.4, source="retrieval"), 15),
         Constraint(2, LoopCandidate(25, 3, 0.8, source="log"), 25)]
    truth = [True, False, True]
    sink.on_start(start(tmp_path))
    for i in range(N):
        new = tuple(x for x in c if x.arrival_frame == i)
        current = frame(i)
        sink.on_frame(FrameUpdate(current, new, tuple(truth[x.id] for x in new), sum(x.arrival_frame <= i for x in c), i * 0.01, i * 0.1))
        if i == 15:
            sink.on_retrieval(RetrievalUpdate(current, tuple(x.candidate for x in new), code=np.arange(20) % 3 == 0,
                                              prefilter_size=7, top_frames=np.array([2, 8]), l2_distances=np.array([0.3, 0.7]),
                                              hamming=np.array([1, 3])))
        if i == 19:
            first = step(19, 0, [0, 1], c[:2], [(3, (1,), 2), (0, (), 1)])
            sink.on_step(StepUpdate(first, metrics(first, truth, c[:2]), c[:2], truth[:2]))
        if i == 29:
            last = step(29, 1, [0, 2], c, [(5, (0, 2), 3), (3, (1,), 1), (0, (), 1)],
                        notes=("end of the log: 1 refused loop accepted across odometry slips (under heavy-tailed odometry): 2 (25↔3)",))
            sink.on_step(StepUpdate(last, metrics(last, truth, c), c, truth, final=True))
    if finish:
        sink.on_finish(RunSummary(frames=N, wall_time_s=0.3, log_duration_s=2.9, method="ilv", constraints=3, accepted=2,
                                  true_positives=2, false_positives=0, false_negatives=0, precision=1.0, recall=1.0,
                                  ate_rmse_m=0.5, hypotheses=3, accepted_constraint_ids=(0, 2), truth_source="labels",
                                  config={"verification": {"window_frames": 20}}))
    sink.close()


