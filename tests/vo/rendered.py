"""Rendered stereo pairs with known motion, from the synthetic street world (recorders/synthetic_world)."""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np

from lcv_replay.records import Pose2D, StereoCalibration
from recorders.synthetic_world import SyntheticWorld, make_route

WIDTH_PX, HEIGHT_PX = 320, 240


@functools.lru_cache(maxsize=1)
def world() -> SyntheticWorld:
    """The seed-0 world (textures are generated on first render, ~5 s, then cached)."""
    return SyntheticWorld.from_seed(0)


def calibration(width_px: int = WIDTH_PX, height_px: int = HEIGHT_PX) -> StereoCalibration:
    return world().calibration(width_px, height_px)


def route(frames: int) -> np.ndarray:
    """``(frames, 3)`` true poses of the default route (starts driving east along a street)."""
    return make_route(world(), frames)


def render_grey(pose: Pose2D, width_px: int = WIDTH_PX, height_px: int = HEIGHT_PX) -> tuple[np.ndarray, np.ndarray]:
    """Grey ``(H, W)`` uint8 left and right images seen from the body pose ``T_world_body``."""
    left, right = world().render_stereo(pose, width_px=width_px, height_px=height_px)
    return cv2.cvtColor(left, cv2.COLOR_RGB2GRAY), cv2.cvtColor(right, cv2.COLOR_RGB2GRAY)


def add_noise(image: np.ndarray, sigma_grey: float, seed: int) -> np.ndarray:
    """Image with additive Gaussian sensor noise (deterministic for ``seed``)."""
    rng = np.random.default_rng(seed)
    return np.clip(image + rng.normal(0.0, sigma_grey, image.shape), 0, 255).astype(np.uint8)


def distort(image: np.ndarray, calib: StereoCalibration, distortion: tuple[float, ...]) -> np.ndarray:
    """The image a lens with ``distortion`` (plumb bob) and the same ``K`` would have taken.

    Every output (distorted) pixel samples the pinhole image at its undistorted position.
    """
    h, w = image.shape[:2]
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pixels = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    undistorted = cv2.undistortPoints(pixels, calib.K, np.asarray(distortion, np.float64), P=calib.K).reshape(h, w, 2)
    return cv2.remap(image, undistorted[..., 0].astype(np.float32), undistorted[..., 1].astype(np.float32), cv2.INTER_LINEAR)


def yaw_deg(pose: Pose2D) -> float:
    return math.degrees(pose.yaw_rad)
