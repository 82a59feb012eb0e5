"""``lcv-replay record folder``: left/right image folders plus a planar odometry CSV into a log.

Inputs (each optional path defaults to a file in ``SOURCE`` when it exists)::

    SOURCE/left/            left images, sorted by file name (png, jpg, pgm, ...)   --left
    SOURCE/right/           right images with the same file names (optional)       --right
    SOURCE/odometry.csv     planar odometry                                          --odometry
    SOURCE/ground_truth.csv planar ground truth, same format                         --ground-truth
    SOURCE/calibration.yaml (or .yml / .json) rectified stereo calibration           --calibration

**Pose CSV** (odometry and ground truth): a header line ``timestamp_ns,x_m,y_m,yaw_rad`` then one row
per pose: integer nanoseconds, metres, radians; planar body convention (x forward, y left, yaw
counter-clockwise about +z), cumulative in the ``odom`` (or ``world``) frame.

**Calibration file** (YAML or JSON, read with OpenCV's FileStorage) of the *rectified* pair::

    fx: 718.856        fy: 718.856      # pixels
    cx: 607.1928       cy: 185.2157
    baseline_m: 0.5372                  # > 0; the right camera is at +baseline along left x
    width: 1241        height: 376      # optional; default: the first image's size
    distortion: [0, 0, 0, 0, 0]         # optional plumb-bob k1 k2 t1 t2 k3 (default zeros)

**Frame stamps** (``stamps``): ``names`` = the image file stems are integer nanosecond stamps (as
ROS and EuRoC exports are named); ``odometry`` = row ``k`` of the odometry CSV is image ``k`` (the
row count must equal the image count); ``rate`` = ``k / rate_hz``. ``auto`` picks ``names`` when
every stem is an integer of at least 10 digits, else ``odometry`` when the counts match, else
``rate`` when ``rate_hz`` is given. Odometry and ground truth are joined to the frame stamps by
linear interpolation (yaw on the shorter arc), refusing gaps over ``max_gap_ns``.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from lcv_replay.errors import RecorderError
from lcv_replay.records import StereoCalibration
from recorders.common import (
    ImageFormat,
    LogHeader,
    ProgressCallback,
    RecordStats,
    interpolate_planar,
    list_images,
    nominal_rate_hz,
    image_loaders,
    make_frames,
    options_config,
    read_image,
    require_path,
    vo_hook,
    write_log,
)

log = logging.getLogger(__name__)

StampSource = Literal["auto", "names", "odometry", "rate"]
_CSV_FIX = "pose CSV rows are 'timestamp_ns,x_m,y_m,yaw_rad' (integer ns, metres, radians)"
_CALIB_FIX = "the calibration file needs fx, fy, cx, cy and baseline_m (see 'lcv-replay record folder --help')"


@dataclass(frozen=True)
class FolderOptions:
    """Options of the folder recorder (see the module docstring for the formats).

    Attributes:
        left, right, odometry, ground_truth, calibration: paths; ``None`` = the default name in
            ``SOURCE`` if it exists (``left`` is required one way or the other).
        stamps: where the frame stamps come from.
        rate_hz: frame rate for ``stamps="rate"`` (and the nominal rate otherwise).
        max_gap_ns: largest gap between poses (or from a frame to a pose) bridged by interpolation;
            ``None`` = three median frame periods.
        vo: compute ``/odom`` with stereo visual odometry on the images (needs ``right`` and
            ``calibration``); an ``odometry.csv`` in ``SOURCE`` then only gives stamps.
    """

    left: Path | None = None
    right: Path | None = None
    odometry: Path | None = None
    ground_truth: Path | None = None
    calibration: Path | None = None
    stamps: StampSource = "auto"
    rate_hz: float | None = None
    max_gap_ns: int | None = None
    dataset: str | None = None
    image_format: ImageFormat = "png"
    jpeg_quality: int = 95
    vo: bool = False

    def __post_init__(self) -> None:
        if self.vo and self.odometry is not None:
            raise RecorderError("--vo and --odometry are exclusive", fix="drop one: --vo computes the odometry from the images")
        if self.stamps not in ("auto", "names", "odometry", "rate"):
            raise RecorderError(f"--stamps {self.stamps!r} is unknown", fix="use auto, names, odometry or rate")
        if self.rate_hz is not None and not self.rate_hz > 0:
            raise RecorderError(f"--rate-hz {self.rate_hz} must be positive", fix="pass e.g. --rate-hz 10")


def read_planar_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Pose CSV -> ``(M,)`` int64 stamps in ns and ``(M, 3)`` planar poses; stamps must increase."""
    path = require_path(path, what="pose CSV", fix=_CSV_FIX)
    stamps: list[int] = []
    poses: list[tuple[float, float, float]] = []
    for line_no, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        parts = [p.strip() for p in text.replace(";", ",").split(",")]
        if not stamps and not parts[0].lstrip("-").isdigit():
            continue  # the header
        try:
            if len(parts) != 4:
                raise ValueError
            stamps.append(int(parts[0]))
            poses.append((float(parts[1]), float(parts[2]), float(parts[3])))
        except ValueError:
            raise RecorderError(f"line {line_no}: expected 4 columns timestamp_ns,x_m,y_m,yaw_rad, got {text[:60]!r}", path=path, fix=_CSV_FIX) from None
        if not all(np.isfinite(poses[-1])):
            raise RecorderError(f"line {line_no}: NaN or inf in the pose", path=path, fix="repair or remove the row")
        if len(stamps) > 1 and stamps[-1] <= stamps[-2]:
            raise RecorderError(f"line {line_no}: timestamp {stamps[-1]} does not increase", path=path, fix="sort the rows by time")
    if not stamps:
        raise RecorderError("the pose CSV has no rows", path=path, fix=_CSV_FIX)
    return np.asarray(stamps, dtype=np.int64), np.asarray(poses, dtype=np.float64)


