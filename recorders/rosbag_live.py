"""Following a ROS 2 MCAP that ``ros2 bag record -s mcap`` is still writing: conversion chunk by chunk.

``lcv-replay BAG.mcap --follow`` cannot convert the whole bag first. :class:`LiveConversion` runs in
a thread beside the replay:

1. it reads each complete chunk of the growing bag with the follower's
   :class:`~lcv_replay.log.follow.ChunkTail` (no summary needed; the same index as for our logs);
2. it deserialises the messages of the chosen topics with a ``rosbags`` typestore built from the
   message definitions stored in the bag's schemas (``ros2msg`` or ``ros2idl``) and feeds them to
   the importer's first pass (:class:`recorders.rosbag.BagScan`);
3. after each growth it plans the frames exactly as ``record rosbag`` does
   (:func:`recorders.rosbag.scan_plan`) and writes the frames whose data is final to a live
   lcv-replay log (:class:`~lcv_replay.log.writer.LogWriter`, ``live=True``), which the replay follows
   like any other.

A frame is final when no later message can change it: the odometry topic (or every ``/tf`` edge of
the odometry chain) has a message at or after its stamp, both image streams have passed it by the
stereo tolerance, and a ground-truth topic has a message at or after it or none within
``max_gap_ns`` before it. With messages in time order (as a recorder writes them) the frames
equal those of the finished bag's conversion, so the replay's results equal an offline replay.

Ends: the bag is finalised (the remaining frames are written, the log is closed); no growth for
``idle_timeout_s`` (the frames so far, as ``--recover``); ``stop()`` (Ctrl-C). What is left out:
the topics are chosen from the channels present when the first messages arrive (a topic that
appears later cannot be chosen); ground truth that starts after the frames is missing on the frames
before it; a ``.db3`` bag being recorded cannot be followed (rosbags reads sqlite3 bags only as a
whole); TF odometry is not suggested automatically (name ``--odom-from-tf``).
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from lcv_replay.errors import LcvError, RecorderError
from lcv_replay.records import Pose2D
from recorders.bags import check_topic_type, pick_topics
from recorders.rosbag import (
    BagScan,
    RosbagOptions,
    image_to_array,
    log_header,
    scan_plan,
    topic_roles,
)

log = logging.getLogger(__name__)


def typestore_from_schemas(schemas: dict[int, Any]) -> Any:
    """A ``rosbags`` typestore with the message definitions of a ROS 2 MCAP's schemas."""
    from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

    types: dict = {}
    for schema in schemas.values():
        text = schema.data.decode() if isinstance(schema.data, (bytes, bytearray)) else str(schema.data)
        if schema.encoding == "ros2msg":
            types.update(get_types_from_msg(text, schema.name))
        elif schema.encoding == "ros2idl":
            separator = "=" * 80 + "\n"
            parts = text.split(separator)[1:] if text.startswith(f"{separator}IDL: ") else [text]
            for part in parts:
                types.update(get_types_from_idl(part.split("\n", 1)[1] if part.startswith("IDL: ") else part))
    store = get_typestore(Stores.EMPTY)
    store.register(types)
    return store


