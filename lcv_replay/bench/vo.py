"""Stereo VO benchmark behind ``lcv-replay bench vo``: drift, speed, a real KITTI step, end to end.

* **Drift on the synthetic world** (:func:`synthetic_drift`): the default route of
  :mod:`recorders.synthetic_world` is rendered frame by frame and fed to the tracker; the estimate is
  scored against the true poses with the KITTI odometry metric (:func:`lcv_replay.vo.drift.kitti_drift`:
  mean translational error in % and rotational error in deg/m over segments of 100..800 m, or
  shorter segments for shorter routes, stated in the output) and the SE(2)-aligned ATE. Rows: clean
  renders, renders with Gaussian sensor noise, and the recorder's simulated-drift odometry as a
  reference.
* **Speed** (:func:`vo_speed`): pairs per second of the tracker over pre-rendered 640x480 pairs
  held in memory (decoding excluded), and with PNG decoding included, the median of several runs.
* **KITTI 06, frames 12 -> 13** (:func:`kitti_step`): 3-D points from the real stereo pair of frame
  12, PnP against the left image of frame 13, compared with the ground-truth relative pose.
* **End to end** (:func:`end_to_end`): the synthetic demo recorded twice, with simulated drift and
  with stereo VO, each replayed through retrieval and verification; precision/recall side by side.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import statistics
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from lcv_replay.fileio import make_folder
from lcv_replay.records import Pose2D, StereoCalibration
from lcv_replay.vo.config import VoConfig

log = logging.getLogger(__name__)

#: KITTI odometry calibration of sequences 04-12 (shared/data/README.md): fx = fy, cx, cy, fx * baseline.
KITTI_04_12 = StereoCalibration(
    width_px=1226, height_px=370, fx_px=707.0912, fy_px=707.0912, cx_px=601.8873, cy_px=183.1104,
    baseline_m=379.8145 / 707.0912,
)


@dataclass(frozen=True)
class DriftRow:
    """Drift of one odometry source on the synthetic route (one row of the drift table)."""

    source: str
    frames: int
    path_length_m: float
    translation_error_pct: float
    rotation_error_deg_per_m: float
    segments: int
    segment_lengths_m: tuple[float, ...]
    ate_rmse_m: float
    end_point_error_m: float
    fallback_frames: int | None = None
    median_inliers: float | None = None
    resolution: str = ""
    noise_grey: float = 0.0

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class SpeedRow:
    """Tracker throughput at one resolution (medians over ``runs``).

    ``pairs_per_s`` is wall-clock throughput (it depends on what else runs on the machine, see
    ``loadavg_1min``); ``cpu_ms_per_pair`` is the process CPU time per pair, all OpenCV threads
    summed (closer to a machine-independent cost).
    """

    resolution: str
    pairs: int
    runs: int
    pairs_per_s: float
    pairs_per_s_min: float
    pairs_per_s_max: float
    ms_per_pair: float
    cpu_ms_per_pair: float
    with_png_decode_pairs_per_s: float
    opencv_threads: int
    loadavg_1min: float

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class KittiStepRow:
    """The KITTI 06 12 -> 13 comparison."""

    gt_step_m: float
    estimated_step_m: float
    translation_error_m: float
    translation_error_pct: float
    rotation_error_deg: float
    gt_rotation_deg: float
    stereo_points: int
    tracked: int
    inliers: int
    reprojection_rmse_px: float

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class EndToEndRow:
    """One replay of the synthetic demo (simulated-drift or VO odometry)."""

    odometry: str
    frames: int
    odometry_translation_error_pct: float
    odometry_ate_m: float
    constraints: int
    accepted: int
    true_positives: int | None
    false_positives: int | None
    false_negatives: int | None
    precision: float | None
    recall: float | None
    ate_rmse_m: float | None
    replay_wall_s: float

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


# ----------------------------------------------------------------------------------- helpers


def relative_to_first(poses: np.ndarray) -> np.ndarray:
    """``(N, 3)`` poses expressed in the frame of the first one (the odometry frame convention)."""
    origin = Pose2D(*poses[0])
    return np.array([origin.between(Pose2D(*p)) for p in poses], dtype=np.float64).reshape(-1, 3)


def drift_row(source: str, estimate: np.ndarray, truth: np.ndarray, **extra) -> DriftRow:
    """Score an ``(N, 3)`` odometry against ``(N, 3)`` true poses (any origin)."""
    from lcv_replay.evaluation.metrics import absolute_trajectory_error
    from lcv_replay.vo.drift import kitti_drift, path_length_m

    true_odom = relative_to_first(truth)
    estimate = relative_to_first(estimate)
    drift = kitti_drift(estimate, true_odom)
    ate = absolute_trajectory_error(estimate, true_odom)
    return DriftRow(
        source=source,
        frames=len(truth),
        path_length_m=float(path_length_m(true_odom)[-1]),
        translation_error_pct=drift.translation_error_pct,
        rotation_error_deg_per_m=drift.rotation_error_deg_per_m,
        segments=drift.segments,
        segment_lengths_m=drift.lengths_m,
        ate_rmse_m=ate.rmse_m,
        end_point_error_m=float(np.hypot(*(estimate[-1, :2] - true_odom[-1, :2]))),
        **extra,
    )


def rendered_pairs(
    world, truth: np.ndarray, width_px: int, height_px: int, *, noise_grey: float = 0.0, seed: int = 0, threads: int = 2
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Grey ``(H, W)`` stereo pairs along ``truth``, rendered ahead on a thread pool.

    With ``noise_grey > 0`` each image gets additive Gaussian sensor noise of that standard
    deviation (deterministic for ``seed``).
    """
    import cv2

    rng = np.random.default_rng([seed, 0x7015E])

    def render(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        left, right = world.render_stereo(Pose2D(*pose), width_px=width_px, height_px=height_px)
        return cv2.cvtColor(left, cv2.COLOR_RGB2GRAY), cv2.cvtColor(right, cv2.COLOR_RGB2GRAY)

    def noisy(image: np.ndarray) -> np.ndarray:
        if noise_grey <= 0:
            return image
        return np.clip(image + rng.normal(0.0, noise_grey, image.shape), 0, 255).astype(np.uint8)

    ahead = 2 * threads + 1
    with ThreadPoolExecutor(threads, thread_name_prefix="lcv-bench-render") as pool:
        pending = {}
        for i in range(len(truth)):
            for k in range(i, min(len(truth), i + ahead)):
                if k not in pending:
                    pending[k] = pool.submit(render, truth[k])
            left, right = pending.pop(i).result()
            yield noisy(left), noisy(right)


# ----------------------------------------------------------------------------------- benches


def synthetic_drift(
    *,
    seed: int = 0,
    frames: int = 1500,
    width_px: int = 640,
    height_px: int = 480,
    noise_levels_grey: tuple[float, ...] = (0.0, 2.0),
    config: VoConfig | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> list[DriftRow]:
    """VO drift on the synthetic route (one row per noise level) plus the simulated-drift reference."""
    from recorders.synthetic import DriftConfig, simulate_odometry
    from recorders.synthetic_world import SyntheticWorld, make_route, t_body_camera
    from lcv_replay.vo.stereo_vo import StereoVoTracker

    world = SyntheticWorld.from_seed(seed)
    truth = make_route(world, frames)
    calibration = world.calibration(width_px, height_px)
    resolution = f"{width_px}x{height_px}"
    rows = []
    for noise in noise_levels_grey:
        tracker = StereoVoTracker(calibration, config, T_body_camera=t_body_camera(world.config))
        steps = []
        label = "stereo VO" + (f" + noise {noise:g}" if noise > 0 else "")
        for i, (left, right) in enumerate(rendered_pairs(world, truth, width_px, height_px, noise_grey=noise, seed=seed)):
            steps.append(tracker.process(left, right))
            if progress is not None:
                progress(label, i + 1, frames)
        estimate = np.array([s.T_odom_base for s in steps])
        ok = [s.quality.n_inliers for s in steps if not s.quality.fallback and s.index > 0]
        rows.append(
            drift_row(
                label, estimate, truth,
                fallback_frames=tracker.fallbacks,
                median_inliers=float(np.median(ok)) if ok else 0.0,
                resolution=resolution,
                noise_grey=noise,
            )
        )
    simulated = simulate_odometry(truth, DriftConfig(), seed)
    rows.append(drift_row("simulated drift (recorder default)", simulated, truth, resolution=resolution))
    return rows


def vo_speed(
    *,
    seed: int = 0,
    pairs: int = 200,
    width_px: int = 640,
    height_px: int = 480,
    runs: int = 5,
    config: VoConfig | None = None,
) -> SpeedRow:
    """Tracker throughput on ``pairs`` pre-rendered frames of the route (median over ``runs``).

    The first timed quantity excludes image decoding (the pairs are held in memory as grey
    arrays); the second decodes every pair from PNG on a worker thread ahead of the tracker (as
    ``lcv-replay vo`` does from a log).
    """
    import cv2

    from recorders.synthetic_world import SyntheticWorld, make_route
    from lcv_replay.vo.log_vo import prefetched
    from lcv_replay.vo.stereo_vo import run_vo

    world = SyntheticWorld.from_seed(seed)
    truth = make_route(world, pairs)
    calibration = world.calibration(width_px, height_px)
    images = list(rendered_pairs(world, truth, width_px, height_px))
    encoded = [tuple(cv2.imencode(".png", im, [cv2.IMWRITE_PNG_COMPRESSION, 1])[1] for im in pair) for pair in images]

    def decode(pair: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        return cv2.imdecode(pair[0], cv2.IMREAD_UNCHANGED), cv2.imdecode(pair[1], cv2.IMREAD_UNCHANGED)

    def decoded() -> Iterator[tuple[np.ndarray, np.ndarray]]:
        return prefetched(encoded, decode)  # as 'lcv-replay vo' decodes a log's images

    rates, rates_png, cpu_ms = [], [], []
    for _ in range(max(1, runs)):
        cpu_started = time.process_time()
        rates.append(run_vo(images, calibration, config).pairs_per_s)
        cpu_ms.append(1000.0 * (time.process_time() - cpu_started) / len(images))
        rates_png.append(run_vo(decoded(), calibration, config).pairs_per_s)
    median = statistics.median(rates)
    return SpeedRow(
        resolution=f"{width_px}x{height_px}",
        pairs=pairs,
        runs=len(rates),
        pairs_per_s=median,
        pairs_per_s_min=min(rates),
        pairs_per_s_max=max(rates),
        ms_per_pair=1000.0 / median,
        cpu_ms_per_pair=statistics.median(cpu_ms),
        with_png_decode_pairs_per_s=statistics.median(rates_png),
        opencv_threads=cv2.getNumThreads(),
        loadavg_1min=os.getloadavg()[0],
    )


def kitti_step(data_dir: Path, config: VoConfig | None = None) -> KittiStepRow:
    """KITTI 06 frames 12 -> 13: stereo at 12, PnP into the left image of 13, versus ``06.txt``."""
    import cv2

    from lcv_replay.errors import OdometryError
    from lcv_replay.vo import stereo_vo as sv

    config = config or VoConfig()
    names = ("kitti06-12.png", "kitti06-12-R.png", "kitti06-13.png", "06.txt")
    missing = [n for n in names if not (data_dir / n).is_file()]
    if missing:
        raise OdometryError(f"KITTI frames not found: {', '.join(missing)}", path=data_dir, fix="pass --kitti-frames ../shared/data/kitti06_frames")
    left12, right12, left13 = (cv2.imread(str(data_dir / n), cv2.IMREAD_GRAYSCALE) for n in names[:3])
    keyframe = sv.make_keyframe(12, left12, right12, KITTI_04_12, config)
    pnp, tracked = sv.track_keyframe(keyframe, left13, KITTI_04_12, config, None)
    if pnp is None:
        raise OdometryError("PnP failed on KITTI 06 frames 12 -> 13", path=data_dir)
    poses = np.loadtxt(data_dir / "06.txt").reshape(-1, 3, 4)
    T12, T13 = np.eye(4), np.eye(4)
    T12[:3], T13[:3] = poses[12], poses[13]
    T_gt = np.linalg.inv(T12) @ T13
    T_est = sv.invert_se3(pnp.T_cur_ref)
    error = np.linalg.inv(T_est) @ T_gt
    gt_step = float(np.linalg.norm(T_gt[:3, 3]))
    return KittiStepRow(
        gt_step_m=gt_step,
        estimated_step_m=float(np.linalg.norm(T_est[:3, 3])),
        translation_error_m=float(np.linalg.norm(error[:3, 3])),
        translation_error_pct=100.0 * float(np.linalg.norm(error[:3, 3])) / gt_step,
        rotation_error_deg=math.degrees(sv.rotation_angle_rad(error[:3, :3])),
        gt_rotation_deg=math.degrees(sv.rotation_angle_rad(T_gt[:3, :3])),
        stereo_points=keyframe.size,
        tracked=tracked,
        inliers=len(pnp.inliers),
        reprojection_rmse_px=pnp.rmse_px,
    )


def end_to_end(
    workdir: Path,
    *,
    seed: int = 0,
    frames: int = 1500,
    width_px: int = 640,
    height_px: int = 480,
    replay_config=None,
    progress: Callable[[str, int, int], None] | None = None,
) -> list[EndToEndRow]:
    """Record the demo with simulated-drift and with VO odometry, replay both, score side by side."""
    from recorders.synthetic import SyntheticOptions, record_synthetic
    from lcv_replay.config import ReplayConfig
    from lcv_replay.log.reader import open_log
    from lcv_replay.replay import ReplayOptions, replay

    make_folder(workdir)
    rows = []
    for odometry in ("simulated", "vo"):
        path = workdir / f"synthetic_{odometry}_{frames}f_{width_px}x{height_px}_seed{seed}.mcap"
        options = SyntheticOptions(frames=frames, seed=seed, width_px=width_px, height_px=height_px, odometry=odometry)
        label = f"record ({odometry})"
        record_synthetic(path, options, force=True, progress=(lambda d, t, label=label: progress(label, d, t)) if progress else None)
        with open_log(path) as reader:
            odom, truth = reader.odometry(), reader.ground_truth()
        scored = drift_row(odometry, odom, truth)
        started = time.perf_counter()
        summary = replay(ReplayOptions(log_path=path, config=replay_config or ReplayConfig()), [], handle_sigint=False)
        rows.append(
            EndToEndRow(
                odometry=odometry,
                frames=summary.frames,
                odometry_translation_error_pct=scored.translation_error_pct,
                odometry_ate_m=scored.ate_rmse_m,
                constraints=summary.constraints,
                accepted=summary.accepted,
                true_positives=summary.true_positives,
                false_positives=summary.false_positives,
                false_negatives=summary.false_negatives,
                precision=summary.precision,
                recall=summary.recall,
                ate_rmse_m=summary.ate_rmse_m,
                replay_wall_s=time.perf_counter() - started,
            )
        )
    return rows
