"""Screenshot what ``rerun REC.rrd`` shows first, for the demo and KITTI 00 with ``ilv+`` and ``ilv``,
and fail on an empty first screen.

Usage::

    python examples/viewer_screenshots.py OUT_DIR            # builds what is missing in OUT_DIR
    python examples/viewer_screenshots.py OUT_DIR --only kitti00-ilvplus

Each recording is made once in ``OUT_DIR`` (``demo.rrd``; ``kitti00.mcap`` recorded from
``../shared/data/robustslam_kitti/00/kitti_00_alpha_0.50.g2o``, then ``kitti00-ilvplus.rrd`` and
``kitti00-ilv.rrd``; the ``ilv`` replay takes minutes) and reused afterwards. Each is screenshot
with ``../shared/tools/viewer-screenshot.sh`` (the real viewer, headless) into ``OUT_DIR/<name>.png``
and every panel of the default layout is measured (``lcv_replay.sinks.screenshot``). Prints one
line per recording and exits 1 if a first screen has an empty panel, 2 if the viewer cannot run.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

from lcv_replay.sinks.screenshot import cannot_screenshot, first_screen, take_screenshot

DATA = Path(os.environ.get("LCV_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
KITTI_GRAPH = DATA / "robustslam_kitti" / "00" / "kitti_00_alpha_0.50.g2o"


def _run(*args: str) -> None:
    print("$ lcv-replay " + " ".join(args), flush=True)
    entry = "import sys; from lcv_replay.cli import main; sys.argv[0] = 'lcv-replay'; main()"
    subprocess.run([sys.executable, "-c", entry, *args], check=True)


def build(name: str, out: Path) -> Path:
    rrd = out / f"{name}.rrd"
    if rrd.is_file():
        return rrd
    if name == "demo":
        _run("demo", "--save", str(rrd), "--quiet")
        return rrd
    log = out / "kitti00.mcap"
    if not log.is_file():
        _run("record", "g2o", str(KITTI_GRAPH), "-o", str(log))
    method = {"kitti00-ilvplus": "ilv+", "kitti00-ilv": "ilv"}[name]
    _run(str(log), "--method", method, "--save", str(rrd), "--quiet")
    return rrd


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--only", choices=("demo", "kitti00-ilvplus", "kitti00-ilv"), action="append")
    args = parser.parse_args()
    reason = cannot_screenshot()
    if reason is not None:
        print(f"skipped: {reason}")
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    failed = False
    for name in args.only or ("demo", "kitti00-ilvplus", "kitti00-ilv"):
        if name != "demo" and not KITTI_GRAPH.is_file():
            print(f"{name}: skipped, {KITTI_GRAPH} not found")
            continue
        try:
            png = take_screenshot(build(name, args.out), args.out / f"{name}.png")
        except RuntimeError as exc:
            print(f"{name}: no screenshot ({exc})")
            failed = True
            continue
        fill = first_screen(png)
        empty = fill.empty_panels()
        failed |= bool(empty)
        figures = ", ".join(f"{panel} {value:.3f}" for panel, value in fill.fill.items())
        print(f"{name}: {'EMPTY ' + ', '.join(empty) if empty else 'ok'} ({figures}) -> {png}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
