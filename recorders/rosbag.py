"""``lcv-replay record rosbag BAG... -o OUT.mcap``: import a ROS 1 or ROS 2 bag through ``rosbags``.

Inputs (:func:`recorders.bags.resolve_source`): ROS 1 ``.bag`` files (split parts in order), a
ROS 2 bag folder (``metadata.yaml`` + ``.db3`` or ``.mcap``), a bare ``.db3``, or a bare ROS 2
``.mcap``. ``record ros2`` is an alias of this command.

Topics (a topic the user does not name is chosen when it is the only candidate of its kind, with a
note; several candidates are an error that lists them with the flag to choose):

* ``--left-topic`` / ``--right-topic``: ``sensor_msgs/Image`` (``mono8``, ``rgb8``, ``bgr8``,
  ``rgba8``, ``bgra8``, ``mono16``) or ``sensor_msgs/CompressedImage``; ``--no-images`` for none.
  Without images the log carries odometry (and ground truth) only.
* ``--odom-topic``: ``nav_msgs/Odometry`` (``pose.pose``), ``geometry_msgs/PoseStamped`` or
  ``PoseWithCovarianceStamped``, or ``--odom-from-tf PARENT:CHILD``: the chain of ``/tf`` and
  ``/tf_static`` transforms from PARENT to CHILD (:mod:`recorders.tf_buffer`), interpolated at the
  frame stamps. Poses are projected to planar by dropping z, roll and pitch
  (:func:`recorders.common.project_to_planar`, identities: ROS frames are z-up, REP 103).
* ``--ground-truth-topic`` / ``--ground-truth-from-tf``: the same kinds, projected the same way.
* ``--left-info-topic`` / ``--right-info-topic``: ``sensor_msgs/CameraInfo`` of the rectified pair
  (``P``; baseline ``= (P_l[0,3] - P_r[0,3]) / fx``); by default the ``camera_info`` next to each
  image topic.

**Frames.** With images: one frame per left image that has a right image within
``stereo_tolerance_ns``. Without images: one frame per odometry message (per sample of the TF
chain's densest ``/tf`` edge), thinned to ``max_rate_hz`` if given. Odometry and ground truth are
interpolated to the frame stamps (gaps up to ``max_gap_ns``); frames at the start or end without
odometry are dropped with a warning, a gap inside is an error. **Stamps** are ``header.stamp``
(``time_source="header"``), the bag's receive time (``"log"``), or the header unless it is zero
(``"auto"``, the default). A repeated stamp keeps the first message.

Two passes over the bag: the first deserialises everything but keeps only stamps, poses, TF and
camera info; the second decodes the images of the chosen frames, in order, while the writer encodes.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Iterator, Literal, Sequence

import numpy as np

from lcv_replay.errors import RecorderError
from lcv_replay.records import StereoCalibration
from recorders.bags import (
    CAMERA_INFO_TYPES,
    POSE_TYPES,
    TF_TOPICS,
    TF_TYPES,
    BagSource,
    TopicPlan,
    TopicRequest,
    add_tf_message,
    bag_topics,
    check_topic_type,
    deserialize,
    is_static_tf_topic,
    message_stamp_ns,
    open_bag,
    pick_topics,
    read_tf,
    resolve_source,
    sibling_camera_info,
)
from recorders.common import (
    R_BODY_IDENTITY,
    ImageFormat,
    LogHeader,
    ProgressCallback,
    RecordStats,
    associate_stamps,
    calibration_from_projections,
    interpolate_planar,
    make_frames,
    nominal_rate_hz,
    options_config,
    project_to_planar,
    transforms_from_quaternions,
    vo_hook,
    write_log,
)
from recorders.tf_buffer import TfBuffer, parse_frame_pair

log = logging.getLogger(__name__)

TimeSource = Literal["auto", "header", "log"]


@dataclass(frozen=True)
class RosbagOptions:
    """Options of the bag importer (see the module docstring).

    Attributes:
        left_topic, right_topic: image topics; ``None`` = choose (the only stereo pair, or the
            only image topic as a mono camera).
        no_images: import no images even if the bag has some.
        odom_topic: odometry pose topic; ``None`` = choose, ``""`` = none.
        odom_from_tf: ``"PARENT:CHILD"``: odometry from the TF chain instead of a topic.
        ground_truth_topic: ground-truth pose topic; ``None`` = the pose topic whose name says
            ground truth (``groundtruth``, ``gt``, ``vicon``, ...), if exactly one; ``""`` = none.
        ground_truth_from_tf: ``"PARENT:CHILD"``: ground truth from the TF chain.
        left_info_topic, right_info_topic: ``CameraInfo`` topics (``None`` = the sibling ``camera_info``).
        time_source: ``auto``, ``header`` or ``log``.
        max_rate_hz: without images, keep at most this many odometry frames per second.
        stereo_tolerance_ns: left/right pairing tolerance.
        max_gap_ns: largest pose gap bridged when interpolating poses to frame stamps.
        max_frames: stop after this many frames.
        vo: compute the odometry with stereo visual odometry on the imported images.
    """

    left_topic: str | None = None
    right_topic: str | None = None
    no_images: bool = False
    odom_topic: str | None = None
    odom_from_tf: str | None = None
    ground_truth_topic: str | None = None
    ground_truth_from_tf: str | None = None
    left_info_topic: str | None = None
    right_info_topic: str | None = None
    time_source: TimeSource = "auto"
    max_rate_hz: float | None = None
    stereo_tolerance_ns: int = 1_000_000
    max_gap_ns: int = 500_000_000
    max_frames: int | None = None
    dataset: str | None = None
    image_format: ImageFormat = "png"
    jpeg_quality: int = 95
    vo: bool = False

    def __post_init__(self) -> None:
        if self.time_source not in ("auto", "header", "log"):
            raise RecorderError(f"--time-source {self.time_source!r} is unknown", fix="use auto, header or log")
        if self.right_topic and not self.left_topic:
            raise RecorderError("--right-topic needs --left-topic", fix="name the left image topic too")
        if self.no_images and (self.left_topic or self.right_topic):
            raise RecorderError("--no-images contradicts --left-topic/--right-topic", fix="pass one or the other")
        if self.odom_from_tf and self.odom_topic:
            raise RecorderError("--odom-topic and --odom-from-tf are exclusive", fix="pass one of them")
        if self.ground_truth_from_tf and self.ground_truth_topic:
            raise RecorderError("--ground-truth-topic and --ground-truth-from-tf are exclusive", fix="pass one of them")
        for flag, value in (("--odom-from-tf", self.odom_from_tf), ("--ground-truth-from-tf", self.ground_truth_from_tf)):
            if value:
                parse_frame_pair(value, flag=flag)
        if self.max_rate_hz is not None and not self.max_rate_hz > 0:
            raise RecorderError(f"--max-rate-hz {self.max_rate_hz} must be positive", fix="pass e.g. --max-rate-hz 10")
        if self.max_frames is not None and self.max_frames < 1:
            raise RecorderError(f"--max-frames {self.max_frames} must be >= 1", fix="pass a positive count")
        if self.max_gap_ns < 1 or self.stereo_tolerance_ns < 0:
            raise RecorderError("--max-gap-ns must be >= 1 and --stereo-tolerance-ns >= 0", fix="pass nanoseconds")

    def request(self) -> TopicRequest:
        """The topics the user named, for :func:`recorders.bags.pick_topics`."""
        return TopicRequest(
            left=self.left_topic,
            right=self.right_topic,
            no_images=self.no_images,
            odom=self.odom_topic,
            odom_from_tf=parse_frame_pair(self.odom_from_tf, flag="--odom-from-tf") if self.odom_from_tf else None,
            ground_truth=self.ground_truth_topic,
            ground_truth_from_tf=(
                parse_frame_pair(self.ground_truth_from_tf, flag="--ground-truth-from-tf") if self.ground_truth_from_tf else None
            ),
        )

    def topic_options(self) -> dict[str, Any]:
        """The options that change which data is imported (the key of a cached conversion)."""
        return {k: v for k, v in asdict(self).items()}


# ---------------------------------------------------------------------------------------------
# Messages -> arrays
# ---------------------------------------------------------------------------------------------


def _pose_of(message: Any, msgtype: str) -> tuple[float, ...]:
    pose = message.pose.pose if msgtype != "geometry_msgs/msg/PoseStamped" else message.pose
    p, q = pose.position, pose.orientation
    return (p.x, p.y, p.z, q.x, q.y, q.z, q.w)


def _byte_array(data: Any) -> np.ndarray:
    if isinstance(data, (bytes, bytearray, memoryview)):
        return np.frombuffer(data, dtype=np.uint8)
    return np.asarray(data, dtype=np.uint8).reshape(-1)


def image_to_array(message: Any, msgtype: str) -> np.ndarray:
    """A ``sensor_msgs`` Image or CompressedImage -> ``(H, W)`` / ``(H, W, 3)`` uint8 RGB.

    Raises ``ValueError`` on an encoding we cannot use or data that does not fit the header.
    """
    import cv2

    if msgtype == "sensor_msgs/msg/CompressedImage":
        array = cv2.imdecode(_byte_array(message.data), cv2.IMREAD_UNCHANGED)
        if array is None:
            raise ValueError(f"CompressedImage ({message.format}) cannot be decoded")
        if array.dtype == np.uint16:
            array = (array >> 8).astype(np.uint8)
        if array.ndim == 3:
            array = cv2.cvtColor(array, cv2.COLOR_BGRA2RGB if array.shape[2] == 4 else cv2.COLOR_BGR2RGB)
        return array
    encoding = str(message.encoding).lower()
    channels, dtype = {
        "mono8": (1, np.uint8), "8uc1": (1, np.uint8), "rgb8": (3, np.uint8), "bgr8": (3, np.uint8),
        "rgba8": (4, np.uint8), "bgra8": (4, np.uint8), "mono16": (1, np.uint16), "16uc1": (1, np.uint16),
    }.get(encoding, (0, None))
    if dtype is None:
        raise ValueError(f"image encoding {message.encoding!r} is not supported (mono8, rgb8, bgr8, rgba8, bgra8, mono16)")
    height, width, step = int(message.height), int(message.width), int(message.step)
    itemsize = np.dtype(dtype).itemsize
    data = _byte_array(message.data)
    if step < width * channels * itemsize or len(data) < step * height:
        raise ValueError(f"image data of {len(data)} bytes does not hold {height} rows of step {step}")
    rows = data[: step * height].reshape(height, step)[:, : width * channels * itemsize]
    array = rows.copy().view(dtype if not message.is_bigendian else np.dtype(dtype).newbyteorder(">"))
    array = array.reshape(height, width, channels) if channels > 1 else array.reshape(height, width)
    if itemsize == 2:
        array = (array.astype(np.uint16) >> 8).astype(np.uint8)
    if encoding in ("bgr8", "bgra8"):
        array = array[:, :, 2::-1]
    elif encoding == "rgba8":
        array = array[:, :, :3]
    return np.ascontiguousarray(array)


def _field(message: Any, name: str) -> Any:
    """A CameraInfo field by its ROS 2 (``p``) or ROS 1 (``P``) name."""
    value = getattr(message, name, None)
    return getattr(message, name.upper()) if value is None else value


def calibration_from_camera_info(info_left: Any, info_right: Any | None) -> StereoCalibration:
    """The rectified pair's calibration from the ``P`` matrices of two ``CameraInfo`` messages."""
    P_left = np.asarray(_field(info_left, "p"), dtype=np.float64).reshape(3, 4)
    P_right = np.asarray(_field(info_right, "p"), dtype=np.float64).reshape(3, 4) if info_right is not None else P_left
    calib = calibration_from_projections(P_left, P_right, int(info_left.width), int(info_left.height))
    distortion = tuple(float(v) for v in list(_field(info_left, "d"))[:5])
    if any(distortion):
        calib = StereoCalibration(**{**asdict(calib), "distortion": distortion + (0.0,) * (5 - len(distortion))})
    return calib


