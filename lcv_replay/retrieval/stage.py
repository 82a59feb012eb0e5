"""Place recognition as a replay stage: frames in, loop candidates and what the sinks draw out.

:class:`RetrievalStage` holds the descriptor backend and the incremental :class:`Retriever`. The
replay feeds it ``(frame, descriptor)`` pairs (descriptors computed in batches, and cached, by
:func:`~lcv_replay.retrieval.cache.describe_frames`) and asks it, frame by frame, for the
candidates of each query and the :class:`~lcv_replay.sinks.base.RetrievalUpdate` the sinks log.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np

from lcv_replay.records import Frame, LoopCandidate
from lcv_replay.retrieval.config import RetrievalConfig
from lcv_replay.sinks.base import RetrievalUpdate

#: A frame and its descriptor (``None``: the image could not be described; the frame is skipped by
#: retrieval).
Described = tuple[Frame, "np.ndarray | None"]


class RetrievalStage:
    """Descriptor backend + incremental retriever, fed with (frame, descriptor) pairs.

    With ``retrieval.fit = "whole-log"`` (post-mortem) every descriptor of the replayed range is
    computed first (and cached), PCA and the codes are fitted on all of them, then the frames are
    replayed; with ``"online"`` (the paper) the retriever warms up on the first frames.

    Args:
        config: the ``[retrieval]`` section.
        log_path: the log, whose content keys the descriptor cache.
        cache: use the descriptor cache (not for a log still being written).
    """

    def __init__(self, config: RetrievalConfig, log_path: Path, *, cache: bool = True):
        from lcv_replay.retrieval.descriptors import make_backend
        from lcv_replay.retrieval.retriever import Retriever

        self.config = config
        self.backend = make_backend(config.backend, config)
        self.retriever = Retriever(config, dim=self.backend.dim)
        self._log_path = log_path
        self._cache = cache  # False for a file still being written: its content hash is not final

    def _describe(self, frames: Iterable[Frame]) -> Iterator[Described]:
        from lcv_replay.retrieval.cache import describe_frames, log_cache_key

        return describe_frames(
            frames,
            self.backend,
            cache_key=log_cache_key(self._log_path) if self._cache else None,
            cache_dir=Path(self.config.cache_dir) if self.config.cache_dir else None,
            batch_size=self.config.batch_size,
        )

    def described(self, frames_factory: Callable[[], Iterator[Frame]]) -> Iterator[Described]:
        """``(frame, descriptor | None)`` in frame order; ``frames_factory()`` gives a fresh iterator."""
        if self.config.fit != "whole-log":
            return self._describe(frames_factory())
        descriptors = {frame.index: d for frame, d in self._describe(frames_factory()) if d is not None}
        if descriptors:
            self.retriever.fit(np.stack([descriptors[i] for i in sorted(descriptors)]))
        return ((frame, descriptors.get(frame.index)) for frame in frames_factory())

    def query(self, local: Frame, descriptor: np.ndarray | None) -> tuple[list[LoopCandidate], RetrievalUpdate | None]:
        """The candidates of ``local`` (a replay-local frame) and the update for the sinks."""
        if descriptor is None:  # an unreadable image: the frame is skipped by retrieval
            return [], None
        output = self.retriever.add(local.index, descriptor)
        candidates = list(output.candidates)
        diag = output.diagnostics
        if diag is None:  # warming up
            return candidates, RetrievalUpdate(frame=local, candidates=tuple(candidates))
        top = tuple(diag.top)
        return candidates, RetrievalUpdate(
            frame=local,
            candidates=tuple(candidates),
            code=code_bits_msb_first(diag.code, diag.code_bits),
            prefilter_size=diag.prefilter_size,
            top_frames=np.array([c.match_frame for c in top], dtype=np.int64),
            l2_distances=np.asarray(diag.l2_distances, dtype=np.float64),
            hamming=np.array([-1 if c.hamming is None else c.hamming for c in top], dtype=np.int64),
        )

    def warmup_message(self) -> str | None:
        """Why retrieval proposed nothing (a log shorter than its warm-up), or ``None``."""
        return self.retriever.warmup_message()


def code_bits_msb_first(code: int, code_bits: int) -> np.ndarray:
    """A packed code (bit ``k`` = ``1 << k``) as ``(code_bits,)`` bool, most significant bit first."""
    return np.array([(int(code) >> k) & 1 for k in range(code_bits - 1, -1, -1)], dtype=bool)
