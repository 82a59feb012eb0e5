"""ROS 2 importer: the real nav2 TurtleBot bag (odometry only), and a stereo bag written with the
real ``mcap-ros2-support`` CDR writer from the real KITTI 06 frames."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from lcv_replay.cli import app
from lcv_replay.log.reader import open_log
from recorders.common import read_image
from recorders.ros2 import Ros2Options, image_to_array, record_ros2
from tests.shared_data import shared_path
from tests.recorders.trees import KITTI06_CX, KITTI06_CY, KITTI06_FX, KITTI06_FX_BASELINE

SEP = "\n" + "=" * 80 + "\n"
HEADER_DEFS = "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id" + SEP + "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
IMAGE_DEF = "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\nuint32 step\nuint8[] data" + SEP + HEADER_DEFS
COMPRESSED_DEF = "std_msgs/Header header\nstring format\nuint8[] data" + SEP + HEADER_DEFS
CAMERA_INFO_DEF = (
    "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] d\nfloat64[9] k\n"
    "float64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\nsensor_msgs/RegionOfInterest roi" + SEP
    + "MSG: sensor_msgs/RegionOfInterest\nuint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify" + SEP + HEADER_DEFS
)


def _nav2_decoded(topic: str) -> list[tuple[int, object]]:
    """(header stamp ns, message) of a topic of the nav2 bag, decoded directly with mcap_ros2."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with shared_path("ros2", "nav2_turtlebot.mcap").open("rb") as handle:
        reader = make_reader(handle, decoder_factories=[DecoderFactory()])
        return [
            (m.header.stamp.sec * 10**9 + m.header.stamp.nanosec, m)
            for _s, _c, _msg, m in reader.iter_decoded_messages(topics=[topic], log_time_order=True)
        ]


def test_nav2_turtlebot_odometry_round_trip(tmp_path: Path) -> None:
    bag = shared_path("ros2", "nav2_turtlebot.mcap")
    out = tmp_path / "nav2.mcap"
    stats = record_ros2(bag, out, Ros2Options(ground_truth_topic="/amcl_pose"))
    odom = _nav2_decoded("/odom")
    stamps = sorted({s for s, _ in odom})
    assert stats.frames == len(stamps) == 2639 and not stats.has_images
    with open_log(out) as log:
        assert np.array_equal(log.frame_stamps_ns, stamps)
        first = {}
        for s, m in odom:
            first.setdefault(s, m)
        q = [first[s].pose.pose.orientation for s in stamps]
        expected_yaw = np.array([2.0 * math.atan2(o.z, o.w) for o in q])  # planar robot: yaw about z only
        poses = log.odometry()
        assert np.allclose(poses[:, 0], [first[s].pose.pose.position.x for s in stamps])
        assert np.allclose(poses[:, 1], [first[s].pose.pose.position.y for s in stamps])
        assert np.allclose(np.cos(poses[:, 2] - expected_yaw), 1.0)
        # /amcl_pose (135 poses) interpolated onto the odometry stamps where it is dense enough.
        truth = log.ground_truth()
        assert log.info.has_ground_truth and np.isfinite(truth).any()
        assert log.info.metadata["recorder"] == "ros2"


