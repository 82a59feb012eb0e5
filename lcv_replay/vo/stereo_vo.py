"""Stereo visual odometry on OpenCV: features, stereo triangulation, KLT tracking, PnP + RANSAC.

The pipeline per stereo pair (rectified images, calibration from the log):

1. **Image health**: blank, dark or bit-identical (duplicate) images are flagged and skipped.
2. **Temporal tracking**: the 3-D points of the reference keyframe (the last well-tracked frame)
   are tracked into the current left image with pyramidal Lucas-Kanade
   (``cv2.calcOpticalFlowPyrLK``), seeded by a constant-velocity prediction and checked
   forward-backward.
3. **Pose**: ``cv2.solvePnPRansac`` on the 3-D/2-D matches, then ``cv2.solvePnPRefineLM`` on the
   inliers (twice, re-selecting the inliers in between).
4. **New keyframe**: FAST corners (``cv2.FastFeatureDetector``) bucketed over the image,
   matched into the right image along the rectified row (LK with a left-right check, same row within
   a tolerance, positive disparity), triangulated with ``Z = fx * baseline / d``.

Frames where tracking fails fall back to a constant-velocity guess, are flagged in a
:class:`VoQuality` record and counted; the tracker keeps the last good keyframe and bridges the gap.

Conventions: the camera optical frame is z forward, x right, y down. The body (odometry) frame is
REP-103: x forward, y left, z up. ``T_a_b`` is a ``(4, 4)`` homogeneous transform taking points from
frame ``b`` into frame ``a`` (the pose of ``b`` in ``a``). Planar odometry is the projection of the
3-D body pose: ``x_m``, ``y_m`` and the yaw ``atan2(R[1, 0], R[0, 0])``.
"""

from __future__ import annotations

import enum
import functools
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Callable, Iterable

import cv2
import numpy as np

from lcv_replay.errors import OdometryError
from lcv_replay.records import IDENTITY_POSE, Pose2D, StereoCalibration
from lcv_replay.vo.config import VoConfig

logger = logging.getLogger(__name__)

#: Rotation of the camera optical frame (z forward, x right, y down) in the body frame (x forward,
#: y left, z up): body x = optical z, body y = -optical x, body z = -optical y.
R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


class TrackStatus(str, enum.Enum):
    """Outcome of one frame. Everything except ``OK`` and ``FIRST`` is a fallback frame."""

    OK = "ok"  # pose from PnP
    FIRST = "first"  # the first frame: the origin of the odometry
    BLANK = "blank"  # (near) uniform image
    DARK = "dark"  # mean grey level below threshold
    DUPLICATE = "duplicate"  # left image bit-identical to the previous one
    NO_REFERENCE = "no_reference"  # no keyframe with enough stereo points to track against
    FEW_INLIERS = "few_inliers"  # too few tracks or PnP inliers
    HIGH_ERROR = "high_error"  # refined reprojection RMSE above threshold

    @property
    def is_fallback(self) -> bool:
        return self not in (TrackStatus.OK, TrackStatus.FIRST)


@dataclass(frozen=True)
class VoQuality:
    """Per-frame tracking quality.

    Attributes:
        index: frame index (0..N-1).
        status: what happened; ``status.is_fallback`` frames use a constant-velocity guess.
        n_stereo: 3-D points triangulated in this frame (0 if it did not become a keyframe).
        n_tracked: keyframe points tracked into this frame (forward-backward checked).
        n_inliers: PnP inliers after refinement.
        reprojection_rmse_px: RMS reprojection error of the inliers (NaN when no pose was solved).
        keyframe_index: the keyframe this frame was tracked against (``-1`` if none).
    """

    index: int
    status: TrackStatus
    n_stereo: int = 0
    n_tracked: int = 0
    n_inliers: int = 0
    reprojection_rmse_px: float = math.nan
    keyframe_index: int = -1

    @property
    def fallback(self) -> bool:
        return self.status.is_fallback

    def as_dict(self) -> dict:
        """JSON-ready fields (``None`` for a NaN error)."""
        rmse = self.reprojection_rmse_px
        return {
            "index": self.index,
            "status": self.status.value,
            "fallback": self.fallback,
            "n_stereo": self.n_stereo,
            "n_tracked": self.n_tracked,
            "n_inliers": self.n_inliers,
            "reprojection_rmse_px": None if math.isnan(rmse) else round(rmse, 4),
            "keyframe_index": self.keyframe_index,
        }


