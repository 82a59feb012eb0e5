"""Write a log, read it back, compare: every compression mode x every image format, plus odometry-only logs."""

from __future__ import annotations

import json

import numpy as np
import pytest
from mcap.reader import make_reader

from lcv_replay.log import format as fmt
from lcv_replay.log.reader import open_log
from tests.log.helpers import CALIB, write_synthetic_log


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
@pytest.mark.parametrize("image_format", ["png", "jpeg", "raw"])
def test_round_trip_images_poses_candidates(tmp_path, compression, image_format):
    path = tmp_path / "log.mcap"
    exp = write_synthetic_log(path, frames=6, compression=compression, image_format=image_format, gt_every=2)
    with open_log(path) as reader:
        info = reader.info
        assert info.frames == 6
        assert (info.has_images, info.has_right_images, info.has_odometry) == (True, True, True)
        assert (info.has_ground_truth, info.has_candidates, info.has_labels) == (True, True, True)
        assert info.start_ns == exp.stamps_ns[0] and info.end_ns == exp.stamps_ns[-1]
        assert info.metadata["dataset"] == "synthetic-test" and info.metadata["compression"] == compression
        assert info.recorder_config == {"frames": 6, "seed": 0}
        assert reader.calibration == CALIB

        frames = list(reader.frames())
        assert [f.index for f in frames] == list(range(6))
        assert [f.stamp_ns for f in frames] == exp.stamps_ns
        for frame in frames:
            for ref, truth in ((frame.left, exp.left[frame.index]), (frame.right, exp.right[frame.index])):
                image = ref.decode()
                assert image.shape == truth.shape and image.dtype == np.uint8
                if image_format == "jpeg":
                    assert np.abs(image.astype(int) - truth.astype(int)).mean() < 6.0
                    assert not np.array_equal(image, truth)  # really lossy: JPEG was used
                else:
                    np.testing.assert_array_equal(image, truth)
            np.testing.assert_allclose(frame.odom, exp.odom[frame.index], atol=1e-12)
            if exp.ground_truth[frame.index] is None:
                assert frame.ground_truth is None
            else:
                np.testing.assert_allclose(frame.ground_truth, exp.ground_truth[frame.index], atol=1e-12)
            assert list(frame.candidates) == [c for c in exp.candidates if c.query_frame == frame.index]
            assert set(frame.true_loops) == {p for p in exp.true_loops if p[0] == frame.index}

        np.testing.assert_allclose(reader.odometry(), np.array(exp.odom), atol=1e-12)
        gt = reader.ground_truth()
        assert np.isnan(gt[1]).all() and not np.isnan(gt[0]).any()
        assert reader.loop_candidates() == exp.candidates
        assert reader.true_loops() == exp.true_loops


def test_grey_images_and_mono_logs(tmp_path):
    path = tmp_path / "mono.mcap"
    exp = write_synthetic_log(path, frames=4, stereo=False, rgb=False)
    with open_log(path) as reader:
        assert reader.info.has_images and not reader.info.has_right_images
        for frame in reader.frames():
            assert frame.right is None
            np.testing.assert_array_equal(frame.left.decode(), exp.left[frame.index])


def test_odometry_only_log_defines_frames_from_odometry(tmp_path):
    path = tmp_path / "graph.mcap"
    exp = write_synthetic_log(path, frames=7, images=False, odometry_information=np.diag([1.0, 2.0, 30.0]))
    with open_log(path) as reader:
        info = reader.info
        assert info.frames == 7 and not info.has_images and info.has_odometry
        assert reader.calibration is None
        np.testing.assert_array_equal(info.odometry_information, np.diag([1.0, 2.0, 30.0]))
        frames = list(reader.frames())
        assert all(f.left is None and f.right is None for f in frames)
        assert [f.stamp_ns for f in frames] == exp.stamps_ns
        np.testing.assert_allclose(reader.odometry(), np.array(exp.odom), atol=1e-12)
        assert reader.loop_candidates() == exp.candidates


