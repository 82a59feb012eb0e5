"""The run record: each constraint's fate from the steps a sink sees, and its round trip through
plain columns (what the recording stores)."""

from __future__ import annotations

import dataclasses

import numpy as np

from lcv_replay.sinks.base import StepUpdate
from lcv_replay.sinks.run_record import RunRecord, RunRecorder
from tests.sinks.scripted import script


class _FlagLast(RunRecorder):
    """A recorder whose final step flags constraint 1 ambiguous (as a verifier may, instead of
    accepting or rejecting it)."""

    def on_step(self, update: StepUpdate) -> None:
        if update.final:
            update = dataclasses.replace(update, step=dataclasses.replace(update.step, ambiguous_constraint_ids=(1,)))
        super().on_step(update)


def test_fates_windows_and_d2(tmp_path):
    recorder = RunRecorder()
    script(recorder, tmp_path)
    r = recorder.record
    assert [(l.state, l.truth, l.first_accepted_frame, l.dropped_frame) for l in r.loops] == [
        ("accepted", True, 19, None), ("rejected", False, 19, 29), ("accepted", True, 29, None)]
    assert [l.query_stamp_ns - r.stamps_ns[0] for l in r.loops] == [1_500_000_000, 1_500_000_000, 2_500_000_000]
    # d² under the final estimate (rank 1: x = frame, y = 0.5): the "same place" loops are 13 m,
    # 7 m and 22 m apart with the 2 m loop sigma of the default config: (d / 2)².
    np.testing.assert_allclose([l.d2 for l in r.loops], [(13 / 2) ** 2, (7 / 2) ** 2, (22 / 2) ** 2])
    assert [(w.frame_index, w.precision, w.final) for w in r.windows] == [(19, 0.5, False), (29, 1.0, True)]
    assert r.first_wrong_acceptance().constraint_id == 1 and r.first_missed is None
    assert r.counts() == {"accepted": 2, "rejected": 1, "pending": 0, "ambiguous": 0, "wrong": 0, "missed": 0}
    assert [s.hypothesis_ids.tolist() for s in r.consistency] == [[3, 0], [5, 3, 0]]
    assert {t.id: (t.parent_id, t.constraint_id) for t in r.tree} == {0: (None, None), 3: (0, 1), 5: (0, 2)}
    assert sorted(r.top_trajectories) == [0, 3, 5] and r.estimate.shape == (30, 3)


def test_columns_round_trip_exactly(tmp_path):
    recorder = RunRecorder()
    script(recorder, tmp_path)
    back = RunRecord.from_columns(recorder.record.to_columns())
    assert back == recorder.record
    assert back != dataclasses.replace(recorder.record, seed=99)


def test_a_constraint_flagged_ambiguous_is_neither_accepted_nor_rejected(tmp_path):
    recorder = _FlagLast()
    script(recorder, tmp_path)
    assert [l.state for l in recorder.record.loops] == ["accepted", "ambiguous", "accepted"]
    assert recorder.record.counts()["ambiguous"] == 1


def test_the_summary_and_the_report_say_what_was_flagged_and_what_became_of_a_wrong_loop(tmp_path):
    from lcv_replay.report.html import summary_rows
    from lcv_replay.sinks.summary import format_summary

    plain = RunRecorder()
    script(plain, tmp_path / "plain")
    assert plain.record.flagged_words() == ""  # nothing flagged: no line, no row
    assert "ambiguous" not in [figure for figure, _, _ in summary_rows(plain.record)]

    recorder = _FlagLast()
    script(recorder, tmp_path / "flagged")
    record = recorder.record
    wrong = record.first_wrong_acceptance()
    assert (wrong.constraint_id, wrong.first_accepted_frame, wrong.later) == (1, 19, "flagged ambiguous from frame 29")
    assert record.loops[0].later == ""  # accepted to the end
    words = "flagged rather than accepted: the verifier could not tell them from true loops (1 false, 0 true by the truth)"
    assert record.flagged_words() == words
    assert ("ambiguous", "1", words) in summary_rows(record)
    text = format_summary(_summary(), record)
    assert f"  ambiguous         1 {words}" in text
    assert "constraint 1 (15↔8) accepted although false (flagged ambiguous from frame 29); open there" in text


def _summary():
    from lcv_replay.sinks.base import RunSummary

    return RunSummary(frames=30, wall_time_s=0.3, log_duration_s=2.9, method="ilv", constraints=3, accepted=2,
                      true_positives=2, false_positives=0, false_negatives=0, precision=1.0, recall=1.0, ate_rmse_m=0.5,
                      hypotheses=3, constraint_source="images", truth_source="labels", rrd="run.rrd", config={})


def test_a_consistency_matrix_with_fewer_rows_than_the_ranking_shows_the_rows_it_has():
    """ilv+ on measured loops gives one consistency row (its working hypothesis) and ranks its
    contests below it: the snapshot shows that row rather than nothing (an empty panel)."""
    from lcv_replay.sinks.run_record import consistency_snapshot
    from lcv_replay.verification.base import HypothesisSummary, VerifierStep

    ranking = tuple(HypothesisSummary(id=h, parent_id=None, constraint_ids=(), score=0, rank=r, window=0) for r, h in ((1, 7), (2, 9)))
    step = VerifierStep(frame_index=9, window_index=0, new_constraint_ids=(0, 1, 2), new_hypotheses=ranking, generation_edges=(),
                        accepted_constraint_ids=(0, 2), ranking=ranking, consistency=np.array([[True, False, True]]))
    snap = consistency_snapshot(step)
    assert snap.hypothesis_ids.tolist() == [7]
    assert snap.consistent.shape == (1, len(snap.constraint_ids)) and snap.consistent.any()
