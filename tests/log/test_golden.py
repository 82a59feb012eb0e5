"""The committed golden log (tests/data/golden.mcap) decodes to its committed expected output.

Both files come from tests/data/make_golden.py; the expected JSON is computed from the writer's
inputs, not by reading the MCAP back.
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from lcv_replay.log.reader import open_log

DATA = Path(__file__).resolve().parents[1] / "data"


def _decoded(path: Path) -> dict:
    """Everything the reader decodes from a log, in the layout of golden_expected.json."""

    make_golden = _make_golden_module()
    digest, candidate_record = make_golden.image_digest, make_golden.candidate_record
    with open_log(path) as reader:
        info = reader.info
        calib = reader.calibration
        return {
            "info": {
                "frames": info.frames,
                "start_ns": info.start_ns,
                "end_ns": info.end_ns,
                "duration_s": info.duration_s,
                "has_ground_truth": info.has_ground_truth,
                "has_candidates": info.has_candidates,
                "has_labels": info.has_labels,
                "nominal_rate_hz": info.nominal_rate_hz,
                "topics": {t.topic: [t.schema, t.count] for t in info.topics},
                "metadata": {k: info.metadata[k] for k in ("dataset", "recorder", "format_version", "units", "image_format")},
                "recorder_config": info.recorder_config,
                "odometry_information": info.odometry_information.tolist(),
            },
            "calibration": {
                k: getattr(calib, k) for k in ("width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px", "baseline_m")
            },
            "frames": [
                {
                    "index": f.index,
                    "stamp_ns": f.stamp_ns,
                    "odom": list(f.odom),
                    "ground_truth": None if f.ground_truth is None else list(f.ground_truth),
                    "left": digest(f.left.decode()),
                    "right": digest(f.right.decode()),
                    "candidates": [list(c.pair) for c in f.candidates],
                    "true_loops": [list(p) for p in f.true_loops],
                }
                for f in reader.frames()
            ],
            "candidates": [candidate_record(c) for c in reader.loop_candidates()],
            "true_loops": sorted(list(p) for p in reader.true_loops()),
        }


def _assert_same(actual, expected, where="$"):
    """Exact comparison, except floats (pose angles go through sin/cos/atan2): 1e-12 relative."""
    if isinstance(expected, float) or isinstance(actual, float):
        assert actual == pytest.approx(expected, rel=1e-12, abs=1e-12), where
    elif isinstance(expected, dict):
        assert isinstance(actual, dict) and actual.keys() == expected.keys(), where
        for key in expected:
            _assert_same(actual[key], expected[key], f"{where}.{key}")
    elif isinstance(expected, list):
        assert isinstance(actual, list) and len(actual) == len(expected), where
        for k, (a, e) in enumerate(zip(actual, expected)):
            _assert_same(a, e, f"{where}[{k}]")
    else:
        assert actual == expected, where


def _make_golden_module():
    spec = importlib.util.spec_from_file_location("make_golden", DATA / "make_golden.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_committed_golden_log_decodes_to_the_committed_expected_output():
    expected = json.loads((DATA / "golden_expected.json").read_text(encoding="utf-8"))
    assert (DATA / "golden.mcap").stat().st_size < 16 * 1024
    _assert_same(_decoded(DATA / "golden.mcap"), expected)


def test_generator_script_matches_the_committed_files(tmp_path):
    """The script's expected output is the committed one, and a fresh write decodes the same."""
    make_golden = _make_golden_module()
    expected = json.loads((DATA / "golden_expected.json").read_text(encoding="utf-8"))
    assert json.loads(json.dumps(make_golden.expected_json())) == expected
    fresh = tmp_path / "golden.mcap"
    make_golden.write_golden(fresh)
    _assert_same(_decoded(fresh), expected)


def test_golden_yaw_and_odometry_arrays(tmp_path):
    with open_log(DATA / "golden.mcap") as reader:
        odom = reader.odometry()
        assert odom.shape == (4, 3)
        np.testing.assert_allclose(odom[:, 2], [0.0, 0.0625, 0.125, 0.1875], rtol=0, atol=1e-12)
        gt = reader.ground_truth()
        assert np.isnan(gt[2]).all() and gt[3, 0] == pytest.approx(4.5)
