"""Check what a user sees on opening a recording: a real viewer screenshot, measured panel by panel.

:func:`take_screenshot` runs the shared tool ``viewer-screenshot.sh REC.rrd OUT.png`` (the real
Rerun viewer, headless, on Xvfb and Mesa's software Vulkan) — what ``rerun REC.rrd`` shows first,
without touching the time cursor — or :func:`headless_screenshot`, the same viewer headless on a
port of its own (the tool's ``rerun`` uses the default port 9876, so two screenshots taken at once
can show each other's recording; tests use the headless one). :func:`first_screen` measures how much is drawn in each panel of
the default layout (:func:`lcv_replay.sinks.blueprint.default_blueprint`); an empty map, an
"(empty)" hypotheses panel or a blank metrics plot shows up as a fill near zero.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: Panels of the default layout as fractions ``(x0, y0, x1, y1)`` of the window, inside their
#: frames (titles excluded): columns 5 : 3 : 4 wide, the time panel expanded below ~77 %.
PANELS: dict[str, tuple[float, float, float, float]] = {
    "map": (0.01, 0.07, 0.40, 0.62),
    "top hypotheses": (0.43, 0.09, 0.65, 0.32),
    "generation tree": (0.43, 0.38, 0.65, 0.74),
    "rank chart": (0.68, 0.07, 0.99, 0.18),
    "consistency": (0.68, 0.22, 0.99, 0.34),
    "metrics": (0.68, 0.39, 0.99, 0.50),
    "events": (0.68, 0.56, 0.99, 0.75),
}
#: The least fill of each panel on a first screen that shows the answer (measured: an empty panel,
#: "(empty)" or a bare plot, is below a tenth of these; KITTI 00 fills them 3 to 30 times over).
MIN_FILL: dict[str, float] = {
    "map": 0.02, "top hypotheses": 0.02, "generation tree": 0.005, "rank chart": 0.05,
    "consistency": 0.05, "metrics": 0.004, "events": 0.02,
}
#: A pixel is drawn when its colour differs from the panel's background by more than this (sum
#: of the absolute RGB differences).
INK_THRESHOLD = 60


@dataclass(frozen=True)
class ScreenFill:
    """Share of drawn pixels per panel (0..1) of one screenshot."""

    png: Path
    fill: dict[str, float]

    def empty_panels(self, minimum: dict[str, float] | None = None) -> list[str]:
        """The panels drawn less than ``minimum`` (default :data:`MIN_FILL`)."""
        minimum = MIN_FILL if minimum is None else minimum
        return [name for name, value in self.fill.items() if value < minimum.get(name, 0.0)]


def screenshot_tool() -> Path | None:
    """``viewer-screenshot.sh``: ``$LCV_VIEWER_SCREENSHOT``, else ``../shared/tools`` beside the repo."""
    env = os.environ.get("LCV_VIEWER_SCREENSHOT")
    candidates = [Path(env)] if env else []
    candidates.append(Path(__file__).resolve().parents[3] / "shared" / "tools" / "viewer-screenshot.sh")
    return next((c for c in candidates if c.is_file()), None)


def cannot_screenshot(*, tool: bool = True) -> str | None:
    """Why no viewer screenshot can be taken here (with the shared tool, or headless), or ``None``."""
    import glob

    if shutil.which("rerun") is None:
        return "the rerun viewer (rerun-sdk) is not on PATH"
    if tool:
        if screenshot_tool() is None:
            return "viewer-screenshot.sh not found (set LCV_VIEWER_SCREENSHOT or check out ../shared/tools)"
        if shutil.which("Xvfb") is None:
            return "Xvfb is not installed (apt-get install xvfb mesa-vulkan-drivers)"
    elif not (glob.glob("/usr/share/vulkan/icd.d/*.json") or glob.glob("/etc/vulkan/icd.d/*.json")):
        return "no Vulkan adapter for a headless viewer (apt-get install mesa-vulkan-drivers)"
    return None


def _port_in_use(port: int) -> bool:
    import socket

    with socket.socket() as s:
        s.settimeout(0.3)
        return s.connect_ex(("127.0.0.1", port)) == 0


def take_screenshot(rrd: str | Path, png: str | Path, *, timeout_s: float = 240.0) -> Path:
    """Screenshot ``rrd`` as ``rerun REC.rrd`` first shows it; returns the PNG path.

    The shared tool runs ``rerun REC.rrd`` on the default port 9876. When that port is taken
    (another viewer: the tool's ``rerun`` would hand the file to it), or the tool writes nothing
    (the software renderer gave up on a loaded machine), the same first screen is taken from a
    headless viewer of our own on a free port (the file opened, the time cursor left where the
    recording's blueprint puts it).

    Raises:
        RuntimeError: neither way gave a screenshot.
    """
    tool = screenshot_tool()
    png = Path(png)
    if tool is None or _port_in_use(9876):
        return headless_screenshot(rrd, png, timeout_s=timeout_s)
    png.unlink(missing_ok=True)
    done = subprocess.run(["bash", str(tool), str(rrd), str(png)], capture_output=True, text=True, timeout=timeout_s)
    if done.returncode == 0 and png.is_file():
        return png
    try:
        return headless_screenshot(rrd, png, timeout_s=timeout_s)
    except Exception as exc:  # the viewer's own errors are not ours to type
        raise RuntimeError(f"viewer-screenshot.sh failed ({done.stderr.strip()[-200:]}), and a headless viewer too ({exc})") from None


def headless_screenshot(rrd: str | Path, png: str | Path, *, timeout_s: float = 240.0) -> Path:
    """Open ``rrd`` in a headless viewer of our own (a free port) and save what it shows first."""
    import socket
    import time

    from rerun.experimental import ViewerClient

    os.environ.setdefault("WGPU_BACKEND", "vulkan")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    viewer = ViewerClient.spawn(headless=True, port=port, hide_welcome_screen=True, memory_limit="2GB")
    try:
        viewer.open(str(Path(rrd).resolve()))
        deadline = time.monotonic() + timeout_s
        state = viewer.get_state()
        while (state.loading or not state.recordings or not state.recordings[0].timelines) and time.monotonic() < deadline:
            time.sleep(0.5)
            state = viewer.get_state()
        time.sleep(2.0)  # let every view paint once
        Path(png).write_bytes(viewer.take_screenshot())
    finally:
        viewer.quit()
    return Path(png)


def panel_fill(image: np.ndarray, box: tuple[float, float, float, float]) -> float:
    """Share of pixels in ``box`` (fractions of the image) that differ from its background.

    Args:
        image: ``(H, W, 3|4)`` uint8 screenshot.
    """
    h, w = image.shape[:2]
    x0, y0, x1, y1 = box
    region = np.asarray(image[int(y0 * h): int(y1 * h), int(x0 * w): int(x1 * w), :3], dtype=np.int32)
    if region.size == 0:
        return 0.0
    pixels = region.reshape(-1, 3)
    values, counts = np.unique(pixels // 8, axis=0, return_counts=True)  # the background: the commonest colour
    background = values[np.argmax(counts)] * 8 + 4
    return float(np.mean(np.abs(pixels - background).sum(axis=1) > INK_THRESHOLD))


def first_screen(png: str | Path) -> ScreenFill:
    """The fill of every panel of :data:`PANELS` in a screenshot."""
    import cv2

    image = cv2.imread(str(png), cv2.IMREAD_COLOR)
    if image is None:
        raise RuntimeError(f"{png}: not a readable image")
    image = image[:, :, ::-1]  # BGR -> RGB
    return ScreenFill(Path(png), {name: panel_fill(image, box) for name, box in PANELS.items()})