def read_calibration_file(path: Path, image_size: tuple[int, int]) -> StereoCalibration:
    """Read the YAML/JSON calibration (module docstring); ``image_size`` = ``(width, height)`` default."""
    path = require_path(path, what="calibration file", fix=_CALIB_FIX)
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            raise RecorderError(f"invalid JSON ({exc.msg} at line {exc.lineno})", path=path, fix=_CALIB_FIX) from None
        if not isinstance(data, dict):
            raise RecorderError("the JSON must be an object", path=path, fix=_CALIB_FIX)
    else:
        data = _read_yaml_numbers(path)
    try:
        distortion = tuple(float(v) for v in data.get("distortion", (0.0,) * 5))
        calib = StereoCalibration(
            width_px=int(data.get("width", image_size[0])),
            height_px=int(data.get("height", image_size[1])),
            fx_px=float(data["fx"]),
            fy_px=float(data["fy"]),
            cx_px=float(data["cx"]),
            cy_px=float(data["cy"]),
            baseline_m=float(data["baseline_m"]),
            distortion=distortion,
        )
    except KeyError as exc:
        raise RecorderError(f"missing key {exc.args[0]!r}", path=path, fix=_CALIB_FIX) from None
    except (TypeError, ValueError) as exc:
        raise RecorderError(f"invalid value ({exc})", path=path, fix=_CALIB_FIX) from None
    if not (calib.fx_px > 0 and calib.fy_px > 0 and calib.baseline_m > 0):
        raise RecorderError("fx, fy and baseline_m must be positive", path=path, fix=_CALIB_FIX)
    if len(distortion) != 5:
        raise RecorderError(f"distortion has {len(distortion)} values", path=path, fix="give 5 plumb-bob coefficients k1 k2 t1 t2 k3")
    if (calib.width_px, calib.height_px) != tuple(image_size):
        raise RecorderError(f"calibration is for {calib.width_px}x{calib.height_px} images, the images are {image_size[0]}x{image_size[1]}", path=path, fix="use the calibration of these images")
    return calib


def _read_yaml_numbers(path: Path) -> dict:
    import cv2

    try:
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise RecorderError(f"cannot parse the YAML ({str(exc).strip().splitlines()[-1]})", path=path, fix=_CALIB_FIX) from None
    data: dict = {}
    for key in ("fx", "fy", "cx", "cy", "baseline_m", "width", "height"):
        node = storage.getNode(key)
        if not node.empty():
            data[key] = node.real()
    node = storage.getNode("distortion")
    if not node.empty():
        data["distortion"] = [node.at(i).real() for i in range(node.size())]
    storage.release()
    return data


def _default(source: Path | None, given: Path | None, *names: str) -> Path | None:
    if given is not None:
        return Path(given)
    if source is None:
        return None
    return next((source / n for n in names if (source / n).exists()), None)


