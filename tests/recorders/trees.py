"""Build small dataset trees in ``tmp_path`` from the real frames in ``../shared/data``.

The shared data holds a handful of real images per dataset, not whole sequences; the trees below
lay them out as the real datasets are laid out, reusing images where a camera has too few
(documented per tree). Poses, times and calibrations are the real ones.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from recorders.common import project_to_planar
from tests.shared_data import shared_path

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


# EuRoC: 4 real stereo pairs (2 loop-closure pairs) from Kimera-VIO's test data.
EUROC_FIRST_STAMP_NS = 1_403_636_579_763_555_584  # MH_01_easy's first cam0 stamp
EUROC_PERIOD_NS = 50_000_000  # 20 Hz


def build_euroc_tree(root: Path, *, ground_truth: bool = True) -> dict:
    """``root/mav0/{cam0,cam1}/{data.csv,data/,sensor.yaml}`` + ``state_groundtruth_estimate0``.

    The 4 pairs ``left_img_N``/``right_img_N`` become frames 0..3, stamped 50 ms apart from a real
    EuRoC stamp (the pairs come from different moments of a sequence; their real stamps are not
    published with them). The ground truth has one row per frame at the frame's stamp, from
    ``gt_poses_from_testLoopClosureDetector.txt`` (``world_T_body``, quaternion w x y z), plus
    zeros for velocity and biases as in the 17-column ASL file.

    Returns ``stamps_ns`` ``(4,)``, ``T_world_body`` ``(4, 4, 4)``, ``left``/``right`` source paths.
    """
    src = shared_path("euroc_loop_pairs")
    mav0 = root / "mav0"
    stamps = [EUROC_FIRST_STAMP_NS + k * EUROC_PERIOD_NS for k in range(4)]
    for cam, prefix, yaml in (("cam0", "left", "sensorLeft.yaml"), ("cam1", "right", "sensorRight.yaml")):
        (mav0 / cam / "data").mkdir(parents=True)
        shutil.copyfile(src / yaml, mav0 / cam / "sensor.yaml")
        lines = ["#timestamp [ns],filename"]
        for k, stamp in enumerate(stamps):
            shutil.copyfile(src / f"{prefix}_img_{k}.png", mav0 / cam / "data" / f"{stamp}.png")
            lines.append(f"{stamp},{stamp}.png")
        (mav0 / cam / "data.csv").write_text("\n".join(lines) + "\n")
    T_world_body = []
    rows = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
            "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], "
            "b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"]
    gt_lines = [ln.split() for ln in (src / "gt_poses_from_testLoopClosureDetector.txt").read_text().splitlines()
                if ln.strip() and not ln.startswith("#")]
    for stamp, fields in zip(stamps, gt_lines):
        qw, qx, qy, qz, x, y, z = (float(v) for v in fields[2:9])
        rows.append(",".join([str(stamp)] + [repr(v) for v in (x, y, z, qw, qx, qy, qz)] + ["0"] * 9))
        from recorders.common import transforms_from_quaternions

        T_world_body.append(transforms_from_quaternions([x, y, z], [qx, qy, qz, qw])[0])
    if ground_truth:
        (mav0 / "state_groundtruth_estimate0").mkdir()
        (mav0 / "state_groundtruth_estimate0" / "data.csv").write_text("\n".join(rows) + "\n")
    return {
        "stamps_ns": np.array(stamps, dtype=np.int64),
        "T_world_body": np.array(T_world_body),
        "left": [src / f"left_img_{k}.png" for k in range(4)],
        "right": [src / f"right_img_{k}.png" for k in range(4)],
        "root": root,
    }


EPOCH_NS = 1_317_000_000_000_000_000


def build_folder_tree(root: Path, *, named_by_stamp: bool) -> dict:
    """left/ right/ odometry.csv ground_truth.csv calibration.yaml from kitti06_frames.

    Left images are the 5 real left frames; right images reuse the only real right image (frame
    12) as a stand-in for every frame. Odometry = the real ground truth projected to planar.
    """
    src = shared_path("kitti06_frames")
    times = np.loadtxt(src / "times.txt")[list(KITTI06_FRAMES)]
    poses = np.loadtxt(src / "06.txt")[list(KITTI06_FRAMES)]
    T = np.tile(np.eye(4), (len(poses), 1, 1))
    T[:, :3, :] = poses.reshape(-1, 3, 4)
    planar = project_to_planar(T)
    stamps = EPOCH_NS + np.rint(times * 1e9).astype(np.int64)
    (root / "left").mkdir(parents=True)
    (root / "right").mkdir()
    for k, frame in enumerate(KITTI06_FRAMES):
        name = f"{stamps[k]}.png" if named_by_stamp else f"{k:06d}.png"
        shutil.copyfile(src / f"kitti06-{frame:02d}.png", root / "left" / name)
        shutil.copyfile(src / "kitti06-12-R.png", root / "right" / name)
    rows = "timestamp_ns,x_m,y_m,yaw_rad\n" + "".join(f"{s},{float(x)!r},{float(y)!r},{float(t)!r}\n" for s, (x, y, t) in zip(stamps, planar))
    (root / "odometry.csv").write_text(rows)
    (root / "calibration.yaml").write_text(
        f"fx: {KITTI06_FX}\nfy: {KITTI06_FX}\ncx: {KITTI06_CX}\ncy: {KITTI06_CY}\nbaseline_m: {KITTI06_FX_BASELINE / KITTI06_FX}\n"
    )
    return {"stamps_ns": stamps, "planar": planar, "left": [src / f"kitti06-{f:02d}.png" for f in KITTI06_FRAMES]}
