"""Odometry drift metrics: the KITTI odometry benchmark's segment errors, on planar trajectories.

The KITTI devkit (``evaluate_odometry.cpp``, Geiger et al. 2012) measures drift over sub-sequences:
for every 10th start frame and every segment length ``L`` (100, 200, ..., 800 m of ground-truth path)
it compares the relative motion over the segment, ``E = (T_est_first⁻¹ T_est_last)⁻¹ ·
(T_gt_first⁻¹ T_gt_last)``, and reports the mean of ``|t(E)| / L`` (translational error, %) and of
``angle(E) / L`` (rotational error, deg/m). Here the poses are planar ``(x_m, y_m, yaw_rad)`` and ``E``
is an SE(2) transform; the rotation angle is ``|yaw(E)|``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lcv_replay import se2
from lcv_replay.errors import OdometryError

KITTI_SEGMENT_LENGTHS_M = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
KITTI_STEP_FRAMES = 10


@dataclass(frozen=True)
class DriftResult:
    """KITTI-style drift of one trajectory.

    Attributes:
        translation_error_pct: mean over all segments of translation error / segment length, in %.
        rotation_error_deg_per_m: mean over all segments of rotation error / segment length.
        segments: number of segments evaluated.
        lengths_m: the segment lengths used.
        per_length: ``{length_m: (translation_error_pct, rotation_error_deg_per_m, segments)}``.
    """

    translation_error_pct: float
    rotation_error_deg_per_m: float
    segments: int
    lengths_m: tuple[float, ...]
    per_length: dict[float, tuple[float, float, int]]


def path_length_m(poses: np.ndarray) -> np.ndarray:
    """``(N,)`` cumulative distance travelled along ``(N, 3)`` planar poses (0 at the first)."""
    steps = np.linalg.norm(np.diff(poses[:, :2], axis=0), axis=1)
    return np.r_[0.0, np.cumsum(steps)]


def segment_lengths_for(total_length_m: float) -> tuple[float, ...]:
    """The KITTI lengths 100..800 m that fit in the route, or, for routes shorter than 200 m,
    five lengths from 10 % to 50 % of the route (rounded to 1 m)."""
    usable = tuple(L for L in KITTI_SEGMENT_LENGTHS_M if L < total_length_m)
    if len(usable) >= 1 and total_length_m >= 200.0:
        return usable
    return tuple(float(max(1.0, round(total_length_m * f))) for f in (0.1, 0.2, 0.3, 0.4, 0.5))


def kitti_drift(
    estimate: np.ndarray,
    ground_truth: np.ndarray,
    lengths_m: tuple[float, ...] | None = None,
    step_frames: int = KITTI_STEP_FRAMES,
) -> DriftResult:
    """KITTI segment errors of a planar trajectory.

    Args:
        estimate: ``(N, 3)`` estimated poses ``[x_m, y_m, yaw_rad]`` (any origin).
        ground_truth: ``(N, 3)`` ground-truth poses.
        lengths_m: segment lengths; ``None`` picks them with :func:`segment_lengths_for`.
        step_frames: stride between segment start frames (KITTI: 10).
    """
    est = np.asarray(estimate, dtype=np.float64)
    gt = np.asarray(ground_truth, dtype=np.float64)
    if est.ndim != 2 or est.shape[1] != 3 or est.shape != gt.shape:
        raise OdometryError(f"drift needs two (N, 3) trajectories of the same length, got {est.shape} and {gt.shape}")
    if not (np.all(np.isfinite(est)) and np.all(np.isfinite(gt))):
        raise OdometryError("drift: the trajectories contain NaN or inf")
    distance = path_length_m(gt)
    lengths = tuple(lengths_m) if lengths_m is not None else segment_lengths_for(float(distance[-1]))
    T_est, T_gt = se2.matrices(est), se2.matrices(gt)
    inv = np.linalg.inv
    errors: dict[float, list[tuple[float, float]]] = {L: [] for L in lengths}
    for first in range(0, len(gt), step_frames):
        for L in lengths:
            last = int(np.searchsorted(distance, distance[first] + L, side="right"))  # first frame farther than L (devkit)
            if last >= len(gt):
                continue
            delta_gt = inv(T_gt[first]) @ T_gt[last]
            delta_est = inv(T_est[first]) @ T_est[last]
            E = inv(delta_est) @ delta_gt
            t_err = math.hypot(E[0, 2], E[1, 2])
            r_err = abs(math.atan2(E[1, 0], E[0, 0]))
            errors[L].append((t_err / L, r_err / L))
    per_length = {
        L: (100.0 * float(np.mean([e[0] for e in v])), math.degrees(float(np.mean([e[1] for e in v]))), len(v))
        for L, v in errors.items()
        if v
    }
    everything = [e for v in errors.values() for e in v]
    if not everything:
        return DriftResult(math.nan, math.nan, 0, lengths, per_length)
    return DriftResult(
        100.0 * float(np.mean([e[0] for e in everything])),
        math.degrees(float(np.mean([e[1] for e in everything]))),
        len(everything),
        lengths,
        per_length,
    )
