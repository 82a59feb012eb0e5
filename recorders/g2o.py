"""``lcv-replay record g2o``: a 2-D pose graph (g2o / TORO / Vertigo text formats) into a log.

A pose graph has no images: the log carries ``/odom`` (the odometry chain ``i -> i+1`` composed into
cumulative poses), ``/loop_candidates`` (every other edge), optionally ``/ground_truth/pose`` and
``/ground_truth/loops``. Frame ``i`` is vertex ``i`` (ids shifted so that the first is 0), stamped
``start_stamp_ns + i / rate_hz`` (10 Hz by default, the rate of robustslam_kitti's libviso2 VO).

Accepted inputs (one graph per file, detected line by line):

* g2o: ``VERTEX_SE2 id x y theta``; ``EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22 I23 I33``
  (measurement ``T_i_j``, upper triangle of the information matrix, row-major);
  Vertigo's ``EDGE_SE2_SWITCHABLE i j switch_id ...`` and ``EDGE_SE2_MAXMIX i j weight ...``
  (same fields after the extra one); ``VERTEX_SWITCH``, ``EDGE_SWITCH_PRIOR`` and ``FIX`` are ignored.
* TORO: ``VERTEX2 id x y theta``; ``EDGE2 i j dx dy dtheta Ixx Ixy Iyy Itt Ixt Iyt``.
* Untagged numeric rows (Vertigo ``groundTruth`` folders): 3 columns ``x y theta`` = vertex of that
  line number (``*_nodes_groundTruth.dat``); 14 columns ``i j dx dy dtheta`` + a row-major 3x3
  **covariance** (``*_edges_groundTruth.dat``), inverted to an information matrix.

Loop candidates are oriented ``query_frame = max(i, j)``, ``match_frame = min(i, j)`` with
``T_match_query`` the pose of the query in the match frame. An edge written (later, earlier), as
all of robustslam_kitti's are, is inverted: ``T_match_query = T_i_j⁻¹`` and the information is
transformed by the SE(2) adjoint, ``Λ' = Ad(T_i_j)⁻ᵀ Λ Ad(T_i_j)⁻¹`` (first order, the same
convention as GTSAM's ``BetweenFactor``).

Outlier injection follows Sünderhauf's Vertigo ``generateDataset.py`` protocol (see
:func:`inject_outliers`).
"""

from __future__ import annotations

import logging
import math
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Literal

import numpy as np

from lcv_replay import se2
from lcv_replay.errors import RecorderError, require_seed
from lcv_replay.records import LoopCandidate, Pose2D
from lcv_replay.se2 import Information6
from recorders.common import (
    LogHeader,
    ProgressCallback,
    RecordStats,
    is_number,
    make_frames,
    options_config,
    read_numeric_rows,
    require_path,
    write_log,
)

log = logging.getLogger(__name__)

OutlierMode = Literal["random", "local", "group"]

#: Vertigo's default information matrix for false loops when the graph has no real loop to copy.
VERTIGO_DEFAULT_INFORMATION: Information6 = (42.7, 0.0, 0.0, 42.7, 0.0, 42.7)
#: Outlier measurement noise of the Vertigo protocol.
OUTLIER_SIGMA_XY_M = 0.3
OUTLIER_SIGMA_YAW_RAD = math.radians(10.0)
#: "local" outliers: the second pose is within this many poses of the first (Vertigo ``-l``).
LOCAL_OUTLIER_SPAN = 20

_G2O_FIX = "check the file is a 2-D g2o pose graph (VERTEX_SE2 / EDGE_SE2 lines)"
_ROBUSTSLAM_NAME = re.compile(r"^kitti_(?P<seq>\d\d)_alpha_(?P<alpha>\d\.\d\d)\.g2o$")
_ROBUSTSLAM_ODOM_NAME = re.compile(r"^kitti_(?P<seq>\d\d)_odom\.g2o$")


# ---------------------------------------------------------------------------------------------
# Records
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class G2oEdge:
    """One edge as written in the file: measurement ``T_from_to`` (pose of ``to`` in ``from``).

    ``information`` is the upper triangle ``(I_xx, I_xy, I_xθ, I_yy, I_yθ, I_θθ)``; ``line`` is the
    1-based line number in the source file (for error messages).
    """

    from_id: int
    to_id: int
    T_from_to: Pose2D
    information: Information6
    line: int = 0

    def as_candidate(self, source: str) -> LoopCandidate:
        """This edge as a :class:`LoopCandidate` oriented (later, earlier)."""
        if self.to_id > self.from_id:
            return LoopCandidate(self.to_id, self.from_id, source=source, T_match_query=self.T_from_to, information=self.information)
        T_inv, info_inv = invert_measurement(self.T_from_to, self.information)
        return LoopCandidate(self.from_id, self.to_id, source=source, T_match_query=T_inv, information=info_inv)


