"""The report's figures: matplotlib (Agg, no pyplot state) from a :class:`RunRecord` to PNG bytes.

Every figure function takes the record and returns ``bytes`` (a PNG) or ``None`` when the run has
nothing to show (no hypotheses, no truth). Colours follow the viewer's legend (accepted true green,
accepted false red, missed orange, rejected grey). PNGs carry no timestamp, so the same record
gives the same bytes.
"""

from __future__ import annotations

import math
import textwrap
from typing import Sequence

import numpy as np

from lcv_replay.sinks.layout import tree_layout
from lcv_replay.sinks.run_record import ANCESTRY_LEAVES, LoopRecord, RunRecord

GREEN = "#23b04a"
RED = "#e0201e"
ORANGE = "#f59e0b"
GREY = "#9a9a9a"
FAINT = "#c8c8d8"
ESTIMATE = "#c99700"
TRUTH = "#3b9dff"
ODOMETRY = "#8c8c8c"
UNKNOWN = "#4a7fd4"
DPI = 100


def _figure(width_in: float, height_in: float):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=DPI, layout="constrained")
    return fig


def _png(fig) -> bytes:
    from lcv_replay.htmlpage import png_bytes

    return png_bytes(fig, dpi=DPI)


# --------------------------------------------------------------------------------------- map
def display_frame(record: RunRecord) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``(estimate_xy, odometry_xy, truth_xy)`` in one frame for drawing.

    With ground truth the map is drawn in its frame: the estimate moved by the SE(2) alignment of
    the ATE, the odometry anchored at the first ground-truth pose (so that its drift shows);
    without, in the odometry frame.
    """
    from lcv_replay import se2
    from lcv_replay.evaluation.metrics import align_se2
    from lcv_replay.sinks.layout import anchor_to_first

    estimate = record.estimate if record.estimate is not None else record.odometry
    est = estimate[:, :2]
    odo = record.odometry[:, :2]
    if record.ground_truth is None:
        return est, odo, None
    gt = record.ground_truth
    known = np.all(np.isfinite(gt[:, :2]), axis=1)
    if known.sum() < 2:
        return est, odo, None
    T = align_se2(est[known], gt[known, :2])
    est = se2.transform_points(T, est)
    first = int(np.flatnonzero(known)[0])
    odo = anchor_to_first(record.odometry[first:], gt[first])[:, :2]
    odo = np.vstack([np.full((first, 2), np.nan), odo])
    truth = np.where(known[:, None], gt[:, :2], np.nan)
    return est, odo, truth


def _segments(xy: np.ndarray, loops: Sequence[LoopRecord]) -> np.ndarray:
    if not loops:
        return np.zeros((0, 2, 2))
    q = np.array([l.query_frame for l in loops])
    m = np.array([l.match_frame for l in loops])
    return np.stack([xy[q], xy[m]], axis=1)


def map_figure(record: RunRecord, *, width_in: float = 9.0, height_in: float = 7.5) -> bytes:
    """The final map: ground truth and odometry under the estimate; accepted loops (true green,
    false red), missed true loops (orange, dashed) and rejected candidates (faint, thin)."""
    from matplotlib.collections import LineCollection

    est, odo, truth = display_frame(record)
    fig = _figure(width_in, height_in)
    ax = fig.subplots()
    rejected = [l for l in record.loops if l.state != "accepted" and not l.missed]
    accepted_true = [l for l in record.loops if l.state == "accepted" and l.truth is not False]
    wrong = [l for l in record.loops if l.wrong]
    missed = [l for l in record.loops if l.missed]
    if rejected:
        ax.add_collection(LineCollection(_segments(est, rejected), colors=FAINT, linewidths=0.4, alpha=0.5, zorder=1,
                                         label=f"rejected ({len(rejected)})"))
    if truth is not None:
        ax.plot(truth[:, 0], truth[:, 1], color=TRUTH, lw=1.2, alpha=0.8, zorder=2, label="ground truth")
    ax.plot(odo[:, 0], odo[:, 1], color=ODOMETRY, lw=0.9, ls="--", zorder=2, label="odometry")
    ax.plot(est[:, 0], est[:, 1], color=ESTIMATE, lw=1.6, zorder=3, label="final estimate")
    if accepted_true:
        label = "accepted, true" if record.has_truth else "accepted"
        ax.add_collection(LineCollection(_segments(est, accepted_true), colors=GREEN, linewidths=1.0, zorder=4,
                                         label=f"{label} ({len(accepted_true)})"))
    if missed:
        ax.add_collection(LineCollection(_segments(est, missed), colors=ORANGE, linewidths=1.3, linestyles="--", zorder=5,
                                         label=f"missed true loop ({len(missed)})"))
    if wrong:
        ax.add_collection(LineCollection(_segments(est, wrong), colors=RED, linewidths=1.8, zorder=6,
                                         label=f"accepted but false ({len(wrong)})"))
    if truth is not None and (wrong or missed):
        # Where the mistakes really are: a false loop joins two places far apart on the ground truth.
        for loops, colour, style, what in ((wrong, RED, "-", "false"), (missed, ORANGE, "--", "missed")):
            segs = _segments(truth, loops)
            segs = segs[np.all(np.isfinite(segs), axis=(1, 2))] if len(segs) else segs
            if len(segs):
                ax.add_collection(LineCollection(segs, colors=colour, linewidths=0.6, linestyles=style, alpha=0.55,
                                                 zorder=2.5, label=f"{what} loops between their true places"))
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    frame = "ground-truth frame (estimate SE(2)-aligned as for the ATE)" if truth is not None else "odometry frame"
    ax.set_title(f"Final map, {frame}", fontsize=10)
    ax.grid(True, lw=0.3, alpha=0.5)
    ax.legend(loc="best", fontsize=8, framealpha=0.85)
    return _png(fig)


# --------------------------------------------------------------------------------------- over time
def metrics_figure(record: RunRecord) -> bytes | None:
    """Precision and recall (fixed 0..1) and ATE over the whole log, one point per window end."""
    if not record.windows:
        return None
    frames = np.array([w.frame_index for w in record.windows])
    fig = _figure(9.0, 4.2)
    top, bottom = fig.subplots(2, 1, sharex=True)

    def values(name: str) -> np.ndarray:
        return np.array([np.nan if getattr(w, name) is None else getattr(w, name) for w in record.windows], dtype=float)

    top.step(frames, values("precision"), where="post", color=GREEN, marker="o", ms=3, label="precision")
    top.step(frames, values("recall"), where="post", color=UNKNOWN, marker="s", ms=3, label="recall")
    top.set_ylim(-0.02, 1.05)
    top.set_ylabel("P / R")
    top.grid(True, lw=0.3)
    top.legend(loc="lower right", fontsize=8)
    if not record.has_truth:
        top.text(0.5, 0.5, "no truth in this log: precision and recall are undefined", ha="center", va="center",
                 transform=top.transAxes, color=GREY)
    ate = values("ate_rmse_m")
    if np.isfinite(ate).any():
        bottom.plot(frames, ate, color=RED, marker="o", ms=3, label="ATE RMSE of the rank-1 estimate")
        bottom.set_ylim(0, max(1.0, float(np.nanmax(ate)) * 1.1))
        bottom.legend(loc="upper left", fontsize=8)
    else:
        bottom.text(0.5, 0.5, "no ground truth: no ATE", ha="center", va="center", transform=bottom.transAxes, color=GREY)
    accepted = values("accepted")
    twin = bottom.twinx()
    twin.plot(frames, accepted, color=GREY, lw=0.8, ls=":", label="accepted loops")
    twin.set_ylabel("accepted", color=GREY)
    bottom.set_ylabel("ATE [m]")
    bottom.set_xlabel("frame (window ends)")
    bottom.set_xlim(0, max(record.frames - 1, 1))
    bottom.grid(True, lw=0.3)
    return _png(fig)


# --------------------------------------------------------------------------------------- Fig. U
def pr_curve(scores: np.ndarray, truth: np.ndarray, *, higher_is_better: bool) -> tuple[np.ndarray, np.ndarray]:
    """Precision and recall of accepting every constraint whose score passes a threshold, for each
    threshold in the scores (a sweep). ``truth``: ``(C,)`` bool of the constraints with known truth.

    Returns:
        ``(precision (T,), recall (T,))`` in the order of a loosening threshold.
    """
    scores = np.asarray(scores, dtype=np.float64)
    truth = np.asarray(truth, dtype=bool)
    ok = np.isfinite(scores)
    scores, truth = scores[ok], truth[ok]
    positives = int(np.asarray(truth).sum())
    if len(scores) == 0 or positives == 0:
        return np.zeros(0), np.zeros(0)
    order = np.argsort(-scores if higher_is_better else scores, kind="stable")
    tp = np.cumsum(truth[order])
    accepted = np.arange(1, len(order) + 1)
    # Only the last position of each tied score is a threshold.
    sorted_scores = scores[order]
    last = np.r_[sorted_scores[1:] != sorted_scores[:-1], True]
    return tp[last] / accepted[last], tp[last] / positives


def pr_figure(record: RunRecord, *, ir_only_count: int = 10) -> bytes | None:
    """The paper's Fig. U: precision–recall. Curves: place recognition alone (thresholding its
    similarity) and the final estimate's ``d²`` (a gate swept over it); points: the verifier at
    each window end and at the end, and the IR-only baseline's expectation (``X`` constraints
    accepted at random: precision = share of true candidates, recall = X / candidates)."""
    known = [l for l in record.loops if l.truth is not None]
    if not known:
        return None
    truth = np.array([l.truth for l in known], dtype=bool)
    fig = _figure(6.5, 5.0)
    ax = fig.subplots()
    p, r = pr_curve(np.array([l.similarity for l in known]), truth, higher_is_better=True)
    if len(p):
        ax.plot(r, p, color=GREY, lw=1.2, label="place recognition alone (similarity threshold)")
    d2 = np.array([np.nan if l.d2 is None else l.d2 for l in known])
    p, r = pr_curve(d2, truth, higher_is_better=False)
    if len(p):
        ax.plot(r, p, color=ESTIMATE, lw=1.4, label="d² under the final estimate (gate swept)")
    windows = [w for w in record.windows if w.precision is not None and w.recall is not None]
    if windows:
        ax.plot([w.recall for w in windows], [w.precision for w in windows], "o-", color=UNKNOWN, ms=4, lw=0.6,
                label=f"{record.method} at each window end")
    final_p, final_r = record.summary.get("precision"), record.summary.get("recall")
    if final_p is not None and final_r is not None:
        ax.plot([final_r], [final_p], "*", color=RED, ms=14, label=f"{record.method}, final")
    positives = int(truth.sum())
    if positives and len(known):
        share = positives / len(known)
        drawn = min(ir_only_count, len(known))
        ax.plot([drawn * share / positives], [share], "D", color="black", ms=6,
                label=f"IR-only baseline, X = {ir_only_count} (expected)")
    ax.set_xlim(-0.02, 1.02)
    ax.set_ylim(-0.02, 1.05)
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_title(f"Precision–recall ({len(known)} constraints, {positives} true)", fontsize=10)
    ax.grid(True, lw=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="lower left", fontsize=7.5)
    if positives == 0:
        ax.text(0.5, 0.5, "no true loop among the constraints: recall is undefined", ha="center", va="center",
                transform=ax.transAxes, color=GREY)
    return _png(fig)


# --------------------------------------------------------------------------------------- Fig. V
def hypotheses_figure(record: RunRecord, *, count: int = 10) -> bytes | None:
    """The paper's Fig. V: the top hypotheses' trajectories at the end, one small map each (rank,
    id, score and ranking key in the title), on the same axes."""
    ranked = [h for h in record.ranking[:count] if h.id in record.top_trajectories]
    if not ranked:
        return None
    cols = min(5, len(ranked))
    rows = math.ceil(len(ranked) / cols)
    fig = _figure(2.2 * cols, 2.3 * rows)
    axes = np.atleast_1d(fig.subplots(rows, cols, sharex=True, sharey=True)).reshape(-1)
    truth = {l.constraint_id: l.truth for l in record.loops}
    for ax, h in zip(axes, ranked):
        traj = record.top_trajectories[h.id]
        ax.plot(record.odometry[:, 0], record.odometry[:, 1], color=ODOMETRY, lw=0.5, ls="--")
        ax.plot(traj[:, 0], traj[:, 1], color=ESTIMATE if h.rank == 1 else UNKNOWN, lw=1.0)
        false_members = sum(1 for c in h.constraint_ids if truth.get(c) is False)
        ax.set_title(f"#{h.rank} H{h.id}: score {h.score}" + (f"\nkey {h.rank_key:.4g}" if h.rank_key != float(h.score) else "")
                     + (f", {false_members} false" if false_members else ""), fontsize=7.5,
                     color=RED if false_members else "black")
        ax.set_aspect("equal", adjustable="box")
        ax.tick_params(labelsize=6)
    for ax in axes[len(ranked):]:
        ax.set_visible(False)
    fig.suptitle("Top hypotheses at the end (odometry dashed)", fontsize=10)
    return _png(fig)


# --------------------------------------------------------------------------------------- Fig. W
def snapshot_windows(record: RunRecord, count: int = 3) -> list[int]:
    """Indices into ``record.consistency`` of ``count`` windows spread over the run (the first
    window with a non-empty matrix, the middle one, the last)."""
    usable = [i for i, s in enumerate(record.consistency) if s.consistent.size]
    if len(usable) <= count:
        return usable
    picks = np.linspace(0, len(usable) - 1, count).round().astype(int)
    return [usable[i] for i in dict.fromkeys(picks.tolist())]


def consistency_figure(record: RunRecord) -> bytes | None:
    """The paper's Fig. W: consistent hypothesis–constraint pairs of the top hypotheses at three
    windows, over the constraints that decide between them; consistent cells coloured by the
    constraint's truth (green true, red false, blue unknown)."""
    from matplotlib.colors import ListedColormap

    picks = snapshot_windows(record)
    if not picks:
        return None
    truth = {l.constraint_id: l.truth for l in record.loops}
    fig = _figure(11.0, 1.0 + 1.0 * len(picks) * 1.9)
    axes = np.atleast_1d(fig.subplots(len(picks), 1)).reshape(-1)
    cmap = ListedColormap(["#eeeeee", GREEN, RED, UNKNOWN])
    for ax, index in zip(axes, picks):
        snap = record.consistency[index]
        code = np.zeros(snap.consistent.shape, dtype=int)
        for c, cid in enumerate(snap.constraint_ids):
            t = truth.get(int(cid))
            code[:, c] = np.where(snap.consistent[:, c], 1 if t is True else 2 if t is False else 3, 0)
        ax.imshow(code, cmap=cmap, vmin=0, vmax=3, aspect="auto", interpolation="nearest")
        ax.set_yticks(range(len(snap.hypothesis_ids)), [f"#{r + 1} H{h}" for r, h in enumerate(snap.hypothesis_ids)], fontsize=6.5)
        ax.set_xticks(range(len(snap.constraint_ids)), [str(c) for c in snap.constraint_ids], fontsize=5.5, rotation=90)
        ax.set_title(f"window {snap.window_index} (frame {snap.frame_index}): top {len(snap.hypothesis_ids)} hypotheses × "
                     f"{len(snap.constraint_ids)} deciding constraints", fontsize=8.5)
    fig.suptitle("Consistent pairs (green: true constraint, red: false, blue: unknown; grey: not consistent)", fontsize=9)
    return _png(fig)


