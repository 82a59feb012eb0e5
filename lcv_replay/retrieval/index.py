"""Incremental code index: Hamming prefilter plus L2 re-rank (paper sec. II-B, steps 4 and 5).

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
"""

from __future__ import annotations

import itertools
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


def rerank_l2(vectors: np.ndarray, rows: np.ndarray, frames: np.ndarray, query: np.ndarray, top_k: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``top_k`` of ``rows`` closest to ``query`` in L2.

    Args:
        vectors: ``(N, K)`` library vectors; rows index into it.
        rows: ``(M,)`` candidate rows.
        frames: ``(N,)`` frame index of each row, the tie-breaker (earlier frame first).
        query: ``(K,)`` query vector.

    Returns:
        ``(rows, distances)``, each ``(min(M, top_k),)``, by increasing distance.
    """
    if rows.size == 0:
        return rows, np.zeros(0, dtype=np.float32)
    diff = vectors[rows] - query
    d2 = np.einsum("ij,ij->i", diff, diff)
    order = np.lexsort((frames[rows], d2))[:top_k]
    return rows[order], np.sqrt(np.maximum(d2[order], 0.0)).astype(np.float32)


class CodeIndex:
    """A growing library of ``(frame index, packed code, re-rank vector)`` triples.

    Args:
        code_bits: ``N_b``, bits per code.
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
        if vector_dim < 1:
            raise RetrievalError(f"vector_dim = {vector_dim} must be >= 1")
        self.code_bits = code_bits
        self.vector_dim = vector_dim
        self.hamming_threshold = hamming_threshold
        self._dtype = code_dtype(code_bits)
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
        capacity = max(1, initial_capacity)
        self._size = 0
        self._frames = np.empty(capacity, dtype=np.int64)
        self._codes = np.empty(capacity, dtype=self._dtype)
        self._vectors = np.empty((capacity, vector_dim), dtype=np.float32)
        if strategy == "table":
            self._masks = probe_masks(code_bits, hamming_threshold)
            self._occupied = np.zeros(1 << code_bits, dtype=np.uint8)  # 1 MiB at 20 bits: stays in cache
            self._buckets: dict[int, list[int]] = {}

    def __len__(self) -> int:
        return self._size

    @property
    def frames(self) -> np.ndarray:
        """``(N,)`` int64 frame indices, increasing (a read-only view)."""
        return _readonly(self._frames[: self._size])

    @property
    def codes(self) -> np.ndarray:
        """``(N,)`` packed codes (a read-only view)."""
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
        self._codes[row] = code
        self._vectors[row] = vector
        self._size += 1
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
        eligible = int(np.searchsorted(self._frames[: self._size], max_frame_index, side="right"))
        rows = self._prefilter(int(code), eligible)
        frames = self._frames[: self._size]
        top_rows, l2 = rerank_l2(self._vectors, rows, frames, vector, top_k)
        hamming = hamming_distances(self._codes[top_rows], int(code)).astype(np.int64)
        return SearchResult(frames=frames[top_rows].copy(), l2_distances=l2, hamming=hamming, prefilter_size=int(rows.size))

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

    def _grow(self) -> None:
        capacity = 2 * self._frames.shape[0]
        self._frames = _resized(self._frames, capacity)
        self._codes = _resized(self._codes, capacity)
        self._vectors = _resized(self._vectors, capacity)


def _resized(array: np.ndarray, capacity: int) -> np.ndarray:
    out = np.empty((capacity, *array.shape[1:]), dtype=array.dtype)
    out[: array.shape[0]] = array
    return out


def _readonly(view: np.ndarray) -> np.ndarray:
    view = view.view()
    view.flags.writeable = False
    return view
