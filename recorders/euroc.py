"""``lcv-replay record euroc``: the EuRoC / ASL layout into a log, with stereo rectification.

Layout (``SOURCE`` is the sequence folder holding ``mav0``, or ``mav0`` itself)::

    mav0/cam0/data.csv                      "#timestamp [ns],filename" per image
    mav0/cam0/data/<timestamp>.png          left images (752x480 grey in EuRoC)
    mav0/cam0/sensor.yaml                   T_BS (camera in body/IMU frame), intrinsics
                                            [fu, fv, cu, cv], radial-tangential distortion
    mav0/cam1/...                           the right camera, same layout
    mav0/state_groundtruth_estimate0/data.csv   optional: timestamp, p_RS_R xyz, q_RS wxyz, ...

**Images are rectified** (the default): EuRoC images are distorted and the two cameras are not
row-aligned, while the replay's stereo VO needs rectified pairs. The recorder computes
``cv2.stereoRectify`` from both ``sensor.yaml`` files (``CALIB_ZERO_DISPARITY``, ``alpha = 0``: only
valid pixels, same size as the input), remaps every image, and writes the rectified calibration:
``fx, fy, cx, cy`` of the new left projection ``P1`` and ``baseline_m = -P2[0, 3] / P2[0, 0]``, no
distortion. ``--no-rectify`` writes the raw images with the left camera's intrinsics and
plumb-bob distortion ``(k1, k2, p1, p2, 0)`` and the camera-centre distance as the baseline (for
viewing; not for the VO).

**Frames** are the left images that have a right image within ``stereo_tolerance_ns`` (EuRoC's are
hardware-synchronised: equal stamps); others are dropped with a warning. The stamp is the image
timestamp.

**Body and ground truth.** The planar body is the (rectified) left camera projected on the ground
plane: x = the optical axis, y = left, yaw about the world's up axis, position = the camera
centre. Ground truth ``T_world_imu`` (a z-up world) becomes ``T_world_imu · T_imu_cam0 · R1ᵀ``,
then :func:`recorders.common.project_to_planar` with the camera-to-body rotation on the right only.
Ground truth is joined to the frames by nearest stamp within ``ground_truth_tolerance_ns``.

**Odometry** (``--odometry FILE``): a TUM or KITTI file of the left camera in the frame of its first
pose (camera-centric VO output), projected as for KITTI. TUM stamps are seconds (EuRoC's
nanosecond stamps / 1e9). Without it the log carries images and ground truth only.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from lcv_replay.errors import RecorderError
from lcv_replay.records import StereoCalibration
from recorders.common import (
    R_BODY_CAMERA,
    R_BODY_IDENTITY,
    ImageFormat,
    LogHeader,
    PoseFormat,
    ProgressCallback,
    RecordStats,
    associate_stamps,
    nominal_rate_hz,
    make_frames,
    options_config,
    project_to_planar,
    read_image,
    read_pose_file,
    require_path,
    seconds_to_ns,
    transforms_from_quaternions,
    vo_hook,
    write_log,
)

log = logging.getLogger(__name__)

_LAYOUT_FIX = "point at a EuRoC sequence folder holding mav0/cam0, mav0/cam1 (data.csv, data/, sensor.yaml)"


@dataclass(frozen=True)
class CameraSensor:
    """One ``sensor.yaml`` of the ASL layout.

    Attributes:
        T_body_camera: ``(4, 4)`` pose of the camera in the body (IMU) frame (``T_BS``).
        K: ``(3, 3)`` intrinsics from ``[fu, fv, cu, cv]``.
        distortion: radial-tangential ``(k1, k2, p1, p2)``.
    """

    path: Path
    T_body_camera: np.ndarray
    width_px: int
    height_px: int
    K: np.ndarray
    distortion: np.ndarray
    rate_hz: float


@dataclass(frozen=True)
class Rectification:
    """Stereo rectification of a EuRoC camera pair (``cv2.stereoRectify`` outputs, see the module doc)."""

    R1: np.ndarray  # (3, 3) rotation: raw left camera -> rectified left camera
    R2: np.ndarray
    P1: np.ndarray  # (3, 4) rectified projections
    P2: np.ndarray
    left_maps: tuple[np.ndarray, np.ndarray]
    right_maps: tuple[np.ndarray, np.ndarray]

    def calibration(self, width_px: int, height_px: int) -> StereoCalibration:
        fx = float(self.P1[0, 0])
        return StereoCalibration(
            width_px=width_px, height_px=height_px, fx_px=fx, fy_px=float(self.P1[1, 1]),
            cx_px=float(self.P1[0, 2]), cy_px=float(self.P1[1, 2]), baseline_m=float(-self.P2[0, 3] / self.P2[0, 0]),
        )


def read_camera_yaml(path: Path) -> CameraSensor:
    """Parse an ASL ``sensor.yaml`` (OpenCV-YAML, ``%YAML:1.0``) with ``cv2.FileStorage``."""
    import cv2

    fix = "use the sensor.yaml of the EuRoC sequence (T_BS, resolution, intrinsics, distortion_coefficients)"
    path = require_path(path, what="camera sensor.yaml", fix=fix)
    try:
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise RecorderError(f"cannot parse the YAML ({str(exc).strip().splitlines()[-1]})", path=path, fix=fix) from None

    def numbers(key: str, count: int) -> list[float]:
        node = storage.getNode(key)
        if key == "T_BS":
            node = node.getNode("data")
        if node.empty() or not node.isSeq() or node.size() != count:
            raise RecorderError(f"'{key}' must list {count} numbers", path=path, fix=fix)
        return [node.at(i).real() for i in range(count)]

    model = storage.getNode("distortion_model").string() or "radial-tangential"
    if model not in ("radial-tangential", "radtan", "plumb_bob"):
        raise RecorderError(f"distortion model {model!r} is not supported", path=path, fix="lcv-replay rectifies radial-tangential (pinhole) cameras only")
    cam_model = storage.getNode("camera_model").string() or "pinhole"
    if cam_model != "pinhole":
        raise RecorderError(f"camera model {cam_model!r} is not supported", path=path, fix="lcv-replay rectifies pinhole cameras only")
    T = np.array(numbers("T_BS", 16)).reshape(4, 4)
    width, height = (int(v) for v in numbers("resolution", 2))
    fu, fv, cu, cv_ = numbers("intrinsics", 4)
    distortion = np.array(numbers("distortion_coefficients", 4))
    rate = storage.getNode("rate_hz").real() or 20.0
    storage.release()
    K = np.array([[fu, 0.0, cu], [0.0, fv, cv_], [0.0, 0.0, 1.0]])
    return CameraSensor(path, T, width, height, K, distortion, float(rate))


def rectify_pair(left: CameraSensor, right: CameraSensor) -> Rectification:
    """``cv2.stereoRectify`` + ``initUndistortRectifyMap`` for a pair sharing one body frame."""
    import cv2

    if (left.width_px, left.height_px) != (right.width_px, right.height_px):
        raise RecorderError("the two cameras have different resolutions", path=right.path, fix="both cameras must have the same resolution")
    T_right_left = np.linalg.inv(right.T_body_camera) @ left.T_body_camera
    size = (left.width_px, left.height_px)
    R1, R2, P1, P2, _Q, _roi1, _roi2 = cv2.stereoRectify(
        left.K, left.distortion, right.K, right.distortion, size,
        T_right_left[:3, :3].copy(), T_right_left[:3, 3].reshape(3, 1).copy(), flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.0,
    )
    left_maps = cv2.initUndistortRectifyMap(left.K, left.distortion, R1, P1, size, cv2.CV_32FC1)
    right_maps = cv2.initUndistortRectifyMap(right.K, right.distortion, R2, P2, size, cv2.CV_32FC1)
    return Rectification(R1, R2, P1, P2, left_maps, right_maps)


def read_image_list(csv_path: Path) -> tuple[np.ndarray, list[str]]:
    """ASL ``data.csv`` -> ``(N,)`` int64 stamps in ns and ``N`` file names."""
    fix = "data.csv lines look like '1403636579763555584,1403636579763555584.png'"
    require_path(csv_path, what="camera data.csv", fix=fix)
    stamps: list[int] = []
    names: list[str] = []
    for line_no, line in enumerate(csv_path.read_text(encoding="utf-8", errors="replace").splitlines(), start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        parts = [p.strip() for p in text.split(",")]
        try:
            stamps.append(int(parts[0]))
            names.append(parts[1])
        except (ValueError, IndexError):
            raise RecorderError(f"line {line_no}: expected 'timestamp_ns,filename'", path=csv_path, fix=fix) from None
    if not stamps:
        raise RecorderError("data.csv lists no images", path=csv_path, fix=fix)
    order = np.argsort(stamps, kind="stable")
    return np.asarray(stamps, dtype=np.int64)[order], [names[k] for k in order]


def read_ground_truth_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``state_groundtruth_estimate0/data.csv`` -> ``(M,)`` int64 stamps in ns and ``(M, 4, 4)`` ``T_world_imu``.

    Stamps are parsed as integers (a float64 cannot hold 19-digit nanosecond stamps exactly).
    """
    fix = "ground-truth rows are 'timestamp_ns, px, py, pz, qw, qx, qy, qz, ...'"
    path = require_path(path, what="ground-truth data.csv", fix=fix)
    stamps: list[int] = []
    values: list[list[float]] = []
    for line_no, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        parts = [p.strip() for p in text.split(",")]
        try:
            if len(parts) < 8:
                raise ValueError
            stamps.append(int(parts[0]))
            values.append([float(v) for v in parts[1:8]])
        except ValueError:
            raise RecorderError(f"line {line_no}: expected 'timestamp_ns' and at least 7 numbers", path=path, fix=fix) from None
    if not stamps:
        raise RecorderError("no ground-truth rows", path=path, fix=fix)
    data = np.asarray(values, dtype=np.float64)
    if not np.isfinite(data).all():
        raise RecorderError("NaN or inf in the ground truth", path=path, fix="repair the file")
    try:
        T = transforms_from_quaternions(data[:, 0:3], data[:, [4, 5, 6, 3]])  # q_RS_w first in ASL
    except ValueError:
        raise RecorderError("a ground-truth quaternion is zero", path=path, fix="repair the file") from None
    order = np.argsort(np.asarray(stamps, dtype=np.int64), kind="stable")
    return np.asarray(stamps, dtype=np.int64)[order], T[order]


