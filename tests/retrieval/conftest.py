"""Fixtures of the retrieval tests: the CNN is built once per test session."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lcv_replay.retrieval.config import RetrievalConfig
from tests.conftest import shared_path

CORRIDOR = ("rtabmap_corridor",)


@pytest.fixture(scope="session")
def lite0_backend():
    """The default EfficientNet-Lite0 backend (weights from the installed package), built once."""
    from lcv_replay.retrieval.descriptors import make_backend

    return make_backend("efficientnet-lite0", RetrievalConfig())


@pytest.fixture(scope="session")
def corridor() -> tuple[list[np.ndarray], np.ndarray, Path]:
    """The 84 rtabmap corridor images (RGB, in order), their symmetric truth matrix, and the folder."""
    from lcv_replay.bench.retrieval import list_images, load_truth_matrix, read_image

    folder = shared_path(*CORRIDOR)
    truth_path = folder / "samples_GT.bmp"
    paths = list_images(folder, exclude=[truth_path])
    return [read_image(p) for p in paths], load_truth_matrix(truth_path, len(paths)), folder


@pytest.fixture(scope="session")
def corridor_descriptors(lite0_backend, corridor) -> np.ndarray:
    """``(84, D)`` EfficientNet-Lite0 descriptors of the corridor images."""
    images, _, _ = corridor
    return lite0_backend.describe(images)
