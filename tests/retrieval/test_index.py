"""The incremental index: exact Hamming prefilter, Δt eligibility, L2 order, growth, empty cases."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from lcv_replay.errors import RetrievalError
from lcv_replay.retrieval.index import CodeIndex, probe_count, probe_masks

STRATEGIES = ["scan", "table"]


def _flip(code: int, bits: tuple[int, ...]) -> int:
    for b in bits:
        code ^= 1 << b
    return code


def _library(strategy: str, *, n: int = 3000, bits: int = 20, dim: int = 8, seed: int = 0):
    rng = np.random.default_rng(seed)
    index = CodeIndex(code_bits=bits, vector_dim=dim, hamming_threshold=3, strategy=strategy, initial_capacity=16)
    query = int(rng.integers(0, 1 << bits))
    codes = rng.integers(0, 1 << bits, size=n)
    # plant codes at every distance 0..5 from the query, several times each
    for i, d in enumerate(itertools.chain.from_iterable(itertools.repeat(range(6), 20))):
        codes[(7 * i + 3) % n] = _flip(query, tuple(rng.choice(bits, size=d, replace=False)))
    vectors = rng.normal(size=(n, dim)).astype(np.float32)
    frames = np.cumsum(rng.integers(1, 3, size=n))  # increasing, with gaps
    for f, c, v in zip(frames, codes, vectors):
        index.add(int(f), int(c), v)
    return index, query, codes, vectors, frames


def test_probe_masks_cover_the_hamming_ball_exactly():
    masks = probe_masks(20, 3)
    assert len(masks) == probe_count(20, 3) == 1 + 20 + 190 + 1140
    assert len(set(masks.tolist())) == len(masks)
    assert np.bitwise_count(masks).max() == 3


@pytest.mark.parametrize("strategy", STRATEGIES)
def test_prefilter_equals_brute_force_including_distance_3(strategy):
    index, query, codes, vectors, frames = _library(strategy)
    assert len(index) == len(codes) and index.frames.shape == frames.shape  # survived doubling from 16
    distances = np.array([bin(int(c) ^ query).count("1") for c in codes])
    assert {0, 1, 2, 3, 4, 5} <= set(distances.tolist())
    last = int(frames[-1])
    result = index.search(query, np.zeros(8, np.float32), max_frame_index=last, top_k=len(codes))
    expected = set(frames[distances <= 3].tolist())
    assert set(result.frames.tolist()) == expected
    assert result.prefilter_size == len(expected)
    assert np.array_equal(result.hamming, distances[np.searchsorted(frames, result.frames)])
    assert 3 in result.hamming.tolist() and 4 not in result.hamming.tolist()


@pytest.mark.parametrize("strategy", STRATEGIES)
def test_only_frames_up_to_max_frame_index_are_eligible(strategy):
    index, query, codes, vectors, frames = _library(strategy)
    distances = np.array([bin(int(c) ^ query).count("1") for c in codes])
    cut = int(frames[len(frames) // 2])
    result = index.search(query, np.zeros(8, np.float32), max_frame_index=cut, top_k=10_000)
    assert result.frames.size and result.frames.max() <= cut
    assert set(result.frames.tolist()) == set(frames[(distances <= 3) & (frames <= cut)].tolist())
    assert index.search(query, np.zeros(8, np.float32), max_frame_index=int(frames[0]) - 1, top_k=10).frames.size == 0


@pytest.mark.parametrize("strategy", STRATEGIES)
def test_top_n_follows_l2_order(strategy):
    index, query, codes, vectors, frames = _library(strategy)
    q = np.random.default_rng(9).normal(size=8).astype(np.float32)
    result = index.search(query, q, max_frame_index=int(frames[-1]), top_k=10)
    distances = np.array([bin(int(c) ^ query).count("1") for c in codes])
    rows = np.flatnonzero(distances <= 3)
    l2 = np.linalg.norm(vectors[rows] - q, axis=1)
    best = rows[np.argsort(l2, kind="stable")[:10]]
    assert np.array_equal(result.frames, frames[best])
    assert np.all(np.diff(result.l2_distances) >= 0)
    assert np.allclose(result.l2_distances, np.sort(l2)[:10], atol=1e-5)


def test_strategies_agree_and_fewer_than_n_is_fine():
    a = _library("scan", n=400, seed=4)[0]
    b = _library("table", n=400, seed=4)[0]
    rng = np.random.default_rng(2)
    for _ in range(30):
        code, vec = int(rng.integers(0, 1 << 20)), rng.normal(size=8).astype(np.float32)
        ra = a.search(code, vec, max_frame_index=500, top_k=10)
        rb = b.search(code, vec, max_frame_index=500, top_k=10)
        assert np.array_equal(ra.frames, rb.frames) and ra.prefilter_size == rb.prefilter_size
        assert len(ra.frames) == min(10, ra.prefilter_size)


def test_ties_in_l2_are_broken_by_frame_index():
    index = CodeIndex(code_bits=8, vector_dim=2, hamming_threshold=3)
    for f in (5, 2 + 5, 9 + 5):
        index.add(f, 0b1, np.array([1.0, 0.0]))
    result = index.search(0b1, np.array([0.0, 0.0]), max_frame_index=100, top_k=2)
    assert result.frames.tolist() == [5, 7]


@pytest.mark.parametrize("strategy", STRATEGIES)
def test_empty_index_and_bad_input(strategy):
    index = CodeIndex(code_bits=20, vector_dim=4, hamming_threshold=3, strategy=strategy)
    empty = index.search(5, np.zeros(4), max_frame_index=1000, top_k=10)
    assert empty.frames.size == 0 and empty.prefilter_size == 0 and len(index) == 0
    index.add(3, 5, np.zeros(4))
    with pytest.raises(RetrievalError, match="increasing frame order"):
        index.add(3, 5, np.zeros(4))
    with pytest.raises(RetrievalError, match="does not fit in 20 bits"):
        index.add(4, 1 << 20, np.zeros(4))
    with pytest.raises(RetrievalError, match="dimensions"):
        index.add(4, 1, np.zeros(5))


def test_table_strategy_refuses_wide_codes_and_auto_is_scan():
    with pytest.raises(RetrievalError, match="at most 24 bits"):
        CodeIndex(code_bits=32, vector_dim=4, hamming_threshold=3, strategy="table")
    with pytest.raises(RetrievalError, match="8192 probes"):
        CodeIndex(code_bits=24, vector_dim=4, hamming_threshold=6, strategy="table")
    assert CodeIndex(code_bits=20, vector_dim=4, hamming_threshold=3).strategy == "scan"
    assert CodeIndex(code_bits=20, vector_dim=4, hamming_threshold=3, strategy="table").strategy == "table"
