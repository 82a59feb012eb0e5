"""The export formats, as pure functions from arrays and records to text.

* **TUM** (evo's ``tum`` format): ``stamp x y z qx qy qz qw`` per line, the stamp in seconds (the
  frame's ``log_time``, written exactly to the nanosecond), planar poses at ``z = 0`` with the yaw
  as a rotation about ``+z``.
* **KITTI** (evo's ``kitti`` format): the 12 values of the ``3 × 4`` matrix ``[R | t]`` per line,
  row-major, one line per frame (no stamps: evo matches KITTI files by line).
* **loops.csv**: one row per constraint (:data:`LOOP_COLUMNS`).
* **g2o**: ``VERTEX_SE2 i x y θ``, then ``EDGE_SE2 i j dx dy dθ I11 I12 I13 I22 I23 I33`` for the
  odometry chain and for each accepted loop (``i`` = match, ``j`` = query, the measurement
  ``T_match_query``), which ``lcv-replay record g2o`` reads back.
* **TOML**: the resolved config, which ``--config`` loads back.
"""

from __future__ import annotations

import csv
import io
import math
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from lcv_replay.sinks.run_record import LoopRecord

#: The columns of ``loops.csv``, in order.
LOOP_COLUMNS: tuple[str, ...] = (
    "constraint_id", "query_frame", "match_frame", "query_stamp_ns", "match_stamp_ns", "similarity", "hamming",
    "state", "truth", "first_accepted_frame", "dropped_frame", "d2",
)


def stamp_seconds(stamp_ns: int) -> str:
    """``1700000000123456789`` -> ``"1700000000.123456789"`` (exact, no float rounding)."""
    ns = int(stamp_ns)
    sign = "-" if ns < 0 else ""
    ns = abs(ns)
    return f"{sign}{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}"


def _finite_rows(poses: np.ndarray) -> np.ndarray:
    return np.all(np.isfinite(np.asarray(poses, dtype=np.float64)), axis=1)


def tum_text(stamps_ns: Sequence[int], poses: np.ndarray) -> str:
    """TUM lines of ``(N, 3)`` planar poses ``[x_m, y_m, yaw_rad]`` at ``(N,)`` stamps; rows with a
    NaN (no ground truth for that frame) are left out."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    if len(stamps_ns) != len(poses):
        raise ValueError(f"{len(stamps_ns)} stamps for {len(poses)} poses")
    lines = []
    for stamp, (x, y, yaw), ok in zip(stamps_ns, poses, _finite_rows(poses)):
        if ok:
            lines.append(f"{stamp_seconds(stamp)} {x:.9g} {y:.9g} 0 0 0 {math.sin(yaw / 2):.12g} {math.cos(yaw / 2):.12g}")
    return "\n".join(lines) + ("\n" if lines else "")


def kitti_text(poses: np.ndarray) -> str:
    """KITTI lines (``r11 r12 r13 tx r21 r22 r23 ty r31 r32 r33 tz``) of ``(N, 3)`` planar poses."""
    lines = []
    for x, y, yaw in np.asarray(poses, dtype=np.float64).reshape(-1, 3):
        c, s = math.cos(yaw), math.sin(yaw)
        values = (c, -s, 0.0, x, s, c, 0.0, y, 0.0, 0.0, 1.0, 0.0)
        lines.append(" ".join(f"{v:.12g}" for v in values))
    return "\n".join(lines) + ("\n" if lines else "")


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return format(value, ".9g")
    return str(value)


def loop_row(loop: LoopRecord) -> dict[str, str]:
    """One ``loops.csv`` row (empty cells for unknown values)."""
    return {
        "constraint_id": _cell(loop.constraint_id), "query_frame": _cell(loop.query_frame),
        "match_frame": _cell(loop.match_frame), "query_stamp_ns": _cell(loop.query_stamp_ns),
        "match_stamp_ns": _cell(loop.match_stamp_ns), "similarity": _cell(float(loop.similarity)),
        "hamming": _cell(loop.hamming), "state": loop.state, "truth": _cell(loop.truth),
        "first_accepted_frame": _cell(loop.first_accepted_frame), "dropped_frame": _cell(loop.dropped_frame),
        "d2": _cell(loop.d2),
    }


def loops_csv_text(loops: Iterable[LoopRecord]) -> str:
    """``loops.csv``: a header of :data:`LOOP_COLUMNS`, then one row per constraint."""
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=LOOP_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for loop in loops:
        writer.writerow(loop_row(loop))
    return out.getvalue()


def _upper6(information: np.ndarray) -> tuple[float, ...]:
    m = np.asarray(information, dtype=np.float64).reshape(3, 3)
    return (m[0, 0], m[0, 1], m[0, 2], m[1, 1], m[1, 2], m[2, 2])


def g2o_text(vertices: np.ndarray, odometry: np.ndarray, odometry_information: np.ndarray, loops: Iterable[LoopRecord]) -> str:
    """A g2o 2-D pose graph: vertices (initial guesses), the odometry chain and the given loops.

    Args:
        vertices: ``(N, 3)`` vertex estimates (the final estimate, or the odometry).
        odometry: ``(N, 3)`` cumulative odometry; the edges are its relative steps.
        odometry_information: ``(3, 3)`` information of one odometry step.
        loops: the loops to write as edges ``match -> query``.
    """
    from lcv_replay import se2

    odometry = np.asarray(odometry, dtype=np.float64).reshape(-1, 3)
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    info = " ".join(f"{v:.12g}" for v in _upper6(odometry_information))
    lines = [f"VERTEX_SE2 {i} {x:.12g} {y:.12g} {t:.12g}" for i, (x, y, t) in enumerate(vertices)]
    steps = se2.relative_steps(odometry) if len(odometry) > 1 else np.zeros((0, 3))
    lines += [f"EDGE_SE2 {k} {k + 1} {x:.12g} {y:.12g} {t:.12g} {info}" for k, (x, y, t) in enumerate(steps)]
    for loop in loops:
        x, y, t = loop.measurement
        values = " ".join(f"{v:.12g}" for v in loop.information)
        lines.append(f"EDGE_SE2 {loop.match_frame} {loop.query_frame} {x:.12g} {y:.12g} {t:.12g} {values}")
    return "\n".join(lines) + "\n"


def toml_text(config: Mapping[str, Any]) -> str:
    """The config as TOML (``tomli_w``); ``None`` values are left out (they mean the default)."""
    import tomli_w

    def clean(value: Any) -> Any:
        if isinstance(value, Mapping):
            return {str(k): clean(v) for k, v in value.items() if v is not None}
        if isinstance(value, (list, tuple)):
            return [clean(v) for v in value]
        return value

    return tomli_w.dumps(clean(config))
