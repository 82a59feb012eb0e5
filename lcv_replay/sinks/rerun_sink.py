"""The Rerun sink: every intermediate result of a replay on the ``frame`` and ``log_time`` timelines.

Outputs combine (tee): ``--save OUT.rrd`` (written to a temp file and renamed when the replay ends,
Ctrl-C included), ``--spawn`` (a local viewer), ``--connect URL`` (a running viewer) and ``--serve``
(a gRPC server plus the web viewer, both bound to 127.0.0.1). What is logged, and where, is listed in
:mod:`lcv_replay.sinks.blueprint`; the pure array work is in :mod:`lcv_replay.sinks.layout`.

Logging discipline: few entities with many instances; per-frame scalar series are buffered and sent
with ``rr.send_columns``; the growing trajectories are re-logged every ``TRAJECTORY_EVERY`` frames and
at each verifier step, not every frame.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import socket
import subprocess
import sys
import time
import uuid
from collections import defaultdict
from pathlib import Path
from typing import Any, Sequence
from urllib.parse import quote

import numpy as np

# Set before the first `import rerun` (the SDK reads them when it loads):
# * Rerun's file writer logs its own lines when a write fails (a full disk); :meth:`RerunSink.close`
#   turns that failure into one ``error:`` line, so those are silenced unless RUST_LOG asks for them.
# * The SDK's allocator (mimalloc) keeps freed memory for a while by default; the arrays this sink
#   logs grow with the replay (whole trajectories, every constraint), and held back they made the
#   process grow by ~3 kB per frame (bench soak: +22 % RSS over 15,000 frames). Returned at once.
os.environ.setdefault(
    "RUST_LOG", "warn,re_log_encoding::rrd::file_sink=off,re_log_encoding::rrd::encoder=off,re_sdk::recording_stream=off"
)
os.environ.setdefault("MIMALLOC_PURGE_DELAY", "0")
import rerun as rr  # noqa: E402 - after the environment above

from lcv_replay.config import RerunConfig
from lcv_replay.sinks.config import RerunOutputs
from lcv_replay.errors import OutputError
from lcv_replay.fileio import check_output_path, is_write_failure, write_error
from lcv_replay.sinks import blueprint as bp
from lcv_replay.sinks.base import BaseSink, FrameUpdate, RetrievalUpdate, RunStart, RunSummary, StepUpdate
from lcv_replay.sinks.run_record import RunRecorder, consistency_snapshot, grow_tree
from lcv_replay.sinks.layout import (
    STATE_STYLE,
    STATE_WIDTH_PT,
    ConstraintState,
    GrowingRows,
    MapEstimate,
    _fmt,
    ancestry,
    anchor_to_first,
    compress_chains,
    constraint_states,
    flatten,
    hypotheses_markdown,
    key_value_markdown,
    retrieval_markdown,
    segments,
    tree_layout,
)

logger = logging.getLogger(__name__)

APPLICATION_ID = "lcv-replay"
#: Summary keys measured on the wall clock (they differ between identical runs).
WALL_CLOCK_KEYS = ("wall_time_s", "x_real_time", "setup_time_s")
TRAJECTORY_EVERY = 50  # frames between re-logs of the growing trajectories (5 s of a 10 Hz log)
COLUMN_FLUSH_FRAMES = 50  # per-frame series are sent with send_columns every this many frames
PENDING_FULL_LIMIT = 500  # re-log the pending constraints at each arrival while there are this few
PENDING_EVERY = 10  # ... else every this many frames
PENDING_MAX_DRAWN = 300  # the newest pending constraints drawn (all of them are judged at the step)
JPEG_QUALITY = 85
DETERMINISTIC_FLUSH_TICK_S = 1e6  # "never": file-only recordings flush on size and at explicit points
LIVE_REFRESH_S = 0.25  # with a viewer watching, buffered rows and the map are sent at least this often

TREE_DX, TREE_DY = 150.0, 40.0  # generation-tree layout: depth step and row step (graph view units)
REJECTED_MAX_DRAWN = 400  # rejected candidates drawn per step (evenly over their ids); all are in /postmortem
_LINE = rr.Radius.ui_points(1.0)
_FAINT_LINE = rr.Radius.ui_points(0.75)
_THICK = rr.Radius.ui_points(2.0)
_RANK1_COLOR = (255, 200, 0)
_AMBIGUOUS_COLOR = (190, 90, 250)
_CELL_OFF, _CELL_TRUE, _CELL_FALSE, _CELL_UNKNOWN = (45, 45, 50), (40, 200, 80), (255, 45, 45), (80, 140, 250)


class _Columns:
    """Per-frame series buffered for ``rr.send_columns`` (one entity per series)."""

    def __init__(self) -> None:
        self._rows: dict[str, list[tuple[int, int, float]]] = defaultdict(list)
        self._points: dict[str, list[tuple[int, int, float, float]]] = defaultdict(list)

    def scalar(self, path: str, frame: int, stamp_ns: int, value: float | None) -> None:
        if value is not None and np.isfinite(value):
            self._rows[path].append((frame, stamp_ns, float(value)))

    def point(self, path: str, frame: int, stamp_ns: int, xy: np.ndarray) -> None:
        self._points[path].append((frame, stamp_ns, float(xy[0]), float(xy[1])))

    def flush(self, rec: rr.RecordingStream) -> None:
        for path, rows in self._rows.items():
            if rows:
                data = np.asarray(rows, dtype=np.float64)
                rec.send_columns(path, indexes=_indexes(rows), columns=rr.Scalars.columns(scalars=data[:, 2]))
        for path, rows in self._points.items():
            if rows:
                data = np.asarray(rows, dtype=np.float64)
                rec.send_columns(path, indexes=_indexes(rows), columns=rr.Points2D.columns(positions=data[:, 2:4]))
        self._rows.clear()
        self._points.clear()


class _RetrievalColumns:
    """Per-query retrieval panels buffered for ``rr.send_columns`` (code, matches table, map lines).

    A query with no match still gets a row (an empty set of lines, "nothing retrieved"), so that
    the panels never show a previous query's matches.
    """

    def __init__(self, code_bits: int, top_k: int) -> None:
        self._format = rr.components.ImageFormat(width=code_bits, height=1, color_model="L", channel_datatype="U8")
        self._top_k = top_k
        self._rows: list[tuple[int, int]] = []
        self._codes: list[np.ndarray] = []
        self._texts: list[str] = []
        self._ends: list[np.ndarray] = []  # (K, 2, 2) per query
        self._matches: list[np.ndarray] = []
        self._l2: list[np.ndarray] = []

    def add(self, frame: int, stamp_ns: int, code: np.ndarray, text: str, ends: np.ndarray, matches: np.ndarray, l2: np.ndarray) -> None:
        self._rows.append((frame, stamp_ns))
        self._codes.append(np.asarray(code, dtype=bool).astype(np.uint8) * 255)
        self._texts.append(text)
        self._ends.append(ends)
        self._matches.append(matches)
        self._l2.append(l2)

    def flush(self, rec: rr.RecordingStream) -> None:
        if not self._rows:
            return
        indexes = _indexes(self._rows)
        n = len(self._rows)
        rec.send_columns(bp.RETRIEVAL_CODE, indexes=indexes, columns=rr.Image.columns(buffer=self._codes, format=[self._format] * n))
        rec.send_columns(bp.RETRIEVAL_MATCHES, indexes=indexes,
                         columns=rr.TextDocument.columns(text=self._texts, media_type=[rr.MediaType.MARKDOWN] * n))
        # L2 distance of rank r = instance r - 1 (NaN: fewer matches), one time series per rank.
        distances = np.full((n, self._top_k), np.nan)
        for row, l2 in enumerate(self._l2):
            distances[row, : min(len(l2), self._top_k)] = l2[: self._top_k]
        rec.send_columns(bp.RETRIEVAL_DISTANCES, indexes=indexes,
                         columns=rr.Scalars.columns(scalars=distances.reshape(-1)).partition([self._top_k] * n))
        lengths = [len(e) for e in self._ends]
        strips = [strip for ends in self._ends for strip in ends]
        rec.send_columns(bp.RETRIEVAL_LINES, indexes=indexes, columns=[
            *rr.LineStrips2D.columns(strips=strips).partition(lengths),
            *rr.AnyValues.columns(match_frame=np.concatenate(self._matches), l2_distance=np.concatenate(self._l2)).partition(lengths),
        ])
        self.__init__(int(self._format.width), self._top_k)


def _any_values(**columns: Any) -> rr.AnyValues:
    """``rr.AnyValues`` that keeps empty columns (typed Arrow arrays: numpy dtypes, or strings for
    lists), so that "no instance at this step" is logged rather than silently dropped. NaN in a
    float column is stored as null (a missing value compares equal to itself across recordings)."""
    import pyarrow as pa

    typed = {}
    for name, value in columns.items():
        if isinstance(value, np.ndarray) and value.dtype.kind == "f":
            missing = np.isnan(value)  # null, with a zero in the data buffer (bitwise-equal runs)
            typed[name] = pa.array(np.where(missing, 0.0, value).astype(value.dtype), mask=missing)
        elif isinstance(value, np.ndarray):
            typed[name] = pa.array(value)
        elif isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value):
            typed[name] = pa.array(list(value), type=pa.string())
        else:
            typed[name] = value
    return rr.AnyValues(**typed)


def _indexes(rows: Sequence[tuple]) -> list:
    frames = np.fromiter((r[0] for r in rows), dtype=np.int64, count=len(rows))
    stamps = np.fromiter((r[1] for r in rows), dtype=np.int64, count=len(rows)).astype("datetime64[ns]")
    return [
        rr.TimeColumn(bp.FRAME_TIMELINE, sequence=frames),
        rr.TimeColumn(bp.LOG_TIME_TIMELINE, timestamp=stamps),
    ]


def start_web_server(grpc_port: int, web_port: int, memory_limit: str, *, timeout_s: float = 20.0) -> subprocess.Popen:
    """Start ``rerun --serve-web`` (gRPC proxy + web viewer) bound to 127.0.0.1 only.

    The server runs in its own session, so a Ctrl-C that stops the replay leaves it serving; the
    sink terminates it when it closes. Raises :class:`OutputError` if it is not listening within
    ``timeout_s`` (e.g. a port in use).
    """
    command = [
        sys.executable, "-m", "rerun_cli", "--serve-web", "--bind", "127.0.0.1", "--port", str(grpc_port),
        "--web-viewer-port", str(web_port), "--server-memory-limit", memory_limit,
    ]
    server = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if server.poll() is not None:
            err = (server.stderr.read() or b"").decode(errors="replace").strip().splitlines()
            raise OutputError(
                f"the Rerun web server could not start on 127.0.0.1 ports {grpc_port}/{web_port}: "
                f"{err[-1] if err else 'exited'}",
                fix="choose free ports with --grpc-port/--web-port",
            )
        if all(_listening(port) for port in (grpc_port, web_port)):
            return server
        time.sleep(0.1)
    stop_web_server(server)
    raise OutputError(
        f"the Rerun web server did not listen on 127.0.0.1 ports {grpc_port}/{web_port} within {timeout_s:g} s",
        fix="choose free ports with --grpc-port/--web-port",
    )


def stop_web_server(server: subprocess.Popen, *, timeout_s: float = 10.0) -> None:
    """Terminate the server's whole process group (``python -m rerun_cli`` and the viewer binary)
    and wait until every process of the group is gone (so its ports are free again)."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(server.pid, signal.SIGTERM)
    deadline = time.monotonic() + timeout_s
    with contextlib.suppress(subprocess.TimeoutExpired):
        server.wait(timeout=timeout_s)
    while time.monotonic() < deadline:
        try:
            os.killpg(server.pid, 0)  # raises once the group has no process left
        except ProcessLookupError:
            return
        time.sleep(0.05)
    with contextlib.suppress(ProcessLookupError):
        os.killpg(server.pid, signal.SIGKILL)