@dataclass(frozen=True)
class VoStep:
    """The tracker's output for one stereo pair.

    Attributes:
        index: frame index.
        T_prev_cur: planar motion since the previous frame (identity for the first frame).
        T_odom_base: cumulative planar odometry pose (the ``/odom`` message of this frame).
        T_odom_camera: ``(4, 4)`` cumulative 3-D pose of the left camera in the odometry frame.
        quality: how the pose was obtained.
    """

    index: int
    T_prev_cur: Pose2D
    T_odom_base: Pose2D
    T_odom_camera: np.ndarray = field(repr=False, compare=False)
    quality: VoQuality = field(default_factory=lambda: VoQuality(0, TrackStatus.FIRST))


@dataclass(frozen=True)
class StereoKeyframe:
    """A frame with triangulated stereo points, the reference later frames are tracked against.

    Attributes:
        index: frame index.
        grey: the ``(H, W)`` uint8 left image.
        pixels_px: ``(N, 2)`` float32 raw (as imaged) left pixel positions of the points.
        points_m: ``(N, 3)`` float64 3-D points in this frame's left camera frame (metres).
    """

    index: int
    grey: np.ndarray = field(repr=False, compare=False)
    pixels_px: np.ndarray = field(repr=False, compare=False)
    points_m: np.ndarray = field(repr=False, compare=False)

    @property
    def size(self) -> int:
        return int(self.points_m.shape[0])


@dataclass(frozen=True)
class PnpResult:
    """A relative pose from PnP.

    Attributes:
        T_cur_ref: ``(4, 4)`` transform taking keyframe-camera points into the current camera.
        inliers: ``(K,)`` int indices of the inlier correspondences.
        rmse_px: RMS reprojection error of the inliers in pixels.
    """

    T_cur_ref: np.ndarray = field(repr=False, compare=False)
    inliers: np.ndarray = field(repr=False, compare=False)
    rmse_px: float = math.nan


# ----------------------------------------------------------------------------------------- geometry


def camera_mount(translation_m: tuple[float, float, float] = (0.0, 0.0, 0.0), pitch_down_rad: float = 0.0) -> np.ndarray:
    """``(4, 4)`` pose ``T_body_camera`` of an optical camera looking along body x.

    Args:
        translation_m: camera position in the body frame (x forward, y left, z up).
        pitch_down_rad: tilt of the optical axis below the horizon.
    """
    c, s = math.cos(pitch_down_rad), math.sin(pitch_down_rad)
    R_pitch = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])  # about body +y: nose down
    T = np.eye(4)
    T[:3, :3] = R_pitch @ R_BODY_OPTICAL
    T[:3, 3] = translation_m
    return T


def invert_se3(T: np.ndarray) -> np.ndarray:
    """Inverse of a ``(4, 4)`` rigid transform."""
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def se3_from_rvec(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """``(4, 4)`` transform from an OpenCV Rodrigues vector and translation."""
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3))[0]
    T[:3, 3] = np.asarray(tvec, dtype=np.float64).reshape(3)
    return T


def planar_from_se3(T_odom_body: np.ndarray) -> Pose2D:
    """Project a ``(4, 4)`` body pose onto the ground plane: ``(x, y, yaw)``."""
    R = T_odom_body[:3, :3]
    return Pose2D(float(T_odom_body[0, 3]), float(T_odom_body[1, 3]), math.atan2(R[1, 0], R[0, 0]))


def body_pose_from_camera(T_odom_camera: np.ndarray, T_body_camera: np.ndarray) -> np.ndarray:
    """``T_odom_body`` where the odometry frame is the body at frame 0: ``T_bc · T_c0_c · T_bc⁻¹``."""
    return T_body_camera @ T_odom_camera @ invert_se3(T_body_camera)


def rotation_angle_rad(R: np.ndarray) -> float:
    """Angle of a ``(3, 3)`` rotation matrix."""
    return math.acos(max(-1.0, min(1.0, (float(np.trace(R)) - 1.0) / 2.0)))