# ---------------------------------------------------------------------------------------------
# Pass 1: stamps, poses, TF, camera info
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PoseStream:
    """The stamps (and planar poses) of one topic after pass 1.

    ``stamps_ns`` ``(M,)`` increasing and unique; ``poses`` ``(M, 3)`` for pose topics, else ``None``.
    """

    stamps_ns: np.ndarray
    poses: np.ndarray | None = None


def _planar(raw: np.ndarray) -> np.ndarray:
    """``(M, 7)`` ``x y z qx qy qz qw`` -> ``(M, 3)`` planar poses (z-up frames on both sides)."""
    return project_to_planar(transforms_from_quaternions(raw[:, :3], raw[:, 3:]), R_sensor_body=R_BODY_IDENTITY, R_planar_world=R_BODY_IDENTITY)


class BagScan:
    """Pass 1, message by message: stamps (and planar poses) per topic, the TF buffer, the first CameraInfo.

    Messages may come in any order (:meth:`stream` sorts them); :meth:`add` is all a batch import
    and a live conversion share. ``wanted`` maps roles (``left``, ``right``, ``odom``, ``gt``,
    ``left_info``, ``right_info``) to topics; TF topics are taken when ``with_tf``.
    """

    def __init__(self, topics: dict[str, str], wanted: dict[str, str], time_source: TimeSource, *, with_tf: bool, path: Path):
        self.topics = dict(topics)
        self.names = set(wanted.values())
        self.time_source = time_source
        self.with_tf = with_tf
        self.path = path
        self.tf = TfBuffer()
        self.infos: dict[str, Any] = {}
        self.messages = 0
        self.refs: dict[str, dict[int, Any]] = {}  # image topic -> {stamp: where the message is}, first wins
        self._stamps: dict[str, list[int]] = {t: [] for t in self.names}
        self._poses: dict[str, list[tuple[float, ...]]] = {t: [] for t in self.names}
        self._streams: dict[str, PoseStream] = {}

    def wants(self, topic: str, msgtype: str) -> bool:
        return topic in self.names or (self.with_tf and topic in TF_TOPICS and msgtype in TF_TYPES)

    def add(self, topic: str, msgtype: str, log_time_ns: int, message: Any, ref: Any = None) -> None:
        """Take one deserialised message; ``ref`` locates an image message for a later decode."""
        self.messages += 1
        if msgtype in TF_TYPES and topic not in self.names:
            add_tf_message(self.tf, message, log_time_ns, static=is_static_tf_topic(topic), time_source=self.time_source)
            return
        if msgtype in CAMERA_INFO_TYPES:
            self.infos.setdefault(topic, message)
            return
        stamp = message_stamp_ns(message, log_time_ns, self.time_source)
        self._stamps[topic].append(stamp)
        self._streams.pop(topic, None)
        if msgtype in POSE_TYPES:
            self._poses[topic].append(_pose_of(message, msgtype))
        elif ref is not None:
            self.refs.setdefault(topic, {}).setdefault(stamp, ref)

    def stream(self, topic: str) -> PoseStream:
        """The topic's stamps, sorted and unique (a repeated stamp keeps its first message), with planar poses."""
        if topic in self._streams:
            return self._streams[topic]
        array = np.asarray(self._stamps[topic], dtype=np.int64)
        order = np.argsort(array, kind="stable")
        array = array[order]
        keep = np.concatenate([[True], np.diff(array) > 0]) if len(array) else np.zeros(0, dtype=bool)
        poses = None
        if self.topics.get(topic) in POSE_TYPES:
            data = np.asarray(self._poses[topic], dtype=np.float64).reshape(-1, 7)[order][keep]
            bad = np.flatnonzero(~np.isfinite(data).all(axis=1))
            if len(bad):
                raise RecorderError(
                    f"topic {topic}: message {int(bad[0])} (stamp {int(array[keep][bad[0]])} ns) has a NaN or inf pose",
                    path=self.path, fix="repair the bag or choose another topic",
                )
            try:
                poses = _planar(data)
            except ValueError:
                raise RecorderError(f"topic {topic}: a pose has a zero quaternion", path=self.path, fix="repair the bag or choose another topic") from None
        self._streams[topic] = PoseStream(array[keep], poses)
        return self._streams[topic]

    def repeated(self, topic: str) -> int:
        """Messages of ``topic`` skipped for repeating an earlier stamp."""
        return len(self._stamps[topic]) - len(self.stream(topic).stamps_ns)


