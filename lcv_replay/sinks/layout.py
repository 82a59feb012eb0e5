"""Pure functions that turn replay records into the arrays and texts the sinks draw.

Nothing here imports rerun; the Rerun sink calls these and logs the results, and tests check them
directly. Poses are ``(N, 3)`` float64 ``[x_m, y_m, yaw_rad]``; positions ``(N, 2)``.
"""

from __future__ import annotations

from enum import IntEnum
from typing import Any, Mapping, Sequence

import numpy as np

from lcv_replay import se2
from lcv_replay.verification.base import Constraint, HypothesisSummary
from lcv_replay.verification.measurements import extend_by_odometry


class ConstraintState(IntEnum):
    """How a constraint is drawn on the map (the Rerun class id of its segment)."""

    PENDING = 0  # arrived since the last verifier step: not judged yet
    ACCEPTED = 1  # consistent with the rank-1 hypothesis (true, or truth unknown)
    REJECTED = 2  # not accepted (truth unknown)
    ACCEPTED_FALSE = 3  # accepted, but labelled false: a wrong loop closure entered the map
    REJECTED_TRUE = 4  # not accepted, but labelled true: a missed loop
    REJECTED_FALSE = 5  # not accepted, labelled false: correctly rejected

    @property
    def accepted(self) -> bool:
        return self in (ConstraintState.ACCEPTED, ConstraintState.ACCEPTED_FALSE)


#: Label and RGBA colour of each state, for the annotation context (legend) of ``/constraints``.
#: What needs attention is opaque (accepted, wrongly accepted, missed); the rest is faint, so that
#: thousands of correctly rejected retrieval candidates do not hide the map.
STATE_STYLE: dict[ConstraintState, tuple[str, tuple[int, int, int, int]]] = {
    ConstraintState.PENDING: ("pending (not judged yet)", (220, 220, 220, 40)),
    ConstraintState.ACCEPTED: ("accepted", (40, 200, 80, 255)),
    ConstraintState.REJECTED: ("rejected", (120, 120, 150, 50)),
    ConstraintState.ACCEPTED_FALSE: ("accepted but truly false", (240, 30, 30, 255)),
    ConstraintState.REJECTED_TRUE: ("rejected but truly true (missed)", (250, 170, 30, 255)),
    ConstraintState.REJECTED_FALSE: ("rejected, truly false", (170, 80, 110, 30)),
}
#: Line width of each state in UI points (index = state value): faint states thin, wrong ones thick.
STATE_WIDTH_PT = (0.5, 1.0, 0.5, 2.5, 1.5, 0.5)


def constraint_states(
    count: int, accepted_ids: Sequence[int], truth: Sequence[bool | None], *, judged: int | None = None
) -> np.ndarray:
    """State of constraints ``0..count-1``.

    Args:
        count: number of constraints ``C``.
        accepted_ids: ids accepted by the rank-1 hypothesis.
        truth: per id, ``True``/``False``/``None`` (unknown); shorter sequences mean unknown.
        judged: constraints with id ``>= judged`` are :attr:`ConstraintState.PENDING`
            (``None``: all judged).

    Returns:
        ``(C,)`` uint8 :class:`ConstraintState` values.
    """
    accepted = np.zeros(count, dtype=bool)
    ids = np.asarray([i for i in accepted_ids if 0 <= i < count], dtype=np.int64)
    accepted[ids] = True
    known_true = np.zeros(count, dtype=bool)
    known_false = np.zeros(count, dtype=bool)
    for i, t in enumerate(truth[:count]):
        if t is True:
            known_true[i] = True
        elif t is False:
            known_false[i] = True
    states = np.full(count, ConstraintState.REJECTED, dtype=np.uint8)
    states[~accepted & known_true] = ConstraintState.REJECTED_TRUE
    states[~accepted & known_false] = ConstraintState.REJECTED_FALSE
    states[accepted] = ConstraintState.ACCEPTED
    states[accepted & known_false] = ConstraintState.ACCEPTED_FALSE
    if judged is not None:
        states[max(judged, 0):] = ConstraintState.PENDING
    return states


