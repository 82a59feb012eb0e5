"""bench soak: chaining pose graphs into one long log, and the curve's two goals."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from lcv_replay import se2
from lcv_replay.bench.soak import JOINT_STEP, SoakReport, SoakSample, chain_recordings, format_report
from lcv_replay.records import LoopCandidate


def _recording(n: int, name: str):
    steps = np.tile([1.0, 0.0, 0.1], (n - 1, 1))
    odometry = se2.compose_chain(steps, (5.0, -2.0, 0.3))
    candidates = (LoopCandidate(n - 1, 2, T_match_query=None), LoopCandidate(3, 0))
    return SimpleNamespace(odometry=odometry, ground_truth=odometry + 0.5, candidates=candidates, true_loops=frozenset({(n - 1, 2)}), dataset=name)


def test_chained_graphs_continue_each_other_and_shift_their_loops():
    a, b = _recording(10, "a"), _recording(6, "b")
    chained = chain_recordings([a, b], 23)  # a, b, then the first 7 frames of a again
    assert len(chained.odometry) == 23 and chained.pieces == (("a", 0, 10), ("b", 10, 6), ("a", 16, 7))
    # each piece keeps its own relative motion, and starts one step ahead of the previous piece's end
    np.testing.assert_allclose(se2.relative_steps(chained.odometry[10:16]), se2.relative_steps(b.odometry), atol=1e-12)
    np.testing.assert_allclose(chained.odometry[10], se2.compose(chained.odometry[9], JOINT_STEP), atol=1e-12)
    np.testing.assert_allclose(chained.ground_truth[16], se2.compose(chained.ground_truth[15], JOINT_STEP), atol=1e-12)
    pairs = sorted(c.pair for c in chained.candidates)
    assert pairs == [(3, 0), (9, 2), (13, 10), (15, 12), (19, 16)]  # the third piece's (9, 2) is cut off
    assert chained.true_loops == {(9, 2), (15, 12)}


def test_the_report_fits_a_line_through_the_jitter():
    samples = [SoakSample(k * 1000, 100.0 + 0.5 * k + (1.0 if k % 2 else -1.0), k * 1.0, 2.0) for k in range(1, 21)]
    report = SoakReport("log", 20_000, True, samples)
    assert report.rss_growth == pytest.approx(7.5 / (100.0 + 0.5 * 5), rel=0.1)
    assert report.rss_growth_kb_per_frame == pytest.approx(0.5, rel=0.1)
    assert report.time_ratio == pytest.approx(1.0)
    assert "goal < 10 %: met" in format_report(report)
