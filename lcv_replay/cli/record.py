"""``lcv-replay record FORMAT SOURCE -o OUT.mcap``: the dataset recorders (``recorders/``).

Each command converts its arguments into the recorder's options dataclass, runs the recorder with a
rich progress bar on stderr (unless ``--quiet``) and prints a one-line summary. Recorder modules
(and with them cv2, mcap) are imported inside the command bodies so that ``--help`` stays fast.
"""

from __future__ import annotations

import contextlib
import logging
from pathlib import Path
from typing import Iterator, Optional

import enum

import typer

from lcv_replay.cli.app import force_option, record_app

log = logging.getLogger(__name__)

class OutlierModeChoice(str, enum.Enum):
    random = "random"
    local = "local"
    group = "group"


class PoseFormatChoice(str, enum.Enum):
    auto = "auto"
    kitti = "kitti"
    tum = "tum"


class ImageFormatChoice(str, enum.Enum):
    png = "png"
    jpeg = "jpeg"
    raw = "raw"


class LoopMeasurementsChoice(str, enum.Enum):
    as_recorded = "as-recorded"
    same_place = "same-place"


OUT_OPTION = typer.Option(..., "--out", "-o", help="Output .mcap file (written atomically).")
FORCE_OPTION = force_option("OUT")
QUIET_OPTION = typer.Option(False, "--quiet", "-q", help="No progress bar and no summary line.")
IMAGE_FORMAT_OPTION = typer.Option(ImageFormatChoice.png, "--image-format", help="png (lossless), jpeg or raw.")
JPEG_QUALITY_OPTION = typer.Option(95, "--jpeg-quality", min=1, max=100, help="JPEG quality with --image-format jpeg.")
START_FRAME_OPTION = typer.Option(0, "--start-frame", min=0, help="First source frame to record.")
MAX_FRAMES_OPTION = typer.Option(None, "--max-frames", min=1, help="Record at most this many frames.")
#: Ground truth, the same in every recorder: ``--ground-truth PATH`` gives it; ``--no-ground-truth``
#: records none, even where the recorder finds one next to the data.
NO_GROUND_TRUTH_OPTION = typer.Option(False, "--no-ground-truth", help="Record no ground truth, even where ROOT/poses/SS.txt exists.")
LIVE_OPTION = typer.Option(
    False, "--live",
    help="Write OUT itself chunk by chunk (one flushed chunk per frame) so that 'lcv-replay OUT --follow' can watch it while it "
    "records. Gives up the atomic rename: OUT is visible and incomplete meanwhile; an interrupted run leaves the frames so far.",
)

# Topic options of bags, shared by 'record rosbag' and the direct replay 'lcv-replay BAG'.
LEFT_TOPIC_OPTION = typer.Option(None, "--left-topic", help="Left camera: sensor_msgs/Image or CompressedImage (default: the only stereo pair or image topic).")
RIGHT_TOPIC_OPTION = typer.Option(None, "--right-topic", help="Right camera (default: the left topic's left/right sibling).")
NO_IMAGES_OPTION = typer.Option(False, "--no-images", help="Import no images (odometry and ground truth only).")
ODOM_TOPIC_OPTION = typer.Option(None, "--odom-topic", help="Odometry: nav_msgs/Odometry, PoseStamped or PoseWithCovarianceStamped (default: the only candidate; '' for none).")
ODOM_FROM_TF_OPTION = typer.Option(None, "--odom-from-tf", metavar="PARENT:CHILD", help="Odometry from the /tf and /tf_static chain PARENT -> CHILD, e.g. odom:base_link.")
GROUND_TRUTH_TOPIC_OPTION = typer.Option(None, "--ground-truth-topic", help="Ground truth, same types (default: the pose topic named like groundtruth/gt/vicon/mocap, if only one; '' for none).")
GROUND_TRUTH_FROM_TF_OPTION = typer.Option(None, "--ground-truth-from-tf", metavar="PARENT:CHILD", help="Ground truth from a TF chain, e.g. map:base_link.")


@contextlib.contextmanager
def recording_progress(description: str, *, quiet: bool) -> Iterator:
    """Yield a ``progress(done, total)`` callback drawing a rich progress bar on stderr (or ``None``).

    No bar when stderr is not a terminal (a log file or a pipe gets no control characters, and an
    error stays one line).
    """
    from rich.console import Console

    console = Console(stderr=True)
    if quiet or not console.is_terminal:
        yield None
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("frames"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
        transient=True,
    ) as bar:
        task = bar.add_task(description, total=None)

        def update(done: int, total: int) -> None:
            bar.update(task, completed=done, total=total)

        yield update


