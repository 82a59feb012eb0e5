"""The stateful Retriever: online warm-up, whole-log fit, Δt exclusion, output records."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lcv_replay.errors import RetrievalError
from lcv_replay.retrieval.config import RetrievalConfig
from lcv_replay.retrieval.retriever import Retriever
from tests.retrieval.helpers import revisit_descriptors

CONFIG = RetrievalConfig(mode="paper", exclusion_frames=30, code_bits=12, hamming_threshold=3, pca_dims=32, top_k=5)


def _run(retriever: Retriever, descriptors: np.ndarray):
    return [retriever.add(i, d) for i, d in enumerate(descriptors)]


def test_online_no_query_until_warm_up_then_finds_revisits():
    x, truth = revisit_descriptors(first_pass=80, revisits=40, dim=48)
    retriever = Retriever(CONFIG, dim=48)
    assert retriever.warmup_frames == 30 and not retriever.fitted
    outputs = _run(retriever, x)
    assert all(o.diagnostics is None and o.candidates == () for o in outputs[:30])
    assert retriever.fitted and all(o.diagnostics is not None for o in outputs[30:])
    found = sum(any(c.match_frame == m for c in outputs[q].candidates) for q, m in truth.items())
    assert found >= 0.8 * len(truth)
    for o in outputs[30:]:
        for c in o.candidates:
            assert c.query_frame - c.match_frame > CONFIG.exclusion_frames  # Δt exclusion
            assert c.source == "retrieval" and 0 <= c.hamming <= CONFIG.hamming_threshold


def test_diagnostics_describe_the_query():
    x, truth = revisit_descriptors(first_pass=80, revisits=40, dim=48)
    retriever = Retriever(CONFIG, dim=48)
    outputs = _run(retriever, x)
    q = 100
    diag = outputs[q].diagnostics
    assert diag.query_frame == q and diag.code_bits == 12 and 0 <= diag.code < (1 << 12)
    assert len(diag.code_bit_string) == 12 and int(diag.code_bit_string, 2) == diag.code
    assert diag.top == outputs[q].candidates and len(diag.l2_distances) == len(diag.top)
    assert diag.prefilter_size >= len(diag.top) and diag.library_size == q
    assert diag.eligible_size == q - CONFIG.exclusion_frames
    # the code is the hasher's code of the descriptor; similarity is the cosine (unit descriptors)
    assert diag.code == int(retriever.hasher.encode(x[q][None])[0])
    for c, d in zip(diag.top, diag.l2_distances):
        assert c.similarity == pytest.approx(float(x[q] @ x[c.match_frame]), abs=1e-5)
        assert d == pytest.approx(float(np.linalg.norm(x[q] - x[c.match_frame])), abs=1e-5)
    assert list(diag.l2_distances) == sorted(diag.l2_distances)


def test_whole_log_fit_queries_from_the_first_frame_and_needs_fit_first():
    x, truth = revisit_descriptors(first_pass=60, revisits=30, dim=48)
    config = dataclasses.replace(CONFIG, fit="whole-log")
    retriever = Retriever(config, dim=48)
    with pytest.raises(RetrievalError, match="fit"):
        retriever.add(0, x[0])
    retriever = Retriever(config, dim=48)
    retriever.fit(x)
    outputs = _run(retriever, x)
    assert all(o.diagnostics is not None for o in outputs)
    assert all(o.candidates == () for o in outputs[: CONFIG.exclusion_frames + 1])  # nothing eligible yet


def test_short_log_gives_a_message_not_a_crash():
    x, _ = revisit_descriptors(first_pass=10, revisits=0, dim=48)
    retriever = Retriever(CONFIG, dim=48)
    outputs = _run(retriever, x)
    assert all(o.diagnostics is None for o in outputs) and not retriever.fitted
    message = retriever.warmup_message()
    assert "10 usable images" in message and "30 needed" in message
    assert retriever.warmup_remaining == 20
    with pytest.raises(RetrievalError, match="needs at least 13"):
        Retriever(dataclasses.replace(CONFIG, fit="whole-log"), dim=48).fit(x)
    with pytest.raises(RetrievalError, match=r"\(N, 48\)"):
        Retriever(CONFIG, dim=48).fit(np.zeros((0,)))


def test_warm_up_is_at_least_code_bits_plus_one():
    retriever = Retriever(dataclasses.replace(CONFIG, exclusion_frames=2), dim=48)
    assert retriever.warmup_frames == 13


def test_pca_rerank_returns_the_same_kind_of_records():
    x, truth = revisit_descriptors(first_pass=80, revisits=40, dim=48)
    outputs = _run(Retriever(dataclasses.replace(CONFIG, rerank="pca"), dim=48), x)
    found = sum(any(c.match_frame == m for c in outputs[q].candidates) for q, m in truth.items())
    assert found >= 0.8 * len(truth)


def test_refit_re_encodes_the_library():
    x, truth = revisit_descriptors(first_pass=80, revisits=40, dim=48)
    retriever = Retriever(CONFIG, dim=48)
    _run(retriever, x[:100])
    before = retriever.hasher
    retriever.refit()
    assert retriever.hasher is not before and retriever.library_size == 100
    out = retriever.add(100, x[100])
    assert out.diagnostics.library_size == 100


def test_bad_input_is_refused():
    retriever = Retriever(CONFIG, dim=48)
    with pytest.raises(RetrievalError, match="48"):
        retriever.add(0, np.zeros(47))
    with pytest.raises(RetrievalError, match="NaN"):
        retriever.add(0, np.full(48, np.nan))
    retriever.add(5, np.ones(48))
    with pytest.raises(RetrievalError, match="increasing"):
        retriever.add(5, np.ones(48))
    with pytest.raises(RetrievalError, match="code"):
        Retriever(CONFIG, dim=8)
