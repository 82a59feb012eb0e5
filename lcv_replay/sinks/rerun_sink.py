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
import rerun as rr

from lcv_replay.config import RerunConfig
from lcv_replay.sinks.config import RerunOutputs
from lcv_replay.errors import OutputError
from lcv_replay.fileio import check_output_path
from lcv_replay.sinks import blueprint as bp
from lcv_replay.sinks.base import BaseSink, FrameUpdate, RetrievalUpdate, RunStart, RunSummary, StepUpdate
from lcv_replay.sinks.layout import (
    STATE_STYLE,
    STATE_WIDTH_PT,
    ConstraintState,
    GrowingRows,
    MapEstimate,
    anchor_to_first,
    consistency_rows,
    constraint_states,
    flatten,
    hypotheses_markdown,
    key_value_markdown,
    retrieval_markdown,
    segments,
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
CONSISTENCY_MAX_CELLS = 1_000_000  # rows of the consistency tensor are cut to fit (best first)
TREE_MAX_NODES = 5_000  # the generation tree keeps the newest nodes beyond this
JPEG_QUALITY = 85
DETERMINISTIC_FLUSH_TICK_S = 1e6  # "never": file-only recordings flush on size and at explicit points
LIVE_REFRESH_S = 0.25  # with a viewer watching, buffered rows and the map are sent at least this often

#: Drawing priority of each ConstraintState (index = state value): what needs attention on top.
DRAW_PRIORITY = np.array([0, 2, 0, 4, 3, 0])
_LINE = rr.Radius.ui_points(1.0)
_THICK = rr.Radius.ui_points(2.5)
_RANK1_COLOR = (255, 200, 0)


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

    @property
    def recording_path(self) -> Path | None:  # type: ignore[override]
        return None if self.outputs.save is None else Path(self.outputs.save)

    # ------------------------------------------------------------------ set-up
    def on_start(self, start: RunStart) -> None:
        self._start = start
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
        blueprint = bp.default_blueprint(has_images=start.has_images, has_retrieval=start.code_bits is not None)
        rec.set_sinks(*sinks, default_blueprint=blueprint)
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
        rec.log(bp.RETRIEVAL_LINES, rr.LineStrips2D.from_fields(radii=[_LINE], colors=[(60, 140, 250)], show_labels=False), static=True)
        rec.log(bp.CONSTRAINTS_PENDING, rr.LineStrips2D.from_fields(radii=[rr.Radius.ui_points(STATE_WIDTH_PT[ConstraintState.PENDING])], class_ids=[int(ConstraintState.PENDING)], show_labels=False), static=True)
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
        rec = self._rec
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
        rec.log(bp.TRAJ_ODOMETRY, rr.LineStrips2D([self._map.odometry[:, :2]], radii=_LINE, colors=[(150, 150, 150)], labels=["odometry"], show_labels=False))
        rec.log(bp.TRAJ_BEST, rr.LineStrips2D([self._map.poses()[:, :2]], radii=_THICK, colors=[_RANK1_COLOR], labels=["best estimate"], show_labels=False))
        if self._gt_rows:  # drawn from the odometry's first pose, so the drift shows as their separation
            gt = anchor_to_first(np.asarray(self._gt_rows[:n]), self._map.odometry[0])
            rec.log(bp.TRAJ_GROUND_TRUTH, rr.LineStrips2D([gt[:, :2]], radii=_LINE, colors=[(90, 200, 255)], labels=["ground truth"], show_labels=False))

    # ------------------------------------------------------------------ retrieval
    def on_retrieval(self, update: RetrievalUpdate) -> None:
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

        # Constraints, coloured by state on that map.
        self._judged = len(constraints)
        states = constraint_states(len(constraints), step.accepted_constraint_ids, truth)
        if constraints:
            # Instances in drawing order: faint states first, wrong acceptances last (on top).
            order = np.argsort(DRAW_PRIORITY[states], kind="stable")
            picked = [constraints[i] for i in order]
            drawn = states[order]
            pairs = np.array([(c.query_frame, c.match_frame) for c in picked], dtype=np.int64)
            positions = self._map.poses()[:, :2]
            # Negative radii are UI points (rr.Radius.ui_points): faint states thin, wrong loops thick.
            radii = -np.asarray(STATE_WIDTH_PT, dtype=np.float32)[drawn]
            rec.log(
                bp.CONSTRAINTS_SEGMENTS,
                rr.LineStrips2D(segments(positions, pairs), radii=radii, class_ids=drawn.astype(np.uint16), show_labels=False),
                rr.AnyValues(
                    constraint_id=np.array([c.id for c in picked], dtype=np.int64),
                    query_frame=pairs[:, 0],
                    match_frame=pairs[:, 1],
                    similarity=np.array([c.candidate.similarity for c in picked], dtype=np.float64),
                    state=[STATE_STYLE[ConstraintState(int(s))][0] for s in drawn],
                ),
            )
        rec.log(bp.CONSTRAINTS_PENDING, rr.Clear(recursive=False))

        # Hypotheses: ranks, top-k trajectories, consistency, tree, sequences.
        if ranking:
            values = _rank_values(ranking)
            rec.log(bp.HYPOTHESES_RANKS, rr.BarChart(values, color=_RANK1_COLOR),
                    rr.AnyValues(hypothesis_id=np.array([h.id for h in ranking], dtype=np.int64),
                                 score=np.array([h.score for h in ranking], dtype=np.int64)))
            strips, labels, colors = [], [], []
            for h in ranking[:top_k]:
                traj = step.trajectories.get(h.id)
                if traj is None or len(traj) == 0:
                    continue
                strips.append(np.asarray(traj)[:, :2])
                labels.append(f"#{h.rank} H{h.id} ({h.score})")
                colors.append(_RANK1_COLOR if h.rank == 1 else _rank_color(h.rank, top_k))
            if strips:
                rec.log(bp.HYPOTHESES_TRAJECTORIES, rr.LineStrips2D(strips, labels=labels, colors=colors, radii=_LINE))
        consistency = np.asarray(step.consistency)
        if consistency.ndim == 2 and consistency.size:
            rows = consistency_rows(consistency.shape, min_rows=top_k, max_cells=CONSISTENCY_MAX_CELLS)
            rec.log(bp.HYPOTHESES_CONSISTENCY, rr.Tensor(consistency[:rows].astype(np.uint8), dim_names=("hypothesis_rank", "constraint_id"), value_range=(0.0, 1.0)))
        self._log_tree(update)
        rec.log(bp.HYPOTHESES_SEQUENCES, rr.TextDocument(hypotheses_markdown(ranking, constraints, top=top_k), media_type=rr.MediaType.MARKDOWN))

        self._log_events(update, states)
        self._log_metrics(update)
        self._log_trajectories()
        self._flush_columns()

    def _log_tree(self, update: StepUpdate) -> None:
        step = update.step
        for h in step.new_hypotheses:
            self._tree.setdefault(h.id, (h.parent_id, None, h.window))
        for parent, child, cid in step.generation_edges:
            _, _, window = self._tree.get(child, (parent, cid, step.window_index))
            self._tree[child] = (parent, cid, window)
        if not self._tree and not step.ranking:
            return
        for h in step.ranking:
            self._tree.setdefault(h.id, (h.parent_id, None, h.window))
        if len(self._tree) > TREE_MAX_NODES:
            for old in sorted(self._tree)[: len(self._tree) - TREE_MAX_NODES]:
                del self._tree[old]
        kept = {h.id: h for h in step.ranking}
        top_id = step.ranking[0].id if step.ranking else None
        ids = sorted(self._tree)
        labels, colors = [], []
        for hid in ids:
            parent, cid, _ = self._tree[hid]
            label = f"H{hid}" + (f" +c{cid}" if cid is not None else "")
            if hid in kept:
                label += f" ({kept[hid].score})"
            labels.append(label)
            colors.append(_RANK1_COLOR if hid == top_id else ((90, 160, 250) if hid in kept else (110, 110, 110)))
        self._rec.log(bp.HYPOTHESES_TREE, rr.GraphNodes([f"H{i}" for i in ids], labels=labels, colors=colors))
        edges = [(f"H{p}", f"H{c}") for c, (p, _, _) in ((i, self._tree[i]) for i in ids) if p is not None and p in self._tree]
        if edges:
            self._rec.log(bp.HYPOTHESES_TREE, rr.GraphEdges(edges, graph_type="directed"))

    def _log_events(self, update: StepUpdate, states: np.ndarray) -> None:
        rec = self._rec
        step = update.step
        constraints = update.constraints
        accepted = set(int(i) for i in step.accepted_constraint_ids)
        frame = step.frame_index
        for cid in sorted(accepted - self._accepted):
            c = constraints[cid]
            state = ConstraintState(int(states[cid]))
            truly = " — TRULY FALSE" if state is ConstraintState.ACCEPTED_FALSE else ""
            rec.log(bp.EVENTS, rr.TextLog(
                f"constraint {cid} ({c.query_frame}↔{c.match_frame}) accepted at frame {frame}{truly}",
                level=rr.TextLogLevel.WARN if truly else rr.TextLogLevel.INFO))
        for cid in sorted(self._accepted - accepted):
            c = constraints[cid]
            rec.log(bp.EVENTS, rr.TextLog(
                f"constraint {cid} ({c.query_frame}↔{c.match_frame}) no longer accepted at frame {frame}",
                level=rr.TextLogLevel.INFO))
        self._accepted = accepted
        if step.ranking:
            top = (step.ranking[0].id, step.ranking[0].score)
            if self._top is None or top[0] != self._top[0]:
                before = "none" if self._top is None else f"#{self._top[0]} (score {self._top[1]})"
                rec.log(bp.EVENTS, rr.TextLog(
                    f"rank-1 hypothesis changed from {before} to #{top[0]} (score {top[1]}) at frame {frame}",
                    level=rr.TextLogLevel.INFO))
            self._top = top
        if step.dropped:
            rec.log(bp.EVENTS, rr.TextLog(f"{len(step.dropped)} hypotheses dropped at frame {frame}: "
                                          + ", ".join(f"#{h} ({why})" for h, why in step.dropped[:10])
                                          + (" …" if len(step.dropped) > 10 else ""),
                                          level=rr.TextLogLevel.DEBUG))

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
        self._finished = True

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
        rec, self._rec = self._rec, None
        if rec is None:
            return
        try:
            rec.flush()
        finally:
            rec.disconnect()
            del rec
            if self._server is not None:
                stop_web_server(self._server)
                self._server = None
        if self._tmp_path is None:
            return
        if self._finished:
            os.replace(self._tmp_path, self.outputs.save)
        else:  # an error: do not leave a half-written recording behind
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


def _rank_color(rank: int, top_k: int) -> tuple[int, int, int]:
    t = (rank - 1) / max(top_k - 1, 1)
    return (int(90 + 60 * t), int(160 - 60 * t), int(250 - 100 * t))