def run_recording(record, *, quiet: bool) -> None:
    """Run ``record()`` (returns ``RecordStats``) where Ctrl-C or SIGTERM stops it after the current frame.

    The log of the frames so far is closed and summarised, and the command exits ``128 + signal``
    (130, 143); a second signal aborts at once and leaves no file (:mod:`lcv_replay.shutdown`).
    """
    from lcv_replay.shutdown import StopToken, stop_on_signals

    stop = StopToken()
    with stop_on_signals(stop, what="stopping after this frame and closing the log"):
        stats = record()
    if not quiet or stats.interrupted:
        typer.echo(stats.summary())
    if stats.interrupted:
        raise typer.Exit(stop.exit_code)


def _run_recorder(name: str, source, out: Path, options, *, force: bool, quiet: bool, live: bool = False) -> None:
    """Run the registered recorder ``name`` with a progress bar, then print its one-line summary."""
    from recorders import get_recorder

    record = get_recorder(name).load()

    def run():
        with recording_progress(name, quiet=quiet) as progress:
            return record(source, out, options, force=force, progress=progress, live=live)

    run_recording(run, quiet=quiet)


@record_app.command("g2o")
def record_g2o_command(
    graph: Path = typer.Argument(..., help="2-D pose graph: .g2o (VERTEX_SE2/EDGE_SE2), TORO, or Vertigo groundTruth .dat."),
    out: Path = OUT_OPTION,
    ground_truth: Optional[Path] = typer.Option(None, "--ground-truth", help="Ground truth: g2o vertices, g2o edge chain i->i+1, or 'x y theta' lines."),
    true_loops: Optional[Path] = typer.Option(None, "--true-loops", help="True-loop labels, 'i j' per line."),
    auto_siblings: bool = typer.Option(True, "--auto-siblings/--no-auto-siblings", help="For robustslam_kitti kitti_SS_alpha_A.g2o, use the sibling _GT_LC.txt labels and kitti_SS_GT.g2o."),
    outliers: int = typer.Option(0, "--outliers", min=0, help="Inject this many false loops (Vertigo protocol)."),
    outlier_mode: OutlierModeChoice = typer.Option(OutlierModeChoice.random, "--outlier-mode", case_sensitive=False, help="random: any two poses; local: within 20 poses; group: runs of mutually consistent loops."),
    group_size: int = typer.Option(10, "--group-size", min=1, help="Loops per run in group mode."),
    seed: int = typer.Option(0, "--seed", help="Random seed of the outlier injection."),
    loop_measurements: LoopMeasurementsChoice = typer.Option(LoopMeasurementsChoice.as_recorded, "--loop-measurements", help="Keep each loop edge's relative pose, or drop it ('same place', as a place recognizer reports)."),
    original_loops_true: Optional[bool] = typer.Option(None, "--original-loops-true/--original-loops-unlabelled", help="Label the graph's own loops true when no --true-loops is given (default: only when injecting outliers)."),
    rate_hz: float = typer.Option(10.0, "--rate-hz", help="Frame rate for the stamps (robustslam_kitti VO is 10 Hz)."),
    start_ns: int = typer.Option(0, "--start-ns", help="Stamp of frame 0 in nanoseconds."),
    source: Optional[str] = typer.Option(None, "--source", help="Detector name on the graph's candidates (default: DLoopDetector for robustslam_kitti, else g2o)."),
    dataset: Optional[str] = typer.Option(None, "--dataset", help="Dataset name for the log metadata."),
    force: bool = FORCE_OPTION,
    quiet: bool = QUIET_OPTION,
    live: bool = LIVE_OPTION,
) -> None:
    """Record a 2-D pose graph: odometry chain -> /odom, other edges -> /loop_candidates."""
    from recorders.g2o import G2oOptions

    options = G2oOptions(
        ground_truth=ground_truth,
        true_loops=true_loops,
        auto_siblings=auto_siblings,
        outliers=outliers,
        outlier_mode=outlier_mode.value,  # type: ignore[arg-type]
        group_size=group_size,
        seed=seed,
        loop_measurements=loop_measurements.value,  # type: ignore[arg-type]
        original_loops_true=original_loops_true,
        rate_hz=rate_hz,
        start_stamp_ns=start_ns,
        source=source,
        dataset=dataset,
    )
    _run_recorder("g2o", graph, out, options, force=force, quiet=quiet, live=live)


