"""The retrieval section of the TOML config: new keys load, bad values are refused by name."""

from __future__ import annotations

import pytest

from lcv_replay.config import load_config
from lcv_replay.errors import ConfigError


def test_retrieval_keys_load_from_toml(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text('[retrieval]\npooling = "gem"\nprecision = "bf16"\nrerank = "pca"\nindex_strategy = "scan"\nnum_threads = 1\n')
    r = load_config(path).retrieval
    assert (r.pooling, r.precision, r.rerank, r.index_strategy, r.num_threads) == ("gem", "bf16", "pca", "scan", 1)
    assert (r.top_k, r.exclusion_frames, r.code_bits, r.hamming_threshold, r.pca_dims) == (10, 200, 20, 3, 128)  # paper


@pytest.mark.parametrize("line, message", [
    ('pooling = "vlad"', "retrieval.pooling"),
    ("thumbnail_patch_px = 100", "retrieval.thumbnail_patch_px"),
    ("gem_p = 0.5", "retrieval.gem_p"),
    ("input_size_px = 230", "retrieval.input_size_px"),
    ("hamming_treshold = 2", "did you mean 'hamming_threshold'"),
    ('mode = "fast"', "retrieval.mode"),
    ('engine = "tensorrt"', "retrieval.engine"),
    ("[retrieval.ranked]\ncandidates = 5", r"retrieval.ranked.candidates' = 5 .*>= retrieval.top_k \(10\)"),
    ("top_k = 20\n[retrieval.ranked]\ncandidates = 19", "retrieval.ranked.candidates' = 19"),
    ("[retrieval.ranked]\ncode_bits = 60", r"retrieval.ranked.code_bits' = 60 .*multiple of 8"),
    ("[retrieval.ranked]\ncode_bits = 256", "retrieval.ranked.code_bits' = 256"),
    ("pca_dims = 32\n[retrieval.ranked]\ncode_bits = 64", r"retrieval.ranked.code_bits' = 64 .*pca_dims \(32\)"),
    ("code_bits = 65", "retrieval.code_bits"),
    ('[retrieval.ranked]\nindex = "hnsw"', "retrieval.ranked.index"),
    ("[retrieval.ranked]\ncandidate = 100", "did you mean 'candidates'"),
])
def test_bad_retrieval_values_are_refused(tmp_path, line, message):
    """Each bad value is refused by its dotted name (M < N_r, code bits out of range, unknown mode...)."""
    path = tmp_path / "c.toml"
    path.write_text(f"[retrieval]\n{line}\n")
    with pytest.raises(ConfigError, match=message):
        load_config(path)


def test_modes_load_and_direct_construction_is_checked_too():
    from lcv_replay.retrieval.config import RetrievalConfig

    assert RetrievalConfig().mode == "ranked" and RetrievalConfig().active_code_bits == 128
    assert RetrievalConfig(mode="paper").active_code_bits == 20
    assert RetrievalConfig(mode="paper").resolved_engine == "torch" and RetrievalConfig().resolved_engine == "onnxruntime"
    # the ranked section is only checked where it is used: a paper config may keep a small PCA
    assert RetrievalConfig(mode="paper", pca_dims=32, code_bits=20).pca_dims == 32
    with pytest.raises(ConfigError, match="retrieval.mode"):
        RetrievalConfig(mode="fast")
