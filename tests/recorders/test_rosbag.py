"""The bag importer (``record rosbag``, through rosbags) on the real bags of ../shared/data, and on a
stereo ROS 2 MCAP written by another writer (``mcap-ros2-support``) from the real KITTI 06 frames.

References are decoded independently of the importer: ROS 2 MCAP with ``mcap_ros2``, ROS 1 bags
with rosbags' low-level ``rosbag1.Reader``.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from lcv_replay.cli import app
from lcv_replay.log.reader import open_log
from recorders.common import read_image
from recorders.rosbag import RosbagOptions, image_to_array, record_rosbag
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
    stats = record_rosbag(bag, out, RosbagOptions(ground_truth_topic="/amcl_pose"))
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
        assert log.info.metadata["recorder"] == "rosbag"
        assert log.info.recorder_config["topics_used"] == {"odom": "/odom", "gt": "/amcl_pose"}


def test_nav2_thinning_and_cli_errors(tmp_path: Path) -> None:
    bag = shared_path("ros2", "nav2_turtlebot.mcap")
    stats = record_rosbag(bag, tmp_path / "10hz.mcap", RosbagOptions(max_rate_hz=10.0))
    with open_log(tmp_path / "10hz.mcap") as log:
        stamps = log.frame_stamps_ns
        assert np.diff(stamps).min() >= 100_000_000
        duration_s = (stamps[-1] - stamps[0]) / 1e9
        # At most 10 Hz; /odom arrives at ~27 Hz with jitter, so a kept frame is at most ~40 ms late.
        assert 0.7 * duration_s * 10 < stats.frames <= duration_s * 10 + 1
    runner = CliRunner()
    result = runner.invoke(app, ["record", "rosbag", str(bag), "-o", str(tmp_path / "x.mcap"), "--left-topic", "/camera/left/image_raw"])
    assert result.exit_code == 2
    assert "topic /camera/left/image_raw (--left-topic) is not in the bag" in result.output
    assert "/odom (nav_msgs/msg/Odometry)" in result.output and "/amcl_pose (geometry_msgs/msg/PoseWithCovarianceStamped)" in result.output
    # A message type we cannot use on the chosen topic (the alias 'record ros2' is the same command).
    result = runner.invoke(app, ["record", "ros2", str(bag), "-o", str(tmp_path / "x.mcap"), "--odom-topic", "/tf"])
    assert result.exit_code == 2 and "topic /tf (--odom-topic) has type tf2_msgs/msg/TFMessage, which lcv-replay cannot use there" in result.output
    assert "expected nav_msgs/msg/Odometry or geometry_msgs/msg/PoseStamped or geometry_msgs/msg/PoseWithCovarianceStamped" in result.output
    not_mcap = tmp_path / "bag.mcap"
    not_mcap.write_bytes(b"definitely not an mcap file")
    result = runner.invoke(app, ["record", "rosbag", str(not_mcap), "-o", str(tmp_path / "x.mcap")])
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
    options = RosbagOptions(left_topic="/stereo/left/image_raw", right_topic="/stereo/right/image_raw/compressed")
    stats = record_rosbag(bag, out, options)
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


# --------------------------------------------------------------------------------------------- ROS 1
def _ros1_poses(path: Path, topic: str) -> tuple[np.ndarray, np.ndarray]:
    """(header stamps, (N, 7) x y z qx qy qz qw) of a ROS 1 pose topic, read with rosbags' low-level reader."""
    from rosbags.rosbag1 import Reader
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    rows = []
    with Reader(path) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        for conn, _t, raw in reader.messages(connections=conns):
            m = ts.deserialize_ros1(raw, conn.msgtype)
            p, q = m.pose.position, m.pose.orientation
            rows.append((m.header.stamp.sec * 10**9 + m.header.stamp.nanosec, p.x, p.y, p.z, q.x, q.y, q.z, q.w))
    rows.sort(key=lambda r: r[0])
    return np.array([r[0] for r in rows], dtype=np.int64), np.array([r[1:] for r in rows])