def _scan(reader: Any, bag: BagSource, topics: dict[str, str], wanted: dict[str, str], options: RosbagOptions, with_tf: bool) -> BagScan:
    scan = BagScan(topics, wanted, options.time_source, with_tf=with_tf, path=bag.paths[0])
    connections = [c for c in reader.connections if scan.wants(c.topic, c.msgtype)]
    for connection, log_time, raw in reader.messages(connections=connections) if connections else ():
        scan.add(connection.topic, connection.msgtype, log_time, deserialize(reader, bag, connection, log_time, raw))
    for topic in scan.names:
        if topics.get(topic) not in CAMERA_INFO_TYPES and scan.repeated(topic):
            log.warning("%s: %d messages repeat an earlier stamp and are skipped", topic, scan.repeated(topic))
    return scan


# ---------------------------------------------------------------------------------------------
# Poses at the frame stamps: a topic or a TF chain
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PoseSource:
    """Where a pose comes from: a topic's :class:`PoseStream`, or a TF chain ``(parent, child)``."""

    name: str
    stream: PoseStream | None = None
    tf: TfBuffer | None = None
    frames: tuple[str, str] | None = None

    def at(self, stamps_ns: np.ndarray, max_gap_ns: int) -> np.ndarray:
        """``(N, 3)`` planar poses at ``stamps_ns``; NaN rows where none is within ``max_gap_ns``."""
        if self.stream is not None:
            return interpolate_planar(self.stream.stamps_ns, self.stream.poses, stamps_ns, max_gap_ns)
        T = self.tf.lookup(*self.frames, stamps_ns, max_gap_ns)
        out = np.full((len(T), 3), np.nan)
        good = np.isfinite(T).all(axis=(1, 2))
        if good.any():
            out[good] = project_to_planar(T[good], R_sensor_body=R_BODY_IDENTITY, R_planar_world=R_BODY_IDENTITY)
        return out

    def sample_stamps(self) -> np.ndarray:
        """The stamps at which this source is observed (frames of an odometry-only import)."""
        if self.stream is not None:
            return self.stream.stamps_ns
        return self.tf.sample_stamps(*self.frames)