@dataclass(frozen=True)
class PoseGraph2D:
    """A planar pose graph split into an odometry chain and loop edges.

    Attributes:
        path: the source file.
        odometry_steps: ``(N - 1, 3)`` relative poses ``T_{k}_{k+1}`` of the chain.
        odometry_information: ``(N - 1, 6)`` upper-triangle information of each chain edge.
        loops: every edge that is not the chain edge ``k -> k+1``, as written (ids shifted to 0).
        vertices: ``(N, 3)`` vertex estimates (``VERTEX_SE2`` / node rows), or ``None``.
        id_offset: the smallest vertex id of the file (subtracted from every id).
        chain_lines: ``(N - 1,)`` source line of each chain edge (0: from the vertices).
        duplicate_edges: ``(line, earlier line)`` of each edge that joins the same two vertices
            as an earlier edge (it is kept, as a loop candidate).
    """

    path: Path
    odometry_steps: np.ndarray
    odometry_information: np.ndarray
    loops: tuple[G2oEdge, ...]
    vertices: np.ndarray | None = None
    id_offset: int = 0
    chain_lines: np.ndarray | None = None
    duplicate_edges: tuple[tuple[int, int], ...] = ()

    @property
    def num_poses(self) -> int:
        return len(self.odometry_steps) + 1

    def odometry_poses(self) -> np.ndarray:
        """``(N, 3)`` cumulative odometry: the chain composed from vertex 0 (or the origin)."""
        start = tuple(self.vertices[0]) if self.vertices is not None else (0.0, 0.0, 0.0)
        return se2.compose_chain(self.odometry_steps, start)

    def trajectory(self) -> np.ndarray:
        """``(N, 3)`` absolute poses: the vertices if the file has them, else the composed chain.

        This is how a ground-truth file is read: a vertices file, an edge chain, or ``x y theta``
        rows all give the same ``(N, 3)`` array.
        """
        return self.vertices.copy() if self.vertices is not None else self.odometry_poses()

    def loop_candidates(self, source: str = "g2o") -> tuple[LoopCandidate, ...]:
        """The loop edges as candidates oriented (later, earlier), in file order."""
        return tuple(edge.as_candidate(source) for edge in self.loops)

    def bad_odometry_information(self) -> np.ndarray:
        """Indices of the chain edges whose information is singular or not positive definite."""
        return np.flatnonzero(~positive_definite(self.odometry_information))

    def bad_loop_information(self) -> list[G2oEdge]:
        """The loop edges whose information is singular or not positive definite."""
        ok = positive_definite(np.array([e.information for e in self.loops]).reshape(-1, 6))
        return [edge for edge, good in zip(self.loops, ok) if not good]

    def warnings(self) -> dict[str, int]:
        """Counts of what the recorder accepts but warns about (keys of ``format.RECORDER_WARNING_NAMES``)."""
        counts = {
            "singular_odometry_information": len(self.bad_odometry_information()),
            "singular_loop_information": len(self.bad_loop_information()),
            "duplicate_edges": len(self.duplicate_edges),
        }
        return {key: n for key, n in counts.items() if n}

    def odometry_information_matrix(self) -> np.ndarray | None:
        """``(3, 3)`` information of the first chain edge whose information is positive definite.

        Identity if the graph has no edges; ``None`` (the verifier's default) if no chain edge has a
        usable one.
        """
        if len(self.odometry_information) == 0:
            return np.eye(3)
        good = np.flatnonzero(positive_definite(self.odometry_information))
        if len(good) == 0:
            return None
        return se2.information_matrix(tuple(self.odometry_information[good[0]]))


def positive_definite(upper6: np.ndarray) -> np.ndarray:
    """``(M,)`` bool: each ``(M, 6)`` upper-triangle information is finite, symmetric positive definite."""
    upper6 = np.asarray(upper6, dtype=np.float64).reshape(-1, 6)
    if len(upper6) == 0:
        return np.zeros(0, dtype=bool)
    a, b, c, d, e, f = upper6.T
    matrices = np.stack([np.stack([a, b, c], -1), np.stack([b, d, e], -1), np.stack([c, e, f], -1)], -2)
    finite = np.isfinite(matrices).all(axis=(1, 2))
    eig = np.linalg.eigvalsh(np.where(finite[:, None, None], matrices, np.eye(3)))
    return finite & (eig[:, 0] > 1e-12 * np.maximum(eig[:, -1], 0.0)) & (eig[:, -1] > 0)


