"""Incremental code indexes: binary prefilter plus L2 re-rank (paper sec. II-B, steps 4 and 5).

Two indexes share one growing library (:class:`CodeIndex` for ``retrieval.mode = "paper"``,
:class:`RankedIndex` for the default ``"ranked"``); they differ in which frames reach the re-rank.

The library grows one frame at a time. Its arrays (frame indices, packed codes, re-rank vectors)
are preallocated and doubled when full, so ``add`` is amortised O(1) and a query never copies the
library. Frames must be added in increasing frame order; the frames eligible for a query
(``query_frame - frame > Δt``) are then a prefix of the library.

Two prefilter strategies give identical results (tests check both against brute force):

* ``"scan"``: vectorised ``popcount(codes ^ q) <= T_b`` over the eligible prefix (numpy 2's
  ``np.bitwise_count``). Linear in the library size but tiny per frame (4-byte codes for
  ``N_b <= 32``).
* ``"table"``: multi-probe hashing. Every code is a bucket of a ``2^N_b`` table; a query probes the
  ``sum_{k<=T_b} C(N_b, k)`` codes within radius ``T_b`` (1351 for the paper's 20 bits and
  ``T_b = 3``), so its probing cost (~12 µs) does not grow with the library, only with the number
  of hits. For ``N_b <= 24`` and at most 8192 probes.

``"auto"`` picks ``"scan"``: measured up to 100k frames (``lcv-replay bench retrieval-index``) the
scan was faster at every size (the prefilter itself costs 4 / 9 / 65 µs at 1k / 10k / 100k frames,
and the re-rank of the ~N * 1351 / 2^20 hits dominates at 100k), and it has no table to hold.

**Ranked** (:class:`RankedIndex`, not in the paper): the ``M`` eligible frames nearest to the query
in Hamming distance, ties to the earlier frame, go to the re-rank, however far they are. This is
an exact Hamming k-nearest-neighbour search, so the re-rank always sees ``min(M, eligible)``
frames: the prefilter can no longer starve the re-rank (the paper's 20-bit, ``T_b = 3`` ball holds
about one frame per query on the RTAB-Map corridor), and the re-rank costs the same at any library
size. Two engines give identical results (tests check both against brute force):

* ``"faiss"``: ``faiss.IndexBinaryFlat`` (SIMD popcount, k-selection in C++), fed with frames as
  they become eligible; it orders by ``(distance, frame)`` like the numpy engine;
* ``"numpy"``: ``np.bitwise_count`` over the eligible prefix, then a counting selection (the radius
  that holds ``M`` frames, ties at that radius to the earlier frames).

``"auto"`` is faiss where it is installed. Both are linear scans with a small slope; faiss's
approximate indexes (HNSW, multi-index hashing) were measured and not chosen (docs/retrieval.md).
"""

from __future__ import annotations

import itertools
import logging
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from lcv_replay.errors import RetrievalError
from lcv_replay.retrieval.hashing import code_dtype, hamming_distances

Strategy = Literal["auto", "scan", "table"]

_TABLE_MAX_BITS = 24
_TABLE_MAX_PROBES = 8192


@dataclass(frozen=True)
class SearchResult:
    """The answer to one query, best first.

    Attributes:
        frames: ``(M,)`` int64 library frame indices, ``M <= top_k``, by increasing L2 distance
            (ties broken by frame index).
        l2_distances: ``(M,)`` float32 L2 distances between the query's and the frames' vectors.
        hamming: ``(M,)`` int64 Hamming distances between the codes.
        prefilter_size: how many eligible library frames passed the Hamming prefilter.
    """

    frames: np.ndarray
    l2_distances: np.ndarray
    hamming: np.ndarray
    prefilter_size: int


def probe_masks(code_bits: int, radius: int) -> np.ndarray:
    """``(P,)`` XOR masks of every bit pattern with at most ``radius`` of ``code_bits`` bits set."""
    dtype = code_dtype(code_bits)
    masks = [0]
    for k in range(1, radius + 1):
        masks.extend(sum(1 << b for b in bits) for bits in itertools.combinations(range(code_bits), k))
    return np.array(masks, dtype=dtype)


def probe_count(code_bits: int, radius: int) -> int:
    """Number of codes within Hamming distance ``radius``: ``sum_{k<=radius} C(code_bits, k)``."""
    return sum(math.comb(code_bits, k) for k in range(radius + 1))