def pose_source(plan_topic: str | None, frames: tuple[str, str] | None, scan: BagScan, path: Path, flag: str) -> PoseSource | None:
    """Where the odometry (or ground truth) of an import comes from: a topic or a TF chain."""
    if frames is not None:
        try:
            scan.tf.chain(*frames)  # raises, naming the frames seen, when nothing connects them
        except RecorderError as exc:
            raise RecorderError(f"{flag} {frames[0]}:{frames[1]}: {exc.message}", path=path, fix=exc.fix) from None
        return PoseSource(f"TF {frames[0]} -> {frames[1]}", tf=scan.tf, frames=frames)
    if plan_topic is None:
        return None
    return PoseSource(plan_topic, stream=scan.stream(plan_topic))


# ---------------------------------------------------------------------------------------------
# Frames
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FramePlan:
    """The frames of an import (pure result of pass 1).

    Attributes:
        stamps_ns: ``(N,)`` frame stamps.
        right_stamps_ns: ``(N,)`` stamp of each frame's right image, or ``None`` (mono / no images).
        odometry: ``(N, 3)`` planar odometry or ``None``.
        ground_truth: ``(N, 3)`` planar ground truth (NaN rows where unknown) or ``None``.
        dropped_unpaired: images dropped for lack of a stereo partner.
    """

    stamps_ns: np.ndarray
    right_stamps_ns: np.ndarray | None
    odometry: np.ndarray | None
    ground_truth: np.ndarray | None
    dropped_unpaired: int = 0


