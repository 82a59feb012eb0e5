"""Generators and readers for the replay and sink tests.

* :func:`square_route_g2o` writes a small 2-D pose graph (a square route driven several laps, noisy
  odometry, true revisit loops and false loops) with its ground truth and labels, as text files in
  the g2o formats the real g2o recorder reads; :func:`record_square_route` records it into a real
  log with ``recorders.g2o.record_g2o``.
* :class:`FakeClock`: an injectable clock whose ``sleep`` only advances time.
* :func:`read_rrd`: every row of a recording, per entity, through ``rerun.chunk.RrdReader``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lcv_replay import se2


# --------------------------------------------------------------------------------------- logs
@dataclass(frozen=True)
class SquareRoute:
    graph: Path
    ground_truth: Path
    true_loops: Path
    frames: int
    true_pairs: frozenset[tuple[int, int]]
    false_pairs: frozenset[tuple[int, int]]


def _compose(a, b):
    return tuple(se2.compose(np.asarray(a, float), np.asarray(b, float)))


def _between(a, b):
    return tuple(se2.between(np.asarray(a, float), np.asarray(b, float)))


def square_route_g2o(
    folder: Path,
    *,
    laps: int = 3,
    side_poses: int = 40,
    step_m: float = 1.0,
    loop_every: int = 8,
    false_loops: int = 12,
    seed: int = 0,
) -> SquareRoute:
    """A square route of ``4 * side_poses`` poses per lap, ``laps`` laps, in g2o text files.

    Odometry steps carry a small yaw bias and noise (the drift that loops must correct). Every
    ``loop_every``-th pose of laps 2.. closes a true loop to the same corner-relative pose of lap 1;
    ``false_loops`` random far-apart pairs are false loops with an identity measurement.
    """
    rng = np.random.default_rng(seed)
    per_lap = 4 * side_poses
    n = laps * per_lap
    gt = [(0.0, 0.0, 0.0)]
    for k in range(1, n):
        turn = math.pi / 2 if k % side_poses == 0 else 0.0
        gt.append(_compose(gt[-1], (step_m, 0.0, turn)))
    odom_steps = []
    for k in range(n - 1):
        true_step = _between(gt[k], gt[k + 1])
        odom_steps.append((
            true_step[0] + rng.normal(0, 0.02),
            true_step[1] + rng.normal(0, 0.02),
            true_step[2] + 0.004 + rng.normal(0, 0.002),
        ))
    odom = [(0.0, 0.0, 0.0)]
    for step in odom_steps:
        odom.append(_compose(odom[-1], step))
    true_pairs = set()
    for q in range(per_lap, n, loop_every):
        true_pairs.add((q, q % per_lap))
    false_pairs = set()
    while len(false_pairs) < false_loops:
        q = int(rng.integers(per_lap, n))
        m = int(rng.integers(0, q - per_lap // 2))
        far = math.dist(gt[q][:2], gt[m][:2]) > 30.0
        if far and (q, m) not in true_pairs:
            false_pairs.add((q, m))
    info_odom = "500 0 0 500 0 5000"
    info_loop = "100 0 0 100 0 1000"
    lines = [f"VERTEX_SE2 {i} {p[0]:.6f} {p[1]:.6f} {p[2]:.6f}" for i, p in enumerate(odom)]
    for k, s in enumerate(odom_steps):
        lines.append(f"EDGE_SE2 {k} {k + 1} {s[0]:.6f} {s[1]:.6f} {s[2]:.6f} {info_odom}")
    for q, m in sorted(true_pairs):
        z = _between(gt[q], gt[m])
        lines.append(f"EDGE_SE2 {q} {m} {z[0]:.6f} {z[1]:.6f} {z[2]:.6f} {info_loop}")
    for q, m in sorted(false_pairs):
        lines.append(f"EDGE_SE2 {q} {m} 0 0 0 {info_loop}")
    folder.mkdir(parents=True, exist_ok=True)
    graph = folder / "square.g2o"
    graph.write_text("\n".join(lines) + "\n", encoding="utf-8")
    gt_path = folder / "square_gt.g2o"
    gt_path.write_text("\n".join(f"VERTEX_SE2 {i} {p[0]:.6f} {p[1]:.6f} {p[2]:.6f}" for i, p in enumerate(gt)) + "\n", encoding="utf-8")
    labels = folder / "square_loops.txt"
    labels.write_text("\n".join(f"{q} {m}" for q, m in sorted(true_pairs)) + "\n", encoding="utf-8")
    return SquareRoute(graph, gt_path, labels, n, frozenset(true_pairs), frozenset(false_pairs))


def record_square_route(folder: Path, *, name: str = "square.mcap", **kwargs) -> tuple[Path, SquareRoute]:
    """Record :func:`square_route_g2o` with the real g2o recorder; returns the log and the route."""
    from recorders.g2o import G2oOptions, record_g2o

    route = square_route_g2o(folder / "src", **kwargs)
    out = folder / name
    record_g2o(route.graph, out, G2oOptions(ground_truth=route.ground_truth, true_loops=route.true_loops), force=True)
    return out, route


def write_config(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


#: A config for fast tests: windows of 100 frames, fewer generation iterations.
FAST_CONFIG_TOML = """
[verification]
window_frames = 100
iterations_per_window = 3
hypotheses_per_iteration = 5
max_hypotheses = 40