# ---------------------------------------------------------------------------------------------
# Edges (the SE(2) algebra is lcv_replay.se2)
# ---------------------------------------------------------------------------------------------


def invert_measurement(T_a_b: Pose2D, information: Information6) -> tuple[Pose2D, Information6]:
    """An edge's measurement ``T_a_b`` and upper-triangle information as ``T_b_a`` and its
    information (:func:`lcv_replay.se2.invert_measurement`)."""
    T_b_a, inverted = se2.invert_measurement(T_a_b, se2.information_matrix(information))
    return Pose2D(*T_b_a.tolist()), se2.upper_triangle(inverted)


# ---------------------------------------------------------------------------------------------
# Parsing
# ---------------------------------------------------------------------------------------------

_IGNORED_TAGS = {"VERTEX_SWITCH", "EDGE_SWITCH_PRIOR", "FIX", "VERTEX_XY", "PARAMS_SE2OFFSET"}
_3D_TAGS = {"VERTEX_SE3:QUAT", "EDGE_SE3:QUAT", "VERTEX3", "EDGE3", "VERTEX_SE3", "EDGE_SE3"}


def _toro_information(values: list[float]) -> Information6:
    """TORO ``Ixx Ixy Iyy Itt Ixt Iyt`` -> g2o ``I11 I12 I13 I22 I23 I33``."""
    ixx, ixy, iyy, itt, ixt, iyt = values
    return (ixx, ixy, ixt, iyy, iyt, itt)


def _covariance_information(values: np.ndarray, path: Path, lines: list[int]) -> list[Information6]:
    """``(M, 9)`` row-major 3x3 covariances -> ``M`` information upper triangles."""
    cov = np.asarray(values, dtype=np.float64).reshape(-1, 3, 3)
    cov = 0.5 * (cov + np.transpose(cov, (0, 2, 1)))
    singular = np.abs(np.linalg.det(cov)) < 1e-300
    if singular.any():
        line = lines[int(np.argmax(singular))]
        raise RecorderError(f"line {line}: singular covariance matrix", path=path, fix="repair the edge's covariance")
    info = np.linalg.inv(cov)
    return [se2.upper_triangle(m) for m in info]


def _parse_tagged(path: Path, lines: list[str]) -> tuple[dict[int, tuple[float, float, float]], list[G2oEdge]]:
    vertices: dict[int, tuple[float, float, float]] = {}
    edges: list[G2oEdge] = []
    for line_no, line in enumerate(lines, start=1):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        tag = tokens[0]
        try:
            if tag in ("VERTEX_SE2", "VERTEX2"):
                if len(tokens) < 5:
                    raise ValueError("expected 'id x y theta'")
                vid = int(tokens[1])
                if vid in vertices:
                    raise ValueError(f"vertex {vid} defined twice")
                vertices[vid] = (float(tokens[2]), float(tokens[3]), float(tokens[4]))
            elif tag in ("EDGE_SE2", "EDGE2", "EDGE_SE2_SWITCHABLE", "EDGE_SE2_MAXMIX"):
                extra = 1 if tag in ("EDGE_SE2_SWITCHABLE", "EDGE_SE2_MAXMIX") else 0
                fields = tokens[3 + extra :]
                if len(fields) < 9:
                    raise ValueError("expected 'i j dx dy dtheta' and 6 information entries")
                values = [float(v) for v in fields[:9]]
                info = _toro_information(values[3:9]) if tag == "EDGE2" else tuple(values[3:9])
                edges.append(G2oEdge(int(tokens[1]), int(tokens[2]), Pose2D(*values[:3]), info, line_no))  # type: ignore[arg-type]
            elif tag in _IGNORED_TAGS:
                continue
            elif tag in _3D_TAGS:
                raise RecorderError(f"line {line_no}: {tag} is a 3-D pose graph", path=path, fix="lcv-replay records 2-D (SE2) graphs only")
            else:
                raise RecorderError(f"line {line_no}: unknown record type {tag!r}", path=path, fix=_G2O_FIX)
        except ValueError as exc:
            raise RecorderError(f"line {line_no}: malformed {tag} ({exc})", path=path, fix=_G2O_FIX) from None
    return vertices, edges