# --------------------------------------------------------------------------------------- Fig. X
def tree_figure(record: RunRecord) -> bytes | None:
    """The paper's Fig. X: the generation graph of the final top hypotheses (their ancestry), left
    to right; each edge is labelled with the constraint(s) the child added (a straight stretch of
    single-child generations is folded into one edge), red where a false constraint entered."""
    from lcv_replay.sinks.layout import compress_chains

    if not record.tree:
        return None
    in_tree = {t.id for t in record.tree}
    leaves = [h.id for h in record.ranking[:ANCESTRY_LEAVES] if h.id in in_tree]
    parents, chains = compress_chains({t.id: t.parent_id for t in record.tree}, {t.id: t.constraint_id for t in record.tree}, leaves)
    positions = tree_layout(list(parents), parents, leaves, dx=1.0, dy=1.0)
    truth = {l.constraint_id: l.truth for l in record.loops}
    depth = max(x for x, _ in positions.values()) + 1
    height = max(y for _, y in positions.values()) + 1
    width_in = min(max(2.0 + 1.6 * depth, 6.0), 16.0)
    fig = _figure(width_in, min(max(1.5 + 0.34 * height, 2.5), 14.0))
    ax = fig.subplots()
    rank = {h.id: h.rank for h in record.ranking}
    for node, parent in parents.items():
        if parent is None or parent not in positions:
            continue
        (x0, y0), (x1, y1) = positions[parent], positions[node]
        added = chains.get(node, ())
        false = [c for c in added if truth.get(c) is False]
        true = [c for c in added if truth.get(c) is True]
        colour = RED if false else GREEN if true else GREY
        ax.plot([x0, x0 + 0.5, x1], [y0, y1, y1], color=colour, lw=1.0)
        ax.text(x0 + 0.55, y1 - 0.12, _edge_label(added, len(false)), fontsize=6, color=colour, va="bottom")
    for node, (x, y) in positions.items():
        r = rank.get(node) if node in leaves else None
        face = ESTIMATE if r == 1 else "#bcd7ff" if r is not None else "white"
        ax.plot([x], [y], "o", ms=5, mfc=face, mec="black", mew=0.6)
        ax.text(x, y + 0.18, f"H{node}" + (f" #{r}" if r is not None else ""), fontsize=6.5, ha="center", va="top")
    # limits that hold every label (a one-row tree would otherwise get a hair-thin y range, its
    # labels far outside it, and constrained layout would collapse the axes)
    ax.set_xlim(-0.5, depth - 0.5)
    ax.set_ylim(height - 0.5, -0.6)
    ax.set_axis_off()
    title = ("Generation graph of the final top hypotheses (left: root; edge: the constraints each child added, "
             "single-child stretches folded; red: a false constraint entered the lineage)")
    ax.set_title("\n".join(textwrap.wrap(title, width=int(13 * width_in))), fontsize=8.5)  # a narrow tree keeps its title
    return _png(fig)


