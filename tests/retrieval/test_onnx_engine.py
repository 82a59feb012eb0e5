"""The ONNX Runtime engine: same descriptors as torch, exported once and cached, torch as fallback;
and the descriptor cache, keyed by the engine each mode runs, never serves one mode's vectors to the other."""

from __future__ import annotations

import logging
import os
import sys

import numpy as np
import pytest

pytest.importorskip("onnxruntime")
torch = pytest.importorskip("torch")

from lcv_replay.errors import RetrievalError  # noqa: E402
from lcv_replay.retrieval import efficientnet as enet  # noqa: E402
from lcv_replay.retrieval import onnx_engine  # noqa: E402
from lcv_replay.retrieval.config import RetrievalConfig  # noqa: E402
from lcv_replay.retrieval.descriptors import make_backend  # noqa: E402

SMALL = dict(input_size_px=64, batch_size=4, pooling="avg")  # a cheap export for the cache tests


@pytest.fixture(scope="module")
def torch_backend():
    """The paper mode's engine (engine auto -> torch), at the default settings."""
    backend = make_backend("efficientnet-lite0", RetrievalConfig(mode="paper"))
    assert backend.engine == "torch"
    return backend


def test_onnxruntime_is_the_default_engine_and_matches_torch(lite0_backend, torch_backend, corridor):
    images, _, _ = corridor
    assert lite0_backend.engine == "onnxruntime" and RetrievalConfig().resolved_engine == "onnxruntime"
    subset = images[::5]
    ort = lite0_backend.describe(subset)
    ref = torch_backend.describe(subset)
    assert ort.shape == ref.shape == (len(subset), 1904)
    assert float((ort * ref).sum(axis=1).min()) >= 0.99999
    assert float(np.abs(ort - ref).max()) <= 1e-5
    assert lite0_backend.signature != torch_backend.signature  # their descriptor caches are separate


@pytest.mark.slow
def test_the_export_is_made_at_first_use_then_read_from_the_cache(tmp_path, caplog):
    pooling = enet.pooling_spec("avg", 3.0)
    first = onnx_engine.OnnxDescriptorModel(64, pooling, num_threads=1, cache_dir=tmp_path)
    assert first.exported and first.path.parent == tmp_path and first.path.with_suffix(".json").is_file()
    batch = np.random.default_rng(1).integers(0, 256, size=(3, 64, 64, 3), dtype=np.uint8)
    out = first(batch)
    assert out.shape == (3, 1280) and np.allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-5)
    again = onnx_engine.OnnxDescriptorModel(64, pooling, num_threads=1, cache_dir=tmp_path)
    assert not again.exported and np.array_equal(again(batch), out)
    # another pooling is another graph: another file
    key = onnx_engine.export_key(64, pooling)
    assert onnx_engine.exported_model_path(onnx_engine.export_key(64, enet.pooling_spec("gem", 3.0)), tmp_path) != first.path
    # damage is detected by the digest in the sidecar, and a changed sidecar by its fields
    data = bytearray(first.path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    first.path.write_bytes(bytes(data))
    assert again._cache_problem(key) == "checksum mismatch (damaged file)"
    first.path.with_suffix(".json").write_text("{not json")
    assert again._cache_problem(key).startswith("unreadable sidecar")
    with caplog.at_level(logging.WARNING):
        rebuilt = onnx_engine.OnnxDescriptorModel(64, pooling, num_threads=1, cache_dir=tmp_path)
    assert rebuilt.exported and "exporting it again" in caplog.text
    assert np.allclose(rebuilt(batch), out, atol=1e-6)


def test_auto_falls_back_to_torch_and_an_explicit_engine_does_not(monkeypatch, caplog):
    def missing():
        raise RetrievalError("retrieval.engine = 'onnxruntime' needs the onnxruntime package")

    monkeypatch.setattr(onnx_engine, "import_onnxruntime", missing)
    with caplog.at_level(logging.WARNING):
        backend = make_backend("efficientnet-lite0", RetrievalConfig(**SMALL))
    assert backend.engine == "torch" and "ONNX Runtime unavailable" in caplog.text
    with pytest.raises(RetrievalError, match="onnxruntime package"):
        make_backend("efficientnet-lite0", RetrievalConfig(engine="onnxruntime", **SMALL))
    with pytest.raises(RetrievalError, match="torch option"):
        make_backend("efficientnet-lite0", RetrievalConfig(engine="onnxruntime", precision="bf16", **SMALL))


def test_the_descriptor_cache_is_invalidated_when_the_mode_changes(lite0_backend, torch_backend, corridor_log, tmp_path):
    """Mode "paper" describes with torch (today's vectors, bit for bit), the default with ONNX
    Runtime: switching modes must not reuse the other engine's cache file; switching back must."""
    from lcv_replay.log.reader import open_log
    from lcv_replay.retrieval.cache import DescribeStats, describe_frames, log_cache_key

    key = log_cache_key(corridor_log)

    def run(backend) -> DescribeStats:
        stats = DescribeStats()
        with open_log(corridor_log) as reader:
            frames = [f for f in reader.frames() if f.index < 8]
            rows = list(describe_frames(frames, backend, cache_key=key, cache_dir=tmp_path, stats=stats))
        assert len(rows) == 8
        return stats

    paper = run(torch_backend)
    assert (paper.described, paper.cached) == (8, 0)
    ranked = run(lite0_backend)
    assert (ranked.described, ranked.cached) == (8, 0) and ranked.cache_path != paper.cache_path
    assert run(torch_backend).cached == 8 and run(lite0_backend).cached == 8


def test_torch_threads_wait_passively_unless_the_user_says_otherwise(monkeypatch):
    """Set before torch loads libgomp (which reads it once); the user's own setting wins."""
    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    monkeypatch.delitem(sys.modules, "torch")  # as in a fresh process (restored after the test)
    assert enet.tune_omp_wait() and os.environ["OMP_WAIT_POLICY"] == "PASSIVE"
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")
    assert enet.tune_omp_wait() and os.environ["OMP_WAIT_POLICY"] == "ACTIVE"
    monkeypatch.setitem(sys.modules, "torch", torch)
    assert not enet.tune_omp_wait()  # torch already loaded its OpenMP runtime: nothing to do