# ------------------------------------------------------------------------------------------ images


def to_grey(image: np.ndarray) -> np.ndarray:
    """``(H, W)`` uint8 grey image from ``(H, W)`` grey, ``(H, W, 3)`` RGB or ``(H, W, 4)`` RGBA.

    16-bit images are scaled to 8 bits. Raises :class:`OdometryError` for other shapes and types.
    """
    image = np.asarray(image)
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    if image.dtype != np.uint8:
        raise OdometryError(f"images must be 8-bit, got dtype {image.dtype}", fix="record 8-bit (mono8/rgb8/png) images")
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_RGBA2GRAY)
    raise OdometryError(f"unsupported image shape {image.shape}", fix="use (H, W) grey or (H, W, 3) RGB images")


def image_health(grey: np.ndarray, previous_grey: np.ndarray | None, config: VoConfig) -> TrackStatus | None:
    """``DARK``, ``BLANK`` or ``DUPLICATE`` for an unusable ``(H, W)`` uint8 image, else ``None``."""
    mean, std = cv2.meanStdDev(grey)
    if float(mean[0, 0]) < config.dark_mean_grey:
        return TrackStatus.DARK
    if float(std[0, 0]) < config.blank_std_grey:
        return TrackStatus.BLANK
    if previous_grey is not None and previous_grey.shape == grey.shape and np.array_equal(previous_grey, grey):
        return TrackStatus.DUPLICATE
    return None


@functools.lru_cache(maxsize=8)
def _fast_detector(threshold: int) -> cv2.FastFeatureDetector:
    return cv2.FastFeatureDetector_create(threshold=threshold, nonmaxSuppression=True)


