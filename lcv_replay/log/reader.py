"""The one log reader: an lcv-replay MCAP as :class:`~lcv_replay.records.Frame` records.

``open_log(path)`` indexes the file (summary + message indexes; no chunk is decoded), checks the
format (required topics, known schemas, increasing timestamps, stereo pairing) and returns a
:class:`LogReader`. Frames come out in time order; images are decoded lazily
(:class:`~lcv_replay.records.ImageRef`); time windows only decompress the chunks they touch.

Frames (docs/log-format.md): a log with left images has one frame per left image that pairs with a
right image (when the log has right images) within the stereo tolerance; a log without images has
one frame per ``/odom`` message. Frame ``i`` is the ``i``-th such frame in ``log_time`` order.
Odometry and ground truth are joined to frames by ``log_time`` within the same tolerance.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from lcv_replay.errors import ConfigError, LogFormatError
from lcv_replay.log import format as fmt
from lcv_replay.log import images, messages
from lcv_replay.log.container import ENTRY_DTYPE, Container, load_container
from lcv_replay.records import Frame, FrameWindow, ImageRef, LoopCandidate, Pose2D, StereoCalibration

log = logging.getLogger(__name__)

# Largest default stereo/odometry join tolerance; the default is min(this, 1/4 of the median frame period).
MAX_DEFAULT_TOLERANCE_NS = 10_000_000
# Stereo streams "cannot be paired" when more than this fraction of the images (and more than
# MAX_UNPAIRED_ABSOLUTE images) find no partner; fewer unpaired images are dropped with a warning.
MAX_UNPAIRED_FRACTION = 0.1
MAX_UNPAIRED_ABSOLUTE = 2

_PROTO, _JSON = "protobuf", "json"
# topic -> (accepted schema names, message encoding)
EXPECTED_SCHEMAS: dict[str, tuple[tuple[str, ...], str]] = {
    fmt.LEFT_IMAGE_TOPIC: ((messages.COMPRESSED_IMAGE_SCHEMA, messages.RAW_IMAGE_SCHEMA), _PROTO),
    fmt.RIGHT_IMAGE_TOPIC: ((messages.COMPRESSED_IMAGE_SCHEMA, messages.RAW_IMAGE_SCHEMA), _PROTO),
    fmt.LEFT_CALIBRATION_TOPIC: ((messages.CAMERA_CALIBRATION_SCHEMA,), _PROTO),
    fmt.RIGHT_CALIBRATION_TOPIC: ((messages.CAMERA_CALIBRATION_SCHEMA,), _PROTO),
    fmt.ODOM_TOPIC: ((messages.POSE_IN_FRAME_SCHEMA,), _PROTO),
    fmt.TF_TOPIC: ((messages.FRAME_TRANSFORM_SCHEMA,), _PROTO),
    fmt.GROUND_TRUTH_TOPIC: ((messages.POSE_IN_FRAME_SCHEMA,), _PROTO),
    fmt.LOOP_CANDIDATES_TOPIC: ((messages.LOOP_CANDIDATE_SCHEMA,), _JSON),
    fmt.TRUE_LOOPS_TOPIC: ((messages.TRUE_LOOP_SCHEMA,), _JSON),
}
# Topics whose log_time must strictly increase in file order.
_MONOTONIC_TOPICS = (fmt.LEFT_IMAGE_TOPIC, fmt.RIGHT_IMAGE_TOPIC, fmt.ODOM_TOPIC, fmt.GROUND_TRUTH_TOPIC)


@dataclass(frozen=True)
class TopicInfo:
    """One topic of a log: schema name, message count and mean rate over its own time span."""

    topic: str
    schema: str
    count: int
    rate_hz: float


@dataclass(frozen=True)
class LogInfo:
    """What ``lcv-replay info`` prints; computed when the log is opened (no chunk decoded).

    Times: ``start_ns``/``end_ns`` are the first and last frame stamps; ``duration_s`` is their
    difference. ``topics`` lists every channel of the file, known or not, sorted by topic.
    """

    path: Path
    file_size_bytes: int
    frames: int
    start_ns: int
    end_ns: int
    duration_s: float
    topics: tuple[TopicInfo, ...]
    has_images: bool
    has_right_images: bool
    has_odometry: bool
    has_ground_truth: bool
    has_candidates: bool
    has_labels: bool
    metadata: dict[str, str]
    recorder_config: dict[str, Any]
    odometry_information: np.ndarray | None
    nominal_rate_hz: float
    recovered_messages: int | None = None
    dropped_unpaired_images: int = 0
    stereo_tolerance_ns: int = 0
    message_count: int = 0
    chunk_count: int = 0
    skipped_chunks: int = 0
    candidate_count: int = 0
    true_loop_count: int = 0
    image_format: str | None = None
    library: str = ""
    recorder_warnings: dict[str, int] = field(default_factory=dict)  # lcv.recorder_warnings: counts by kind
    growing: bool = False  # opened while still being written (--follow): frames and counts are those known so far


@dataclass
class _Tables:
    """Per-frame message locations (rows of ``ENTRY_DTYPE`` tables) built at open."""

    stamps_ns: np.ndarray  # (N,) int64
    left: np.ndarray | None = None  # (N,) ENTRY_DTYPE or None
    right: np.ndarray | None = None
    odom: np.ndarray | None = None  # (N,) ENTRY_DTYPE; rows with chunk == -2 are missing
    ground_truth: np.ndarray | None = None
    candidates: np.ndarray = field(default_factory=lambda: np.empty(0, ENTRY_DTYPE))  # sorted by log_time
    true_loops: np.ndarray = field(default_factory=lambda: np.empty(0, ENTRY_DTYPE))
    candidate_frames: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))  # frame of each row
    true_loop_frames: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))


_MISSING = -2  # chunk value of a joined row without a message
# What a JSON message of the wrong shape raises while parsed (a list for an object, deep nesting, ...).
_JSON_ERRORS = (ValueError, KeyError, TypeError, AttributeError, RecursionError)


def open_log(path: str | Path, *, recover: bool = False, stereo_tolerance_ns: int | None = None) -> "LogReader":
    """Open and check an lcv-replay MCAP log.

    Args:
        path: the ``.mcap`` file.
        recover: salvage the complete chunks of a truncated or damaged file instead of refusing it;
            ``reader.info.recovered_messages`` says how many messages were recovered.
        stereo_tolerance_ns: left/right pairing and odometry/ground-truth join tolerance; default
            ``min(10 ms, median frame period / 4)``.

    Raises:
        LogFormatError: the file is not an MCAP, is truncated (without ``recover``), lacks required
            topics, carries an unknown schema on a known topic, has timestamps that go backwards,
            stereo streams that cannot be paired, or no frames. The message names the file, the
            problem and the fix.
    """
    return LogReader(load_container(path, recover=recover), stereo_tolerance_ns=stereo_tolerance_ns)


class LogReader:
    """An opened log (see :func:`open_log`). A context manager; holds no open file handle."""

    def __init__(self, container: Container, *, stereo_tolerance_ns: int | None = None):
        self._c = container
        self.path = container.path
        self._decoders: dict[int, Any] = {}
        self._topic_entries = {topic: self._entries_of(topic) for topic in EXPECTED_SCHEMAS}
        self._check_schemas()
        self._check_monotonic()
        self._tables, self._dropped, self._tolerance_ns = self._build_frames(stereo_tolerance_ns)
        self.info = self._build_info()
        self._candidates: list[LoopCandidate] | None = None
        self._true_loops: set[tuple[int, int]] | None = None
        self._odometry: np.ndarray | None = None
        self._ground_truth: np.ndarray | None = None

    def __enter__(self) -> "LogReader":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Drop cached chunks (the reader opens the file only while it reads)."""
        self._c._cache.clear()

    # -- public ------------------------------------------------------------------------------------
    @property
    def frame_stamps_ns(self) -> np.ndarray:
        """``(N,)`` int64 frame stamps (``log_time``) in nanoseconds, increasing."""
        return self._tables.stamps_ns.copy()

    @property
    def chunks_decoded(self) -> int:
        """Chunk decompressions done so far to read messages (time-window reads skip chunks)."""
        return self._c.chunks_decoded

    @cached_property
    def calibration(self) -> StereoCalibration | None:
        """Left calibration with the baseline from the right ``P[0, 3]``; ``None`` without calibration."""
        left = self._first_message(fmt.LEFT_CALIBRATION_TOPIC)
        if left is None:
            return None
        return messages.calibration_from_messages(left, self._first_message(fmt.RIGHT_CALIBRATION_TOPIC))

    def window(self, start_offset_s: float = 0.0, duration_s: float | None = None) -> FrameWindow:
        """The frames stamped in ``[stamp_0 + start_offset_s, + duration_s)`` (``None``: to the end).

        Raises:
            ConfigError: a negative offset or a duration that is not > 0.
        """
        if not (math.isfinite(start_offset_s) and start_offset_s >= 0):
            raise ConfigError(f"start offset {start_offset_s} s must be >= 0", fix="pass a non-negative --start-offset")
        if duration_s is not None and not (duration_s > 0):
            raise ConfigError(f"duration {duration_s} s must be > 0", fix="pass a positive --duration")
        stamps = self._tables.stamps_ns
        if len(stamps) == 0:
            return FrameWindow(0, 0)
        t0 = int(stamps[0]) + round(start_offset_s * 1e9)
        first = int(np.searchsorted(stamps, t0, "left"))
        if duration_s is None or not math.isfinite(duration_s):
            return FrameWindow(first, len(stamps))
        return FrameWindow(first, int(np.searchsorted(stamps, t0 + round(duration_s * 1e9), "left")))

    def frames(
        self, *, start_offset_s: float = 0.0, duration_s: float | None = None, window: FrameWindow | None = None
    ) -> Iterator[Frame]:
        """Frames in time order, optionally within ``[start + start_offset_s, + duration_s)``, or
        within a ``window`` from :meth:`window`. Frames keep their log indices.

        Only the chunks holding messages of the window are decompressed. Images are
        :class:`ImageRef` (decoded on ``.decode()``). ``Frame.candidates``/``true_loops`` hold the
        log's candidates/labels whose ``query_frame`` is the frame's index.
        """
        if window is None:
            window = self.window(start_offset_s, duration_s)  # raises here, not at the first next()
        return self._iter_frames(window.first, window.last)

    def _iter_frames(self, first: int, last: int) -> Iterator[Frame]:
        t = self._tables
        candidate_rows = _rows_by_frame(t.candidates, t.candidate_frames, first, last)
        true_loop_rows = _rows_by_frame(t.true_loops, t.true_loop_frames, first, last)
        for i in range(first, last):
            yield Frame(
                index=i,
                stamp_ns=int(t.stamps_ns[i]),
                odom=self._pose_at(t.odom, i, fmt.ODOM_TOPIC),
                ground_truth=self._pose_at(t.ground_truth, i, fmt.GROUND_TRUTH_TOPIC, allow_missing=True),
                left=self._image_at(t.left, i),
                right=self._image_at(t.right, i),
                candidates=tuple(self._at_frame(i, candidate_rows.get(i, ()), self._decode_candidate)),
                true_loops=tuple(self._at_frame(i, true_loop_rows.get(i, ()), self._decode_true_loop)),
            )

    def loop_candidates(self) -> list[LoopCandidate]:
        """Every candidate of ``/loop_candidates``, sorted by (query_frame, file order)."""
        if self._candidates is None:
            t = self._tables
            decoded = [
                item
                for row, frame in zip(t.candidates, t.candidate_frames)
                for item in self._at_frame(int(frame), (row,), self._decode_candidate)
            ]
            self._candidates = sorted(decoded, key=lambda c: c.query_frame)
        return list(self._candidates)

    def true_loops(self) -> set[tuple[int, int]]:
        """Labelled true pairs ``(query_frame, match_frame)`` of ``/ground_truth/loops``."""
        if self._true_loops is None:
            t = self._tables
            self._true_loops = {
                item
                for row, frame in zip(t.true_loops, t.true_loop_frames)
                for item in self._at_frame(int(frame), (row,), self._decode_true_loop)
            }
        return set(self._true_loops)

    def odometry(self) -> np.ndarray:
        """``(N, 3)`` float64 ``[x_m, y_m, yaw_rad]`` per frame; :class:`LogFormatError` if missing or not finite."""
        if self._odometry is None:
            if self._tables.odom is None:
                raise LogFormatError(
                    f"the log has no odometry ({fmt.ODOM_TOPIC})",
                    path=self.path,
                    fix="record it with odometry (e.g. --odometry) or estimate it with 'lcv-replay vo'",
                )
            self._odometry = self._poses(self._tables.odom, fmt.ODOM_TOPIC, allow_missing=False)
        return self._odometry.copy()

    def ground_truth(self) -> np.ndarray | None:
        """``(N, 3)`` ground truth ``[x_m, y_m, yaw_rad]`` (NaN rows where a frame has none), or ``None``."""
        if self._tables.ground_truth is None:
            return None
        if self._ground_truth is None:
            self._ground_truth = self._poses(self._tables.ground_truth, fmt.GROUND_TRUTH_TOPIC, allow_missing=True)
        return self._ground_truth.copy()

    def check(self) -> None:
        """Full check: every chunk's CRC, the data-section CRC, finite odometry, valid candidates/labels.

        Decodes everything but images.
        """
        self._c.verify_chunks()
        self._c.verify_data_section()
        if self._tables.odom is not None:
            self.odometry()
        self.ground_truth()
        self.loop_candidates()
        self.true_loops()

    # -- building ----------------------------------------------------------------------------------
    def _entries_of(self, topic: str) -> np.ndarray | None:
        """Message table of ``topic`` in file order, or ``None`` when the file has no such channel."""
        ids = self._c.topic_channels(topic)
        if not ids:
            return None
        parts = [self._c.entries.get(cid, np.empty(0, ENTRY_DTYPE)) for cid in ids]
        table = np.concatenate(parts)
        return table[np.lexsort((table["offset"], table["chunk"]))] if len(ids) > 1 else table

    def _check_schemas(self) -> None:
        for cid, channel in self._c.channels.items():
            expected = EXPECTED_SCHEMAS.get(channel.topic)
            if expected is None:
                continue
            names, encoding = expected
            schema = self._c.schemas.get(channel.schema_id)
            schema_name = schema.name if schema is not None else "(none)"
            if schema_name not in names or channel.message_encoding != encoding:
                raise LogFormatError(
                    f"topic {channel.topic} has unknown schema {schema_name!r} "
                    f"(encoding {channel.message_encoding!r}); expected {' or '.join(names)} ({encoding})",
                    path=self.path,
                    fix="convert the file with 'lcv-replay record' (e.g. 'lcv-replay record rosbag' for ROS 1 and ROS 2 bags, or replay the bag directly)",
                )

    def _check_monotonic(self) -> None:
        for topic in _MONOTONIC_TOPICS:
            table = self._topic_entries[topic]
            if table is None or len(table) < 2:
                continue
            bad = np.flatnonzero(np.diff(table["log_time"]) <= 0)
            if len(bad):
                k = int(bad[0]) + 1
                # Message indexes carry no CRC: blame the stamps only once the messages confirm them.
                self._c.read_entry(table[k - 1])
                self._c.read_entry(table[k])
                raise LogFormatError(
                    f"timestamps go backwards on {topic}: message {k} has log_time {int(table['log_time'][k])} ns, "
                    f"not after message {k - 1} at {int(table['log_time'][k - 1])} ns",
                    path=self.path,
                    fix="re-record the log with increasing stamps (lcv-replay record sorts them)",
                )

    def _build_frames(self, tolerance_ns: int | None) -> tuple[_Tables, int, int]:
        e = self._topic_entries
        left, right, odom = e[fmt.LEFT_IMAGE_TOPIC], e[fmt.RIGHT_IMAGE_TOPIC], e[fmt.ODOM_TOPIC]
        if not any(len(table) for table in self._c.entries.values()):
            if self._c.recovered_messages is not None:
                raise LogFormatError(
                    f"--recover salvaged nothing: {self._c.damage or 'the file holds no message'}",
                    path=self.path,
                    fix="the file is damaged before its first complete chunk; re-copy it from its source or re-record it",
                )
            raise LogFormatError(
                "the log is empty: it has no messages",
                path=self.path,
                fix="re-record it; the recorder produced no frames",
            )
        if left is None and odom is None:
            present = sorted({ch.topic for ch in self._c.channels.values()})
            what = (
                f"it has {fmt.RIGHT_IMAGE_TOPIC} but no {fmt.LEFT_IMAGE_TOPIC}"
                if right is not None
                else f"topics present: {', '.join(present) if present else 'none'}"
            )
            raise LogFormatError(
                f"missing required topics: a log needs {fmt.LEFT_IMAGE_TOPIC} or {fmt.ODOM_TOPIC} ({what})",
                path=self.path,
                fix="record the log with 'lcv-replay record'",
            )
        defining = left if left is not None and len(left) else odom
        if defining is None or len(defining) == 0:
            raise LogFormatError(
                f"the log is empty: no messages on {fmt.LEFT_IMAGE_TOPIC} or {fmt.ODOM_TOPIC}",
                path=self.path,
                fix="re-record it; the recorder produced no frames",
            )
        stamps = defining["log_time"]
        if tolerance_ns is None:
            period = float(np.median(np.diff(stamps))) if len(stamps) > 1 else math.inf
            tolerance_ns = int(min(MAX_DEFAULT_TOLERANCE_NS, period / 4))
        tolerance_ns = int(tolerance_ns)
        dropped = 0
        tables = _Tables(stamps_ns=stamps.astype(np.int64))
        if defining is left:
            tables.left = left
            if right is not None:
                li, ri = _match(left["log_time"], right["log_time"], tolerance_ns)
                dropped = (len(left) - len(li)) + (len(right) - len(ri))
                if len(li) == 0 or dropped > max(MAX_UNPAIRED_ABSOLUTE, MAX_UNPAIRED_FRACTION * max(len(left), len(right))):
                    raise LogFormatError(
                        f"stereo images cannot be paired: {len(left)} left and {len(right)} right images, "
                        f"only {len(li)} pairs within ±{tolerance_ns / 1e6:g} ms",
                        path=self.path,
                        fix="check the right camera's timestamps, or record the left camera only",
                    )
                if dropped:
                    log.warning(
                        "%s: dropped %d stereo images without a partner within ±%g ms (%d left, %d right images, %d pairs)",
                        self.path, dropped, tolerance_ns / 1e6, len(left), len(right), len(li),
                    )
                tables.left, tables.right = left[li], right[ri]
                tables.stamps_ns = tables.left["log_time"].astype(np.int64)
            if odom is not None and len(odom):
                tables.odom = _join(tables.stamps_ns, odom, tolerance_ns)
                if self._c.recovered_messages is not None:
                    self._trim_incomplete_tail(tables)
        else:
            tables.odom = odom
        gt = e[fmt.GROUND_TRUTH_TOPIC]
        if gt is not None and len(gt):
            tables.ground_truth = _join(tables.stamps_ns, gt, tolerance_ns)
        for name, topic in (("candidate", fmt.LOOP_CANDIDATES_TOPIC), ("true_loop", fmt.TRUE_LOOPS_TOPIC)):
            table = e[topic]
            if table is None or len(table) == 0:
                continue
            table = table[np.argsort(table["log_time"], kind="stable")]
            frames = np.full(len(table), -1, dtype=np.int64)
            ia, ib = _match(table["log_time"], tables.stamps_ns, tolerance_ns, one_to_one=False)
            frames[ia] = ib
            if np.any(frames < 0) and self._c.recovered_messages is not None:
                log.warning("%s: dropped %d %s messages of frames that were not recovered", self.path, int(np.sum(frames < 0)), topic)
                table, frames = table[frames >= 0], frames[frames >= 0]
            if np.any(frames < 0):
                k = int(np.flatnonzero(frames < 0)[0])
                raise LogFormatError(
                    f"a {topic} message at {int(table['log_time'][k])} ns is not at any frame's stamp",
                    path=self.path,
                    fix="loop candidates and labels must carry the query frame's stamp; re-record the log",
                )
            setattr(tables, name + "s", table)
            setattr(tables, name + "_frames", frames)
        return tables, dropped, tolerance_ns

    def _trim_incomplete_tail(self, tables: _Tables) -> None:
        """Recover mode: drop the last frames whose odometry was in the lost part of the file."""
        have = np.flatnonzero(tables.odom["chunk"] != _MISSING)
        keep = int(have[-1]) + 1 if len(have) else 0
        if keep == len(tables.stamps_ns):
            return
        log.warning("%s: dropped the last %d frames: their odometry was not recovered", self.path, len(tables.stamps_ns) - keep)
        if keep == 0:
            raise LogFormatError("no complete frame could be recovered", path=self.path, fix="the file is damaged beyond repair; re-record it")
        tables.stamps_ns = tables.stamps_ns[:keep]
        for name in ("left", "right", "odom"):
            table = getattr(tables, name)
            if table is not None:
                setattr(tables, name, table[:keep])

    def _build_info(self) -> LogInfo:
        c, t = self._c, self._tables
        topics = []
        for cid, channel in sorted(c.channels.items(), key=lambda item: item[1].topic):
            table = c.entries.get(cid, np.empty(0, ENTRY_DTYPE))
            span_s = (int(table["log_time"].max()) - int(table["log_time"].min())) / 1e9 if len(table) else 0.0
            rate = (len(table) - 1) / span_s if len(table) > 1 and span_s > 0 else 0.0
            schema = c.schemas.get(channel.schema_id)
            topics.append(TopicInfo(channel.topic, schema.name if schema else "", int(len(table)), rate))
        meta = dict(c.metadata.get(fmt.METADATA_NAME, {}))
        config: dict[str, Any] = {}
        for key, value in c.metadata.get(fmt.RECORDER_CONFIG_METADATA_NAME, {}).items():
            try:
                config[key] = json.loads(value)
            except (ValueError, RecursionError):
                config[key] = value
        try:
            information = messages.information_from_json(meta.get("odometry_information"))
        except (*_JSON_ERRORS, OverflowError):
            information = np.zeros(0)
        if information is not None and (information.shape != (3, 3) or fmt.information_problem(information.ravel())):
            raise LogFormatError(
                "the lcv metadata's odometry_information is not a 3x3 JSON matrix of plausible numbers",
                path=self.path,
                fix="re-record the log",
            )
        stamps = t.stamps_ns
        warnings = _warning_counts(meta.get(fmt.RECORDER_WARNINGS_KEY))
        if warnings is None:
            log.warning("%s: ignoring the unreadable lcv metadata %s", self.path, fmt.RECORDER_WARNINGS_KEY)
        try:
            nominal = float(meta["nominal_rate_hz"])
        except (KeyError, ValueError):
            nominal = 1e9 / float(np.median(np.diff(stamps))) if len(stamps) > 1 else 0.0
        image_format = None
        if t.left is not None:
            schema = self._schema_of(fmt.LEFT_IMAGE_TOPIC)
            image_format = meta.get("image_format") or ("raw" if schema == messages.RAW_IMAGE_SCHEMA else "compressed")
        e = self._topic_entries
        return LogInfo(
            path=self.path,
            file_size_bytes=c.file_size_bytes,
            frames=int(len(stamps)),
            start_ns=int(stamps[0]),
            end_ns=int(stamps[-1]),
            duration_s=(int(stamps[-1]) - int(stamps[0])) / 1e9,
            topics=tuple(topics),
            has_images=t.left is not None,
            has_right_images=t.right is not None,
            has_odometry=t.odom is not None,
            has_ground_truth=t.ground_truth is not None,
            has_candidates=len(t.candidates) > 0,
            has_labels=e[fmt.TRUE_LOOPS_TOPIC] is not None,
            metadata=meta,
            recorder_config=config,
            odometry_information=information,
            nominal_rate_hz=nominal,
            recovered_messages=c.recovered_messages,
            dropped_unpaired_images=self._dropped,
            stereo_tolerance_ns=self._tolerance_ns,
            message_count=int(sum(len(v) for v in c.entries.values())),
            chunk_count=len(c.chunks),
            skipped_chunks=c.skipped_chunks,
            candidate_count=int(len(t.candidates)),
            true_loop_count=int(len(t.true_loops)),
            image_format=image_format,
            library=c.library,
            recorder_warnings=warnings or {},
        )

    # -- decoding ----------------------------------------------------------------------------------
    def _schema_of(self, topic: str) -> str | None:
        for cid in self._c.topic_channels(topic):
            schema = self._c.schemas.get(self._c.channels[cid].schema_id)
            if schema is not None:
                return schema.name
        return None

    def _decode(self, row: np.void) -> tuple[Any, Any]:
        """Decode the message at a table row; returns ``(raw message, decoded object)``."""
        raw = self._c.read_entry(row)
        channel = self._c.channels.get(raw.channel_id)
        if channel is None:
            raise LogFormatError(f"a message refers to unknown channel {raw.channel_id}", path=self.path, fix="re-record the log")
        if channel.message_encoding == _JSON:
            return raw, raw.data
        cls = self._decoders.get(raw.channel_id)
        if cls is None:
            cls = messages.PROTOBUF_CLASSES[self._c.schemas[channel.schema_id].name]
            self._decoders[raw.channel_id] = cls
        message = cls()
        try:
            message.ParseFromString(raw.data)
        except Exception as exc:
            raise LogFormatError(
                f"a {cls.DESCRIPTOR.full_name} message on {channel.topic} at {raw.log_time_ns} ns cannot be decoded ({exc})",
                path=self.path,
                fix="the file is corrupted; re-record it",
            ) from None
        return raw, message

    def _first_message(self, topic: str) -> Any:
        table = self._topic_entries[topic]
        if table is None or len(table) == 0:
            return None
        return self._decode(table[int(np.argmin(table["log_time"]))])[1]

    def _image_at(self, table: np.ndarray | None, i: int) -> ImageRef | None:
        if table is None:
            return None
        raw, message = self._decode(table[i])
        encoding = message.encoding if isinstance(message, messages.RawImage) else (message.format or "compressed")
        path, topic = self.path, self._c.channels[raw.channel_id].topic

        def decode(message=message, stamp=raw.log_time_ns) -> np.ndarray:
            try:
                return images.decode_image_message(message)
            except ValueError as exc:
                raise LogFormatError(f"the image on {topic} at {stamp} ns is damaged: {exc}", path=path, fix="re-record the log") from None

        return ImageRef(stamp_ns=raw.log_time_ns, encoding=encoding, decoder=decode)

    def _pose_at(self, table: np.ndarray | None, i: int, topic: str, *, allow_missing: bool = False) -> Pose2D | None:
        if table is None or table[i]["chunk"] == _MISSING:
            return None
        pose = messages.pose_from_pose_in_frame(self._decode(table[i])[1])
        problem = fmt.pose_problem(*pose)
        if problem is not None:
            if allow_missing and problem == "not finite":
                return None
            raise self._bad_pose(topic, i, pose, problem)
        return pose

    def _poses(self, table: np.ndarray, topic: str, *, allow_missing: bool) -> np.ndarray:
        out = np.full((len(table), 3), np.nan)
        for i in range(len(table)):
            if table[i]["chunk"] == _MISSING:
                if allow_missing:
                    continue
                raise LogFormatError(
                    f"frame {i} (stamp {int(self._tables.stamps_ns[i])} ns) has no {topic} message within "
                    f"±{self._tolerance_ns / 1e6:g} ms",
                    path=self.path,
                    fix="record odometry for every frame",
                )
            pose = messages.pose_from_pose_in_frame(self._decode(table[i])[1])
            problem = fmt.pose_problem(*pose)
            if problem is not None and not (allow_missing and problem == "not finite"):
                raise self._bad_pose(topic, i, pose, problem)
            out[i] = pose
        return out

    def _bad_pose(self, topic: str, i: int, pose: Pose2D, problem: str) -> LogFormatError:
        return LogFormatError(
            f"{topic} of frame {i} (stamp {int(self._tables.stamps_ns[i])} ns) is {problem}: "
            f"x={pose.x_m}, y={pose.y_m}, yaw={pose.yaw_rad}",
            path=self.path,
            fix="fix the odometry source and re-record the log",
        )

    def _decode_candidate(self, row: np.void) -> LoopCandidate:
        raw, data = self._decode(row)
        try:
            candidate = messages.candidate_from_json(data)
        except _JSON_ERRORS as exc:
            raise self._bad_json(fmt.LOOP_CANDIDATES_TOPIC, raw.log_time_ns, exc) from None
        self._check_pair(candidate.pair, fmt.LOOP_CANDIDATES_TOPIC)
        problem = None
        if candidate.T_match_query is not None and fmt.pose_problem(*candidate.T_match_query):
            problem = f"T_match_query {tuple(candidate.T_match_query)} is {fmt.pose_problem(*candidate.T_match_query)}"
        elif candidate.information is not None and fmt.information_problem(candidate.information):
            problem = f"information {candidate.information} is {fmt.information_problem(candidate.information)}"
        if problem is not None:
            raise LogFormatError(
                f"{fmt.LOOP_CANDIDATES_TOPIC} candidate {candidate.pair} at {raw.log_time_ns} ns: {problem}",
                path=self.path,
                fix="fix the place recognizer's output and re-record the log",
            )
        return candidate

    def _decode_true_loop(self, row: np.void) -> tuple[int, int]:
        raw, data = self._decode(row)
        try:
            pair = messages.true_loop_from_json(data)
        except _JSON_ERRORS as exc:
            raise self._bad_json(fmt.TRUE_LOOPS_TOPIC, raw.log_time_ns, exc) from None
        self._check_pair(pair, fmt.TRUE_LOOPS_TOPIC)
        return pair

    def _bad_json(self, topic: str, stamp_ns: int, exc: Exception) -> LogFormatError:
        return LogFormatError(
            f"a message on {topic} at {stamp_ns} ns is not valid JSON of its schema ({exc})", path=self.path, fix="re-record the log"
        )

    def _check_pair(self, pair: tuple[int, int], topic: str) -> None:
        query, match = pair
        n = len(self._tables.stamps_ns)
        if not (0 <= match < query < n):
            raise LogFormatError(
                f"{topic} pair (query {query}, match {match}) is invalid for a log of {n} frames "
                "(need 0 <= match_frame < query_frame < frames)",
                path=self.path,
                fix="re-record the log",
            )

    def _at_frame(self, i: int, rows, decode) -> list:
        """Decode the candidate/label rows stamped at frame ``i``; each must have ``query_frame == i``."""
        items = []
        for row in rows:
            item = decode(row)
            query, match = item.pair if isinstance(item, LoopCandidate) else item
            if query != i:
                raise LogFormatError(
                    f"pair (query {query}, match {match}) is stamped at frame {i} ({int(row['log_time'])} ns), "
                    f"not at its query frame {query}",
                    path=self.path,
                    fix="loop candidates and labels must carry the query frame's stamp; re-record the log",
                )
            items.append(item)
        return items


