"""Helpers shared by the recorders: pose files, 3-D -> planar projection, stamps, statistics.

Conventions (see :mod:`lcv_replay.records`): planar poses are ``(x_m, y_m, yaw_rad)`` of the body
(x forward, y left, yaw counter-clockwise about +z). Arrays of planar poses have shape ``(N, 3)``;
arrays of rigid transforms have shape ``(N, 4, 4)``.

**3-D -> planar projection.** A 3-D pose ``T_world_sensor`` is first expressed in a body frame with
z up (``T_body0_body = R_body_sensor · T_sensor0_sensor · R_body_sensorᵀ``; the world frame is the
first body frame rotated by the same fixed rotation), then projected: ``x_m``, ``y_m`` are the
translation's x and y, and ``yaw_rad = atan2(R[1, 0], R[0, 0])``, the heading of the body x axis in
the x-y plane (the z-y-x Euler yaw). Height, roll and pitch are dropped.

* KITTI (and most visual odometry) poses are of a camera with x right, y down, z forward:
  body x = camera z, body y = -camera x, body z = -camera y (:data:`R_BODY_CAMERA`).
* EuRoC ground truth and ROS odometry are already of a z-up body (:data:`R_BODY_IDENTITY`).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Protocol, Sequence

import numpy as np

from lcv_replay.errors import RecorderError
from lcv_replay.records import Pose2D

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
        return (
            f"wrote {self.path}: {', '.join(parts)}, {format_size(self.size_bytes)} in {self.elapsed_s:.1f} s "
            f"({self.frames_per_s:.0f} frames/s)"
        )


def format_size(size_bytes: int) -> str:
    """``1234567 -> '1.2 MB'`` (decimal units, as ``ros2 bag info``)."""
    size = float(size_bytes)
    for unit in ("B", "kB", "MB", "GB"):
        if size < 1000.0 or unit == "GB":
            return f"{size:.0f} {unit}" if unit == "B" else f"{size:.1f} {unit}"
        size /= 1000.0
    raise AssertionError("unreachable")


# ---------------------------------------------------------------------------------------------
# Planar pose algebra over arrays
# ---------------------------------------------------------------------------------------------


def wrap_angles(angles_rad: np.ndarray) -> np.ndarray:
    """Wrap angles to ``[-pi, pi)``, element-wise."""
    return (np.asarray(angles_rad, dtype=np.float64) + math.pi) % (2.0 * math.pi) - math.pi


def compose_chain(steps: np.ndarray, start: Pose2D | Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """Cumulative poses of a chain of relative steps.

    Args:
        steps: ``(M, 3)`` relative poses ``T_{k}_{k+1}`` as ``(x_m, y_m, yaw_rad)``.
        start: the pose ``T_world_0`` of the first node.

    Returns:
        ``(M + 1, 3)`` poses ``T_world_k``; row 0 is ``start``. Yaw is wrapped to ``[-pi, pi)``.
    """
    steps = np.asarray(steps, dtype=np.float64).reshape(-1, 3)
    x0, y0, yaw0 = (float(v) for v in start)
    # Heading before each step; positions are the running sum of the rotated step translations.
    heading = yaw0 + np.concatenate([[0.0], np.cumsum(steps[:, 2])])
    cos_h, sin_h = np.cos(heading[:-1]), np.sin(heading[:-1])
    dx = cos_h * steps[:, 0] - sin_h * steps[:, 1]
    dy = sin_h * steps[:, 0] + cos_h * steps[:, 1]
    poses = np.empty((len(steps) + 1, 3))
    poses[:, 0] = x0 + np.concatenate([[0.0], np.cumsum(dx)])
    poses[:, 1] = y0 + np.concatenate([[0.0], np.cumsum(dy)])
    poses[:, 2] = wrap_angles(heading)
    return poses


def relative_steps(poses: np.ndarray) -> np.ndarray:
    """Inverse of :func:`compose_chain`: ``(N, 3)`` poses -> ``(N - 1, 3)`` steps ``T_{k}_{k+1}``."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    d = poses[1:, :2] - poses[:-1, :2]
    c, s = np.cos(poses[:-1, 2]), np.sin(poses[:-1, 2])
    steps = np.empty((max(len(poses) - 1, 0), 3))
    steps[:, 0] = c * d[:, 0] + s * d[:, 1]
    steps[:, 1] = -s * d[:, 0] + c * d[:, 1]
    steps[:, 2] = wrap_angles(poses[1:, 2] - poses[:-1, 2])
    return steps


def poses_to_records(poses: np.ndarray) -> list[Pose2D]:
    """``(N, 3)`` array -> list of :class:`Pose2D`."""
    return [Pose2D(float(x), float(y), float(t)) for x, y, t in np.asarray(poses, dtype=np.float64)]


def project_to_planar(T_world_sensor: np.ndarray, R_body_sensor: np.ndarray = R_BODY_CAMERA) -> np.ndarray:
    """Project 3-D poses to planar body poses (see the module docstring).

    Args:
        T_world_sensor: ``(N, 4, 4)`` rigid transforms of the sensor in its world frame.
        R_body_sensor: ``(3, 3)`` rotation taking sensor-frame vectors to the z-up body frame.

    Returns:
        ``(N, 3)`` planar poses ``(x_m, y_m, yaw_rad)`` in the z-up world frame aligned with the
        sensor's world frame by the same rotation.
    """
    T = np.asarray(T_world_sensor, dtype=np.float64).reshape(-1, 4, 4)
    R_bs = np.asarray(R_body_sensor, dtype=np.float64)
    rot = np.einsum("ij,njk,lk->nil", R_bs, T[:, :3, :3], R_bs)  # R_bs · R · R_bsᵀ
    trans = T[:, :3, 3] @ R_bs.T
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
