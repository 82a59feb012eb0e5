"""Typed records that flow between the pipeline stages.

Conventions (the same everywhere in lcv-replay):

* Planar poses follow ROS REP-103 for the body: x forward, y left, yaw counter-clockwise about +z,
  in radians. ``T_a_b`` is the pose of frame ``b`` expressed in frame ``a``.
* Frame indices are 0..N-1 in time order. ``stamp_ns`` is the frame's MCAP ``log_time`` in
  nanoseconds since the Unix epoch (or since the start of the recording for sources without clock).
* A loop candidate is always oriented ``query_frame > match_frame``: the query is the later frame,
  at whose arrival the candidate becomes known; the match is the earlier, revisited frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable, Iterable, NamedTuple

import numpy as np

from lcv_replay import se2


class Pose2D(NamedTuple):
    """A planar pose ``T_a_b``: position of ``b`` in ``a`` in metres and heading in radians."""

    x_m: float
    y_m: float
    yaw_rad: float

    def compose(self, other: "Pose2D") -> "Pose2D":
        """``self ∘ other``: ``T_a_b ∘ T_b_c = T_a_c``."""
        return Pose2D(*se2.compose_pose(self, other))

    def inverse(self) -> "Pose2D":
        """``T_a_b⁻¹ = T_b_a``."""
        return Pose2D(*se2.inverse_pose(self))

    def between(self, other: "Pose2D") -> "Pose2D":
        """``self⁻¹ ∘ other``: with ``self = T_w_a`` and ``other = T_w_b`` this is ``T_a_b``."""
        return Pose2D(*se2.between_pose(self, other))

    def as_array(self) -> np.ndarray:
        """``(3,)`` float64 array ``[x_m, y_m, yaw_rad]``."""
        return np.array([self.x_m, self.y_m, self.yaw_rad], dtype=np.float64)


IDENTITY_POSE = Pose2D(0.0, 0.0, 0.0)


@dataclass(frozen=True)
class StereoCalibration:
    """Rectified stereo pinhole calibration, as carried by ``foxglove.CameraCalibration``.

    ``baseline_m`` is positive; in ROS convention the right camera's projection matrix has
    ``P[0, 3] = -fx * baseline_m``. ``distortion`` holds the left camera's plumb-bob coefficients
    ``(k1, k2, t1, t2, k3)``; all zeros for rectified images.
    """

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    baseline_m: float
    distortion: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    frame_id: str = "camera_left"

    @property
    def K(self) -> np.ndarray:
        """``(3, 3)`` intrinsic matrix of the (rectified) left camera."""
        return np.array(
            [[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]]
        )


@dataclass(frozen=True)
class ImageRef:
    """An image of a frame, decoded only when :meth:`decode` is called.

    ``decoder`` returns an ``(H, W)`` uint8 grey or ``(H, W, 3)`` uint8 RGB array.
    ``encoding`` is e.g. ``"png"``, ``"jpeg"``, ``"mono8"``, ``"rgb8"``.
    """

    stamp_ns: int
    encoding: str
    decoder: Callable[[], np.ndarray] = field(repr=False, compare=False)

    def decode(self) -> np.ndarray:
        return self.decoder()


@dataclass(frozen=True)
class LoopCandidate:
    """A loop-closure candidate: "frame ``query_frame`` is the same place as ``match_frame``".

    Attributes:
        query_frame: the later frame (the query); ``query_frame > match_frame``.
        match_frame: the earlier, revisited frame.
        similarity: place-recognition similarity score, larger is more similar (source-specific;
            our retrieval's is in [0, 1], see lcv_replay.retrieval.similarity).
        hamming: Hamming distance of the binary codes, where retrieval produced the candidate.
        source: who proposed it, e.g. ``"retrieval"``, ``"DLoopDetector"``, ``"injected"``.
        T_match_query: measured pose of the query frame in the match frame, if the source gives
            one (g2o candidates do); ``None`` means "same place", identity with config noise.
        information: upper triangle ``(I_xx, I_xy, I_xθ, I_yy, I_yθ, I_θθ)`` of the 3x3
            information matrix of ``T_match_query`` (g2o order), or ``None``.
        l2_distance: the re-rank L2 distance of the descriptors, where retrieval produced the
            candidate, else ``None``.
    """

    query_frame: int
    match_frame: int
    similarity: float = 1.0
    hamming: int | None = None
    source: str = "unknown"
    T_match_query: Pose2D | None = None
    information: tuple[float, float, float, float, float, float] | None = None
    l2_distance: float | None = None

    @property
    def pair(self) -> tuple[int, int]:
        """``(query_frame, match_frame)``: the key used for labels and de-duplication."""
        return (self.query_frame, self.match_frame)


@dataclass(frozen=True)
class Frame:
    """One frame of a log, as the reader yields it.

    Attributes:
        index: 0..N-1 in time order; the MCAP ``sequence`` of every message of this frame.
        stamp_ns: the frame's ``log_time`` in nanoseconds.
        odom: cumulative planar odometry ``T_odom_base``, or ``None`` if the log has none.
        ground_truth: planar ground-truth ``T_world_base``, or ``None``.
        left, right: the stereo images, decoded lazily; ``None`` if the log has no images.
        candidates: loop candidates carried by the log whose ``query_frame == index``.
        true_loops: labelled true pairs ``(query_frame, match_frame)`` that arrive at this frame.
    """

    index: int
    stamp_ns: int
    odom: Pose2D | None = None
    ground_truth: Pose2D | None = None
    left: ImageRef | None = None
    right: ImageRef | None = None
    candidates: tuple[LoopCandidate, ...] = ()
    true_loops: tuple[tuple[int, int], ...] = ()


@dataclass(frozen=True)
class FrameWindow:
    """The frames ``[first, last)`` of a log that a run replays, and the map to replay-local indices.

    Inside a replay the first replayed frame is frame 0: log frame ``k`` is ``k - first``. Loop
    candidates and labels that reach back before ``first`` are dropped. The reader computes the
    window once (:meth:`~lcv_replay.log.reader.LogReader.window`); every rebase goes through here.
    """

    first: int
    last: int

    @property
    def frames(self) -> int:
        """Number of frames in the window."""
        return max(self.last - self.first, 0)

    def rows(self, per_frame: np.ndarray) -> np.ndarray:
        """The window's rows of a per-frame array of the whole log (e.g. ``(N, 3)`` ground truth)."""
        return per_frame[self.first : self.last]

    def pairs(self, pairs: Iterable[tuple[int, int]]) -> tuple[tuple[int, int], ...]:
        """``(query, match)`` pairs in replay-local indices, in order; those whose match precedes
        the window are dropped."""
        return tuple((q - self.first, m - self.first) for q, m in pairs if m >= self.first)

    def candidates(self, candidates: Iterable[LoopCandidate]) -> tuple[LoopCandidate, ...]:
        """Candidates in replay-local indices; those reaching back before the window are dropped."""
        return tuple(
            replace(c, query_frame=c.query_frame - self.first, match_frame=c.match_frame - self.first)
            for c in candidates
            if c.match_frame >= self.first and c.query_frame >= self.first
        )

    def frame(self, frame: Frame) -> Frame:
        """``frame`` with its index, candidates and labels in replay-local indices."""
        if self.first == 0:
            return frame
        return replace(
            frame,
            index=frame.index - self.first,
            candidates=self.candidates(frame.candidates),
            true_loops=self.pairs(frame.true_loops),
        )
