"""The ranked prefilter (the default mode): exact Hamming k-NN, then L2; checked against brute force.

The property: the re-rank sees exactly the ``M`` eligible frames nearest in Hamming distance (ties to
the earlier frame), so every frame of the brute-force L2 top ``N_r`` that is within that candidate
budget is found, in L2 order; with ``M`` >= the eligible frames the answer *is* the brute-force
L2 top ``N_r``.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lcv_replay.retrieval.config import RetrievalConfig
from lcv_replay.retrieval.index import RankedIndex, faiss_available, hamming_nearest
from lcv_replay.retrieval.retriever import Retriever
from tests.retrieval.helpers import revisit_descriptors

ENGINES = ["numpy"] + (["faiss"] if faiss_available() else [])


def _popcount(x: int) -> int:
    return bin(x).count("1")


def sq_l2(vectors, vector):
    """Squared L2 distances in the index's float32 arithmetic (``|x|^2 + |q|^2 - 2 x.q``, row by row)."""
    norms = np.array([v @ v for v in vectors], dtype=np.float32)
    return np.maximum(norms + np.float32(vector @ vector) - 2.0 * (vectors @ vector), 0.0)


def brute_force(frames, codes, vectors, code, vector, *, max_frame, candidates, top_k):
    """The reference: Hamming top-M by (distance, frame), then L2 top-k by (distance, frame)."""
    eligible = [i for i, f in enumerate(frames) if f <= max_frame]
    budget = sorted(eligible, key=lambda i: (_popcount(int(codes[i]) ^ code), frames[i]))[:candidates]
    d2 = sq_l2(vectors[budget], vector)
    order = sorted(range(len(budget)), key=lambda k: (d2[k], frames[budget[k]]))[:top_k]
    return [frames[budget[k]] for k in order], set(frames[i] for i in budget), eligible


def l2_top(frames, vectors, vector, eligible, top_k):
    d2 = sq_l2(vectors[eligible], vector)
    return [frames[eligible[k]] for k in sorted(range(len(eligible)), key=lambda k: (d2[k], frames[eligible[k]]))[:top_k]]


