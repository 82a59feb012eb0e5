"""Fixtures of the retrieval tests: the CNN is built once per test session."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lcv_replay.retrieval.config import RetrievalConfig
from tests.retrieval.helpers import DESCRIPTOR_CACHE_DIRS
from tests.shared_data import shared_path

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


T0_NS = 1_700_000_000_000_000_000


def write_corridor_log(path: Path, images: list[np.ndarray], truth: np.ndarray) -> Path:
    """A recorder-made MCAP of the corridor: left images (lossless PNG) and the labelled true loops."""
    from lcv_replay.log.writer import LogWriter
    from lcv_replay.records import Pose2D

    stamps = [T0_NS + i * 500_000_000 for i in range(len(images))]
    with LogWriter(path, dataset="rtabmap_corridor", recorder="tests", nominal_rate_hz=2.0, recorder_config={}) as writer:
        writer.declare_labels()
        for i, image in enumerate(images):
            writer.write_frame(i, stamps[i], left=image, odom=Pose2D(float(i), 0.0, 0.0))
            for m in np.flatnonzero(truth[i, :i]):
                writer.write_true_loop(i, int(m), stamps[i])
    return path


@pytest.fixture(scope="session")
def corridor_log(corridor, tmp_path_factory) -> Path:
    images, truth, _ = corridor
    return write_corridor_log(tmp_path_factory.mktemp("corridor") / "corridor.mcap", images, truth)


@pytest.fixture(scope="session")
def corridor_descriptors(lite0_backend, corridor_log, tmp_path_factory) -> np.ndarray:
    """``(84, D)`` EfficientNet-Lite0 descriptors of the corridor, described from the MCAP log
    through :func:`describe_frames` (PNG is lossless: the same pixels as the JPEG files decode to).
    The cache written here is checked by test_mcap.py."""
    from lcv_replay.log.reader import open_log
    from lcv_replay.retrieval.cache import describe_frames, log_cache_key

    cache_dir = tmp_path_factory.mktemp("descriptor-cache")
    with open_log(corridor_log) as reader:
        rows = list(describe_frames(reader.frames(), lite0_backend, cache_key=log_cache_key(corridor_log), cache_dir=cache_dir))
    assert all(d is not None for _, d in rows)
    DESCRIPTOR_CACHE_DIRS[corridor_log] = cache_dir
    return np.stack([d for _, d in rows])