def test_nav2_thinning_and_cli_errors(tmp_path: Path) -> None:
    bag = shared_path("ros2", "nav2_turtlebot.mcap")
    stats = record_ros2(bag, tmp_path / "10hz.mcap", Ros2Options(max_rate_hz=10.0))
    with open_log(tmp_path / "10hz.mcap") as log:
        stamps = log.frame_stamps_ns
        assert np.diff(stamps).min() >= 100_000_000
        duration_s = (stamps[-1] - stamps[0]) / 1e9
        # At most 10 Hz; /odom arrives at ~27 Hz with jitter, so a kept frame is at most ~40 ms late.
        assert 0.7 * duration_s * 10 < stats.frames <= duration_s * 10 + 1
    runner = CliRunner()
    result = runner.invoke(app, ["record", "ros2", str(bag), "-o", str(tmp_path / "x.mcap"), "--left-topic", "/camera/left/image_raw"])
    assert result.exit_code == 2
    assert "topic /camera/left/image_raw (--left-topic) is not in the file" in result.output
    assert "/odom (nav_msgs/msg/Odometry)" in result.output and "/amcl_pose (geometry_msgs/msg/PoseWithCovarianceStamped)" in result.output
    result = runner.invoke(app, ["record", "ros2", str(bag), "-o", str(tmp_path / "x.mcap"), "--odom-topic", "/tf"])
    assert result.exit_code == 2 and "has type tf2_msgs/msg/TFMessage, expected nav_msgs/msg/Odometry" in result.output
    not_mcap = tmp_path / "bag.mcap"
    not_mcap.write_bytes(b"definitely not an mcap file")
    result = runner.invoke(app, ["record", "ros2", str(not_mcap), "-o", str(tmp_path / "x.mcap")])
    assert result.exit_code == 2 and "not a readable MCAP file" in result.output
    assert not (tmp_path / "x.mcap").exists()


