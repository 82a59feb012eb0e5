"""``lcv-replay record kitti``: the KITTI odometry layout into a log.

Layout (``SOURCE`` is either the sequence folder or the dataset root with ``--sequence SS``)::

    ROOT/sequences/SS/image_0/000000.png ...   left grey camera (image_2: left colour)
    ROOT/sequences/SS/image_1/000000.png ...   right grey camera (image_3: right colour)
    ROOT/sequences/SS/calib.txt                 "P0: 12 numbers" ... "P3: ..." (rectified 3x4)
    ROOT/sequences/SS/times.txt                 seconds since the sequence start, one per frame
    ROOT/poses/SS.txt                           optional ground truth, KITTI 3x4 format

* Frame ``i`` is image ``i``; its stamp is ``start_stamp_ns + times[i]`` in nanoseconds.
* Calibration: ``fx, fy, cx, cy`` from the left projection matrix; the baseline is
  ``(P_left[0, 3] - P_right[0, 3]) / fx`` (= ``-P1[0, 3] / fx`` for the grey pair).
* Odometry comes from ``--odometry FILE`` in KITTI pose format (one line per frame) or TUM format
  (``stamp tx ty tz qx qy qz qw``, matched to ``times.txt`` within ``stamp_tolerance_s``). Without
  it, the log carries images and ground truth only (``lcv-replay vo`` can add odometry).
* 3-D -> planar: KITTI poses are of the left camera (x right, y down, z forward) in the frame of
  the first camera; the body is x = camera z (forward), y = -camera x (left), yaw about the
  camera's -y axis (up). See :func:`recorders.common.project_to_planar`.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lcv_replay.errors import RecorderError
from lcv_replay.records import StereoCalibration
from recorders.common import (
    ImageFormat,
    LogHeader,
    PoseFormat,
    ProgressCallback,
    RecordStats,
    associate_stamps,
    calibration_from_projections,
    list_images,
    nominal_rate_hz,
    make_frames,
    options_config,
    image_loaders,
    project_to_planar,
    read_image,
    read_numeric_rows,
    read_pose_file,
    require_path,
    seconds_to_ns,
    vo_hook,
    write_log,
)

log = logging.getLogger(__name__)

_LAYOUT_FIX = "point at a KITTI sequence folder (with image_0, image_1, calib.txt, times.txt) or the dataset root with --sequence SS"


@dataclass(frozen=True)
class KittiOptions:
    """Options of the KITTI recorder.

    Attributes:
        sequence: sequence name (``"06"``) when ``SOURCE`` is the dataset root.
        odometry: odometry file (KITTI or TUM format); ``None`` = no odometry.
        odometry_format: ``auto`` (by column count), ``kitti`` or ``tum``.
        ground_truth: ground-truth poses file; ``None`` = ``ROOT/poses/SS.txt`` if it exists.
        auto_ground_truth: look for ``ROOT/poses/SS.txt`` when ``ground_truth`` is ``None``.
        color: record the colour pair ``image_2``/``image_3`` (``P2``/``P3``) instead of the grey one.
        start_frame, max_frames: record frames ``start_frame .. start_frame + max_frames - 1``
            (renumbered from 0; ``frame_offset`` in the recorder config keeps the source index).
        stamp_tolerance_s: TUM odometry stamps must be this close to ``times.txt``.
        start_stamp_ns: added to ``times.txt`` (KITTI times start at 0).
        image_format, jpeg_quality: how the writer encodes the images.
        vo: compute ``/odom`` with stereo visual odometry on the images (:mod:`lcv_replay.vo`).
    """

    sequence: str | None = None
    odometry: Path | None = None
    odometry_format: PoseFormat = "auto"
    ground_truth: Path | None = None
    auto_ground_truth: bool = True
    color: bool = False
    start_frame: int = 0
    max_frames: int | None = None
    stamp_tolerance_s: float = 0.01
    start_stamp_ns: int = 0
    image_format: ImageFormat = "png"
    jpeg_quality: int = 95
    vo: bool = False

    def __post_init__(self) -> None:
        if self.vo and self.odometry is not None:
            raise RecorderError("--vo and --odometry are exclusive", fix="drop one: --vo computes the odometry from the images")
        if self.start_frame < 0:
            raise RecorderError(f"--start-frame {self.start_frame} is negative", fix="pass a frame index >= 0")
        if self.max_frames is not None and self.max_frames < 1:
            raise RecorderError(f"--max-frames {self.max_frames} must be >= 1", fix="pass a positive count")
        if self.odometry_format not in ("auto", "kitti", "tum"):
            raise RecorderError(f"--odometry-format {self.odometry_format!r} is unknown", fix="use auto, kitti or tum")


@dataclass(frozen=True)
class KittiSequence:
    """A KITTI sequence, resolved and checked, images not loaded.

    Attributes:
        left_images, right_images: ``N`` image paths each.
        stamps_ns: ``(N,)`` frame stamps.
        odometry: ``(N, 3)`` planar odometry or ``None``.
        ground_truth: ``(N, 3)`` planar ground truth or ``None``.
        frame_offset: source index of frame 0 (``start_frame``).
    """

    folder: Path
    name: str
    left_images: tuple[Path, ...]
    right_images: tuple[Path, ...]
    stamps_ns: np.ndarray
    calibration: StereoCalibration
    odometry: np.ndarray | None
    ground_truth: np.ndarray | None
    odometry_path: Path | None
    ground_truth_path: Path | None
    frame_offset: int = 0


def read_calib(path: Path) -> dict[str, np.ndarray]:
    """``calib.txt`` -> ``{"P0": (3, 4), ...}`` (other keys such as ``Tr`` are kept too)."""
    fix = "calib.txt lines look like 'P0: fx 0 cx 0 0 fy cy 0 0 0 1 0'"
    require_path(path, what="KITTI calib.txt", fix=fix)
    out: dict[str, np.ndarray] = {}
    for line_no, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), start=1):
        if not line.strip():
            continue
        key, sep, rest = line.partition(":")
        if not sep:
            raise RecorderError(f"line {line_no}: expected 'KEY: numbers'", path=path, fix=fix)
        try:
            values = np.array([float(v) for v in rest.split()])
        except ValueError:
            raise RecorderError(f"line {line_no}: not a number after {key.strip()}:", path=path, fix=fix) from None
        if len(values) == 12:
            out[key.strip()] = values.reshape(3, 4)
    return out


def resolve_sequence_folder(source: Path, sequence: str | None) -> tuple[Path, str]:
    """The ``sequences/SS`` folder and its name, from a sequence folder or a dataset root."""
    source = require_path(source, what="KITTI source folder", fix=_LAYOUT_FIX, folder=True)
    if (source / "image_0").is_dir() or (source / "image_2").is_dir():
        if sequence is not None and sequence != source.name:
            raise RecorderError(f"--sequence {sequence} does not match the sequence folder {source.name}", path=source, fix="drop --sequence or point at the dataset root")
        return source, source.name
    if sequence is None:
        found = sorted(p.name for p in (source / "sequences").glob("*") if p.is_dir()) if (source / "sequences").is_dir() else []
        hint = f"pass --sequence (found: {', '.join(found[:12])})" if found else _LAYOUT_FIX
        raise RecorderError("not a KITTI sequence folder (no image_0)", path=source, fix=hint)
    folder = source / "sequences" / sequence
    require_path(folder, what=f"KITTI sequence {sequence}", fix=_LAYOUT_FIX, folder=True)
    return folder, sequence


def load_kitti_sequence(source: str | Path, options: KittiOptions = KittiOptions()) -> KittiSequence:
    """Resolve, read and check everything but the images.

    Raises:
        RecorderError: missing folders/files, image counts that differ between the cameras, a
            ``times.txt``/pose file whose length differs from the image count, TUM stamps that do
            not cover the frames.
    """
    folder, name = resolve_sequence_folder(Path(source), options.sequence)
    left_dir, right_dir, p_left, p_right = ("image_2", "image_3", "P2", "P3") if options.color else ("image_0", "image_1", "P0", "P1")
    left = list_images(folder / left_dir, what=f"left image folder {left_dir}")
    right = list_images(folder / right_dir, what=f"right image folder {right_dir}")
    if len(left) != len(right):
        raise RecorderError(f"{left_dir} has {len(left)} images but {right_dir} has {len(right)}", path=folder, fix="every frame needs both images")
    for a, b in zip(left, right):
        if a.stem != b.stem:
            raise RecorderError(f"{left_dir}/{a.name} has no partner (found {right_dir}/{b.name})", path=folder, fix="the two folders must hold the same file names")
    n_all = len(left)

    times_path = folder / "times.txt"
    rows = read_numeric_rows(times_path, what="KITTI times.txt", fix="times.txt lists one time in seconds per frame")
    times_s = np.array([v[0] for _, v in rows], dtype=np.float64)
    if len(times_s) != n_all:
        raise RecorderError(f"times.txt has {len(times_s)} lines but {left_dir} has {n_all} images", path=times_path, fix="use the times.txt of the same sequence")
    if np.any(np.diff(times_s) <= 0):
        k = int(np.argmax(np.diff(times_s) <= 0)) + 1
        raise RecorderError(f"time of frame {k} does not increase", path=times_path, fix="times.txt must be increasing")

    calib_path = folder / "calib.txt"
    calib = read_calib(calib_path)
    if p_left not in calib or p_right not in calib:
        raise RecorderError(f"calib.txt has no {p_left}/{p_right} line", path=calib_path, fix="use the KITTI odometry calib.txt")
    first = read_image(left[0])
    calibration = calibration_from_projections(calib[p_left], calib[p_right], first.shape[1], first.shape[0])
    if not calibration.baseline_m > 0:
        raise RecorderError(f"{p_left}/{p_right} give a baseline of {calibration.baseline_m} m", path=calib_path, fix="check the projection matrices")

    odometry = ground_truth = None
    if options.odometry is not None:
        odometry = _planar_poses(Path(options.odometry), options.odometry_format, times_s, n_all, options.stamp_tolerance_s, "odometry")
    elif options.vo:
        log.info("odometry from stereo VO on the %s pair", "colour" if options.color else "grey")
    else:
        log.warning("no --odometry given: the log carries images%s only (estimate odometry with --vo or 'lcv-replay vo')", " and ground truth" if options.ground_truth or options.auto_ground_truth else "")
    gt_path = options.ground_truth
    if gt_path is None and options.auto_ground_truth:
        candidate = folder.parent.parent / "poses" / f"{name}.txt"
        if candidate.is_file():
            gt_path = candidate
            log.info("using the ground truth %s", candidate)
    if gt_path is not None:
        ground_truth = _planar_poses(Path(gt_path), "auto", times_s, n_all, options.stamp_tolerance_s, "ground truth")

    first_frame = options.start_frame
    last_frame = n_all if options.max_frames is None else min(n_all, first_frame + options.max_frames)
    if first_frame >= n_all:
        raise RecorderError(f"--start-frame {first_frame} is past the last frame {n_all - 1}", path=folder, fix="pass a smaller --start-frame")
    keep = slice(first_frame, last_frame)
    return KittiSequence(
        folder=folder,
        name=name,
        left_images=tuple(left[keep]),
        right_images=tuple(right[keep]),
        stamps_ns=options.start_stamp_ns + seconds_to_ns(times_s[keep]),
        calibration=calibration,
        odometry=None if odometry is None else odometry[keep],
        ground_truth=None if ground_truth is None else ground_truth[keep],
        odometry_path=options.odometry,
        ground_truth_path=gt_path,
        frame_offset=first_frame,
    )


def _planar_poses(path: Path, fmt: PoseFormat, times_s: np.ndarray, n: int, tolerance_s: float, what: str) -> np.ndarray:
    """``(n, 3)`` planar poses of the frames from a KITTI or TUM camera trajectory."""
    poses = read_pose_file(path, fmt)
    if poses.format == "kitti":
        if len(poses.T_world_sensor) != n:
            raise RecorderError(f"{what} has {len(poses.T_world_sensor)} poses but the sequence has {n} frames", path=path, fix="use the poses of the same sequence (KITTI format: one line per frame)")
        return project_to_planar(poses.T_world_sensor)
    index = associate_stamps(seconds_to_ns(times_s), seconds_to_ns(poses.stamps_s), int(round(tolerance_s * 1e9)))
    missing = np.flatnonzero(index < 0)
    if len(missing):
        raise RecorderError(
            f"{what}: {len(missing)} of {n} frames have no pose within {tolerance_s} s (first: frame {missing[0]} at {times_s[missing[0]]:.6f} s)",
            path=path,
            fix="TUM stamps must be the times.txt seconds of the same sequence (or raise --stamp-tolerance)",
        )
    return project_to_planar(poses.T_world_sensor[index])


def record_kitti(
    source: str | Path,
    out_path: str | Path,
    options: KittiOptions = KittiOptions(),
    *,
    force: bool = False,
    progress: ProgressCallback | None = None,
    live: bool = False,
) -> RecordStats:
    """Record a KITTI odometry sequence into an lcv-replay log at ``out_path`` (atomically, or chunk by chunk with ``live``)."""
    from lcv_replay.fileio import check_output_path

    started = time.perf_counter()
    out_path = check_output_path(out_path, force=force)
    seq = load_kitti_sequence(source, options)
    frames = make_frames(
        seq.stamps_ns,
        left=image_loaders(seq.left_images),
        right=image_loaders(seq.right_images),
        odometry=seq.odometry,
        ground_truth=seq.ground_truth,
    )
    config = options_config(
        options,
        source=seq.folder,
        ground_truth=seq.ground_truth_path,
        frame_offset=seq.frame_offset,
        planar_projection="body x = camera z, body y = -camera x, yaw about camera -y; world = first camera frame",
    )
    header = LogHeader(
        dataset=f"kitti/{seq.name}",
        recorder="kitti",
        nominal_rate_hz=nominal_rate_hz(seq.stamps_ns),
        config=config,
        calibration=seq.calibration,
        image_format=options.image_format,
        jpeg_quality=options.jpeg_quality,
    )
    return write_log(out_path, header, frames, force=force, progress=progress, started=started, live=live, image_odometry=vo_hook(options.vo, seq.calibration))


__all__ = ["KittiOptions", "KittiSequence", "load_kitti_sequence", "read_calib", "record_kitti"]