@record_app.command("kitti")
def record_kitti_command(
    source: Path = typer.Argument(..., help="KITTI sequence folder (sequences/SS) or the dataset root with --sequence."),
    out: Path = OUT_OPTION,
    sequence: Optional[str] = typer.Option(None, "--sequence", help="Sequence name (e.g. 06) when SOURCE is the dataset root."),
    odometry: Optional[Path] = typer.Option(None, "--odometry", help="Odometry of the left camera: KITTI pose file or TUM file (stamps = times.txt)."),
    odometry_format: PoseFormatChoice = typer.Option(PoseFormatChoice.auto, "--odometry-format", help="auto (by column count), kitti or tum."),
    ground_truth: Optional[Path] = typer.Option(None, "--ground-truth", help="Ground-truth poses (default: ROOT/poses/SS.txt if present)."),
    no_ground_truth: bool = NO_GROUND_TRUTH_OPTION,
    _auto_ground_truth: bool = typer.Option(True, "--auto-ground-truth", hidden=True, help="Old spelling of the default."),
    color: bool = typer.Option(False, "--color", help="Record image_2/image_3 (P2/P3) instead of the grey pair."),
    start_frame: int = START_FRAME_OPTION,
    max_frames: Optional[int] = MAX_FRAMES_OPTION,
    vo: bool = typer.Option(False, "--vo", help="Compute /odom with stereo visual odometry on the images (instead of --odometry)."),
    stamp_tolerance_s: float = typer.Option(0.01, "--stamp-tolerance", help="TUM stamps must match times.txt within this many seconds."),
    image_format: ImageFormatChoice = IMAGE_FORMAT_OPTION,
    jpeg_quality: int = JPEG_QUALITY_OPTION,
    force: bool = FORCE_OPTION,
    quiet: bool = QUIET_OPTION,
    live: bool = LIVE_OPTION,
) -> None:
    """Record a KITTI odometry sequence (stereo images, calibration, odometry, ground truth)."""
    from recorders.kitti import KittiOptions

    options = KittiOptions(
        sequence=sequence,
        odometry=odometry,
        odometry_format=odometry_format.value,  # type: ignore[arg-type]
        ground_truth=ground_truth,
        auto_ground_truth=not no_ground_truth,
        color=color,
        start_frame=start_frame,
        max_frames=max_frames,
        stamp_tolerance_s=stamp_tolerance_s,
        vo=vo,
        image_format=image_format.value,  # type: ignore[arg-type]
        jpeg_quality=jpeg_quality,
    )
    _run_recorder("kitti", source, out, options, force=force, quiet=quiet, live=live)


@record_app.command("euroc")
def record_euroc_command(
    source: Path = typer.Argument(..., help="EuRoC sequence folder holding mav0 (or mav0 itself)."),
    out: Path = OUT_OPTION,
    rectify: bool = typer.Option(True, "--rectify/--no-rectify", help="Rectify the stereo pair (cv2.stereoRectify) and write the rectified calibration; --no-rectify writes raw distorted images."),
    odometry: Optional[Path] = typer.Option(None, "--odometry", help="Left-camera odometry (TUM with stamps in seconds, or KITTI format, one line per frame)."),
    odometry_format: PoseFormatChoice = typer.Option(PoseFormatChoice.auto, "--odometry-format", help="auto, kitti or tum."),
    vo: bool = typer.Option(False, "--vo", help="Compute /odom with stereo visual odometry on the images (instead of --odometry)."),
    no_ground_truth: bool = typer.Option(False, "--no-ground-truth", help="Record no ground truth, even where mav0/state_groundtruth_estimate0 exists."),
    _ground_truth: bool = typer.Option(True, "--ground-truth", hidden=True, help="Old spelling of the default."),
    stereo_tolerance_ns: int = typer.Option(1_000_000, "--stereo-tolerance-ns", min=0, help="Left/right stamps closer than this form a pair."),
    start_frame: int = START_FRAME_OPTION,
    max_frames: Optional[int] = MAX_FRAMES_OPTION,
    image_format: ImageFormatChoice = IMAGE_FORMAT_OPTION,
    jpeg_quality: int = JPEG_QUALITY_OPTION,
    force: bool = FORCE_OPTION,
    quiet: bool = QUIET_OPTION,
    live: bool = LIVE_OPTION,
) -> None:
    """Record a EuRoC (ASL layout) stereo sequence, rectified, with its ground truth."""
    from recorders.euroc import EurocOptions

    options = EurocOptions(
        rectify=rectify,
        odometry=odometry,
        odometry_format=odometry_format.value,  # type: ignore[arg-type]
        ground_truth=not no_ground_truth,
        stereo_tolerance_ns=stereo_tolerance_ns,
        start_frame=start_frame,
        vo=vo,
        max_frames=max_frames,
        image_format=image_format.value,  # type: ignore[arg-type]
        jpeg_quality=jpeg_quality,
    )
    _run_recorder("euroc", source, out, options, force=force, quiet=quiet, live=live)