def _parse_untagged(path: Path) -> tuple[dict[int, tuple[float, float, float]], list[G2oEdge]]:
    rows = read_numeric_rows(path, what="pose graph", fix=_G2O_FIX)
    widths = {len(values) for _, values in rows}
    vertices: dict[int, tuple[float, float, float]] = {}
    edges: list[G2oEdge] = []
    if widths == {3}:
        vertices = {k: (v[0], v[1], v[2]) for k, (_, v) in enumerate(rows)}
    elif widths == {14}:
        infos = _covariance_information(np.array([v[5:14] for _, v in rows]), path, [ln for ln, _ in rows])
        for (line_no, v), info in zip(rows, infos):
            edges.append(G2oEdge(int(v[0]), int(v[1]), Pose2D(v[2], v[3], v[4]), info, line_no))
    elif widths == {11}:
        for line_no, v in rows:
            edges.append(G2oEdge(int(v[0]), int(v[1]), Pose2D(v[2], v[3], v[4]), tuple(v[5:11]), line_no))  # type: ignore[arg-type]
    else:
        raise RecorderError(
            f"untagged rows with {sorted(widths)} columns",
            path=path,
            fix="expected 'x y theta' rows (3 columns) or 'i j dx dy dtheta' + covariance (14) / information (11)",
        )
    return vertices, edges


def load_g2o(path: str | Path) -> PoseGraph2D:
    """Parse a 2-D pose graph file (see the module docstring for the accepted formats).

    The odometry chain is the edge ``k -> k+1`` for every consecutive vertex pair (an edge written
    ``k+1 -> k`` is inverted); every other edge, including a second ``k -> k+1`` edge, is a loop.
    A file with vertices and no edges (``x y theta`` rows) gets its chain from the vertices.

    Raises:
        RecorderError: missing file, unknown record, malformed line, non-finite value, vertex ids
            that are not contiguous, or a missing chain edge.
    """
    path = require_path(path, what="pose graph file", fix="pass the path of a .g2o file")
    with path.open("r", encoding="utf-8", errors="replace") as handle:
        lines = handle.readlines()
    first = next((ln.split()[0] for ln in lines if ln.split() and not ln.lstrip().startswith("#")), None)
    if first is None:
        raise RecorderError("pose graph file is empty", path=path, fix=_G2O_FIX)
    if is_number(first):
        vertices, edges = _parse_untagged(path)
    else:
        vertices, edges = _parse_tagged(path, lines)
    return _build_graph(path, vertices, edges)


def _build_graph(path: Path, vertices: dict[int, tuple[float, float, float]], edges: list[G2oEdge]) -> PoseGraph2D:
    for edge in edges:
        values = (*edge.T_from_to, *edge.information)
        if not all(math.isfinite(v) for v in values):
            raise RecorderError(f"line {edge.line}: NaN or inf in an edge", path=path, fix="repair or remove the edge")
        if edge.from_id == edge.to_id:
            raise RecorderError(f"line {edge.line}: edge from vertex {edge.from_id} to itself", path=path, fix="remove the edge")
    ids = set(vertices)
    for edge in edges:
        ids.update((edge.from_id, edge.to_id))
    if not ids:
        raise RecorderError("pose graph has no vertices and no edges", path=path, fix=_G2O_FIX)
    first_id, last_id = min(ids), max(ids)
    if len(ids) != last_id - first_id + 1:
        missing = next(k for k in range(first_id, last_id + 1) if k not in ids)
        raise RecorderError(f"vertex ids are not contiguous: {missing} is missing between {first_id} and {last_id}", path=path, fix="renumber the vertices 0..N-1")
    if vertices and len(vertices) != len(ids):
        missing = next(k for k in sorted(ids) if k not in vertices)
        raise RecorderError(f"vertex {missing} is used by an edge but has no VERTEX line", path=path, fix="add the vertex or remove the edge")
    num_poses = last_id - first_id + 1
    if first_id != 0:
        log.info("%s: vertex ids start at %d; frame k is vertex %d + k", path, first_id, first_id)
    shifted = [
        G2oEdge(e.from_id - first_id, e.to_id - first_id, e.T_from_to, e.information, e.line) for e in edges
    ]
    vertex_array = None
    if vertices:
        vertex_array = np.array([vertices[first_id + k] for k in range(num_poses)], dtype=np.float64)
        if not np.isfinite(vertex_array).all():
            raise RecorderError("NaN or inf in a vertex", path=path, fix="repair the VERTEX lines")

    steps = np.full((num_poses - 1, 3), np.nan)
    step_info = np.zeros((num_poses - 1, 6))
    chain_lines = np.zeros(num_poses - 1, dtype=np.int64)
    loops: list[G2oEdge] = []
    first_line: dict[tuple[int, int], int] = {}
    duplicates: list[tuple[int, int]] = []
    for edge in shifted:
        pair = (min(edge.from_id, edge.to_id), max(edge.from_id, edge.to_id))
        if pair in first_line:
            duplicates.append((edge.line, first_line[pair]))
        else:
            first_line[pair] = edge.line
        lo = min(edge.from_id, edge.to_id)
        if abs(edge.to_id - edge.from_id) == 1 and np.isnan(steps[lo, 0]):
            chain_lines[lo] = edge.line
            if edge.to_id > edge.from_id:
                T, info = edge.T_from_to, edge.information
            else:
                T, info = invert_measurement(edge.T_from_to, edge.information)
            steps[lo] = T
            step_info[lo] = info
        else:
            loops.append(edge)
    if not edges and vertex_array is not None:
        steps = se2.relative_steps(vertex_array)
        step_info[:] = (1.0, 0.0, 0.0, 1.0, 0.0, 1.0)
    elif np.isnan(steps[:, 0]).any():
        k = int(np.argmax(np.isnan(steps[:, 0])))
        raise RecorderError(
            f"no odometry edge between vertices {k + first_id} and {k + 1 + first_id}",
            path=path,
            fix="the chain i -> i+1 must be complete (one graph per file)",
        )
    return PoseGraph2D(path, steps, step_info, tuple(loops), vertex_array, first_id, chain_lines, tuple(duplicates))


