"""The one log writer: frames, odometry, ground truth and loop candidates into an lcv-replay MCAP.

Every recorder hands its records to :class:`LogWriter`, which owns the schemas, the compression and
the temp-then-rename step (:func:`lcv_replay.fileio.atomic_output`): an interrupted or failed
recording leaves no output file, and an existing file is refused unless ``force``.

**Live mode** (``live=True``, ``record ... --live``) writes the final path itself, one MCAP chunk per
frame, flushed to the operating system after every frame, so that ``lcv-replay LOG.mcap --follow``
can read each frame as it lands. It gives up the atomic rename: while the recording runs, the file
is visible and incomplete (no summary until it ends), and ``--force`` truncates the old file at the
start, not at the end. An interrupted or failed live recording is finished with the frames written
so far (a valid, shorter log), or removed if no frame was written. The ``lcv`` metadata says
``chunking = frame`` (every chunk ends at a frame boundary), which lets a follower use each chunk
as soon as it is complete.

Frame index <-> time (docs/log-format.md): frame ``i`` is the ``i``-th call of :meth:`write_frame`;
all of its messages get ``log_time = publish_time = stamp_ns`` and MCAP ``sequence = i``.
"""

from __future__ import annotations

import contextlib
import json
import math
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Literal

import numpy as np
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_protobuf.schema import register_schema

from lcv_replay import __version__
from lcv_replay.errors import RecorderError
from lcv_replay.fileio import atomic_output, is_write_failure, write_error
from lcv_replay.log import format as fmt
from lcv_replay.log import images, messages
from lcv_replay.records import LoopCandidate, Pose2D, StereoCalibration

_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}

# The `lcv` metadata keys the writer owns; extra_metadata may not override them.
RESERVED_METADATA_KEYS = (
    "dataset",
    "nominal_rate_hz",
    "recorder",
    "recorder_version",
    "format_version",
    "units",
    "frame_conventions",
    "frame_index",
    "odometry_information",
    "image_format",
    "compression",
    fmt.RECORDER_WARNINGS_KEY,
    "chunking",
)