def record_folder(
    source: str | Path | None,
    out_path: str | Path,
    options: FolderOptions = FolderOptions(),
    *,
    force: bool = False,
    progress: ProgressCallback | None = None,
    live: bool = False,
) -> RecordStats:
    """Record image folders and pose CSVs into an lcv-replay log at ``out_path`` (atomically, or chunk by chunk with ``live``)."""
    from lcv_replay.fileio import check_output_path

    started = time.perf_counter()
    out_path = check_output_path(out_path, force=force)
    src = None if source is None else require_path(source, what="source folder", fix="pass the folder holding left/, right/ and odometry.csv", folder=True)
    left_dir = _default(src, options.left, "left")
    if left_dir is None:
        raise RecorderError("no left image folder", path=src, fix="pass --left DIR (or put the images in SOURCE/left)")
    right_dir = _default(src, options.right, "right")
    odom_path = _default(src, options.odometry, "odometry.csv")
    gt_path = _default(src, options.ground_truth, "ground_truth.csv")
    calib_path = _default(src, options.calibration, "calibration.yaml", "calibration.yml", "calibration.json")

    left = list_images(left_dir, what="left image folder")
    right = None
    if right_dir is not None:
        right = list_images(right_dir, what="right image folder")
        if [p.name for p in right] != [p.name for p in left]:
            names = {p.name for p in right}
            odd = next((p.name for p in left if p.name not in names), None) or next(p.name for p in right if p.name not in {q.name for q in left})
            raise RecorderError(f"left and right folders differ ({len(left)} vs {len(right)} images; e.g. {odd} has no partner)", path=right_dir, fix="the two folders must hold the same file names")
    odom = read_planar_csv(odom_path) if odom_path is not None else None
    gt = read_planar_csv(gt_path) if gt_path is not None else None
    stamps, how = _frame_stamps(left, odom, options, left_dir)
    if options.vo:
        if right is None:
            raise RecorderError("stereo is required: --vo needs right images", path=src or left_dir, fix="pass --right DIR (or put the images in SOURCE/right)")
        if calib_path is None:
            raise RecorderError("--vo needs the stereo calibration", path=src or left_dir, fix="pass --calibration FILE (fx, fy, cx, cy, baseline_m)")
        if odom is not None:
            log.info("--vo: %s gives the frame stamps only; the odometry comes from stereo VO", odom_path)
        odom = None
    elif odom is None:
        log.warning("no odometry CSV: the log carries images%s only", " and ground truth" if gt else "")

    period = float(np.median(np.diff(stamps))) if len(stamps) > 1 else 1e8
    max_gap = options.max_gap_ns if options.max_gap_ns is not None else int(3 * period)
    odom_poses = None
    if odom is not None:
        odom_poses = odom[1] if how == "odometry" else interpolate_planar(odom[0], odom[1], stamps, max_gap)
        bad = np.flatnonzero(~np.isfinite(odom_poses).all(axis=1))
        if len(bad):
            raise RecorderError(f"{len(bad)} frames have no odometry within {max_gap} ns (first: frame {bad[0]}, {left[bad[0]].name} at {stamps[bad[0]]} ns)", path=odom_path, fix="the odometry must cover every image (or raise --max-gap-ns)")
    gt_poses = interpolate_planar(gt[0], gt[1], stamps, max_gap) if gt is not None else None

    first = read_image(left[0])
    calibration = read_calibration_file(calib_path, (first.shape[1], first.shape[0])) if calib_path is not None else None
    if calibration is None and right is not None:
        log.warning("no calibration file: stereo VO cannot run on this log (pass --calibration)")

    frames = make_frames(
        stamps,
        left=image_loaders(left),
        right=image_loaders(right) if right is not None else None,
        odometry=odom_poses,
        ground_truth=gt_poses,
    )
    config = options_config(
        options, left=left_dir, right=right_dir, odometry=odom_path, ground_truth=gt_path, calibration=calib_path, stamps_from=how
    )
    header = LogHeader(
        dataset=options.dataset or (src.name if src is not None else Path(left_dir).resolve().parent.name),
        recorder="folder",
        nominal_rate_hz=options.rate_hz or nominal_rate_hz(stamps),
        config=config,
        calibration=calibration,
        image_format=options.image_format,
        jpeg_quality=options.jpeg_quality,
    )
    return write_log(out_path, header, frames, force=force, progress=progress, started=started, live=live, image_odometry=vo_hook(options.vo, calibration))


def _frame_stamps(left: list[Path], odom: tuple[np.ndarray, np.ndarray] | None, options: FolderOptions, left_dir: Path) -> tuple[np.ndarray, str]:
    """``(N,)`` frame stamps and where they came from (``names``, ``odometry`` or ``rate``)."""
    how = options.stamps
    stems_are_stamps = all(p.stem.isdigit() and len(p.stem) >= 10 for p in left)
    if how == "auto":
        if stems_are_stamps:
            how = "names"
        elif odom is not None and len(odom[0]) == len(left):
            how = "odometry"
        elif options.rate_hz is not None:
            how = "rate"
        else:
            raise RecorderError(
                f"cannot tell the frame stamps: file names are not nanosecond stamps and the odometry has {len(odom[0]) if odom else 0} rows for {len(left)} images",
                path=left_dir,
                fix="name the images by their ns stamp, give one odometry row per image, or pass --rate-hz",
            )
    if how == "names":
        if not all(p.stem.isdigit() for p in left):
            bad = next(p.name for p in left if not p.stem.isdigit())
            raise RecorderError(f"{bad} is not named by an integer nanosecond stamp", path=left_dir, fix="use --stamps odometry or --stamps rate")
        stamps = np.array([int(p.stem) for p in left], dtype=np.int64)
    elif how == "odometry":
        if odom is None or len(odom[0]) != len(left):
            raise RecorderError(f"--stamps odometry needs one odometry row per image ({len(left)} images, {len(odom[0]) if odom else 0} rows)", path=left_dir, fix="give one row per image or use --stamps rate")
        stamps = odom[0].copy()
    else:
        if options.rate_hz is None:
            raise RecorderError("--stamps rate needs --rate-hz", path=left_dir, fix="pass --rate-hz")
        stamps = np.rint(np.arange(len(left)) * (1e9 / options.rate_hz)).astype(np.int64)
    if np.any(np.diff(stamps) <= 0):
        raise RecorderError("frame stamps do not increase with the file-name order", path=left_dir, fix="name the files so that sorting them sorts them by time")
    return stamps, how