def bucket_strongest(pixels_px: np.ndarray, response: np.ndarray, bucket_px: int, per_bucket: int, max_total: int) -> np.ndarray:
    """Indices of the ``per_bucket`` strongest points in each ``bucket_px`` square, strongest first.

    Args:
        pixels_px: ``(N, 2)`` pixel positions ``(u, v)``.
        response: ``(N,)`` detector responses.
    Returns:
        ``(K,)`` int indices, ``K <= max_total``, sorted by decreasing response.
    """
    if len(pixels_px) == 0:
        return np.zeros(0, dtype=np.int64)
    cell = (pixels_px // bucket_px).astype(np.int64)
    cell_id = cell[:, 1] * 100_000 + cell[:, 0]
    order = np.lexsort((-response, cell_id))  # by cell, then strongest first
    sorted_cells = cell_id[order]
    first = np.r_[0, np.flatnonzero(np.diff(sorted_cells)) + 1]
    rank = np.arange(len(order)) - np.repeat(first, np.diff(np.r_[first, len(order)]))
    keep = order[rank < per_bucket]
    keep = keep[np.argsort(-response[keep], kind="stable")]
    return keep[:max_total]


def detect_features(grey: np.ndarray, config: VoConfig) -> np.ndarray:
    """FAST corners spread over the image by bucketing (``config.buckets`` square buckets).

    Returns:
        ``(N, 2)`` float32 pixel positions ``(u, v)``, strongest first; ``(0, 2)`` if none.
    """
    keypoints = _fast_detector(config.fast_threshold).detect(grey)
    if not keypoints:
        return np.zeros((0, 2), dtype=np.float32)
    pixels = cv2.KeyPoint_convert(keypoints).astype(np.float32).reshape(-1, 2)
    response = np.fromiter((k.response for k in keypoints), dtype=np.float64, count=len(keypoints))
    h, w = grey.shape[:2]
    bucket_px = max(4, int(round(math.sqrt(w * h / config.buckets))))
    keep = bucket_strongest(pixels, response, bucket_px, config.features_per_bucket, config.max_features)
    return pixels[keep]


def track_points(
    grey_from: np.ndarray,
    grey_to: np.ndarray,
    pixels_px: np.ndarray,
    guess_px: np.ndarray | None,
    config: VoConfig,
    max_roundtrip_px: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Track points between two images with pyramidal LK and a forward-backward check.

    Args:
        pixels_px: ``(N, 2)`` float32 positions in the ``from`` image.
        guess_px: ``(N, 2)`` float32 initial positions in the ``to`` image, or ``None`` (same place).
        max_roundtrip_px: allowed distance between a point and its round-trip track; 0 skips the
            backward track (half the cost).
    Returns:
        ``(N, 2)`` float32 positions in the ``to`` image and an ``(N,)`` bool mask of good tracks.
    """
    n = len(pixels_px)
    if n == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    win = (config.klt_window_px, config.klt_window_px)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, config.klt_iterations, 0.01)
    p0 = np.ascontiguousarray(pixels_px, dtype=np.float32).reshape(-1, 1, 2)
    if guess_px is None:
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(grey_from, grey_to, p0, None, winSize=win, maxLevel=config.klt_levels, criteria=criteria)
    else:
        p1 = np.ascontiguousarray(guess_px, dtype=np.float32).reshape(-1, 1, 2).copy()
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(
            grey_from, grey_to, p0, p1, winSize=win, maxLevel=config.klt_levels,
            criteria=criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
    ok = st1.reshape(-1) == 1
    if max_roundtrip_px > 0:
        # Seeded at the start point, a consistent track converges at full resolution right away.
        p0b, st2, _ = cv2.calcOpticalFlowPyrLK(
            grey_to, grey_from, p1, p0.copy(), winSize=win, maxLevel=0,
            criteria=criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        roundtrip = np.linalg.norm((p0b - p0).reshape(-1, 2), axis=1)
        ok &= (st2.reshape(-1) == 1) & (roundtrip <= max_roundtrip_px)
    out = p1.reshape(-1, 2)
    h, w = grey_to.shape[:2]
    ok &= (out[:, 0] >= 0) & (out[:, 1] >= 0) & (out[:, 0] <= w - 1) & (out[:, 1] <= h - 1)
    return out, ok


def has_distortion(calibration: StereoCalibration) -> bool:
    return any(abs(float(k)) > 0.0 for k in calibration.distortion)


def undistort_pixels(pixels_px: np.ndarray, calibration: StereoCalibration) -> np.ndarray:
    """Remove lens distortion from ``(N, 2)`` pixel positions (``cv2.undistortPoints`` with ``P = K``).

    Returns the input (as float64) when the calibration has no distortion.
    """
    pixels = np.asarray(pixels_px, dtype=np.float64).reshape(-1, 2)
    if len(pixels) == 0 or not has_distortion(calibration):
        return pixels
    K = calibration.K
    dist = np.asarray(calibration.distortion, dtype=np.float64)
    return cv2.undistortPoints(pixels.reshape(-1, 1, 2), K, dist, P=K).reshape(-1, 2)


def triangulate_rectified(left_px: np.ndarray, disparity_px: np.ndarray, calibration: StereoCalibration) -> np.ndarray:
    """3-D points in the left camera frame from rectified stereo: ``Z = fx * baseline / d``.

    Args:
        left_px: ``(N, 2)`` undistorted left pixel positions.
        disparity_px: ``(N,)`` positive disparities ``u_left - u_right``.
    Returns:
        ``(N, 3)`` float64 points (x right, y down, z forward) in metres.
    """
    z = calibration.fx_px * calibration.baseline_m / np.asarray(disparity_px, dtype=np.float64)
    x = (left_px[:, 0] - calibration.cx_px) * z / calibration.fx_px
    y = (left_px[:, 1] - calibration.cy_px) * z / calibration.fy_px
    return np.column_stack([x, y, z])


def stereo_filter(left_px: np.ndarray, right_px: np.ndarray, config: VoConfig) -> np.ndarray:
    """``(N,)`` bool mask of rectified stereo matches: same row within tolerance, positive disparity."""
    dv = np.abs(left_px[:, 1] - right_px[:, 1])
    disparity = left_px[:, 0] - right_px[:, 0]
    return (dv <= config.stereo_row_tolerance_px) & (disparity >= config.min_disparity_px)


def make_keyframe(
    index: int,
    left_grey: np.ndarray,
    right_grey: np.ndarray,
    calibration: StereoCalibration,
    config: VoConfig,
) -> StereoKeyframe:
    """Detect features in the left image, match them along rows into the right one, triangulate."""
    pixels = detect_features(left_grey, config)
    right_px, ok = track_points(left_grey, right_grey, pixels, None, config, config.lr_check_px)
    pixels, right_px = pixels[ok], right_px[ok]
    left_u = undistort_pixels(pixels, calibration)
    right_u = undistort_pixels(right_px, calibration)
    keep = stereo_filter(left_u, right_u, config)
    points = triangulate_rectified(left_u[keep], left_u[keep, 0] - right_u[keep, 0], calibration)
    return StereoKeyframe(index, left_grey, np.ascontiguousarray(pixels[keep]), points)


def project_points(points_m: np.ndarray, T_cam_ref: np.ndarray, calibration: StereoCalibration) -> tuple[np.ndarray, np.ndarray]:
    """Project ``(N, 3)`` reference-frame points into a camera at ``T_cam_ref`` (undistorted pixels).

    Returns ``(N, 2)`` pixels and an ``(N,)`` bool mask of points in front of the camera.
    """
    p = points_m @ T_cam_ref[:3, :3].T + T_cam_ref[:3, 3]
    front = p[:, 2] > 1e-6
    z = np.where(front, p[:, 2], 1.0)
    u = calibration.fx_px * p[:, 0] / z + calibration.cx_px
    v = calibration.fy_px * p[:, 1] / z + calibration.cy_px
    return np.column_stack([u, v]), front


def distort_pixels(pixels_px: np.ndarray, calibration: StereoCalibration) -> np.ndarray:
    """Apply the calibration's lens distortion to ``(N, 2)`` undistorted pixels (for KLT seeds)."""
    if len(pixels_px) == 0 or not has_distortion(calibration):
        return pixels_px
    K = calibration.K
    normalized = (pixels_px - [calibration.cx_px, calibration.cy_px]) / [calibration.fx_px, calibration.fy_px]
    points = np.column_stack([normalized, np.ones(len(normalized))])
    out, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), K, np.asarray(calibration.distortion, np.float64))
    return out.reshape(-1, 2)