def plan_frames(
    left: PoseStream | None,
    right: PoseStream | None,
    odom: PoseSource | None,
    ground_truth: PoseSource | None,
    options: RosbagOptions,
    *,
    path: Path | None = None,
) -> FramePlan:
    """Frame stamps, stereo partners and poses at the frames (see the module docstring)."""
    right_of = None
    dropped = 0
    if left is not None:
        left_ns = left.stamps_ns
        if right is not None:
            index = associate_stamps(left_ns, right.stamps_ns, options.stereo_tolerance_ns)
            used, keep = set(), []
            for k, r in enumerate(index):
                if r >= 0 and int(r) not in used:
                    used.add(int(r))
                    keep.append(k)
            dropped = len(left_ns) + len(right.stamps_ns) - 2 * len(keep)
            stamps, right_of = left_ns[keep], right.stamps_ns[index[keep]]
        else:
            stamps = left_ns
        if len(stamps) == 0:
            raise RecorderError(
                "no stereo pair: no left image has a right image within the tolerance" if right is not None else "no image",
                path=path, fix="check the image topics (or raise --stereo-tolerance-ns)",
            )
    else:
        if odom is None:
            raise RecorderError("nothing to record: no image topic and no odometry", path=path, fix="pass --left-topic, --odom-topic or --odom-from-tf")
        stamps = odom.sample_stamps()
        if len(stamps) == 0:
            raise RecorderError(f"{odom.name} has no message to define frames", path=path, fix="choose another odometry source")
        if options.max_rate_hz is not None:
            keep, last = [], None
            for k, s in enumerate(stamps):
                if last is None or s - last >= 1e9 / options.max_rate_hz:
                    keep.append(k)
                    last = s
            stamps = stamps[keep]
    odometry = None
    if odom is not None:
        odometry = odom.at(stamps, options.max_gap_ns)
        have = np.isfinite(odometry).all(axis=1)
        if not have.any():
            raise RecorderError(
                f"no frame has odometry from {odom.name} within {options.max_gap_ns / 1e6:g} ms "
                f"(frames {int(stamps[0])} .. {int(stamps[-1])} ns)",
                path=path,
                fix="check that the odometry covers the frames, the --time-source, or raise --max-gap-ns",
            )
        first, last = int(np.argmax(have)), len(have) - int(np.argmax(have[::-1]))
        if first or last < len(have):
            log.warning("%s: dropped %d frames at the start and %d at the end without odometry from %s",
                        path, first, len(have) - last, odom.name)
        inner = np.flatnonzero(~have[first:last])
        if len(inner):
            k = first + int(inner[0])
            raise RecorderError(
                f"{len(inner)} frames have no odometry from {odom.name} within {options.max_gap_ns / 1e6:g} ms "
                f"(first: frame {k - first} at {int(stamps[k])} ns)",
                path=path,
                fix="raise --max-gap-ns, or check the odometry source",
            )
        stamps, odometry = stamps[first:last], odometry[first:last]
        right_of = right_of[first:last] if right_of is not None else None
    if options.max_frames is not None:
        stamps = stamps[: options.max_frames]
        odometry = odometry[: options.max_frames] if odometry is not None else None
        right_of = right_of[: options.max_frames] if right_of is not None else None
    truth = ground_truth.at(stamps, options.max_gap_ns) if ground_truth is not None else None
    if truth is not None and not np.isfinite(truth).all(axis=1).any():
        log.warning("%s: ground truth from %s covers none of the %d frames; the log has no ground truth", path, ground_truth.name, len(stamps))
        truth = None
    return FramePlan(stamps, right_of, odometry, truth, dropped)


