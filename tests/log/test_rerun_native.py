"""Rerun opens our logs natively: rerun.chunk.McapReader (the `rerun mcap convert` decoders) must turn
the images into EncodedImage / Image, the poses into InstancePoses3D and /tf into Transform3D.

What rerun-sdk 0.41 does NOT decode (documented in docs/log-format.md): the JSON-schema topics
/loop_candidates and /ground_truth/loops stay raw McapMessage rows (checked below), and the stereo
baseline in the right P matrix is not turned into a transform between the two cameras.
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections import defaultdict

import numpy as np
import pytest

from lcv_replay.log.images import decode_compressed
from tests.log.helpers import CALIB, write_synthetic_log

rerun_chunk = pytest.importorskip("rerun.chunk")


def _columns(path):
    """entity path -> column name -> list of per-row values, over every chunk of the MCAP."""
    import pyarrow as pa

    table: dict[str, dict[str, list]] = defaultdict(lambda: defaultdict(list))
    for chunk in rerun_chunk.McapReader(path).stream():
        batch = chunk.to_record_batch()
        for field in batch.schema:
            column = batch.column(field.name)
            if pa.types.is_timestamp(field.type):  # nanosecond timelines as int64
                column = column.cast(pa.int64())
            table[chunk.entity_path][field.name].extend(column.to_pylist())
    return table


def _rows(columns: dict[str, list], name: str) -> list:
    return [value for value in columns[name] if value is not None]


def test_png_images_and_poses_become_rerun_archetypes(tmp_path):
    path = tmp_path / "log.mcap"
    exp = write_synthetic_log(path, frames=4)
    cols = _columns(path)

    for topic, images in (("/stereo/left/image", exp.left), ("/stereo/right/image", exp.right)):
        blobs = _rows(cols[topic], "EncodedImage:blob")
        assert _rows(cols[topic], "EncodedImage:media_type") == [["image/png"]] * 4
        assert len(blobs) == 4
        assert _rows(cols[topic], "message_log_time") == exp.stamps_ns
        for blob, truth in zip(blobs, images):
            np.testing.assert_array_equal(decode_compressed(bytes(blob[0]), "png"), truth)

    for topic, poses in (("/odom", exp.odom), ("/ground_truth/pose", exp.ground_truth)):
        translations = np.array([row[0] for row in _rows(cols[topic], "InstancePoses3D:translations")])
        quaternions = np.array([row[0] for row in _rows(cols[topic], "InstancePoses3D:quaternions")])
        truth = np.array(poses)
        np.testing.assert_allclose(translations[:, :2], truth[:, :2], rtol=1e-6, atol=1e-5)
        np.testing.assert_array_equal(translations[:, 2], 0.0)
        np.testing.assert_allclose(quaternions[:, 2:], np.c_[np.sin(truth[:, 2] / 2), np.cos(truth[:, 2] / 2)], atol=1e-6)
    assert _rows(cols["/odom"], "CoordinateFrame:frame")[0] == ["odom"]
    assert _rows(cols["/ground_truth/pose"], "CoordinateFrame:frame")[0] == ["world"]

    tf = cols["/tf"]
    assert _rows(tf, "Transform3D:parent_frame") == [["odom"]] * 4
    assert _rows(tf, "Transform3D:child_frame") == [["base_link"]] * 4
    np.testing.assert_allclose(np.array([r[0] for r in _rows(tf, "Transform3D:translation")])[:, :2], np.array(exp.odom)[:, :2], rtol=1e-6, atol=1e-5)

    (K,) = _rows(cols["/stereo/left/calibration"], "Pinhole:image_from_camera")
    np.testing.assert_allclose(np.array(K[0]).reshape(3, 3).T, CALIB.K)  # rerun stores it column-major

    # Not decoded by rerun 0.41: our JSON-schema topics arrive as raw McapMessage payloads.
    raw = _rows(cols["/loop_candidates"], "McapMessage:data")
    assert [json.loads(bytes(r[0]))["query_frame"] for r in raw] == [c.query_frame for c in exp.candidates]
    assert not any(name.startswith(("Points", "Arrows", "LineStrips")) for name in cols["/loop_candidates"])


def test_raw_images_become_rerun_image(tmp_path):
    path = tmp_path / "raw.mcap"
    exp = write_synthetic_log(path, frames=3, image_format="raw", rgb=False)
    cols = _columns(path)["/stereo/left/image"]
    formats = _rows(cols, "Image:format")
    buffers = _rows(cols, "Image:buffer")
    assert len(buffers) == 3
    assert formats[0][0]["width"] == CALIB.width_px and formats[0][0]["height"] == CALIB.height_px
    for buffer, truth in zip(buffers, exp.left):
        np.testing.assert_array_equal(np.array(buffer[0], dtype=np.uint8).reshape(truth.shape), truth)


def test_rerun_mcap_convert_cli_writes_images_and_poses(tmp_path):
    path = tmp_path / "log.mcap"
    write_synthetic_log(path, frames=3)
    rrd = tmp_path / "log.rrd"
    proc = subprocess.run(
        [sys.executable, "-m", "rerun", "mcap", "convert", str(path), "-o", str(rrd)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    columns: dict[str, set] = defaultdict(set)
    for chunk in rerun_chunk.RrdReader(rrd).stream():
        columns[chunk.entity_path].update(chunk.to_record_batch().schema.names)
    assert "EncodedImage:blob" in columns["/stereo/left/image"]
    assert "EncodedImage:blob" in columns["/stereo/right/image"]
    assert "InstancePoses3D:translations" in columns["/odom"]
    assert "Transform3D:translation" in columns["/tf"]
    assert "Pinhole:image_from_camera" in columns["/stereo/right/calibration"]