[rerun]
image_every = 5
"""


# --------------------------------------------------------------------------------------- clock
class FakeClock:
    """``now()`` returns a counter that only ``sleep`` and ``advance`` move (no real waiting)."""

    def __init__(self, start: float = 1000.0):
        self.t = start
        self.sleeps: list[float] = []

    def now(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        assert seconds >= 0
        self.sleeps.append(seconds)
        self.t += seconds

    def advance(self, seconds: float) -> None:
        self.t += seconds


# --------------------------------------------------------------------------------------- rrd
def read_rrd(path: Path) -> dict[str, "object"]:
    """``{entity_path: pyarrow.Table}`` of every temporal and static row of the first recording.

    Rows of one entity from several chunks are concatenated (columns unified by name).
    """
    import pyarrow as pa
    from rerun.chunk import RrdReader

    tables: dict[str, list] = {}
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        tables.setdefault(chunk.entity_path, []).append(pa.Table.from_batches([batch]))
    return {entity: pa.concat_tables(parts, promote_options="permissive") for entity, parts in tables.items()}


def column(table, suffix: str) -> str:
    """The name of the column of ``table`` ending with ``suffix`` (e.g. ``"BarChart:values"``)."""
    names = [n for n in table.column_names if n.endswith(suffix)]
    if len(names) != 1:
        raise KeyError(f"{suffix!r} matches {names} among {table.column_names}")
    return names[0]


def last_row(table, suffix: str, *, timeline: str = "frame"):
    """The value of column ``suffix`` in the row with the largest ``timeline`` value (ties: last)."""
    name = column(table, suffix)
    values = table.column(name).to_pylist()
    times = table.column(timeline).to_pylist() if timeline in table.column_names else list(range(len(values)))
    rows = [(t, i) for i, (t, v) in enumerate(zip(times, values)) if v is not None]
    _, i = max(rows)
    return values[i]


def by_frame(table, suffix: str, *, timeline: str = "frame") -> dict:
    """``{time: value}`` of column ``suffix`` over the temporal rows (static rows left out)."""
    values = table.column(column(table, suffix)).to_pylist()
    return {t: v for t, v in zip(table.column(timeline).to_pylist(), values) if t is not None and v is not None}


def series(table, *, timeline: str = "frame") -> list[tuple[int, float]]:
    """``(time, value)`` of a Scalars entity, in time order."""
    name = column(table, "Scalars:scalars")
    times = table.column(timeline).to_pylist()
    values = table.column(name).to_pylist()
    return sorted((int(t), float(v[0])) for t, v in zip(times, values) if v and t is not None)


def last_verdicts(tables) -> dict[int, int]:
    """``{constraint_id: ConstraintState}`` drawn at the last step, over the per-verdict constraint
    entities (the rejected ones are thinned beyond ``REJECTED_MAX_DRAWN``)."""
    from lcv_replay.sinks import blueprint as bp

    out: dict[int, int] = {}
    for path in bp.CONSTRAINT_ENTITIES:
        if path not in tables or not any(n.endswith("constraint_id") for n in tables[path].column_names):
            continue  # absent, or only its static style (e.g. no ambiguous constraint ever)
        ids = last_row(tables[path], "constraint_id")
        classes = last_row(tables[path], "LineStrips2D:class_ids")
        out.update(zip(ids, classes))
    return out