class LiveConversion(threading.Thread):
    """Convert a growing ROS 2 MCAP into a live lcv-replay log (see the module docstring).

    Attributes:
        ready: set once the output exists with its first frame, or on an error.
        error: the exception that ended the conversion, if any.
        frames: frames written so far.
    """

    def __init__(self, source: Path, out: Path, options: RosbagOptions, *, idle_timeout_s: float, poll_s: float = 0.05,
                 stop: Callable[[], bool] = lambda: False):
        super().__init__(daemon=True, name="lcv-live-conversion")
        self.source, self.out, self.options = Path(source), Path(out), options
        self.idle_timeout_s, self.poll_s, self.stop = idle_timeout_s, poll_s, stop
        self.ready = threading.Event()
        self.error: BaseException | None = None
        self.frames = 0
        self.end_reason: str | None = None
        self._calibrated = False

    def run(self) -> None:
        try:
            self._run()
        except BaseException as exc:  # noqa: BLE001 - handed to the caller
            self.error = exc
        finally:
            self.ready.set()

    # -- the loop --------------------------------------------------------------------------------
    def _run(self) -> None:
        from lcv_replay.log.follow import ChunkTail

        tail = ChunkTail(self.source)
        last_size, last_growth = -1, time.monotonic()
        scan = plan = wanted = store = None
        done: dict[int, int] = {}
        writer = None
        last_stamp: int | None = None
        try:
            while True:
                new = tail.poll()
                if tail.size_bytes != last_size:
                    last_size, last_growth = tail.size_bytes, time.monotonic()
                ended = tail.finished or tail.damaged is not None
                if not ended and (self.stop() or time.monotonic() - last_growth >= self.idle_timeout_s):
                    ended = True
                    self.end_reason = "stopped" if self.stop() else "idle"
                    if self.end_reason == "idle":
                        log.warning("%s: no growth for %.1f s and not finalised: converting the frames so far (as --recover)",
                                    self.source, self.idle_timeout_s)
                if plan is None and tail.messages:
                    topics = {ch.topic: tail.container.schemas[ch.schema_id].name
                              for ch in tail.container.channels.values() if ch.schema_id in tail.container.schemas}
                    plan = pick_topics(topics, self.options.request(), path=self.source)
                    for flag, topic in (("--left-info-topic", self.options.left_info_topic), ("--right-info-topic", self.options.right_info_topic)):
                        if topic:
                            check_topic_type(topics, topic, ("sensor_msgs/msg/CameraInfo",), flag, path=self.source)
                    for note in plan.notes:
                        log.info("%s: %s", self.source.name, note)
                    wanted = topic_roles(plan, topics, self.options, name=self.source.stem)
                    scan = BagScan(topics, wanted, self.options.time_source, with_tf=plan.needs_tf, path=self.source)
                    store = typestore_from_schemas(tail.container.schemas)
                if plan is not None and (new or ended):
                    self._feed(tail, scan, store, done)
                    frames, final = self._final_frames(scan, plan, wanted, ended)
                    if final and writer is None:
                        writer = self._open_writer(scan, plan, wanted, frames)
                    if writer is not None:
                        self._write_calibration_once(writer, scan, plan, wanted, frames)
                        last_stamp = self._emit(writer, tail, scan, store, wanted, frames, final, last_stamp)
                if ended:
                    if writer is None:
                        raise RecorderError("the recording ended before its first frame", path=self.source,
                                            fix="check the topics (lcv-replay info on the finished bag)")
                    writer.close()
                    writer = None
                    self.end_reason = self.end_reason or ("finalised" if tail.finished else "damaged")
                    return
                time.sleep(self.poll_s)
        except BaseException:
            if writer is not None:
                writer.abort()  # live: finished with the frames written so far
            raise

    def _feed(self, tail: Any, scan: BagScan, store: Any, done: dict[int, int]) -> None:
        """Deserialise the new messages of the chosen topics into the first pass."""
        container = tail.container
        for cid, table in container.entries.items():
            channel = container.channels.get(cid)
            start = done.get(cid, 0)
            done[cid] = len(table)
            if channel is None or start >= len(table):
                continue
            msgtype = container.schemas[channel.schema_id].name
            if not scan.wants(channel.topic, msgtype):
                continue
            for row in table[start:]:
                raw = container.read_message(int(row["chunk"]), int(row["offset"]))
                message = store.deserialize_cdr(raw.data, msgtype)
                scan.add(channel.topic, msgtype, raw.log_time_ns, message, ref=(int(row["chunk"]), int(row["offset"]), msgtype))

    def _final_frames(self, scan: BagScan, plan: Any, wanted: dict[str, str], ended: bool):
        """The frame plan of what arrived, and how many of its frames are final."""
        try:
            frames = scan_plan(scan, plan, wanted, self.options, path=self.source)
        except RecorderError:
            if ended:
                raise
            return None, 0
        if ended:
            return frames, len(frames.stamps_ns)
        stamps = frames.stamps_ns
        limit = np.iinfo(np.int64).max
        for role in ("left", "odom"):
            if role in wanted and not (role == "odom" and self.options.vo):
                stream = scan.stream(wanted[role]).stamps_ns
                limit = min(limit, int(stream[-1]) if len(stream) else -1)
        if "right" in wanted:
            stream = scan.stream(wanted["right"]).stamps_ns
            limit = min(limit, int(stream[-1]) - self.options.stereo_tolerance_ns if len(stream) else -1)
        for pair in (plan.odom_from_tf, plan.ground_truth_from_tf):
            if pair is not None and not self.options.vo:
                up, down = scan.tf.chain(*pair)
                for edge in (*up, *down):
                    if not edge.static:
                        limit = min(limit, int(edge.stamps_ns[-1]))
        final = stamps <= limit
        if "gt" in wanted:
            gt = scan.stream(wanted["gt"]).stamps_ns
            if len(gt):  # a later ground-truth message could still reach these frames
                final &= ~((stamps > gt[-1]) & (stamps <= gt[-1] + self.options.max_gap_ns))
        return frames, int(np.argmin(final)) if not final.all() else len(final)

    def _open_writer(self, scan: BagScan, plan: Any, wanted: dict[str, str], frames: Any) -> Any:
        from lcv_replay.log.writer import LogWriter

        header = log_header(scan, plan, wanted, self.options, dataset=self.source.stem, stamps_ns=frames.stamps_ns,
                            config=dict(source=[str(self.source)], bag_format="ros2", storage="mcap", followed=True))
        writer = LogWriter(self.out, force=True, dataset=header.dataset, recorder=header.recorder,
                           nominal_rate_hz=header.nominal_rate_hz, recorder_config=header.config,
                           image_format=header.image_format, jpeg_quality=header.jpeg_quality, live=True)
        if "gt" in wanted or plan.ground_truth_from_tf:
            writer.declare_ground_truth()
        return writer

    def _write_calibration_once(self, writer: Any, scan: BagScan, plan: Any, wanted: dict[str, str], frames: Any) -> None:
        """The calibration, as soon as the camera infos have arrived (stamped at the first frame)."""
        if self._calibrated or "left_info" not in wanted or wanted["left_info"] not in scan.infos:
            return
        header = log_header(scan, plan, wanted, self.options, dataset="", stamps_ns=frames.stamps_ns, config={})
        writer.write_calibration(header.calibration, int(frames.stamps_ns[0]))
        self._calibrated = True

    def _emit(self, writer: Any, tail: Any, scan: BagScan, store: Any, wanted: dict[str, str], frames: Any, final: int,
              last_stamp: int | None) -> int | None:
        """Write the final frames after ``last_stamp``; returns the new last stamp."""
        for k in range(final):
            stamp = int(frames.stamps_ns[k])
            if last_stamp is not None and stamp <= last_stamp:
                continue
            images = {}
            for role in ("left", "right"):
                if role in wanted:
                    image_stamp = stamp if role == "left" else int(frames.right_stamps_ns[k])
                    images[role] = self._image(tail, store, scan.refs[wanted[role]][image_stamp])
            odom = None if frames.odometry is None else Pose2D(*frames.odometry[k])
            truth = None
            if frames.ground_truth is not None and np.isfinite(frames.ground_truth[k]).all():
                truth = Pose2D(*frames.ground_truth[k])
            writer.write_frame(writer.frames_written, stamp, left=images.get("left"), right=images.get("right"),
                               odom=odom, ground_truth=truth)
            writer.flush()
            last_stamp = stamp
            self.frames = writer.frames_written
            if self.frames == 1:
                self.ready.set()
        return last_stamp

    def _image(self, tail: Any, store: Any, ref: tuple[int, int, str]) -> np.ndarray:
        chunk, offset, msgtype = ref
        raw = tail.container.read_message(chunk, offset)
        try:
            return image_to_array(store.deserialize_cdr(raw.data, msgtype), msgtype)
        except ValueError as exc:
            raise RecorderError(f"an image at {raw.log_time_ns} ns: {exc}", path=self.source,
                                fix="record mono8/rgb8/bgr8 images or CompressedImage") from None


def start_live_conversion(source: Path, out: Path, options: RosbagOptions, *, idle_timeout_s: float,
                          stop: Callable[[], bool]) -> LiveConversion:
    """Start converting a growing ROS 2 MCAP; returns once the output has its first frame.

    Raises the conversion's error (bad topic, no frame before the recording ended, ...) if it
    ends before the first frame.
    """
    conversion = LiveConversion(source, out, options, idle_timeout_s=idle_timeout_s, stop=stop)
    conversion.start()
    conversion.ready.wait()
    if conversion.error is not None and conversion.frames == 0:
        conversion.join()
        error = conversion.error
        if isinstance(error, (LcvError, KeyboardInterrupt)):
            raise error
        raise RecorderError(f"the live conversion failed: {error}", path=source) from error
    return conversion