def anchor_to_first(reference: np.ndarray, first_pose: np.ndarray) -> np.ndarray:
    """Move a trajectory rigidly so that its first pose coincides with ``first_pose``.

    Used to draw the ground truth (``world`` frame) on the odometry map (``odom`` frame): both start
    at the same pose, so the drift shows as their separation.

    Args:
        reference: ``(N, 3)`` poses.
        first_pose: ``(3,)`` pose that ``reference[0]`` is moved onto.
    """
    reference = np.asarray(reference, dtype=np.float64)
    if len(reference) == 0:
        return reference.copy()
    T = se2.compose(np.asarray(first_pose, dtype=np.float64), se2.inverse(reference[0]))
    return se2.compose(T, reference)


class GrowingRows:
    """An ``(N, width)`` array grown by appending rows (capacity doubles: amortised O(1))."""

    def __init__(self, width: int, dtype=np.float64, capacity: int = 1024):
        self._buffer = np.zeros((capacity, width), dtype=dtype)
        self._count = 0

    def __len__(self) -> int:
        return self._count

    @property
    def view(self) -> np.ndarray:
        """The filled ``(N, width)`` rows (a view: do not modify)."""
        return self._buffer[: self._count]

    def extend(self, rows: np.ndarray) -> None:
        rows = np.asarray(rows, dtype=self._buffer.dtype).reshape(-1, self._buffer.shape[1])
        needed = self._count + len(rows)
        if needed > len(self._buffer):
            grown = np.zeros((max(needed, 2 * len(self._buffer)), self._buffer.shape[1]), dtype=self._buffer.dtype)
            grown[: self._count] = self.view
            self._buffer = grown
        self._buffer[self._count : needed] = rows
        self._count = needed

    def append(self, row: Sequence[float]) -> None:
        self.extend(np.asarray(row)[None, :])


class MapEstimate:
    """The current best map: the rank-1 trajectory of the latest step, extended by odometry.

    The replay appends each frame's odometry; at a verifier step the rank-1 trajectory replaces the
    optimised prefix. Before the first step the map is the odometry itself.
    """

    def __init__(self) -> None:
        self._odom = GrowingRows(3)
        self._best = np.zeros((0, 3), dtype=np.float64)

    @property
    def frames(self) -> int:
        return len(self._odom)

    @property
    def odometry(self) -> np.ndarray:
        """``(N, 3)`` odometry poses so far (a view: do not modify)."""
        return self._odom.view

    @property
    def optimised_frames(self) -> int:
        """Frames covered by the latest rank-1 trajectory (0 before the first step)."""
        return len(self._best)

    def add_odometry(self, pose: Sequence[float]) -> None:
        """Append the next frame's cumulative odometry ``(3,)``."""
        self._odom.append(pose)

    def set_best(self, trajectory: np.ndarray) -> None:
        """Replace the optimised prefix with the ``(M, 3)`` rank-1 trajectory (``M <= N``)."""
        trajectory = np.asarray(trajectory, dtype=np.float64)
        self._best = trajectory[: self.frames].copy()

    def poses(self) -> np.ndarray:
        """``(N, 3)`` best poses of every frame so far."""
        if len(self._best) == 0:
            return self.odometry.copy()
        return extend_by_odometry(self._best, self.odometry)

    def position_of(self, frame: int) -> tuple[float, float]:
        """Best position of one frame (``< N``); one-pose maths, for the per-frame hot path."""
        odom = self.odometry
        m = len(self._best)
        if m == 0:
            return float(odom[frame, 0]), float(odom[frame, 1])
        if frame < m:
            return float(self._best[frame, 0]), float(self._best[frame, 1])
        x_m, y_m, _ = se2.compose_pose(self._best[m - 1], se2.between_pose(odom[m - 1], odom[frame]))
        return float(x_m), float(y_m)

    def positions_of(self, frames: np.ndarray) -> np.ndarray:
        """``(K, 2)`` best positions of the given frame indices (each ``< N``)."""
        frames = np.asarray(frames, dtype=np.int64).reshape(-1)
        odom = self.odometry
        if len(self._best) == 0:
            return odom[frames, :2].copy()
        m = len(self._best)
        out = np.empty((len(frames), 2), dtype=np.float64)
        inside = frames < m
        out[inside] = self._best[frames[inside], :2]
        if np.any(~inside):
            later = se2.compose(self._best[m - 1], se2.between(odom[m - 1], odom[frames[~inside]]))
            out[~inside] = later[:, :2]
        return out