@dataclass(frozen=True)
class EurocOptions:
    """Options of the EuRoC recorder (see the module docstring).

    Attributes:
        rectify: rectify the images and write the rectified calibration (default).
        odometry, odometry_format: camera-centric odometry file (TUM or KITTI), optional.
        ground_truth: use ``state_groundtruth_estimate0`` when present.
        stereo_tolerance_ns: left/right stamps closer than this form a pair.
        ground_truth_tolerance_ns: a frame takes the nearest ground-truth row within this.
        odometry_tolerance_s: TUM odometry stamps must be this close to the frames.
        start_frame, max_frames: the slice of (paired) frames to record.
        vo: compute ``/odom`` with stereo visual odometry on the rectified images (:mod:`lcv_replay.vo`).
    """

    rectify: bool = True
    odometry: Path | None = None
    odometry_format: PoseFormat = "auto"
    ground_truth: bool = True
    stereo_tolerance_ns: int = 1_000_000
    ground_truth_tolerance_ns: int = 5_000_000
    odometry_tolerance_s: float = 0.005
    start_frame: int = 0
    max_frames: int | None = None
    image_format: ImageFormat = "png"
    jpeg_quality: int = 95
    vo: bool = False

    def __post_init__(self) -> None:
        if self.vo and self.odometry is not None:
            raise RecorderError("--vo and --odometry are exclusive", fix="drop one: --vo computes the odometry from the images")
        if self.vo and not self.rectify:
            raise RecorderError("--vo needs rectified stereo pairs", fix="drop --no-rectify")
        if self.start_frame < 0 or (self.max_frames is not None and self.max_frames < 1):
            raise RecorderError("--start-frame must be >= 0 and --max-frames >= 1", fix="pass valid frame counts")