def _warn_about(graph: PoseGraph2D) -> None:
    """Log what the graph has that a user should know about (the counts go into the log, too)."""
    bad = graph.bad_odometry_information()
    if len(bad):
        k = int(bad[0])
        information = se2.information_matrix(tuple(graph.odometry_information[k]))
        eigenvalues = np.round(np.linalg.eigvalsh(np.nan_to_num(information)), 6).tolist()
        used = "the first chain edge with a positive-definite one" if graph.odometry_information_matrix() is not None else "none (the verifier's default odometry noise)"
        log.warning(
            "%s: %d odometry edges have a singular or non-positive-definite information matrix "
            "(first: line %d, vertices %d -> %d, eigenvalues %s); the log's odometry information is %s",
            graph.path, len(bad), int(graph.chain_lines[k]), k + graph.id_offset, k + 1 + graph.id_offset, eigenvalues, used,
        )
    bad_loops = graph.bad_loop_information()
    if bad_loops:
        edge = bad_loops[0]
        log.warning(
            "%s: %d loop edges have a singular or non-positive-definite information matrix (first: line %d, "
            "vertices %d -> %d); verifiers refuse such a candidate when it arrives",
            graph.path, len(bad_loops), edge.line, edge.from_id + graph.id_offset, edge.to_id + graph.id_offset,
        )
    if graph.duplicate_edges:
        line, earlier = graph.duplicate_edges[0]
        log.warning(
            "%s: %d duplicate edges join the same two vertices as an earlier edge (first: line %d repeats line %d); "
            "each is recorded as its own loop candidate",
            graph.path, len(graph.duplicate_edges), line, earlier,
        )


def load_ground_truth(path: str | Path, num_poses: int) -> np.ndarray:
    """``(N, 3)`` ground-truth poses from a vertices file, an edge chain, or ``x y theta`` rows.

    Raises :class:`RecorderError` if the file's pose count differs from ``num_poses``.
    """
    path = Path(path)
    poses = load_g2o(path).trajectory()
    if len(poses) != num_poses:
        raise RecorderError(
            f"ground truth has {len(poses)} poses but the graph has {num_poses}",
            path=path,
            fix="pass the ground truth of the same sequence",
        )
    return poses


def load_true_loops(path: str | Path, num_poses: int) -> frozenset[tuple[int, int]]:
    """True loop pairs from ``i j`` lines, oriented ``(query, match) = (max, min)``."""
    path = Path(path)
    fix = "pass a text file with one 'i j' pair of frame indices per line"
    pairs: set[tuple[int, int]] = set()
    for line_no, values in read_numeric_rows(path, what="true-loop file", fix=fix):
        if len(values) < 2 or any(v != int(v) for v in values[:2]):
            raise RecorderError(f"line {line_no}: expected two frame indices", path=path, fix=fix)
        i, j = int(values[0]), int(values[1])
        if not (0 <= i < num_poses and 0 <= j < num_poses) or i == j:
            raise RecorderError(f"line {line_no}: pair ({i}, {j}) is not two distinct frames of 0..{num_poses - 1}", path=path, fix="pass the labels of the same sequence")
        pairs.add((max(i, j), min(i, j)))
    return frozenset(pairs)


# ---------------------------------------------------------------------------------------------
# Outlier injection (Vertigo protocol)
# ---------------------------------------------------------------------------------------------