def estimate_pose_pnp(
    points_m: np.ndarray,
    pixels_px: np.ndarray,
    calibration: StereoCalibration,
    config: VoConfig,
) -> PnpResult | None:
    """Relative pose from 3-D keyframe points and their undistorted pixels in the current image.

    ``cv2.solvePnPRansac`` (AP3P minimal sets, EPnP on the inliers), then ``cv2.solvePnPRefineLM``
    on the inliers, re-selecting inliers at the RANSAC threshold and refining once more.

    Args:
        points_m: ``(N, 3)`` points in the keyframe camera frame.
        pixels_px: ``(N, 2)`` undistorted pixels in the current left image.
    Returns:
        a :class:`PnpResult`, or ``None`` if there are too few points or RANSAC fails.
    """
    n = len(points_m)
    if n < max(6, config.min_inliers):
        return None
    K = calibration.K
    obj = np.ascontiguousarray(points_m, dtype=np.float64)
    img = np.ascontiguousarray(pixels_px, dtype=np.float64)
    try:
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            obj, img, K, None,
            iterationsCount=config.ransac_iterations, reprojectionError=config.ransac_reprojection_px,
            confidence=config.ransac_confidence, flags=cv2.SOLVEPNP_AP3P,
        )
    except cv2.error as exc:  # degenerate configurations
        logger.debug("solvePnPRansac failed: %s", exc)
        return None
    if not ok or inliers is None or len(inliers) < 6:
        return None
    idx = inliers.reshape(-1)
    threshold_sq = config.ransac_reprojection_px**2
    for _ in range(2):
        rvec, tvec = cv2.solvePnPRefineLM(obj[idx], img[idx], K, None, rvec, tvec)
        T = se3_from_rvec(rvec, tvec)
        projected, front = project_points(obj, T, calibration)
        err_sq = np.sum((projected - img) ** 2, axis=1)
        new_idx = np.flatnonzero(front & (err_sq <= threshold_sq))
        if len(new_idx) < 6:
            return None
        if np.array_equal(new_idx, idx):
            break
        idx = new_idx
    rmse = float(np.sqrt(np.mean(err_sq[idx])))
    return PnpResult(T, idx, rmse)


