"""A small real synthetic log (the real recorder) through the image route, and ``lcv-replay demo``.

One short drive is recorded once per module through the demo's own cache logic; the retrieval test
replays it with the weight-free ``thumbnail`` descriptor backend and a short Δt (the CNN is the
retrieval tests' business); the demo test runs the command on the cached recording.
"""

from __future__ import annotations

import json
import os

import pytest
from typer.testing import CliRunner

from lcv_replay.cli import app
from lcv_replay.cli.demo import DEMO_HEIGHT_PX, DEMO_WIDTH_PX, demo_log_path, ensure_demo_log
from lcv_replay.config import load_config
from lcv_replay.replay import ReplayOptions, replay
from lcv_replay.sinks import blueprint as bp
from lcv_replay.sinks.config import RerunOutputs
from lcv_replay.sinks.rerun_sink import RerunSink
from lcv_replay.sinks.summary import SummarySink
from tests.replay.helpers import last_row, read_rrd, write_config

FRAMES = 120
SEED = 3

IMAGE_ROUTE_TOML = """
[retrieval]
backend = "thumbnail"
exclusion_frames = 30
top_k = 5
hamming_threshold = 4

[verification]
window_frames = 40
iterations_per_window = 2
hypotheses_per_iteration = 3
max_hypotheses = 12

[rerun]
image_every = 10
log_right_image = true
"""


@pytest.fixture(scope="module")
def demo_cache(tmp_path_factory):
    cache = tmp_path_factory.mktemp("cache")
    old = os.environ.get("LCV_CACHE_DIR")
    os.environ["LCV_CACHE_DIR"] = str(cache)
    try:
        log = ensure_demo_log(FRAMES, SEED, DEMO_WIDTH_PX, DEMO_HEIGHT_PX, quiet=True)
        yield cache, log
    finally:
        if old is None:
            os.environ.pop("LCV_CACHE_DIR", None)
        else:
            os.environ["LCV_CACHE_DIR"] = old


def test_the_demo_recording_is_cached_by_its_settings(demo_cache):
    cache, log = demo_cache
    assert log == demo_log_path(FRAMES, SEED, DEMO_WIDTH_PX, DEMO_HEIGHT_PX) and log.parent == cache / "demo"
    before = log.stat().st_mtime_ns
    assert ensure_demo_log(FRAMES, SEED, DEMO_WIDTH_PX, DEMO_HEIGHT_PX, quiet=True) == log
    assert log.stat().st_mtime_ns == before  # reused, not recorded again
    assert demo_log_path(FRAMES, SEED + 1, DEMO_WIDTH_PX, DEMO_HEIGHT_PX) != log


def test_image_route_logs_camera_and_retrieval(demo_cache, tmp_path):
    _, log = demo_cache
    config = load_config(write_config(tmp_path / "images.toml", IMAGE_ROUTE_TOML))
    rrd, js = tmp_path / "images.rrd", tmp_path / "images.json"
    summary = replay(ReplayOptions(log_path=log, config=config, seed=SEED),
                     [RerunSink(config.rerun, RerunOutputs(save=rrd)), SummarySink(json_path=js)], handle_sigint=False)
    assert summary.constraint_source == "images" and summary.frames == FRAMES
    assert summary.truth_source == "ground_truth" and summary.constraints > 0
    tables = read_rrd(rrd)
    for path in (bp.CAMERA_LEFT, bp.CAMERA_RIGHT, bp.RETRIEVAL_CODE, bp.RETRIEVAL_DISTANCES, bp.RETRIEVAL_MATCHES,
                 bp.RETRIEVAL_LINES, bp.metric_path("prefilter_size"), bp.CONSTRAINTS_ACCEPTED,
                 bp.CONSTRAINTS_REJECTED):
        assert path in tables, path
    assert tables[bp.CAMERA_LEFT].column("frame").to_pylist() == list(range(0, FRAMES, 10))
    queries = [f for f in tables[bp.RETRIEVAL_CODE].column("frame").to_pylist() if f is not None]
    assert min(queries) == 30  # warm-up: Δt = 30 frames, then every frame queries
    code = last_row(tables[bp.RETRIEVAL_CODE], "Image:buffer")[0]
    assert len(code) == 24 and set(code) <= {0, 255}  # ranked codes: 30 warm-up frames span 29 PCA axes, 24 bits
    # The last query's table and distance series agree; L2 distances sorted (best first).
    row = [v for v in last_row(tables[bp.RETRIEVAL_DISTANCES], "Scalars:scalars") if v == v]  # drop NaN
    assert row == sorted(row) and 1 <= len(row) <= 5
    text = last_row(tables[bp.RETRIEVAL_MATCHES], "TextDocument:text")[0]
    assert text.count("\n| ") == len(row) + 1  # header row + one row per match
    lines = tables[bp.RETRIEVAL_LINES]
    assert len(last_row(lines, "LineStrips2D:strips")) == len(last_row(lines, "match_frame")) == len(row)
    data = json.loads(js.read_text())
    assert data["constraints"] == summary.constraints and data["constraint_source"] == "images"
    # recall both ways: against the candidates proposed, and against every ground-truth revisit
    # (this short drive does not come back to a place more than Δt frames later: no revisit to close)
    assert data["revisits"] == data["revisits_proposed"] == data["revisits_closed"] == 0 and data["revisit_recall"] is None
    assert summary.revisits == 0


def test_demo_command_replays_the_cached_recording(demo_cache, tmp_path):
    _, log = demo_cache
    before = log.stat().st_mtime_ns
    rrd, js = tmp_path / "demo.rrd", tmp_path / "demo.json"
    result = CliRunner().invoke(app, ["demo", "--frames", str(FRAMES), "--seed", str(SEED), "--save", str(rrd),
                                      "--summary-json", str(js), "--quiet"])
    assert result.exit_code == 0, result.output
    assert log.stat().st_mtime_ns == before
    assert f"rerun {rrd}" in result.output and "lcv-replay summary" in result.output
    assert "revisit recall" in result.output  # recall both ways in the demo's summary
    data = json.loads(js.read_text())
    assert data["frames"] == FRAMES and data["constraint_source"] == "images" and data["log"] == str(log)
    assert data["config"]["retrieval"]["backend"] == "efficientnet-lite0"  # the defaults
    # our retrieval's loops are same-place (no relative pose): ilv+ verifies them with its hypothesis table
    assert data["config"]["verification"]["ilv_plus"]["loops"] == "same-place"
    assert bp.CAMERA_LEFT in read_rrd(rrd)