def segments(positions: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """``(C, 2, 2)`` line segments from the query to the match position of each pair.

    Args:
        positions: ``(N, 2)`` positions by frame index.
        pairs: ``(C, 2)`` ``(query_frame, match_frame)``.
    """
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    return np.stack([positions[pairs[:, 0]], positions[pairs[:, 1]]], axis=1)


def consistency_rows(shape: tuple[int, int], *, min_rows: int, max_cells: int) -> int:
    """How many rows (hypotheses, best first) of an ``(H, C)`` consistency matrix to log.

    All rows while ``H × C <= max_cells``; otherwise as many as fit, but at least ``min_rows``.
    """
    h, c = shape
    if h * c <= max_cells or c == 0:
        return h
    return min(h, max(min_rows, max_cells // c))


def _fmt(value: Any, digits: int = 3) -> str:
    if value is None:
        return "—"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def hypotheses_markdown(
    ranking: Sequence[HypothesisSummary], constraints: Sequence[Constraint], *, top: int
) -> str:
    """Markdown table of the top hypotheses with the constraint sequence that built each."""
    lines = [
        "| rank | hypothesis | parent | score | χ² | window | constraints (id: query↔match, in order) |",
        "|---:|---:|---:|---:|---:|---:|---|",
    ]
    for h in ranking[:top]:
        seq = ", ".join(
            f"{cid}: {constraints[cid].query_frame}↔{constraints[cid].match_frame}"
            if 0 <= cid < len(constraints)
            else str(cid)
            for cid in h.constraint_ids
        )
        parent = "root" if h.parent_id is None else f"#{h.parent_id}"
        lines.append(
            f"| {h.rank} | #{h.id} | {parent} | {h.score} | {_fmt(h.chi2, 1)} | {h.window} | {seq or '(odometry only)'} |"
        )
    if not ranking:
        lines.append("| — | — | — | — | — | — | (this method keeps no hypotheses) |")
    return "\n".join(lines)


def retrieval_markdown(query_frame: int, top_frames: Sequence[int], l2: Sequence[float], hamming: Sequence[int] | None,
                       admitted: set[int], similarity: Sequence[float | None] | None = None) -> str:
    """Markdown table of the top-N retrieved frames of one query (with each one's similarity, if given)."""
    lines = [
        f"**query frame {query_frame}**: {len(top_frames)} retrieved",
        "",
        "| rank | frame | L2 distance | Hamming | similarity | constraint |",
        "|---:|---:|---:|---:|---:|---|",
    ]
    for rank, frame in enumerate(top_frames, start=1):
        ham = "—" if hamming is None else str(int(hamming[rank - 1]))
        sim = similarity[rank - 1] if similarity is not None else None
        lines.append(
            f"| {rank} | {int(frame)} | {float(l2[rank - 1]):.4f} | {ham} | {'—' if sim is None else f'{sim:.3f}'} | "
            f"{'yes' if int(frame) in admitted else 'no'} |"
        )
    return "\n".join(lines)


def key_value_markdown(title: str, items: Mapping[str, Any]) -> str:
    """A two-column markdown table (``key | value``) under a heading."""
    lines = [f"## {title}", "", "| key | value |", "|---|---|"]
    for key, value in items.items():
        lines.append(f"| `{key}` | {_fmt(value, 4)} |")
    return "\n".join(lines)


def flatten(mapping: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` (for config tables)."""
    out: dict[str, Any] = {}
    for key, value in mapping.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(flatten(value, prefix=f"{name}."))
        else:
            out[name] = value
    return out
