"""``lcv-replay open REC.rrd --first-wrong``: the one command the summary prints puts a real
viewer's time cursor on the first wrong acceptance."""

from __future__ import annotations

import os
import shutil
import time

import pytest
from typer.testing import CliRunner

from lcv_replay.cli import app
from lcv_replay.report.rrd import read_run_record
from tests.sinks.test_viewer_layout import _free_port, _vulkan_available


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("rerun") is None, reason="the rerun viewer executable (rerun-sdk) is not on PATH")
@pytest.mark.skipif(not _vulkan_available(), reason="no Vulkan adapter for a headless viewer (apt-get install mesa-vulkan-drivers)")
def test_open_at_the_first_wrong_acceptance(square_run):
    from rerun.experimental import ViewerClient

    first = read_run_record(square_run.rrd).first_wrong_acceptance()
    assert first is not None, "the fixture's ilv run accepts a false loop at some window"
    assert f"lcv-replay open {square_run.rrd} --frame {first.first_accepted_frame}" in square_run.output
    os.environ.setdefault("WGPU_BACKEND", "vulkan")
    try:
        viewer = ViewerClient.spawn(headless=True, port=_free_port(), hide_welcome_screen=True, memory_limit="2GB")
    except Exception as exc:
        pytest.skip(f"headless viewer unavailable here: {exc}")
    try:
        result = CliRunner().invoke(app, ["open", str(square_run.rrd), "--first-wrong", "--connect", viewer.url])
        assert result.exit_code == 0, result.output
        assert f"at frame {first.first_accepted_frame} (paused)" in result.output
        deadline = time.monotonic() + 30
        state = viewer.get_state()
        while (not state.recordings or state.recordings[0].current_time is None) and time.monotonic() < deadline:
            time.sleep(0.5)
            state = viewer.get_state()
        (recording,) = state.recordings
        assert recording.current_timeline == "frame" and recording.current_time == first.first_accepted_frame
    finally:
        viewer.quit()



def test_open_refuses_what_it_cannot_show(square_run, tmp_path):
    result = CliRunner().invoke(app, ["open", str(tmp_path / "missing.rrd")])
    assert result.exit_code == 2 and result.output.startswith("error:") and "recording not found" in result.output
