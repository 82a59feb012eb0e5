"""Pure conversions between lcv-replay records and the log's message types.

Protobuf messages are the ``foxglove`` schemas (``foxglove_schemas_protobuf``); the loop-closure
topics are JSON messages with the JSON schemas below. Nothing here touches files.

Planar convention (docs/log-format.md): a :class:`Pose2D` ``(x_m, y_m, yaw_rad)`` is written as a
3-D pose with ``z = 0`` and the quaternion of a rotation of ``yaw_rad`` about ``+z``
``(x, y, z, w) = (0, 0, sin(yaw/2), cos(yaw/2))``. Reading a 3-D orientation back takes the yaw of
its ZYX Euler decomposition (the heading of the body's x axis projected on the ground plane).
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

from lcv_replay.records import LoopCandidate, Pose2D, StereoCalibration

# Schema names of the protobuf messages this format uses, as stored in MCAP Schema records.
COMPRESSED_IMAGE_SCHEMA = "foxglove.CompressedImage"
RAW_IMAGE_SCHEMA = "foxglove.RawImage"
CAMERA_CALIBRATION_SCHEMA = "foxglove.CameraCalibration"
POSE_IN_FRAME_SCHEMA = "foxglove.PoseInFrame"
FRAME_TRANSFORM_SCHEMA = "foxglove.FrameTransform"
LOOP_CANDIDATE_SCHEMA = "lcv.LoopCandidate"
TRUE_LOOP_SCHEMA = "lcv.TrueLoop"

PROTOBUF_CLASSES: dict[str, Any] = {
    COMPRESSED_IMAGE_SCHEMA: CompressedImage,
    RAW_IMAGE_SCHEMA: RawImage,
    CAMERA_CALIBRATION_SCHEMA: CameraCalibration,
    POSE_IN_FRAME_SCHEMA: PoseInFrame,
    FRAME_TRANSFORM_SCHEMA: FrameTransform,
}

_POSE_2D_JSON_SCHEMA = {
    "type": ["object", "null"],
    "description": "Planar pose T_match_query: x forward, y left (metres), yaw about +z (radians).",
    "properties": {
        "x_m": {"type": "number"},
        "y_m": {"type": "number"},
        "yaw_rad": {"type": "number"},
    },
    "required": ["x_m", "y_m", "yaw_rad"],
}

LOOP_CANDIDATE_JSON_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": LOOP_CANDIDATE_SCHEMA,
    "description": (
        "A loop-closure candidate from a place recognizer: frame query_frame (the later frame) is "
        "the same place as match_frame (earlier). Frame indices are 0..N-1 in time order "
        "(docs/log-format.md). log_time = the query frame's stamp, sequence = query_frame."
    ),
    "type": "object",
    "properties": {
        "query_frame": {"type": "integer", "minimum": 1},
        "match_frame": {"type": "integer", "minimum": 0},
        "similarity": {"type": "number", "description": "larger is more similar; source-specific"},
        "hamming": {"type": ["integer", "null"], "description": "Hamming distance of binary codes"},
        "source": {"type": "string", "description": "who proposed it, e.g. retrieval, DLoopDetector"},
        "T_match_query": _POSE_2D_JSON_SCHEMA,
        "information": {
            "type": ["array", "null"],
            "description": "upper triangle (I_xx, I_xy, I_xyaw, I_yy, I_yyaw, I_yawyaw), g2o order",
            "items": {"type": "number"},
            "minItems": 6,
            "maxItems": 6,
        },
    },
    "required": ["query_frame", "match_frame", "similarity", "source"],
}

TRUE_LOOP_JSON_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": TRUE_LOOP_SCHEMA,
    "description": "A labelled true loop closure (query_frame > match_frame). log_time = the query frame's stamp.",
    "type": "object",
    "properties": {
        "query_frame": {"type": "integer", "minimum": 1},
        "match_frame": {"type": "integer", "minimum": 0},
    },
    "required": ["query_frame", "match_frame"],
}


def _set_stamp(message: Any, stamp_ns: int) -> None:
    message.timestamp.seconds = stamp_ns // 1_000_000_000
    message.timestamp.nanos = stamp_ns % 1_000_000_000


def yaw_quaternion(yaw_rad: float) -> tuple[float, float, float, float]:
    """``(x, y, z, w)`` of a rotation of ``yaw_rad`` about ``+z``."""
    return (0.0, 0.0, math.sin(0.5 * yaw_rad), math.cos(0.5 * yaw_rad))


def quaternion_yaw(x: float, y: float, z: float, w: float) -> float:
    """Yaw (rotation about ``+z``) of a unit quaternion, from its ZYX Euler decomposition."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def pose_in_frame(pose: Pose2D, stamp_ns: int, frame_id: str) -> PoseInFrame:
    """A planar pose as ``foxglove.PoseInFrame`` (z = 0, yaw quaternion)."""
    message = PoseInFrame(frame_id=frame_id)
    _set_stamp(message, stamp_ns)
    message.pose.position.x = pose.x_m
    message.pose.position.y = pose.y_m
    message.pose.position.z = 0.0
    qx, qy, qz, qw = yaw_quaternion(pose.yaw_rad)
    message.pose.orientation.x, message.pose.orientation.y = qx, qy
    message.pose.orientation.z, message.pose.orientation.w = qz, qw
    return message