def inject_outliers(
    num_poses: int,
    count: int,
    *,
    mode: OutlierMode = "random",
    group_size: int = 10,
    information: Information6 = VERTIGO_DEFAULT_INFORMATION,
    seed: int = 0,
    existing_pairs: Iterable[tuple[int, int]] = (),
    ground_truth: np.ndarray | None = None,
    min_distance_m: float = 0.0,
) -> tuple[LoopCandidate, ...]:
    """False loop closures drawn as in Sünderhauf's Vertigo ``generateDataset.py``.

    * ``random``: two poses anywhere; ``local``: the second within :data:`LOCAL_OUTLIER_SPAN` poses
      after the first; ``group``: ``count`` loops in runs of ``group_size`` consecutive pairs
      ``(a + k, b + k)`` sharing one measurement, so each run is mutually consistent (the last run
      is shorter when ``group_size`` does not divide ``count``).
    * A pair never joins a pose to itself or to its odometry neighbour, nor repeats a pair in
      ``existing_pairs`` or an earlier outlier (such a draw is redrawn).
    * With ``ground_truth`` (``(N, 3)`` poses) and ``min_distance_m > 0``, a pair never joins two
      poses closer than ``min_distance_m`` (redrawn): in a graph that revisits its places densely
      (a grid city), a random pair can be a real revisit, and a loop there is not false.
    * Measurement ``T_match_query``: x, y ~ N(0, 0.3 m), yaw ~ N(0, 10°), with ``information``.

    Returns ``count`` candidates with ``source="injected"``, oriented (later, earlier).
    """
    if count < 0:
        raise RecorderError(f"--outliers {count} is negative", fix="pass a count >= 0")
    if mode not in ("random", "local", "group"):
        raise RecorderError(f"--outlier-mode {mode!r} is unknown", fix="use random, local or group")
    run = group_size if mode == "group" else 1
    if run < 1:
        raise RecorderError(f"--group-size {group_size} must be >= 1", fix="pass e.g. --group-size 10")
    last = num_poses - 1 - run  # the largest first index of a run, as in Vertigo
    if count and last < 2:
        raise RecorderError(f"a graph of {num_poses} poses is too small for {mode} outliers of runs of {run}", fix="use a larger graph or a smaller --group-size")
    if min_distance_m > 0.0 and ground_truth is None:
        raise RecorderError("outliers kept away from real revisits need the ground truth", fix="pass --ground-truth, or no minimum distance")
    rng = np.random.default_rng(seed)
    taken = {(max(q, m), min(q, m)) for q, m in existing_pairs}
    out: list[LoopCandidate] = []
    attempts = 0
    while len(out) < count:
        attempts += 1
        if attempts > 1000 + 100 * count:
            raise RecorderError(f"cannot place {count} distinct {mode} outliers in a graph of {num_poses} poses", fix="ask for fewer outliers")
        a = int(rng.integers(0, last + 1))
        b = int(rng.integers(a, min(last, a + LOCAL_OUTLIER_SPAN) + 1)) if mode == "local" else int(rng.integers(0, last + 1))
        a, b = min(a, b), max(a, b)
        if b == a:
            continue
        if b == a + 1:
            b = a + 2  # Vertigo: never duplicate an odometry edge
        n = min(run, count - len(out))
        pairs = [(b + k, a + k) for k in range(n)]
        if any(p in taken for p in pairs):
            continue
        if min_distance_m > 0.0 and any(np.hypot(*(ground_truth[q, :2] - ground_truth[m, :2])) < min_distance_m for q, m in pairs):
            continue  # a real revisit, not a false loop
        x_m, y_m = rng.normal(0.0, OUTLIER_SIGMA_XY_M, size=2)
        yaw_rad = rng.normal(0.0, OUTLIER_SIGMA_YAW_RAD)
        measurement = Pose2D(float(x_m), float(y_m), float(yaw_rad))
        for query, match in pairs:
            taken.add((query, match))
            out.append(LoopCandidate(query, match, source="injected", T_match_query=measurement, information=tuple(information)))  # type: ignore[arg-type]
    return tuple(out)


