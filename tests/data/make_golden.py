"""Generate the golden log ``golden.mcap`` and its expected decoded content ``golden_expected.json``.

Run from the repository root: ``python tests/data/make_golden.py``. The expected JSON is computed
from the *inputs* handed to the writer, never by reading the MCAP back, so the golden test
(tests/log/test_golden.py) checks the reader against independent truth. Images are 16x12 RGB PNGs; poses are exact binary fractions so that the JSON is exact.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np

from lcv_replay.log.writer import LogWriter
from lcv_replay.records import LoopCandidate, Pose2D, StereoCalibration

HERE = Path(__file__).resolve().parent
T0_NS = 1_600_000_000_000_000_000
CALIB = StereoCalibration(width_px=16, height_px=12, fx_px=20.0, fy_px=20.0, cx_px=7.5, cy_px=5.5, baseline_m=0.5)


def golden_inputs() -> dict:
    """Every record of the golden log (deterministic, no randomness)."""
    frames = []
    for i in range(4):
        yy, xx = np.mgrid[0:12, 0:16]
        left = np.stack([(xx * 16 + yy * 8 + i * 40) % 256, (yy * 21) % 256, (xx * yy + i) % 256], axis=-1).astype(np.uint8)
        right = np.stack([(xx * 15 + i) % 256, (yy * 20) % 256, ((xx + yy) * 7 + 3 * i) % 256], axis=-1).astype(np.uint8)
        frames.append(
            {
                "index": i,
                "stamp_ns": T0_NS + i * 250_000_000,
                "left": left,
                "right": right,
                "odom": Pose2D(1.25 * i, 0.125 * i, 0.0625 * i),
                "ground_truth": Pose2D(1.5 * i, -0.25 * i, 0.125 * i) if i != 2 else None,
            }
        )
    candidates = [
        LoopCandidate(3, 0, similarity=0.875, hamming=2, source="golden", T_match_query=Pose2D(0.5, -0.25, 0.125), information=(100.0, 0.0, 0.0, 100.0, 0.0, 1000.0)),
        LoopCandidate(3, 1, similarity=0.5, hamming=None, source="golden"),
    ]
    return {"frames": frames, "candidates": candidates, "true_loops": [(3, 0)]}


def write_golden(path: Path, *, force: bool = False) -> None:
    inputs = golden_inputs()
    with LogWriter(
        path,
        force=force,
        dataset="golden",
        recorder="make_golden",
        nominal_rate_hz=4.0,
        recorder_config={"frames": 4, "note": "tests/data/make_golden.py"},
        odometry_information=np.diag([100.0, 100.0, 1000.0]),
        compression="zstd",
    ) as writer:
        writer.write_calibration(CALIB, T0_NS)
        for f in inputs["frames"]:
            writer.write_frame(f["index"], f["stamp_ns"], left=f["left"], right=f["right"], odom=f["odom"], ground_truth=f["ground_truth"])
        stamp3 = inputs["frames"][3]["stamp_ns"]
        for c in inputs["candidates"]:
            writer.write_loop_candidate(c, stamp3)
        for q, m in inputs["true_loops"]:
            writer.write_true_loop(q, m, stamp3)


def image_digest(image: np.ndarray) -> dict:
    """Shape and SHA-256 of an image's pixels."""
    return {"shape": list(image.shape), "sha256": hashlib.sha256(np.ascontiguousarray(image).tobytes()).hexdigest()}


def candidate_record(c: LoopCandidate) -> dict:
    """A candidate as a JSON-ready dict (the layout of golden_expected.json)."""
    return {
        "query_frame": c.query_frame,
        "match_frame": c.match_frame,
        "similarity": c.similarity,
        "hamming": c.hamming,
        "source": c.source,
        "T_match_query": None if c.T_match_query is None else list(c.T_match_query),
        "information": None if c.information is None else list(c.information),
    }


def expected_json() -> dict:
    """What a correct reader must decode from the golden log."""
    inputs = golden_inputs()
    return {
        "info": {
            "frames": 4,
            "start_ns": T0_NS,
            "end_ns": T0_NS + 750_000_000,
            "duration_s": 0.75,
            "has_ground_truth": True,
            "has_candidates": True,
            "has_labels": True,
            "nominal_rate_hz": 4.0,
            "topics": {
                "/stereo/left/image": ["foxglove.CompressedImage", 4],
                "/stereo/right/image": ["foxglove.CompressedImage", 4],
                "/stereo/left/calibration": ["foxglove.CameraCalibration", 1],
                "/stereo/right/calibration": ["foxglove.CameraCalibration", 1],
                "/odom": ["foxglove.PoseInFrame", 4],
                "/tf": ["foxglove.FrameTransform", 4],
                "/ground_truth/pose": ["foxglove.PoseInFrame", 3],
                "/loop_candidates": ["lcv.LoopCandidate", 2],
                "/ground_truth/loops": ["lcv.TrueLoop", 1],
            },
            "metadata": {"dataset": "golden", "recorder": "make_golden", "format_version": "1", "units": "m, rad, ns", "image_format": "png"},
            "recorder_config": {"frames": 4, "note": "tests/data/make_golden.py"},
            "odometry_information": np.diag([100.0, 100.0, 1000.0]).tolist(),
        },
        "calibration": {
            "width_px": 16, "height_px": 12, "fx_px": 20.0, "fy_px": 20.0, "cx_px": 7.5, "cy_px": 5.5, "baseline_m": 0.5,
        },
        "frames": [
            {
                "index": f["index"],
                "stamp_ns": f["stamp_ns"],
                "odom": list(f["odom"]),
                "ground_truth": None if f["ground_truth"] is None else list(f["ground_truth"]),
                "left": image_digest(f["left"]),
                "right": image_digest(f["right"]),
                "candidates": [[c.query_frame, c.match_frame] for c in inputs["candidates"] if c.query_frame == f["index"]],
                "true_loops": [list(p) for p in inputs["true_loops"] if p[0] == f["index"]],
            }
            for f in inputs["frames"]
        ],
        "candidates": [candidate_record(c) for c in inputs["candidates"]],
        "true_loops": [list(p) for p in inputs["true_loops"]],
    }


def main() -> int:
    write_golden(HERE / "golden.mcap", force=True)
    (HERE / "golden_expected.json").write_text(json.dumps(expected_json(), indent=1) + "\n", encoding="utf-8")
    print(f"wrote {HERE / 'golden.mcap'} ({(HERE / 'golden.mcap').stat().st_size} bytes) and golden_expected.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
