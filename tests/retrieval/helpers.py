"""Small synthetic inputs and shared state of the retrieval tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: The descriptor cache folder of each log described by the session fixture ``corridor_descriptors``
#: (filled by tests/retrieval/conftest.py; a test that reuses the cache reads it here).
DESCRIPTOR_CACHE_DIRS: dict[Path, Path] = {}


def revisit_descriptors(*, first_pass: int, revisits: int, dim: int = 64, noise: float = 0.05, seed: int = 0) -> tuple[np.ndarray, dict[int, int]]:
    """Descriptors of a route walked once (``first_pass`` places) then partly again.

    Frame ``first_pass + i`` revisits place ``i`` (same vector plus noise). Neighbouring places are
    correlated, as along a real route.

    Returns:
        ``(descriptors (N, dim) float32 L2-normalised, {revisit frame: true match frame})``.
    """
    rng = np.random.default_rng(seed)
    places = np.cumsum(rng.normal(size=(first_pass, dim)), axis=0) * 0.3 + rng.normal(size=(first_pass, dim))
    rows = [places[i] + noise * rng.normal(size=dim) for i in range(first_pass)]
    truth = {}
    for i in range(revisits):
        rows.append(places[i] + noise * rng.normal(size=dim))
        truth[first_pass + i] = i
    x = np.asarray(rows, dtype=np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True), truth
