"""`lcv-replay bench retrieval` (folder and MCAP modes), `bench retrieval-index`, and bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from lcv_replay.cli import app
from lcv_replay.log.writer import LogWriter
from lcv_replay.records import Pose2D
from tests.shared_data import shared_path

runner = CliRunner()


def _corridor():
    folder = shared_path("rtabmap_corridor")
    return folder, folder / "samples_GT.bmp"


def test_folder_bench_prints_a_table_and_writes_json(tmp_path):
    folder, truth = _corridor()
    out = tmp_path / "r.json"
    result = runner.invoke(app, ["bench", "retrieval", str(folder), "--truth-matrix", str(truth), "--exclude-frames", "20",
                                 "--backend", "thumbnail", "--json", str(out), "--timing-runs", "1", "--mode", "paper", "--mode", "ranked"])
    assert result.exit_code == 0, result.output
    assert "thumbnail" in result.stdout and "R@1" in result.stdout
    payload = json.loads(out.read_text())
    assert payload["images"] == 84 and payload["exclusion_frames"] == 20
    paper, ranked = payload["backends"]
    for row in (paper, ranked):
        for key in ("backend", "queries", "recall_at_1", "recall_at_10", "candidate_precision", "descriptor_frames_per_s", "descriptor_warmup_s"):
            assert key in row
        assert row["backend"] == "thumbnail" and row["queries"] == 44
        assert 0.0 <= row["recall_at_1"] <= row["recall_at_10"] <= 1.0 and row["descriptor_frames_per_s"] > 0
    assert (paper["mode"], ranked["mode"]) == ("paper", "ranked")
    # at most 63 frames are eligible on the corridor, fewer than M = 100: ranked is the exhaustive search
    assert ranked["recall_at_1"] == ranked["exhaustive_recall_at_1"] and ranked["recall_at_10"] == ranked["exhaustive_recall_at_10"]
    # the JSON is not overwritten without --force
    again = runner.invoke(app, ["bench", "retrieval", str(folder), "--truth-matrix", str(truth), "--exclude-frames", "20",
                                "--backend", "thumbnail", "--json", str(out)])
    assert again.exit_code == 2 and "--force" in again.output


def test_folder_bench_bad_input_is_one_error_line(tmp_path):
    folder, truth = _corridor()
    small = tmp_path / "gt.txt"
    small.write_text("\n".join(" ".join("0" for _ in range(10)) for _ in range(10)))
    cases = [
        ([str(folder), "--backend", "thumbnail"], "needs --truth-matrix"),
        ([str(folder), "--truth-matrix", str(small), "--backend", "thumbnail"], "10x10 but the folder has 85 images"),
        ([str(tmp_path / "nope"), "--truth-matrix", str(truth)], "not found"),
        ([str(folder), "--truth-matrix", str(truth), "--backend", "thumbnail"], "no image has a true match more than"),
        ([str(folder), "--truth-matrix", str(truth), "--backend", "vgg16"], "unknown descriptor backend 'vgg16'"),
        ([str(folder), "--truth-matrix", str(truth), "--code-bits", "70"], "'retrieval.ranked.code_bits' = 70"),
        ([str(folder), "--truth-matrix", str(truth), "--code-bits", "70", "--mode", "paper"], "'retrieval.code_bits' = 70"),
        ([str(folder), "--truth-matrix", str(truth), "--candidates", "5"], "'retrieval.ranked.candidates' = 5"),
        ([str(folder), "--truth-matrix", str(truth), "--mode", "fast"], "--mode 'fast' is not known"),
    ]
    for args, message in cases:
        result = runner.invoke(app, ["bench", "retrieval", *args])
        assert result.exit_code == 2, (args, result.output)
        assert message in result.output and "Traceback" not in result.output


def _loop_log(path, *, places: int = 30, seed: int = 0):
    """A route around a 30-place square driven twice: revisit images are the first pass plus noise."""
    rng = np.random.default_rng(seed)
    views = [rng.integers(0, 256, size=(48, 64), dtype=np.uint8) for _ in range(places)]
    with LogWriter(path, dataset="loop", recorder="tests", nominal_rate_hz=10.0, recorder_config={}) as writer:
        for i in range(2 * places):
            p = i % places
            angle = 2 * np.pi * p / places
            gt = Pose2D(50 * np.cos(angle), 50 * np.sin(angle), angle)
            image = np.clip(views[p].astype(int) + rng.integers(-10, 11, size=(48, 64)), 0, 255).astype(np.uint8)
            writer.write_frame(i, 1_000_000_000 * (i + 1), left=image, odom=gt, ground_truth=gt)
    return path


def test_log_bench_scores_candidates_against_ground_truth(tmp_path):
    log = _loop_log(tmp_path / "loop.mcap")
    out = tmp_path / "log.json"
    result = runner.invoke(app, ["bench", "retrieval", str(log), "--backend", "thumbnail", "--exclude-frames", "20",
                                 "--code-bits", "8", "--top-k", "1", "--json", str(out)])
    assert result.exit_code == 0, result.output
    (row,) = json.loads(out.read_text())["backends"]
    # frames 30..59 revisit 0..29 (places 10.4 m apart: only the same place is within 10 m);
    # online fit on the first 20 frames; with N_r = 1 the single candidate should be the revisit
    assert row["frames"] == 60 and row["queries"] == 30
    assert row["revisits_found"] >= 0.8 and row["false_candidate_fraction"] <= 0.3


def test_log_without_ground_truth_is_refused(tmp_path):
    path = tmp_path / "nogt.mcap"
    with LogWriter(path, dataset="x", recorder="tests", nominal_rate_hz=1.0, recorder_config={}) as writer:
        for i in range(3):
            writer.write_frame(i, i + 1, left=np.zeros((8, 8), np.uint8), odom=Pose2D(i, 0, 0))
    result = runner.invoke(app, ["bench", "retrieval", str(path), "--backend", "thumbnail"])
    assert result.exit_code == 2 and "no ground truth" in result.output


def test_index_bench_reports_each_size_and_variant(tmp_path):
    out = tmp_path / "index.json"
    result = runner.invoke(app, ["bench", "retrieval-index", "--sizes", "100,1000", "--queries", "20", "--vector-dim", "16",
                                 "--variant", "paper/scan", "--variant", "ranked/numpy", "--variant", "ranked/faiss", "--json", str(out)])
    assert result.exit_code == 0, result.output
    rows = json.loads(out.read_text())["rows"]
    assert [(r["library_frames"], r["variant"]) for r in rows] == [
        (100, "paper/scan"), (100, "ranked/numpy"), (100, "ranked/faiss"), (1000, "paper/scan"), (1000, "ranked/numpy"), (1000, "ranked/faiss")]
    for r in rows:
        if r["mode"] == "ranked":  # exact engines: the full budget M = 100 (all 100 frames at the small size), recall 1
            assert r["recall_vs_exact"] == 1.0 and r["mean_prefilter_size"] == 100 and r["code_bits"] == 128
        else:
            assert r["recall_vs_exact"] is None and r["code_bits"] == 20
        assert r["query_us_median"] >= r["first_stage_us_median"] > 0
    assert rows[0]["query_vs_smallest"] == 1.0
    bad = runner.invoke(app, ["bench", "retrieval-index", "--variant", "ranked/annoy"])
    assert bad.exit_code == 2 and "unknown variant 'ranked/annoy'" in bad.output


@pytest.mark.slow
def test_descriptor_speed_json_names_the_onnxruntime_rung_and_the_default_engine(tmp_path):
    out = tmp_path / "speed.json"
    result = runner.invoke(app, ["bench", "descriptor-speed", "--variant", "onnxruntime", "--variant", "matmul-bound",
                                 "--repeats", "1", "--runs", "2", "--batch", "2", "--json", str(out)])
    assert result.exit_code == 0, result.output
    rows = {r["variant"]: r for r in json.loads(out.read_text())["variants"]}
    assert rows["onnxruntime"]["default"] is True and rows["matmul-bound"]["default"] is False
    assert rows["onnxruntime"]["ms_per_image_median"] > 0 and rows["matmul-bound"]["ms_per_image_median"] > 0
    assert rows["onnxruntime"]["cosine_min"] >= 0.99999  # against the torch export module, same input
    assert rows["matmul-bound"]["gflops_median"] > 0 and rows["matmul-bound"]["cosine_min"] is None
