"""Stereo VO on lcv-replay logs: check a log's stereo inputs, run VO over its frames, and write a copy
of the log with the VO odometry on ``/odom`` (and ``/tf``).

This is the I/O edge of :mod:`lcv_replay.vo`: the core (:mod:`lcv_replay.vo.stereo_vo`) knows
arrays and records; this module knows topics and files. The output is written atomically (temp
file, then rename) and the input is never modified.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from collections import deque
from typing import Callable, Iterable, Iterator, Sequence, TypeVar

import numpy as np

from lcv_replay import __version__
from lcv_replay.errors import OdometryError, OutputError
from lcv_replay.fileio import atomic_output
from lcv_replay.log import format as fmt
from lcv_replay.log import messages
from lcv_replay.log.reader import LogReader, open_log
from lcv_replay.records import Frame, Pose2D, StereoCalibration
from lcv_replay.shutdown import raise_if_stopped, stop_requested
from lcv_replay.vo.config import VoConfig
from lcv_replay.vo.stereo_vo import StereoVoTracker, VoResult, VoStep, check_calibration, check_image_size, run_vo, to_grey

logger = logging.getLogger(__name__)

T = TypeVar("T")
R = TypeVar("R")

VO_METADATA_NAME = "lcv.vo"  # MCAP metadata record written next to VO odometry: config and summary
RIGHT_IMAGE_HINT = (
    "record the right camera as well: KITTI image_1, EuRoC cam1, 'record folder --right DIR', "
    "'record rosbag --right-topic TOPIC'"
)


def stereo_calibration_of(reader: LogReader) -> StereoCalibration:
    """The log's stereo calibration, checked for VO; :class:`OdometryError` naming the topic otherwise."""
    info = reader.info
    if not info.has_images:
        raise OdometryError(
            f"the log has no images on {fmt.LEFT_IMAGE_TOPIC}: stereo VO needs stereo image pairs",
            path=reader.path,
            fix=f"record {fmt.LEFT_IMAGE_TOPIC} and {fmt.RIGHT_IMAGE_TOPIC}",
        )
    if not info.has_right_images:
        raise OdometryError(
            f"stereo is required: the log has left images on {fmt.LEFT_IMAGE_TOPIC} but no right images on "
            f"{fmt.RIGHT_IMAGE_TOPIC}",
            path=reader.path,
            fix=RIGHT_IMAGE_HINT,
        )
    calibration = reader.calibration
    if calibration is None:
        raise OdometryError(
            f"missing calibration: the log has no {fmt.LEFT_CALIBRATION_TOPIC} message; stereo VO needs the "
            "intrinsics and the baseline",
            path=reader.path,
            fix=f"record foxglove.CameraCalibration on {fmt.LEFT_CALIBRATION_TOPIC} and {fmt.RIGHT_CALIBRATION_TOPIC}",
        )
    if not calibration.baseline_m > 0:
        raise OdometryError(
            f"no stereo baseline: {fmt.RIGHT_CALIBRATION_TOPIC} is missing or its P[0][3] (= -fx * baseline) is "
            f"{0.0 if calibration.baseline_m == 0 else calibration.baseline_m}",
            path=reader.path,
            fix="record the right camera's calibration with the baseline in P, as in ROS",
        )
    try:
        return check_calibration(calibration, where=f"the calibration on {fmt.LEFT_CALIBRATION_TOPIC}")
    except OdometryError as exc:
        raise OdometryError(exc.message, path=reader.path, fix=exc.fix) from None


def prefetched(items: Iterable[T], load: Callable[[T], R], *, ahead: int = 3) -> Iterator[R]:
    """``load(item)`` for every item, in order, computed up to ``ahead`` items early on one worker
    thread (image decoding in OpenCV releases the GIL, so it overlaps with the VO)."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(1, thread_name_prefix="lcv-vo-decode") as pool:
        pending: deque = deque()
        iterator = iter(items)
        for item in iterator:
            pending.append(pool.submit(load, item))
            if len(pending) > ahead:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()


def _decode_pair(frame: Frame) -> tuple[np.ndarray, np.ndarray]:
    return to_grey(frame.left.decode()), to_grey(frame.right.decode())


def stereo_pairs(reader: LogReader, calibration: StereoCalibration, frames: Iterable[Frame] | None = None) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Decoded ``(left, right)`` grey images of every frame (decoded ahead on a worker thread);
    checks the first pair against the calibration."""
    for k, (left, right) in enumerate(prefetched(reader.frames() if frames is None else frames, _decode_pair)):
        if k == 0:
            for topic, image in ((fmt.LEFT_IMAGE_TOPIC, left), (fmt.RIGHT_IMAGE_TOPIC, right)):
                try:
                    check_image_size(image.shape, calibration, f"the image on {topic}", f"the calibration on {fmt.LEFT_CALIBRATION_TOPIC}")
                except OdometryError as exc:
                    raise OdometryError(exc.message, path=reader.path, fix=exc.fix) from None
        yield left, right