# ---------------------------------------------------------------------------------------------
# Pass 2: images
# ---------------------------------------------------------------------------------------------


class _ImageSource:
    """Images in frame order, decoded on request (thread-safe; used by the writer's prefetch pool)."""

    def __init__(self, bag: BagSource, wanted: dict[str, dict[int, int]], time_source: TimeSource):
        self._bag = bag
        self._wanted = wanted  # topic -> {stamp_ns: frame index}
        self._time_source = time_source
        self._lock = threading.Lock()
        self._cache: dict[tuple[str, int], np.ndarray] = {}
        self._seen: set[tuple[str, int]] = set()
        self._context = None
        self._reader = None
        self._messages: Iterator | None = None

    def close(self) -> None:
        if self._context is not None:
            self._context.__exit__(None, None, None)
            self._context = None

    def get(self, topic: str, frame: int) -> np.ndarray:
        with self._lock:
            if self._messages is None:
                self._context = open_bag(self._bag)
                self._reader = self._context.__enter__()
                connections = [c for c in self._reader.connections if c.topic in self._wanted]
                self._messages = self._reader.messages(connections=connections)
            while (topic, frame) not in self._cache:
                try:
                    connection, log_time, raw = next(self._messages)
                except StopIteration:
                    raise RecorderError(f"topic {topic}: the image of frame {frame} was not found on the second pass",
                                        path=self._bag.paths[0], fix="the bag changed while importing?") from None
                message = deserialize(self._reader, self._bag, connection, log_time, raw)
                index = self._wanted[connection.topic].get(message_stamp_ns(message, log_time, self._time_source))
                if index is None or (connection.topic, index) in self._seen:
                    continue
                self._seen.add((connection.topic, index))
                try:
                    self._cache[(connection.topic, index)] = image_to_array(message, connection.msgtype)
                except ValueError as exc:
                    raise RecorderError(f"topic {connection.topic}, frame {index}: {exc}", path=self._bag.paths[0],
                                        fix="record mono8/rgb8/bgr8 images or CompressedImage") from None
            return self._cache.pop((topic, frame))


