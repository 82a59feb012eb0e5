"""Recall against every true revisit (the paper's measure), beside recall against the candidates.

The summary's ``recall`` counts the true candidates that were proposed and accepted: it cannot see
the revisits that place recognition never proposed. A user wants to know how many of the log's
loops they got, so where the log has ground-truth poses a run also reports:

* a **revisit** is a frame ``q`` with an earlier frame ``m`` within ``T_p`` (``radius_m``, the
  paper's 10 m) in the ground truth and more than ``Δt`` frames before it (``q - m > Δt``: the
  frames retrieval may propose for ``q``);
* **proposed**: revisits with at least one true constraint among the run's constraints;
* **closed**: revisits with at least one accepted true constraint;
* ``recall = closed / revisits``, and ``proposed / revisits`` is retrieval's share.

Pure functions over arrays; a KD-tree (scipy) finds the neighbours, so long logs cost little.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np


@dataclass(frozen=True)
class RevisitRecall:
    """How many of the log's revisits a run proposed and closed.

    Attributes:
        revisits: frames that revisit a place (see the module docstring).
        proposed: revisits with a true constraint.
        closed: revisits with an accepted true constraint.
        radius_m: ``T_p``.
        exclusion_frames: ``Δt``.
    """

    revisits: int
    proposed: int
    closed: int
    radius_m: float
    exclusion_frames: int

    @property
    def recall(self) -> float | None:
        """``closed / revisits`` (``None`` without revisits)."""
        return self.closed / self.revisits if self.revisits else None

    @property
    def proposed_share(self) -> float | None:
        """``proposed / revisits`` (``None`` without revisits)."""
        return self.proposed / self.revisits if self.revisits else None


def revisit_frames(positions_m: np.ndarray, *, radius_m: float, exclusion_frames: int) -> np.ndarray:
    """``(N,)`` bool: frames with an earlier frame more than ``exclusion_frames`` before, within ``radius_m``.

    Args:
        positions_m: ``(N, 2)`` ground-truth ``x, y`` in metres, in frame order; NaN rows revisit
            nothing and are revisited by nothing.
    """
    from scipy.spatial import cKDTree

    p = np.asarray(positions_m, dtype=np.float64)[:, :2]
    out = np.zeros(p.shape[0], dtype=bool)
    valid = np.flatnonzero(np.all(np.isfinite(p), axis=1))
    if valid.size < 2:
        return out
    tree = cKDTree(p[valid])
    # strictly closer than radius_m, as the constraint truth (evaluation.truth) judges a pair
    radius = np.nextafter(float(radius_m), 0.0)
    for row, neighbours in zip(valid, tree.query_ball_point(p[valid], r=radius)):
        out[row] = bool(neighbours) and int(valid[min(neighbours)]) < row - exclusion_frames
    return out


def revisit_recall(
    positions_m: np.ndarray,
    query_frames: Sequence[int],
    is_true: Sequence[bool | None],
    accepted_ids: Iterable[int],
    *,
    radius_m: float,
    exclusion_frames: int,
) -> RevisitRecall:
    """Count the revisits of ``positions_m`` proposed and closed by a run's constraints.

    Args:
        positions_m: ``(N, 2)`` ground truth of the frames replayed (frame ``i`` is row ``i``).
        query_frames: the query frame of each constraint, by constraint id.
        is_true: the truth of each constraint, by constraint id (``None`` = unknown, not true).
        accepted_ids: ids of the accepted constraints.
    """
    revisit = revisit_frames(positions_m, radius_m=radius_m, exclusion_frames=exclusion_frames)
    accepted = set(int(i) for i in accepted_ids)
    proposed: set[int] = set()
    closed: set[int] = set()
    for cid, (q, true) in enumerate(zip(query_frames, is_true)):
        if true is True and 0 <= q < revisit.size and revisit[q]:
            proposed.add(int(q))
            if cid in accepted:
                closed.add(int(q))
    return RevisitRecall(int(revisit.sum()), len(proposed), len(closed), float(radius_m), int(exclusion_frames))
