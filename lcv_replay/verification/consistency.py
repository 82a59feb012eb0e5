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


def left_out_d2(residuals: np.ndarray, loop_covariances: np.ndarray, held_covariance: np.ndarray) -> float | None:
    """The innovation of ``L`` loops under the graph without them (linear-Gaussian), from the
    graph that holds them: ``rᵀ (R - Σ)⁻¹ r`` with ``r`` their ``(L, 3)`` residuals stacked, ``R``
    their ``(L, 3, 3)`` covariances block-diagonal and ``Σ`` the ``(3L, 3L)`` joint covariance of
    their relative poses under the graph that holds them. ``None`` where ``R - Σ`` is singular:
    they are the only evidence for their relative poses, so there is nothing to test them against.
    """
    residuals = np.asarray(residuals, dtype=np.float64).reshape(-1)
    loop_covariances = np.asarray(loop_covariances, dtype=np.float64)
    remaining = -np.asarray(held_covariance, dtype=np.float64)
    for k, block in enumerate(loop_covariances):
        remaining[3 * k : 3 * k + 3, 3 * k : 3 * k + 3] += block
    remaining = 0.5 * (remaining + remaining.T)
    if np.min(np.linalg.eigvalsh(remaining)) <= 1e-9 * float(np.trace(loop_covariances.sum(axis=0))):
        return None
    return float(residuals @ np.linalg.solve(remaining, residuals))


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


# ----------------------------------------------------------------------------------------------
# Pairwise consistency of nearby loops (PCM's test on short cycles) and clusters (ilv+)
# ----------------------------------------------------------------------------------------------


