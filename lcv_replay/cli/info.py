"""`lcv-replay info LOG [--json] [--recover]`: inspect a log, like ``ros2 bag info``.

LOG is an lcv-replay MCAP log, or any foreign log: a ROS 1 bag (several split parts), a ROS 2 bag
folder or ``.db3``, a ROS 2 ``.mcap``, or any other MCAP. A foreign log gets ``ros2 bag info``'s
listing plus what lcv-replay could use from it and the command that imports it
(:func:`recorders.bags.inspect_bag`).
"""

from __future__ import annotations

from pathlib import Path

import typer

from lcv_replay.cli.app import app, bench_app, check_outputs, force_option


@app.command("info", help="Show a log's topics, counts, rates, frames and contents (like 'ros2 bag info'); also ROS 1/ROS 2 bags and any MCAP.")
def info_command(
    logs: list[Path] = typer.Argument(..., metavar="LOG", help="An lcv-replay MCAP log, or a foreign log: ROS 1 .bag (split parts), ROS 2 bag folder, .db3, ROS 2 or other .mcap."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object (stable keys; see docs/log-format.md)."),
    recover: bool = typer.Option(False, "--recover", help="Salvage the complete chunks of a truncated or damaged file."),
    check: bool = typer.Option(
        True, "--check/--no-check", help="Verify every chunk's CRC and decode odometry and candidates (default on)."
    ),
) -> None:
    import json

    from lcv_replay.errors import ConfigError, LogFormatError
    from lcv_replay.log.container import load_container
    from lcv_replay.log.inspect import format_info, info_to_json
    from lcv_replay.log import format as fmt
    from lcv_replay.log.reader import EXPECTED_SCHEMAS, LogReader
    from recorders.bags import bag_info_to_json, format_bag_info, inspect_bag, inspect_mcap, is_foreign_log

    if len(logs) > 1 or is_foreign_log(logs[0]):
        if recover:
            raise ConfigError("--recover applies to lcv-replay logs", fix="drop --recover for a bag")
        bag = inspect_bag(logs)
        typer.echo(json.dumps(bag_info_to_json(bag), indent=2) if as_json else format_bag_info(bag))
        return
    log = logs[0]
    container = load_container(log, recover=recover)
    try:
        reader = LogReader(container)
    except LogFormatError as exc:
        topics = {ch.topic for ch in container.channels.values()}
        if fmt.METADATA_NAME in container.metadata or not topics or topics & set(EXPECTED_SCHEMAS):
            raise  # an lcv-replay log (or an empty file): say what is wrong with it
        # Some other MCAP (channels, but no lcv metadata and none of our topics): list it as 'ros2 bag info' would.
        bag = inspect_mcap(container, reason=exc.message)
        typer.echo(json.dumps(bag_info_to_json(bag), indent=2) if as_json else format_bag_info(bag))
        return
    with reader:
        if check:
            reader.check()
        info = reader.info
    if info.recovered_messages is not None:
        typer.echo(
            f"note: {log}: recovered {info.recovered_messages} messages from {info.chunk_count} complete chunks"
            + (f", skipped {info.skipped_chunks} damaged chunks" if info.skipped_chunks else ""),
            err=True,
        )
    if as_json:
        typer.echo(json.dumps(info_to_json(info), indent=2))
    else:
        typer.echo(format_info(info))


@bench_app.command("log", help="Log I/O benchmark: write/read throughput and size of 640x480 RGB stereo logs.")
def bench_log_command(
    frames: int = typer.Option(300, "--frames", help="Frames per run."),
    resolution: str = typer.Option("640x480", "--resolution", help="WxH of each image."),
    source: list[str] = typer.Option(["corridor", "synthetic"], "--source", help="corridor (real RTAB-Map images) and/or synthetic; repeat for both."),
    image_format: str = typer.Option("png", "--image-format", help="png, jpeg or raw."),
    compression: str = typer.Option("zstd", "--compression", help="zstd, lz4 or none."),
    repeats: int = typer.Option(3, "--repeats", help="Runs per source; medians are reported."),
    corridor: Path = typer.Option(None, "--corridor", help="Folder of the corridor JPEGs (default $LCV_SHARED_DATA/rtabmap_corridor)."),
    output: Path = typer.Option(Path("bench-out/log_bench.json"), "-o", "--output", help="JSON results."),
    force: bool = force_option("the JSON results"),
) -> None:
    import json

    from lcv_replay.errors import ConfigError
    from lcv_replay.fileio import write_text_atomic
    from lcv_replay.log.bench import format_results, results_to_json, run_log_benchmark

    try:
        width, height = (int(v) for v in resolution.lower().split("x"))
    except ValueError:
        raise ConfigError(f"resolution {resolution!r} is not WxH", fix="e.g. --resolution 640x480") from None
    output.parent.mkdir(parents=True, exist_ok=True)
    check_outputs(output, force=force)
    if corridor is None:
        import os

        shared = os.environ.get("LCV_SHARED_DATA", Path(__file__).resolve().parents[3] / "shared" / "data")
        corridor = Path(shared) / "rtabmap_corridor"
    results = [
        run_log_benchmark(
            frames=frames, width_px=width, height_px=height, source=s, corridor=corridor,
            image_format=image_format, compression=compression, repeats=repeats,
        )
        for s in source
    ]
    typer.echo(format_results(results))
    write_text_atomic(output, json.dumps(results_to_json(results), indent=2) + "\n")
    typer.echo(f"wrote {output}")
