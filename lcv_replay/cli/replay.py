"""`lcv-replay LOG.mcap [options]`: the replay (the hidden default command ``replay``).

Field logs are replayed as they come (the field-log part of this command):

* a ROS 1 bag, ROS 2 bag or ROS 2 MCAP is converted first (:func:`recorders.convert.converted_log`:
  the topic options of ``record rosbag``, cached by content and options), then replayed;
* ``--follow`` opens the log with the follower of :mod:`lcv_replay.log.follow` (a reader mode: the
  replay itself is unchanged), for a log that a recorder is still writing.
"""

from __future__ import annotations

import enum
import logging
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import typer

from lcv_replay.cli.app import LcvCommand, app, check_outputs, config_option, force_option
from lcv_replay.cli.record import (
    GROUND_TRUTH_FROM_TF_OPTION,
    GROUND_TRUTH_TOPIC_OPTION,
    LEFT_TOPIC_OPTION,
    NO_IMAGES_OPTION,
    ODOM_FROM_TF_OPTION,
    ODOM_TOPIC_OPTION,
    RIGHT_TOPIC_OPTION,
)

logger = logging.getLogger(__name__)


class ConstraintChoice(str, enum.Enum):
    images = "images"
    log = "log"
    both = "both"


def default_save_path(log_path: Path, name: str | None = None) -> Path:
    """``LOG.rrd`` next to the log (``NAME.rrd`` if given), or in the current folder when the log's
    folder is not writable."""
    beside = log_path.with_suffix(".rrd") if name is None else log_path.parent / f"{name}.rrd"
    folder = beside.parent if str(beside.parent) else Path(".")
    if os.access(folder, os.W_OK):
        return beside
    return Path.cwd() / beside.name


def build_sinks(*, rerun_config, outputs, summary_json: Optional[Path], quiet: bool,
                export: Optional[Path] = None, report: Optional[Path] = None) -> list:
    """The sinks of one replay, in call order: progress, run record, Rerun, summary, export,
    report, (serve until Ctrl-C). Every output path is checked here, before any work starts.

    Args:
        rerun_config: the config's ``[rerun]`` section.
        outputs: a :class:`~lcv_replay.sinks.config.RerunOutputs`, or ``None`` for no Rerun output.
        export: ``--export DIR``; report: ``--report FILE.html``.
    """
    from lcv_replay.sinks.run_record import RunRecorder
    from lcv_replay.sinks.summary import SummarySink

    sinks: list = []
    if not quiet:
        from lcv_replay.sinks.progress import ProgressSink

        sinks.append(ProgressSink())
    recorder = RunRecorder()
    sinks.append(recorder)
    rerun_sink = None
    if outputs is not None and outputs.any:
        from lcv_replay.sinks.rerun_sink import RerunSink

        rerun_sink = RerunSink(rerun_config, outputs)
        sinks.append(rerun_sink)
    sinks.append(SummarySink(stream=sys.stdout, json_path=summary_json, recorder=recorder))
    if export is not None:
        from lcv_replay.export.sink import ExportSink

        sinks.append(ExportSink(recorder, export, stream=sys.stdout))
    if report is not None:
        from lcv_replay.report.sink import ReportSink

        sinks.append(ReportSink(recorder, report, stream=sys.stdout))
    if rerun_sink is not None and outputs.serve:
        sinks.append(_ServeUntilInterrupted(rerun_sink))
    return sinks


class _ServeUntilInterrupted:
    """After the replay, keeps the served viewer up until Ctrl-C (``--serve``)."""

    recording_path = None

    def __init__(self, rerun_sink):
        self.rerun_sink = rerun_sink

    def on_start(self, start) -> None:
        typer.echo(f"web viewer: {self.rerun_sink.served_url}", err=True)

    def on_frame(self, update) -> None:
        pass

    def on_retrieval(self, update) -> None:
        pass

    def on_step(self, update) -> None:
        pass

    def on_finish(self, summary) -> None:
        import time

        from lcv_replay.shutdown import stop_requested

        typer.echo(f"serving the recording at {self.rerun_sink.served_url} — press Ctrl-C to stop", err=True)
        try:
            while not stop_requested():
                time.sleep(0.2)
        except KeyboardInterrupt:
            pass

    def close(self) -> None:
        pass


