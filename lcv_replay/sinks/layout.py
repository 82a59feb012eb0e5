"""Pure functions that turn replay records into the arrays and texts the sinks draw.

Nothing here imports rerun; the Rerun sink calls these and logs the results, and tests check them
directly. Poses are ``(N, 3)`` float64 ``[x_m, y_m, yaw_rad]``; positions ``(N, 2)``.
"""

from __future__ import annotations

import math
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


#: Label and RGBA colour of each state, for the annotation context of ``/constraints`` and the
#: legend. What needs attention is opaque (accepted, wrongly accepted, missed); the rest is faint,
#: so that thousands of correctly rejected retrieval candidates never hide the map.
STATE_STYLE: dict[ConstraintState, tuple[str, tuple[int, int, int, int]]] = {
    ConstraintState.PENDING: ("pending (not judged yet)", (220, 220, 220, 45)),
    ConstraintState.ACCEPTED: ("accepted", (40, 200, 80, 255)),
    ConstraintState.REJECTED: ("rejected", (150, 150, 170, 30)),
    ConstraintState.ACCEPTED_FALSE: ("accepted but truly false", (255, 45, 45, 255)),
    ConstraintState.REJECTED_TRUE: ("rejected but truly true (missed)", (250, 170, 30, 255)),
    ConstraintState.REJECTED_FALSE: ("rejected, truly false", (150, 150, 170, 30)),
}
#: Line width of each state in UI points (index = state value): faint states thin, wrong ones thick.
STATE_WIDTH_PT = (0.5, 1.5, 0.4, 3.0, 2.0, 0.4)


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
    T = se2.compose(np.asarray(first_pose, dtype=np.float64), se2.between(reference[0], np.zeros(3)))  # reference[0]⁻¹
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


def _fmt(value: Any, digits: int = 3) -> str:
    if value is None:
        return "—"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def hypotheses_markdown(
    ranking: Sequence[HypothesisSummary], constraints: Sequence[Constraint], *, top: int,
    truth: Sequence[bool | None] = (), key_name: str | None = None,
) -> str:
    """Markdown table of the top hypotheses with the constraint sequence that built each.

    ``key_name``: where hypotheses are ranked by something other than their score (``ilv+``), the
    key's name; its column then comes right after the rank, so that the order is visibly the key's.
    Constraints labelled false are marked ``✗``.
    """
    keyed = key_name is not None and any(h.rank_key != float(h.score) for h in ranking[:top])
    key_head, key_align = (f" {key_name} |", "---:|") if keyed else ("", "")
    lines = [
        f"| rank |{key_head} hypothesis | parent | score | χ² | window | constraints (id: query↔match, in order; ✗ false) |",
        f"|---:|{key_align}---:|---:|---:|---:|---:|---|",
    ]
    for h in ranking[:top]:
        seq = ", ".join(
            f"{cid}: {constraints[cid].query_frame}↔{constraints[cid].match_frame}"
            + (" ✗" if cid < len(truth) and truth[cid] is False else "")
            if 0 <= cid < len(constraints)
            else str(cid)
            for cid in h.constraint_ids
        )
        parent = "root" if h.parent_id is None else f"#{h.parent_id}"
        key = f" {h.rank_key:.1f} |" if keyed else ""
        lines.append(
            f"| {h.rank} |{key} #{h.id} | {parent} | {h.score} | {_fmt(h.chi2, 1)} | {h.window} | {seq or '(odometry only)'} |"
        )
    if not ranking:
        lines.append("| — |" + (" — |" if keyed else "") + " — | — | — | — | — | (this method keeps no hypotheses) |")
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


# --------------------------------------------------------------------------------------- panels
def deciding_constraints(consistency: np.ndarray, *, rows: int, max_columns: int, context: int = 5) -> np.ndarray:
    """The constraints that decide between the top hypotheses, ordered so that structure shows.

    The paper's Fig. W: of an ``(H, C)`` consistency matrix (rows in rank order), the top ``rows``
    hypotheses × at most ``max_columns`` constraints. When there are more constraints than fit,
    the ones on which the top hypotheses disagree are kept, those that separate rank 1 from rank 2
    first (then from rank 3, ...); free columns are filled with constraints every top hypothesis
    holds. The kept columns are sorted by their pattern down the rows (rank 1 most significant),
    so that the blocks of constraints each hypothesis holds show as blocks.

    Returns:
        ``(D,)`` int64 constraint ids (column indices), ``D <= max_columns``.
    """
    m = np.asarray(consistency, dtype=bool)[:rows]
    if m.ndim != 2 or m.size == 0:
        return np.zeros(0, dtype=np.int64)
    k, c = m.shape
    columns = np.arange(c, dtype=np.int64)
    if c > max_columns:
        differs = m != m[:1]
        deciding = np.flatnonzero(differs.any(axis=0))
        first = differs[:, deciding].argmax(axis=0)  # the first rank that disagrees with rank 1
        keep = deciding[np.lexsort((deciding, first))][:max_columns]
        held = np.flatnonzero(m.all(axis=0))
        room = max_columns - len(keep) if len(keep) == 0 else min(context, max_columns - len(keep))
        keep = np.concatenate([keep, held[:room]])
        columns = keep
    sub = m[:, columns]
    # Sort by the column pattern, rank 1 as the most significant row, then by id.
    order = np.lexsort((columns, *[~sub[r] for r in range(k - 1, -1, -1)]))
    return columns[order]


