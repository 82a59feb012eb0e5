"""The stateful place-recognition front end: descriptor in, loop candidates out (paper sec. II-B).

Online use (the default, ``fit = "online"``)::

    retriever = Retriever(config, dim=backend.dim)
    for frame, descriptor in describe_frames(frames, backend, cache_key=key):
        if descriptor is None:           # unreadable image: skipped
            continue
        output = retriever.add(frame.index, descriptor)
        output.candidates                # up to N_r LoopCandidate, best first
        output.diagnostics               # None while warming up

No frame queries until the warm-up is over: the first ``warmup_frames`` descriptors fit PCA and
the ITQ rotation (:mod:`lcv_replay.retrieval.hashing`), then enter the index without querying
(none of them could have an eligible match ``|t - t'| > Δt`` anyway when the warm-up is ``Δt``).
After that each added frame first queries the index (frames ``t' < t - Δt``) and is then added to
it. The warm-up is ``max(Δt, N_b + 1)`` in mode "paper"; in mode "ranked" it is ``max(Δt, 9)`` and
the code is shortened, to a multiple of 8 bits, when the fitting frames span fewer PCA axes than
``ranked.code_bits`` (``N - 1`` axes for ``N`` frames: a 21-frame warm-up gives 16-bit codes).

The mode (``retrieval.mode``) picks the index (:mod:`lcv_replay.retrieval.index`):

* ``"ranked"`` (default): 128-bit codes, the ``M = 100`` Hamming-nearest eligible frames, top ``N_r``
  by L2 (:class:`~lcv_replay.retrieval.index.RankedIndex`);
* ``"paper"``: 20-bit codes, frames within Hamming ``T_b = 3``, top ``N_r`` by L2
  (:class:`~lcv_replay.retrieval.index.CodeIndex`), bit-identical to the pipeline before modes.

Post-mortem use (``fit = "whole-log"``): call :meth:`Retriever.fit` with every descriptor of the
log first; then every :meth:`add` queries.

Each candidate carries its re-rank L2 distance ``l2_distance`` and its Hamming distance. Its
``similarity`` is, in mode ``"ranked"``, calibrated to the log (0 = as alike as two unrelated
frames, 1 = identical; :mod:`lcv_replay.retrieval.similarity`) and, in mode ``"paper"``,
``1 - d^2 / 2`` for re-rank distance ``d``: the cosine similarity of the L2-normalised descriptors
with ``rerank = "descriptor"`` (the default); with ``rerank = "pca"`` it is the same expression on
the PCA vectors (monotone in ``d``, no longer a cosine).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from lcv_replay.errors import RetrievalError
from lcv_replay.records import LoopCandidate
from lcv_replay.retrieval.config import RetrievalConfig
from lcv_replay.retrieval.hashing import BinaryHasher, fit_hasher
from lcv_replay.retrieval.index import CodeIndex, RankedIndex
from lcv_replay.retrieval.similarity import background_sq_distance, calibrated_similarity

log = logging.getLogger(__name__)

SOURCE = "retrieval"


@dataclass(frozen=True)
class QueryDiagnostics:
    """What one query saw, for the Rerun timeline and post-mortems.

    Attributes:
        query_frame: the query's frame index.
        code: the query's packed binary code (bit ``k`` = ``1 << k``).
        code_bits: the code length of the mode (``N_b`` in mode "paper").
        prefilter_size: eligible library frames passed to the L2 re-rank: those within Hamming
            ``T_b`` of the code (paper), or the ``M`` nearest (ranked).
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
    mode: str = "paper"

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
_MIN_RANKED_BITS = 8