def _segment(chain, a: np.ndarray, b: np.ndarray, prefix: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Odometry ``O_a⁻¹ O_b`` ``(K, 3)`` and its covariance ``(K, 3, 3)`` (right perturbation) for
    any order of ``a`` and ``b`` (zero for ``a == b``); ``prefix`` as in
    :meth:`~lcv_replay.verification.measurements.OdometryChain.segment_covariance`."""
    from lcv_replay import se2

    odom = chain.poses
    rel = se2.between(odom[a], odom[b])
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    cov = np.zeros((len(a), 3, 3))
    moving = lo < hi
    if moving.any():
        cov[moving] = chain.segment_covariance(lo[moving], hi[moving], prefix)
    backwards = b < a  # O_a⁻¹ O_b = (O_b⁻¹ O_a)⁻¹: right perturbation Exp(-Ad(O_b⁻¹ O_a) ε)
    if backwards.any():
        ad = se2.adjoint(se2.between(odom[b[backwards]], odom[a[backwards]]))
        cov[backwards] = ad @ cov[backwards] @ np.swapaxes(ad, -1, -2)
    return rel, cov


class Cycles:
    """The short cycles ``m1 -> q1 -> q2 -> m2 -> m1`` of loop pairs (PCM, Mangelson et al. 2018),
    closed by the odometry between their ends.

    With ``Z_i = x_{m_i}⁻¹ x_{q_i}``, ``A = x_{m1}⁻¹ x_{m2}`` and ``B = x_{q1}⁻¹ x_{q2}``,
    ``Z_2 = A⁻¹ Z_1 B`` holds exactly; its error with the measured ``Ẑ1, Ẑ2`` and odometry
    ``Â, B̂`` is ``e = Log(Ẑ2⁻¹ Â⁻¹ Ẑ1 B̂)``, with covariance (right perturbations, first order)
    ``Ad(B⁻¹) R1 Ad(B⁻¹)ᵀ + Ad(B⁻¹Z1⁻¹A) Σ_A Ad(·)ᵀ + Σ_B + R2``. Nothing but the two loops and the
    odometry between their ends enters, so for nearby loops the test is tight and cheap.

    Args:
        chain: the :class:`~lcv_replay.verification.measurements.OdometryChain`.
        match, query: ``(m1, m2)`` and ``(q1, q2)``, each ``(K,)`` frame indices.
        measured: ``(Ẑ1, Ẑ2)``, each ``(K, 3)`` ``T_match_query``.
    """

    def __init__(self, chain, match, query, measured):
        from lcv_replay import se2

        self.chain = chain
        self.m1, self.m2 = (np.asarray(v, dtype=np.int64) for v in match)
        self.q1, self.q2 = (np.asarray(v, dtype=np.int64) for v in query)
        z1, z2 = (np.asarray(v, dtype=np.float64).reshape(-1, 3) for v in measured)
        odom = chain.poses
        a = se2.between(odom[self.m1], odom[self.m2])
        b = se2.between(odom[self.q1], odom[self.q2])
        predicted = se2.compose(se2.between(a, z1), b)  # A⁻¹ Z1 B
        self.error = se2.logmap(se2.between(z2, predicted))  # (K, 3)
        self._ad_r1 = se2.adjoint_inverse(b)  # Ad(B⁻¹)
        self._ad_a = se2.adjoint_inverse(predicted)  # Ad(B⁻¹ Z1⁻¹ A) = Ad((A⁻¹ Z1 B)⁻¹)

    def __len__(self) -> int:
        return len(self.error)

    @property
    def first_loop_transport(self) -> np.ndarray:
        """``(K, 3, 3)`` ``Ad(B⁻¹)``, which carries the first loop's noise into the error."""
        return self._ad_r1

    def covariance(self, loops: tuple[np.ndarray, np.ndarray] | None, odometry_prefix: np.ndarray | None) -> np.ndarray:
        """``(K, 3, 3)`` covariance of the errors for loop covariances ``(R1, R2)`` (each
        ``(K, 3, 3)``, or ``None`` for exact loops) and the odometry step covariance whose prefix
        sums are ``odometry_prefix`` (``None``: the chain's own; see
        :func:`~lcv_replay.verification.measurements.random_walk_prefix`). Linear in both."""
        _, cov_a = _segment(self.chain, self.m1, self.m2, odometry_prefix)
        _, cov_b = _segment(self.chain, self.q1, self.q2, odometry_prefix)
        t = np.swapaxes
        cov = self._ad_a @ cov_a @ t(self._ad_a, -1, -2) + cov_b
        if loops is not None:
            r1, r2 = loops
            cov = cov + self._ad_r1 @ r1 @ t(self._ad_r1, -1, -2) + r2
        return cov

    def d2(self, loops: tuple[np.ndarray, np.ndarray], odometry_prefix: np.ndarray | None = None) -> np.ndarray:
        """``(K,)`` ``eᵀ C⁻¹ e``: a 3-dof chi-square when both loops are true and the covariances right."""
        if len(self) == 0:
            return np.zeros(0)
        return mahalanobis_d2(self.error, self.covariance(loops, odometry_prefix))


def cycle_d2(
    chain,
    match: tuple[np.ndarray, np.ndarray],
    query: tuple[np.ndarray, np.ndarray],
    measured: tuple[np.ndarray, np.ndarray],
    covariance: tuple[np.ndarray, np.ndarray],
) -> np.ndarray:
    """Pairwise consistency of loop pairs over their short cycle (:class:`Cycles`), with loop
    covariances ``(R1, R2)`` and the chain's odometry noise: ``(K,)`` chi-square statistics."""
    if len(np.asarray(match[0])) == 0:
        return np.zeros(0)
    return Cycles(chain, match, query, measured).d2(covariance)


def neighbour_pairs(match: np.ndarray, query: np.ndarray, span_frames: int) -> np.ndarray:
    """``(P, 2)`` index pairs ``(i, j)``, ``i < j`` in the given order, of loops whose query frames
    and match frames both lie within ``span_frames`` of each other (runs of loops from one
    revisit, or one group of Vertigo outliers). Cost ``O(K log K + P)``."""
    match = np.asarray(match, dtype=np.int64)
    query = np.asarray(query, dtype=np.int64)
    order = np.argsort(query, kind="stable")
    q_sorted = query[order]
    pairs = []
    for k in range(len(order)):
        end = np.searchsorted(q_sorted, q_sorted[k] + span_frames, side="right")
        if end > k + 1:
            others = order[k + 1 : end]
            near = others[np.abs(match[others] - match[order[k]]) <= span_frames]
            pairs.extend((min(order[k], o), max(order[k], o)) for o in near.tolist())
    return np.asarray(sorted(pairs), dtype=np.int64).reshape(-1, 2)


def shared_end_pairs(match: np.ndarray, query: np.ndarray, span_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of loops of two passes over one place: one end of each (match or query frame) within
    ``span_frames`` of the other's, their other ends farther apart than that (not one revisit's
    run, :func:`neighbour_pairs`), and each loop's own two frames farther apart than that (a loop
    between nearby frames measures the odometry's stretch, not another pass). Returns
    ``(pairs (P, 2), shared_is_query (P, 2))``: the loop indices ``(i, j)``, ``i != j``, each
    unordered pair once per pair of shared ends, and whether each loop's shared end is its query
    frame (else its match frame). Cost ``O(K log K + P)``."""
    match = np.asarray(match, dtype=np.int64)
    query = np.asarray(query, dtype=np.int64)
    k = len(match)
    ends = np.concatenate([match, query])
    owner = np.tile(np.arange(k), 2)
    is_query = np.repeat([False, True], k)
    order = np.argsort(ends, kind="stable")
    within = np.searchsorted(ends[order], ends[order] + span_frames, side="right") - np.arange(2 * k) - 1
    first = np.repeat(np.arange(2 * k), within)  # each sorted end with every later one within the span
    second = first + 1 + np.arange(int(within.sum())) - np.repeat(np.cumsum(within) - within, within)
    a, b = order[first], order[second]
    other_a = np.where(is_query[a], match[owner[a]], query[owner[a]])
    other_b = np.where(is_query[b], match[owner[b]], query[owner[b]])
    revisit = np.abs(query - match) > span_frames
    keep = (owner[a] != owner[b]) & (np.abs(other_a - other_b) > span_frames) & revisit[owner[a]] & revisit[owner[b]]
    a, b = a[keep], b[keep]
    return np.stack([owner[a], owner[b]], axis=1).reshape(-1, 2), np.stack([is_query[a], is_query[b]], axis=1).reshape(-1, 2)


def connected_labels(count: int, edges: np.ndarray) -> np.ndarray:
    """``(count,)`` component labels (0, 1, ... in order of first member) of an undirected graph
    with ``(E, 2)`` ``edges`` (union-find)."""
    parent = np.arange(count)

    def find(i: int) -> int:
        root = i
        while parent[root] != root:
            root = parent[root]
        while parent[i] != root:
            parent[i], i = root, parent[i]
        return root

    for a, b in np.asarray(edges, dtype=np.int64).reshape(-1, 2).tolist():
        ra, rb = find(a), find(b)
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)
    roots = np.array([find(i) for i in range(count)], dtype=np.int64)
    _, labels = np.unique(roots, return_inverse=True)
    return labels.astype(np.int64)


def short_cycle_runs(
    chain, match: np.ndarray, query: np.ndarray, measured: np.ndarray, *, span_frames: int, gap_factor: float, min_cycles: int = 20
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
    """The loops joined in runs by their short cycles, on the scale of their own gaps: pairs
    within ``span_frames`` (:func:`neighbour_pairs`) agree where their cycle's gap (the length of
    its translation error, :class:`Cycles`, in metres) is below ``gap_factor`` times the median
    gap of all of them. Returns ``(labels, pairs, agree, bound)``: ``(K,)`` component labels
    (:func:`connected_labels`), the ``(P, 2)`` pairs, ``(P,)`` bool, and the bound in metres;
    ``None`` where fewer than ``min_cycles`` pairs give no scale."""
    pairs = neighbour_pairs(match, query, span_frames)
    if len(pairs) < min_cycles:
        return None
    i, j = pairs[:, 0], pairs[:, 1]
    error = Cycles(chain, (match[i], match[j]), (query[i], query[j]), (measured[i], measured[j])).error
    gap = np.hypot(error[:, 0], error[:, 1])
    bound = gap_factor * float(np.median(gap))
    agree = gap < bound
    return connected_labels(len(match), pairs[agree]), pairs, agree, bound