# ---------------------------------------------------------------------------------------------
# The recorder
# ---------------------------------------------------------------------------------------------


def choose_topics(reader: Any, bag: BagSource, options: RosbagOptions) -> tuple[dict[str, str], TopicPlan]:
    """``({topic: type}, the plan)`` for an opened bag; errors list candidates and flags."""
    topics = bag_topics(reader)
    counts = {name: int(info.msgcount) for name, info in reader.topics.items()}
    request = options.request()
    try:
        plan = pick_topics(topics, request, counts=counts, path=bag.paths[0])
    except RecorderError:
        if not any(ty in TF_TYPES for ty in topics.values()):
            raise
        hint = read_tf(reader, bag, options.time_source).suggest_odometry_pair()
        plan = pick_topics(topics, request, counts=counts, path=bag.paths[0], tf_hint=hint)
    for flag, topic in (("--left-info-topic", options.left_info_topic), ("--right-info-topic", options.right_info_topic)):
        if topic:
            check_topic_type(topics, topic, CAMERA_INFO_TYPES, flag, path=bag.paths[0])
    return topics, plan


def topic_roles(plan: TopicPlan, topics: dict[str, str], options: RosbagOptions, *, name: str) -> dict[str, str]:
    """Role -> topic of an import: images, odometry and ground-truth topics, camera infos (the named
    ones, else the sibling ``camera_info`` of each image topic)."""
    wanted: dict[str, str] = {}
    for role, topic in (("left", plan.left), ("right", plan.right), ("odom", plan.odom), ("gt", plan.ground_truth),
                        ("left_info", options.left_info_topic), ("right_info", options.right_info_topic)):
        if topic:
            wanted[role] = topic
    for side in ("left", "right"):
        if side in wanted and f"{side}_info" not in wanted:
            sibling = sibling_camera_info(wanted[side], topics)
            if sibling:
                wanted[f"{side}_info"] = sibling
                log.info("%s: camera info of %s: %s", name, wanted[side], sibling)
    return wanted


def scan_plan(scan: BagScan, plan: TopicPlan, wanted: dict[str, str], options: RosbagOptions, *, path: Path) -> FramePlan:
    """The frames of what :class:`BagScan` has seen (the TF chains checked first)."""
    odom = pose_source(plan.odom, plan.odom_from_tf, scan, path, "--odom-from-tf")
    truth = pose_source(plan.ground_truth, plan.ground_truth_from_tf, scan, path, "--ground-truth-from-tf")
    if options.vo and "left" not in wanted:
        raise RecorderError("--vo needs stereo images", path=path, fix="name the image topics with --left-topic/--right-topic")
    return plan_frames(
        scan.stream(wanted["left"]) if "left" in wanted else None, scan.stream(wanted["right"]) if "right" in wanted else None,
        None if options.vo else odom, truth, options, path=path,
    )


