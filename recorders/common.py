"""Helpers shared by the recorders: pose files, 3-D -> planar projection, stamps, statistics.

Conventions (see :mod:`lcv_replay.records`): planar poses are ``(x_m, y_m, yaw_rad)`` of the body
(x forward, y left, yaw counter-clockwise about +z). Arrays of planar poses have shape ``(N, 3)``;
arrays of rigid transforms have shape ``(N, 4, 4)``.

**3-D -> planar projection** (:func:`project_to_planar`). A 3-D pose ``T_world_sensor`` is turned
into a z-up body in a z-up world, ``T = R_planar_world · T_world_sensor · R_sensor_body``, then
projected: ``x_m``, ``y_m`` are the translation's x and y, and ``yaw_rad = atan2(R[1, 0], R[0, 0])``,
the heading of the body x axis in the ground plane (the z-y-x Euler yaw). Height, roll and pitch
are dropped.

* KITTI poses (and camera-centric visual odometry) are of a camera with x right, y down,
  z forward, in the frame of the first camera: body x = camera z, body y = -camera x,
  body z = -camera y (:data:`R_BODY_CAMERA`), applied on both sides.
* EuRoC ground truth is of the IMU in a z-up world: the body is the left camera
  (``T_world_imu · T_imu_cam0``) with the camera rotation on the right side only.
* ROS odometry (``base_link`` in ``odom``, REP-103) is already z-up on both sides: identities.
"""

from __future__ import annotations

import contextlib
import math
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Literal, Protocol, Sequence

import numpy as np

from lcv_replay.errors import RecorderError
from lcv_replay.fileio import format_size
from lcv_replay.log.format import describe_warnings
from lcv_replay.se2 import wrap_angles
from lcv_replay.records import LoopCandidate, Pose2D, StereoCalibration
from lcv_replay.shutdown import raise_if_stopped, stop_requested

#: ``R_body_camera`` for a camera with x right, y down, z forward (KITTI, OpenCV).
R_BODY_CAMERA = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
#: ``R_body_sensor`` for poses that are already of a z-up body (EuRoC, ROS ``base_link``).
R_BODY_IDENTITY = np.eye(3)

PoseFormat = Literal["auto", "kitti", "tum"]


class ProgressCallback(Protocol):
    """Told how far a recording is: ``done`` frames written out of ``total``."""

    def __call__(self, done: int, total: int) -> None: ...


@dataclass(frozen=True)
class RecordStats:
    """What a recorder wrote: one line of summary for the CLI and numbers for the benchmarks."""

    path: Path
    frames: int
    candidates: int
    true_loops: int
    size_bytes: int
    elapsed_s: float
    has_images: bool
    has_odometry: bool
    has_ground_truth: bool
    frames_planned: int | None = None  # set when a stop request (Ctrl-C, SIGTERM) ended the recording early
    warnings: dict[str, int] = field(default_factory=dict)  # what was accepted with a warning (format.RECORDER_WARNING_NAMES)

    @property
    def interrupted(self) -> bool:
        return self.frames_planned is not None

    @property
    def frames_per_s(self) -> float:
        return self.frames / self.elapsed_s if self.elapsed_s > 0 else float("inf")

    def summary(self) -> str:
        """One line: ``wrote OUT.mcap: 4541 frames, 337 candidates, 120 true loops, 1.2 MB in 0.8 s``."""
        parts = [f"{self.frames} frames"]
        if self.candidates:
            parts.append(f"{self.candidates} candidates")
        if self.true_loops:
            parts.append(f"{self.true_loops} true loops")
        if not self.has_odometry:
            parts.append("no odometry")
        stopped = f" (INTERRUPTED: the first {self.frames} of {self.frames_planned} frames)" if self.interrupted else ""
        warned = f"; warnings: {describe_warnings(self.warnings)}" if self.warnings else ""
        return (
            f"wrote {self.path}: {', '.join(parts)}, {format_size(self.size_bytes)} in {self.elapsed_s:.1f} s "
            f"({self.frames_per_s:.0f} frames/s){stopped}{warned}"
        )


# ---------------------------------------------------------------------------------------------
# Planar poses (the algebra is lcv_replay.se2)
# ---------------------------------------------------------------------------------------------


def poses_to_records(poses: np.ndarray) -> list[Pose2D]:
    """``(N, 3)`` array -> list of :class:`Pose2D`."""
    return [Pose2D(float(x), float(y), float(t)) for x, y, t in np.asarray(poses, dtype=np.float64)]