def prefilter_scan(codes: np.ndarray, code: int, threshold: int) -> np.ndarray:
    """Rows of ``(N,)`` packed ``codes`` within Hamming distance ``threshold`` of ``code`` (sorted)."""
    return np.flatnonzero(hamming_distances(codes, code) <= threshold)


def rerank_l2_order(
    vectors: np.ndarray, rows: np.ndarray, frames: np.ndarray, query: np.ndarray, top_k: int, *, sq_norms: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The ``top_k`` of ``rows`` closest to ``query`` in L2.

    Args:
        vectors: ``(N, K)`` library vectors; rows index into it.
        rows: ``(M,)`` candidate rows.
        frames: ``(N,)`` frame index of each row, the tie-breaker (earlier frame first).
        query: ``(K,)`` query vector.
        sq_norms: ``(N,)`` squared norms of ``vectors``: when given, ``d^2 = |x|^2 + |q|^2 - 2 x.q``
            (one matrix-vector product, about 1.6x faster for M = 100 rows of 1904-D than the
            difference form the paper mode keeps, bit for bit).

    Returns:
        ``(order, distances)``, each ``(min(M, top_k),)``: positions in ``rows`` by increasing
        distance, and the distances.
    """
    if rows.size == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.float32)
    if sq_norms is not None:
        d2 = np.maximum(sq_norms[rows] + np.float32(query @ query) - 2.0 * (vectors[rows] @ query), 0.0)
    else:
        diff = vectors[rows] - query
        d2 = np.einsum("ij,ij->i", diff, diff)
    order = np.lexsort((frames[rows], d2))[:top_k]
    return order, np.sqrt(np.maximum(d2[order], 0.0)).astype(np.float32)


class _Library:
    """The growing library both indexes search: frame indices, codes and re-rank vectors.

    Args:
        code_bits: bits per code.
        code_words: ``0`` to store each code as one unsigned integer of :func:`code_dtype`
            (``<= 64`` bits), else the number of uint64 words per code (bit ``k`` of the code is bit
            ``k % 64`` of word ``k // 64``).
        vector_dim: dimension of the re-rank vectors.
        initial_capacity: rows preallocated before the first doubling.
    """

    def __init__(self, *, code_bits: int, code_words: int, vector_dim: int, initial_capacity: int):
        if vector_dim < 1:
            raise RetrievalError(f"vector_dim = {vector_dim} must be >= 1")
        self.code_bits = code_bits
        self.vector_dim = vector_dim
        self._words = code_words
        self._dtype = code_dtype(code_bits) if code_words == 0 else np.dtype(np.uint64)
        capacity = max(1, initial_capacity)
        self._size = 0
        self._frames = np.empty(capacity, dtype=np.int64)
        self._codes = np.empty((capacity, code_words) if code_words else capacity, dtype=self._dtype)
        self._vectors = np.empty((capacity, vector_dim), dtype=np.float32)
        self._sq_norms = np.empty(capacity, dtype=np.float32)

    def __len__(self) -> int:
        return self._size

    @property
    def frames(self) -> np.ndarray:
        """``(N,)`` int64 frame indices, increasing (a read-only view)."""
        return _readonly(self._frames[: self._size])

    @property
    def codes(self) -> np.ndarray:
        """``(N,)`` packed codes, or ``(N, W)`` uint64 words (a read-only view)."""
        return _readonly(self._codes[: self._size])

    @property
    def vectors(self) -> np.ndarray:
        """``(N, K)`` float32 re-rank vectors (a read-only view)."""
        return _readonly(self._vectors[: self._size])

    def add(self, frame_index: int, code: int, vector: np.ndarray) -> None:
        """Append one frame; ``frame_index`` must exceed every frame already in the library."""
        vector = np.asarray(vector, dtype=np.float32).reshape(-1)
        if vector.shape[0] != self.vector_dim:
            raise RetrievalError(f"vector has {vector.shape[0]} dimensions, the index holds {self.vector_dim}")
        if self._size and frame_index <= self._frames[self._size - 1]:
            raise RetrievalError(
                f"frame {frame_index} added after frame {int(self._frames[self._size - 1])}",
                fix="add frames in increasing frame order",
            )
        code = int(code)
        if code < 0 or code >> self.code_bits:
            raise RetrievalError(f"code {code:#x} does not fit in {self.code_bits} bits")
        if self._size == self._frames.shape[0]:
            self._grow()
        row = self._size
        self._frames[row] = frame_index
        self._codes[row] = code_words(code, self._words) if self._words else code
        self._vectors[row] = vector
        self._sq_norms[row] = vector @ vector
        self._size += 1
        self._added(row, code)

    def _added(self, row: int, code: int) -> None:
        """Hook for an index's own bookkeeping of a new row."""

    def _eligible_rows(self, max_frame_index: int) -> int:
        """How many library rows hold frames ``<= max_frame_index`` (they are a prefix)."""
        return int(np.searchsorted(self._frames[: self._size], max_frame_index, side="right"))

    def _result(self, rows: np.ndarray, hamming: np.ndarray, vector: np.ndarray, top_k: int, *, dot_form: bool = False) -> SearchResult:
        """Re-rank ``rows`` (with their Hamming distances) by L2 to ``vector``: the answer."""
        frames = self._frames[: self._size]
        order, l2 = rerank_l2_order(self._vectors, rows, frames, vector, top_k, sq_norms=self._sq_norms if dot_form else None)
        return SearchResult(
            frames=frames[rows[order]].copy(),
            l2_distances=l2,
            hamming=np.asarray(hamming, dtype=np.int64)[order],
            prefilter_size=int(rows.size),
        )

    def _grow(self) -> None:
        capacity = 2 * self._frames.shape[0]
        self._frames = _resized(self._frames, capacity)
        self._codes = _resized(self._codes, capacity)
        self._vectors = _resized(self._vectors, capacity)
        self._sq_norms = _resized(self._sq_norms, capacity)


class CodeIndex(_Library):
    """The paper's index: frames within Hamming ``T_b`` of the query, re-ranked by L2.

    Args:
        code_bits: ``N_b``, bits per code (at most 64).
        vector_dim: dimension of the re-rank vectors.
        hamming_threshold: ``T_b`` (the table strategy precomputes its probes for it).
        strategy: ``"auto"``, ``"scan"`` or ``"table"`` (see the module docstring).
        initial_capacity: rows preallocated before the first doubling.
    """

    def __init__(
        self,
        *,
        code_bits: int,
        vector_dim: int,
        hamming_threshold: int,
        strategy: Strategy = "auto",
        initial_capacity: int = 1024,
    ):
        super().__init__(code_bits=code_bits, code_words=0, vector_dim=vector_dim, initial_capacity=initial_capacity)
        self.hamming_threshold = hamming_threshold
        if strategy == "auto":
            strategy = "scan"
        if strategy == "table" and (code_bits > _TABLE_MAX_BITS or probe_count(code_bits, hamming_threshold) > _TABLE_MAX_PROBES):
            raise RetrievalError(
                f"the table strategy needs codes of at most {_TABLE_MAX_BITS} bits and at most {_TABLE_MAX_PROBES} probes, "
                f"got {code_bits} bits with T_b = {hamming_threshold}",
                fix="use strategy 'scan'",
            )
        if strategy not in ("scan", "table"):
            raise RetrievalError(f"unknown index strategy '{strategy}'", fix="use 'auto', 'scan' or 'table'")
        self.strategy: Literal["scan", "table"] = strategy
        if strategy == "table":
            self._masks = probe_masks(code_bits, hamming_threshold)
            self._occupied = np.zeros(1 << code_bits, dtype=np.uint8)  # 1 MiB at 20 bits: stays in cache
            self._buckets: dict[int, list[int]] = {}

    def _added(self, row: int, code: int) -> None:
        if self.strategy == "table":
            self._occupied[code] = 1
            self._buckets.setdefault(code, []).append(row)

    def search(
        self, code: int, vector: np.ndarray, *, max_frame_index: int, top_k: int
    ) -> SearchResult:
        """Frames ``<= max_frame_index`` within Hamming ``T_b`` of ``code``, re-ranked by L2.

        Args:
            code: the query's packed code.
            vector: ``(K,)`` the query's re-rank vector.
            max_frame_index: the last eligible frame (``query_frame - Δt - 1``).
            top_k: ``N_r``; fewer come back when fewer pass the prefilter.
        """
        vector = np.asarray(vector, dtype=np.float32).reshape(-1)
        rows, hamming = self.prefilter(code, max_frame_index=max_frame_index)
        return self._result(rows, hamming, vector, top_k)

    def prefilter(self, code: int, *, max_frame_index: int) -> tuple[np.ndarray, np.ndarray]:
        """The first stage alone: ``(rows, Hamming distances)`` of the frames within ``T_b``."""
        rows = self._prefilter(int(code), self._eligible_rows(max_frame_index))
        return rows, hamming_distances(self._codes[rows], int(code))

    def _prefilter(self, code: int, eligible: int) -> np.ndarray:
        if eligible == 0:
            return np.zeros(0, dtype=np.int64)
        if self.strategy == "scan":
            return prefilter_scan(self._codes[:eligible], code, self.hamming_threshold)
        probes = self._masks ^ self._dtype.type(code)
        hits = probes[self._occupied[probes] != 0]
        if hits.size == 0:
            return np.zeros(0, dtype=np.int64)
        rows = np.fromiter(
            itertools.chain.from_iterable(self._buckets[int(h)] for h in hits), dtype=np.int64
        )
        rows = rows[rows < eligible]
        rows.sort()
        return rows


class RankedIndex(_Library):
    """The improved index: the ``candidates`` Hamming-nearest eligible frames, re-ranked by L2.

    Args:
        code_bits: bits per code, a multiple of 8 (stored as ``ceil(code_bits / 64)`` uint64 words).
        vector_dim: dimension of the re-rank vectors.
        candidates: ``M``, frames passed to the re-rank (all eligible ones when fewer).
        engine: ``"auto"`` (faiss when installed), ``"faiss"`` or ``"numpy"`` (module docstring).
        initial_capacity: rows preallocated before the first doubling.
    """

    def __init__(
        self,
        *,
        code_bits: int,
        vector_dim: int,
        candidates: int,
        engine: Literal["auto", "faiss", "numpy"] = "auto",
        initial_capacity: int = 1024,
    ):
        if code_bits < 8 or code_bits % 8:
            raise RetrievalError(f"ranked codes must have a multiple of 8 bits, got {code_bits}", fix="use a multiple of 8, e.g. 128")
        if candidates < 1:
            raise RetrievalError(f"candidates = {candidates} must be >= 1")
        super().__init__(code_bits=code_bits, code_words=-(-code_bits // 64), vector_dim=vector_dim, initial_capacity=initial_capacity)
        self.candidates = candidates
        if engine == "auto":
            engine = "faiss" if faiss_available() else "numpy"
        if engine not in ("faiss", "numpy"):
            raise RetrievalError(f"unknown ranked index engine '{engine}'", fix="use 'auto', 'faiss' or 'numpy'")
        if engine == "faiss" and not faiss_available():
            raise RetrievalError("retrieval.ranked.index = 'faiss' needs the faiss-cpu package", fix="pip install faiss-cpu, or use 'numpy'")
        self.engine: Literal["faiss", "numpy"] = engine
        self._faiss = _FaissHamming(self._words) if engine == "faiss" else None

    def search(self, code: int, vector: np.ndarray, *, max_frame_index: int, top_k: int) -> SearchResult:
        """The ``M`` frames ``<= max_frame_index`` nearest to ``code`` in Hamming, re-ranked by L2.

        Args:
            code: the query's packed code (a Python int of ``code_bits`` bits).
            vector: ``(K,)`` the query's re-rank vector.
            max_frame_index: the last eligible frame (``query_frame - Δt - 1``).
            top_k: ``N_r``; fewer come back only when fewer frames are eligible.
        """
        vector = np.asarray(vector, dtype=np.float32).reshape(-1)
        rows, hamming = self.prefilter(code, max_frame_index=max_frame_index)
        return self._result(rows, hamming, vector, top_k, dot_form=True)

    def prefilter(self, code: int, *, max_frame_index: int) -> tuple[np.ndarray, np.ndarray]:
        """The first stage alone: ``(rows, Hamming distances)`` of the ``M`` nearest eligible frames."""
        eligible = self._eligible_rows(max_frame_index)
        query = code_words(int(code), self._words)
        if self._faiss is not None and self._faiss.can_search(eligible):
            self._faiss.extend(self._codes, eligible)
            return self._faiss.search(query, min(self.candidates, eligible))
        return hamming_nearest(self._codes[:eligible], query, self.candidates)


def code_words(code: int, words: int) -> np.ndarray:
    """A code (Python int) as ``(words,)`` uint64, least significant word first."""
    return np.array([(code >> (64 * w)) & 0xFFFF_FFFF_FFFF_FFFF for w in range(words)], dtype=np.uint64)


def hamming_nearest(codes: np.ndarray, query: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``count`` rows of ``codes`` nearest to ``query`` in Hamming distance, ties to the earlier row.

    Args:
        codes: ``(N, W)`` uint64 code words.
        query: ``(W,)`` uint64 words of the query.
        count: how many rows to return (all ``N`` when fewer).

    Returns:
        ``(rows, distances)``: ``(min(N, count),)`` int64 rows, sorted, and their int64 distances.
    """
    distances = np.zeros(codes.shape[0], dtype=np.uint8)  # <= 255 bits: one byte per distance
    for word in range(codes.shape[1]):  # per word: a contiguous-enough 1-D popcount, no 2-D reduction
        distances += np.bitwise_count(codes[:, word] ^ query[word])
    if distances.size <= count:
        return np.arange(distances.size, dtype=np.int64), distances.astype(np.int64)
    cumulative = np.cumsum(np.bincount(distances))
    radius = int(np.searchsorted(cumulative, count))  # smallest radius holding `count` rows
    inside = distances < radius
    ties = np.flatnonzero(distances == radius)[: count - (int(cumulative[radius - 1]) if radius else 0)]
    inside[ties] = True
    rows = np.flatnonzero(inside)
    return rows, distances[rows].astype(np.int64)


_FAISS_AVAILABLE: bool | None = None


def faiss_available() -> bool:
    """Whether ``faiss`` (the faiss-cpu package) imports."""
    global _FAISS_AVAILABLE
    if _FAISS_AVAILABLE is None:
        logging.getLogger("faiss.loader").setLevel(logging.WARNING)  # its INFO lines name CPU builds tried
        try:
            import faiss  # noqa: F401

            _FAISS_AVAILABLE = True
        except ImportError:
            _FAISS_AVAILABLE = False
    return _FAISS_AVAILABLE


class _FaissHamming:
    """An exact Hamming k-NN over a prefix of the library rows: ``faiss.IndexBinaryFlat``.

    Rows enter the faiss index only once they are eligible (frames are added in increasing order
    and queries come in increasing order), so every search covers exactly the rows it may see; a
    query for a smaller prefix than already indexed (a query back in time) is answered by the numpy
    scan instead (:meth:`can_search`).
    """

    def __init__(self, words: int):
        import faiss

        # One query at a time: faiss's OpenMP team costs ~0.7 ms of spin-up per search on 2 cores,
        # against ~3 µs single-threaded. faiss ships its own libgomp, so torch's threads keep theirs.
        faiss.omp_set_num_threads(1)
        self._index = faiss.IndexBinaryFlat(64 * words)
        self._words = words

    @property
    def rows(self) -> int:
        return int(self._index.ntotal)

    def can_search(self, eligible: int) -> bool:
        return eligible >= self.rows and eligible > 0

    def extend(self, codes: np.ndarray, eligible: int) -> None:
        """Add library rows ``[rows, eligible)`` from ``(N, W)`` uint64 ``codes``."""
        if eligible > self.rows:
            block = np.ascontiguousarray(codes[self.rows : eligible])
            self._index.add(block.view(np.uint8).reshape(block.shape[0], 8 * self._words))

    def search(self, query: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
        """``(rows, distances)`` of the ``count`` nearest rows, ordered by ``(distance, row)``."""
        q = np.ascontiguousarray(query, dtype=np.uint64).view(np.uint8).reshape(1, 8 * self._words)
        distances, labels = self._index.search(q, count)
        keep = labels[0] >= 0
        return labels[0][keep].astype(np.int64), distances[0][keep].astype(np.int64)


def _resized(array: np.ndarray, capacity: int) -> np.ndarray:
    out = np.empty((capacity, *array.shape[1:]), dtype=array.dtype)
    out[: array.shape[0]] = array
    return out


def _readonly(view: np.ndarray) -> np.ndarray:
    view = view.view()
    view.flags.writeable = False
    return view
