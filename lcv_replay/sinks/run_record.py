"""The finished run as one record: what the export, the report and the recording's post-mortem read.

:class:`RunRecorder` is a sink. It follows the replay's records (``RunStart``, ``FrameUpdate``,
``StepUpdate``, ``RunSummary``) and, at ``on_finish``, builds a :class:`RunRecord`:

* the per-frame series: stamps, odometry, the final estimate, ground truth, frame times;
* every constraint with its **fate** (:class:`LoopRecord`): final state, truth, the frame at which it
  was first accepted and the frame at which it was last dropped, and its ``d²`` under the final
  estimate;
* every window's metrics and timings (:class:`WindowRecord`);
* the final ranking, the top hypotheses' trajectories, the consistency of the top hypotheses with
  the constraints that decide between them at every window (:class:`ConsistencySnapshot`, the
  paper's Fig. W), and the ancestry of the final top hypotheses (:class:`TreeNode`, Fig. X).

A record converts to plain columns and back (:meth:`RunRecord.to_columns`,
:meth:`RunRecord.from_columns`): the Rerun sink stores those columns in the ``.rrd`` (static
``/postmortem/*`` entities), so that ``lcv-replay report REC.rrd`` rebuilds the same record from a
recording as the replay had at its end. Frames are replay-local (0 = first replayed frame). What
differs between identical runs (wall-clock times, the recording's path) is in its own table,
``volatile``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, fields
from typing import Any, Mapping, Sequence

import numpy as np

from lcv_replay.sinks.base import BaseSink, FrameUpdate, RetrievalUpdate, RunStart, RunSummary, StepUpdate
from lcv_replay.sinks.layout import ancestry, deciding_constraints
from lcv_replay.verification.base import Constraint, HypothesisSummary, VerifierStep

#: Version of the column layout written into recordings (``/postmortem/meta``).
FORMAT_VERSION = 1
#: Rows (top hypotheses) and columns (deciding constraints) of each consistency snapshot.
SNAPSHOT_ROWS = 10
SNAPSHOT_COLUMNS = 60
#: Hypotheses whose ancestry is kept (the final top-k).
ANCESTRY_LEAVES = 10

STATES = ("accepted", "rejected", "pending", "ambiguous")


@dataclass(frozen=True)
class LoopRecord:
    """One constraint and its fate (a row of ``loops.csv``).

    Attributes:
        constraint_id: id in the constraint history (0, 1, ... in arrival order).
        query_frame, match_frame: the frames it joins (replay-local).
        query_stamp_ns, match_stamp_ns: their ``log_time`` stamps.
        arrival_frame: the frame at which it entered the history.
        similarity: place-recognition similarity (source-specific scale).
        hamming: Hamming distance of the binary codes, ``None`` if not from our retrieval.
        source: who proposed it (``retrieval``, ``g2o``, ...).
        measurement: ``(x_m, y_m, yaw_rad)`` measured ``T_match_query`` (identity for "same place").
        information: upper triangle ``(I_xx, I_xy, I_xθ, I_yy, I_yθ, I_θθ)`` of its information
            matrix (the candidate's own, else ``verification.loop_sigmas``).
        state: ``accepted``, ``rejected``, ``pending`` (not judged when the run ended) or
            ``ambiguous`` (the verifier flagged it rather than accept it).
        truth: ``True``/``False`` by labels or ground truth, ``None`` when unknown.
        first_accepted_frame: frame of the first window end at which it was accepted (``None``: never).
        dropped_frame: frame of the last window end at which it left the accepted set (``None``: never).
        d2: whitened squared residual ``rᵀ Ω r`` of its measurement under the final estimate
            (3 degrees of freedom; ``None`` without a final estimate).
    """

    constraint_id: int
    query_frame: int
    match_frame: int
    query_stamp_ns: int
    match_stamp_ns: int
    arrival_frame: int
    similarity: float
    hamming: int | None
    source: str
    measurement: tuple[float, float, float]
    information: tuple[float, float, float, float, float, float]
    state: str
    truth: bool | None
    first_accepted_frame: int | None
    dropped_frame: int | None
    d2: float | None

    @property
    def wrong(self) -> bool:
        """Accepted, but labelled false."""
        return self.state == "accepted" and self.truth is False

    @property
    def missed(self) -> bool:
        """Labelled true, but not accepted."""
        return self.state != "accepted" and self.truth is True

    @property
    def later(self) -> str:
        """What became of it after it was accepted, in words (``""`` if it ended accepted or was
        never accepted): e.g. ``"flagged ambiguous from frame 1999"``."""
        if self.first_accepted_frame is None or self.state == "accepted":
            return ""
        if self.state == "pending":
            return "undecided at the end"
        what = "flagged ambiguous" if self.state == "ambiguous" else "refused"
        return f"{what} from frame {self.dropped_frame}" if self.dropped_frame is not None else f"{what} by the end"


@dataclass(frozen=True)
class WindowRecord:
    """Metrics after one verifier step (window end); ``None`` where undefined (see evaluation)."""

    window_index: int
    frame_index: int
    constraints: int
    accepted: int
    true_positives: int | None
    false_positives: int | None
    false_negatives: int | None
    precision: float | None
    recall: float | None
    ate_rmse_m: float | None
    hypotheses: int | None
    gate_chi2: float | None
    rank1_id: int | None
    rank1_score: int | None
    rank1_key: float | None
    timings_s: Mapping[str, float] = field(default_factory=dict)
    final: bool = False


def same(a: Any, b: Any) -> bool:
    """Deep equality over records, mappings, sequences and arrays (NaN equals NaN)."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        if a.dtype.kind in "fc" or b.dtype.kind in "fc":
            return a.shape == b.shape and bool(np.array_equal(a, b, equal_nan=True))
        return a.shape == b.shape and bool(np.array_equal(a, b))
    if hasattr(a, "__dataclass_fields__") and type(a) is type(b):
        return all(same(getattr(a, f.name), getattr(b, f.name)) for f in fields(a))
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return a == b


@dataclass(frozen=True, eq=False)
class ConsistencySnapshot:
    """The top hypotheses × the constraints that decide between them, at one window end.

    Attributes:
        hypothesis_ids: ``(K,)`` rows in rank order.
        constraint_ids: ``(D,)`` columns (:func:`~lcv_replay.sinks.layout.deciding_constraints`).
        consistent: ``(K, D)`` bool.
    """

    window_index: int
    frame_index: int
    hypothesis_ids: np.ndarray
    constraint_ids: np.ndarray
    consistent: np.ndarray

    def __eq__(self, other: object) -> bool:
        return isinstance(other, ConsistencySnapshot) and same(self, other)


@dataclass(frozen=True)
class TreeNode:
    """A hypothesis in the ancestry of the final top hypotheses (the paper's Fig. X).

    ``constraint_id`` is the constraint its parent was extended by (``-1``: the parent absorbed
    every constraint consistent with it; ``None``: a root or unknown).
    """

    id: int
    parent_id: int | None
    constraint_id: int | None
    window: int


@dataclass(frozen=True, eq=False)
class RunRecord:
    """Everything a post-mortem of one replay needs (see the module docstring).

    Attributes:
        log, method, constraint_source, truth_source, seed, config, log_metadata: as in ``RunStart``.
        frames: replayed frames ``N``; ``first_log_frame``: the log's index of frame 0.
        summary: ``RunSummary.to_json_dict()``.
        stamps_ns: ``(N,)`` int64 ``log_time`` of each frame.
        odometry: ``(N, 3)`` cumulative odometry ``[x_m, y_m, yaw_rad]``.
        estimate: ``(N, 3)`` the final best estimate (rank 1, extended by odometry), or ``None``.
        ground_truth: ``(N, 3)`` ground truth (NaN rows where unknown), or ``None``.
        frame_time_s: ``(N,)`` wall-clock seconds spent on each frame.
        odometry_information: ``(3, 3)`` information of one odometry step.
        loops: one :class:`LoopRecord` per constraint, by id.
        windows: one :class:`WindowRecord` per verifier step.
        ranking: the final ranking (best first).
        top_trajectories: ``{hypothesis_id: (N, 3)}`` of the final top hypotheses.
        consistency: one :class:`ConsistencySnapshot` per window end.
        tree: the ancestry of the final top hypotheses.
        first_missed: ``(frame, constraint_id)``: the first window end at which a true constraint
            that had arrived was not accepted, or ``None``.
        queries: frames that went through retrieval as queries (``None``: retrieval did not run).
    """

    log: str
    method: str
    constraint_source: str
    truth_source: str
    seed: int
    config: Mapping[str, Any]
    log_metadata: Mapping[str, Any]
    frames: int
    first_log_frame: int
    summary: Mapping[str, Any]
    stamps_ns: np.ndarray
    odometry: np.ndarray
    estimate: np.ndarray | None
    ground_truth: np.ndarray | None
    frame_time_s: np.ndarray
    odometry_information: np.ndarray
    loops: tuple[LoopRecord, ...]
    windows: tuple[WindowRecord, ...]
    ranking: tuple[HypothesisSummary, ...]
    top_trajectories: Mapping[int, np.ndarray]
    consistency: tuple[ConsistencySnapshot, ...]
    tree: tuple[TreeNode, ...]
    first_missed: tuple[int, int] | None = None
    queries: int | None = None

    def __eq__(self, other: object) -> bool:
        return isinstance(other, RunRecord) and same(self, other)

    # ------------------------------------------------------------------ questions a user asks
    @property
    def has_truth(self) -> bool:
        return self.truth_source != "none"

    def first_wrong_acceptance(self) -> LoopRecord | None:
        """The constraint whose (first) acceptance came first among those labelled false and ever
        accepted (ties: the lower id); ``None`` without truth or without such a constraint."""
        wrong = [loop for loop in self.loops if loop.truth is False and loop.first_accepted_frame is not None]
        return min(wrong, key=lambda loop: (loop.first_accepted_frame, loop.constraint_id), default=None)

    def flagged_words(self) -> str:
        """What the loops the verifier flagged ambiguous are, in words (``""`` if none), e.g.
        ``"flagged rather than accepted: ... (10 false, 0 true by the truth)"``; their number is
        ``counts()["ambiguous"]``."""
        flagged = [loop for loop in self.loops if loop.state == "ambiguous"]
        if not flagged:
            return ""
        text = "flagged rather than accepted: the verifier could not tell them from true loops"
        if self.has_truth:
            false = sum(loop.truth is False for loop in flagged)
            text += f" ({false} false, {sum(loop.truth is True for loop in flagged)} true by the truth)"
        return text

    def first_missed_loop(self) -> LoopRecord | None:
        """The true constraint that was first left out at a window end after it had arrived
        (:attr:`first_missed`); ``None`` if every true loop was accepted at its first window end."""
        if self.first_missed is None:
            return None
        return self.loops[self.first_missed[1]]

    def counts(self) -> dict[str, int]:
        """Constraints by final state, and the wrong and missed ones."""
        out = {state: 0 for state in STATES}
        for loop in self.loops:
            out[loop.state] = out.get(loop.state, 0) + 1
        out["wrong"] = sum(loop.wrong for loop in self.loops)
        out["missed"] = sum(loop.missed for loop in self.loops)
        return out

    # ------------------------------------------------------------------ columns
    def to_columns(self) -> dict[str, dict[str, Any]]:
        """The record as ``{table: {column: array or list}}`` (every column of a table has one
        value per row), plus ``meta`` with one JSON string. :meth:`from_columns` inverts it."""
        n = self.frames
        nan3 = np.full((n, 3), np.nan)
        est = self.estimate if self.estimate is not None else nan3
        gt = self.ground_truth if self.ground_truth is not None else nan3
        meta = {
            "format_version": FORMAT_VERSION,
            "log": self.log, "method": self.method, "constraint_source": self.constraint_source,
            "truth_source": self.truth_source, "seed": self.seed, "config": dict(self.config),
            "log_metadata": dict(self.log_metadata), "frames": self.frames, "first_log_frame": self.first_log_frame,
            "summary": {k: v for k, v in self.summary.items() if k not in VOLATILE_SUMMARY_KEYS},
            "has_estimate": self.estimate is not None,
            "has_ground_truth": self.ground_truth is not None,
            "odometry_information": np.asarray(self.odometry_information, dtype=float).tolist(),
            "first_missed": None if self.first_missed is None else list(self.first_missed),
            "queries": self.queries,
        }
        frames = {
            "stamp_ns": np.asarray(self.stamps_ns, dtype=np.int64),
            "odom_x_m": self.odometry[:, 0], "odom_y_m": self.odometry[:, 1], "odom_yaw_rad": self.odometry[:, 2],
            "est_x_m": est[:, 0], "est_y_m": est[:, 1], "est_yaw_rad": est[:, 2],
            "gt_x_m": gt[:, 0], "gt_y_m": gt[:, 1], "gt_yaw_rad": gt[:, 2],
        }
        volatile = {
            "frame_time_s": np.asarray(self.frame_time_s, dtype=np.float64),
            "json": json.dumps({"summary": {k: self.summary.get(k) for k in VOLATILE_SUMMARY_KEYS},
                                "windows": [dict(w.timings_s) for w in self.windows]}, sort_keys=True),
        }
        loops = {
            "constraint_id": _ints([l.constraint_id for l in self.loops]),
            "query_frame": _ints([l.query_frame for l in self.loops]),
            "match_frame": _ints([l.match_frame for l in self.loops]),
            "query_stamp_ns": _ints([l.query_stamp_ns for l in self.loops]),
            "match_stamp_ns": _ints([l.match_stamp_ns for l in self.loops]),
            "arrival_frame": _ints([l.arrival_frame for l in self.loops]),
            "similarity": _floats([l.similarity for l in self.loops]),
            "hamming": _ints([l.hamming for l in self.loops]),
            "source": [l.source for l in self.loops],
            "measurement": _floats([v for l in self.loops for v in l.measurement]),
            "information": _floats([v for l in self.loops for v in l.information]),
            "state": [l.state for l in self.loops],
            "truth": np.array([-1 if l.truth is None else int(l.truth) for l in self.loops], dtype=np.int8),
            "first_accepted_frame": _ints([l.first_accepted_frame for l in self.loops]),
            "dropped_frame": _ints([l.dropped_frame for l in self.loops]),
            "d2": _floats([l.d2 for l in self.loops]),
        }
        windows = {f.name: [] for f in fields(WindowRecord) if f.name != "timings_s"}
        for w in self.windows:
            for name in windows:
                windows[name].append(getattr(w, name))
        windows = {
            name: (_floats(values) if name in _FLOAT_WINDOW_FIELDS
                   else np.asarray(values, dtype=bool) if name == "final" else _ints(values))
            for name, values in windows.items()
        }
        ranking = {
            "id": _ints([h.id for h in self.ranking]), "parent_id": _ints([h.parent_id for h in self.ranking]),
            "score": _ints([h.score for h in self.ranking]), "rank": _ints([h.rank for h in self.ranking]),
            "window": _ints([h.window for h in self.ranking]), "chi2": _floats([h.chi2 for h in self.ranking]),
            "rank_key": _floats([h.rank_key for h in self.ranking]),
            "constraint_ids": [json.dumps(list(h.constraint_ids)) for h in self.ranking],
        }
        ids = sorted(self.top_trajectories)
        top = {
            "hypothesis_id": _ints([h for h in ids for _ in range(len(self.top_trajectories[h]))]),
            "x_m": _floats([v for h in ids for v in self.top_trajectories[h][:, 0]]),
            "y_m": _floats([v for h in ids for v in self.top_trajectories[h][:, 1]]),
            "yaw_rad": _floats([v for h in ids for v in self.top_trajectories[h][:, 2]]),
        }
        cells: dict[str, list] = {k: [] for k in ("window_index", "frame_index", "row", "hypothesis_id", "column", "constraint_id", "consistent")}
        for snap in self.consistency:
            for r, hid in enumerate(snap.hypothesis_ids):
                for c, cid in enumerate(snap.constraint_ids):
                    cells["window_index"].append(snap.window_index)
                    cells["frame_index"].append(snap.frame_index)
                    cells["row"].append(r)
                    cells["hypothesis_id"].append(int(hid))
                    cells["column"].append(c)
                    cells["constraint_id"].append(int(cid))
                    cells["consistent"].append(bool(snap.consistent[r, c]))
            if len(snap.hypothesis_ids) == 0 or len(snap.constraint_ids) == 0:  # keep the window
                for key, value in (("window_index", snap.window_index), ("frame_index", snap.frame_index), ("row", -1),
                                   ("hypothesis_id", -1), ("column", -1), ("constraint_id", -1), ("consistent", False)):
                    cells[key].append(value)
        consistency = {k: (np.asarray(v, dtype=bool) if k == "consistent" else _ints(v)) for k, v in cells.items()}
        tree = {
            "id": _ints([t.id for t in self.tree]), "parent_id": _ints([t.parent_id for t in self.tree]),
            "constraint_id": _ints([t.constraint_id for t in self.tree]), "window": _ints([t.window for t in self.tree]),
        }
        return {
            "meta": {"json": json.dumps(meta, sort_keys=True, allow_nan=True)},
            "volatile": volatile,
            "frames": frames, "loops": loops, "windows": windows, "ranking": ranking,
            "top_trajectories": top, "consistency": consistency, "tree": tree,
        }

    @classmethod
    def from_columns(cls, tables: Mapping[str, Mapping[str, Any]]) -> "RunRecord":
        """Inverse of :meth:`to_columns` (columns may be lists or arrays).

        Raises:
            KeyError, ValueError: a table or column is missing or malformed.
        """
        meta_text = tables["meta"]["json"]
        meta = json.loads(meta_text[0] if isinstance(meta_text, (list, tuple, np.ndarray)) else meta_text)
        if meta.get("format_version") != FORMAT_VERSION:
            raise ValueError(f"post-mortem format version {meta.get('format_version')} (this lcv-replay reads {FORMAT_VERSION})")
        f = {k: np.asarray(v, dtype=np.int64 if k == "stamp_ns" else np.float64) for k, v in tables["frames"].items()}
        timing_text = tables["volatile"]["json"]
        timing = json.loads(timing_text[0] if isinstance(timing_text, (list, tuple, np.ndarray)) else timing_text)
        summary = {**meta["summary"], **timing["summary"]}
        n = int(meta["frames"])
        odometry = np.column_stack([f["odom_x_m"], f["odom_y_m"], f["odom_yaw_rad"]]).astype(np.float64).reshape(n, 3)
        estimate = np.column_stack([f["est_x_m"], f["est_y_m"], f["est_yaw_rad"]]).astype(np.float64).reshape(n, 3) if meta["has_estimate"] else None
        gt = np.column_stack([f["gt_x_m"], f["gt_y_m"], f["gt_yaw_rad"]]).astype(np.float64).reshape(n, 3) if meta["has_ground_truth"] else None
        lt = tables["loops"]
        count = len(lt["constraint_id"])
        meas = np.asarray(lt["measurement"], dtype=np.float64).reshape(count, 3)
        info = np.asarray(lt["information"], dtype=np.float64).reshape(count, 6)
        lt = {k: (np.asarray(v, dtype=np.float64) if k in ("similarity", "d2") else v) for k, v in lt.items()}
        loops = tuple(
            LoopRecord(
                constraint_id=int(lt["constraint_id"][i]), query_frame=int(lt["query_frame"][i]),
                match_frame=int(lt["match_frame"][i]), query_stamp_ns=int(lt["query_stamp_ns"][i]),
                match_stamp_ns=int(lt["match_stamp_ns"][i]), arrival_frame=int(lt["arrival_frame"][i]),
                similarity=float(lt["similarity"][i]), hamming=_int_or_none(lt["hamming"][i]), source=str(lt["source"][i]),
                measurement=tuple(float(v) for v in meas[i]), information=tuple(float(v) for v in info[i]),
                state=str(lt["state"][i]), truth=None if int(lt["truth"][i]) < 0 else bool(int(lt["truth"][i])),
                first_accepted_frame=_int_or_none(lt["first_accepted_frame"][i]),
                dropped_frame=_int_or_none(lt["dropped_frame"][i]), d2=_float_or_none(lt["d2"][i]),
            )
            for i in range(count)
        )
        wt = tables["windows"]
        windows = []
        for i in range(len(wt["window_index"])):
            values: dict[str, Any] = {"timings_s": timing["windows"][i]}
            for fd in fields(WindowRecord):
                if fd.name == "timings_s":
                    continue
                raw = wt[fd.name][i]
                if fd.name == "final":
                    values[fd.name] = bool(raw)
                elif fd.name in _FLOAT_WINDOW_FIELDS:
                    values[fd.name] = _float_or_none(raw)
                else:
                    values[fd.name] = _int_or_none(raw)
            windows.append(WindowRecord(**values))
        rt = tables["ranking"]
        ranking = tuple(
            HypothesisSummary(
                id=int(rt["id"][i]), parent_id=_int_or_none(rt["parent_id"][i]),
                constraint_ids=tuple(int(c) for c in json.loads(rt["constraint_ids"][i])), score=int(rt["score"][i]),
                rank=int(rt["rank"][i]), window=int(rt["window"][i]), chi2=_float_or_none(rt["chi2"][i]),
                rank_key=float(rt["rank_key"][i]),
            )
            for i in range(len(rt["id"]))
        )
        tt = {k: np.asarray(v, dtype=np.int64 if k == "hypothesis_id" else np.float64) for k, v in tables["top_trajectories"].items()}
        top: dict[int, np.ndarray] = {}
        for hid in dict.fromkeys(int(h) for h in tt["hypothesis_id"]):
            rows = tt["hypothesis_id"] == hid
            top[hid] = np.column_stack([tt["x_m"][rows], tt["y_m"][rows], tt["yaw_rad"][rows]]).astype(np.float64)
        ct = {k: np.asarray(v) for k, v in tables["consistency"].items()}
        snapshots = []
        for window in dict.fromkeys(int(w) for w in ct["window_index"]):
            rows = ct["window_index"] == window
            r, c = ct["row"][rows], ct["column"][rows]
            real = r >= 0
            k = int(r[real].max()) + 1 if real.any() else 0
            d = int(c[real].max()) + 1 if real.any() else 0
            hyp = np.zeros(k, dtype=np.int64)
            con = np.zeros(d, dtype=np.int64)
            mat = np.zeros((k, d), dtype=bool)
            hyp[r[real]] = ct["hypothesis_id"][rows][real]
            con[c[real]] = ct["constraint_id"][rows][real]
            mat[r[real], c[real]] = ct["consistent"][rows][real]
            snapshots.append(ConsistencySnapshot(window, int(ct["frame_index"][rows][0]), hyp, con, mat))
        tr = tables["tree"]
        tree = tuple(
            TreeNode(int(tr["id"][i]), _int_or_none(tr["parent_id"][i]), _int_or_none(tr["constraint_id"][i]), int(tr["window"][i]))
            for i in range(len(tr["id"]))
        )
        return cls(
            log=meta["log"], method=meta["method"], constraint_source=meta["constraint_source"],
            truth_source=meta["truth_source"], seed=int(meta["seed"]), config=meta["config"],
            log_metadata=meta["log_metadata"], frames=n, first_log_frame=int(meta["first_log_frame"]),
            summary={k: summary[k] for k in summary_order(summary)}, stamps_ns=np.asarray(f["stamp_ns"], dtype=np.int64),
            odometry=odometry, estimate=estimate, ground_truth=gt,
            frame_time_s=np.asarray(tables["volatile"]["frame_time_s"], dtype=np.float64),  # None (null) -> NaN
            odometry_information=np.asarray(meta["odometry_information"], dtype=np.float64).reshape(3, 3),
            loops=loops, windows=tuple(windows), ranking=ranking, top_trajectories=top,
            consistency=tuple(snapshots), tree=tree,
            first_missed=None if meta.get("first_missed") is None else tuple(int(v) for v in meta["first_missed"]),
            queries=meta.get("queries"),
        )


#: Summary keys that differ between identical runs (wall-clock figures, the recording's own path):
#: stored apart (``/postmortem/volatile``), so that the rest of a recording is a deterministic
#: function of the log, the config and the seed.
VOLATILE_SUMMARY_KEYS = ("wall_time_s", "x_real_time", "setup_time_s", "rrd")


def summary_order(summary: Mapping[str, Any]) -> list[str]:
    """The keys of a summary dict in ``RunSummary.to_json_dict`` order (stable keys first)."""
    from lcv_replay.sinks.base import SUMMARY_KEYS

    head = [k for k in SUMMARY_KEYS if k in summary]
    context = ["x_real_time", "rate_requested", "setup_time_s", "interrupted", "log", "rrd", "constraint_source",
               "truth_source", "seed", "accepted_constraint_ids", "config"]
    rest = [k for k in context if k in summary and k not in head]
    return head + rest + [k for k in summary if k not in head and k not in rest]


_FLOAT_WINDOW_FIELDS = {"precision", "recall", "ate_rmse_m", "gate_chi2", "rank1_key"}
_NONE_INT = np.iinfo(np.int64).min  # ``None`` in an int64 column


def _ints(values: Sequence[int | None]) -> np.ndarray:
    return np.array([_NONE_INT if v is None else int(v) for v in values], dtype=np.int64)


def _floats(values: Sequence[float | None]) -> np.ndarray:
    return np.array([np.nan if v is None else float(v) for v in values], dtype=np.float64)


def _int_or_none(value: Any) -> int | None:
    v = int(value)
    return None if v == _NONE_INT else v


def _float_or_none(value: Any) -> float | None:
    if value is None:
        return None
    v = float(value)
    return None if math.isnan(v) else v


# --------------------------------------------------------------------------------------- the recorder
class RunRecorder(BaseSink):
    """Builds the :class:`RunRecord` of a replay from the sink calls; :attr:`record` is set at
    ``on_finish`` (also after Ctrl-C, as of the last completed window)."""

    def __init__(self, *, top_hypotheses: int = ANCESTRY_LEAVES):
        self.top_hypotheses = top_hypotheses
        self.record: RunRecord | None = None
        self._start: RunStart | None = None
        self._stamps: list[int] = []
        self._odometry: list[tuple[float, float, float]] = []
        self._frame_time: list[float] = []
        self._frame_truth: list[tuple[float, float, float]] = []  # each frame's own ground truth (NaN: none)
        self._constraints: list[Constraint] = []
        self._truth: list[bool | None] = []
        self._first_accepted: dict[int, int] = {}
        self._dropped: dict[int, int] = {}
        self._accepted: set[int] = set()
        self._windows: list[WindowRecord] = []
        self._snapshots: list[ConsistencySnapshot] = []
        self._tree: dict[int, tuple[int | None, int | None, int]] = {}
        self._last: StepUpdate | None = None
        self._first_missed: tuple[int, int] | None = None
        self._queries: int | None = None

    def on_start(self, start: RunStart) -> None:
        self._start = start

    def on_frame(self, update: FrameUpdate) -> None:
        frame = update.frame
        self._stamps.append(int(frame.stamp_ns))
        odom = frame.odom
        if odom is not None:
            self._odometry.append((float(odom.x_m), float(odom.y_m), float(odom.yaw_rad)))
        else:
            self._odometry.append(self._odometry[-1] if self._odometry else (0.0, 0.0, 0.0))
        self._frame_time.append(float(update.frame_time_s))
        gt = frame.ground_truth
        self._frame_truth.append((np.nan, np.nan, np.nan) if gt is None else (float(gt.x_m), float(gt.y_m), float(gt.yaw_rad)))
        self._constraints.extend(update.new_constraints)
        self._truth.extend(update.new_constraint_truth)

    def on_retrieval(self, update: RetrievalUpdate) -> None:
        if update.code is not None:
            self._queries = (self._queries or 0) + 1

    def on_step(self, update: StepUpdate) -> None:
        step, metrics = update.step, update.metrics
        frame = step.frame_index
        accepted = {int(i) for i in step.accepted_constraint_ids}
        for cid in accepted:
            self._first_accepted.setdefault(cid, frame)
        for cid in self._accepted - accepted:
            self._dropped[cid] = frame
        self._accepted = accepted
        if self._first_missed is None:
            missed = [c.id for c, t in zip(update.constraints, update.constraint_truth)
                      if t is True and c.arrival_frame <= frame and c.id not in accepted]
            if missed:
                self._first_missed = (frame, min(missed))
        if len(update.constraint_truth) > len(self._truth):  # a sink fed steps only (tests, bench)
            self._truth = list(update.constraint_truth)
            self._constraints = list(update.constraints)
        det = metrics.detection
        top = step.ranking[0] if step.ranking else None
        self._windows.append(WindowRecord(
            window_index=step.window_index, frame_index=frame, constraints=metrics.constraints, accepted=det.accepted,
            true_positives=det.true_positives, false_positives=det.false_positives, false_negatives=det.false_negatives,
            precision=det.precision, recall=det.recall, ate_rmse_m=metrics.ate_rmse_m, hypotheses=metrics.hypotheses,
            gate_chi2=step.gate_chi2, rank1_id=None if top is None else top.id, rank1_score=None if top is None else top.score,
            rank1_key=None if top is None else top.rank_key, timings_s=dict(step.timings_s), final=update.final,
        ))
        self._snapshots.append(consistency_snapshot(step))
        grow_tree(self._tree, step)
        self._last = update

    def on_finish(self, summary: RunSummary) -> None:
        self.record = self._build(summary)

    def _build(self, summary: RunSummary) -> RunRecord:
        start = self._start
        n = len(self._stamps)
        odometry = np.asarray(self._odometry, dtype=np.float64).reshape(n, 3)
        stamps = np.asarray(self._stamps, dtype=np.int64)
        step = self._last.step if self._last is not None else None
        from lcv_replay.evaluation.metrics import top_trajectory
        from lcv_replay.verification.measurements import extend_by_odometry

        estimate = None
        top_trajectories: dict[int, np.ndarray] = {}
        if step is not None and n:
            best = top_trajectory(step)
            if best is not None and len(best):
                estimate = extend_by_odometry(np.asarray(best, dtype=np.float64)[:n], odometry)
            for h in step.ranking[: self.top_hypotheses]:
                traj = step.trajectories.get(h.id)
                if traj is not None and len(traj):
                    top_trajectories[h.id] = extend_by_odometry(np.asarray(traj, dtype=np.float64)[:n], odometry)
        # The start's ground truth; past its end (a followed log still being written), each frame's.
        ground_truth = np.asarray(self._frame_truth, dtype=np.float64).reshape(n, 3)
        if start.ground_truth is not None and len(start.ground_truth):
            gt = np.asarray(start.ground_truth, dtype=np.float64)[:n]
            ground_truth[: len(gt)] = gt
        if not np.isfinite(ground_truth).any():
            ground_truth = None
        config = dict(start.config)
        loop_info, odom_info = _default_informations(config, start.log_metadata)
        ambiguous = {int(i) for i in step.ambiguous_constraint_ids} if step is not None else set()
        loops = self._loops(stamps, estimate, loop_info, step, ambiguous, summary)
        tree_ids = ancestry(self._tree, [h.id for h in step.ranking[: self.top_hypotheses]]) if step is not None else []
        return RunRecord(
            log=str(start.log_path), method=start.method, constraint_source=start.constraint_source,
            truth_source=summary.truth_source, seed=int(start.seed), config=config, log_metadata=_plain(dict(start.log_metadata)),
            frames=n, first_log_frame=int(start.first_log_frame), summary=summary.to_json_dict(),
            stamps_ns=stamps, odometry=odometry, estimate=estimate, ground_truth=ground_truth,
            frame_time_s=np.asarray(self._frame_time, dtype=np.float64), odometry_information=odom_info,
            loops=loops, windows=tuple(self._windows), ranking=tuple(step.ranking) if step is not None else (),
            top_trajectories=top_trajectories, consistency=tuple(self._snapshots),
            tree=tuple(TreeNode(i, self._tree[i][0], self._tree[i][1], self._tree[i][2]) for i in tree_ids),
            first_missed=self._first_missed, queries=self._queries,
        )

    def _loops(self, stamps, estimate, loop_info, step: VerifierStep | None, ambiguous: set[int], summary: RunSummary) -> tuple[LoopRecord, ...]:
        from lcv_replay.se2 import between_chi2
        from lcv_replay.verification.measurements import loop_arrays

        constraints = self._constraints
        if not constraints:
            return ()
        match, query, measured, info = loop_arrays(constraints, loop_info)
        d2 = between_chi2(estimate, match, query, measured, info) if estimate is not None else np.full(len(constraints), np.nan)
        accepted = set(summary.accepted_constraint_ids) if step is not None else set()
        last_frame = step.frame_index if step is not None else -1
        out = []
        for k, c in enumerate(constraints):
            if c.id in accepted:
                state = "accepted"
            elif c.id in ambiguous:
                state = "ambiguous"
            elif c.arrival_frame > last_frame:
                state = "pending"
            else:
                state = "rejected"
            omega = info[k]
            out.append(LoopRecord(
                constraint_id=c.id, query_frame=c.query_frame, match_frame=c.match_frame,
                query_stamp_ns=int(stamps[c.query_frame]), match_stamp_ns=int(stamps[c.match_frame]),
                arrival_frame=c.arrival_frame, similarity=float(c.candidate.similarity),
                hamming=None if c.candidate.hamming is None else int(c.candidate.hamming), source=str(c.candidate.source),
                measurement=tuple(float(v) for v in measured[k]),
                information=(omega[0, 0], omega[0, 1], omega[0, 2], omega[1, 1], omega[1, 2], omega[2, 2]),
                state=state, truth=self._truth[k] if k < len(self._truth) else None,
                first_accepted_frame=self._first_accepted.get(c.id), dropped_frame=self._dropped.get(c.id),
                d2=None if not np.isfinite(d2[k]) else float(d2[k]),
            ))
        return tuple(out)


def consistency_snapshot(step: VerifierStep, *, rows: int = SNAPSHOT_ROWS, columns: int = SNAPSHOT_COLUMNS) -> ConsistencySnapshot:
    """The top ``rows`` hypotheses that have a consistency row × the deciding constraints of one
    step (``ilv+`` on measured loops has one row, its working hypothesis: the alternatives of its
    contests are ranked by their cost, not solved to the end)."""
    matrix = np.asarray(step.consistency, dtype=bool)
    ids = np.array([h.id for h in step.ranking[:rows]], dtype=np.int64)
    if matrix.ndim == 2:
        ids = ids[: matrix.shape[0]]
    if matrix.ndim != 2 or not len(ids):
        return ConsistencySnapshot(step.window_index, step.frame_index, np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 0), bool))
    cols = deciding_constraints(matrix, rows=len(ids), max_columns=columns)
    return ConsistencySnapshot(step.window_index, step.frame_index, ids, cols, matrix[: len(ids)][:, cols])


