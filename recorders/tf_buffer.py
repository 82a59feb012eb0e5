"""A TF buffer: the transform between two frames of ``/tf`` and ``/tf_static``, interpolated in time.

The semantics are tf2's, the code is ours (pure numpy; the messages come from ``rosbags``):

* Every transform ``(parent, child)`` is an edge ``T_parent_child`` of a forest: each frame has at
  most one parent. A child published under several parents (a broken TF tree) keeps the parent with
  the most messages, with a warning.
* ``/tf_static`` edges hold at every time (the last message wins); ``/tf`` edges are sampled at their
  header stamps and interpolated between samples: translation linearly, rotation by quaternion
  slerp. A query outside an edge's samples takes the nearest sample if it is within
  ``max_gap_ns`` of it (tf2 refuses to extrapolate at all; a small tolerance absorbs stamp jitter
  between topics), and a query between two samples more than ``max_gap_ns`` apart is refused.
  Refused queries are NaN rows.
* ``lookup(parent, child, stamps)`` composes the chain ``parent <- common ancestor -> child``:
  ``T_parent_child = inv(T_root_parent) @ T_root_child``.

Frame names lose a leading ``/`` (ROS 1 bags often have ``/odom``), as tf2 does.

Arrays: ``(N, 4, 4)`` rigid transforms, ``(N, 3)`` translations in metres, ``(N, 4)`` unit
quaternions ``(x, y, z, w)``, stamps in integer nanoseconds.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np

from lcv_replay.errors import RecorderError
from recorders.common import quaternion_to_matrix

log = logging.getLogger(__name__)


def normalize_frame(name: str) -> str:
    """A frame id without the leading ``/`` that ROS 1 allowed (``/odom`` -> ``odom``)."""
    return str(name).lstrip("/")


def parse_frame_pair(text: str, *, flag: str) -> tuple[str, str]:
    """``"odom:base_link"`` -> ``("odom", "base_link")``; :class:`RecorderError` naming ``flag`` otherwise."""
    parts = [normalize_frame(p.strip()) for p in str(text).split(":")]
    if len(parts) != 2 or not all(parts) or parts[0] == parts[1]:
        raise RecorderError(f"{flag} {text!r} is not PARENT:CHILD", fix=f"pass two different frames, e.g. {flag} odom:base_link")
    return parts[0], parts[1]


@dataclass(frozen=True)
class Edge:
    """The samples of one transform ``T_parent_child``.

    Attributes:
        parent, child: frame ids.
        static: from ``/tf_static`` (one pose, valid at every time).
        stamps_ns: ``(M,)`` strictly increasing sample stamps (``(1,)`` for a static edge).
        translations: ``(M, 3)`` translations of the child origin in the parent frame, metres.
        quaternions: ``(M, 4)`` unit quaternions ``(x, y, z, w)`` of the child axes in the parent frame.
    """

    parent: str
    child: str
    static: bool
    stamps_ns: np.ndarray
    translations: np.ndarray
    quaternions: np.ndarray

    def at(self, stamps_ns: np.ndarray, max_gap_ns: int) -> np.ndarray:
        """``(N, 4, 4)`` ``T_parent_child`` at ``stamps_ns``; NaN rows where it cannot be interpolated."""
        query = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        if self.static:
            return np.broadcast_to(_matrices(self.translations[:1], self.quaternions[:1]), (len(query), 4, 4)).copy()
        t, q = interpolate_poses(self.stamps_ns, self.translations, self.quaternions, query, max_gap_ns)
        return _matrices(t, q)


def interpolate_poses(
    stamps_ns: np.ndarray, translations: np.ndarray, quaternions: np.ndarray, query_ns: np.ndarray, max_gap_ns: int
) -> tuple[np.ndarray, np.ndarray]:
    """Poses at ``query_ns``: translation lerp and quaternion slerp between the bracketing samples.

    Args:
        stamps_ns: ``(M,)`` strictly increasing sample stamps.
        translations: ``(M, 3)``.
        quaternions: ``(M, 4)`` unit ``(x, y, z, w)``.
        query_ns: ``(N,)`` stamps.
        max_gap_ns: largest gap bridged between two samples, and largest distance to the nearest
            sample for a query before the first or after the last one.

    Returns:
        ``(N, 3)`` translations and ``(N, 4)`` quaternions, NaN rows where refused.
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    query = np.asarray(query_ns, dtype=np.int64)
    t_out = np.full((len(query), 3), np.nan)
    q_out = np.full((len(query), 4), np.nan)
    if len(stamps) == 0 or len(query) == 0:
        return t_out, q_out
    hi = np.clip(np.searchsorted(stamps, query, side="left"), 0, len(stamps) - 1)
    lo = np.clip(hi - 1, 0, len(stamps) - 1)
    exact = stamps[hi] == query
    inside = (query > stamps[0]) & (query < stamps[-1]) & ~exact
    gap = stamps[hi] - stamps[lo]
    ok_inside = inside & (gap <= max_gap_ns)
    w = np.zeros(len(query))
    w[ok_inside] = (query[ok_inside] - stamps[lo[ok_inside]]) / np.maximum(gap[ok_inside], 1)
    t_out[ok_inside] = translations[lo[ok_inside]] + w[ok_inside, None] * (translations[hi[ok_inside]] - translations[lo[ok_inside]])
    q_out[ok_inside] = slerp(quaternions[lo[ok_inside]], quaternions[hi[ok_inside]], w[ok_inside])
    t_out[exact] = translations[hi[exact]]
    q_out[exact] = quaternions[hi[exact]]
    before = (query < stamps[0]) & (stamps[0] - query <= max_gap_ns)
    after = (query > stamps[-1]) & (query - stamps[-1] <= max_gap_ns)
    t_out[before], q_out[before] = translations[0], quaternions[0]
    t_out[after], q_out[after] = translations[-1], quaternions[-1]
    return t_out, q_out