def track_keyframe(
    keyframe: StereoKeyframe,
    left_grey: np.ndarray,
    calibration: StereoCalibration,
    config: VoConfig,
    T_cur_ref_guess: np.ndarray | None = None,
) -> tuple[PnpResult | None, int]:
    """Track a keyframe's points into a new left image and solve the relative pose by PnP.

    Args:
        keyframe: the reference frame with its 3-D points.
        left_grey: the new ``(H, W)`` uint8 left image.
        T_cur_ref_guess: ``(4, 4)`` predicted motion (seeds the tracks), or ``None``.
    Returns:
        ``(pnp, n_tracked)``: the :class:`PnpResult` (``None`` on failure) and the number of
        forward-backward consistent tracks.
    """
    if T_cur_ref_guess is None:
        guess = keyframe.pixels_px
    else:
        guess, front = project_points(keyframe.points_m, T_cur_ref_guess, calibration)
        guess = distort_pixels(guess, calibration)
        h, w = left_grey.shape[:2]
        inside = front & (guess[:, 0] >= 0) & (guess[:, 1] >= 0) & (guess[:, 0] < w) & (guess[:, 1] < h)
        guess = np.where(inside[:, None], guess, keyframe.pixels_px)
    tracked, ok = track_points(keyframe.grey, left_grey, keyframe.pixels_px, guess.astype(np.float32), config, config.fb_check_px)
    pixels = undistort_pixels(tracked[ok], calibration)
    pnp = estimate_pose_pnp(keyframe.points_m[ok], pixels, calibration, config)
    return pnp, int(ok.sum())


# ----------------------------------------------------------------------------------------- tracker


def check_calibration(calibration: StereoCalibration | None, where: str = "the calibration") -> StereoCalibration:
    """Raise :class:`OdometryError` unless ``calibration`` can drive stereo VO."""
    if calibration is None:
        raise OdometryError(f"{where} is missing: stereo VO needs the camera intrinsics and the baseline", fix="record the calibration with the images")
    bad = []
    if not (calibration.fx_px > 0 and calibration.fy_px > 0):
        bad.append(f"focal lengths fx={calibration.fx_px}, fy={calibration.fy_px} must be > 0")
    if not calibration.baseline_m > 0:
        bad.append(f"baseline {calibration.baseline_m} m must be > 0 (is the right camera's P[0][3] = -fx*baseline set?)")
    if not (calibration.width_px > 0 and calibration.height_px > 0):
        bad.append(f"image size {calibration.width_px}x{calibration.height_px} must be positive")
    if not all(math.isfinite(float(v)) for v in (calibration.fx_px, calibration.fy_px, calibration.cx_px, calibration.cy_px, calibration.baseline_m)):
        bad.append("intrinsics must be finite")
    if bad:
        raise OdometryError(f"{where} is unusable: " + "; ".join(bad), fix="fix the calibration")
    return calibration


def check_image_size(shape: tuple[int, ...], calibration: StereoCalibration, what: str = "image", where: str = "the calibration") -> None:
    """Raise :class:`OdometryError` if an image's size differs from the calibration's."""
    h, w = int(shape[0]), int(shape[1])
    if (w, h) != (calibration.width_px, calibration.height_px):
        raise OdometryError(
            f"{what} is {w}x{h} px but {where} is for {calibration.width_px}x{calibration.height_px} px",
            fix="record the calibration of these images (or resize the images to the calibrated size)",
        )