# ---------------------------------------------------------------------------------------------
# Recording
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class G2oOptions:
    """Options of the g2o recorder (CLI: ``lcv-replay record g2o GRAPH -o OUT.mcap``).

    Attributes:
        ground_truth: ground-truth trajectory file (vertices, edge chain or ``x y theta`` rows).
        true_loops: true-loop labels, ``i j`` per line.
        auto_siblings: for robustslam_kitti files ``kitti_SS_alpha_A.g2o``, use the sibling
            ``kitti_SS_alpha_A_GT_LC.txt`` and ``kitti_SS_GT.g2o`` unless given explicitly.
        outliers: number of false loops to inject (0 = none).
        outlier_mode: ``random``, ``local`` or ``group``.
        group_size: loops per run in ``group`` mode.
        outlier_min_distance_m: injected loops never join two poses closer than this in the ground
            truth (0: no check; the suite's generated worlds use their revisit radius).
        outlier_information: information of injected loops; ``None`` = that of the graph's first
            loop (Vertigo protocol), or Vertigo's default ``42.7·I`` if the graph has no loop.
        seed: random seed of the injection.
        loop_measurements: ``as-recorded`` keeps each edge's relative pose; ``same-place`` drops it
            (``T_match_query = None``: "same place", identity with the verifier's noise), as a place
            recognizer would report. robustslam_kitti writes real relative poses on its true loops
            and zeros on its false ones, so ``as-recorded`` lets a verifier tell them apart by
            the measurement alone.
        original_loops_true: label the graph's own loops true when no ``true_loops`` file is given.
            ``None`` = automatic: true when outliers are injected (the Vertigo protocol spoils a
            graph whose loops are all correct) unless the loops come from a place recognizer
            (robustslam_kitti), unlabelled otherwise.
        rate_hz: frame rate used for the stamps.
        start_stamp_ns: stamp of frame 0.
        source: detector name written on the graph's candidates (default: ``DLoopDetector`` for
            robustslam_kitti, else ``g2o``).
        dataset: dataset name in the log metadata (default: derived from the file name).
    """

    ground_truth: Path | None = None
    true_loops: Path | None = None
    auto_siblings: bool = True
    outliers: int = 0
    outlier_mode: OutlierMode = "random"
    group_size: int = 10
    outlier_min_distance_m: float = 0.0
    outlier_information: Information6 | None = None
    seed: int = 0
    loop_measurements: Literal["as-recorded", "same-place"] = "as-recorded"
    original_loops_true: bool | None = None
    rate_hz: float = 10.0
    start_stamp_ns: int = 0
    source: str | None = None
    dataset: str | None = None

    def __post_init__(self) -> None:
        if not (self.rate_hz > 0 and math.isfinite(self.rate_hz)):
            raise RecorderError(f"--rate-hz {self.rate_hz} must be a positive number", fix="pass e.g. --rate-hz 10")
        if self.start_stamp_ns < 0:
            raise RecorderError(f"--start-ns {self.start_stamp_ns} is negative", fix="pass a stamp >= 0")
        require_seed(self.seed, "record g2o --seed")
        if self.loop_measurements not in ("as-recorded", "same-place"):
            raise RecorderError(f"--loop-measurements {self.loop_measurements!r} is unknown", fix="use as-recorded or same-place")


@dataclass(frozen=True)
class DatasetHints:
    """What a file name tells about its dataset (robustslam_kitti naming)."""

    name: str
    source: str
    ground_truth: Path | None = None
    true_loops: Path | None = None


def dataset_hints(graph_path: Path) -> DatasetHints:
    """Dataset name, detector and sibling files guessed from the file name."""
    match = _ROBUSTSLAM_NAME.match(graph_path.name)
    if match:
        seq, alpha = match["seq"], match["alpha"]
        gt = graph_path.with_name(f"kitti_{seq}_GT.g2o")
        labels = graph_path.with_name(f"kitti_{seq}_alpha_{alpha}_GT_LC.txt")
        return DatasetHints(
            f"robustslam_kitti/{seq}/alpha_{alpha}",
            "DLoopDetector",
            gt if gt.is_file() else None,
            labels if labels.is_file() else None,
        )
    match = _ROBUSTSLAM_ODOM_NAME.match(graph_path.name)
    if match:
        gt = graph_path.with_name(f"kitti_{match['seq']}_GT.g2o")
        return DatasetHints(f"robustslam_kitti/{match['seq']}/odom", "g2o", gt if gt.is_file() else None)
    return DatasetHints(graph_path.stem, "g2o")


@dataclass(frozen=True)
class G2oRecording:
    """Everything a g2o log will carry, before writing (pure; see :func:`prepare_g2o`).

    Attributes:
        odometry: ``(N, 3)`` cumulative odometry.
        ground_truth: ``(N, 3)`` ground truth or ``None``.
        candidates: all candidates (graph loops, then injected), oriented (later, earlier).
        true_loops: labelled true pairs ``(query, match)``; ``None`` when the log has no labels.
        stamps_ns: ``(N,)`` frame stamps.
    """

    graph: PoseGraph2D
    dataset: str
    source: str
    odometry: np.ndarray
    ground_truth: np.ndarray | None
    candidates: tuple[LoopCandidate, ...]
    true_loops: frozenset[tuple[int, int]] | None
    stamps_ns: np.ndarray
    config: dict = field(default_factory=dict)


