"""Build small dataset trees in ``tmp_path`` from the real frames in ``../shared/data``.

The shared data holds a handful of real images per dataset, not whole sequences; the trees below
lay them out as the real datasets are laid out, reusing images where a camera has too few
(documented per tree). Poses, times and calibrations are the real ones.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from tests.conftest import shared_path

# KITTI calibration of sequences 04-12 (06 among them), from the data README.
KITTI06_FX = 707.0912
KITTI06_CX = 601.8873
KITTI06_CY = 183.1104
KITTI06_FX_BASELINE = 379.8145

# Source frames of sequence 06 that have a real left image in kitti06_frames.
KITTI06_FRAMES = (1, 12, 13, 435, 436)


def kitti06_calib_text() -> str:
    p0 = f"{KITTI06_FX} 0 {KITTI06_CX} 0 0 {KITTI06_FX} {KITTI06_CY} 0 0 0 1 0"
    p1 = f"{KITTI06_FX} 0 {KITTI06_CX} {-KITTI06_FX_BASELINE} 0 {KITTI06_FX} {KITTI06_CY} 0 0 0 1 0"
    return f"P0: {p0}\nP1: {p1}\nP2: {p0}\nP3: {p1}\n"


def build_kitti_tree(root: Path, frames: tuple[int, ...] = KITTI06_FRAMES) -> dict:
    """``root/sequences/06/{image_0,image_1,calib.txt,times.txt}`` and ``root/poses/06.txt``.

    Tree frame ``k`` is sequence-06 frame ``frames[k]``: its left image, time and pose are the real
    ones. Only frame 12 has a real right image (``kitti06-12-R.png``); every other tree frame
    reuses it as a stand-in right image (the recorder does not look at image content).

    Returns a dict with the source rows: ``times_s`` ``(K,)``, ``poses`` ``(K, 12)``, ``left``,
    ``right`` (source image paths per tree frame), ``sequence`` (the sequence folder).
    """
    src = shared_path("kitti06_frames")
    seq = root / "sequences" / "06"
    (seq / "image_0").mkdir(parents=True)
    (seq / "image_1").mkdir()
    (root / "poses").mkdir()
    all_times = np.loadtxt(src / "times.txt")
    all_poses = np.loadtxt(src / "06.txt")
    lefts, rights = [], []
    for k, frame in enumerate(frames):
        left = src / f"kitti06-{frame:02d}.png"
        right = src / f"kitti06-{frame:02d}-R.png"
        right = right if right.exists() else src / "kitti06-12-R.png"
        shutil.copyfile(left, seq / "image_0" / f"{k:06d}.png")
        shutil.copyfile(right, seq / "image_1" / f"{k:06d}.png")
        lefts.append(left)
        rights.append(right)
    times = all_times[list(frames)]
    poses = all_poses[list(frames)]
    (seq / "times.txt").write_text("".join(f"{t:.6e}\n" for t in times))
    (seq / "calib.txt").write_text(kitti06_calib_text())
    np.savetxt(root / "poses" / "06.txt", poses, fmt="%.9e")
    return {"times_s": times, "poses": poses, "left": lefts, "right": rights, "sequence": seq}
