"""Small ROS bags written by ``rosbags``' own writers (ROS 1 ``.bag``, ROS 2 sqlite3 and MCAP), for tests.

Messages are built from the writer's typestore (ROS 1 Noetic or ROS 2 Humble definitions), so the
bags are what a ROS system would have recorded. Helpers build the messages lcv-replay imports.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

BagKind = Literal["ros1", "ros2-sqlite3", "ros2-mcap"]


@dataclass
class BagBuilder:
    """Messages collected by topic, written in receive-time order by :meth:`write`."""

    kind: BagKind = "ros2-mcap"
    messages: list[tuple[int, str, str, Any]] = field(default_factory=list)

    def __post_init__(self) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.ts = get_typestore(Stores.ROS1_NOETIC if self.kind == "ros1" else Stores.ROS2_HUMBLE)
        self.T = self.ts.types

    # -- messages ---------------------------------------------------------------------------------
    def header(self, stamp_ns: int, frame_id: str) -> Any:
        stamp = self.T["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
        if self.kind == "ros1":
            return self.T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame_id)
        return self.T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)

    def pose(self, x: float, y: float, yaw: float, z: float = 0.0) -> Any:
        T = self.T
        return T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=x, y=y, z=z),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)),
        )

    def odometry(self, stamp_ns: int, x: float, y: float, yaw: float) -> Any:
        T = self.T
        zero = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        return T["nav_msgs/msg/Odometry"](
            header=self.header(stamp_ns, "odom"), child_frame_id="base_link",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose(x, y, yaw), covariance=np.zeros(36)),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=T["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=np.zeros(36)),
        )

    def pose_stamped(self, stamp_ns: int, x: float, y: float, yaw: float) -> Any:
        return self.T["geometry_msgs/msg/PoseStamped"](header=self.header(stamp_ns, "world"), pose=self.pose(x, y, yaw))

    def image(self, stamp_ns: int, array: np.ndarray, frame_id: str = "camera") -> Any:
        array = np.ascontiguousarray(array)
        encoding = "mono8" if array.ndim == 2 else "rgb8"
        return self.T["sensor_msgs/msg/Image"](
            header=self.header(stamp_ns, frame_id), height=array.shape[0], width=array.shape[1], encoding=encoding,
            is_bigendian=0, step=array.shape[1] * (1 if array.ndim == 2 else 3), data=array.reshape(-1).view(np.uint8),
        )

    def compressed_png(self, stamp_ns: int, array: np.ndarray, frame_id: str = "camera") -> Any:
        import cv2

        bgr = array if array.ndim == 2 else cv2.cvtColor(array, cv2.COLOR_RGB2BGR)
        ok, png = cv2.imencode(".png", bgr)
        assert ok
        return self.T["sensor_msgs/msg/CompressedImage"](header=self.header(stamp_ns, frame_id), format="png", data=png.reshape(-1))

    def camera_info(self, stamp_ns: int, width: int, height: int, fx: float, cx: float, cy: float, tx: float = 0.0) -> Any:
        P = np.array([fx, 0, cx, tx, 0, fx, cy, 0, 0, 0, 1, 0], dtype=np.float64)
        K = np.array([fx, 0, cx, 0, fx, cy, 0, 0, 1], dtype=np.float64)
        R = np.eye(3).reshape(-1)
        roi = self.T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        fields = dict(header=self.header(stamp_ns, "camera"), height=height, width=width, distortion_model="plumb_bob",
                      binning_x=0, binning_y=0, roi=roi)
        if self.kind == "ros1":
            return self.T["sensor_msgs/msg/CameraInfo"](**fields, D=np.zeros(5), K=K, R=R, P=P)
        return self.T["sensor_msgs/msg/CameraInfo"](**fields, d=np.zeros(5), k=K, r=R, p=P)

    def tf(self, transforms: list[tuple[str, str, int, tuple[float, float, float], float]]) -> Any:
        """A ``tf2_msgs/TFMessage`` of ``(parent, child, stamp_ns, translation, yaw)`` planar transforms."""
        T = self.T
        items = [
            T["geometry_msgs/msg/TransformStamped"](
                header=self.header(stamp, parent), child_frame_id=child,
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=t[0], y=t[1], z=t[2]),
                    rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)),
                ),
            )
            for parent, child, stamp, t, yaw in transforms
        ]
        return T["tf2_msgs/msg/TFMessage"](transforms=items)

    # -- writing ----------------------------------------------------------------------------------
    def add(self, topic: str, log_time_ns: int, message: Any) -> None:
        self.messages.append((int(log_time_ns), topic, message.__msgtype__, message))

    def write(self, path: Path) -> Path:
        """Write the bag: ``path`` is the ``.bag`` file or the ROS 2 bag folder."""
        ordered = sorted(self.messages, key=lambda m: m[0])
        if self.kind == "ros1":
            from rosbags.rosbag1 import Writer

            writer = Writer(path)
            serialize = self.ts.serialize_ros1
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            plugin = StoragePlugin.MCAP if self.kind == "ros2-mcap" else StoragePlugin.SQLITE3
            writer = Writer(path, version=9, storage_plugin=plugin)
            serialize = self.ts.serialize_cdr
        connections: dict[str, Any] = {}
        with writer:
            for log_time, topic, msgtype, message in ordered:
                if topic not in connections:
                    connections[topic] = writer.add_connection(topic, msgtype, typestore=self.ts)
                writer.write(connections[topic], log_time, serialize(message, msgtype))
        return path