def _write_stereo_bag(path: Path) -> dict:
    """A ROS 2 bag: mono8 Image left, PNG CompressedImage right, CameraInfo pair, Odometry at 2x.

    Images: the real KITTI 06 left frames 12 and 13 and the real right frame 12 (reused as the
    right image of frame 13). Odometry: the nav2 bag's real Odometry definition, straight motion.
    """
    import cv2
    from mcap_ros2.writer import Writer

    src = shared_path("kitti06_frames")
    nav2 = shared_path("ros2", "nav2_turtlebot.mcap")
    from mcap.reader import make_reader

    with nav2.open("rb") as handle:
        summary = make_reader(handle).get_summary()
        odom_schema = next(s for s in summary.schemas.values() if s.name == "nav_msgs/msg/Odometry")
    lefts = [read_image(src / "kitti06-12.png"), read_image(src / "kitti06-13.png")]
    right = read_image(src / "kitti06-12-R.png")
    stamps = [1_000_000_000_000 + k * 100_000_000 for k in range(2)]
    with path.open("wb") as handle:
        writer = Writer(handle)
        image_schema = writer.register_msgdef("sensor_msgs/msg/Image", IMAGE_DEF)
        compressed_schema = writer.register_msgdef("sensor_msgs/msg/CompressedImage", COMPRESSED_DEF)
        info_schema = writer.register_msgdef("sensor_msgs/msg/CameraInfo", CAMERA_INFO_DEF)
        odom_def = writer.register_msgdef("nav_msgs/msg/Odometry", odom_schema.data.decode())

        def header(stamp: int, frame: str) -> dict:
            return {"stamp": {"sec": stamp // 10**9, "nanosec": stamp % 10**9}, "frame_id": frame}

        for side, tx in (("left", 0.0), ("right", -KITTI06_FX_BASELINE)):
            p = [KITTI06_FX, 0, KITTI06_CX, tx, 0, KITTI06_FX, KITTI06_CY, 0, 0, 0, 1, 0]
            writer.write_message(f"/stereo/{side}/camera_info", info_schema, {
                "header": header(stamps[0], side), "height": 370, "width": 1226, "distortion_model": "plumb_bob",
                "d": [0.0] * 5, "k": [KITTI06_FX, 0, KITTI06_CX, 0, KITTI06_FX, KITTI06_CY, 0, 0, 1], "r": [1, 0, 0, 0, 1, 0, 0, 0, 1],
                "p": p, "binning_x": 0, "binning_y": 0,
                "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
            }, log_time=stamps[0] - 1)
        for k in range(4):  # odometry at 20 Hz, moving 1 m/s along x with a slow turn
            t = stamps[0] - 50_000_000 + k * 50_000_000
            yaw = 0.1 * k
            writer.write_message("/odom", odom_def, {
                "header": header(t, "odom"), "child_frame_id": "base_link",
                "pose": {"pose": {"position": {"x": 0.05 * k, "y": 0.0, "z": 0.0},
                                  "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2), "w": math.cos(yaw / 2)}},
                         "covariance": [0.0] * 36},
                "twist": {"twist": {"linear": {"x": 1.0, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": 0.0}},
                          "covariance": [0.0] * 36},
            }, log_time=t)
        ok, png = cv2.imencode(".png", right)
        assert ok
        for stamp, left in zip(stamps, lefts):
            writer.write_message("/stereo/left/image_raw", image_schema, {
                "header": header(stamp, "left"), "height": left.shape[0], "width": left.shape[1], "encoding": "mono8",
                "is_bigendian": 0, "step": left.shape[1], "data": left.tobytes(),
            }, log_time=stamp + 1000)
            writer.write_message("/stereo/right/image_raw/compressed", compressed_schema, {
                "header": header(stamp, "right"), "format": "png", "data": png.tobytes(),
            }, log_time=stamp + 2000)
        writer.finish()
    return {"stamps": stamps, "lefts": lefts, "right": right}


def test_stereo_bag_round_trip(tmp_path: Path) -> None:
    bag = tmp_path / "stereo.mcap"
    written = _write_stereo_bag(bag)
    out = tmp_path / "log.mcap"
    options = Ros2Options(left_topic="/stereo/left/image_raw", right_topic="/stereo/right/image_raw/compressed")
    stats = record_ros2(bag, out, options)
    assert stats.frames == 2 and stats.has_images and stats.has_odometry
    with open_log(out) as log:
        assert log.frame_stamps_ns.tolist() == written["stamps"]
        for frame, left in zip(log.frames(), written["lefts"]):
            assert np.array_equal(frame.left.decode(), left)
            assert np.array_equal(frame.right.decode(), written["right"])
        # Odometry at 20 Hz (k = 0..3 at -50, 0, 50, 100 ms) interpolated at 0 and 100 ms: k = 1 and 3.
        assert np.allclose(log.odometry(), [[0.05, 0.0, 0.1], [0.15, 0.0, 0.3]])
        calib = log.calibration  # from the sibling camera_info topics
        assert calib.fx_px == pytest.approx(KITTI06_FX) and calib.baseline_m == pytest.approx(KITTI06_FX_BASELINE / KITTI06_FX)


def test_image_encodings() -> None:
    class Msg:
        def __init__(self, encoding: str, data: bytes, width: int, height: int, step: int, big: int = 0):
            self.encoding, self.data, self.width, self.height, self.step, self.is_bigendian = encoding, data, width, height, step, big

    rgb = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    assert np.array_equal(image_to_array(Msg("rgb8", rgb.tobytes(), 3, 2, 9), "sensor_msgs/msg/Image"), rgb)
    assert np.array_equal(image_to_array(Msg("bgr8", rgb[:, :, ::-1].tobytes(), 3, 2, 9), "sensor_msgs/msg/Image"), rgb)
    padded = np.zeros((2, 4), dtype=np.uint8)
    padded[:, :3] = [[1, 2, 3], [4, 5, 6]]
    assert image_to_array(Msg("mono8", padded.tobytes(), 3, 2, 4), "sensor_msgs/msg/Image").tolist() == [[1, 2, 3], [4, 5, 6]]
    mono16 = np.array([[0x0100, 0xFF00]], dtype=">u2")
    assert image_to_array(Msg("mono16", mono16.tobytes(), 2, 1, 4, big=1), "sensor_msgs/msg/Image").tolist() == [[1, 255]]
    with pytest.raises(ValueError, match="encoding 'bayer_rggb8' is not supported"):
        image_to_array(Msg("bayer_rggb8", b"\0" * 4, 2, 2, 2), "sensor_msgs/msg/Image")
    with pytest.raises(ValueError, match="does not hold 2 rows"):
        image_to_array(Msg("mono8", b"\0" * 3, 2, 2, 2), "sensor_msgs/msg/Image")