def frame_transform(pose: Pose2D, stamp_ns: int, parent_frame_id: str, child_frame_id: str) -> FrameTransform:
    """A planar pose ``T_parent_child`` as ``foxglove.FrameTransform``."""
    message = FrameTransform(parent_frame_id=parent_frame_id, child_frame_id=child_frame_id)
    _set_stamp(message, stamp_ns)
    message.translation.x = pose.x_m
    message.translation.y = pose.y_m
    message.translation.z = 0.0
    qx, qy, qz, qw = yaw_quaternion(pose.yaw_rad)
    message.rotation.x, message.rotation.y, message.rotation.z, message.rotation.w = qx, qy, qz, qw
    return message


def pose_from_pose_in_frame(message: PoseInFrame) -> Pose2D:
    """The planar pose of a ``foxglove.PoseInFrame`` (z dropped, yaw of the orientation).

    An all-zero quaternion (an unset field) reads as the identity rotation.
    """
    q = message.pose.orientation
    if q.x == 0.0 and q.y == 0.0 and q.z == 0.0 and q.w == 0.0:
        yaw = 0.0
    else:
        yaw = quaternion_yaw(q.x, q.y, q.z, q.w)
    return Pose2D(float(message.pose.position.x), float(message.pose.position.y), yaw)


def calibration_messages(
    calib: StereoCalibration, stamp_ns: int, right_frame_id: str = "camera_right"
) -> tuple[CameraCalibration, CameraCalibration]:
    """Left and right ``foxglove.CameraCalibration`` of a rectified stereo pair (ROS convention).

    Both share K; R is the identity (rectified); the right camera's ``P[0, 3] = -fx * baseline_m``.
    """
    K = [calib.fx_px, 0.0, calib.cx_px, 0.0, calib.fy_px, calib.cy_px, 0.0, 0.0, 1.0]
    R = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    messages = []
    for frame_id, tx in ((calib.frame_id, 0.0), (right_frame_id, -calib.fx_px * calib.baseline_m)):
        message = CameraCalibration(
            frame_id=frame_id,
            width=calib.width_px,
            height=calib.height_px,
            distortion_model="plumb_bob",
            D=list(calib.distortion) if frame_id == calib.frame_id else [0.0] * len(calib.distortion),
            K=K,
            R=R,
            P=[calib.fx_px, 0.0, calib.cx_px, tx, 0.0, calib.fy_px, calib.cy_px, 0.0, 0.0, 0.0, 1.0, 0.0],
        )
        _set_stamp(message, stamp_ns)
        messages.append(message)
    return messages[0], messages[1]