def _listening(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex(("127.0.0.1", port)) == 0


def web_viewer_url(web_port: int, grpc_uri: str) -> str:
    """The URL that opens the served web viewer connected to the gRPC server."""
    return f"http://127.0.0.1:{web_port}/?url={quote(grpc_uri, safe='')}"


class RerunSink(BaseSink):
    """Logs a replay to Rerun (see the module docstring and :mod:`lcv_replay.sinks.blueprint`)."""

    def __init__(self, config: RerunConfig, outputs: RerunOutputs, *, recording_id: str | None = None):
        if not outputs.any:
            raise OutputError("the Rerun sink has no output", fix="pass --save, --spawn, --connect or --serve")
        if outputs.save is not None:
            check_output_path(outputs.save, force=True)
        self.config = config
        self.outputs = outputs
        self.served_url: str | None = None
        self._recording_id = recording_id or uuid.uuid4().hex
        self._rec: rr.RecordingStream | None = None
        self._server: subprocess.Popen | None = None  # `rerun --serve-web` for --serve
        self._tmp_path: Path | None = None
        self._finished = False
        self._columns = _Columns()
        self._retrieval: _RetrievalColumns | None = None  # created at the first query
        self._map = MapEstimate()
        self._start: RunStart | None = None
        self._constraint_rows = GrowingRows(3, dtype=np.int64)  # id, query_frame, match_frame
        self._judged = 0
        self._last_pending_frame = -(10**9)
        self._accepted: set[int] = set()
        self._top: tuple[int, int] | None = None  # (hypothesis id, score) of rank 1
        self._tree: dict[int, tuple[int | None, int | None, int]] = {}  # id -> (parent, constraint, window)
        self._gt_rows: list[np.ndarray] = []  # ground truth per frame (world frame): the start's, then the frames'
        self._frame = 0
        self._stamp_ns = 0
        self._stamps: list[int] = []  # log_time of each frame, by index
        self._stages: list[str] | None = None  # verifier stage names of /metrics/stage_time_s
        self._last_refresh = time.monotonic()
        self._recorder = RunRecorder()  # the run record, stored under /postmortem at the end
        self._wrong_seen = False  # a false acceptance was bookmarked
        self._missed_seen = False  # a missed true loop was bookmarked
        self._drawn_rejected = (0, 0)  # rejected constraints drawn / judged at the last step

    @property
    def recording_path(self) -> Path | None:  # type: ignore[override]
        return None if self.outputs.save is None else Path(self.outputs.save)

    # ------------------------------------------------------------------ set-up
    def on_start(self, start: RunStart) -> None:
        self._start = start
        self._recorder.on_start(start)
        # No automatic properties: their start time is the wall clock; ours is the log's (below).
        # A file-only recording is batched by size alone (no wall-clock flush tick), so that the same
        # log, config and seed give the same chunks; live viewers keep Rerun's default tick.
        batcher = None if self.outputs.live else rr.ChunkBatcherConfig(flush_tick=DETERMINISTIC_FLUSH_TICK_S)
        rec = rr.RecordingStream(APPLICATION_ID, recording_id=self._recording_id, send_properties=False, batcher_config=batcher)
        rec.set_log_time_enabled(False)  # our log_time is the MCAP's, not the wall clock
        rec.set_log_tick_enabled(False)
        self._rec = rec  # from here on, close() cleans up (server, temp file) whatever fails next
        sinks: list[Any] = []
        memory_limit = self.outputs.memory_limit or self.config.memory_limit
        if self.outputs.save is not None:
            save = Path(self.outputs.save)
            self._tmp_path = save.with_name(f".{save.name}.{os.getpid()}.tmp")
            sinks.append(rr.FileSink(str(self._tmp_path)))
        if self.outputs.spawn:
            rr.spawn(port=self.outputs.grpc_port, connect=False, memory_limit=memory_limit, hide_welcome_screen=True)
            sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{self.outputs.grpc_port}/proxy"))
        if self.outputs.connect is not None:
            sinks.append(rr.GrpcSink(self.outputs.connect))
        if self.outputs.serve:
            self._server = start_web_server(self.outputs.grpc_port, self.outputs.web_port, memory_limit)
            grpc_url = f"rerun+http://127.0.0.1:{self.outputs.grpc_port}/proxy"
            sinks.append(rr.GrpcSink(grpc_url))
            self.served_url = web_viewer_url(self.outputs.web_port, grpc_url)
        blueprint = bp.default_blueprint(has_images=start.has_images, has_retrieval=start.code_bits is not None,
                                         frames=start.frames, method=start.method)
        rec.set_sinks(*sinks)
        # Active, not only default: a viewer that kept another layout for this application id
        # (an older recording, a user's rearrangement) still opens this recording on the answer.
        rec.send_blueprint(blueprint, make_active=True, make_default=True)
        rec.send_recording_name(f"{start.log_path.name} · {start.method}")
        rec.send_recording_start_time_nanos(int(start.start_ns))
        self._log_static(start)

    def _log_static(self, start: RunStart) -> None:
        rec = self._rec
        for root in bp.MAP_ROOTS:  # the map is y-up (x forward, y left), like the log's odom frame
            rec.log(root, rr.Transform3D(scale=[1.0, -1.0, 1.0]), static=True)
        rec.log(
            "/constraints",
            rr.AnnotationContext(
                [rr.ClassDescription(info=rr.AnnotationInfo(id=int(state), label=label, color=color))
                 for state, (label, color) in STATE_STYLE.items()]
            ),
            static=True,
        )
        rec.log(bp.REPORT, rr.TextDocument(self._report_markdown(None), media_type=rr.MediaType.MARKDOWN), static=True)
        # Styles of the column-logged entities, static (rows carry only the data).
        rec.log(bp.RETRIEVAL_LINES, rr.LineStrips2D.from_fields(radii=[_LINE], colors=[(60, 140, 250)], show_labels=False,
                                                                draw_order=bp.DRAW_ORDER[bp.RETRIEVAL_LINES]), static=True)
        S = ConstraintState
        for path, state in ((bp.CONSTRAINTS_PENDING, S.PENDING), (bp.CONSTRAINTS_ACCEPTED, S.ACCEPTED),
                            (bp.CONSTRAINTS_WRONG, S.ACCEPTED_FALSE), (bp.CONSTRAINTS_MISSED, S.REJECTED_TRUE),
                            (bp.CONSTRAINTS_REJECTED, S.REJECTED_FALSE)):
            rec.log(path, rr.LineStrips2D.from_fields(radii=[rr.Radius.ui_points(STATE_WIDTH_PT[state])], show_labels=False,
                                                      draw_order=bp.DRAW_ORDER[path]), static=True)
        for path, colour in ((bp.TRUTH_WRONG, (255, 45, 45, 150)), (bp.TRUTH_MISSED, (250, 170, 30, 150))):
            rec.log(path, rr.LineStrips2D.from_fields(radii=[rr.Radius.ui_points(1.0)], colors=[colour], show_labels=False,
                                                      draw_order=bp.DRAW_ORDER[path]), static=True)
        rec.log(bp.CONSTRAINTS_AMBIGUOUS, rr.LineStrips2D.from_fields(radii=[rr.Radius.ui_points(2.0)], colors=[_AMBIGUOUS_COLOR],
                                                                      show_labels=False, draw_order=bp.DRAW_ORDER[bp.CONSTRAINTS_AMBIGUOUS]), static=True)
        for path, colour, radius, label in (
            (bp.TRAJ_ODOMETRY, (150, 150, 150, 170), _LINE, "odometry"),
            (bp.TRAJ_GROUND_TRUTH, (90, 200, 255, 170), _LINE, "ground truth"),
            (bp.TRAJ_BEST, _RANK1_COLOR, _THICK, "best estimate (rank-1 hypothesis)"),
        ):
            rec.log(path, rr.LineStrips2D.from_fields(colors=[colour], radii=[radius], labels=[label], show_labels=False,
                                                      draw_order=bp.DRAW_ORDER[path]), static=True)
        rec.log(bp.TRAJ_CURRENT, rr.Points2D.from_fields(colors=[(255, 255, 255)], radii=[rr.Radius.ui_points(4.0)],
                                                         draw_order=bp.DRAW_ORDER[bp.TRAJ_CURRENT]), static=True)
        for name, color in (("precision", (40, 200, 80)), ("recall", (60, 140, 250)), ("ate_rmse_m", (240, 90, 40))):
            rec.log(bp.metric_path(name), rr.SeriesLines(colors=[color], names=[name]), static=True)
        if start.ground_truth is not None and len(start.ground_truth):
            self._gt_rows = list(np.asarray(start.ground_truth, dtype=np.float64))

    # ------------------------------------------------------------------ per frame
    def _set_time(self, frame: int, stamp_ns: int) -> None:
        self._frame, self._stamp_ns = frame, stamp_ns
        self._rec.set_time(bp.FRAME_TIMELINE, sequence=frame)
        self._rec.set_time(bp.LOG_TIME_TIMELINE, timestamp=np.datetime64(int(stamp_ns), "ns"))

    def on_frame(self, update: FrameUpdate) -> None:
        self._recorder.on_frame(update)
        frame = update.frame
        self._set_time(frame.index, frame.stamp_ns)
        self._stamps.append(int(frame.stamp_ns))
        odom = frame.odom
        self._map.add_odometry((odom.x_m, odom.y_m, odom.yaw_rad) if odom is not None else self._last_odom())
        if frame.index >= len(self._gt_rows) and (frame.ground_truth is not None or self._gt_rows):
            # A log still being written (--follow) knew only part of its ground truth at the start.
            self._gt_rows += [np.full(3, np.nan)] * (frame.index - len(self._gt_rows))
            gt = frame.ground_truth
            self._gt_rows.append(np.array([gt.x_m, gt.y_m, gt.yaw_rad]) if gt is not None else np.full(3, np.nan))
        if update.new_constraints:
            self._constraint_rows.extend([(c.id, c.query_frame, c.match_frame) for c in update.new_constraints])

        every = self.config.image_every
        if every > 0 and frame.index % every == 0:
            if frame.left is not None:
                self._log_image(bp.CAMERA_LEFT, frame.left.decode())
            if self.config.log_right_image and frame.right is not None:
                self._log_image(bp.CAMERA_RIGHT, frame.right.decode())

        current = self._map.position_of(frame.index)
        self._columns.point(bp.TRAJ_CURRENT, frame.index, frame.stamp_ns, current)
        self._columns.scalar(bp.metric_path("constraints"), frame.index, frame.stamp_ns, update.constraints_total)
        self._columns.scalar(bp.FRAME_TIME, frame.index, frame.stamp_ns, update.frame_time_s)
        if update.new_constraints:
            pending = len(self._constraint_rows) - self._judged
            if pending <= PENDING_FULL_LIMIT or frame.index - self._last_pending_frame >= PENDING_EVERY:
                self._log_pending()
        if frame.index % TRAJECTORY_EVERY == 0:
            self._log_trajectories()
        if frame.index % COLUMN_FLUSH_FRAMES == COLUMN_FLUSH_FRAMES - 1:
            self._flush_columns()
        elif self.outputs.live and time.monotonic() - self._last_refresh >= LIVE_REFRESH_S:
            # Frames that arrive slowly (a followed log, a paced replay): a viewer sees each one now,
            # not 50 frames later. A replay at full speed never gets here between two batches.
            self._flush_columns()
            self._log_trajectories()
            self._last_refresh = time.monotonic()

    def _flush_columns(self) -> None:
        self._columns.flush(self._rec)
        if self._retrieval is not None:
            self._retrieval.flush(self._rec)

    def _last_odom(self) -> tuple[float, float, float]:
        odom = self._map.odometry
        return tuple(odom[-1]) if len(odom) else (0.0, 0.0, 0.0)

    def _log_image(self, path: str, image: np.ndarray) -> None:
        import cv2

        array = np.asarray(image)
        if array.ndim == 3 and array.shape[2] == 3:
            array = cv2.cvtColor(array, cv2.COLOR_RGB2BGR)
        ok, encoded = cv2.imencode(".jpg", array, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:  # pragma: no cover - cv2 encodes any uint8 image
            self._rec.log(path, rr.Image(image))
            return
        self._rec.log(path, rr.EncodedImage(contents=encoded.tobytes(), media_type="image/jpeg"))

    def _log_pending(self) -> None:
        # (P, 3): id, query, match of the newest pending constraints (retrieval proposes ~N_r per
        # frame: thousands per window would hide the map; the newest are the ones to watch).
        pending = self._constraint_rows.view[max(self._judged, len(self._constraint_rows) - PENDING_MAX_DRAWN) :]
        self._last_pending_frame = self._frame
        if not len(pending):
            self._rec.log(bp.CONSTRAINTS_PENDING, rr.Clear(recursive=False))
            return
        ends = self._map.positions_of(pending[:, 1:3].reshape(-1)).reshape(-1, 2, 2)
        self._rec.log(
            bp.CONSTRAINTS_PENDING,
            rr.LineStrips2D(ends),
            rr.AnyValues(constraint_id=pending[:, 0], query_frame=pending[:, 1], match_frame=pending[:, 2]),
        )

    def _log_trajectories(self) -> None:
        rec = self._rec
        n = self._map.frames
        rec.log(bp.TRAJ_ODOMETRY, rr.LineStrips2D([self._map.odometry[:, :2]]))
        rec.log(bp.TRAJ_BEST, rr.LineStrips2D([self._map.poses()[:, :2]]))
        truth = self._truth_display()
        if truth is not None:  # drawn from the odometry's first pose, so the drift shows as their separation
            rec.log(bp.TRAJ_GROUND_TRUTH, rr.LineStrips2D([truth[:n, :2]]))

    def _truth_display(self) -> np.ndarray | None:
        """``(N, 3)`` ground truth of the frames so far moved onto the odometry's first pose (NaN
        rows where unknown), or ``None`` without ground truth."""
        n = self._map.frames
        if not self._gt_rows or n == 0:
            return None
        rows = np.asarray(self._gt_rows[:n], dtype=np.float64)
        if len(rows) < n:
            rows = np.vstack([rows, np.full((n - len(rows), 3), np.nan)])
        return anchor_to_first(rows, self._map.odometry[0])

    # ------------------------------------------------------------------ retrieval
    def on_retrieval(self, update: RetrievalUpdate) -> None:
        self._recorder.on_retrieval(update)
        frame = update.frame
        if update.code is None:  # warming up: no query was made
            return
        self._columns.scalar(bp.metric_path("prefilter_size"), frame.index, frame.stamp_ns, update.prefilter_size)
        top = np.asarray(update.top_frames, dtype=np.int64).reshape(-1)
        l2 = np.asarray(update.l2_distances, dtype=np.float64).reshape(-1)
        if len(top):
            admitted = {int(c.match_frame) for c in update.candidates}
            similarity = {int(c.match_frame): float(c.similarity) for c in update.candidates}
            text = retrieval_markdown(frame.index, top, l2, update.hamming, admitted, [similarity.get(int(f)) for f in top])
            query = self._map.position_of(frame.index)
            ends = np.stack([np.broadcast_to(query, (len(top), 2)), self._map.positions_of(top)], axis=1)
        else:
            text = f"**query frame {frame.index}**: nothing retrieved"
            ends = np.zeros((0, 2, 2))
        if self._retrieval is None:
            top_k = int(dict(self._start.config).get("retrieval", {}).get("top_k", max(len(top), 1)))
            self._retrieval = _RetrievalColumns(len(update.code), top_k)
            self._rec.log(bp.RETRIEVAL_DISTANCES, rr.SeriesLines(names=[f"rank {r}" for r in range(1, top_k + 1)]), static=True)
        self._retrieval.add(frame.index, frame.stamp_ns, update.code, text, ends, top, l2)

    # ------------------------------------------------------------------ verifier steps
    def on_step(self, update: StepUpdate) -> None:
        self._recorder.on_step(update)
        rec = self._rec
        step = update.step
        self._set_time(step.frame_index, self._stamps[min(step.frame_index, len(self._stamps) - 1)])
        rec.set_time(bp.WINDOW_TIMELINE, sequence=step.window_index)
        try:
            self._log_step(update)
        finally:
            rec.disable_timeline(bp.WINDOW_TIMELINE)

    def _log_step(self, update: StepUpdate) -> None:
        rec = self._rec
        step = update.step
        constraints = list(update.constraints)
        truth = list(update.constraint_truth)
        self._constraint_rows = GrowingRows(3, dtype=np.int64)
        self._constraint_rows.extend([(c.id, c.query_frame, c.match_frame) for c in constraints])
        ranking = step.ranking
        top_k = self.config.top_hypotheses

        # Map of the rank-1 hypothesis.
        top_traj = _top_trajectory(step)
        if top_traj is not None:
            self._map.set_best(top_traj)

        # Constraints on that map, one entity per verdict (drawn in DRAW_ORDER: the verdict on top).
        self._judged = len(constraints)
        states = constraint_states(len(constraints), step.accepted_constraint_ids, truth)
        ambiguous = {int(i) for i in step.ambiguous_constraint_ids}
        self._log_constraints(constraints, states, ambiguous)
        rec.log(bp.CONSTRAINTS_PENDING, rr.Clear(recursive=False))

        # Hypotheses: ranks, top-k trajectories, consistency, tree, sequences.
        if ranking:
            values = _rank_values(ranking)
            rec.log(bp.HYPOTHESES_RANKS, rr.BarChart(values, color=_RANK1_COLOR),
                    rr.AnyValues(hypothesis_id=np.array([h.id for h in ranking], dtype=np.int64),
                                 score=np.array([h.score for h in ranking], dtype=np.int64),
                                 rank_key=np.array([h.rank_key for h in ranking], dtype=np.float64)))
            strips, labels, colors = [], [], []
            for h in ranking[:top_k]:
                traj = step.trajectories.get(h.id)
                if traj is None or len(traj) == 0 or h.rank == 1:  # rank 1 is the best estimate itself
                    continue
                strips.append(np.asarray(traj)[:, :2])
                labels.append(f"#{h.rank} H{h.id} (score {h.score})")
                colors.append(_rank_color(h.rank, top_k))
            rec.log(bp.HYPOTHESES_TRAJECTORIES, rr.LineStrips2D(strips, labels=labels, colors=colors, radii=_FAINT_LINE,
                                                                show_labels=False, draw_order=bp.DRAW_ORDER[bp.HYPOTHESES_TRAJECTORIES]))
        self._log_consistency(step, truth)
        self._log_tree(step, truth)
        key_name = "TLS key" if self._start.method == "ilv+" else None
        rec.log(bp.HYPOTHESES_SEQUENCES, rr.TextDocument(
            hypotheses_markdown(ranking, constraints, top=top_k, truth=truth, key_name=key_name), media_type=rr.MediaType.MARKDOWN))

        self._log_events(update, states)
        self._log_legend(states, ambiguous)
        self._log_metrics(update)
        self._log_trajectories()
        self._flush_columns()

    def _log_constraints(self, constraints: Sequence, states: np.ndarray, ambiguous: set[int]) -> None:
        """Every judged constraint on the rank-1 map, split by verdict; the rejected ones thinned."""
        positions = self._map.poses()[:, :2]
        S = ConstraintState
        groups = {
            bp.CONSTRAINTS_ACCEPTED: states == S.ACCEPTED,
            bp.CONSTRAINTS_WRONG: states == S.ACCEPTED_FALSE,
            bp.CONSTRAINTS_MISSED: states == S.REJECTED_TRUE,
            bp.CONSTRAINTS_REJECTED: (states == S.REJECTED) | (states == S.REJECTED_FALSE),
        }
        is_ambiguous = np.zeros(len(states), dtype=bool)
        is_ambiguous[[i for i in ambiguous if 0 <= i < len(states)]] = True
        groups = {path: mask & ~is_ambiguous for path, mask in groups.items()}
        groups[bp.CONSTRAINTS_AMBIGUOUS] = is_ambiguous  # logged (empty) at every step: a flag can be lifted
        for path, mask in groups.items():
            ids = np.flatnonzero(mask)
            if path == bp.CONSTRAINTS_REJECTED and len(ids) > REJECTED_MAX_DRAWN:
                ids = ids[np.unique(np.linspace(0, len(ids) - 1, REJECTED_MAX_DRAWN).round().astype(np.int64))]
            picked = [constraints[i] for i in ids]
            pairs = np.array([(c.query_frame, c.match_frame) for c in picked], dtype=np.int64).reshape(-1, 2)
            labels = [STATE_STYLE[ConstraintState(int(states[i]))][0] for i in ids]
            if path == bp.CONSTRAINTS_AMBIGUOUS:
                labels = ["ambiguous (flagged by the verifier)"] * len(ids)
            self._rec.log(
                path,
                rr.LineStrips2D(segments(positions, pairs), class_ids=states[ids].astype(np.uint16)),
                _any_values(
                    constraint_id=np.array([c.id for c in picked], dtype=np.int64),
                    query_frame=pairs[:, 0], match_frame=pairs[:, 1],
                    similarity=np.array([c.candidate.similarity for c in picked], dtype=np.float64),
                    state=labels,
                ),
            )
        self._drawn_rejected = (int(min(groups[bp.CONSTRAINTS_REJECTED].sum(), REJECTED_MAX_DRAWN)), int(groups[bp.CONSTRAINTS_REJECTED].sum()))
        truth = self._truth_display()
        if truth is not None:  # the verdict's mistakes where the places really are
            truth_xy = truth[:, :2]
            for path, mask in ((bp.TRUTH_WRONG, groups[bp.CONSTRAINTS_WRONG]), (bp.TRUTH_MISSED, groups[bp.CONSTRAINTS_MISSED])):
                picked = [constraints[i] for i in np.flatnonzero(mask)]
                pairs = np.array([(c.query_frame, c.match_frame) for c in picked], dtype=np.int64).reshape(-1, 2)
                ends = segments(truth_xy, pairs)
                known = np.all(np.isfinite(ends), axis=(1, 2))
                self._rec.log(path, rr.LineStrips2D(ends[known]),
                              _any_values(constraint_id=np.array([c.id for c in picked], dtype=np.int64)[known]))

    def _log_legend(self, states: np.ndarray, ambiguous: set[int]) -> None:
        """The map's legend, with the count of each kind at this step."""
        S = ConstraintState
        count = {state: int(np.count_nonzero(states == state)) for state in S}
        drawn, rejected = self._drawn_rejected
        truth_known = count[S.ACCEPTED_FALSE] + count[S.REJECTED_TRUE] + count[S.REJECTED_FALSE] > 0
        cells = [
            ("gold (thick)", "best estimate (rank 1)"),
            ("green", f"{count[S.ACCEPTED]} accepted" + (" true" if truth_known else "")),
            ("red (thickest)", f"{count[S.ACCEPTED_FALSE]} accepted but false"),
            ("orange", f"{count[S.REJECTED_TRUE]} true loops missed"),
        ]
        if ambiguous:
            cells.append(("violet", f"{len(ambiguous)} ambiguous (flagged)"))
        cells += [
            ("faint grey", f"{rejected} rejected" + (f" ({drawn} drawn)" if drawn < rejected else "")),
            ("light blue / grey", "ground truth / odometry (under)"),
        ]
        if self._gt_rows:
            cells.append(("thin red / orange on the light blue", "false / missed loops between their true places"))
        cells += [
            ("thin blue", "other top hypotheses"),
        ]
        # Prose, not a table: it wraps to whatever width the panel has.
        text = " · ".join(f"**{colour}**: {meaning}" for colour, meaning in cells)
        self._rec.log(bp.LEGEND, rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN))

    def _log_consistency(self, step, truth: Sequence[bool | None]) -> None:
        """The top hypotheses × the constraints that decide between them (the paper's Fig. W), as an
        image: a cell is lit where the hypothesis is consistent with the constraint, green for a
        true constraint, red for a false one, blue where the truth is unknown."""
        snap = consistency_snapshot(step, rows=self.config.top_hypotheses)
        if not snap.consistent.size:
            self._rec.log(bp.HYPOTHESES_CONSISTENCY, rr.Clear(recursive=False))
            return
        colours = np.array([_CELL_OFF, _CELL_TRUE, _CELL_FALSE, _CELL_UNKNOWN], dtype=np.uint8)
        code = np.zeros(snap.consistent.shape, dtype=np.int64)
        for c, cid in enumerate(snap.constraint_ids):
            t = truth[cid] if cid < len(truth) else None
            code[:, c] = np.where(snap.consistent[:, c], 1 if t is True else 2 if t is False else 3, 0)
        self._rec.log(
            bp.HYPOTHESES_CONSISTENCY,
            # From bytes with explicit sizes: an ndarray of one row would be taken for a 2-D image.
            rr.Image(bytes=colours[code].tobytes(), width=code.shape[1], height=code.shape[0], color_model="RGB",
                     datatype="u8", magnification_filter="Nearest"),
            _any_values(rows_hypothesis_id=snap.hypothesis_ids, columns_constraint_id=snap.constraint_ids),
        )

    def _log_tree(self, step, truth: Sequence[bool | None]) -> None:
        """The ancestry of the current top hypotheses (the paper's Fig. X), laid out left to right."""
        grow_tree(self._tree, step)
        if not step.ranking:
            return
        top = step.ranking[: self.config.top_hypotheses]
        nodes = ancestry(self._tree, [h.id for h in top])
        if not nodes:
            return
        parents, chains = compress_chains({n: self._tree[n][0] for n in nodes}, {n: self._tree[n][1] for n in nodes},
                                          [h.id for h in top])
        nodes = sorted(parents)
        positions = tree_layout(nodes, parents, [h.id for h in top], dx=TREE_DX, dy=TREE_DY)
        rank = {h.id: h for h in top}
        labels, colors = [], []
        for n in nodes:
            added = chains.get(n, ())
            false_added = [c for c in added if 0 <= c < len(truth) and truth[c] is False]
            h = rank.get(n)
            labels.append(f"H{n}" + (f" #{h.rank}" if h else "") + _chain_label(added, false_added))
            colors.append(_RANK1_COLOR if h is not None and h.rank == 1 else (255, 60, 60) if false_added
                          else (90, 160, 250) if h is not None else (130, 130, 130))
        self._rec.log(bp.HYPOTHESES_TREE, rr.GraphNodes([f"H{n}" for n in nodes], labels=labels, colors=colors,
                                                        positions=[positions[n] for n in nodes], show_labels=True))
        edges = [(f"H{p}", f"H{n}") for n, p in parents.items() if p is not None and p in parents]
        self._rec.log(bp.HYPOTHESES_TREE, rr.GraphEdges(edges, graph_type="directed"))

    def _log_events(self, update: StepUpdate, states: np.ndarray) -> None:
        """Bookmarks on the ``frame`` timeline: each window end, each false acceptance (the first
        named as such), the first missed true loop, drops, and each change of the rank-1 hypothesis."""
        rec = self._rec
        step = update.step
        constraints = update.constraints
        accepted = set(int(i) for i in step.accepted_constraint_ids)
        frame = step.frame_index
        newly = sorted(accepted - self._accepted)
        for cid in newly:
            c = constraints[cid]
            if ConstraintState(int(states[cid])) is ConstraintState.ACCEPTED_FALSE:
                first = "" if self._wrong_seen else "FIRST wrong acceptance: "
                self._wrong_seen = True
                rec.log(bp.EVENTS, rr.TextLog(f"frame {frame}: {first}constraint {cid} ({c.query_frame}↔{c.match_frame}) "
                                              "accepted, but it is false", level="WRONG"))
        dropped = sorted(self._accepted - accepted)
        if dropped:
            rec.log(bp.EVENTS, rr.TextLog(f"frame {frame}: {len(dropped)} no longer accepted: " + ", ".join(
                f"{cid} ({constraints[cid].query_frame}↔{constraints[cid].match_frame})" for cid in dropped[:12])
                + (" …" if len(dropped) > 12 else ""), level="DROPPED"))
        if not self._missed_seen:
            missed = np.flatnonzero(states == ConstraintState.REJECTED_TRUE)
            if len(missed):
                self._missed_seen = True
                c = constraints[int(missed[0])]
                rec.log(bp.EVENTS, rr.TextLog(
                    f"frame {frame}: FIRST missed true loop: constraint {c.id} ({c.query_frame}↔{c.match_frame}) not accepted"
                    + (f" ({len(missed)} true loops left out here)" if len(missed) > 1 else ""), level="MISSED"))
        self._accepted = accepted
        if step.ranking:
            top = (step.ranking[0].id, step.ranking[0].score)
            if self._top is not None and top[0] != self._top[0]:
                rec.log(bp.EVENTS, rr.TextLog(f"frame {frame}: rank 1 H{self._top[0]} (score {self._top[1]}) → H{top[0]} (score {top[1]})",
                                              level="RANK-1"))
            self._top = top
        det = update.metrics.detection
        parts = [f"frame {frame}: window {step.window_index} ends, {det.accepted} accepted (+{len(newly)})"]
        if det.false_positives is not None:
            parts.append(f"{det.false_positives} false, {det.false_negatives} missed")
        if det.precision is not None or det.recall is not None:
            parts.append(f"P {_fmt(det.precision)} R {_fmt(det.recall)}")
        if update.metrics.ate_rmse_m is not None:
            parts.append(f"ATE {update.metrics.ate_rmse_m:.2f} m")
        if step.ranking:
            parts.append(f"rank 1 H{step.ranking[0].id} (score {step.ranking[0].score})")
        rec.log(bp.EVENTS, rr.TextLog(", ".join(parts), level="FINAL" if update.final else "WINDOW"))
        for note in step.notes:
            rec.log(bp.EVENTS, rr.TextLog(f"frame {frame}: {note}", level="NOTE"))


    def _log_metrics(self, update: StepUpdate) -> None:
        rec = self._rec
        m = update.metrics
        det = m.detection
        for name, value in (
            ("precision", det.precision),
            ("recall", det.recall),
            ("ate_rmse_m", m.ate_rmse_m),
            ("accepted", det.accepted),
            ("hypotheses", m.hypotheses),
        ):
            if value is not None and np.isfinite(value):
                rec.log(bp.metric_path(name), rr.Scalars(float(value)))
        if update.step.gate_chi2 is not None:  # ilv+: the chi-square gate, calibrated to the data
            rec.log(bp.metric_path("gate_chi2"), rr.Scalars(float(update.step.gate_chi2)))
        timings = update.step.timings_s
        if timings:
            if self._stages is None:  # one entity, one instance per stage (fixed at the first step)
                self._stages = sorted(timings)
                rec.log(bp.STAGE_TIMES, rr.SeriesLines(names=self._stages), static=True)
            rec.log(bp.STAGE_TIMES, rr.Scalars([float(timings.get(s, float("nan"))) for s in self._stages]))

    # ------------------------------------------------------------------ end
    def on_finish(self, summary: RunSummary) -> None:
        if self._rec is None:
            return
        self._flush_columns()
        self._log_trajectories_if_any()
        self._rec.log(bp.REPORT, rr.TextDocument(self._report_markdown(summary), media_type=rr.MediaType.MARKDOWN), static=True)
        self._rec.log(bp.REPORT_TIMING, rr.TextDocument(_timing_markdown(summary), media_type=rr.MediaType.MARKDOWN), static=True)
        self._recorder.on_finish(summary)
        self._log_postmortem(self._recorder.record)
        self._finished = True

    def _log_postmortem(self, record) -> None:
        """The run record's columns as static ``/postmortem/<table>`` entities (``lcv-replay report``)."""
        for table, columns in record.to_columns().items():
            self._rec.log(f"{bp.POSTMORTEM}/{table}", _any_values(**columns), static=True)

    def _log_trajectories_if_any(self) -> None:
        if self._map.frames:
            self._set_time(self._frame, self._stamp_ns)
            self._log_trajectories()

    def _report_markdown(self, summary: RunSummary | None) -> str:
        start = self._start
        parts = [f"# lcv-replay: {start.log_path.name}", ""]
        if summary is None:
            parts.append("*replay running…*")
        else:
            items = summary.to_json_dict()
            # Wall-clock figures go to /report/timing; the config has its own table; the .rrd's own path
            # is where the reader already is.
            for volatile in ("config", "rrd", *WALL_CLOCK_KEYS):
                items.pop(volatile, None)
            ids = items.pop("accepted_constraint_ids", [])
            parts.append(key_value_markdown("Summary", items))
            parts.append("")
            parts.append(f"accepted constraint ids: {', '.join(map(str, ids)) or '(none)'}")
        parts += ["", key_value_markdown("Log", {
            "path": str(start.log_path), "frames": start.frames, "first log frame": start.first_log_frame,
            "duration_s": start.log_duration_s, "images": start.has_images, "ground truth": start.has_ground_truth,
            "truth of constraints": start.truth_source, **flatten(dict(start.log_metadata), "metadata."),
        })]
        parts += ["", key_value_markdown("Run", {
            "method": start.method, "constraints from": start.constraint_source,
            "rate": "max" if start.rate is None else start.rate, "seed": start.seed,
        })]
        parts += ["", key_value_markdown("Config", flatten(dict(start.config)))]
        return "\n".join(parts)

    def close(self) -> None:
        """Flush and disconnect; rename the finished recording onto ``--save``, or remove the temp file.

        A file writer that died (a full disk, usually; Rerun says ``File-writer thread shut down
        prematurely``) ends in one :class:`OutputError` naming the path and the free space, with
        the temp file removed.
        """
        rec, self._rec = self._rec, None
        if rec is None:
            return
        failure: Exception | None = None
        try:
            rec.flush()
        except Exception as exc:  # RuntimeError from the Rust file writer
            failure = exc
        except BaseException:  # a second Ctrl-C / SIGTERM while flushing: abort, keep no temp file
            self._finished = False
            with contextlib.suppress(Exception):
                rec.disconnect()
            self._remove_temp()
            raise
        finally:
            with contextlib.suppress(Exception):
                rec.disconnect()
            del rec
            if self._server is not None:
                stop_web_server(self._server)
                self._server = None
        if self._tmp_path is None:
            if failure is not None:
                raise failure
            return
        save = Path(self.outputs.save)
        error = None
        if failure is not None:
            error = write_error(save, failure, what="the Rerun recording")
        elif self._finished:
            try:
                os.replace(self._tmp_path, save)
                return
            except OSError as exc:
                if not is_write_failure(exc):
                    raise
                error = write_error(save, exc, what="the Rerun recording")
        self._remove_temp()  # an error, or not finished: do not leave a half-written recording behind
        if error is not None:
            raise error from None

    def _remove_temp(self) -> None:
        if self._tmp_path is not None:
            with contextlib.suppress(FileNotFoundError):
                self._tmp_path.unlink()


def _timing_markdown(summary: RunSummary) -> str:
    """The wall-clock figures of the run (kept apart from /report, which is deterministic)."""
    items = summary.to_json_dict()
    return key_value_markdown("Timing (wall clock)", {key: items[key] for key in WALL_CLOCK_KEYS})


def _top_trajectory(step) -> np.ndarray | None:
    from lcv_replay.evaluation.metrics import top_trajectory

    return top_trajectory(step)


def _rank_values(ranking) -> np.ndarray:
    """Bar heights in rank order: the ranking key (``float(score)`` for ``ilv``)."""
    keys = np.array([h.rank_key for h in ranking], dtype=np.float64)
    if np.any(keys != 0.0):
        return keys
    return np.array([h.score for h in ranking], dtype=np.float64)


def _chain_label(added: Sequence[int], false_added: Sequence[int]) -> str:
    """``" +c12"``, ``" +absorb"``, or ``" +5 (c3…c40, 2✗)"`` for a collapsed chain."""
    if not added:
        return ""
    if len(added) == 1:
        c = added[0]
        return (" +absorb" if c < 0 else f" +c{c}") + (" ✗" if false_added else "")
    named = [c for c in added if c >= 0]
    span = f"c{named[0]}…c{named[-1]}" if len(named) > 1 else (f"c{named[0]}" if named else "absorb")
    return f" +{len(added)} ({span}" + (f", {len(false_added)}✗" if false_added else "") + ")"


def _rank_color(rank: int, top_k: int) -> tuple[int, int, int, int]:
    """Faint blue to violet by rank (the other top hypotheses stay under the estimate)."""
    t = (rank - 1) / max(top_k - 1, 1)
    return (int(90 + 80 * t), int(150 - 70 * t), 250, 110)
