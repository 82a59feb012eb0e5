"""What ``rerun REC.rrd`` shows first, in the real viewer: the map with the estimate and its
loops, the hypotheses panels filled, metrics drawn.

The check measures each panel of the default layout on the screenshot and fails on an empty
first screen (``lcv_replay.sinks.screenshot``). The viewer runs headless on a port of its own, so
that tests running at the same time never see each other's recording (the shared
``viewer-screenshot.sh`` uses the default port; ``examples/viewer_screenshots.py`` uses it for the
demo and KITTI 00 with ``ilv+`` and ``ilv``). Skipped, with the reason, where the viewer cannot run.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from lcv_replay.sinks.screenshot import MIN_FILL, cannot_screenshot, first_screen, headless_screenshot

pytestmark = pytest.mark.skipif(cannot_screenshot(tool=False) is not None, reason=str(cannot_screenshot(tool=False)))


def _keep(png: Path) -> None:
    folder = os.environ.get("LCV_SCREENSHOT_DIR")
    if folder:
        Path(folder).mkdir(parents=True, exist_ok=True)
        (Path(folder) / png.name).write_bytes(png.read_bytes())


def test_the_check_fails_on_an_empty_first_screen(tmp_path):
    """A recording with our layout but nothing at the time the viewer opens on: every panel empty."""
    import rerun as rr

    from lcv_replay.sinks.blueprint import default_blueprint

    rrd = tmp_path / "empty.rrd"
    rec = rr.RecordingStream("lcv-replay", send_properties=False)
    rec.save(str(rrd))
    rec.send_blueprint(default_blueprint(has_images=False, has_retrieval=False, frames=100), make_active=True)
    rec.set_time("frame", sequence=0)
    rec.log("/metrics/constraints", rr.Scalars(0.0))
    rec.flush()
    rec.disconnect()
    fill = first_screen(headless_screenshot(rrd, tmp_path / "empty.png"))
    assert {"map", "top hypotheses", "generation tree", "rank chart", "consistency"} <= set(fill.empty_panels()), fill.fill


def test_a_replay_opens_on_the_answer(square_run, tmp_path):
    png = headless_screenshot(square_run.rrd, tmp_path / "square-ilv.png")
    _keep(png)
    fill = first_screen(png)
    assert fill.empty_panels() == [], (fill.fill, MIN_FILL)


@pytest.mark.slow
def test_kitti00_opens_on_the_answer(kitti_run, tmp_path):
    png = headless_screenshot(kitti_run.rrd, tmp_path / "kitti00-ilvplus.png")
    _keep(png)
    fill = first_screen(png)
    assert fill.empty_panels() == [], (fill.fill, MIN_FILL)