@dataclass(frozen=True)
class EurocSequence:
    """A EuRoC sequence resolved and checked (images not loaded)."""

    mav0: Path
    name: str
    stamps_ns: np.ndarray  # (N,)
    left_images: tuple[Path, ...]
    right_images: tuple[Path, ...]
    calibration: StereoCalibration
    rectification: Rectification | None
    odometry: np.ndarray | None  # (N, 3)
    ground_truth: np.ndarray | None  # (N, 3), NaN rows where no ground truth is close enough
    dropped_unpaired: int


def resolve_mav0(source: Path) -> Path:
    source = require_path(source, what="EuRoC source folder", fix=_LAYOUT_FIX, folder=True)
    for folder in (source / "mav0", source):
        if (folder / "cam0").is_dir():
            return folder
    raise RecorderError("not a EuRoC sequence (no mav0/cam0 folder)", path=source, fix=_LAYOUT_FIX)


def pair_stamps(left_ns: np.ndarray, right_ns: np.ndarray, tolerance_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices ``(left_idx, right_idx)`` of stereo pairs: each left image's nearest right image
    within ``tolerance_ns``, each right image used at most once."""
    nearest = associate_stamps(left_ns, right_ns, tolerance_ns)
    keep = nearest >= 0
    left_idx, right_idx = np.flatnonzero(keep), nearest[keep]
    _, first = np.unique(right_idx, return_index=True)
    first.sort()
    return left_idx[first], right_idx[first]


def load_euroc_sequence(source: str | Path, options: EurocOptions = EurocOptions()) -> EurocSequence:
    """Resolve, read and check a EuRoC sequence; compute the rectification; no image is loaded."""
    mav0 = resolve_mav0(Path(source))
    name = mav0.parent.name if mav0.name == "mav0" else mav0.name
    cams = []
    for cam in ("cam0", "cam1"):
        folder = require_path(mav0 / cam, what=f"camera folder {cam}", fix=_LAYOUT_FIX, folder=True)
        stamps, names = read_image_list(folder / "data.csv")
        cams.append((folder, stamps, names, read_camera_yaml(folder / "sensor.yaml")))
    (left_dir, left_ns, left_names, left_cam), (right_dir, right_ns, right_names, right_cam) = cams
    li, ri = pair_stamps(left_ns, right_ns, options.stereo_tolerance_ns)
    dropped = len(left_ns) + len(right_ns) - 2 * len(li)
    if len(li) == 0:
        raise RecorderError("no left image has a right image within the stereo tolerance", path=mav0, fix="check cam0/cam1 data.csv stamps (or raise --stereo-tolerance-ns)")
    if dropped:
        log.warning("%s: dropped %d images without a stereo partner", mav0, dropped)
    first = options.start_frame
    if first >= len(li):
        raise RecorderError(f"--start-frame {first} is past the last frame {len(li) - 1}", path=mav0, fix="pass a smaller --start-frame")
    last = len(li) if options.max_frames is None else min(len(li), first + options.max_frames)
    li, ri = li[first:last], ri[first:last]
    stamps = left_ns[li]
    left_images = tuple(left_dir / "data" / left_names[k] for k in li)
    right_images = tuple(right_dir / "data" / right_names[k] for k in ri)
    for path in (left_images[0], right_images[0]):
        require_path(path, what="image listed in data.csv", fix="the data/ folder must hold every image that data.csv lists")

    if options.rectify:
        rect = rectify_pair(left_cam, right_cam)
        calibration = rect.calibration(left_cam.width_px, left_cam.height_px)
        R_cam0_sensor = rect.R1.T  # the rectified left camera in raw cam0 coordinates
    else:
        rect = None
        k1, k2, p1, p2 = (float(v) for v in left_cam.distortion)
        centre_distance = float(np.linalg.norm(left_cam.T_body_camera[:3, 3] - right_cam.T_body_camera[:3, 3]))
        calibration = StereoCalibration(
            left_cam.width_px, left_cam.height_px, float(left_cam.K[0, 0]), float(left_cam.K[1, 1]),
            float(left_cam.K[0, 2]), float(left_cam.K[1, 2]), centre_distance, (k1, k2, p1, p2, 0.0),
        )
        R_cam0_sensor = np.eye(3)

    ground_truth = None
    gt_csv = mav0 / "state_groundtruth_estimate0" / "data.csv"
    if options.ground_truth and gt_csv.is_file():
        gt_ns, T_world_imu = read_ground_truth_csv(gt_csv)
        T_imu_sensor = left_cam.T_body_camera.copy()
        T_imu_sensor[:3, :3] = T_imu_sensor[:3, :3] @ R_cam0_sensor
        planar = project_to_planar(T_world_imu @ T_imu_sensor, R_sensor_body=R_BODY_CAMERA.T, R_planar_world=R_BODY_IDENTITY)
        index = associate_stamps(stamps, gt_ns, options.ground_truth_tolerance_ns)
        ground_truth = np.where((index >= 0)[:, None], planar[np.maximum(index, 0)], np.nan)
        missing = int((index < 0).sum())
        if missing:
            log.warning("%s: %d of %d frames have no ground truth within %d ns", gt_csv, missing, len(stamps), options.ground_truth_tolerance_ns)
    elif options.ground_truth:
        log.info("%s not found: no ground truth", gt_csv)

    odometry = None
    if options.odometry is not None:
        poses = read_pose_file(Path(options.odometry), options.odometry_format)
        if poses.format == "kitti":
            if len(poses.T_world_sensor) != len(stamps):
                raise RecorderError(f"odometry has {len(poses.T_world_sensor)} poses but {len(stamps)} frames are recorded", path=options.odometry, fix="one KITTI line per recorded frame, or use a TUM file")
            T = poses.T_world_sensor
        else:
            index = associate_stamps(stamps, seconds_to_ns(poses.stamps_s), int(round(options.odometry_tolerance_s * 1e9)))
            missing = np.flatnonzero(index < 0)
            if len(missing):
                raise RecorderError(f"{len(missing)} of {len(stamps)} frames have no odometry pose within {options.odometry_tolerance_s} s (first: frame {missing[0]})", path=options.odometry, fix="TUM stamps are the image stamps in seconds")
            T = poses.T_world_sensor[index]
        odometry = project_to_planar(T)
    elif options.vo:
        log.info("odometry from stereo VO on the rectified pairs")
    else:
        log.warning("no --odometry given: the log carries images and ground truth only (estimate odometry with --vo or 'lcv-replay vo')")

    return EurocSequence(mav0, name, stamps, left_images, right_images, calibration, rect, odometry, ground_truth, dropped)


def _loader(path: Path, maps: tuple[np.ndarray, np.ndarray] | None) -> Callable[[], np.ndarray]:
    def load() -> np.ndarray:
        image = read_image(path)
        if maps is None:
            return image
        import cv2

        return cv2.remap(image, maps[0], maps[1], cv2.INTER_LINEAR)

    return load


def record_euroc(
    source: str | Path,
    out_path: str | Path,
    options: EurocOptions = EurocOptions(),
    *,
    force: bool = False,
    progress: ProgressCallback | None = None,
    live: bool = False,
) -> RecordStats:
    """Record a EuRoC sequence into an lcv-replay log at ``out_path`` (atomically, or chunk by chunk with ``live``)."""
    from lcv_replay.fileio import check_output_path

    started = time.perf_counter()
    out_path = check_output_path(out_path, force=force)
    seq = load_euroc_sequence(source, options)
    rect = seq.rectification
    frames = make_frames(
        seq.stamps_ns,
        left=[_loader(p, rect.left_maps if rect else None) for p in seq.left_images],
        right=[_loader(p, rect.right_maps if rect else None) for p in seq.right_images],
        odometry=seq.odometry,
        ground_truth=seq.ground_truth,
    )
    config = options_config(
        options,
        source=seq.mav0,
        dropped_unpaired_images=seq.dropped_unpaired,
        body="rectified left camera projected on the ground plane (x = optical axis, yaw about world z)",
    )
    header = LogHeader(
        dataset=f"euroc/{seq.name}",
        recorder="euroc",
        nominal_rate_hz=nominal_rate_hz(seq.stamps_ns, default=20.0),
        config=config,
        calibration=seq.calibration,
        image_format=options.image_format,
        jpeg_quality=options.jpeg_quality,
    )
    return write_log(out_path, header, frames, force=force, progress=progress, started=started, live=live, image_odometry=vo_hook(options.vo, seq.calibration))