class StampSourceChoice(str, enum.Enum):
    auto = "auto"
    names = "names"
    odometry = "odometry"
    rate = "rate"


@record_app.command("folder")
def record_folder_command(
    source: Optional[Path] = typer.Argument(None, help="Folder holding left/, right/, odometry.csv, ground_truth.csv, calibration.yaml (each overridable)."),
    out: Path = OUT_OPTION,
    left: Optional[Path] = typer.Option(None, "--left", help="Left image folder (default SOURCE/left)."),
    right: Optional[Path] = typer.Option(None, "--right", help="Right image folder with the same file names (default SOURCE/right)."),
    odometry: Optional[Path] = typer.Option(None, "--odometry", help="Planar odometry CSV: timestamp_ns,x_m,y_m,yaw_rad (default SOURCE/odometry.csv)."),
    ground_truth: Optional[Path] = typer.Option(None, "--ground-truth", help="Planar ground-truth CSV, same format (default SOURCE/ground_truth.csv)."),
    calibration: Optional[Path] = typer.Option(None, "--calibration", help="Rectified stereo calibration, YAML or JSON: fx, fy, cx, cy, baseline_m [, width, height, distortion]."),
    vo: bool = typer.Option(False, "--vo", help="Compute /odom with stereo visual odometry on the images (instead of --odometry)."),
    stamps: StampSourceChoice = typer.Option(StampSourceChoice.auto, "--stamps", help="Frame stamps from ns file names, odometry rows, or --rate-hz."),
    rate_hz: Optional[float] = typer.Option(None, "--rate-hz", help="Frame rate for --stamps rate."),
    max_gap_ns: Optional[int] = typer.Option(None, "--max-gap-ns", min=1, help="Largest pose gap bridged by interpolation (default: 3 frame periods)."),
    dataset: Optional[str] = typer.Option(None, "--dataset", help="Dataset name for the log metadata."),
    image_format: ImageFormatChoice = IMAGE_FORMAT_OPTION,
    jpeg_quality: int = JPEG_QUALITY_OPTION,
    force: bool = FORCE_OPTION,
    quiet: bool = QUIET_OPTION,
    live: bool = LIVE_OPTION,
) -> None:
    """Record left/right image folders plus a timestamped planar odometry CSV."""
    from recorders.folder import FolderOptions

    options = FolderOptions(
        left=left,
        right=right,
        odometry=odometry,
        ground_truth=ground_truth,
        calibration=calibration,
        stamps=stamps.value,  # type: ignore[arg-type]
        rate_hz=rate_hz,
        max_gap_ns=max_gap_ns,
        dataset=dataset,
        vo=vo,
        image_format=image_format.value,  # type: ignore[arg-type]
        jpeg_quality=jpeg_quality,
    )
    _run_recorder("folder", source, out, options, force=force, quiet=quiet, live=live)


class TimeSourceChoice(str, enum.Enum):
    auto = "auto"
    header = "header"
    log = "log"


def rosbag_options(
    *,
    left_topic: Optional[str] = None,
    right_topic: Optional[str] = None,
    no_images: bool = False,
    odom_topic: Optional[str] = None,
    odom_from_tf: Optional[str] = None,
    ground_truth_topic: Optional[str] = None,
    ground_truth_from_tf: Optional[str] = None,
    **more,
):
    """The :class:`recorders.rosbag.RosbagOptions` of the topic flags (shared with the direct replay)."""
    from recorders.rosbag import RosbagOptions

    return RosbagOptions(
        left_topic=left_topic,
        right_topic=right_topic,
        no_images=no_images,
        odom_topic=odom_topic,
        odom_from_tf=odom_from_tf,
        ground_truth_topic=ground_truth_topic,
        ground_truth_from_tf=ground_truth_from_tf,
        **more,
    )


