"""Recall against every true revisit: the revisit frames by brute force, and the counts of a run."""

from __future__ import annotations

import numpy as np
import pytest

from lcv_replay.evaluation.revisits import revisit_frames, revisit_recall


def _brute_force(p: np.ndarray, radius_m: float, exclusion_frames: int) -> np.ndarray:
    out = np.zeros(len(p), bool)
    for q in range(len(p)):
        for m in range(0, max(0, q - exclusion_frames)):
            if np.all(np.isfinite(p[[q, m]])) and np.hypot(*(p[q] - p[m])) < radius_m:
                out[q] = True
                break
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_revisit_frames_equal_brute_force(seed):
    rng = np.random.default_rng(seed)
    p = np.cumsum(rng.normal(size=(300, 2)), axis=0) * 2.0  # a random walk that crosses itself
    p[rng.integers(0, 300, size=10)] = np.nan  # frames without ground truth revisit nothing
    got = revisit_frames(p, radius_m=10.0, exclusion_frames=20)
    assert got.any() and np.array_equal(got, _brute_force(p, 10.0, 20))


def test_the_radius_is_strict_like_the_constraint_truth():
    p = np.array([[0.0, 0.0], [50.0, 0.0], [10.0, 0.0], [9.999, 0.0]])
    assert revisit_frames(p, radius_m=10.0, exclusion_frames=1).tolist() == [False, False, False, True]


def test_revisit_recall_counts_frames_not_constraints():
    # frames 0..9 drive away, 10..19 come back over the same places (x = 10 - (i - 10))
    x = np.array([float(i) for i in range(10)] + [float(19 - i) for i in range(10, 20)])
    p = np.stack([x * 5.0, np.zeros(20)], axis=1)  # 5 m apart: only the same place is within 3 m
    # constraint ids: 0 (15, 4) true accepted; 1 (15, 3) false; 2 (16, 3) true not accepted;
    # 3 (17, 2) true accepted; 4 (17, 1) true accepted (same frame again); 5 (5, 4): not a revisit
    queries = [15, 15, 16, 17, 17, 5]
    truth = [True, False, True, True, True, True]
    result = revisit_recall(p, queries, truth, {0, 3, 4, 5}, radius_m=3.0, exclusion_frames=2)
    # frame 10 is at frame 9's place (1 frame back, within Δt); frames 11..19 revisit 8..0
    assert result.revisits == 9
    assert (result.proposed, result.closed) == (3, 2)
    assert result.recall == pytest.approx(2 / 9) and result.proposed_share == pytest.approx(3 / 9)
    assert revisit_recall(p[:3], [], [], set(), radius_m=3.0, exclusion_frames=2).recall is None