def ranked_code_bits(config: RetrievalConfig, *, frames: int, dim: int) -> int:
    """The ranked code length for a fit on ``frames`` descriptors of ``dim`` dimensions.

    ``ranked.code_bits``, shortened to the largest multiple of 8 that the fit's PCA axes
    (``min(pca_dims, dim, frames - 1)``) can carry, with an info line when it is shortened.
    """
    axes = min(config.pca_dims, dim, frames - 1)
    bits = min(config.ranked.code_bits, _MIN_RANKED_BITS * (axes // _MIN_RANKED_BITS))
    if bits < _MIN_RANKED_BITS:
        raise RetrievalError(
            f"{frames} descriptors of {dim} dimensions span {axes} PCA axes, fewer than the {_MIN_RANKED_BITS} bits of the shortest ranked code",
            fix="use a longer log or warm-up (retrieval.exclusion_frames)",
        )
    if bits < config.ranked.code_bits:
        log.info("retrieval: ranked codes shortened to %d bits: %d fitting frames span %d PCA axes", bits, frames, axes)
    return bits


class Retriever:
    """Incremental retrieval over a growing library of descriptors.

    Args:
        config: retrieval parameters (``N_r``, ``Δt``, ``N_b``, ``T_b``, PCA size, fit mode...).
        dim: descriptor length ``D`` of the backend.
    """

    def __init__(self, config: RetrievalConfig, *, dim: int):
        if dim < 1:
            raise RetrievalError(f"descriptor dimension {dim} must be >= 1")
        self.config = config
        self.dim = dim
        self.code_bits = config.active_code_bits  # ranked: the target length until the fit settles it
        if dim < self.min_fit_frames - 1:
            raise RetrievalError(
                f"descriptors of {dim} dimensions cannot give {self.min_fit_frames - 1}-bit codes",
                fix="lower retrieval.code_bits" if config.mode == "paper" else "use a descriptor of at least 8 dimensions",
            )
        self._hasher: BinaryHasher | None = None
        self._index: CodeIndex | RankedIndex | None = None
        self._background_sq: float | None = None  # d0^2 of the calibrated similarity (mode "ranked")
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
    def min_fit_frames(self) -> int:
        """Fewest descriptors a fit accepts: ``N_b + 1`` (paper), or 9 for 8-bit ranked codes."""
        return self.config.code_bits + 1 if self.config.mode == "paper" else _MIN_RANKED_BITS + 1

    @property
    def warmup_frames(self) -> int:
        """Descriptors needed before the online fit: ``max(Δt, min_fit_frames)``."""
        return max(self.config.exclusion_frames, self.min_fit_frames)

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
            f"{self.warmup_frames} needed to fit PCA and the binary codes "
            f"(max(Δt = {self.config.exclusion_frames}, {self.min_fit_frames})); lower retrieval.exclusion_frames "
            "or use a longer log"
        )

    # --- fitting -------------------------------------------------------------------------------

    def fit(self, descriptors: np.ndarray) -> None:
        """Fit PCA and ITQ on ``(N, D)`` descriptors (whole-log mode) and reset the library.

        Raises:
            RetrievalError: too few descriptors (fewer than ``N_b + 1``), with the numbers.
        """
        descriptors = self._check_batch(descriptors)
        if descriptors.shape[0] < self.min_fit_frames:
            raise RetrievalError(
                f"the log has {descriptors.shape[0]} usable images; fitting {self.min_fit_frames - 1}-bit codes "
                f"needs at least {self.min_fit_frames}",
                fix="use a longer log" if self.config.mode == "ranked" else "use a longer log or lower retrieval.code_bits",
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
        if self._index is None or len(self._index) < self.min_fit_frames:
            raise RetrievalError("not enough library frames to refit", fix="add more frames first")
        frames = self._index.frames.copy()
        descriptors = self._index.vectors.copy()  # the full descriptors (rerank = "descriptor")
        self._hasher = self._fit(descriptors)
        self._reset_index()
        self._insert(frames, descriptors)

    def _fit(self, descriptors: np.ndarray) -> BinaryHasher:
        c = self.config
        if c.mode == "ranked":
            self.code_bits = ranked_code_bits(c, frames=descriptors.shape[0], dim=descriptors.shape[1])
        hasher = fit_hasher(descriptors, pca_dims=c.pca_dims, code_bits=self.code_bits, iterations=c.itq_iterations, seed=c.seed)
        if c.mode == "ranked":
            vectors = descriptors if c.rerank == "descriptor" else hasher.project(descriptors)
            self._background_sq = background_sq_distance(vectors, min_gap_rows=max(1, c.exclusion_frames // 2))
        log.info(
            "retrieval: fitted PCA-%d + ITQ %d-bit codes on %d descriptors (quantisation loss %.3f)",
            hasher.pca.dims, self.code_bits, descriptors.shape[0], hasher.quantisation_loss,
        )
        return hasher

    def _reset_index(self) -> None:
        assert self._hasher is not None
        c = self.config
        dim = self.dim if c.rerank == "descriptor" else self._hasher.pca.dims
        if c.mode == "ranked":
            self._index = RankedIndex(code_bits=self.code_bits, vector_dim=dim, candidates=c.ranked.candidates, engine=c.ranked.index)
        else:
            self._index = CodeIndex(code_bits=self.code_bits, vector_dim=dim, hamming_threshold=c.hamming_threshold, strategy=c.index_strategy)

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
        """Query without adding: frames ``t' < frame_index - Δt``, prefiltered by the mode, top ``N_r`` by L2."""
        if self._hasher is None or self._index is None:
            raise RetrievalError("the retriever is not fitted yet", fix="add warm-up frames or call fit()")
        c = self.config
        descriptor = self._check_one(descriptor)
        projected = self._hasher.project(descriptor[None, :])
        code = int(self._hasher.encode_projected(projected)[0])
        vector = descriptor if c.rerank == "descriptor" else projected[0]
        max_frame = int(frame_index) - c.exclusion_frames - 1
        result = self._index.search(code, vector, max_frame_index=max_frame, top_k=c.top_k)
        if c.mode == "ranked":
            assert self._background_sq is not None
            similarities = [float(s) for s in calibrated_similarity(result.l2_distances, self._background_sq)]
        else:  # the paper mode's similarity as before modes existed, bit for bit
            similarities = [float(1.0 - 0.5 * float(d) ** 2) for d in result.l2_distances]
        candidates = tuple(
            LoopCandidate(
                query_frame=int(frame_index),
                match_frame=int(match),
                similarity=similarity,
                hamming=int(h),
                source=SOURCE,
                l2_distance=float(d),
            )
            for match, d, h, similarity in zip(result.frames, result.l2_distances, result.hamming, similarities)
        )
        eligible = int(np.searchsorted(self._index.frames, max_frame, side="right"))
        self.queries += 1
        diagnostics = QueryDiagnostics(
            query_frame=int(frame_index),
            code=code,
            code_bits=self.code_bits,
            prefilter_size=result.prefilter_size,
            top=candidates,
            l2_distances=tuple(float(d) for d in result.l2_distances),
            library_size=len(self._index),
            eligible_size=eligible,
            mode=c.mode,
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
