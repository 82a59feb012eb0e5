"""Stereo visual odometry configuration.

The paper computes odometry with libviso2 (Geiger et al., "StereoScan", IV 2011; Tanaka, SII 2016,
sec. IV). Our VO follows the same recipe on OpenCV parts: bucketed corner features, stereo matching
along rectified rows, triangulation with the baseline, temporal tracking, PnP + RANSAC, then
least-squares refinement. Where a default mirrors libviso2 the comment says so.
"""

from __future__ import annotations

from dataclasses import dataclass

from lcv_replay.errors import require


@dataclass(frozen=True)
class VoConfig:
    """Parameters of :class:`lcv_replay.vo.stereo_vo.StereoVoTracker`.

    Features and stereo:
        fast_threshold: FAST corner threshold (grey levels).
        buckets: number of square buckets features are spread over; the bucket side is
            ``sqrt(W * H / buckets)`` (40 px at 640x480, 49 px on KITTI; libviso2: 50 px).
        features_per_bucket: strongest corners kept per bucket (libviso2: 2).
        max_features: hard cap on features per frame, strongest first.
        stereo_row_tolerance_px: rectified stereo: a right match must lie on the same row within this.
        min_disparity_px: matches with a smaller (or negative) disparity are dropped (Z = fx b / d).
        lr_check_px: left->right->left round-trip error allowed for a stereo match (0: no check).

    Tracking and pose:
        klt_window_px: Lucas-Kanade window side (odd).
        klt_levels: pyramid levels above the full image (3 covers ~40 px motions at 11 px windows;
            temporal tracks are seeded by a constant-velocity prediction).
        klt_iterations: Lucas-Kanade iterations per pyramid level (stops earlier at 0.01 px).
        fb_check_px: forward-backward error allowed for a temporal track (0: no backward track;
            PnP RANSAC rejects the outliers).
        ransac_reprojection_px: PnP RANSAC inlier threshold (libviso2: 2 px).
        ransac_iterations: PnP RANSAC iterations.
        ransac_confidence: PnP RANSAC confidence.
        min_inliers: fewer PnP inliers than this is a tracking failure.
        max_reprojection_rmse_px: a refined pose with a larger inlier RMSE is a tracking failure.
        keyframe_max_gap_frames: frames are tracked against a keyframe at most this many frames old
            (1: frame-to-frame VO, like libviso2).
        keyframe_min_inlier_fraction: a new keyframe is also made when the PnP inliers fall below
            this fraction of the keyframe's stereo points.

    Image health (failures fall back to a constant-velocity guess):
        dark_mean_grey: an image with a mean grey level below this is "dark".
        blank_std_grey: an image with a grey-level standard deviation below this is "blank".
        max_bridge_frames: after a failure the last good keyframe is kept and the next frames are
            tracked against it (bridging the gap); after this many consecutive failures the tracker
            re-anchors on the current frame.
    """

    fast_threshold: int = 12
    buckets: int = 192
    features_per_bucket: int = 4
    max_features: int = 1200
    stereo_row_tolerance_px: float = 1.0
    min_disparity_px: float = 0.5
    lr_check_px: float = 0.5
    klt_window_px: int = 11
    klt_levels: int = 3
    klt_iterations: int = 30
    fb_check_px: float = 0.0
    ransac_reprojection_px: float = 1.5
    ransac_iterations: int = 150
    ransac_confidence: float = 0.999
    min_inliers: int = 25
    max_reprojection_rmse_px: float = 1.5
    keyframe_max_gap_frames: int = 1
    keyframe_min_inlier_fraction: float = 0.5
    dark_mean_grey: float = 10.0
    blank_std_grey: float = 2.0
    max_bridge_frames: int = 5

    def __post_init__(self) -> None:
        require(1 <= self.fast_threshold <= 254, "vo.fast_threshold", self.fast_threshold, "an integer in 1..254")
        require(self.buckets >= 1, "vo.buckets", self.buckets, "an integer >= 1")
        require(self.features_per_bucket >= 1, "vo.features_per_bucket", self.features_per_bucket, "an integer >= 1")
        require(self.max_features >= 8, "vo.max_features", self.max_features, "an integer >= 8")
        require(self.stereo_row_tolerance_px > 0, "vo.stereo_row_tolerance_px", self.stereo_row_tolerance_px, "a number > 0")
        require(self.min_disparity_px > 0, "vo.min_disparity_px", self.min_disparity_px, "a number > 0")
        require(self.lr_check_px >= 0, "vo.lr_check_px", self.lr_check_px, "a number >= 0 (0: no check)")
        require(self.klt_window_px >= 5 and self.klt_window_px % 2 == 1, "vo.klt_window_px", self.klt_window_px, "an odd integer >= 5")
        require(0 <= self.klt_levels <= 8, "vo.klt_levels", self.klt_levels, "an integer in 0..8")
        require(self.klt_iterations >= 1, "vo.klt_iterations", self.klt_iterations, "an integer >= 1")
        require(self.fb_check_px >= 0, "vo.fb_check_px", self.fb_check_px, "a number >= 0 (0: no check)")
        require(self.ransac_reprojection_px > 0, "vo.ransac_reprojection_px", self.ransac_reprojection_px, "a number > 0")
        require(self.ransac_iterations >= 1, "vo.ransac_iterations", self.ransac_iterations, "an integer >= 1")
        require(0 < self.ransac_confidence < 1, "vo.ransac_confidence", self.ransac_confidence, "a number in (0, 1)")
        require(self.min_inliers >= 6, "vo.min_inliers", self.min_inliers, "an integer >= 6")
        require(self.max_reprojection_rmse_px > 0, "vo.max_reprojection_rmse_px", self.max_reprojection_rmse_px, "a number > 0")
        require(self.keyframe_max_gap_frames >= 1, "vo.keyframe_max_gap_frames", self.keyframe_max_gap_frames, "an integer >= 1")
        require(0 <= self.keyframe_min_inlier_fraction <= 1, "vo.keyframe_min_inlier_fraction", self.keyframe_min_inlier_fraction, "a number in [0, 1]")
        require(0 <= self.dark_mean_grey < 255, "vo.dark_mean_grey", self.dark_mean_grey, "a number in [0, 255)")
        require(self.blank_std_grey >= 0, "vo.blank_std_grey", self.blank_std_grey, "a number >= 0")
        require(self.max_bridge_frames >= 0, "vo.max_bridge_frames", self.max_bridge_frames, "an integer >= 0")
