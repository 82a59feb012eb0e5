"""Tiny synthetic logs for the log-package tests: textured images, drifting odometry, candidates."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lcv_replay.log.writer import LogWriter
from lcv_replay.records import LoopCandidate, Pose2D, StereoCalibration

T0_NS = 1_700_000_000_000_000_000
PERIOD_NS = 100_000_000  # 10 Hz
CALIB = StereoCalibration(width_px=40, height_px=30, fx_px=35.0, fy_px=36.0, cx_px=20.0, cy_px=15.0, baseline_m=0.54)


def textured_image(rng: np.random.Generator, height: int, width: int, *, rgb: bool) -> np.ndarray:
    """``(H, W)`` or ``(H, W, 3)`` uint8: smooth gradients plus blocks plus mild noise (JPEG-friendly)."""
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    phase = rng.uniform(0, 2 * np.pi, size=3)
    channels = []
    for c in range(3 if rgb else 1):
        base = 128 + 80 * np.sin(xx / 5.0 + phase[c]) * np.cos(yy / 7.0 + phase[(c + 1) % 3])
        blocks = 30.0 * ((xx // 8 + yy // 8) % 2)
        channels.append(base + blocks + rng.normal(0, 4, size=base.shape))
    image = np.clip(np.stack(channels, axis=-1), 0, 255).astype(np.uint8)
    return image if rgb else image[:, :, 0]


@dataclass
class Expected:
    """What a synthetic log was written with."""

    stamps_ns: list[int] = field(default_factory=list)
    left: list[np.ndarray] = field(default_factory=list)
    right: list[np.ndarray] = field(default_factory=list)
    odom: list[Pose2D] = field(default_factory=list)
    ground_truth: list[Pose2D | None] = field(default_factory=list)
    candidates: list[LoopCandidate] = field(default_factory=list)
    true_loops: set[tuple[int, int]] = field(default_factory=set)


def write_synthetic_log(
    path: Path,
    *,
    frames: int = 8,
    images: bool = True,
    stereo: bool = True,
    rgb: bool = True,
    seed: int = 0,
    gt_every: int = 1,
    **writer_kwargs,
) -> Expected:
    """Write a small log with ``frames`` frames (stereo images unless disabled, odometry, ground truth on
    every ``gt_every``-th frame, a candidate at every frame >= 3 and a label for each even query)."""
    rng = np.random.default_rng(seed)
    exp = Expected()
    kwargs = dict(dataset="synthetic-test", recorder="tests", nominal_rate_hz=10.0, recorder_config={"frames": frames, "seed": seed})
    kwargs.update(writer_kwargs)
    pose = Pose2D(0.0, 0.0, 0.0)
    with LogWriter(path, **kwargs) as writer:
        if images:
            writer.write_calibration(CALIB, T0_NS)
        for i in range(frames):
            stamp = T0_NS + i * PERIOD_NS + int(rng.integers(0, 1000))
            pose = pose.compose(Pose2D(1.0 + 0.1 * rng.normal(), 0.05 * rng.normal(), 0.1 + 0.02 * rng.normal()))
            gt = Pose2D(pose.x_m + 0.5, pose.y_m - 0.25, pose.yaw_rad) if i % gt_every == 0 else None
            left = textured_image(rng, CALIB.height_px, CALIB.width_px, rgb=rgb) if images else None
            right = textured_image(rng, CALIB.height_px, CALIB.width_px, rgb=rgb) if images and stereo else None
            writer.write_frame(i, stamp, left=left, right=right, odom=pose, ground_truth=gt)
            exp.stamps_ns.append(stamp)
            exp.left.append(left)
            exp.right.append(right)
            exp.odom.append(pose)
            exp.ground_truth.append(gt)
            if i >= 3:
                cand = LoopCandidate(
                    query_frame=i,
                    match_frame=i - 3,
                    similarity=float(rng.uniform()),
                    hamming=int(rng.integers(0, 4)),
                    source="tests",
                    T_match_query=Pose2D(float(rng.normal()), float(rng.normal()), float(rng.normal())) if i % 2 else None,
                    information=(10.0, 0.0, 0.0, 10.0, 0.0, 100.0) if i % 2 else None,
                )
                writer.write_loop_candidate(cand, stamp)
                exp.candidates.append(cand)
                if i % 2 == 0:
                    writer.write_true_loop(i, i - 3, stamp)
                    exp.true_loops.add((i, i - 3))
    return exp