@pytest.mark.parametrize("engine", ENGINES)
@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(1, 300),
    bits=st.sampled_from([8, 16, 64, 128]),
    candidates=st.integers(1, 80),
    top_k=st.integers(1, 12),
    seed=st.integers(0, 2**32 - 1),
    cut=st.floats(0.0, 1.2),
)
def test_ranked_index_equals_brute_force_on_random_codes(engine, n, bits, candidates, top_k, seed, cut):
    rng = np.random.default_rng(seed)
    # few distinct codes and vectors on a coarse grid: many Hamming and L2 ties to break by frame
    pool = [int.from_bytes(rng.bytes(bits // 8), "little") for _ in range(max(1, n // 4))]
    codes = [pool[int(i)] for i in rng.integers(0, len(pool), size=n)]
    vectors = (rng.integers(-2, 3, size=(n, 6)) / 2.0).astype(np.float32)
    frames = np.cumsum(rng.integers(1, 4, size=n)).tolist()
    index = RankedIndex(code_bits=bits, vector_dim=6, candidates=candidates, engine=engine, initial_capacity=4)
    for f, c, v in zip(frames, codes, vectors):
        index.add(f, c, v)
    code = int.from_bytes(rng.bytes(bits // 8), "little") if rng.random() < 0.5 else codes[int(rng.integers(0, n))]
    vector = (rng.integers(-2, 3, size=6) / 2.0).astype(np.float32)
    max_frame = int(cut * frames[-1])
    result = index.search(code, vector, max_frame_index=max_frame, top_k=top_k)
    expected, budget, eligible = brute_force(frames, codes, vectors, code, vector, max_frame=max_frame, candidates=candidates, top_k=top_k)
    assert result.frames.tolist() == expected
    assert result.prefilter_size == min(candidates, len(eligible))
    assert result.hamming.tolist() == [_popcount(codes[frames.index(f)] ^ code) for f in expected]
    # every brute-force L2 top-k frame within the candidate budget is found
    assert set(l2_top(frames, vectors, vector, eligible, top_k)) & budget <= set(result.frames.tolist())
    if candidates >= len(eligible):
        assert result.frames.tolist() == l2_top(frames, vectors, vector, eligible, top_k)


@pytest.mark.parametrize("engine", ENGINES)
def test_engines_agree_when_queries_go_back_in_time(engine):
    """faiss holds the rows eligible so far; an earlier query falls back to the numpy scan, exactly."""
    rng = np.random.default_rng(3)
    index = RankedIndex(code_bits=64, vector_dim=4, candidates=20, engine=engine)
    reference = RankedIndex(code_bits=64, vector_dim=4, candidates=20, engine="numpy")
    for f in range(500):
        code, vec = int(rng.integers(0, 2**63)), rng.normal(size=4).astype(np.float32)
        index.add(f, code, vec)
        reference.add(f, code, vec)
    for max_frame in (100, 400, 250, 499, 3, -1):
        code, vec = int(rng.integers(0, 2**63)), rng.normal(size=4).astype(np.float32)
        a = index.search(code, vec, max_frame_index=max_frame, top_k=10)
        b = reference.search(code, vec, max_frame_index=max_frame, top_k=10)
        assert a.frames.tolist() == b.frames.tolist() and a.hamming.tolist() == b.hamming.tolist()
        assert a.prefilter_size == min(20, max_frame + 1)


def test_hamming_nearest_keeps_the_earliest_of_tied_rows():
    codes = np.array([[0b111], [0b001], [0b011], [0b001], [0b000], [0b011]], dtype=np.uint64)
    rows, d = hamming_nearest(codes, np.array([0], dtype=np.uint64), 4)
    assert rows.tolist() == [1, 2, 3, 4] and d.tolist() == [1, 2, 1, 0]
    rows, _ = hamming_nearest(codes[:0], np.array([0], dtype=np.uint64), 4)
    assert rows.size == 0


@pytest.mark.parametrize("fit", ["whole-log", "online"])
@pytest.mark.parametrize("candidates", [10, 25])
def test_retriever_keeps_every_l2_neighbour_within_the_budget_on_real_descriptors(corridor_descriptors, fit, candidates):
    """The corridor's CNN descriptors through the Retriever (PCA, ITQ, Δt, the index), with budgets
    small enough that the prefilter decides (up to 63 frames are eligible)."""
    x = corridor_descriptors
    config = RetrievalConfig(exclusion_frames=20, fit=fit, ranked=dataclasses.replace(RetrievalConfig().ranked, candidates=candidates))
    retriever = Retriever(config, dim=x.shape[1])
    if fit == "whole-log":
        retriever.fit(x)
    hasher_checked = False
    frames = list(range(x.shape[0]))
    for q in range(x.shape[0]):
        out = retriever.add(q, x[q])
        if out.diagnostics is None:
            continue
        if not hasher_checked:  # fitted once (whole-log, or at the end of the warm-up)
            codes = [int(c) for c in retriever.hasher.encode(x)]
        eligible = [f for f in frames if f < q - 20]
        assert out.diagnostics.code == codes[q]
        expected, budget, _ = brute_force(frames, codes, x, codes[q], x[q], max_frame=q - 21, candidates=candidates, top_k=10)
        assert [c.match_frame for c in out.candidates] == expected
        assert set(l2_top(frames, x, x[q], eligible, 10)) & budget <= {c.match_frame for c in out.candidates}
        hasher_checked = True
    assert hasher_checked


def test_candidates_carry_l2_hamming_and_a_calibrated_similarity():
    x, truth = revisit_descriptors(first_pass=120, revisits=60, dim=48)
    config = RetrievalConfig(exclusion_frames=30, pca_dims=32, ranked=dataclasses.replace(RetrievalConfig().ranked, code_bits=32, candidates=20))
    retriever = Retriever(config, dim=48)
    outputs = [retriever.add(i, d) for i, d in enumerate(x)]
    assert retriever.code_bits == 24  # 30 warm-up frames span 29 PCA axes
    found = 0
    for q, m in truth.items():
        cands = outputs[q].candidates
        assert len(cands) == 10 and [c.l2_distance for c in cands] == sorted(c.l2_distance for c in cands)
        for c in cands:
            assert c.l2_distance == pytest.approx(float(np.linalg.norm(x[q] - x[c.match_frame])), abs=1e-5)
            assert 0 <= c.hamming <= 24 and 0.0 <= c.similarity <= 1.0
        assert [c.similarity for c in cands] == sorted((c.similarity for c in cands), reverse=True)
        found += cands[0].match_frame == m
    assert found >= 0.9 * len(truth)
    # revisits (same place plus noise) are near 1; unrelated frames of the route near 0
    true_sim = [outputs[q].candidates[0].similarity for q, m in truth.items() if outputs[q].candidates[0].match_frame == m]
    assert np.median(true_sim) > 0.9