def run_vo_on_log(
    reader: LogReader,
    config: VoConfig | None = None,
    *,
    T_body_camera: np.ndarray | None = None,
    on_step: Callable[[VoStep], None] | None = None,
) -> VoResult:
    """Stereo VO over every frame of an opened log (images decoded on the fly).

    A stop request (Ctrl-C, SIGTERM: :func:`lcv_replay.shutdown.stop_requested`) ends it after the
    current frame: the result then covers the first frames only.
    """
    calibration = stereo_calibration_of(reader)
    return run_vo(_until_stopped(stereo_pairs(reader, calibration)), calibration, config, T_body_camera=T_body_camera, on_step=on_step)


def _until_stopped(items: Iterable) -> Iterator:
    """``items`` until a stop is requested (:class:`Interrupted` if that is before the first one)."""
    for k, item in enumerate(items):
        if stop_requested():
            if k == 0:
                raise_if_stopped()
            return
        yield item


def camera_mount_of(reader: LogReader) -> np.ndarray | None:
    """``T_body_camera`` from the log's ``lcv`` metadata key ``T_body_camera`` (16 numbers, JSON), if any."""
    text = reader.info.metadata.get("T_body_camera")
    if not text:
        return None
    try:
        T = np.asarray(json.loads(text), dtype=np.float64).reshape(4, 4)
    except (ValueError, TypeError):
        logger.warning("%s: ignoring the unreadable lcv metadata T_body_camera %r", reader.path, text)
        return None
    return T


class ImageOdometry:
    """Planar odometry from stereo images, one call per frame: the recorders' ``--vo`` hook.

    ``hook(left, right)`` returns the cumulative ``T_odom_base`` of the frame (see
    :meth:`StereoVoTracker.process`); fallback frames are counted on :attr:`tracker` and the first
    one is reported with a warning.
    """

    def __init__(self, calibration: StereoCalibration | None, config: VoConfig | None = None, *, T_body_camera: np.ndarray | None = None):
        self.tracker = StereoVoTracker(check_calibration(calibration, where="the stereo calibration"), config, T_body_camera=T_body_camera)
        self._warned = False

    def __call__(self, left: np.ndarray | None, right: np.ndarray | None) -> Pose2D:
        if left is None or right is None:
            raise OdometryError("stereo is required: --vo needs a left and a right image for every frame", fix=RIGHT_IMAGE_HINT)
        step = self.tracker.process(left, right)
        if step.quality.fallback and not self._warned:
            self._warned = True
            logger.warning(
                "stereo VO: frame %d is %s, using a constant-velocity guess (further fallbacks are counted, not reported)",
                step.index, step.quality.status.value,
            )
        return step.T_odom_base


@dataclass(frozen=True)
class VoLogStats:
    """What :func:`add_vo_odometry` did."""

    path: Path
    result: VoResult
    replaced_odometry: bool
    frames_planned: int | None = None  # set when a stop request ended the VO early (the log is cut there)

    @property
    def interrupted(self) -> bool:
        return self.frames_planned is not None


def refuse_input_as_output(source: Path, out: Path) -> None:
    """:class:`OutputError` when ``out`` is the same file as ``source`` (even with ``--force``)."""
    if out.exists() and source.exists() and os.path.samefile(source, out):
        raise OutputError("the output is the input log; lcv-replay vo never rewrites its input", path=out, fix="name a new output file")


