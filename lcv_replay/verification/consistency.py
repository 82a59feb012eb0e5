"""Consistency of loop constraints with trajectory hypotheses, and the incremental lookup table.

Paper (Tanaka, SII 2016, sec. II-A): a constraint ``z = (t, t')`` is consistent with hypothesis
``h`` when ``||p(t, h) - p(t', h)|| < T_p``; the score of ``h`` is the number of constraints of the
whole history consistent with it. :func:`position_consistent` is that test; ``ilv+`` replaces it
with a Mahalanobis test (:func:`mahalanobis_d2`, see :mod:`lcv_replay.verification.ilv`).

The :class:`ConsistencyTable` holds the hypotheses × constraints booleans. It is append-only by
construction: a hypothesis' trajectory never changes once it has been optimised (frames added later
extend it by odometry from its last optimised frame, which changes none of its earlier poses), and
a constraint only references frames that existed when it arrived. So an entry ``(h, c)`` depends on
nothing that can change after both exist, and is computed exactly once:

* a new constraint adds a column, computed for every kept hypothesis;
* a new hypothesis adds a row, computed for every constraint of the history;
* pruning a hypothesis frees its row; nothing else is ever recomputed, unless the test itself
  changes (``ilv+`` calibrates its chi-square gate to the data once per window, and then rewrites
  the kept rows: :meth:`ConsistencyTable.rewrite`).

Space is ``O(max_hypotheses × C)`` booleans, and each score is kept as a running row sum.
"""

from __future__ import annotations

from typing import Iterable, Sequence

import numpy as np

from lcv_replay.errors import VerificationError


def position_consistent(query_poses: np.ndarray, match_poses: np.ndarray, radius_m: float) -> np.ndarray:
    """The paper's test (sec. II-A): ``||p(t) - p(t')|| < T_p``.

    Args:
        query_poses, match_poses: ``(K, 3)`` (or ``(K, 2)``) poses of the two frames of ``K``
            constraints under one hypothesis.
        radius_m: ``T_p``.

    Returns:
        ``(K,)`` bool.
    """
    q = np.asarray(query_poses, dtype=np.float64)
    m = np.asarray(match_poses, dtype=np.float64)
    if q.shape != m.shape or q.ndim != 2 or q.shape[1] < 2:
        raise VerificationError(f"query and match poses must be two (K, 2|3) arrays, got {q.shape} and {m.shape}")
    return np.hypot(q[:, 0] - m[:, 0], q[:, 1] - m[:, 1]) < radius_m