class StereoVoTracker:
    """Incremental stereo VO: feed stereo pairs in time order, get one :class:`VoStep` per pair.

    Args:
        calibration: rectified stereo calibration (left intrinsics, baseline, image size).
        config: parameters.
        T_body_camera: ``(4, 4)`` pose of the left camera in the body frame (default: at the body
            origin, looking along body x, see :func:`camera_mount`).
    """

    def __init__(self, calibration: StereoCalibration, config: VoConfig | None = None, *, T_body_camera: np.ndarray | None = None):
        self.calibration = check_calibration(calibration)
        self.config = config or VoConfig()
        self.T_body_camera = camera_mount() if T_body_camera is None else np.asarray(T_body_camera, dtype=np.float64)
        if has_distortion(calibration):
            logger.warning(
                "the calibration has lens distortion %s: images are treated as rectified and feature "
                "positions are undistorted with cv2.undistortPoints (rectify the images for best results)",
                tuple(round(float(k), 6) for k in calibration.distortion),
            )
        self._index = 0
        self._keyframe: StereoKeyframe | None = None
        self._T_odom_keyframe = np.eye(4)
        self._T_odom_prev = np.eye(4)
        self._velocity = np.eye(4)  # T_prev_cur of the last well-tracked frame (camera frame)
        self._fallbacks_in_row = 0
        self._prev_left: np.ndarray | None = None
        self._prev_pose = IDENTITY_POSE
        self.status_counts: dict[TrackStatus, int] = {s: 0 for s in TrackStatus}

    @property
    def frames(self) -> int:
        """Frames processed so far."""
        return self._index

    @property
    def fallbacks(self) -> int:
        """Frames that fell back to the constant-velocity guess."""
        return sum(n for s, n in self.status_counts.items() if s.is_fallback)

    def process(self, left: np.ndarray, right: np.ndarray) -> VoStep:
        """Estimate the pose of the next stereo pair.

        Args:
            left, right: ``(H, W)`` grey or ``(H, W, 3)`` RGB uint8 rectified images, of the
                calibration's size.
        """
        cfg = self.config
        index = self._index
        left_grey, right_grey = to_grey(left), to_grey(right)
        check_image_size(left_grey.shape, self.calibration, "the left image")
        check_image_size(right_grey.shape, self.calibration, "the right image")

        health = image_health(left_grey, self._prev_left, cfg) or image_health(right_grey, None, cfg)
        T_odom_predicted = self._T_odom_prev @ self._velocity
        tracked_keyframe = -1 if self._keyframe is None else self._keyframe.index
        n_tracked, pnp = 0, None
        if health is not None:
            status = health
        elif self._keyframe is None:
            status = TrackStatus.FIRST if index == 0 else TrackStatus.NO_REFERENCE
        else:
            status, n_tracked, pnp = self._track(left_grey, T_odom_predicted)

        if status == TrackStatus.OK:
            T_odom_cur = self._T_odom_keyframe @ invert_se3(pnp.T_cur_ref)
            if self._fallbacks_in_row == 0:  # the previous frame was tracked too
                self._velocity = invert_se3(self._T_odom_prev) @ T_odom_cur
            self._fallbacks_in_row = 0
        elif status == TrackStatus.FIRST:
            T_odom_cur = np.eye(4)
        else:
            T_odom_cur = T_odom_predicted
            self._fallbacks_in_row += 1

        # A new keyframe: at the start, when the keyframe is getting old or losing its points, or
        # when bridging a tracking gap has gone on too long.
        n_stereo = 0
        if status == TrackStatus.OK:
            renew = (
                index - self._keyframe.index >= cfg.keyframe_max_gap_frames
                or len(pnp.inliers) < cfg.keyframe_min_inlier_fraction * self._keyframe.size
            )
        else:
            renew = status in (TrackStatus.FIRST, TrackStatus.NO_REFERENCE) or self._fallbacks_in_row > cfg.max_bridge_frames
        if renew and health is None:
            keyframe = make_keyframe(index, left_grey, right_grey, self.calibration, cfg)
            n_stereo = keyframe.size
            if keyframe.size >= cfg.min_inliers:
                if status.is_fallback:
                    logger.debug("frame %d: re-anchoring on a new keyframe after %d fallback frames", index, self._fallbacks_in_row)
                self._keyframe, self._T_odom_keyframe = keyframe, T_odom_cur
                self._fallbacks_in_row = 0

        quality = VoQuality(
            index=index,
            status=status,
            n_stereo=n_stereo,
            n_tracked=n_tracked,
            n_inliers=0 if pnp is None else len(pnp.inliers),
            reprojection_rmse_px=math.nan if pnp is None else pnp.rmse_px,
            keyframe_index=tracked_keyframe,
        )
        if status.is_fallback:
            logger.debug("frame %d: %s (tracked %d, inliers %d), constant-velocity fallback", index, status.value, n_tracked, quality.n_inliers)
        pose = planar_from_se3(body_pose_from_camera(T_odom_cur, self.T_body_camera))
        step = VoStep(index, self._prev_pose.between(pose) if index else IDENTITY_POSE, pose, T_odom_cur, quality)
        self.status_counts[status] += 1
        self._T_odom_prev = T_odom_cur
        self._prev_pose = pose
        self._prev_left = left_grey
        self._index += 1
        return step

    def _track(self, left_grey: np.ndarray, T_odom_predicted: np.ndarray) -> tuple[TrackStatus, int, PnpResult | None]:
        """Track the keyframe into the current image and solve PnP; ``(status, n_tracked, pnp)``."""
        cfg = self.config
        T_cur_ref_guess = invert_se3(T_odom_predicted) @ self._T_odom_keyframe
        pnp, n_tracked = track_keyframe(self._keyframe, left_grey, self.calibration, cfg, T_cur_ref_guess)
        if pnp is None or len(pnp.inliers) < cfg.min_inliers:
            return TrackStatus.FEW_INLIERS, n_tracked, pnp
        if pnp.rmse_px > cfg.max_reprojection_rmse_px:
            return TrackStatus.HIGH_ERROR, n_tracked, pnp
        return TrackStatus.OK, n_tracked, pnp