def test_ros1_example_pose_topics_as_odometry_and_ground_truth(tmp_path: Path, caplog) -> None:
    """ROS_example.bag: PoseStamped on ORB-SLAM (odometry) and groundtruth (picked by its name)."""
    bag = shared_path("ros1", "ROS_example.bag")
    runner = CliRunner()
    result = runner.invoke(app, ["record", "rosbag", str(bag), "-o", str(tmp_path / "x.mcap")])
    assert result.exit_code == 2 and result.output.count("\n") == 1
    assert "several odometry candidates: ORB-SLAM (geometry_msgs/msg/PoseStamped, 8362 messages), S-PTAM" in result.output
    assert "choose one with --odom-topic" in result.output and not (tmp_path / "x.mcap").exists()

    out = tmp_path / "orb.mcap"
    with caplog.at_level(logging.INFO, logger="recorders.rosbag"):
        result = runner.invoke(app, ["record", "rosbag", str(bag), "--odom-topic", "ORB-SLAM", "-o", str(out), "--quiet"])
    assert result.exit_code == 0, result.output
    assert "ground truth: groundtruth (geometry_msgs/msg/PoseStamped; by its name" in caplog.text  # says what was chosen
    stamps, raw = _ros1_poses(bag, "ORB-SLAM")
    gt_stamps, gt_raw = _ros1_poses(bag, "groundtruth")
    with open_log(out) as log:
        assert np.array_equal(log.frame_stamps_ns, stamps)
        odom = log.odometry()
        assert np.allclose(odom[:, :2], raw[:, :2])
        # Yaw: heading of the body x axis; checked against the quaternion's rotation matrix.
        R = _rotation(raw[:, 3:])
        assert np.allclose(np.cos(odom[:, 2] - np.arctan2(R[:, 1, 0], R[:, 0, 0])), 1.0)
        truth = log.ground_truth()
        # groundtruth (~17 Hz, a few gaps of 2 s) interpolated linearly at the ORB-SLAM stamps, across
        # gaps up to --max-gap-ns (500 ms); frames in a longer gap have none.
        assert gt_stamps[0] < stamps[0] and stamps[-1] < gt_stamps[-1]
        t = (stamps - gt_stamps[0]) / 1e9
        expected = np.stack([np.interp(t, (gt_stamps - gt_stamps[0]) / 1e9, gt_raw[:, k]) for k in (0, 1)], axis=1)
        after = np.searchsorted(gt_stamps, stamps)
        bridged = (gt_stamps[after] - gt_stamps[np.maximum(after - 1, 0)] <= 500_000_000) | (gt_stamps[after] == stamps)
        assert 8000 < bridged.sum() < len(stamps)
        assert np.array_equal(np.isfinite(truth[:, 0]), bridged)
        assert np.allclose(truth[bridged, :2], expected[bridged], atol=1e-6)
        assert log.info.metadata["recorder"] == "rosbag" and log.info.recorder_config["bag_format"] == "ros1"


def _rotation(q: np.ndarray) -> np.ndarray:
    from recorders.common import quaternion_to_matrix

    return quaternion_to_matrix(q)


def test_tf_example_ros1_and_ros2_give_the_same_trajectory(tmp_path: Path) -> None:
    """The same real recording as a ROS 1 bag and a ROS 2 sqlite3 bag: odometry from /tf + /tf_static."""
    outs = {}
    for name, bag in (("ros1", shared_path("ros1", "tf_example.bag")), ("ros2", shared_path("ros2", "tf_example"))):
        outs[name] = tmp_path / f"{name}.mcap"
        record_rosbag(bag, outs[name], RosbagOptions(odom_from_tf="odom:base_link"))
    with open_log(outs["ros1"]) as a, open_log(outs["ros2"]) as b:
        assert a.info.frames == b.info.frames == 517
        assert np.array_equal(a.frame_stamps_ns, b.frame_stamps_ns)
        assert np.array_equal(a.odometry(), b.odometry())
        odom = a.odometry()
    # By hand: /tf carries odom -> base_footprint, /tf_static base_footprint -> base_link (identity);
    # so frame k is the k-th odom -> base_footprint transform, planar.
    from rosbags.rosbag1 import Reader
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.EMPTY)
    rows = []
    with Reader(shared_path("ros1", "tf_example.bag")) as reader:
        tf_conns = [c for c in reader.connections if c.topic == "/tf"]
        ts.register(get_types_from_msg(tf_conns[0].msgdef.data, tf_conns[0].msgtype))  # the bag's own definition
        for conn, _t, raw in reader.messages(connections=tf_conns):
            for tf in ts.deserialize_ros1(raw, conn.msgtype).transforms:
                assert (tf.header.frame_id, tf.child_frame_id) == ("odom", "base_footprint")
                r = tf.transform.rotation
                rows.append((tf.header.stamp.sec * 10**9 + tf.header.stamp.nanosec, tf.transform.translation.x,
                             tf.transform.translation.y, 2 * math.atan2(r.z, r.w)))
    rows.sort()
    expected = np.array([r[1:] for r in rows])
    assert np.allclose(odom[:, :2], expected[:, :2]) and np.allclose(np.cos(odom[:, 2] - expected[:, 2]), 1.0)
    assert np.ptp(odom[:, 0]) > 1.0  # the robot moves


