"""The HTML report: the same page at the end of a replay and from its recording, self-contained,
rendered by a real headless Chromium; bad recordings get one ``error:`` line."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from lcv_replay.cli import app
from tests.postmortem.conftest import one_error

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser") or ("/usr/bin/chromium" if Path("/usr/bin/chromium").exists() else None)


def test_report_from_the_recording_equals_the_report_at_the_end_of_the_replay(square_run, tmp_path):
    out = tmp_path / "again.html"
    result = CliRunner().invoke(app, ["report", str(square_run.rrd), "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert out.read_bytes() == square_run.report.read_bytes()
    assert f"report            {square_run.report}" in square_run.output


def test_report_is_one_self_contained_page_with_every_section(square_run):
    page = square_run.report.read_text(encoding="utf-8")
    for heading in ("Summary", "Final map", "Precision, recall and ATE over time", "Fig. U", "Fig. V", "Fig. W",
                    "Fig. X", "Wrong and missed loops", "Accepted but false", "True loops missed", "Timings"):
        assert heading in page, heading
    assert len(re.findall(r'<img [^>]*src="data:image/png;base64,', page)) == 7  # map, metrics, U, V, W, X, timings
    assert not re.search(r'(src|href)="(https?:)?//', page)  # nothing fetched from the network
    assert "<script" not in page and "<link" not in page
    s = square_run.summary
    assert f"precision {s['precision']:.3f}" in page and f"{s['ate_rmse_m']:.2f} m" in page
    assert "verification.window_frames" in page  # the config


@pytest.mark.skipif(CHROMIUM is None, reason="headless Chromium is not installed (Debian: apt-get install chromium)")
def test_chromium_renders_the_report_with_its_figures(square_run, tmp_path):
    import cv2

    png = tmp_path / "report.png"
    done = subprocess.run(
        [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--no-first-run", f"--screenshot={png}",
         "--window-size=1280,4200", square_run.report.resolve().as_uri()],
        capture_output=True, text=True, timeout=120,
    )
    assert png.is_file(), done.stderr[-2000:]
    image = cv2.imread(str(png))[:, :, ::-1].astype(int)
    assert image.shape[:2] == (4200, 1280)

    def pixels_like(rgb: tuple[int, int, int]) -> int:
        return int(np.count_nonzero(np.abs(image - np.array(rgb)).sum(axis=2) < 30))

    # The figures were decoded and painted: the estimate's gold, the accepted loops' green and the
    # recall's blue appear (an image that failed to load shows none of them).
    assert pixels_like((201, 151, 0)) > 500  # final estimate (map, Fig. V)
    assert pixels_like((35, 176, 74)) > 200  # accepted true loops, precision
    assert pixels_like((74, 127, 212)) > 100  # recall, window points


def test_report_on_bad_recordings_is_one_error_line(square_run, tmp_path):
    text = tmp_path / "notes.rrd"
    text.write_text("not a recording\n")
    one_error(["report", str(text), "-o", str(tmp_path / "a.html")], "notes.rrd", "not a readable Rerun recording")
    truncated = tmp_path / "truncated.rrd"
    data = square_run.rrd.read_bytes()
    truncated.write_bytes(data[: len(data) // 2])
    one_error(["report", str(truncated), "-o", str(tmp_path / "b.html")], "truncated.rrd")
    import rerun as rr

    foreign = tmp_path / "foreign.rrd"
    rec = rr.RecordingStream("someone-else", send_properties=False)
    rec.save(str(foreign))
    rec.log("/points", rr.Points2D([[0.0, 1.0]]))
    rec.flush()
    rec.disconnect()
    one_error(["report", str(foreign), "-o", str(tmp_path / "c.html")], "foreign.rrd", "not an lcv-replay")
    one_error(["report", str(tmp_path / "missing.rrd")], "missing.rrd", "not found")
    assert not list(tmp_path.glob("*.html"))  # nothing half-written


def test_report_refuses_to_overwrite_without_force(square_run, tmp_path):
    out = tmp_path / "r.html"
    out.write_text("keep me")
    one_error(["report", str(square_run.rrd), "-o", str(out)], "already exists", "--force")
    assert out.read_text() == "keep me"
    assert CliRunner().invoke(app, ["report", str(square_run.rrd), "-o", str(out), "--force"]).exit_code == 0


@pytest.mark.slow
def test_kitti00_report_from_the_recording_equals_the_live_one(kitti_run, tmp_path):
    out = tmp_path / "kitti.html"
    assert CliRunner().invoke(app, ["report", str(kitti_run.rrd), "-o", str(out)]).exit_code == 0
    assert out.read_bytes() == kitti_run.report.read_bytes()