def test_every_message_of_frame_i_has_sequence_i_and_log_time_stamp(tmp_path):
    """The documented frame index <-> log_time mapping, read with the reference mcap library."""
    path = tmp_path / "log.mcap"
    exp = write_synthetic_log(path, frames=5)
    frame_of_stamp = {stamp: i for i, stamp in enumerate(exp.stamps_ns)}
    per_topic: dict[str, int] = {}
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            if channel.topic in (fmt.LEFT_CALIBRATION_TOPIC, fmt.RIGHT_CALIBRATION_TOPIC):
                continue
            assert message.publish_time == message.log_time
            if channel.topic in (fmt.LOOP_CANDIDATES_TOPIC, fmt.TRUE_LOOPS_TOPIC):
                query = json.loads(message.data)["query_frame"]
                assert message.sequence == query and message.log_time == exp.stamps_ns[query]
            else:
                assert message.sequence == frame_of_stamp[message.log_time]
            per_topic[channel.topic] = per_topic.get(channel.topic, 0) + 1
    assert per_topic[fmt.TF_TOPIC] == per_topic[fmt.ODOM_TOPIC] == 5
    assert schema is not None


def test_planar_pose_projection_of_a_tilted_3d_orientation():
    """A 3-D orientation with roll and pitch reads back as its heading (yaw about +z)."""
    from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame

    from lcv_replay.log.messages import pose_from_pose_in_frame

    yaw, pitch, roll = 0.7, 0.2, -0.3
    cy, sy, cp, sp, cr, sr = np.cos(yaw / 2), np.sin(yaw / 2), np.cos(pitch / 2), np.sin(pitch / 2), np.cos(roll / 2), np.sin(roll / 2)
    message = PoseInFrame(frame_id="odom")
    q = message.pose.orientation
    q.w, q.x = cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy
    q.y, q.z = cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy
    message.pose.position.x, message.pose.position.y, message.pose.position.z = 1.5, -2.0, 9.0
    pose = pose_from_pose_in_frame(message)
    assert pose.x_m == 1.5 and pose.y_m == -2.0
    assert pose.yaw_rad == pytest.approx(yaw, abs=1e-12)


def test_real_kitti_stereo_pair_round_trips_losslessly(tmp_path):
    import cv2

    from tests.shared_data import shared_path

    folder = shared_path("kitti06_frames")
    left = cv2.imread(str(folder / "kitti06-12.png"), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(folder / "kitti06-12-R.png"), cv2.IMREAD_GRAYSCALE)
    assert left.shape == (370, 1226)
    from lcv_replay.log.writer import LogWriter
    from lcv_replay.records import Pose2D, StereoCalibration

    calib = StereoCalibration(1226, 370, 707.0912, 707.0912, 601.8873, 183.1104, 379.8145 / 707.0912)
    path = tmp_path / "kitti.mcap"
    with LogWriter(path, dataset="kitti/06", recorder="tests", nominal_rate_hz=10.0, recorder_config={}) as writer:
        writer.write_calibration(calib, 0)
        writer.write_frame(0, 0, left=left, right=right, odom=Pose2D(0, 0, 0))
        writer.write_frame(1, 103_000_000, left=right, right=left, odom=Pose2D(0.9, 0, 0.01))
    with open_log(path) as reader:
        assert reader.calibration.baseline_m == pytest.approx(379.8145 / 707.0912, rel=1e-12)
        frames = list(reader.frames())
        np.testing.assert_array_equal(frames[0].left.decode(), left)
        np.testing.assert_array_equal(frames[0].right.decode(), right)
        np.testing.assert_array_equal(frames[1].left.decode(), right)


def test_unchunked_mcap_from_another_writer_reads_the_same(tmp_path):
    """A file with top-level message records (no chunks) is indexed by a scan and reads identically."""
    from mcap.writer import Writer as McapWriter

    path = tmp_path / "log.mcap"
    exp = write_synthetic_log(path, frames=4)
    flat = tmp_path / "flat.mcap"
    with open(path, "rb") as src, open(flat, "wb") as dst:
        reader = make_reader(src)
        summary = reader.get_summary()
        writer = McapWriter(dst, use_chunking=False)
        writer.start()
        for schema in summary.schemas.values():
            writer.register_schema(schema.name, schema.encoding, schema.data)
        for channel in summary.channels.values():
            writer.register_channel(channel.topic, channel.message_encoding, channel.schema_id)
        for record in reader.iter_metadata():
            writer.add_metadata(record.name, record.metadata)
        for _, channel, message in reader.iter_messages(log_time_order=False):
            writer.add_message(channel.id, message.log_time, message.data, message.publish_time, message.sequence)
        writer.finish()
    with open_log(flat) as reader:
        assert reader.info.chunk_count == 0 and reader.info.frames == 4
        assert reader.info.metadata["dataset"] == "synthetic-test"
        for frame in reader.frames():
            np.testing.assert_array_equal(frame.left.decode(), exp.left[frame.index])
        assert reader.loop_candidates() == exp.candidates