def test_nav2_odometry_from_a_tf_chain_agrees_with_amcl(tmp_path: Path) -> None:
    """map -> odom (AMCL) -> base_link composed from /tf, against AMCL's own /amcl_pose (real data)."""
    bag = shared_path("ros2", "nav2_turtlebot.mcap")
    out = tmp_path / "map.mcap"
    runner = CliRunner()
    result = runner.invoke(app, ["record", "rosbag", str(bag), "--odom-from-tf", "map:base_link", "-o", str(out), "--quiet"])
    assert result.exit_code == 2 and "have no odometry from TF map -> base_link within 500 ms" in result.output
    record_rosbag(bag, out, RosbagOptions(odom_from_tf="map:base_link", ground_truth_topic="/amcl_pose", max_gap_ns=10_000_000_000))
    with open_log(out) as log:
        odom, amcl = log.odometry(), log.ground_truth()
        have = np.isfinite(amcl).all(axis=1)
        error = np.linalg.norm(odom[have, :2] - amcl[have, :2], axis=1)
        assert have.sum() > 2000 and np.median(error) < 0.1 and error.max() < 0.5


def test_bad_bags_get_one_error_line(tmp_path: Path) -> None:
    runner = CliRunner()

    def fails(args: list[str], *expected: str) -> None:
        result = runner.invoke(app, ["record", "rosbag", *args, "-o", str(tmp_path / "out.mcap")])
        assert result.exit_code == 2, result.output
        assert result.output.startswith("error: ") and result.output.count("\n") == 1, result.output
        for text in expected:
            assert text in result.output, result.output
        assert not (tmp_path / "out.mcap").exists()

    # A TF chain that never connects the two frames names the frames seen.
    fails([str(shared_path("ros2", "tf_example")), "--odom-from-tf", "map:base_link"],
          "--odom-from-tf map:base_link: no TF chain connects map and base_link", "frames seen: base_footprint, base_link, odom")
    # Only /tf: no odometry topic, the error suggests the TF pair.
    fails([str(shared_path("ros1", "tf_example.bag"))], "nothing to record", "--odom-from-tf odom:base_link")
    # A metadata.yaml without its db3.
    folder = tmp_path / "bag"
    folder.mkdir()
    (folder / "metadata.yaml").write_bytes(shared_path("ros2", "tf_example", "metadata.yaml").read_bytes())
    fails([str(folder)], "metadata.yaml lists tf_example.db3, which is not in the bag folder", "copy the whole bag folder")
    fails([str(folder / "metadata.yaml")], "metadata.yaml lists tf_example.db3")
    # A split ROS 1 bag with a missing part.
    _split_bag(tmp_path)
    fails([str(tmp_path / "run_0.bag"), str(tmp_path / "run_2.bag")], "split bag run: part run_1.bag is missing", "pass every part")
    (tmp_path / "run_1.bag").rename(tmp_path / "elsewhere.bag")
    fails([str(tmp_path / "run_2.bag"), str(tmp_path / "run_0.bag")], "part run_1.bag is missing", "copy the missing part")
    # A damaged bag.
    broken = tmp_path / "broken.bag"
    broken.write_bytes(shared_path("ros1", "tf_example.bag").read_bytes()[:5000])
    fails([str(broken), "--odom-from-tf", "odom:base_link"], "the bag cannot be read")


def _split_bag(folder: Path) -> None:
    """run_0.bag, run_1.bag, run_2.bag: a ROS 1 recording split in three parts of 3 odometry messages."""
    from tests.recorders.bag_writer import BagBuilder

    for part in (0, 1, 2):
        builder = BagBuilder("ros1")
        for k in range(3):
            t = (10 * part + k) * 10**9
            builder.add("/odom", t, builder.odometry(t, float(10 * part + k), 0.0, 0.0))
        builder.write(folder / f"run_{part}.bag")


def test_split_ros1_parts_import_in_order(tmp_path: Path) -> None:
    _split_bag(tmp_path)
    out = tmp_path / "run.mcap"
    stats = record_rosbag([tmp_path / "run_2.bag", tmp_path / "run_0.bag", tmp_path / "run_1.bag"], out, RosbagOptions())
    assert stats.frames == 9
    with open_log(out) as log:
        assert log.odometry()[:, 0].tolist() == [0, 1, 2, 10, 11, 12, 20, 21, 22]
        assert log.info.metadata["dataset"] == "run"
