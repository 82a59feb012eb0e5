"""The stateful place-recognition front end: descriptor in, loop candidates out (paper sec. II-B).

Online use (the default, ``fit = "online"``)::

    retriever = Retriever(config, dim=backend.dim)
    for frame, descriptor in describe_frames(frames, backend, cache_key=key):
        if descriptor is None:           # unreadable image: skipped
            continue
        output = retriever.add(frame.index, descriptor)
        output.candidates                # up to N_r LoopCandidate, best first
        output.diagnostics               # None while warming up

No frame queries until the warm-up is over: the first ``warmup_frames = max(Δt, N_b + 1)``
descriptors fit PCA and the ITQ rotation (:mod:`lcv_replay.retrieval.hashing`), then enter the
index without querying (none of them could have an eligible match ``|t - t'| > Δt`` anyway when
``Δt >= N_b + 1``). After that each added frame first queries the index (frames ``t' < t - Δt``,
Hamming distance ``<= T_b``, top ``N_r`` by L2) and is then added to it.

Post-mortem use (``fit = "whole-log"``): call :meth:`Retriever.fit` with every descriptor of the
log first; then every :meth:`add` queries.

``similarity`` of a candidate is ``1 - d^2 / 2`` for re-rank distance ``d``: the cosine similarity
of the L2-normalised descriptors with ``rerank = "descriptor"`` (the default); with
``rerank = "pca"`` it is the same expression on the PCA vectors (monotone in ``d``, no longer a
cosine).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from lcv_replay.errors import RetrievalError
from lcv_replay.records import LoopCandidate
from lcv_replay.retrieval.config import RetrievalConfig
from lcv_replay.retrieval.hashing import BinaryHasher, fit_hasher
from lcv_replay.retrieval.index import CodeIndex

log = logging.getLogger(__name__)

SOURCE = "retrieval"


@dataclass(frozen=True)
class QueryDiagnostics:
    """What one query saw, for the Rerun timeline and post-mortems.

    Attributes:
        query_frame: the query's frame index.
        code: the query's packed binary code (bit ``k`` = ``1 << k``).
        code_bits: ``N_b``.
        prefilter_size: eligible library frames within Hamming ``T_b`` of the code.
        top: the re-ranked top ``N_r`` (the same records as the output's candidates).
        l2_distances: re-rank L2 distance of each entry of ``top``.
        library_size: library frames at query time (eligible or not).
        eligible_size: library frames with ``query_frame - frame > Δt``.
    """

    query_frame: int
    code: int
    code_bits: int
    prefilter_size: int
    top: tuple[LoopCandidate, ...]
    l2_distances: tuple[float, ...]
    library_size: int = 0
    eligible_size: int = 0

    @property
    def code_bit_string(self) -> str:
        """The code as ``N_b`` characters, most significant bit first (e.g. ``"0110..."``)."""
        return format(self.code, f"0{self.code_bits}b")


@dataclass(frozen=True)
class RetrievalOutput:
    """The result of :meth:`Retriever.add`: candidates (best first) and diagnostics.

    ``diagnostics`` is ``None`` while the retriever warms up (no query was made).
    """

    candidates: tuple[LoopCandidate, ...]
    diagnostics: QueryDiagnostics | None


_WARMING_UP = RetrievalOutput((), None)


class Retriever:
    """Incremental retrieval over a growing library of descriptors.

    Args:
        config: retrieval parameters (``N_r``, ``Δt``, ``N_b``, ``T_b``, PCA size, fit mode...).
        dim: descriptor length ``D`` of the backend.
    """

    def __init__(self, config: RetrievalConfig, *, dim: int):
        if dim < 1:
            raise RetrievalError(f"descriptor dimension {dim} must be >= 1")
        if dim < config.code_bits:
            raise RetrievalError(
                f"descriptors of {dim} dimensions cannot give {config.code_bits}-bit codes",
                fix="lower retrieval.code_bits",
            )
        self.config = config
        self.dim = dim
        self._hasher: BinaryHasher | None = None
        self._index: CodeIndex | None = None
        self._pending: list[tuple[int, np.ndarray]] = []  # warm-up frames (online fit)
        self._last_frame: int | None = None
        self.queries = 0

    # --- state ---------------------------------------------------------------------------------

    @property
    def fitted(self) -> bool:
        """Whether PCA and the code rotation are fitted (queries happen only then)."""
        return self._hasher is not None

    @property
    def hasher(self) -> BinaryHasher | None:
        return self._hasher

    @property
    def warmup_frames(self) -> int:
        """Descriptors needed before the online fit: ``max(Δt, N_b + 1)``."""
        return max(self.config.exclusion_frames, self.config.code_bits + 1)

    @property
    def warmup_remaining(self) -> int:
        """Descriptors still to add before the first query (0 once fitted)."""
        return 0 if self.fitted else self.warmup_frames - len(self._pending)

    @property
    def library_size(self) -> int:
        return 0 if self._index is None else len(self._index)

    def warmup_message(self) -> str | None:
        """A one-line explanation when the log ended before the warm-up, else ``None``."""
        if self.fitted:
            return None
        return (
            f"retrieval never queried: the log gave {len(self._pending)} usable images, fewer than the "
            f"{self.warmup_frames} needed to fit PCA and the {self.config.code_bits}-bit codes "
            f"(max(Δt = {self.config.exclusion_frames}, N_b + 1)); lower retrieval.exclusion_frames "
            "or use a longer log"
        )

    # --- fitting -------------------------------------------------------------------------------

    def fit(self, descriptors: np.ndarray) -> None:
        """Fit PCA and ITQ on ``(N, D)`` descriptors (whole-log mode) and reset the library.

        Raises:
            RetrievalError: too few descriptors (fewer than ``N_b + 1``), with the numbers.
        """
        descriptors = self._check_batch(descriptors)
        if descriptors.shape[0] < self.config.code_bits + 1:
            raise RetrievalError(
                f"the log has {descriptors.shape[0]} usable images; fitting {self.config.code_bits}-bit codes "
                f"needs at least {self.config.code_bits + 1}",
                fix="use a longer log or lower retrieval.code_bits",
            )
        self._hasher = self._fit(descriptors)
        self._reset_index()
        self._pending.clear()

    def refit(self) -> None:
        """Re-fit PCA and ITQ on every descriptor in the library and re-encode it (on request only).

        Needs ``rerank = "descriptor"`` (the library keeps the full descriptors then).
        """
        if self.config.rerank != "descriptor":
            raise RetrievalError("refit needs the full descriptors", fix="use retrieval.rerank = 'descriptor'")
        if self._index is None or len(self._index) < self.config.code_bits + 1:
            raise RetrievalError("not enough library frames to refit", fix="add more frames first")
        frames = self._index.frames.copy()
        descriptors = self._index.vectors.copy()  # the full descriptors (rerank = "descriptor")
        self._hasher = self._fit(descriptors)
        self._reset_index()
        self._insert(frames, descriptors)

    def _fit(self, descriptors: np.ndarray) -> BinaryHasher:
        c = self.config
        hasher = fit_hasher(descriptors, pca_dims=c.pca_dims, code_bits=c.code_bits, iterations=c.itq_iterations, seed=c.seed)
        log.info(
            "retrieval: fitted PCA-%d + ITQ %d-bit codes on %d descriptors (quantisation loss %.3f)",
            hasher.pca.dims, c.code_bits, descriptors.shape[0], hasher.quantisation_loss,
        )
        return hasher

    def _reset_index(self) -> None:
        assert self._hasher is not None
        dim = self.dim if self.config.rerank == "descriptor" else self._hasher.pca.dims
        self._index = CodeIndex(
            code_bits=self.config.code_bits,
            vector_dim=dim,
            hamming_threshold=self.config.hamming_threshold,
            strategy=self.config.index_strategy,
        )

    def _insert(self, frames: np.ndarray, descriptors: np.ndarray) -> None:
        assert self._hasher is not None and self._index is not None
        projected = self._hasher.project(descriptors)
        codes = self._hasher.encode_projected(projected)
        vectors = descriptors if self.config.rerank == "descriptor" else projected
        for frame, code, vector in zip(frames, codes, vectors):
            self._index.add(int(frame), int(code), vector)

    # --- the per-frame step --------------------------------------------------------------------

    def add(self, frame_index: int, descriptor: np.ndarray) -> RetrievalOutput:
        """Add frame ``frame_index``'s ``(D,)`` descriptor; query first when fitted.

        Frames must come in increasing order (gaps are fine: skipped frames).
        """
        descriptor = self._check_one(descriptor)
        frame_index = int(frame_index)
        if self._last_frame is not None and frame_index <= self._last_frame:
            raise RetrievalError(
                f"frame {frame_index} added after frame {self._last_frame}", fix="add frames in increasing order"
            )
        self._last_frame = frame_index
        if not self.fitted:
            if self.config.fit == "whole-log":
                raise RetrievalError(
                    "retrieval.fit = 'whole-log' needs Retriever.fit(all descriptors) before the first add",
                    fix="call fit() first, or use fit = 'online'",
                )
            self._pending.append((frame_index, descriptor))
            if len(self._pending) >= self.warmup_frames:
                frames = np.array([f for f, _ in self._pending], dtype=np.int64)
                descriptors = np.stack([d for _, d in self._pending])
                self._hasher = self._fit(descriptors)
                self._reset_index()
                self._insert(frames, descriptors)
                self._pending.clear()
            return _WARMING_UP
        output = self.query(frame_index, descriptor)
        self._insert(np.array([frame_index]), descriptor[None, :])
        return output

    def query(self, frame_index: int, descriptor: np.ndarray) -> RetrievalOutput:
        """Query without adding: frames ``t' < frame_index - Δt``, Hamming ``<= T_b``, top ``N_r`` by L2."""
        if self._hasher is None or self._index is None:
            raise RetrievalError("the retriever is not fitted yet", fix="add warm-up frames or call fit()")
        c = self.config
        descriptor = self._check_one(descriptor)
        projected = self._hasher.project(descriptor[None, :])
        code = int(self._hasher.encode_projected(projected)[0])
        vector = descriptor if c.rerank == "descriptor" else projected[0]
        max_frame = int(frame_index) - c.exclusion_frames - 1
        result = self._index.search(code, vector, max_frame_index=max_frame, top_k=c.top_k)
        candidates = tuple(
            LoopCandidate(
                query_frame=int(frame_index),
                match_frame=int(match),
                similarity=float(1.0 - 0.5 * float(d) ** 2),
                hamming=int(h),
                source=SOURCE,
            )
            for match, d, h in zip(result.frames, result.l2_distances, result.hamming)
        )
        eligible = int(np.searchsorted(self._index.frames, max_frame, side="right"))
        self.queries += 1
        diagnostics = QueryDiagnostics(
            query_frame=int(frame_index),
            code=code,
            code_bits=c.code_bits,
            prefilter_size=result.prefilter_size,
            top=candidates,
            l2_distances=tuple(float(d) for d in result.l2_distances),
            library_size=len(self._index),
            eligible_size=eligible,
        )
        return RetrievalOutput(candidates, diagnostics)

    # --- checks --------------------------------------------------------------------------------

    def _check_one(self, descriptor: np.ndarray) -> np.ndarray:
        d = np.asarray(descriptor, dtype=np.float32).reshape(-1)
        if d.shape[0] != self.dim:
            raise RetrievalError(f"descriptor has {d.shape[0]} dimensions, the retriever expects {self.dim}")
        if not np.all(np.isfinite(d)):
            raise RetrievalError("descriptor contains NaN or infinity", fix="check the descriptor backend's input")
        return d

    def _check_batch(self, descriptors: np.ndarray) -> np.ndarray:
        x = np.asarray(descriptors, dtype=np.float32)
        if x.ndim != 2 or x.shape[1] != self.dim:
            raise RetrievalError(f"descriptors must be (N, {self.dim}), got shape {x.shape}")
        return x
