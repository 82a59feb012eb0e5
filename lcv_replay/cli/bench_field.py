"""``lcv-replay bench follow`` (latency of ``--follow``, :mod:`lcv_replay.bench.follow`) and ``bench rosbag``
(import speed of a bag, :mod:`lcv_replay.bench.rosbag`)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from lcv_replay.cli.app import bench_app, check_outputs, force_option

DEFAULT_GRAPH = Path("robustslam_kitti") / "00" / "kitti_00_alpha_0.50.g2o"


@bench_app.command("follow", help="Latency of --follow: a real g2o log re-recorded live at 10 Hz; chunk on disk -> frame in the recording.")
def bench_follow_command(
    log: Optional[Path] = typer.Option(None, "--log", help="An lcv-replay log to re-record live (default: KITTI 00 alpha 0.50 of ../shared/data, recorded from its g2o graph)."),
    frames: int = typer.Option(600, "--frames", min=2, help="Frames to follow (600 = one minute at 10 Hz)."),
    rate_hz: float = typer.Option(10.0, "--rate-hz", help="Frames per second of the live writer."),
    poll_s: float = typer.Option(0.05, "--poll-s", help="Seconds between two looks at the growing file."),
    outputs: list[str] = typer.Option(["file", "serve"], "--outputs", help="file (--save only) and/or serve (a live gRPC server too)."),
    output: Path = typer.Option(Path("bench-out/follow.json"), "-o", "--output", help="JSON results."),
    force: bool = force_option("the JSON results"),
) -> None:
    import json
    import os
    import tempfile

    from lcv_replay.bench.follow import format_results, results_to_json, run_follow_benchmark
    from lcv_replay.fileio import write_text_atomic

    output.parent.mkdir(parents=True, exist_ok=True)
    check_outputs(output, force=force)
    with tempfile.TemporaryDirectory() as tmp:
        if log is None:
            from recorders.g2o import record_g2o

            shared = Path(os.environ.get("LCV_SHARED_DATA", Path(__file__).resolve().parents[3] / "shared" / "data"))
            log = Path(tmp) / "source.mcap"
            record_g2o(shared / DEFAULT_GRAPH, log)
        results = [run_follow_benchmark(log, frames=frames, rate_hz=rate_hz, poll_s=poll_s, outputs=o) for o in outputs]
    typer.echo(format_results(results))
    typer.echo("goal: p99 < 1000 ms at 10 Hz: " + ("met" if all(r.latency_p99_ms < 1000 for r in results) else "NOT met"))
    write_text_atomic(output, json.dumps(results_to_json(results), indent=2) + "\n")
    typer.echo(f"wrote {output}")


@bench_app.command("rosbag", help="Import speed of a bag (messages/s), side by side with rosbags alone reading and deserialising the same messages.")
def bench_rosbag_command(
    bag: Optional[Path] = typer.Argument(None, help="The bag (default: ../shared/data/ros1/ROS_example.bag with --odom-topic ORB-SLAM)."),
    odom_topic: Optional[str] = typer.Option(None, "--odom-topic", help="Odometry topic (default: ORB-SLAM for the default bag, else chosen)."),
    odom_from_tf: Optional[str] = typer.Option(None, "--odom-from-tf", metavar="PARENT:CHILD", help="Odometry from a TF chain."),
    repeats: int = typer.Option(4, "--repeats", min=1, help="Runs per measurement after one warm-up run; medians are reported."),
    output: Path = typer.Option(Path("bench-out/rosbag_import.json"), "-o", "--output", help="JSON results."),
    force: bool = force_option("the JSON results"),
) -> None:
    import json
    import os

    from lcv_replay.bench.rosbag import format_results, results_to_json, run_import_benchmark
    from lcv_replay.fileio import write_text_atomic
    from recorders.rosbag import RosbagOptions

    output.parent.mkdir(parents=True, exist_ok=True)
    check_outputs(output, force=force)
    if bag is None:
        shared = Path(os.environ.get("LCV_SHARED_DATA", Path(__file__).resolve().parents[3] / "shared" / "data"))
        bag = shared / "ros1" / "ROS_example.bag"
        odom_topic = odom_topic or "ORB-SLAM"
    results = run_import_benchmark(bag, RosbagOptions(odom_topic=odom_topic, odom_from_tf=odom_from_tf), repeats=repeats)
    typer.echo(format_results(results))
    write_text_atomic(output, json.dumps(results_to_json(results), indent=2) + "\n")
    typer.echo(f"wrote {output}")