def _edge_label(added: Sequence[int], false: int) -> str:
    if not added:
        return ""
    if len(added) == 1:
        return "absorb" if added[0] < 0 else f"+c{added[0]}"
    named = [c for c in added if c >= 0]
    span = f"c{named[0]}…c{named[-1]}" if len(named) > 1 else (f"c{named[0]}" if named else "absorb")
    return f"+{len(added)} ({span}" + (f", {false} false" if false else "") + ")"


# --------------------------------------------------------------------------------------- timings
def timing_figure(record: RunRecord) -> bytes | None:
    """Seconds per window end, stacked by verifier stage, and the time per frame."""
    stages = sorted({s for w in record.windows for s in w.timings_s if s != "total"})
    if not stages and not len(record.frame_time_s):
        return None
    fig = _figure(9.0, 3.2)
    left, right = fig.subplots(1, 2, width_ratios=[3, 2])
    if stages:
        x = np.arange(len(record.windows))
        bottom = np.zeros(len(record.windows))
        for stage in stages:
            v = np.array([w.timings_s.get(stage, 0.0) for w in record.windows])
            left.bar(x, v, bottom=bottom, label=stage)
            bottom += v
        total = np.array([w.timings_s.get("total", np.nan) for w in record.windows])
        if np.isfinite(total).any():
            left.plot(x, total, "k_", ms=14, label="total")
        left.set_xticks(x, [str(w.window_index) for w in record.windows], fontsize=6)
        left.set_xlabel("window")
        left.set_ylabel("seconds")
        left.legend(fontsize=7)
        left.set_title("verifier time per window, by stage", fontsize=9)
    ft = np.asarray(record.frame_time_s, dtype=float) * 1000.0
    if len(ft):
        right.plot(np.arange(len(ft)), ft, color=GREY, lw=0.5)
        right.set_yscale("log")
        right.set_xlabel("frame")
        right.set_ylabel("ms per frame")
        right.set_title("time per frame (window ends are the spikes)", fontsize=9)
    return _png(fig)