def project_to_planar(
    T_world_sensor: np.ndarray,
    *,
    R_sensor_body: np.ndarray = R_BODY_CAMERA.T,
    R_planar_world: np.ndarray = R_BODY_CAMERA,
) -> np.ndarray:
    """Project 3-D poses to planar body poses (see the module docstring).

    ``T_planar_body = R_planar_world · T_world_sensor · R_sensor_body`` (rotations only on the
    sides), then ``x_m, y_m`` = translation x, y and ``yaw_rad = atan2(R[1, 0], R[0, 0])``.
    The defaults suit KITTI and camera-centric visual odometry: the world is the first camera frame
    and the sensor is a camera (x right, y down, z forward). For a z-up world and a z-up body pass
    identities (:data:`R_BODY_IDENTITY`).

    Args:
        T_world_sensor: ``(N, 4, 4)`` rigid transforms of the sensor in its world frame.
        R_sensor_body: ``(3, 3)`` rotation of the planar body axes in the sensor frame.
        R_planar_world: ``(3, 3)`` rotation taking world vectors to the z-up planar world.

    Returns:
        ``(N, 3)`` planar poses ``(x_m, y_m, yaw_rad)``.
    """
    T = np.asarray(T_world_sensor, dtype=np.float64).reshape(-1, 4, 4)
    R_pw = np.asarray(R_planar_world, dtype=np.float64)
    rot = np.einsum("ij,njk,kl->nil", R_pw, T[:, :3, :3], np.asarray(R_sensor_body, dtype=np.float64))
    trans = T[:, :3, 3] @ R_pw.T
    return np.stack([trans[:, 0], trans[:, 1], np.arctan2(rot[:, 1, 0], rot[:, 0, 0])], axis=1)


def quaternion_to_matrix(q_xyzw: np.ndarray) -> np.ndarray:
    """``(N, 4)`` unit quaternions ``(qx, qy, qz, qw)`` -> ``(N, 3, 3)`` rotation matrices."""
    q = np.asarray(q_xyzw, dtype=np.float64).reshape(-1, 4)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    if np.any(norm < 1e-9):
        raise ValueError("zero quaternion")
    x, y, z, w = (q / norm).T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=1),
        ],
        axis=1,
    )