class LogWriter:
    """Write an lcv-replay MCAP log atomically (a context manager).

    Args:
        path: output ``.mcap`` path; written as a temp file in the same folder, renamed on success.
        force: overwrite an existing ``path``.
        dataset: dataset name, e.g. ``"kitti/06"``.
        recorder: recorder name, e.g. ``"kitti"``.
        nominal_rate_hz: nominal frame rate.
        recorder_config: the recorder's full configuration; each value is stored JSON-encoded in the
            ``lcv.recorder_config`` metadata record.
        image_format: ``"png"`` (lossless, default), ``"jpeg"`` (``jpeg_quality``) or ``"raw"``.
        compression: MCAP chunk compression.
        odometry_information: ``(3, 3)`` information matrix of one odometry step (x, y, yaw), if known.
        extra_metadata: more string entries for the ``lcv`` record (not the reserved keys).
        recorder_warnings: counts of what the recorder accepted with a warning (e.g.
            ``{"duplicate_edges": 3}``), stored as JSON under ``lcv.recorder_warnings``.
        chunk_size_bytes: target MCAP chunk size; smaller chunks make time-window reads finer.
        encode_threads: image-encoding worker threads; up to ``4 * encode_threads`` frames may be
            queued (encoding) before :meth:`write_frame` blocks. An encoding failure is raised by a
            later call (``write_*`` or :meth:`close`).
        live: write ``path`` directly, one flushed chunk per frame (see the module docstring).

    Raises:
        OutputError: ``path`` exists (without ``force``) or its folder is missing/unwritable.
        RecorderError: invalid arguments or records (the message names the frame).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        force: bool = False,
        dataset: str,
        recorder: str,
        nominal_rate_hz: float,
        recorder_config: dict,
        image_format: Literal["png", "jpeg", "raw"] = "png",
        jpeg_quality: int = 95,
        compression: Literal["zstd", "lz4", "none"] = "zstd",
        odometry_information: np.ndarray | None = None,
        extra_metadata: dict[str, str] | None = None,
        recorder_warnings: dict[str, int] | None = None,
        chunk_size_bytes: int = 1 << 20,
        encode_threads: int = 2,
        live: bool = False,
    ):
        self.path = Path(path)
        if image_format not in images.IMAGE_FORMATS:
            raise RecorderError(f"unknown image format {image_format!r}", fix="use png, jpeg or raw")
        if compression not in _COMPRESSION:
            raise RecorderError(f"unknown compression {compression!r}", fix="use zstd, lz4 or none")
        if not 1 <= int(jpeg_quality) <= 100:
            raise RecorderError(f"jpeg_quality {jpeg_quality} is out of range", fix="use 1..100")
        if not (math.isfinite(nominal_rate_hz) and nominal_rate_hz > 0):
            raise RecorderError(f"nominal_rate_hz {nominal_rate_hz} must be a positive number")
        if odometry_information is not None:
            odometry_information = np.asarray(odometry_information, dtype=np.float64)
            if odometry_information.shape != (3, 3) or fmt.information_problem(odometry_information.ravel()):
                raise RecorderError(
                    f"odometry_information must be a finite (3, 3) matrix, got shape {odometry_information.shape}"
                )
        extra = dict(extra_metadata or {})
        clash = sorted(set(extra) & set(RESERVED_METADATA_KEYS))
        if clash:
            raise RecorderError(f"extra_metadata may not set the reserved keys {clash}")
        if recorder_warnings:
            extra[fmt.RECORDER_WARNINGS_KEY] = json.dumps({str(k): int(v) for k, v in sorted(recorder_warnings.items())})
        try:
            config_record = {str(k): json.dumps(v, sort_keys=True) for k, v in recorder_config.items()}
        except (TypeError, ValueError) as exc:
            raise RecorderError(f"recorder_config is not JSON-serialisable: {exc}") from None

        self.image_format = image_format
        self.jpeg_quality = int(jpeg_quality)
        self.compression = compression
        self._frames_written = 0
        self._last_stamp_ns: int | None = None
        self._frame_stamps_ns: list[int] = []
        self._layout: tuple[bool, bool, bool] | None = None  # (left, right, odom) present
        self._image_shape: tuple[int, ...] | None = None
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._closed = False
        # Image encoding runs on worker threads (OpenCV releases the GIL): write_frame returns once
        # the frame is queued, and frames are written to the MCAP in order as their images finish.
        self._encode_threads = max(1, int(encode_threads))
        self._pool: ThreadPoolExecutor | None = None
        self._pending: deque[_PendingFrame] = deque()

        self.live = bool(live)
        if self.live:  # the final path, written as it goes; only explicit flushes end a chunk
            self._atomic = _LiveOutput(self.path, force=force)
            chunk_size_bytes = 1 << 62
        else:
            self._atomic = atomic_output(self.path, force=force)
        tmp = self._atomic.__enter__()
        try:
            self._stream: BinaryIO = open(tmp, "wb")
            self._mcap = McapWriter(
                self._stream,
                chunk_size=int(chunk_size_bytes),
                compression=_COMPRESSION[compression],
                enable_crcs=True,
                enable_data_crcs=True,  # lets `info --check` verify metadata and message indexes too
            )
            self._mcap.start(profile="", library=f"lcv-replay/{__version__}")
            self._mcap.add_metadata(
                fmt.METADATA_NAME,
                {
                    "dataset": str(dataset),
                    "nominal_rate_hz": repr(float(nominal_rate_hz)),
                    "recorder": str(recorder),
                    "recorder_version": __version__,
                    "format_version": fmt.FORMAT_VERSION,
                    "units": "m, rad, ns",
                    "frame_conventions": fmt.FRAME_CONVENTIONS,
                    "frame_index": fmt.FRAME_INDEX_CONVENTION,
                    "odometry_information": messages.information_to_json(odometry_information),
                    "image_format": image_format,
                    "compression": compression,
                    **({"chunking": "frame"} if self.live else {}),
                    **{str(k): str(v) for k, v in extra.items()},
                },
            )
            self._mcap.add_metadata(fmt.RECORDER_CONFIG_METADATA_NAME, config_record)
            if self.live:
                self._stream.flush()
        except OSError as exc:
            error = write_error(self.path, exc) if is_write_failure(exc) else None
            self._abort(*_exc_info())
            if error is None:
                raise
            raise error from None
        except BaseException:
            self._abort(*_exc_info())
            raise

    # -- context manager -------------------------------------------------------------------------
    def __enter__(self) -> "LogWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            self.close()
        elif is_write_failure(exc):  # a full disk while writing a frame: one error naming the path
            error = write_error(self.path, exc)
            self._abort(exc_type, exc, tb)
            raise error from None
        else:
            self._abort(exc_type, exc, tb)
        return False

    @property
    def frames_written(self) -> int:
        """Number of frames written so far (the next frame's index)."""
        return self._frames_written

    def close(self) -> None:
        """Finish the MCAP (summary, indexes) and rename the temp file onto ``path``.

        Raises :class:`RecorderError` (and leaves no file) when no frame was written, and
        :class:`~lcv_replay.errors.OutputError` (naming the path and the free space) when the disk
        is full or the folder unwritable.
        """
        if self._closed:
            return
        if self._frames_written == 0:
            error = RecorderError(
                "no frames were written; refusing to create an empty log",
                path=self.path,
                fix="check that the source has images or odometry",
            )
            self._abort(type(error), error, None)
            raise error
        try:
            self._drain()
            self._mcap.finish()
            self._stream.close()
        except OSError as exc:
            error = write_error(self.path, exc) if is_write_failure(exc) else None  # before the clean-up
            self._abort(*_exc_info())
            if error is None:
                raise
            raise error from None
        except BaseException:
            self._abort(*_exc_info())
            raise
        self._closed = True
        self._shutdown_pool()
        self._atomic.__exit__(None, None, None)

    def abort(self) -> None:
        """Discard the recording: close and delete the temp file; ``path`` is left untouched.

        In live mode the frames written so far are kept as a finished log (see the module docstring).
        """
        self._abort(RuntimeError, RuntimeError("aborted"), None)

    def flush(self) -> None:
        """Live mode: end the current frame's chunk and flush it to the file, for a follower to read.

        Call it after a frame's candidates and labels (a chunk must hold whole frames). A no-op
        without ``live``: the temp file is not visible anyway.
        """
        self._check_open()
        if self.live:
            self._drain()
            self._mcap.flush()

    def _abort(self, exc_type, exc, tb) -> None:
        if self._closed:
            return
        self._closed = True
        self._pending.clear()
        self._shutdown_pool()
        if self.live and self._frames_written:  # the file is public: leave a valid log of what was written
            with contextlib.suppress(Exception):
                self._mcap.finish()
                self._atomic.keep = True
        with contextlib.suppress(Exception):
            self._stream.close()
        with contextlib.suppress(BaseException):
            self._atomic.__exit__(exc_type, exc, tb)

    # -- records ---------------------------------------------------------------------------------
    def write_calibration(self, calib: StereoCalibration, stamp_ns: int) -> None:
        """Write the left and right ``foxglove.CameraCalibration`` (right ``P[0, 3] = -fx * baseline_m``)."""
        self._check_open()
        if not (calib.width_px > 0 and calib.height_px > 0 and calib.fx_px > 0 and calib.fy_px > 0):
            raise RecorderError(f"invalid calibration {calib}", path=self.path)
        if not (math.isfinite(calib.baseline_m) and calib.baseline_m >= 0):
            raise RecorderError(f"calibration baseline_m {calib.baseline_m} must be >= 0", path=self.path)
        self._drain()
        left, right = messages.calibration_messages(calib, int(stamp_ns))
        self._write_proto(fmt.LEFT_CALIBRATION_TOPIC, left, int(stamp_ns), 0)
        self._write_proto(fmt.RIGHT_CALIBRATION_TOPIC, right, int(stamp_ns), 0)

    def write_frame(
        self,
        index: int,
        stamp_ns: int,
        *,
        left: np.ndarray | None = None,
        right: np.ndarray | None = None,
        odom: Pose2D | None = None,
        ground_truth: Pose2D | None = None,
    ) -> None:
        """Write frame ``index`` (must be :attr:`frames_written`) at ``stamp_ns`` (strictly increasing).

        Args:
            left, right: ``(H, W)`` uint8 grey or ``(H, W, 3)`` uint8 RGB images of the same shape.
            odom: cumulative planar odometry ``T_odom_base`` (also written to ``/tf``).
            ground_truth: planar ground truth ``T_world_base``.

        Every frame must have the same layout as frame 0 (left / right / odometry present or not);
        ground truth may be missing on some frames. A frame needs a left image or odometry.
        """
        self._check_open()
        index, stamp_ns = int(index), int(stamp_ns)
        if self.live and self._frames_written:
            self.flush()  # the previous frame's chunk ends here, if the caller did not flush it
        if index != self._frames_written:
            raise RecorderError(
                f"frame index {index} is out of order, expected {self._frames_written}", path=self.path
            )
        if self._last_stamp_ns is not None and stamp_ns <= self._last_stamp_ns:
            raise RecorderError(
                f"frame {index}: stamp {stamp_ns} ns is not after the previous frame's {self._last_stamp_ns} ns",
                path=self.path,
                fix="frame stamps must strictly increase",
            )
        if stamp_ns < 0:
            raise RecorderError(f"frame {index}: negative stamp {stamp_ns} ns", path=self.path)
        layout = (left is not None, right is not None, odom is not None)
        if not (layout[0] or layout[2]):
            raise RecorderError(f"frame {index} has neither a left image nor odometry", path=self.path)
        if layout[1] and not layout[0]:
            raise RecorderError(f"frame {index} has a right image but no left image", path=self.path)
        if self._layout is None:
            self._layout = layout
        elif layout != self._layout:
            names = ("left image", "right image", "odometry")
            diff = [n for n, a, b in zip(names, layout, self._layout) if a != b]
            raise RecorderError(
                f"frame {index} differs from frame 0 in {', '.join(diff)}",
                path=self.path,
                fix="every frame must carry the same kinds of data (ground truth excepted)",
            )
        for name, pose in (("odometry", odom), ("ground truth", ground_truth)):
            problem = None if pose is None else fmt.pose_problem(*(float(v) for v in pose))
            if problem is not None:
                raise RecorderError(f"frame {index}: {name} {tuple(pose)} is {problem}", path=self.path)

        checked = {}
        try:
            for side, image in (("left", left), ("right", right)):
                if image is not None:
                    array = images.check_image(image, f"frame {index} {side} image")
                    if self._image_shape is None:
                        self._image_shape = array.shape
                    elif array.shape != self._image_shape:
                        raise ValueError(
                            f"frame {index} {side} image has shape {array.shape}, earlier images {self._image_shape}"
                        )
                    checked[side] = array
        except ValueError as exc:
            raise RecorderError(str(exc), path=self.path) from None

        if checked and self._pool is None:
            self._pool = ThreadPoolExecutor(self._encode_threads, thread_name_prefix="lcv-encode")
        pending = _PendingFrame(
            index=index,
            stamp_ns=stamp_ns,
            images={
                side: self._pool.submit(self._image_message, array.copy(), side, stamp_ns)  # type: ignore[union-attr]
                for side, array in checked.items()
            },
            odom=None if odom is None else Pose2D(float(odom[0]), float(odom[1]), float(odom[2])),
            ground_truth=None if ground_truth is None else Pose2D(*(float(v) for v in ground_truth)),
        )
        self._pending.append(pending)
        self._frames_written += 1
        self._last_stamp_ns = stamp_ns
        self._frame_stamps_ns.append(stamp_ns)
        self._flush_done(max_pending=0 if self.live else 4 * self._encode_threads)

    def write_loop_candidate(self, candidate: LoopCandidate, stamp_ns: int) -> None:
        """Write a candidate on ``/loop_candidates``; ``stamp_ns`` is the query frame's stamp.

        The query frame must already be written (``query_frame < frames_written``).
        """
        self._check_open()
        self._check_pair(candidate.query_frame, candidate.match_frame, int(stamp_ns), "loop candidate")
        self._drain()
        if not math.isfinite(float(candidate.similarity)):
            raise RecorderError(f"loop candidate {candidate.pair} has similarity {candidate.similarity}", path=self.path)
        if candidate.information is not None and (
            len(candidate.information) != 6 or fmt.information_problem(candidate.information)
        ):
            raise RecorderError(
                f"loop candidate {candidate.pair}: information must be 6 numbers within ±{fmt.MAX_INFORMATION:g}", path=self.path
            )
        if candidate.T_match_query is not None and fmt.pose_problem(*(float(v) for v in candidate.T_match_query)):
            raise RecorderError(
                f"loop candidate {candidate.pair}: T_match_query is {fmt.pose_problem(*(float(v) for v in candidate.T_match_query))}",
                path=self.path,
            )
        self._write_json(
            fmt.LOOP_CANDIDATES_TOPIC,
            messages.LOOP_CANDIDATE_SCHEMA,
            messages.LOOP_CANDIDATE_JSON_SCHEMA,
            messages.candidate_to_json(candidate),
            int(stamp_ns),
            int(candidate.query_frame),
        )

    def write_true_loop(self, query_frame: int, match_frame: int, stamp_ns: int) -> None:
        """Write a labelled true pair on ``/ground_truth/loops``; ``stamp_ns`` is the query frame's stamp."""
        self._check_open()
        self._check_pair(int(query_frame), int(match_frame), int(stamp_ns), "true loop")
        self._drain()
        self._write_json(
            fmt.TRUE_LOOPS_TOPIC,
            messages.TRUE_LOOP_SCHEMA,
            messages.TRUE_LOOP_JSON_SCHEMA,
            messages.true_loop_to_json(query_frame, match_frame),
            int(stamp_ns),
            int(query_frame),
        )

    def declare_labels(self) -> None:
        """Declare that this dataset has loop-closure labels, even if no true loop gets written.

        Registers the ``/ground_truth/loops`` channel, so readers report ``has_labels`` (an empty
        label set then means "every candidate is false", not "unknown").
        """
        self._check_open()
        self._json_channel(fmt.TRUE_LOOPS_TOPIC, messages.TRUE_LOOP_SCHEMA, messages.TRUE_LOOP_JSON_SCHEMA)

    def declare_candidates(self) -> None:
        """Register ``/loop_candidates`` before its first message (a follower then knows the log has candidates)."""
        self._check_open()
        self._json_channel(fmt.LOOP_CANDIDATES_TOPIC, messages.LOOP_CANDIDATE_SCHEMA, messages.LOOP_CANDIDATE_JSON_SCHEMA)

    def declare_ground_truth(self) -> None:
        """Register ``/ground_truth/pose`` before its first message (a follower then knows the log has ground truth)."""
        self._check_open()
        self._channel(fmt.GROUND_TRUTH_TOPIC, self._proto_schema(messages.PoseInFrame), MessageEncoding.Protobuf)

    # -- internals -------------------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise RecorderError("the log writer is closed", path=self.path)

    def _check_pair(self, query_frame: int, match_frame: int, stamp_ns: int, what: str) -> None:
        if not 0 <= match_frame < query_frame:
            raise RecorderError(
                f"{what} ({query_frame}, {match_frame}) must have 0 <= match_frame < query_frame", path=self.path
            )
        if query_frame >= self._frames_written:
            raise RecorderError(
                f"{what} ({query_frame}, {match_frame}) refers to frame {query_frame}, "
                f"but only {self._frames_written} frames are written",
                path=self.path,
                fix="write the query frame before its loop candidates",
            )
        if stamp_ns != self._frame_stamps_ns[query_frame]:
            raise RecorderError(
                f"{what} ({query_frame}, {match_frame}) has stamp {stamp_ns} ns, "
                f"but frame {query_frame} has {self._frame_stamps_ns[query_frame]} ns",
                path=self.path,
                fix="pass the query frame's stamp_ns",
            )

    def _flush_done(self, max_pending: int) -> None:
        """Write queued frames, in order, whose images are encoded; block while more than ``max_pending`` wait."""
        while self._pending and (len(self._pending) > max_pending or all(f.done() for f in self._pending[0].images.values())):
            frame = self._pending.popleft()
            self._write_pending(frame)

    def _drain(self) -> None:
        self._flush_done(max_pending=0)

    def _write_pending(self, frame: "_PendingFrame") -> None:
        index, stamp_ns = frame.index, frame.stamp_ns
        for side, topic in (("left", fmt.LEFT_IMAGE_TOPIC), ("right", fmt.RIGHT_IMAGE_TOPIC)):
            future = frame.images.get(side)
            if future is None:
                continue
            try:
                message = future.result()
            except ValueError as exc:
                raise RecorderError(f"frame {index} {side} image: {exc}", path=self.path) from None
            self._write_proto(topic, message, stamp_ns, index)
        if frame.odom is not None:
            self._write_proto(fmt.ODOM_TOPIC, messages.pose_in_frame(frame.odom, stamp_ns, fmt.ODOM_FRAME_ID), stamp_ns, index)
            self._write_proto(
                fmt.TF_TOPIC,
                messages.frame_transform(frame.odom, stamp_ns, fmt.ODOM_FRAME_ID, fmt.BASE_FRAME_ID),
                stamp_ns,
                index,
            )
        if frame.ground_truth is not None:
            self._write_proto(
                fmt.GROUND_TRUTH_TOPIC, messages.pose_in_frame(frame.ground_truth, stamp_ns, fmt.WORLD_FRAME_ID), stamp_ns, index
            )

    def _shutdown_pool(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def _image_message(self, image: np.ndarray, side: str, stamp_ns: int) -> Any:
        frame_id = "camera_left" if side == "left" else "camera_right"
        if self.image_format == "raw":
            message = messages.RawImage(frame_id=frame_id, **images.raw_image_fields(image))
        else:
            data = images.encode_compressed(image, self.image_format, jpeg_quality=self.jpeg_quality)
            message = messages.CompressedImage(frame_id=frame_id, data=data, format=self.image_format)
        message.timestamp.seconds = stamp_ns // 1_000_000_000
        message.timestamp.nanos = stamp_ns % 1_000_000_000
        return message

    def _channel(self, topic: str, schema_id: int, encoding: str) -> int:
        channel_id = self._channels.get(topic)
        if channel_id is None:
            channel_id = self._mcap.register_channel(topic=topic, message_encoding=encoding, schema_id=schema_id)
            self._channels[topic] = channel_id
        return channel_id

    def _proto_schema(self, message_class: Any) -> int:
        name = message_class.DESCRIPTOR.full_name
        schema_id = self._schemas.get(name)
        if schema_id is None:
            schema_id = register_schema(self._mcap, message_class)
            self._schemas[name] = schema_id
        return schema_id

    def _write_proto(self, topic: str, message: Any, stamp_ns: int, sequence: int) -> None:
        channel_id = self._channel(topic, self._proto_schema(type(message)), MessageEncoding.Protobuf)
        self._mcap.add_message(
            channel_id=channel_id,
            log_time=stamp_ns,
            publish_time=stamp_ns,
            sequence=sequence,
            data=message.SerializeToString(),
        )

    def _json_channel(self, topic: str, schema_name: str, schema: dict) -> int:
        schema_id = self._schemas.get(schema_name)
        if schema_id is None:
            schema_id = self._mcap.register_schema(
                name=schema_name, encoding=SchemaEncoding.JSONSchema, data=json.dumps(schema).encode()
            )
            self._schemas[schema_name] = schema_id
        return self._channel(topic, schema_id, MessageEncoding.JSON)

    def _write_json(self, topic: str, schema_name: str, schema: dict, data: bytes, stamp_ns: int, sequence: int) -> None:
        channel_id = self._json_channel(topic, schema_name, schema)
        self._mcap.add_message(
            channel_id=channel_id, log_time=stamp_ns, publish_time=stamp_ns, sequence=sequence, data=data
        )


class _LiveOutput:
    """The output of a live recording: the final path itself (no temp file, no rename).

    Checks the path like :func:`lcv_replay.fileio.atomic_output`; on failure the file is removed
    unless :attr:`keep` was set (the writer finished it with the frames written so far).
    """

    def __init__(self, path: Path, *, force: bool):
        from lcv_replay.fileio import check_output_path

        self.path = check_output_path(path, force=force)
        self.keep = False

    def __enter__(self) -> Path:
        return self.path

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None and not self.keep:
            with contextlib.suppress(FileNotFoundError):
                self.path.unlink()


@dataclass
class _PendingFrame:
    """A frame queued while its images are being encoded."""

    index: int
    stamp_ns: int
    images: dict[str, Future]
    odom: Pose2D | None
    ground_truth: Pose2D | None


def _exc_info():
    import sys

    return sys.exc_info()


class MessageCopier:
    """Copies messages read from one MCAP (``mcap.reader`` triples) into an ``mcap.writer.Writer``,
    registering each schema and channel once (``lcv-replay vo``, the fuzz benchmark's plain copies)."""

    def __init__(self, writer: McapWriter):
        self.writer = writer
        self._schemas: dict[int, int] = {}
        self._channels: dict[int, int] = {}

    def add(self, schema: Any, channel: Any, message: Any) -> None:
        """Write ``message`` of ``channel`` (with ``schema``, or ``None``) as it was."""
        channel_id = self._channels.get(channel.id)
        if channel_id is None:
            schema_id = 0
            if schema is not None:
                if schema.id not in self._schemas:
                    self._schemas[schema.id] = self.writer.register_schema(schema.name, schema.encoding, schema.data)
                schema_id = self._schemas[schema.id]
            channel_id = self.writer.register_channel(channel.topic, channel.message_encoding, schema_id, dict(channel.metadata))
            self._channels[channel.id] = channel_id
        self.writer.add_message(channel_id, message.log_time, message.data, message.publish_time, message.sequence)
