"""The scoring functions of the retrieval benchmark, on hand-made cases."""

from __future__ import annotations

import numpy as np
import pytest

from lcv_replay.bench.retrieval import (
    exhaustive_candidates,
    list_images,
    load_truth_matrix,
    query_frames,
    score_candidates,
    truth_from_poses,
)
from lcv_replay.errors import RetrievalError
from lcv_replay.records import LoopCandidate


def _truth(n: int, pairs) -> np.ndarray:
    t = np.zeros((n, n), bool)
    for q, m in pairs:
        t[q, m] = t[m, q] = True
    return t


def test_queries_need_a_true_match_beyond_the_exclusion_zone():
    truth = _truth(12, [(9, 1), (10, 8), (11, 2), (11, 3)])
    assert query_frames(truth, 5).tolist() == [9, 11]  # (10, 8) is inside Δt
    assert query_frames(truth, 8).tolist() == [11]
    assert query_frames(truth, 20).tolist() == []


def test_recall_and_precision_by_hand():
    truth = _truth(12, [(9, 1), (11, 2), (11, 3)])
    c = lambda q, m: LoopCandidate(q, m)  # noqa: E731
    candidates = {
        9: (c(9, 0), c(9, 1)),   # true at rank 2: recall@2 only
        11: (c(11, 3),),         # true at rank 1
        7: (c(7, 0),),           # not a query; a false candidate
    }
    s = score_candidates(candidates, truth, exclusion_frames=5, top_k=2)
    assert (s.queries, s.recall_at_1, s.recall_at_k) == (2, 0.5, 1.0)
    assert (s.candidates, s.true_candidates, s.candidate_precision) == (4, 2, 0.5)
    assert score_candidates({9: [0, 1]}, truth, exclusion_frames=5, top_k=1).recall_at_k == 0.0
    empty = score_candidates({}, truth, exclusion_frames=5, top_k=2)
    assert empty.recall_at_1 == 0.0 and np.isnan(empty.candidate_precision)


def test_exhaustive_candidates_respect_exclusion_and_order():
    x = np.array([[0.0], [1.0], [5.0], [0.1], [4.9]], dtype=np.float32)
    ex = exhaustive_candidates(x, exclusion_frames=1, top_k=2)
    assert ex == {2: [0], 3: [0, 1], 4: [2, 1]}  # frame 2: only frame 0 is more than 1 earlier


def test_truth_from_poses_uses_a_strict_radius_and_ignores_missing_poses():
    p = np.array([[0.0, 0.0], [9.99, 0.0], [10.0, 0.0], [np.nan, np.nan], [0.0, 0.5]])
    t = truth_from_poses(p, 10.0)
    assert t[0, 1] and not t[0, 2] and not t[3].any() and not t[:, 3].any() and t[4, 0]
    assert not t.diagonal().any() and (t == t.T).all()


def test_truth_matrix_from_text_is_symmetrised(tmp_path):
    path = tmp_path / "gt.csv"
    path.write_text("0,0,0\n0,0,0\n1,0,0\n")
    t = load_truth_matrix(path, 3)
    assert t[2, 0] and t[0, 2] and t.sum() == 2
    with pytest.raises(RetrievalError, match="3x3 but the folder has 4"):
        load_truth_matrix(path, 4)
    path.write_text("0,x\n")
    with pytest.raises(RetrievalError, match="cannot read the truth matrix"):
        load_truth_matrix(path, 1)


def test_images_are_listed_in_natural_order(tmp_path):
    for name in ("10.png", "2.png", "1.png", "notes.txt", "gt.bmp"):
        (tmp_path / name).write_bytes(b"")
    assert [p.name for p in list_images(tmp_path, exclude=[tmp_path / "gt.bmp"])] == ["1.png", "2.png", "10.png"]
    (tmp_path / "sub").mkdir()
    with pytest.raises(RetrievalError, match="no images"):
        list_images(tmp_path / "sub")