def log_header(scan: BagScan, plan: TopicPlan, wanted: dict[str, str], options: RosbagOptions, *, dataset: str,
               stamps_ns: np.ndarray, config: dict[str, Any]) -> LogHeader:
    """The writer's header of an import: calibration from the camera infos, the topics used in the config."""
    calibration = None
    if "left_info" in wanted and wanted["left_info"] in scan.infos:
        calibration = calibration_from_camera_info(scan.infos[wanted["left_info"]], scan.infos.get(wanted.get("right_info", "")))
    used = dict(wanted)
    if plan.odom_from_tf:
        used["odom_from_tf"] = ":".join(plan.odom_from_tf)
    if plan.ground_truth_from_tf:
        used["ground_truth_from_tf"] = ":".join(plan.ground_truth_from_tf)
    return LogHeader(
        dataset=options.dataset or dataset,
        recorder="rosbag",
        nominal_rate_hz=nominal_rate_hz(stamps_ns),
        config=options_config(options, topics_used=used, **config),
        calibration=calibration,
        image_format=options.image_format,
        jpeg_quality=options.jpeg_quality,
    )


def record_rosbag(
    source: str | Path | Sequence[str | Path],
    out_path: str | Path,
    options: RosbagOptions = RosbagOptions(),
    *,
    force: bool = False,
    progress: ProgressCallback | None = None,
    live: bool = False,
    extra_config: dict[str, Any] | None = None,
) -> RecordStats:
    """Import a ROS 1 / ROS 2 bag into an lcv-replay log at ``out_path``.

    ``source`` is one path or several (split ROS 1 parts). The log is written atomically, or, with
    ``live``, chunk by chunk at its final path (see :class:`lcv_replay.log.writer.LogWriter`).
    ``extra_config`` entries are added to the log's recorder config (the conversion cache's key).
    """
    from lcv_replay.fileio import check_output_path

    started = time.perf_counter()
    bag = resolve_source([source] if isinstance(source, (str, Path)) else list(source))
    out_path = check_output_path(out_path, force=force)
    with open_bag(bag) as reader:
        topics, plan = choose_topics(reader, bag, options)
        for note in plan.notes:
            log.info("%s: %s", bag.name, note)
        wanted = topic_roles(plan, topics, options, name=bag.name)
        scan = _scan(reader, bag, topics, wanted, options, with_tf=plan.needs_tf)
    frames_plan = scan_plan(scan, plan, wanted, options, path=bag.paths[0])
    if frames_plan.dropped_unpaired:
        log.warning("%s: dropped %d images without a stereo partner within %d ns", bag.name, frames_plan.dropped_unpaired, options.stereo_tolerance_ns)
    stamps = frames_plan.stamps_ns

    header = log_header(scan, plan, wanted, options, dataset=bag.name, stamps_ns=stamps, config=dict(
        source=[str(p) for p in bag.paths], bag_format=bag.kind, storage=bag.storage, messages_read=scan.messages,
        **(extra_config or {}),
    ))
    image_source = None
    if "left" in wanted:
        image_wanted = {wanted["left"]: {int(s): i for i, s in enumerate(stamps)}}
        if "right" in wanted:
            image_wanted[wanted["right"]] = {int(s): i for i, s in enumerate(frames_plan.right_stamps_ns)}
        image_source = _ImageSource(bag, image_wanted, options.time_source)

    def loaders(role: str) -> list | None:
        if image_source is None or role not in wanted:
            return None
        return [lambda i=i: image_source.get(wanted[role], i) for i in range(len(stamps))]

    frames = make_frames(stamps, left=loaders("left"), right=loaders("right"), odometry=frames_plan.odometry,
                         ground_truth=frames_plan.ground_truth)
    try:
        return write_log(out_path, header, frames, force=force, progress=progress, started=started, prefetch=2,
                         image_odometry=vo_hook(options.vo, header.calibration), live=live)
    finally:
        if image_source is not None:
            image_source.close()
