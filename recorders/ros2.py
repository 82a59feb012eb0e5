"""``lcv-replay record ros2``: import a ROS 2 MCAP (CDR-encoded, ``ros2msg`` schemas).

Messages are decoded with ``mcap-ros2-support``. Topics:

* ``--left-topic`` / ``--right-topic``: ``sensor_msgs/msg/Image`` (``mono8``, ``rgb8``, ``bgr8``,
  ``rgba8``, ``bgra8``, ``mono16``) or ``sensor_msgs/msg/CompressedImage``. Optional: a log
  without images carries odometry (and candidates from elsewhere) only.
* ``--odom-topic`` (default ``/odom``): ``nav_msgs/msg/Odometry``; ``pose.pose`` of the child frame
  (``base_link``, REP-103: x forward, y left, z up) in the odometry frame, projected to planar by
  dropping z, roll and pitch (yaw = heading of the body x axis, see
  :func:`recorders.common.project_to_planar`).
* ``--ground-truth-topic``: ``nav_msgs/msg/Odometry``, ``geometry_msgs/msg/PoseStamped`` or
  ``geometry_msgs/msg/PoseWithCovarianceStamped``, projected the same way.
* ``--left-info-topic`` / ``--right-info-topic``: ``sensor_msgs/msg/CameraInfo`` of the rectified
  pair (``P`` matrices; baseline ``= (P_l[0,3] - P_r[0,3]) / fx``); by default the
  ``camera_info`` topic next to each image topic, when the file has it.

**Frames.** With images: one frame per left image that has a right image within
``stereo_tolerance_ns``; odometry and ground truth are interpolated to the image stamps.
Without images: one frame per odometry message (thinned to ``max_rate_hz`` if given).
**Stamps** are the messages' ``header.stamp`` (``time_source="header"``), their MCAP
``log_time`` (``"log"``), or header stamps unless one is zero (``"auto"``, the default). Repeated
stamps keep the first message. A named topic that is not in the file is an error that lists the
topics that are.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Iterator, Literal

import numpy as np

from lcv_replay.errors import RecorderError
from lcv_replay.records import StereoCalibration
from recorders.common import (
    R_BODY_IDENTITY,
    ImageFormat,
    LogHeader,
    ProgressCallback,
    RecordStats,
    associate_stamps,
    calibration_from_projections,
    interpolate_planar,
    nominal_rate_hz,
    make_frames,
    options_config,
    project_to_planar,
    require_path,
    transforms_from_quaternions,
    write_log,
)

log = logging.getLogger(__name__)

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
ODOMETRY_TYPES = ("nav_msgs/msg/Odometry",)
POSE_TYPES = ("nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped")
CAMERA_INFO_TYPES = ("sensor_msgs/msg/CameraInfo",)
TimeSource = Literal["auto", "header", "log"]


@dataclass(frozen=True)
class Ros2Options:
    """Options of the ROS 2 importer (see the module docstring).

    Attributes:
        left_topic, right_topic: image topics (``None`` = no images / mono).
        odom_topic: odometry topic; ``None`` or ``""`` = no odometry.
        ground_truth_topic: optional ground-truth pose topic.
        left_info_topic, right_info_topic: ``CameraInfo`` topics (``None`` = the sibling
            ``camera_info`` topic if present).
        time_source: ``auto``, ``header`` or ``log``.
        max_rate_hz: without images, keep at most this many odometry frames per second.
        stereo_tolerance_ns: left/right pairing tolerance.
        max_gap_ns: largest pose gap bridged when interpolating odometry to image stamps.
        max_frames: stop after this many frames.
    """

    left_topic: str | None = None
    right_topic: str | None = None
    odom_topic: str | None = "/odom"
    ground_truth_topic: str | None = None
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

    def __post_init__(self) -> None:
        if self.time_source not in ("auto", "header", "log"):
            raise RecorderError(f"--time-source {self.time_source!r} is unknown", fix="use auto, header or log")
        if self.right_topic and not self.left_topic:
            raise RecorderError("--right-topic needs --left-topic", fix="name the left image topic too")
        if self.max_rate_hz is not None and not self.max_rate_hz > 0:
            raise RecorderError(f"--max-rate-hz {self.max_rate_hz} must be positive", fix="pass e.g. --max-rate-hz 10")
        if self.max_frames is not None and self.max_frames < 1:
            raise RecorderError(f"--max-frames {self.max_frames} must be >= 1", fix="pass a positive count")


def _open_reader(path: Path, handle) -> Any:
    from mcap.exceptions import McapError
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    try:
        reader = make_reader(handle, decoder_factories=[DecoderFactory()])
        reader.get_header()
        return reader
    except (McapError, ValueError, OSError) as exc:
        raise RecorderError(f"not a readable MCAP file ({exc})", path=path, fix="pass a ROS 2 bag recorded with the mcap storage plugin") from None


def list_topics(path: str | Path) -> dict[str, str]:
    """``{topic: schema name}`` of an MCAP (from its summary, or a scan if it has none)."""
    path = require_path(path, what="ROS 2 MCAP file", fix="pass the .mcap file of a ROS 2 bag")
    with path.open("rb") as handle:
        reader = _open_reader(path, handle)
        try:
            summary = reader.get_summary()
        except Exception:  # noqa: BLE001 - a damaged summary: fall back to a scan
            summary = None
        if summary is not None and summary.channels:
            return {ch.topic: summary.schemas[ch.schema_id].name if ch.schema_id in summary.schemas else "" for ch in summary.channels.values()}
        topics: dict[str, str] = {}
        for schema, channel, _message in reader.iter_messages():
            topics.setdefault(channel.topic, schema.name if schema else "")
        return topics


def _check_topic(path: Path, topics: dict[str, str], topic: str, accepted: tuple[str, ...], flag: str) -> None:
    listing = ", ".join(f"{t} ({s})" for t, s in sorted(topics.items())) or "none"
    if topic not in topics:
        raise RecorderError(f"topic {topic} ({flag}) is not in the file", path=path, fix=f"topics here: {listing}")
    if topics[topic] not in accepted:
        raise RecorderError(f"topic {topic} has type {topics[topic]}, expected {' or '.join(accepted)}", path=path, fix=f"topics here: {listing}")


def _stamp(ros_msg: Any, log_time: int, source: TimeSource) -> int:
    if source == "log":
        return int(log_time)
    header = getattr(ros_msg, "header", None)
    stamp = 0 if header is None else int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
    if stamp == 0 and source == "auto":
        return int(log_time)
    return stamp


def _pose_of(ros_msg: Any, schema: str) -> tuple[float, ...]:
    pose = ros_msg.pose.pose if schema in ("nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseWithCovarianceStamped") else ros_msg.pose
    p, q = pose.position, pose.orientation
    return (p.x, p.y, p.z, q.x, q.y, q.z, q.w)


def image_to_array(ros_msg: Any, schema: str) -> np.ndarray:
    """A decoded ``sensor_msgs`` Image or CompressedImage -> ``(H, W)`` / ``(H, W, 3)`` uint8 RGB."""
    import cv2

    if schema == "sensor_msgs/msg/CompressedImage":
        array = cv2.imdecode(np.frombuffer(bytes(ros_msg.data), dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        if array is None:
            raise ValueError(f"CompressedImage ({ros_msg.format}) cannot be decoded")
        if array.dtype == np.uint16:
            array = (array >> 8).astype(np.uint8)
        if array.ndim == 3:
            array = cv2.cvtColor(array, cv2.COLOR_BGRA2RGB if array.shape[2] == 4 else cv2.COLOR_BGR2RGB)
        return array
    encoding = ros_msg.encoding.lower()
    channels, dtype = {
        "mono8": (1, np.uint8), "8uc1": (1, np.uint8), "rgb8": (3, np.uint8), "bgr8": (3, np.uint8),
        "rgba8": (4, np.uint8), "bgra8": (4, np.uint8), "mono16": (1, np.uint16), "16uc1": (1, np.uint16),
    }.get(encoding, (0, None))
    if dtype is None:
        raise ValueError(f"image encoding {ros_msg.encoding!r} is not supported (mono8, rgb8, bgr8, rgba8, bgra8, mono16)")
    height, width, step = int(ros_msg.height), int(ros_msg.width), int(ros_msg.step)
    itemsize = np.dtype(dtype).itemsize
    data = np.frombuffer(bytes(ros_msg.data), dtype=np.uint8)
    if step < width * channels * itemsize or len(data) < step * height:
        raise ValueError(f"image data of {len(data)} bytes does not hold {height} rows of step {step}")
    rows = data[: step * height].reshape(height, step)[:, : width * channels * itemsize]
    array = rows.copy().view(dtype if not ros_msg.is_bigendian else np.dtype(dtype).newbyteorder(">"))
    array = array.reshape(height, width, channels) if channels > 1 else array.reshape(height, width)
    if itemsize == 2:
        array = (array.astype(np.uint16) >> 8).astype(np.uint8)
    if encoding in ("bgr8", "bgra8"):
        array = array[:, :, 2::-1]
    elif encoding == "rgba8":
        array = array[:, :, :3]
    return np.ascontiguousarray(array)


@dataclass(frozen=True)
class _Stream:
    """Stamps (and poses) of one topic after pass 1."""

    stamps_ns: np.ndarray  # (M,) increasing, unique
    poses: np.ndarray | None = None  # (M, 3) planar, pose topics only


def _scan(path: Path, topics: dict[str, str], wanted: dict[str, str], source: TimeSource) -> tuple[dict[str, _Stream], dict[str, Any]]:
    """Pass 1: stamps of every wanted topic, planar poses of the pose topics, the first CameraInfo."""
    stamps: dict[str, list[int]] = {t: [] for t in wanted.values()}
    raw_poses: dict[str, list[tuple[float, ...]]] = {t: [] for t in wanted.values()}
    infos: dict[str, Any] = {}
    with path.open("rb") as handle:
        reader = _open_reader(path, handle)
        for schema, channel, message, ros_msg in reader.iter_decoded_messages(topics=list(set(wanted.values())), log_time_order=True):
            topic = channel.topic
            if schema.name in CAMERA_INFO_TYPES:
                infos.setdefault(topic, ros_msg)
                continue
            stamps[topic].append(_stamp(ros_msg, message.log_time, source))
            if schema.name in POSE_TYPES:
                raw_poses[topic].append(_pose_of(ros_msg, schema.name))
    streams: dict[str, _Stream] = {}
    for topic, values in stamps.items():
        if topics.get(topic) in CAMERA_INFO_TYPES:
            continue
        array = np.asarray(values, dtype=np.int64)
        order = np.argsort(array, kind="stable")
        array = array[order]
        keep = np.concatenate([[True], np.diff(array) > 0]) if len(array) else np.zeros(0, dtype=bool)
        if (~keep).sum():
            log.warning("%s: %d messages repeat an earlier stamp and are skipped", topic, int((~keep).sum()))
        poses = None
        if topics[topic] in POSE_TYPES:
            data = np.asarray(raw_poses[topic], dtype=np.float64).reshape(-1, 7)[order][keep]
            bad = np.flatnonzero(~np.isfinite(data).all(axis=1))
            if len(bad):
                raise RecorderError(f"topic {topic}: message {int(bad[0])} (stamp {int(array[keep][bad[0]])} ns) has a NaN or inf pose", path=path, fix="repair the bag or choose another topic")
            try:
                poses = project_to_planar(transforms_from_quaternions(data[:, :3], data[:, 3:]), R_sensor_body=R_BODY_IDENTITY, R_planar_world=R_BODY_IDENTITY)
            except ValueError:
                raise RecorderError(f"topic {topic}: a pose has a zero quaternion", path=path, fix="repair the bag or choose another topic") from None
        streams[topic] = _Stream(array[keep], poses)
    return streams, infos


class _ImageSource:
    """Pass 2: images in frame order, decoded on request (thread-safe; used by the prefetch pool)."""

    def __init__(self, path: Path, topics: dict[str, str], wanted: dict[str, dict[int, int]], source: TimeSource):
        self._path = path
        self._topics = topics
        self._wanted = wanted  # topic -> {stamp_ns: frame index}
        self._source = source
        self._lock = threading.Lock()
        self._cache: dict[tuple[str, int], np.ndarray] = {}
        self._seen: set[tuple[str, int]] = set()
        self._handle = None
        self._messages: Iterator | None = None

    def close(self) -> None:
        if self._handle is not None:
            self._handle.close()
            self._handle = None

    def get(self, topic: str, frame: int) -> np.ndarray:
        with self._lock:
            if self._messages is None:
                self._handle = self._path.open("rb")
                reader = _open_reader(self._path, self._handle)
                self._messages = reader.iter_decoded_messages(topics=list(self._wanted), log_time_order=True)
            while (topic, frame) not in self._cache:
                try:
                    schema, channel, message, ros_msg = next(self._messages)
                except StopIteration:
                    raise RecorderError(f"topic {topic}: the image of frame {frame} was not found on the second pass", path=self._path, fix="the file changed while recording?") from None
                index = self._wanted[channel.topic].get(_stamp(ros_msg, message.log_time, self._source))
                if index is None or (channel.topic, index) in self._seen:
                    continue
                self._seen.add((channel.topic, index))
                try:
                    self._cache[(channel.topic, index)] = image_to_array(ros_msg, schema.name)
                except ValueError as exc:
                    raise RecorderError(f"topic {channel.topic}, frame {index}: {exc}", path=self._path, fix="record mono8/rgb8/bgr8 images or CompressedImage") from None
            return self._cache.pop((topic, frame))


def _calibration(info_left: Any, info_right: Any) -> StereoCalibration:
    P_left = np.asarray(info_left.p, dtype=np.float64).reshape(3, 4)
    P_right = np.asarray(info_right.p, dtype=np.float64).reshape(3, 4) if info_right is not None else P_left
    calib = calibration_from_projections(P_left, P_right, int(info_left.width), int(info_left.height))
    distortion = tuple(float(v) for v in list(info_left.d)[:5])
    if any(distortion):
        calib = StereoCalibration(**{**asdict(calib), "distortion": distortion + (0.0,) * (5 - len(distortion))})
    return calib


def _sibling_info(image_topic: str, topics: dict[str, str]) -> str | None:
    base = image_topic.rsplit("/", 1)[0]
    for candidate in (f"{base}/camera_info", f"{base.rsplit('/', 1)[0]}/camera_info"):
        if topics.get(candidate) in CAMERA_INFO_TYPES:
            return candidate
    return None


def record_ros2(
    source: str | Path,
    out_path: str | Path,
    options: Ros2Options = Ros2Options(),
    *,
    force: bool = False,
    progress: ProgressCallback | None = None,
) -> RecordStats:
    """Import a ROS 2 MCAP into an lcv-replay log at ``out_path`` (atomically)."""
    from lcv_replay.fileio import check_output_path

    started = time.perf_counter()
    path = Path(source)
    topics = list_topics(path)
    out_path = check_output_path(out_path, force=force)
    odom_topic = options.odom_topic or None
    wanted: dict[str, str] = {}
    for role, topic, accepted, flag in (
        ("left", options.left_topic, IMAGE_TYPES, "--left-topic"),
        ("right", options.right_topic, IMAGE_TYPES, "--right-topic"),
        ("odom", odom_topic, ODOMETRY_TYPES, "--odom-topic"),
        ("gt", options.ground_truth_topic, POSE_TYPES, "--ground-truth-topic"),
        ("left_info", options.left_info_topic, CAMERA_INFO_TYPES, "--left-info-topic"),
        ("right_info", options.right_info_topic, CAMERA_INFO_TYPES, "--right-info-topic"),
    ):
        if topic:
            _check_topic(path, topics, topic, accepted, flag)
            wanted[role] = topic
    if "left" not in wanted and "odom" not in wanted:
        raise RecorderError("nothing to record: no image topic and no odometry topic", path=path, fix="pass --left-topic and/or --odom-topic")
    for side in ("left", "right"):
        if side in wanted and f"{side}_info" not in wanted:
            sibling = _sibling_info(wanted[side], topics)
            if sibling:
                wanted[f"{side}_info"] = sibling
                log.info("using the camera info %s for %s", sibling, wanted[side])

    streams, infos = _scan(path, topics, wanted, options.time_source)
    odom = streams.get(wanted.get("odom", ""))
    gt = streams.get(wanted.get("gt", ""))
    image_source = None
    if "left" in wanted:
        left_ns = streams[wanted["left"]].stamps_ns
        if "right" in wanted:
            right_ns = streams[wanted["right"]].stamps_ns
            index = associate_stamps(left_ns, right_ns, options.stereo_tolerance_ns)
            used, keep = set(), []
            for k, r in enumerate(index):
                if r >= 0 and r not in used:
                    used.add(int(r))
                    keep.append(k)
            dropped = len(left_ns) + len(right_ns) - 2 * len(keep)
            if dropped:
                log.warning("%s: dropped %d images without a stereo partner within %d ns", path, dropped, options.stereo_tolerance_ns)
            right_of = {int(left_ns[k]): int(right_ns[index[k]]) for k in keep}
            stamps = left_ns[keep]
        else:
            stamps, right_of = left_ns, {}
        if options.max_frames is not None:
            stamps = stamps[: options.max_frames]
        if len(stamps) == 0:
            raise RecorderError(f"no stereo pair on {wanted['left']} / {wanted.get('right')}", path=path, fix="check the topics (or raise --stereo-tolerance-ns)")
        frame_of = {int(s): i for i, s in enumerate(stamps)}
        image_wanted = {wanted["left"]: frame_of}
        if "right" in wanted:
            image_wanted[wanted["right"]] = {right_of[int(s)]: i for i, s in enumerate(stamps)}
        image_source = _ImageSource(path, topics, image_wanted, options.time_source)
        odom_poses = interpolate_planar(odom.stamps_ns, odom.poses, stamps, options.max_gap_ns) if odom is not None else None
        if odom_poses is not None:
            bad = np.flatnonzero(~np.isfinite(odom_poses).all(axis=1))
            if len(bad):
                raise RecorderError(f"{len(bad)} frames have no odometry on {wanted['odom']} within {options.max_gap_ns} ns (first: frame {bad[0]})", path=path, fix="check --odom-topic (or raise --max-gap-ns)")
    else:
        stamps, odom_poses = odom.stamps_ns, odom.poses
        if options.max_rate_hz is not None:
            keep, last = [], None
            for k, s in enumerate(stamps):
                if last is None or s - last >= 1e9 / options.max_rate_hz:
                    keep.append(k)
                    last = s
            stamps, odom_poses = stamps[keep], odom_poses[keep]
        if options.max_frames is not None:
            stamps, odom_poses = stamps[: options.max_frames], odom_poses[: options.max_frames]
    gt_poses = interpolate_planar(gt.stamps_ns, gt.poses, stamps, options.max_gap_ns) if gt is not None else None

    calibration = None
    if "left_info" in wanted and wanted["left_info"] in infos:
        calibration = _calibration(infos[wanted["left_info"]], infos.get(wanted.get("right_info", "")))

    def loaders(role: str) -> list | None:
        if image_source is None or role not in wanted:
            return None
        return [lambda i=i: image_source.get(wanted[role], i) for i in range(len(stamps))]

    frames = make_frames(stamps, left=loaders("left"), right=loaders("right"), odometry=odom_poses, ground_truth=gt_poses)
    config = options_config(options, source=path, topics_used=wanted)
    header = LogHeader(
        dataset=options.dataset or path.stem,
        recorder="ros2",
        nominal_rate_hz=nominal_rate_hz(stamps),
        config=config,
        calibration=calibration,
        image_format=options.image_format,
        jpeg_quality=options.jpeg_quality,
    )
    try:
        return write_log(out_path, header, frames, force=force, progress=progress, started=started, prefetch=2)
    finally:
        if image_source is not None:
            image_source.close()