# ------------------------------------------------------------------------------------------ runner


@dataclass(frozen=True)
class VoResult:
    """VO over a whole sequence.

    Attributes:
        steps: one :class:`VoStep` per stereo pair, in order.
        elapsed_s: wall time spent in the tracker (image decoding included when the pairs are lazy).
    """

    steps: tuple[VoStep, ...]
    elapsed_s: float

    @property
    def poses(self) -> np.ndarray:
        """``(N, 3)`` cumulative planar odometry ``[x_m, y_m, yaw_rad]``."""
        return np.array([s.T_odom_base for s in self.steps], dtype=np.float64).reshape(-1, 3)

    @property
    def fallback_frames(self) -> list[int]:
        return [s.index for s in self.steps if s.quality.fallback]

    @property
    def pairs_per_s(self) -> float:
        return len(self.steps) / self.elapsed_s if self.elapsed_s > 0 else math.inf

    def status_counts(self) -> dict[str, int]:
        counts: dict[str, int] = {}
        for s in self.steps:
            counts[s.quality.status.value] = counts.get(s.quality.status.value, 0) + 1
        return counts

    def summary(self) -> dict:
        """JSON-ready summary: frames, fallbacks by status, inlier and error medians, speed."""
        ok = [s.quality for s in self.steps if s.quality.status == TrackStatus.OK]
        return {
            "frames": len(self.steps),
            "fallback_frames": len(self.fallback_frames),
            "status_counts": self.status_counts(),
            "median_inliers": float(np.median([q.n_inliers for q in ok])) if ok else 0.0,
            "median_reprojection_rmse_px": float(np.median([q.reprojection_rmse_px for q in ok])) if ok else None,
            "elapsed_s": self.elapsed_s,
            "pairs_per_s": self.pairs_per_s,
        }


def run_vo(
    pairs: Iterable[tuple[np.ndarray, np.ndarray]],
    calibration: StereoCalibration,
    config: VoConfig | None = None,
    *,
    T_body_camera: np.ndarray | None = None,
    on_step: Callable[[VoStep], None] | None = None,
) -> VoResult:
    """Run stereo VO over ``(left, right)`` image pairs in time order.

    Args:
        pairs: iterable of ``(left, right)`` images (see :meth:`StereoVoTracker.process`).
        on_step: called with every step as it is produced (progress bars, streaming writers).
    """
    tracker = StereoVoTracker(calibration, config, T_body_camera=T_body_camera)
    steps = []
    start = time.perf_counter()
    for left, right in pairs:
        step = tracker.process(left, right)
        steps.append(step)
        if on_step is not None:
            on_step(step)
    elapsed = time.perf_counter() - start
    result = VoResult(tuple(steps), elapsed)
    if result.fallback_frames:
        logger.warning("VO fell back to constant velocity on %d of %d frames: %s", len(result.fallback_frames), len(steps), result.status_counts())
    return result