class ReplayCommand(LcvCommand):
    """The default command: its usage is ``lcv-replay LOG.mcap [OPTIONS]``."""

    def format_usage(self, ctx, formatter) -> None:
        formatter.write_usage(ctx.parent.command_path if ctx.parent else ctx.command_path, "LOG.mcap [OPTIONS]")


@app.command("replay", cls=ReplayCommand, hidden=True, help="Replay LOG.mcap (or a ROS bag, converted on the fly) through retrieval and incremental verification, logging every step to Rerun.")
def replay_command(
    logs: list[Path] = typer.Argument(..., metavar="LOG", help="An lcv-replay MCAP log, or a ROS 1 bag (split parts), ROS 2 bag folder, .db3 or ROS 2 .mcap (converted first)."),
    rate: str = typer.Option("max", "--rate", "-r", help="Playback rate: 1.0 = real time by the log's timestamps; 'max' = as fast as possible."),
    start_offset: float = typer.Option(0.0, "--start-offset", help="Start this many seconds into the log."),
    duration: Optional[float] = typer.Option(None, "--duration", help="Replay only this many seconds."),
    method: Optional[str] = typer.Option(None, "--method", "-m", help="Verifier: ilv (the paper), ilv+, none, ir-only, dcs, gm, cauchy, gnc, oracle (default: the config's verification.method)."),
    constraints: Optional[ConstraintChoice] = typer.Option(None, "--constraints", case_sensitive=False, help="Loop constraints from our retrieval on the images, the log's /loop_candidates, or both (default: log if it has candidates, else images)."),
    config: Optional[Path] = config_option("over the paper defaults, unknown keys refused"),
    seed: Optional[int] = typer.Option(None, "--seed", help="Seed of retrieval and verification (default: the config's)."),
    save: Optional[Path] = typer.Option(None, "--save", help="Write the Rerun recording here (default: LOG.rrd next to the log, or in the current folder if that one is not writable)."),
    no_save: bool = typer.Option(False, "--no-save", help="Write no .rrd (with --spawn/--connect/--serve)."),
    spawn: bool = typer.Option(False, "--spawn", help="Open a Rerun viewer and stream to it."),
    connect: Optional[str] = typer.Option(None, "--connect", help="Stream to a running viewer, e.g. rerun+http://127.0.0.1:9876/proxy."),
    serve: bool = typer.Option(False, "--serve", help="Serve gRPC + the web viewer on 127.0.0.1 and print the URL; keeps serving after the replay until Ctrl-C."),
    grpc_port: int = typer.Option(9876, "--grpc-port", help="gRPC port for --spawn / --serve."),
    web_port: int = typer.Option(9090, "--web-port", help="Web viewer port for --serve."),
    memory_limit: Optional[str] = typer.Option(None, "--memory-limit", help="Viewer/server memory limit, e.g. 25% or 4GB (default: the config's rerun.memory_limit)."),
    image_every: Optional[int] = typer.Option(None, "--image-every", min=0, help="Log the camera image every k-th frame (0: never; default: the config's rerun.image_every)."),
    no_rerun: bool = typer.Option(False, "--no-rerun", help="No Rerun output at all (summary only)."),
    summary_json: Optional[Path] = typer.Option(None, "--summary-json", help="Also write the summary as JSON (keys: docs/summary-json.md)."),
    export: Optional[Path] = typer.Option(None, "--export", metavar="DIR", help="Write the results for other tools into DIR (created if missing): trajectory.tum/.kitti, odometry.tum, ground_truth.tum, loops.csv, accepted.g2o, config.toml, summary.json."),
    report: Optional[Path] = typer.Option(None, "--report", metavar="FILE.html", help="Write a self-contained HTML report of the run (also later: 'lcv-replay report REC.rrd')."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
    recover: bool = typer.Option(False, "--recover", help="Read the complete chunks of a truncated log."),
    follow: bool = typer.Option(False, "--follow", help="Follow a log that is still being written (record ... --live): read each chunk as it lands; end at its footer, after --idle-timeout without growth, or on Ctrl-C."),
    idle_timeout: float = typer.Option(30.0, "--idle-timeout", metavar="S", help="With --follow: end after S seconds without growth (a writer that stopped)."),
    left_topic: Optional[str] = LEFT_TOPIC_OPTION,
    right_topic: Optional[str] = RIGHT_TOPIC_OPTION,
    no_images: bool = NO_IMAGES_OPTION,
    odom_topic: Optional[str] = ODOM_TOPIC_OPTION,
    odom_from_tf: Optional[str] = ODOM_FROM_TF_OPTION,
    ground_truth_topic: Optional[str] = GROUND_TRUTH_TOPIC_OPTION,
    ground_truth_from_tf: Optional[str] = GROUND_TRUTH_FROM_TF_OPTION,
    keep_converted: bool = typer.Option(False, "--keep-converted", help="For a bag: write the converted log beside it (NAME.lcv.mcap) instead of the cache (~/.cache/lcv-replay/converted)."),
    force: bool = force_option("the recording, the summary JSON, the report and the export folder's files"),
) -> None:
    import dataclasses

    from lcv_replay.config import load_config
    from lcv_replay.pacing import parse_rate
    from lcv_replay.replay import ReplayOptions, replay
    from lcv_replay.shutdown import StopToken

    topic_flags = {
        "--left-topic": left_topic, "--right-topic": right_topic, "--no-images": no_images or None,
        "--odom-topic": odom_topic, "--odom-from-tf": odom_from_tf, "--ground-truth-topic": ground_truth_topic,
        "--ground-truth-from-tf": ground_truth_from_tf, "--keep-converted": keep_converted or None,
    }
    check_outputs(None if no_rerun or no_save else save, summary_json, report, force=force, folder=export)  # before converting a bag
    stop = StopToken()
    field = _field_log(logs, topic_flags, follow=follow, recover=recover, quiet=quiet, idle_timeout_s=idle_timeout, stop=stop)
    log = field.path
    replay_config = load_config(config)
    if image_every is not None:
        replay_config = dataclasses.replace(replay_config, rerun=dataclasses.replace(replay_config.rerun, image_every=image_every))
    options = ReplayOptions(
        log_path=log,
        config=replay_config,
        method=method,
        constraints=None if constraints is None else constraints.value,
        rate=parse_rate(rate),
        start_offset_s=start_offset,
        duration_s=duration,
        seed=seed,
        recover=recover,
        open_reader=_follower(field.follow_idle_timeout_s or idle_timeout, stop) if follow else None,
    )
    if not log.exists():  # before any output is touched
        from lcv_replay.errors import LogFormatError

        raise LogFormatError("file not found", path=log, fix="check the path")
    outputs = None
    if not no_rerun:
        from lcv_replay.sinks.config import RerunOutputs

        save_path = None if no_save else (save if save is not None else field.default_rrd)
        # A file the user names is never overwritten without --force; the default recording beside
        # the log is the replay's own output, replaced by each run (as 'lcv-replay demo' does).
        check_outputs(save_path, force=force or save is None)
        if save is None and save_path is not None and save_path.exists():
            logger.info("replacing %s (the default recording; name one with --save to keep this one)", save_path)
        outputs = RerunOutputs(
            save=save_path,
            spawn=spawn, connect=connect, serve=serve, grpc_port=grpc_port, web_port=web_port,
            memory_limit=memory_limit,
        )
    sinks = build_sinks(rerun_config=replay_config.rerun, outputs=outputs, summary_json=summary_json, quiet=quiet,
                        export=export, report=report)
    try:
        summary = replay(options, sinks, stop=stop)
    except KeyboardInterrupt as exc:  # before the first frame (a follower waiting for the recorder)
        typer.echo("interrupted before the first frame: nothing to summarise", err=True)
        raise typer.Exit(getattr(exc, "exit_code", 130)) from None
    finally:
        field.close()
    if summary.interrupted:
        raise typer.Exit(stop.exit_code)


@dataclass
class _FieldLog:
    """What the replay reads for the LOG argument: the log, its default .rrd, and a live conversion to wait for."""

    path: Path
    default_rrd: Path
    conversion: object = None  # recorders.rosbag_live.LiveConversion while following a bag being recorded
    follow_idle_timeout_s: float | None = None

    def close(self) -> None:
        """Stop waiting for a live conversion; raise its error (after the replay's outputs are written)."""
        if self.conversion is None:
            return
        self.conversion.join(timeout=60.0)
        if self.conversion.error is not None:
            raise self.conversion.error


def _field_log(logs: list[Path], topic_flags: dict, *, follow: bool, recover: bool, quiet: bool, idle_timeout_s: float,
               stop) -> _FieldLog:
    """The lcv-replay log to replay: a bag is converted first (its .rrd goes beside the bag); a ROS 2
    MCAP being recorded is converted chunk by chunk while the replay follows the conversion."""
    from lcv_replay.errors import ConfigError
    from recorders.bags import is_foreign_log

    given = [flag for flag, value in topic_flags.items() if value is not None]
    if len(logs) == 1 and not is_foreign_log(logs[0]):
        if given:
            raise ConfigError(
                f"{', '.join(given)} applies to bags, and {logs[0]} is an lcv-replay log (its topics are fixed)",
                fix="drop the option, or pass the bag itself",
            )
        return _FieldLog(logs[0], default_save_path(logs[0]))
    if recover:
        raise ConfigError("--recover applies to lcv-replay logs, not to bags", fix="drop --recover")
    from lcv_replay.cli.record import recording_progress, rosbag_options

    options = rosbag_options(
        left_topic=topic_flags["--left-topic"], right_topic=topic_flags["--right-topic"],
        no_images=bool(topic_flags["--no-images"]), odom_topic=topic_flags["--odom-topic"],
        odom_from_tf=topic_flags["--odom-from-tf"], ground_truth_topic=topic_flags["--ground-truth-topic"],
        ground_truth_from_tf=topic_flags["--ground-truth-from-tf"],
    )
    keep = bool(topic_flags["--keep-converted"])
    if follow:
        return _follow_bag(logs, options, keep=keep, quiet=quiet, idle_timeout_s=idle_timeout_s, stop=stop)
    from recorders.convert import converted_log

    with recording_progress("converting", quiet=quiet) as progress:
        converted = converted_log(logs, options, keep_converted=keep, progress=progress)
    if not quiet:
        verb = "using the conversion of" if converted.reused else "converted"
        typer.echo(f"{verb} {converted.source.display}: {converted.path}", err=True)
    return _FieldLog(converted.path, default_save_path(converted.source.paths[0], converted.source.name))


def _follow_bag(logs: list[Path], options, *, keep: bool, quiet: bool, idle_timeout_s: float, stop) -> _FieldLog:
    """--follow on a ROS 2 MCAP being recorded: convert it chunk by chunk in a thread, follow the conversion."""
    import time

    from lcv_replay.errors import ConfigError
    from recorders.convert import cache_dir
    from recorders.rosbag_live import start_live_conversion

    path = logs[0]
    if path.is_dir():  # a ROS 2 bag folder being recorded: its newest .mcap is the part being written
        parts = sorted(path.glob("*.mcap"), key=lambda p: p.stat().st_mtime)
        path = parts[-1] if parts else path
    if len(logs) > 1 or path.suffix.lower() != ".mcap":
        raise ConfigError(
            f"--follow on {logs[0]}: only a ROS 2 MCAP being recorded can be followed (rosbags reads ROS 1 bags and "
            "sqlite3 bags only once they are complete)",
            fix="record with 'ros2 bag record -s mcap', or replay the finished bag without --follow",
        )
    folder = path.parent if keep else cache_dir()
    folder.mkdir(parents=True, exist_ok=True)
    out = folder / f"{path.stem}.followed-{time.strftime('%Y%m%d-%H%M%S')}.lcv.mcap"
    conversion = start_live_conversion(path, out, options, idle_timeout_s=idle_timeout_s, stop=lambda: stop.requested)
    if not quiet:
        typer.echo(f"following {path} through its live conversion {out}", err=True)
    # The conversion closes its log when the bag ends or stops growing; the follower waits a little longer.
    return _FieldLog(out, default_save_path(path), conversion, follow_idle_timeout_s=idle_timeout_s + 10.0)


def _follower(idle_timeout_s: float, stop):
    """``open_reader`` of ReplayOptions for --follow: the follower, stopped by the replay's Ctrl-C."""
    import functools

    from lcv_replay.log.follow import follow_log

    return functools.partial(follow_log, idle_timeout_s=idle_timeout_s, stop=lambda: stop.requested)
