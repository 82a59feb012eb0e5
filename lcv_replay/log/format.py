"""The lcv-replay MCAP log format: topic names, schemas and conventions (docs/log-format.md).

Every message that belongs to a frame carries the frame index in the MCAP message ``sequence`` field
and the frame's ``stamp_ns`` as ``log_time`` (and ``publish_time``).
"""

from __future__ import annotations

import math

LEFT_IMAGE_TOPIC = "/stereo/left/image"  # foxglove.CompressedImage (png default, jpeg) or foxglove.RawImage
RIGHT_IMAGE_TOPIC = "/stereo/right/image"
LEFT_CALIBRATION_TOPIC = "/stereo/left/calibration"  # foxglove.CameraCalibration
RIGHT_CALIBRATION_TOPIC = "/stereo/right/calibration"  # P[0][3] = -fx * baseline_m, as in ROS
ODOM_TOPIC = "/odom"  # foxglove.PoseInFrame, frame_id "odom", planar (x forward, y left, yaw about +z)
TF_TOPIC = "/tf"  # foxglove.FrameTransform odom -> base_link, mirrors /odom for viewers
GROUND_TRUTH_TOPIC = "/ground_truth/pose"  # foxglove.PoseInFrame, frame_id "world"
LOOP_CANDIDATES_TOPIC = "/loop_candidates"  # JSON schema lcv.LoopCandidate
TRUE_LOOPS_TOPIC = "/ground_truth/loops"  # JSON schema lcv.TrueLoop

ODOM_FRAME_ID = "odom"
BASE_FRAME_ID = "base_link"
WORLD_FRAME_ID = "world"

METADATA_NAME = "lcv"  # MCAP metadata record: dataset, nominal_rate_hz, recorder, version, units
RECORDER_CONFIG_METADATA_NAME = "lcv.recorder_config"  # the recorder's full configuration (JSON values)

FORMAT_VERSION = "1"

#: Plausibility bounds of the values a log carries (beyond them a value is damage, not data): planar
#: coordinates within ±1e8 m (100,000 km: any Earth-fixed frame fits), information entries within
#: ±1e12 (a standard deviation of a micrometre).
MAX_COORDINATE_M = 1e8
MAX_INFORMATION = 1e12


def pose_problem(x_m: float, y_m: float, yaw_rad: float) -> str | None:
    """Why a planar pose cannot be data (``"not finite"``, ``"out of range"``), or ``None``."""
    if not all(map(math.isfinite, (x_m, y_m, yaw_rad))):
        return "not finite"
    if abs(x_m) > MAX_COORDINATE_M or abs(y_m) > MAX_COORDINATE_M:
        return f"out of range (|x|, |y| <= {MAX_COORDINATE_M:g} m)"
    return None


def information_problem(values) -> str | None:
    """Why information-matrix entries cannot be data, or ``None``."""
    if not all(math.isfinite(float(v)) for v in values):
        return "not finite"
    if any(abs(float(v)) > MAX_INFORMATION for v in values):
        return f"out of range (entries within ±{MAX_INFORMATION:g})"
    return None


#: `lcv` metadata key: what the recorder accepted but warned about, a JSON object of counts.
RECORDER_WARNINGS_KEY = "recorder_warnings"
#: Human names of the counts (``lcv-replay info``, the record summary); unknown keys print as they are.
RECORDER_WARNING_NAMES = {
    "singular_odometry_information": "odometry edges with a singular or non-positive-definite information matrix",
    "singular_loop_information": "loop edges with a singular or non-positive-definite information matrix",
    "duplicate_edges": "duplicate edges (the same two vertices as an earlier edge)",
}


def describe_warnings(counts: dict[str, int]) -> str:
    """``'3 duplicate edges (...), 1 odometry edges with ...'`` (empty for no warning)."""
    return ", ".join(f"{n} {RECORDER_WARNING_NAMES.get(key, key)}" for key, n in sorted(counts.items()) if n)

# Written into the `lcv` metadata record so that a log explains itself.
FRAME_CONVENTIONS = (
    "planar REP-103: x forward, y left, yaw counter-clockwise about +z; /odom is T_odom_base_link, "
    "/ground_truth/pose is T_world_base_link; 3-D poses are stored with z = 0 and a yaw-only quaternion"
)
FRAME_INDEX_CONVENTION = (
    "frame i (0..N-1 in time order) has log_time = publish_time = its stamp_ns; every message of frame i "
    "carries MCAP sequence = i; loop candidates and labels carry log_time = the query frame's stamp_ns "
    "and sequence = query_frame"
)
