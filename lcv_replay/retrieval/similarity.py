"""A similarity in [0, 1] calibrated to the log: 0 = as alike as two unrelated frames, 1 = identical.

The re-rank's L2 distance ``d`` between L2-normalised descriptors is a cosine in disguise
(``cos = 1 - d^2 / 2``), but its useful range depends on the descriptor and on the log: on the
RTAB-Map corridor, unrelated frames have cosines around 0.88, on the synthetic world around 0.91,
so a raw cosine of 0.9 means nothing on its own. The improved mode therefore measures, when it fits
PCA and the codes, the **background**: the median squared distance ``d0^2`` between fitting frames
more than ``Δt / 2`` apart (different places, as far as the warm-up can tell), and reports::

    similarity = clip(1 - d^2 / d0^2, 0, 1)

that is, the cosine rescaled so that the log's typical unrelated pair is 0 and an identical image
is 1 (for unit descriptors ``1 - d^2 / d0^2 = (cos - cos0) / (1 - cos0)``). With the re-rank on PCA
vectors (``rerank = "pca"``) the same holds in PCA space. It is monotone in ``d``, so it never
reorders candidates; it is not a probability (appearance alone cannot say how often a look-alike
place is a different one: docs/retrieval.md gives the measured precision per similarity band).

The paper mode keeps its similarity of before, ``1 - d^2 / 2``, so that it stays bit-identical.
"""

from __future__ import annotations

import numpy as np

from lcv_replay.errors import RetrievalError

MAX_BACKGROUND_ROWS = 1000  # rows sampled (evenly) from a long fitting set: 500k pairs at most


def background_sq_distance(vectors: np.ndarray, *, min_gap_rows: int) -> float:
    """Median squared L2 distance between rows of ``vectors`` more than ``min_gap_rows`` apart.

    Args:
        vectors: ``(N, K)`` fitting vectors in time order (``N >= 2``); at most
            :data:`MAX_BACKGROUND_ROWS` evenly spaced rows are used.
        min_gap_rows: pairs closer in time are skipped (they are the same place); when no pair is
            that far apart, every pair counts.

    Returns:
        ``d0^2 > 0``; a set of identical vectors gives the smallest positive float.
    """
    x = np.asarray(vectors, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] < 2:
        raise RetrievalError(f"the background needs at least 2 fitting vectors, got shape {x.shape}")
    rows = np.unique(np.linspace(0, x.shape[0] - 1, min(x.shape[0], MAX_BACKGROUND_ROWS)).round().astype(np.int64))
    x = x[rows]
    sq = np.einsum("ij,ij->i", x, x)
    i, j = np.triu_indices(rows.size, k=1)
    far = rows[j] - rows[i] > min_gap_rows
    if far.any():
        i, j = i[far], j[far]
    d2 = np.maximum(sq[i] + sq[j] - 2.0 * np.einsum("ij,ij->i", x[i], x[j]), 0.0)
    return max(float(np.median(d2)), float(np.finfo(np.float64).tiny))


def calibrated_similarity(l2_distances: np.ndarray, background_sq: float) -> np.ndarray:
    """``(M,)`` L2 distances -> ``(M,)`` float64 similarities ``clip(1 - d^2 / d0^2, 0, 1)``."""
    d = np.asarray(l2_distances, dtype=np.float64)
    return np.clip(1.0 - d * d / float(background_sq), 0.0, 1.0)