def write_log_with_odometry(
    source: str | Path,
    out: str | Path,
    stamps_ns: Sequence[int],
    poses: Sequence[Pose2D],
    *,
    force: bool = False,
    replace_odometry: bool = False,
    vo_metadata: dict[str, str] | None = None,
    until_ns: int | None = None,
) -> Path:
    """Copy every record of ``source`` into ``out`` and add planar odometry on ``/odom`` and ``/tf``.

    Args:
        stamps_ns: ``(N,)`` frame stamps; message ``i`` gets ``log_time = stamps_ns[i]`` and MCAP
            ``sequence = i`` (the frame index, as every lcv-replay recorder writes it).
        poses: ``N`` cumulative planar poses ``T_odom_base``.
        replace_odometry: drop the source's ``/odom`` and ``/tf`` messages (otherwise a source with
            odometry is refused).
        vo_metadata: string entries of an extra ``lcv.vo`` metadata record.
        until_ns: copy only the messages up to this ``log_time`` (the VO stopped early there).

    The ``lcv`` metadata record is copied with ``odometry_information`` cleared (the source's
    value, if any, described another odometry) and ``odometry_source`` set.
    """
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer
    from mcap_protobuf.schema import register_schema

    from lcv_replay.log.writer import MessageCopier

    source, out = Path(source), Path(out)
    refuse_input_as_output(source, out)
    if len(stamps_ns) != len(poses):
        raise OdometryError(f"{len(stamps_ns)} stamps but {len(poses)} poses")
    vo_messages = sorted(zip((int(s) for s in stamps_ns), range(len(poses)), poses))
    with atomic_output(out, force=force) as tmp, open(source, "rb") as fin, open(tmp, "wb") as fout:
        reader = make_reader(fin)
        header = reader.get_header()
        writer = Writer(fout, chunk_size=1 << 20, compression=CompressionType.ZSTD, enable_crcs=True)
        writer.start(profile=header.profile, library=f"lcv-replay/{__version__} vo (from {header.library})")
        copier = MessageCopier(writer)
        odom_channel = tf_channel = None
        pending = 0

        def flush_until(stamp_ns: int | None) -> None:
            nonlocal pending, odom_channel, tf_channel
            while pending < len(vo_messages) and (stamp_ns is None or vo_messages[pending][0] <= stamp_ns):
                stamp, index, pose = vo_messages[pending]
                odom = messages.pose_in_frame(pose, stamp, fmt.ODOM_FRAME_ID)
                tf = messages.frame_transform(pose, stamp, fmt.ODOM_FRAME_ID, fmt.BASE_FRAME_ID)
                if odom_channel is None:
                    odom_channel = writer.register_channel(fmt.ODOM_TOPIC, "protobuf", register_schema(writer, type(odom)))
                    tf_channel = writer.register_channel(fmt.TF_TOPIC, "protobuf", register_schema(writer, type(tf)))
                writer.add_message(odom_channel, stamp, odom.SerializeToString(), stamp, index)
                writer.add_message(tf_channel, stamp, tf.SerializeToString(), stamp, index)
                pending += 1

        for schema, channel, message in reader.iter_messages(log_time_order=True):
            if until_ns is not None and message.log_time > until_ns:
                break
            if channel.topic in (fmt.ODOM_TOPIC, fmt.TF_TOPIC):
                if not replace_odometry:
                    raise OdometryError(
                        f"the log already has odometry on {channel.topic}",
                        path=source,
                        fix="pass --replace-odometry to replace it with the VO odometry",
                    )
                continue
            flush_until(message.log_time)
            copier.add(schema, channel, message)
        flush_until(None)
        for record in reader.iter_metadata():
            data = dict(record.metadata)
            if record.name == fmt.METADATA_NAME:
                data["odometry_information"] = messages.information_to_json(None)
                data["odometry_source"] = "stereo visual odometry (lcv-replay vo)"
            if record.name != VO_METADATA_NAME:
                writer.add_metadata(record.name, data)
        if vo_metadata:
            writer.add_metadata(VO_METADATA_NAME, dict(vo_metadata))
        for attachment in reader.iter_attachments():
            writer.add_attachment(attachment.create_time, attachment.log_time, attachment.name, attachment.media_type, attachment.data)
        writer.finish()
    return out


def vo_metadata_record(config: VoConfig, result: VoResult) -> dict[str, str]:
    """The ``lcv.vo`` metadata: VO config and run summary, JSON-encoded values."""
    from lcv_replay.config import to_dict

    return {
        "config": json.dumps(to_dict(config), sort_keys=True),
        "summary": json.dumps(result.summary(), sort_keys=True, default=float),
        "fallback_frames": json.dumps(result.fallback_frames),
        "version": __version__,
    }


def add_vo_odometry(
    log_path: str | Path,
    out_path: str | Path,
    config: VoConfig | None = None,
    *,
    force: bool = False,
    replace_odometry: bool = False,
    on_step: Callable[[VoStep], None] | None = None,
) -> VoLogStats:
    """``lcv-replay vo LOG -o OUT``: run stereo VO on ``LOG`` and write ``OUT`` with ``/odom`` added.

    Raises:
        OdometryError: no right images, missing or mismatching calibration, or (without
            ``replace_odometry``) a log that already has odometry.
        OutputError: ``OUT`` exists (without ``force``) or is the input.
    """
    log_path, out_path = Path(log_path), Path(out_path)
    config = config or VoConfig()
    refuse_input_as_output(log_path, out_path)
    from lcv_replay.fileio import check_output_path

    check_output_path(out_path, force=force)
    reader = open_log(log_path)
    if reader.info.has_odometry and not replace_odometry:
        raise OdometryError(
            f"the log already has odometry on {fmt.ODOM_TOPIC}",
            path=log_path,
            fix="pass --replace-odometry to replace it with the VO odometry",
        )
    result = run_vo_on_log(reader, config, T_body_camera=camera_mount_of(reader), on_step=on_step)
    done = len(result.steps)
    stamps = reader.frame_stamps_ns[:done].tolist()
    stopped = done < reader.info.frames
    write_log_with_odometry(
        log_path,
        out_path,
        stamps,
        [s.T_odom_base for s in result.steps],
        force=force,
        replace_odometry=replace_odometry,
        vo_metadata=vo_metadata_record(config, result),
        until_ns=stamps[-1] if stopped else None,
    )
    return VoLogStats(out_path, result, reader.info.has_odometry, reader.info.frames if stopped else None)