def slerp(q0: np.ndarray, q1: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Spherical linear interpolation of ``(N, 4)`` unit quaternions at fractions ``(N,)`` in ``[0, 1]``.

    Takes the shorter arc (``q`` and ``-q`` are the same rotation); nearly equal rotations are
    interpolated linearly and renormalised.
    """
    q0 = np.asarray(q0, dtype=np.float64).reshape(-1, 4)
    q1 = np.asarray(q1, dtype=np.float64).reshape(-1, 4)
    w = np.asarray(w, dtype=np.float64).reshape(-1, 1)
    dot = np.sum(q0 * q1, axis=1, keepdims=True)
    q1 = np.where(dot < 0.0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin_theta = np.sin(theta)
    near = sin_theta < 1e-6
    safe = np.where(near, 1.0, sin_theta)
    a = np.where(near, 1.0 - w, np.sin((1.0 - w) * theta) / safe)
    b = np.where(near, w, np.sin(w * theta) / safe)
    out = a * q0 + b * q1
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def _matrices(translations: np.ndarray, quaternions: np.ndarray) -> np.ndarray:
    """``(N, 3)`` + ``(N, 4)`` -> ``(N, 4, 4)``; NaN rows stay NaN."""
    t = np.asarray(translations, dtype=np.float64).reshape(-1, 3)
    q = np.asarray(quaternions, dtype=np.float64).reshape(-1, 4)
    T = np.full((len(t), 4, 4), np.nan)
    good = np.isfinite(t).all(axis=1) & np.isfinite(q).all(axis=1)
    T[good] = np.eye(4)
    if good.any():
        T[good, :3, :3] = quaternion_to_matrix(q[good])
        T[good, :3, 3] = t[good]
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of ``(N, 4, 4)`` rigid transforms (NaN rows stay NaN)."""
    T = np.asarray(T, dtype=np.float64)
    out = np.zeros_like(T)
    R_t = np.swapaxes(T[:, :3, :3], 1, 2)
    out[:, :3, :3] = R_t
    out[:, :3, 3] = -np.einsum("nij,nj->ni", R_t, T[:, :3, 3])
    out[:, 3, 3] = 1.0
    out[~np.isfinite(T).all(axis=(1, 2))] = np.nan
    return out


class TfBuffer:
    """Transforms of ``/tf`` and ``/tf_static``, added message by message, looked up by frame pair."""

    def __init__(self) -> None:
        self._samples: dict[tuple[str, str], list[tuple[int, tuple[float, ...]]]] = {}
        self._static: dict[tuple[str, str], tuple[float, ...]] = {}
        self._edges: dict[str, Edge] | None = None

    def add(
        self, parent: str, child: str, stamp_ns: int, translation: Sequence[float], rotation_xyzw: Sequence[float], *, static: bool = False
    ) -> None:
        """Add one transform ``T_parent_child`` (a ``geometry_msgs/TransformStamped``)."""
        key = (normalize_frame(parent), normalize_frame(child))
        values = (*map(float, translation), *map(float, rotation_xyzw))
        if len(values) != 7:
            raise ValueError("a transform needs 3 translation and 4 rotation values")
        if static:
            self._static[key] = values
        else:
            self._samples.setdefault(key, []).append((int(stamp_ns), values))
        self._edges = None

    @property
    def frames(self) -> list[str]:
        """Every frame id seen, sorted."""
        return sorted({name for key in (*self._samples, *self._static) for name in key})

    def __len__(self) -> int:
        return sum(len(v) for v in self._samples.values()) + len(self._static)

    def edges(self) -> dict[str, Edge]:
        """The forest: child frame -> its :class:`Edge` (one parent per child)."""
        if self._edges is None:
            self._edges = self._build_edges()
        return self._edges

    def _build_edges(self) -> dict[str, Edge]:
        by_child: dict[str, list[Edge]] = {}
        for (parent, child), values in self._static.items():
            v = np.asarray(values, dtype=np.float64)
            by_child.setdefault(child, []).append(
                Edge(parent, child, True, np.zeros(1, dtype=np.int64), v[None, :3], _unit(v[None, 3:]))
            )
        for (parent, child), samples in self._samples.items():
            stamps = np.array([s for s, _ in samples], dtype=np.int64)
            data = np.array([v for _, v in samples], dtype=np.float64)
            order = np.argsort(stamps, kind="stable")
            stamps, data = stamps[order], data[order]
            keep = np.concatenate([[True], np.diff(stamps) > 0])  # a repeated stamp keeps its first sample
            finite = np.isfinite(data).all(axis=1) & (np.linalg.norm(data[:, 3:], axis=1) > 1e-9)
            if not finite.all():
                log.warning("TF %s -> %s: %d transforms with NaN or a zero quaternion are skipped", parent, child, int((~finite).sum()))
            keep &= finite
            if keep.any():
                by_child.setdefault(child, []).append(
                    Edge(parent, child, False, stamps[keep], data[keep, :3], _unit(data[keep, 3:]))
                )
        edges = {}
        for child, candidates in by_child.items():
            best = max(candidates, key=lambda e: (len(e.stamps_ns), e.static))
            if len(candidates) > 1:
                others = ", ".join(sorted(e.parent for e in candidates if e is not best))
                log.warning("TF frame %s has several parents (%s and %s); using %s, the one with the most transforms",
                            child, best.parent, others, best.parent)
            edges[child] = best
        return edges

    # -- chains ------------------------------------------------------------------------------------
    def _ancestors(self, frame: str) -> list[str]:
        edges = self.edges()
        path = [frame]
        while path[-1] in edges:
            parent = edges[path[-1]].parent
            if parent in path:  # a cycle: stop at the repeat
                break
            path.append(parent)
        return path

    def chain(self, parent: str, child: str, *, topics: str = "/tf and /tf_static") -> tuple[list[Edge], list[Edge]]:
        """The edges from the common ancestor down to ``parent`` and down to ``child``.

        Returns ``(up, down)``: ``up`` leads from the common ancestor to ``parent``, ``down`` from
        it to ``child``, each ordered from the ancestor outwards.

        Raises:
            RecorderError: a frame is not in the buffer, or the two frames lie in separate trees;
                the message lists the frames seen and the trees.
        """
        parent, child = normalize_frame(parent), normalize_frame(child)
        seen = self.frames
        missing = [f for f in (parent, child) if f not in seen]
        if missing or not seen:
            raise RecorderError(
                f"no TF chain connects {parent} and {child}: {' and '.join(repr(f) for f in missing) or 'no frame'} "
                f"never appears on {topics} (frames seen: {', '.join(seen) or 'none'})",
                fix=self._fix(),
            )
        up_path, down_path = self._ancestors(parent), self._ancestors(child)
        common = next((f for f in down_path if f in up_path), None)
        if common is None:
            raise RecorderError(
                f"no TF chain connects {parent} and {child} on {topics}: they lie in separate trees "
                f"({self.describe_tree(up_path[-1])} and {self.describe_tree(down_path[-1])}; frames seen: {', '.join(seen)})",
                fix=self._fix(),
            )
        edges = self.edges()
        up = [edges[f] for f in reversed(up_path[: up_path.index(common)])]
        down = [edges[f] for f in reversed(down_path[: down_path.index(common)])]
        return up, down

    def describe_tree(self, root: str) -> str:
        """``"map -> odom -> base_link"``-style text of the tree under ``root`` (breadth first)."""
        children: dict[str, list[str]] = {}
        for child, edge in self.edges().items():
            children.setdefault(edge.parent, []).append(child)
        names, queue = [root], [root]
        while queue and len(names) < 12:
            for kid in sorted(children.get(queue.pop(0), ())):
                if kid not in names:
                    names.append(kid)
                    queue.append(kid)
        more = len(self._subtree(root)) - len(names)
        return f"tree of {root}: " + ", ".join(names) + (f" and {more} more" if more > 0 else "")

    def _subtree(self, root: str) -> set[str]:
        return {f for f in self.frames if self._ancestors(f)[-1] == root}

    def _fix(self) -> str:
        suggestion = self.suggest_odometry_pair()
        example = f"e.g. {suggestion[0]}:{suggestion[1]}" if suggestion else "two frames of one tree"
        return f"pass PARENT:CHILD frames of one TF tree ({example})"

    def lookup(self, parent: str, child: str, stamps_ns: np.ndarray, max_gap_ns: int) -> np.ndarray:
        """``(N, 4, 4)`` ``T_parent_child`` at ``stamps_ns`` (NaN rows where an edge of the chain is refused).

        Raises :class:`RecorderError` when no chain connects the frames (see :meth:`chain`).
        """
        up, down = self.chain(parent, child)
        stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        T_root_parent = _compose([e.at(stamps, max_gap_ns) for e in up], len(stamps))
        T_root_child = _compose([e.at(stamps, max_gap_ns) for e in down], len(stamps))
        return np.einsum("nij,njk->nik", invert(T_root_parent), T_root_child)

    def sample_stamps(self, parent: str, child: str) -> np.ndarray:
        """Stamps at which the chain is observed: those of its densest ``/tf`` edge (empty if all static)."""
        up, down = self.chain(parent, child)
        dynamic = [e for e in (*up, *down) if not e.static]
        if not dynamic:
            return np.zeros(0, dtype=np.int64)
        return max(dynamic, key=lambda e: len(e.stamps_ns)).stamps_ns.copy()

    def dynamic_edges(self) -> list[Edge]:
        """The ``/tf`` edges of the forest, most samples first."""
        return sorted((e for e in self.edges().values() if not e.static), key=lambda e: -len(e.stamps_ns))

    def suggest_odometry_pair(self) -> tuple[str, str] | None:
        """A likely ``--odom-from-tf`` pair (REP 105): ``odom`` to ``base_link`` (or the body frame under ``odom``).

        Returns ``None`` when ``/tf`` has no moving transform.
        """
        dynamic = self.dynamic_edges()
        if not dynamic:
            return None
        from_odom = [e for e in dynamic if e.parent == "odom"]
        edge = from_odom[0] if from_odom else dynamic[0]
        if edge.parent == "odom" and "base_link" in self.frames and self._connected(edge.parent, "base_link"):
            return edge.parent, "base_link"
        return edge.parent, edge.child

    def _connected(self, a: str, b: str) -> bool:
        return self._ancestors(a)[-1] == self._ancestors(b)[-1]


def _unit(q: np.ndarray) -> np.ndarray:
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _compose(transforms: Iterable[np.ndarray], n: int) -> np.ndarray:
    out = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    for T in transforms:
        out = np.einsum("nij,njk->nik", out, T)
    return out