@record_app.command("rosbag")
def record_rosbag_command(
    bag: list[Path] = typer.Argument(..., metavar="BAG", help="ROS 1 .bag file(s) (split parts in any order), a ROS 2 bag folder (metadata.yaml + .db3/.mcap), a .db3, or a ROS 2 .mcap."),
    out: Path = OUT_OPTION,
    left_topic: Optional[str] = LEFT_TOPIC_OPTION,
    right_topic: Optional[str] = RIGHT_TOPIC_OPTION,
    no_images: bool = NO_IMAGES_OPTION,
    odom_topic: Optional[str] = ODOM_TOPIC_OPTION,
    odom_from_tf: Optional[str] = ODOM_FROM_TF_OPTION,
    ground_truth_topic: Optional[str] = GROUND_TRUTH_TOPIC_OPTION,
    ground_truth_from_tf: Optional[str] = GROUND_TRUTH_FROM_TF_OPTION,
    left_info_topic: Optional[str] = typer.Option(None, "--left-info-topic", help="sensor_msgs/CameraInfo of the left camera (default: the sibling camera_info)."),
    right_info_topic: Optional[str] = typer.Option(None, "--right-info-topic", help="sensor_msgs/CameraInfo of the right camera (default: the sibling camera_info)."),
    time_source: TimeSourceChoice = typer.Option(TimeSourceChoice.auto, "--time-source", help="Stamps from header.stamp, the bag's receive time (log), or header unless zero (auto)."),
    max_rate_hz: Optional[float] = typer.Option(None, "--max-rate-hz", help="Without images: keep at most this many odometry frames per second."),
    stereo_tolerance_ns: int = typer.Option(1_000_000, "--stereo-tolerance-ns", min=0, help="Left/right stamps closer than this form a pair."),
    max_gap_ns: int = typer.Option(500_000_000, "--max-gap-ns", min=1, help="Largest pose (or TF) gap bridged by interpolation to the frame stamps."),
    max_frames: Optional[int] = MAX_FRAMES_OPTION,
    vo: bool = typer.Option(False, "--vo", help="Compute /odom with stereo visual odometry on the images (instead of an odometry topic)."),
    dataset: Optional[str] = typer.Option(None, "--dataset", help="Dataset name for the log metadata (default: the bag's name)."),
    image_format: ImageFormatChoice = IMAGE_FORMAT_OPTION,
    jpeg_quality: int = JPEG_QUALITY_OPTION,
    force: bool = FORCE_OPTION,
    quiet: bool = QUIET_OPTION,
    live: bool = LIVE_OPTION,
) -> None:
    """Import a ROS 1 or ROS 2 bag (rosbags): stereo images, odometry (a pose topic or a TF chain), ground truth.

    Topics you do not name are chosen when there is only one candidate of their kind (a note says
    which); with several, the error lists them and the flag to choose. 'lcv-replay info BAG' shows
    what a bag holds and the command to import it.
    """
    options = rosbag_options(
        left_topic=left_topic, right_topic=right_topic, no_images=no_images, odom_topic=odom_topic, odom_from_tf=odom_from_tf,
        ground_truth_topic=ground_truth_topic, ground_truth_from_tf=ground_truth_from_tf,
        left_info_topic=left_info_topic,
        right_info_topic=right_info_topic,
        time_source=time_source.value,
        max_rate_hz=max_rate_hz,
        stereo_tolerance_ns=stereo_tolerance_ns,
        max_gap_ns=max_gap_ns,
        max_frames=max_frames,
        dataset=dataset,
        image_format=image_format.value,
        jpeg_quality=jpeg_quality,
        vo=vo,
    )
    _run_recorder("rosbag", bag, out, options, force=force, quiet=quiet, live=live)


# The importer of earlier versions read ROS 2 MCAP only; its name stays as an alias.
record_app.command("ros2", hidden=True, help="Alias of 'record rosbag' (kept for existing scripts).")(record_rosbag_command)