def mahalanobis_d2(residuals: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """``rᵀ C⁻¹ r`` for ``(K, 3)`` residuals and ``(K, 3, 3)`` covariances -> ``(K,)``."""
    residuals = np.asarray(residuals, dtype=np.float64)
    if len(residuals) == 0:
        return np.zeros(0)
    solved = np.linalg.solve(covariances, residuals[..., None])[..., 0]
    return np.einsum("ki,ki->k", residuals, solved)


class ConsistencyTable:
    """The hypotheses × constraints lookup table (see the module docstring).

    Rows are hypothesis ids (any ints), columns are constraint ids ``0..C-1`` in arrival order.
    Each entry holds whether the constraint is consistent with the hypothesis and, optionally, a
    float "support" (``ilv+`` ranks by its sum; ``ilv`` leaves it 0). Both row sums are kept
    running. Storage grows geometrically; a pruned hypothesis' row slot is reused.

    Attributes:
        entries_computed: total number of entries ever written (each ``(h, c)`` once).
    """

    def __init__(self) -> None:
        self._data = np.zeros((8, 64), dtype=bool)
        self._support = np.zeros((8, 64), dtype=np.float64)
        self._slot: dict[int, int] = {}
        self._free: list[int] = []
        self._score: dict[int, int] = {}
        self._support_sum: dict[int, float] = {}
        self._num_columns = 0
        self.entries_computed = 0

    # ------------------------------------------------------------------ queries
    @property
    def num_constraints(self) -> int:
        return self._num_columns

    @property
    def hypothesis_ids(self) -> list[int]:
        """Kept hypotheses, in insertion order."""
        return list(self._slot)

    def __len__(self) -> int:
        return len(self._slot)

    def __contains__(self, hypothesis_id: int) -> bool:
        return hypothesis_id in self._slot

    def row(self, hypothesis_id: int) -> np.ndarray:
        """``(C,)`` bool copy of one hypothesis' row."""
        return self._data[self._slot_of(hypothesis_id), : self._num_columns].copy()

    def score(self, hypothesis_id: int) -> int:
        """Number of constraints consistent with the hypothesis (its running row sum)."""
        self._slot_of(hypothesis_id)
        return self._score[hypothesis_id]

    def support(self, hypothesis_id: int) -> float:
        """Sum of the hypothesis' support entries (running)."""
        self._slot_of(hypothesis_id)
        return self._support_sum[hypothesis_id]

    def matrix(self, hypothesis_ids: Sequence[int]) -> np.ndarray:
        """``(H, C)`` bool rows of ``hypothesis_ids`` in that order."""
        slots = [self._slot_of(h) for h in hypothesis_ids]
        return self._data[slots, : self._num_columns].copy()

    def support_matrix(self, hypothesis_ids: Sequence[int]) -> np.ndarray:
        """``(H, C)`` float support of ``hypothesis_ids`` in that order."""
        slots = [self._slot_of(h) for h in hypothesis_ids]
        return self._support[slots, : self._num_columns].copy()

    # ------------------------------------------------------------------ updates
    def add_hypothesis(self, hypothesis_id: int, row: np.ndarray, support: np.ndarray | None = None) -> None:
        """Add a row: ``row`` is ``(C,)`` bool over every constraint of the history, ``support``
        ``(C,)`` float or ``None`` (zeros)."""
        if hypothesis_id in self._slot:
            raise VerificationError(f"hypothesis {hypothesis_id} is already in the consistency table")
        row, support = self._checked_row(row, support)
        if self._free:
            slot = self._free.pop()
        else:
            slot = len(self._slot)
            if slot >= self._data.shape[0]:
                self._resize(rows=2 * self._data.shape[0])
        self._data[slot, : self._num_columns] = row
        self._data[slot, self._num_columns :] = False
        self._support[slot, : self._num_columns] = support
        self._support[slot, self._num_columns :] = 0.0
        self._slot[hypothesis_id] = slot
        self._score[hypothesis_id] = int(row.sum())
        self._support_sum[hypothesis_id] = float(support.sum())
        self.entries_computed += row.size

    def add_constraints(self, hypothesis_ids: Sequence[int], block: np.ndarray, support: np.ndarray | None = None) -> None:
        """Add ``k`` columns (the next constraint ids): ``block`` is ``(H, k)`` bool (``support``
        ``(H, k)`` float or ``None``), one row per id of ``hypothesis_ids``, which must be exactly
        the kept hypotheses."""
        block = np.asarray(block, dtype=bool)
        support = np.zeros(block.shape) if support is None else np.asarray(support, dtype=np.float64)
        if support.shape != block.shape:
            raise VerificationError(f"support block has shape {support.shape}, expected {block.shape}")
        if set(hypothesis_ids) != set(self._slot) or len(hypothesis_ids) != len(self._slot):
            raise VerificationError("new constraint columns must cover exactly the kept hypotheses")
        if block.ndim != 2 or block.shape[0] != len(hypothesis_ids):
            raise VerificationError(f"column block has shape {block.shape}, expected ({len(hypothesis_ids)}, k)")
        k = block.shape[1]
        if self._num_columns + k > self._data.shape[1]:
            self._resize(columns=max(2 * self._data.shape[1], self._num_columns + k))
        for h, values, weights in zip(hypothesis_ids, block, support):
            self._data[self._slot[h], self._num_columns : self._num_columns + k] = values
            self._support[self._slot[h], self._num_columns : self._num_columns + k] = weights
            self._score[h] += int(values.sum())
            self._support_sum[h] += float(weights.sum())
        self._num_columns += k
        self.entries_computed += block.size

    def rewrite(self, hypothesis_id: int, row: np.ndarray, support: np.ndarray | None = None) -> None:
        """Replace a kept hypothesis' row (its test changed: ``ilv+`` recalibrated its gate)."""
        slot = self._slot_of(hypothesis_id)
        row, support = self._checked_row(row, support)
        self._data[slot, : self._num_columns] = row
        self._support[slot, : self._num_columns] = support
        self._score[hypothesis_id] = int(row.sum())
        self._support_sum[hypothesis_id] = float(support.sum())
        self.entries_computed += row.size

    def remove(self, hypothesis_ids: Iterable[int]) -> None:
        """Drop rows (pruned hypotheses); their slots are reused."""
        for h in hypothesis_ids:
            slot = self._slot.pop(self._require(h))
            del self._score[h]
            del self._support_sum[h]
            self._free.append(slot)

    # ------------------------------------------------------------------ internals
    def _checked_row(self, row: np.ndarray, support: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        row = np.asarray(row, dtype=bool)
        if row.shape != (self._num_columns,):
            raise VerificationError(f"row has shape {row.shape}, expected ({self._num_columns},)")
        support = np.zeros(row.shape) if support is None else np.asarray(support, dtype=np.float64)
        if support.shape != row.shape:
            raise VerificationError(f"support has shape {support.shape}, expected {row.shape}")
        return row, support

    def _require(self, hypothesis_id: int) -> int:
        if hypothesis_id not in self._slot:
            raise VerificationError(f"hypothesis {hypothesis_id} is not in the consistency table")
        return hypothesis_id

    def _slot_of(self, hypothesis_id: int) -> int:
        return self._slot[self._require(hypothesis_id)]

    def _resize(self, *, rows: int | None = None, columns: int | None = None) -> None:
        r = rows or self._data.shape[0]
        c = columns or self._data.shape[1]
        data = np.zeros((r, c), dtype=bool)
        data[: self._data.shape[0], : self._data.shape[1]] = self._data
        self._data = data
        support = np.zeros((r, c), dtype=np.float64)
        support[: self._support.shape[0], : self._support.shape[1]] = self._support
        self._support = support