def calibration_from_messages(left: CameraCalibration, right: CameraCalibration | None) -> StereoCalibration:
    """Rebuild a :class:`StereoCalibration` from the left message and the right one's ``P[0, 3]``.

    Without a right calibration the baseline is 0 (a monocular log).
    """
    if len(left.P) == 12:
        fx, cx, fy, cy = left.P[0], left.P[2], left.P[5], left.P[6]
    else:
        fx, cx, fy, cy = left.K[0], left.K[2], left.K[4], left.K[5]
    baseline_m = 0.0
    if right is not None and len(right.P) == 12 and right.P[0] != 0.0:
        baseline_m = -right.P[3] / right.P[0]
    return StereoCalibration(
        width_px=int(left.width),
        height_px=int(left.height),
        fx_px=float(fx),
        fy_px=float(fy),
        cx_px=float(cx),
        cy_px=float(cy),
        baseline_m=float(baseline_m),
        distortion=tuple(float(d) for d in left.D) or (0.0, 0.0, 0.0, 0.0, 0.0),
        frame_id=left.frame_id or "camera_left",
    )


def candidate_to_json(candidate: LoopCandidate) -> bytes:
    """A :class:`LoopCandidate` as a JSON message of schema ``lcv.LoopCandidate``."""
    T = candidate.T_match_query
    return json.dumps(
        {
            "query_frame": int(candidate.query_frame),
            "match_frame": int(candidate.match_frame),
            "similarity": float(candidate.similarity),
            "hamming": None if candidate.hamming is None else int(candidate.hamming),
            "source": str(candidate.source),
            "T_match_query": None if T is None else {"x_m": float(T.x_m), "y_m": float(T.y_m), "yaw_rad": float(T.yaw_rad)},
            "information": None if candidate.information is None else [float(v) for v in candidate.information],
        },
        separators=(",", ":"),
        allow_nan=False,
    ).encode()


def candidate_from_json(data: bytes) -> LoopCandidate:
    """Parse an ``lcv.LoopCandidate`` JSON message. Raises ``ValueError``/``KeyError``/``TypeError`` on bad content."""
    obj = json.loads(data)
    T = obj.get("T_match_query")
    info = obj.get("information")
    if info is not None and len(info) != 6:
        raise ValueError(f"information has {len(info)} values, expected 6")
    hamming = obj.get("hamming")
    return LoopCandidate(
        query_frame=int(obj["query_frame"]),
        match_frame=int(obj["match_frame"]),
        similarity=float(obj.get("similarity", 1.0)),
        hamming=None if hamming is None else int(hamming),
        source=str(obj.get("source", "unknown")),
        T_match_query=None if T is None else Pose2D(float(T["x_m"]), float(T["y_m"]), float(T["yaw_rad"])),
        information=None if info is None else tuple(float(v) for v in info),  # type: ignore[arg-type]
    )


def true_loop_to_json(query_frame: int, match_frame: int) -> bytes:
    """A labelled true pair as a JSON message of schema ``lcv.TrueLoop``."""
    return json.dumps({"query_frame": int(query_frame), "match_frame": int(match_frame)}, separators=(",", ":")).encode()


def true_loop_from_json(data: bytes) -> tuple[int, int]:
    """Parse an ``lcv.TrueLoop`` JSON message into ``(query_frame, match_frame)``."""
    obj = json.loads(data)
    return int(obj["query_frame"]), int(obj["match_frame"])


def information_to_json(information: np.ndarray | None) -> str:
    """A ``(3, 3)`` information matrix as a JSON list of rows, or ``"null"``."""
    if information is None:
        return "null"
    return json.dumps(np.asarray(information, dtype=np.float64).tolist())


def information_from_json(text: str | None) -> np.ndarray | None:
    """Inverse of :func:`information_to_json`: a ``(3, 3)`` float64 array or ``None``."""
    if text is None or text == "null":
        return None
    return np.asarray(json.loads(text), dtype=np.float64).reshape(3, 3)