def grow_tree(tree: dict[int, tuple[int | None, int | None, int]], step: VerifierStep) -> None:
    """Add a step's new hypotheses and generation edges to ``{id: (parent, constraint, window)}``."""
    for h in step.new_hypotheses:
        tree.setdefault(h.id, (h.parent_id, None, h.window))
    for parent, child, cid in step.generation_edges:
        window = tree[child][2] if child in tree else step.window_index
        tree[child] = (parent, cid, window)
    for h in step.ranking:
        tree.setdefault(h.id, (h.parent_id, None, h.window))


def _default_informations(config: Mapping[str, Any], log_metadata: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """``(loop, odometry)`` ``(3, 3)`` information matrices: the log's odometry information if it
    carries one, else the config's sigmas."""
    verification = dict(config.get("verification", {}))
    loop_sigmas = np.asarray(verification.get("loop_sigmas", (2.0, 2.0, 0.2)), dtype=np.float64)
    odom_sigmas = np.asarray(verification.get("odometry_sigmas", (0.05, 0.05, 0.002)), dtype=np.float64)
    odom = np.diag(1.0 / np.square(odom_sigmas))
    raw = log_metadata.get("odometry_information") if log_metadata else None
    if raw is not None:
        try:
            parsed = np.asarray(json.loads(raw) if isinstance(raw, str) else raw, dtype=np.float64)
            if parsed.size == 9 and np.all(np.isfinite(parsed)):
                odom = parsed.reshape(3, 3)
        except (TypeError, ValueError):
            pass
    return np.diag(1.0 / np.square(loop_sigmas)), odom


def _plain(value: Any) -> Any:
    """JSON-ready copy (numpy scalars and arrays to Python)."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value