def prepare_g2o(graph_path: str | Path, options: G2oOptions = G2oOptions()) -> G2oRecording:
    """Load a graph and its optional ground truth and labels, inject outliers; no output yet."""
    graph_path = Path(graph_path)
    graph = load_g2o(graph_path)
    _warn_about(graph)
    hints = dataset_hints(graph_path)
    n = graph.num_poses
    gt_path = options.ground_truth or (hints.ground_truth if options.auto_siblings else None)
    labels_path = options.true_loops or (hints.true_loops if options.auto_siblings else None)
    if options.auto_siblings and options.ground_truth is None and gt_path is not None:
        log.info("using the sibling ground truth %s (--no-auto-siblings to skip)", gt_path)
    if options.auto_siblings and options.true_loops is None and labels_path is not None:
        log.info("using the sibling true-loop labels %s (--no-auto-siblings to skip)", labels_path)
    ground_truth = load_ground_truth(gt_path, n) if gt_path is not None else None

    source = options.source or hints.source
    candidates = list(graph.loop_candidates(source))
    if options.loop_measurements == "same-place":
        candidates = [LoopCandidate(c.query_frame, c.match_frame, c.similarity, c.hamming, c.source) for c in candidates]
    original_pairs = {c.pair for c in candidates}

    injected: tuple[LoopCandidate, ...] = ()
    if options.outliers:
        info = options.outlier_information or (graph.loops[0].information if graph.loops else VERTIGO_DEFAULT_INFORMATION)
        if options.outlier_information is None and not graph.loops:
            log.info("the graph has no loop to copy the information matrix from; injected loops use Vertigo's default 42.7*I")
        injected = inject_outliers(
            n, options.outliers, mode=options.outlier_mode, group_size=options.group_size,
            information=info, seed=options.seed, existing_pairs=original_pairs,
            ground_truth=ground_truth, min_distance_m=options.outlier_min_distance_m,
        )

    true_loops: frozenset[tuple[int, int]] | None = None
    if labels_path is not None:
        true_loops = load_true_loops(labels_path, n)
        unknown = true_loops - original_pairs
        if unknown:
            log.warning("%s: %d labelled true loops are not among the graph's candidates, e.g. %s", labels_path, len(unknown), sorted(unknown)[0])
    else:
        # Automatic: a graph spoiled with outliers had all-true loops (the Vertigo protocol), unless
        # its loops come from a place recognizer (robustslam_kitti), whose loops are mostly false.
        auto = bool(options.outliers) and hints.source == "g2o"
        label_originals = options.original_loops_true if options.original_loops_true is not None else auto
        if options.original_loops_true is None and options.outliers and not auto:
            log.warning("%s: the graph's loops come from %s and no --true-loops is given: the log has no labels", graph_path, hints.source)
        if label_originals:
            true_loops = frozenset(original_pairs)

    stamps_ns = options.start_stamp_ns + np.rint(np.arange(n) * (1e9 / options.rate_hz)).astype(np.int64)
    config = options_config(options, graph=graph_path, ground_truth=gt_path, true_loops=labels_path, graph_loops=len(graph.loops))
    return G2oRecording(
        graph, options.dataset or hints.name, source, graph.odometry_poses(), ground_truth,
        tuple(candidates) + injected, true_loops, stamps_ns, config,
    )


def record_g2o(
    graph_path: str | Path,
    out_path: str | Path,
    options: G2oOptions = G2oOptions(),
    *,
    force: bool = False,
    progress: ProgressCallback | None = None,
    live: bool = False,
) -> RecordStats:
    """Record a 2-D pose graph into an lcv-replay log at ``out_path`` (atomically).

    Raises:
        RecorderError: the graph, ground truth or labels cannot be read.
        OutputError: ``out_path`` exists (without ``force``) or cannot be written.
    """
    from lcv_replay.fileio import check_output_path

    started = time.perf_counter()
    out_path = check_output_path(out_path, force=force)
    rec = prepare_g2o(graph_path, options)
    frames = make_frames(rec.stamps_ns, odometry=rec.odometry, ground_truth=rec.ground_truth)
    header = LogHeader(
        dataset=rec.dataset,
        recorder="g2o",
        nominal_rate_hz=options.rate_hz,
        config=rec.config,
        odometry_information=rec.graph.odometry_information_matrix(),
        warnings=rec.graph.warnings(),
    )
    return write_log(
        out_path, header, frames, candidates=rec.candidates, true_loops=rec.true_loops or (),
        force=force, progress=progress, started=started, live=live,
    )