def _match(
    a_ns: np.ndarray, b_ns: np.ndarray, tolerance_ns: int, *, one_to_one: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest matching of sorted stamps ``a_ns`` to increasing stamps ``b_ns`` within ``tolerance_ns``.

    Returns index arrays ``(ia, ib)`` of the matched pairs. With ``one_to_one`` each ``b`` keeps
    only the first ``a`` that claims it.
    """
    if len(a_ns) == 0 or len(b_ns) == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    pos = np.searchsorted(b_ns, a_ns)
    before = np.clip(pos - 1, 0, len(b_ns) - 1)
    after = np.clip(pos, 0, len(b_ns) - 1)
    d_before = np.abs(a_ns - b_ns[before])
    d_after = np.abs(b_ns[after] - a_ns)
    nearest = np.where(d_after < d_before, after, before)
    distance = np.minimum(d_before, d_after)
    ok = distance <= tolerance_ns
    ia = np.flatnonzero(ok)
    ib = nearest[ok]
    if not one_to_one:
        return ia.astype(np.int64), ib.astype(np.int64)
    keep = np.ones(len(ib), dtype=bool)
    keep[1:] = ib[1:] != ib[:-1]
    return ia[keep].astype(np.int64), ib[keep].astype(np.int64)


def _warning_counts(text: str | None) -> dict[str, int] | None:
    """The ``recorder_warnings`` metadata value as counts; ``{}`` when absent, ``None`` when unreadable."""
    if not text:
        return {}
    try:
        value = json.loads(text)
    except (ValueError, RecursionError):
        return None
    if not isinstance(value, dict) or not all(isinstance(n, int) and not isinstance(n, bool) for n in value.values()):
        return None
    return {str(k): int(n) for k, n in value.items()}


def _rows_by_frame(table: np.ndarray, frames: np.ndarray, first: int, last: int) -> dict[int, list]:
    """Rows of ``table`` whose frame (``frames``) lies in ``[first, last)``, grouped by frame."""
    groups: dict[int, list] = {}
    for k in np.flatnonzero((frames >= first) & (frames < last)):
        groups.setdefault(int(frames[k]), []).append(table[k])
    return groups


def _join(stamps_ns: np.ndarray, table: np.ndarray, tolerance_ns: int) -> np.ndarray:
    """Rows of ``table`` matched to each stamp (``chunk == _MISSING`` where none is within tolerance)."""
    out = np.zeros(len(stamps_ns), dtype=ENTRY_DTYPE)
    out["chunk"] = _MISSING
    ia, ib = _match(stamps_ns, table["log_time"], tolerance_ns)
    out[ia] = table[ib]
    return out