def transforms_from_quaternions(t_xyz: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    """``(N, 3)`` translations and ``(N, 4)`` quaternions ``(qx, qy, qz, qw)`` -> ``(N, 4, 4)``."""
    t = np.asarray(t_xyz, dtype=np.float64).reshape(-1, 3)
    T = np.tile(np.eye(4), (len(t), 1, 1))
    T[:, :3, :3] = quaternion_to_matrix(q_xyzw)
    T[:, :3, 3] = t
    return T


# ---------------------------------------------------------------------------------------------
# Text pose files: KITTI (3x4 row-major per line) and TUM (stamp tx ty tz qx qy qz qw)
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PoseFile:
    """A 3-D trajectory read from a text file.

    Attributes:
        path: the file.
        format: ``"kitti"`` or ``"tum"``.
        T_world_sensor: ``(N, 4, 4)`` poses.
        stamps_s: ``(N,)`` timestamps in seconds (TUM), or ``None`` (KITTI: one pose per frame).
    """

    path: Path
    format: Literal["kitti", "tum"]
    T_world_sensor: np.ndarray
    stamps_s: np.ndarray | None


_SPLIT = re.compile(r"[\s,]+")


def read_numeric_rows(path: Path, *, what: str, fix: str) -> list[tuple[int, list[float]]]:
    """Non-empty, non-comment (``#``) lines of a whitespace/comma separated file as floats.

    Returns ``(line_number, values)`` pairs; a header line of words is skipped if it is the first.
    Raises :class:`RecorderError` naming the file and the line on a value that is not a number.
    """
    path = Path(path)
    if not path.is_file():
        raise RecorderError(f"{what} not found", path=path, fix=fix)
    rows: list[tuple[int, list[float]]] = []
    with path.open("r", encoding="utf-8", errors="replace") as handle:
        for line_no, line in enumerate(handle, start=1):
            text = line.strip()
            if not text or text.startswith("#") or text.startswith("%"):
                continue
            tokens = [t for t in _SPLIT.split(text) if t]
            try:
                rows.append((line_no, [float(t) for t in tokens]))
            except ValueError:
                if not rows and not any(is_number(t) for t in tokens):
                    continue  # a header line before the data, such as "timestamp_ns,x_m,y_m,yaw_rad"
                raise RecorderError(f"line {line_no}: not a number in {text[:60]!r}", path=path, fix=fix) from None
    return rows


def is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def read_pose_file(path: str | Path, fmt: PoseFormat = "auto") -> PoseFile:
    """Read a KITTI or TUM trajectory file.

    * KITTI: 12 numbers per line, the first 3 rows of ``T_world_camera`` row-major; one line per
      frame, no timestamps.
    * TUM: ``stamp_s tx ty tz qx qy qz qw`` per line (8 numbers).

    ``fmt="auto"`` decides by the column count of the first data line.
    """
    path = Path(path)
    fix = "pass a KITTI pose file (12 numbers per line) or a TUM file (stamp tx ty tz qx qy qz qw)"
    rows = read_numeric_rows(path, what="pose file", fix=fix)
    if not rows:
        raise RecorderError("pose file has no poses", path=path, fix=fix)
    if fmt == "auto":
        width = len(rows[0][1])
        if width == 12:
            fmt = "kitti"
        elif width == 8:
            fmt = "tum"
        else:
            raise RecorderError(f"cannot tell the pose format from {width} columns on line {rows[0][0]}", path=path, fix=fix)
    width = 12 if fmt == "kitti" else 8
    for line_no, values in rows:
        if len(values) != width:
            raise RecorderError(f"line {line_no}: expected {width} numbers for the {fmt.upper()} format, got {len(values)}", path=path, fix=fix)
    data = np.array([values for _, values in rows], dtype=np.float64)
    bad = ~np.isfinite(data).all(axis=1)
    if bad.any():
        line_no = rows[int(np.argmax(bad))][0]
        raise RecorderError(f"line {line_no}: NaN or inf in a pose", path=path, fix="remove or repair that line")
    if fmt == "kitti":
        T = np.tile(np.eye(4), (len(data), 1, 1))
        T[:, :3, :4] = data.reshape(-1, 3, 4)
        return PoseFile(path, "kitti", T, None)
    stamps = data[:, 0]
    if np.any(np.diff(stamps) <= 0):
        k = int(np.argmax(np.diff(stamps) <= 0)) + 1
        raise RecorderError(f"line {rows[k][0]}: timestamps do not increase", path=path, fix="sort the file by time")
    try:
        T = transforms_from_quaternions(data[:, 1:4], data[:, 4:8])
    except ValueError:
        raise RecorderError("a quaternion is zero", path=path, fix="repair the orientation columns") from None
    return PoseFile(path, "tum", T, stamps)


def associate_stamps(frame_stamps_ns: np.ndarray, pose_stamps_ns: np.ndarray, tolerance_ns: int) -> np.ndarray:
    """Nearest pose for each frame, or -1 when none is within ``tolerance_ns``.

    Args:
        frame_stamps_ns: ``(N,)`` increasing frame stamps.
        pose_stamps_ns: ``(M,)`` increasing pose stamps.

    Returns:
        ``(N,)`` int64 indices into the poses (``-1`` = no pose close enough).
    """
    frames = np.asarray(frame_stamps_ns, dtype=np.int64)
    poses = np.asarray(pose_stamps_ns, dtype=np.int64)
    if len(poses) == 0:
        return np.full(len(frames), -1, dtype=np.int64)
    right = np.clip(np.searchsorted(poses, frames), 0, len(poses) - 1)
    left = np.clip(right - 1, 0, len(poses) - 1)
    pick = np.where(np.abs(poses[left] - frames) <= np.abs(poses[right] - frames), left, right)
    return np.where(np.abs(poses[pick] - frames) <= tolerance_ns, pick, -1).astype(np.int64)


def seconds_to_ns(stamps_s: np.ndarray) -> np.ndarray:
    """Seconds (float) -> integer nanoseconds, rounded to the nearest ns."""
    return np.rint(np.asarray(stamps_s, dtype=np.float64) * 1e9).astype(np.int64)


def require_path(path: str | Path, *, what: str, fix: str, folder: bool = False) -> Path:
    """Return ``path`` if it exists as a file (or folder); else raise :class:`RecorderError`."""
    path = Path(path)
    ok = path.is_dir() if folder else path.is_file()
    if not ok:
        problem = f"{what} not found" if not path.exists() else f"{what} is not a {'folder' if folder else 'file'}"
        raise RecorderError(problem, path=path, fix=fix)
    return path


def interpolate_planar(stamps_ns: np.ndarray, poses: np.ndarray, query_ns: np.ndarray, max_gap_ns: int) -> np.ndarray:
    """Planar poses at ``query_ns`` by linear interpolation (yaw along the shorter arc).

    Args:
        stamps_ns: ``(M,)`` increasing stamps of ``poses``.
        poses: ``(M, 3)`` planar poses.
        query_ns: ``(N,)`` stamps to interpolate at.
        max_gap_ns: a query between two poses more than this far apart, or before the first /
            after the last pose by more than this, gets a NaN row (a query outside the poses but
            within ``max_gap_ns`` takes the nearest pose).

    Returns:
        ``(N, 3)`` poses, NaN where no pose is close enough.
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    query = np.asarray(query_ns, dtype=np.int64)
    out = np.full((len(query), 3), np.nan)
    if len(stamps) == 0:
        return out
    hi = np.clip(np.searchsorted(stamps, query), 1, max(len(stamps) - 1, 1))
    lo = hi - 1
    if len(stamps) == 1:
        near = np.abs(stamps[0] - query) <= max_gap_ns
        out[near] = poses[0]
        return out
    t0, t1 = stamps[lo], stamps[hi]
    w = np.clip((query - t0) / np.maximum(t1 - t0, 1), 0.0, 1.0)
    dyaw = wrap_angles(poses[hi, 2] - poses[lo, 2])
    interp = np.stack(
        [
            poses[lo, 0] + w * (poses[hi, 0] - poses[lo, 0]),
            poses[lo, 1] + w * (poses[hi, 1] - poses[lo, 1]),
            wrap_angles(poses[lo, 2] + w * dyaw),
        ],
        axis=1,
    )
    inside = (query >= t0) & (query <= t1) & (t1 - t0 <= max_gap_ns)
    nearest = np.where(np.abs(query - t0) <= np.abs(t1 - query), lo, hi)
    distance = np.abs(stamps[nearest] - query)
    outside = (query < stamps[0]) | (query > stamps[-1])
    close = (distance == 0) | (outside & (distance <= max_gap_ns))
    out[close] = poses[nearest[close]]
    out[inside] = interp[inside]
    return out


# ---------------------------------------------------------------------------------------------
# Images and calibration
# ---------------------------------------------------------------------------------------------


def read_image(path: Path) -> np.ndarray:
    """Read an image file as ``(H, W)`` uint8 grey or ``(H, W, 3)`` uint8 RGB.

    16-bit images are scaled to 8 bits; 4-channel images lose alpha. Raises
    :class:`RecorderError` naming the file when it cannot be decoded.
    """
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise RecorderError("cannot read the image (missing, unreadable or not an image)", path=path, fix="check the file")
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    elif image.dtype != np.uint8:
        raise RecorderError(f"unsupported image depth {image.dtype}", path=path, fix="use 8- or 16-bit images")
    if image.ndim == 3:
        if image.shape[2] == 1:
            image = image[:, :, 0]
        else:
            image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGB if image.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    return image


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pgm", ".ppm", ".bmp", ".tif", ".tiff")


def list_images(folder: Path, *, what: str) -> list[Path]:
    """Image files of ``folder`` sorted by name; :class:`RecorderError` if the folder is missing or empty."""
    folder = require_path(folder, what=what, fix="check the path", folder=True)
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    if not files:
        raise RecorderError(f"{what} holds no images ({', '.join(IMAGE_SUFFIXES)})", path=folder, fix="check the path")
    return files


def calibration_from_projections(P_left: np.ndarray, P_right: np.ndarray, width_px: int, height_px: int) -> StereoCalibration:
    """Rectified stereo calibration from two ``(3, 4)`` projection matrices (KITTI ``P0/P1``, ROS ``P``).

    ``baseline_m = (P_left[0, 3] - P_right[0, 3]) / fx`` (KITTI's P2/P3 carry an offset on both).
    """
    P_left = np.asarray(P_left, dtype=np.float64).reshape(3, 4)
    P_right = np.asarray(P_right, dtype=np.float64).reshape(3, 4)
    fx = float(P_left[0, 0])
    return StereoCalibration(
        width_px=int(width_px),
        height_px=int(height_px),
        fx_px=fx,
        fy_px=float(P_left[1, 1]),
        cx_px=float(P_left[0, 2]),
        cy_px=float(P_left[1, 2]),
        baseline_m=float((P_left[0, 3] - P_right[0, 3]) / fx),
    )


# ---------------------------------------------------------------------------------------------
# Writing: one loop for every recorder
# ---------------------------------------------------------------------------------------------

ImageFormat = Literal["png", "jpeg", "raw"]


@dataclass(frozen=True)
class SourceFrame:
    """One frame of a source dataset, images loaded on demand.

    ``left``/``right`` return ``(H, W)`` or ``(H, W, 3)`` uint8 arrays (they may run in a worker
    thread); ``odom``/``ground_truth`` are planar poses or ``None``.
    """

    stamp_ns: int
    left: Callable[[], np.ndarray] | None = None
    right: Callable[[], np.ndarray] | None = None
    odom: Pose2D | None = None
    ground_truth: Pose2D | None = None


@dataclass(frozen=True)
class LogHeader:
    """Per-log arguments of the writer."""

    dataset: str
    recorder: str
    nominal_rate_hz: float
    config: dict
    calibration: StereoCalibration | None = None
    odometry_information: np.ndarray | None = None
    image_format: ImageFormat = "png"
    jpeg_quality: int = 95
    warnings: dict[str, int] | None = None  # counts of what the recorder accepted with a warning


def make_frames(
    stamps_ns: np.ndarray,
    *,
    left: Sequence[Callable[[], np.ndarray]] | None = None,
    right: Sequence[Callable[[], np.ndarray]] | None = None,
    odometry: np.ndarray | None = None,
    ground_truth: np.ndarray | None = None,
) -> list[SourceFrame]:
    """Zip per-frame arrays into :class:`SourceFrame` records.

    Args:
        stamps_ns: ``(N,)`` frame stamps.
        left, right: ``N`` image loaders each, or ``None``.
        odometry: ``(N, 3)`` planar odometry, or ``None``.
        ground_truth: ``(N, 3)`` planar ground truth, NaN rows where a frame has none, or ``None``.
    """
    odom = poses_to_records(odometry) if odometry is not None else None
    truth = poses_to_records(ground_truth) if ground_truth is not None else None
    return [
        SourceFrame(
            int(stamp),
            left=left[i] if left is not None else None,
            right=right[i] if right is not None else None,
            odom=odom[i] if odom is not None else None,
            ground_truth=truth[i] if truth is not None and all(map(math.isfinite, truth[i])) else None,
        )
        for i, stamp in enumerate(np.asarray(stamps_ns, dtype=np.int64))
    ]


def options_config(options: Any, **extra: Any) -> dict:
    """A recorder's options dataclass as JSON-ready values (paths as strings), plus ``extra``."""
    from dataclasses import asdict

    values = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(options).items()}
    return {**values, **{k: (str(v) if isinstance(v, Path) else v) for k, v in extra.items()}}


def image_loaders(paths: Sequence[Path]) -> list[Callable[[], np.ndarray]]:
    """One :func:`read_image` loader per path."""
    return [lambda p=p: read_image(p) for p in paths]


def nominal_rate_hz(stamps_ns: np.ndarray, default: float = 10.0) -> float:
    """``1 / median frame period`` of ``(N,)`` stamps, or ``default`` with fewer than 2 frames."""
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    if len(stamps) < 2:
        return default
    period = float(np.median(np.diff(stamps)))
    return 1e9 / period if period > 0 else default


def vo_hook(enabled: bool, calibration: StereoCalibration | None) -> Callable[[np.ndarray | None, np.ndarray | None], Pose2D] | None:
    """The ``--vo`` odometry hook of :func:`write_log` (stereo VO on the loaded images), or ``None``."""
    if not enabled:
        return None
    from lcv_replay.vo.log_vo import ImageOdometry

    return ImageOdometry(calibration)


def write_log(
    out_path: str | Path,
    header: LogHeader,
    frames: Sequence[SourceFrame],
    *,
    candidates: Sequence[LoopCandidate] = (),
    true_loops: Iterable[tuple[int, int]] = (),
    force: bool = False,
    progress: ProgressCallback | None = None,
    started: float | None = None,
    prefetch: int = 4,
    image_odometry: Callable[[np.ndarray | None, np.ndarray | None], Pose2D] | None = None,
    live: bool = False,
) -> RecordStats:
    """Write ``frames`` (and candidates/labels at their query frames) through the one log writer.

    With ``live`` the log is written at ``out_path`` itself, one flushed chunk per frame, for
    ``lcv-replay LOG --follow`` (no atomic rename; see :class:`lcv_replay.log.writer.LogWriter`).

    Images are loaded ``prefetch`` frames ahead on a small thread pool (decoding and rectifying in
    OpenCV release the GIL), while the writer encodes in this thread.

    ``image_odometry(left, right)``, when given, computes each frame's odometry from its loaded
    images, in frame order (``--vo``: :class:`lcv_replay.vo.log_vo.ImageOdometry`), instead of
    ``frame.odom``.

    A stop request (:func:`lcv_replay.shutdown.stop_requested`: Ctrl-C or SIGTERM) ends the loop
    after the current frame and closes a valid, shorter log (the candidates and labels of the
    written frames included); before the first frame it raises
    :class:`~lcv_replay.shutdown.Interrupted` and writes nothing.
    """
    from concurrent.futures import ThreadPoolExecutor

    from lcv_replay.log.writer import LogWriter

    started = time.perf_counter() if started is None else started
    n = len(frames)
    by_query: dict[int, list[LoopCandidate]] = {}
    for cand in candidates:
        by_query.setdefault(cand.query_frame, []).append(cand)
    labels_by_query: dict[int, list[tuple[int, int]]] = {}
    for pair in sorted(set(true_loops)):
        labels_by_query.setdefault(pair[0], []).append(pair)

    def load(frame: SourceFrame) -> tuple[np.ndarray | None, np.ndarray | None]:
        return (frame.left() if frame.left else None, frame.right() if frame.right else None)

    has_images = any(f.left is not None for f in frames[:1])
    with contextlib.ExitStack() as stack:
        writer = stack.enter_context(
            LogWriter(
                out_path,
                force=force,
                dataset=header.dataset,
                recorder=header.recorder,
                nominal_rate_hz=header.nominal_rate_hz,
                recorder_config=header.config,
                image_format=header.image_format,
                jpeg_quality=header.jpeg_quality,
                odometry_information=header.odometry_information,
                recorder_warnings=header.warnings,
                live=live,
            )
        )
        pool = stack.enter_context(ThreadPoolExecutor(max_workers=2)) if has_images else None
        pending: dict[int, Any] = {}
        if header.calibration is not None and n:
            writer.write_calibration(header.calibration, frames[0].stamp_ns)
        if live:  # a follower learns what the log carries from its first chunk
            if by_query:
                writer.declare_candidates()
            if labels_by_query:
                writer.declare_labels()
            if any(f.ground_truth is not None for f in frames):
                writer.declare_ground_truth()
        written = 0
        for i, frame in enumerate(frames):
            if stop_requested():
                if i == 0:
                    raise_if_stopped()
                break
            if pool is not None:
                for k in range(i, min(n, i + prefetch + 1)):
                    if k not in pending:
                        pending[k] = pool.submit(load, frames[k])
                left, right = pending.pop(i).result()
            else:
                left, right = None, None
            odom = frame.odom if image_odometry is None else image_odometry(left, right)
            writer.write_frame(i, frame.stamp_ns, left=left, right=right, odom=odom, ground_truth=frame.ground_truth)
            for cand in by_query.get(i, ()):
                writer.write_loop_candidate(cand, frame.stamp_ns)
            for query, match in labels_by_query.get(i, ()):
                writer.write_true_loop(query, match, frame.stamp_ns)
            writer.flush()  # live: the frame is complete, a follower can read it now
            written = i + 1
            if progress is not None and (has_images or i % 256 == 0 or i == n - 1):
                progress(i + 1, n)
    out_path = Path(out_path)
    return RecordStats(
        path=out_path,
        frames=written,
        candidates=sum(len(by_query.get(i, ())) for i in range(written)),
        true_loops=sum(len(labels_by_query.get(i, ())) for i in range(written)),
        size_bytes=out_path.stat().st_size,
        elapsed_s=time.perf_counter() - started,
        has_images=has_images,
        has_odometry=image_odometry is not None or any(f.odom is not None for f in frames[:1]),
        has_ground_truth=any(f.ground_truth is not None for f in frames[:written]),
        frames_planned=n if written < n else None,
        warnings=dict(header.warnings or {}),
    )
