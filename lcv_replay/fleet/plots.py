"""Figures of the fleet and compare pages (matplotlib, object API, no pyplot state), as PNG bytes.

Each returns ``None`` when there is nothing to draw (no log with the figure).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from lcv_replay.fleet.table import FleetRow

RED, BLUE, GREY, GREEN = "#d62728", "#1f77b4", "#9a9a9a", "#2ca02c"


def _figure(width_in: float, height_in: float, ncols: int = 1):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), layout="constrained")
    axes = fig.subplots(1, ncols)
    return fig, np.atleast_1d(axes)


def _integer_ticks(axis) -> None:
    from matplotlib.ticker import MaxNLocator

    axis.set_major_locator(MaxNLocator(integer=True))


def _png(fig) -> bytes:
    from lcv_replay.htmlpage import png_bytes

    return png_bytes(fig)


def detection_figure(rows: Sequence[FleetRow]) -> bytes | None:
    """Per log: recall (x) against wrong acceptances (y); red where a wrong loop was accepted."""
    judged = [r for r in rows if r.done and r.recall is not None and r.false_positives is not None]
    if not judged:
        return None
    fig, (ax,) = _figure(8.0, 4.2)
    recall = np.array([r.recall for r in judged])
    fp = np.array([r.false_positives for r in judged], dtype=float)
    jitter = np.random.default_rng(0).uniform(-0.12, 0.12, len(judged))  # overlapping zeros stay visible
    colors = [RED if r.false_positives else BLUE for r in judged]
    ax.scatter(recall, fp + jitter * (fp == 0), c=colors, s=28, alpha=0.8, edgecolors="none")
    worst = sorted(judged, key=lambda r: (-(r.false_positives or 0), r.recall))[:5]
    for r in worst:
        if r.false_positives:
            ax.annotate(r.name, (r.recall, r.false_positives), fontsize=7, xytext=(4, 3), textcoords="offset points")
    ax.set_xlabel("recall (true loops accepted / true loops proposed)")
    ax.set_ylabel("wrong loop closures accepted")
    ax.set_xlim(-0.02, 1.02)
    ax.set_ylim(-0.5, max(float(fp.max()), 1.0) + 0.5)
    _integer_ticks(ax.yaxis)
    ax.grid(alpha=0.3)
    ax.set_title(f"{len(judged)} logs with truth; {int((fp > 0).sum())} with wrong acceptances")
    return _png(fig)


def ate_figure(rows: Sequence[FleetRow]) -> bytes | None:
    """Histograms of ATE RMSE and of ATE over the oracle's ATE."""
    ates = np.array([r.ate_rmse_m for r in rows if r.done and r.ate_rmse_m is not None], dtype=float)
    ratios = np.array([r.ate_over_oracle for r in rows if r.done and r.ate_over_oracle is not None], dtype=float)
    if not len(ates):
        return None
    fig, (left, right) = _figure(9.0, 3.4, 2)
    left.hist(ates, bins=min(30, max(len(ates), 5)), color=BLUE, alpha=0.85)
    left.set_xlabel("ATE RMSE (m, SE(2)-aligned)")
    left.set_ylabel("logs")
    _integer_ticks(left.yaxis)
    left.axvline(float(np.median(ates)), color=GREY, ls="--", lw=1)
    if len(ratios):
        right.hist(ratios, bins=min(30, max(len(ratios), 5)), color=GREEN, alpha=0.85)
        right.axvline(1.0, color=GREY, ls="--", lw=1)
        right.set_xlabel("ATE / oracle ATE (1 = the true loops exactly)")
        _integer_ticks(right.yaxis)
    else:
        right.text(0.5, 0.5, "no oracle reference\n(no ground truth)", ha="center", va="center", transform=right.transAxes)
        right.set_axis_off()
    for ax in (left, right):
        ax.grid(alpha=0.3)
    return _png(fig)


def speed_figure(rows: Sequence[FleetRow]) -> bytes | None:
    """Replay wall time against log duration (log-log), with 1×/10×/100× real-time lines."""
    timed = [r for r in rows if r.status == "ok" and r.wall_time_s and r.log_duration_s]
    if not timed:
        return None
    fig, (ax,) = _figure(6.5, 4.0)
    duration = np.array([r.log_duration_s for r in timed])
    wall = np.array([r.wall_time_s for r in timed])
    ax.scatter(duration, wall, s=24, color=BLUE, alpha=0.8, edgecolors="none")
    lo, hi = max(min(duration.min(), wall.min()) / 2, 1e-3), max(duration.max(), wall.max()) * 2
    xs = np.array([lo, hi])
    for factor in (1, 10, 100):
        ax.plot(xs, xs / factor, color=GREY, ls="--", lw=0.8)
        ax.text(hi, hi / factor, f" {factor}×", fontsize=7, color=GREY, va="center")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("log duration (s)")
    ax.set_ylabel("replay wall time (s)")
    ax.grid(alpha=0.3, which="both")
    return _png(fig)


def compare_figure(pairs: Sequence[tuple[FleetRow, FleetRow]], regressed: set[str], labels: tuple[str, str]) -> bytes | None:
    """Run A (x) against run B (y) per log, for recall, wrong acceptances, ATE and replay time;
    regressed logs in red. Points above the diagonal are higher in B."""
    if not pairs:
        return None
    metrics = (("recall", "recall"), ("false_positives", "wrong acceptances"), ("ate_rmse_m", "ATE RMSE (m)"),
               ("wall_time_s", "replay time (s)"))
    fig, axes = _figure(12.0, 3.2, len(metrics))
    for ax, (key, label) in zip(axes, metrics):
        xs, ys, cs = [], [], []
        for a, b in pairs:
            va, vb = getattr(a, key), getattr(b, key)
            if va is None or vb is None:
                continue
            xs.append(float(va))
            ys.append(float(vb))
            cs.append(RED if a.name in regressed else BLUE)
        ax.set_title(label, fontsize=10)
        if not xs:
            ax.text(0.5, 0.5, "n/a", ha="center", va="center", transform=ax.transAxes)
            ax.set_axis_off()
            continue
        lo, hi = min(xs + ys), max(xs + ys)
        pad = (hi - lo) * 0.05 or 0.5
        ax.plot([lo - pad, hi + pad], [lo - pad, hi + pad], color=GREY, ls="--", lw=0.8)
        ax.scatter(xs, ys, c=cs, s=22, alpha=0.85, edgecolors="none")
        ax.set_xlabel(labels[0], fontsize=8)
        ax.set_ylabel(labels[1], fontsize=8)
        ax.grid(alpha=0.3)
    return _png(fig)