def ancestry(tree: Mapping[int, tuple[int | None, int | None, int]], leaves: Sequence[int]) -> list[int]:
    """Ids of ``leaves`` and all their ancestors in ``tree`` (``{id: (parent, constraint, window)}``),
    sorted; a parent missing from ``tree`` ends the chain."""
    seen: set[int] = set()
    for leaf in leaves:
        node: int | None = int(leaf)
        while node is not None and node not in seen and node in tree:
            seen.add(node)
            node = tree[node][0]
    return sorted(seen)


def tree_layout(nodes: Sequence[int], parents: Mapping[int, int | None], leaves: Sequence[int],
                *, dx: float = 120.0, dy: float = 40.0) -> dict[int, tuple[float, float]]:
    """Positions of a generation tree drawn left to right: x = depth, leaves stacked in the order
    given (rank order), each parent at the mean height of its children.

    Args:
        nodes: the node ids to place (an ancestry, see :func:`ancestry`).
        parents: parent id of each node (``None`` or absent from ``nodes``: a root).
        leaves: the nodes to stack first, top to bottom (the current top hypotheses by rank).
    """
    node_set = set(int(n) for n in nodes)
    children: dict[int, list[int]] = {n: [] for n in node_set}
    roots = []
    for n in sorted(node_set):
        p = parents.get(n)
        if p is not None and p in node_set and p != n:
            children[p].append(n)
        else:
            roots.append(n)
    rank = {int(leaf): i for i, leaf in enumerate(leaves)}

    memo_rank: dict[int, float] = {}
    for n in sorted(node_set, reverse=True):  # children have larger ids than parents
        memo_rank[n] = min([rank.get(n, math.inf)] + [memo_rank.get(ch, math.inf) for ch in children[n]])
    positions: dict[int, tuple[float, float]] = {}
    row = [0]

    def place(n: int, depth: int) -> float:
        kids = sorted(children[n], key=lambda ch: (memo_rank.get(ch, math.inf), ch))
        if not kids:
            y = row[0] * dy
            row[0] += 1
        else:
            y = float(np.mean([place(ch, depth + 1) for ch in kids]))
        positions[n] = (depth * dx, y)
        return y

    for root in sorted(roots, key=lambda r: (memo_rank.get(r, math.inf), r)):
        place(root, 0)
    return positions


def compress_chains(parents: Mapping[int, int | None], added: Mapping[int, int | None], keep: Sequence[int]
                    ) -> tuple[dict[int, int | None], dict[int, tuple[int, ...]]]:
    """Collapse the linear stretches of a generation tree, so that a deep ancestry stays readable.

    A node that is not in ``keep``, has a parent and exactly one child is removed; its child is
    attached to its parent and inherits the constraint it added.

    Args:
        parents: parent of each node (``None``: a root).
        added: the constraint each node's parent was extended by (``None``: unknown / root).
        keep: nodes never removed (the current top hypotheses).

    Returns:
        ``(parents, added_chain)``: the compressed tree, and per node the constraints added along
        the edge from its (new) parent, oldest first.
    """
    children: dict[int, list[int]] = {n: [] for n in parents}
    for n, p in parents.items():
        if p is not None and p in children:
            children[p].append(n)
    keep_set = set(int(k) for k in keep)
    new_parent = dict(parents)
    chain: dict[int, tuple[int, ...]] = {n: (() if added.get(n) is None else (int(added[n]),)) for n in parents}
    for n in sorted(parents):  # parents before children (ids grow with generation)
        p = new_parent.get(n)
        if n in keep_set or p is None or p not in new_parent or len(children[n]) != 1:
            continue
        (child,) = children[n]
        new_parent[child] = p
        chain[child] = chain[n] + chain[child]
        children[p] = [child if c == n else c for c in children[p]]
        del new_parent[n], chain[n]
    return new_parent, chain
