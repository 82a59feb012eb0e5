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
])
def test_bad_retrieval_values_are_refused(tmp_path, line, message):
    path = tmp_path / "c.toml"
    path.write_text(f"[retrieval]\n{line}\n")
    with pytest.raises(ConfigError, match=message):
        load_config(path)
