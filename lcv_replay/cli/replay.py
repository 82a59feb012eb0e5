"""`lcv-replay LOG.mcap [options]`: the replay (the hidden default command ``replay``)."""

from __future__ import annotations

import enum
import os
import sys
from pathlib import Path
from typing import Optional

import typer

from lcv_replay.cli.app import app


class ConstraintChoice(str, enum.Enum):
    images = "images"
    log = "log"
    both = "both"


def default_save_path(log_path: Path) -> Path:
    """``LOG.rrd`` next to the log, or in the current folder when the log's folder is not writable."""
    beside = log_path.with_suffix(".rrd")
    folder = beside.parent if str(beside.parent) else Path(".")
    if os.access(folder, os.W_OK):
        return beside
    return Path.cwd() / beside.name


def build_sinks(*, rerun_config, outputs, summary_json: Optional[Path], quiet: bool) -> list:
    """The sinks of one replay, in call order: progress, Rerun, summary, (serve until Ctrl-C).

    Args:
        rerun_config: the config's ``[rerun]`` section.
        outputs: a :class:`~lcv_replay.sinks.config.RerunOutputs`, or ``None`` for no Rerun output.
    """
    from lcv_replay.sinks.summary import SummarySink

    sinks: list = []
    if not quiet:
        from lcv_replay.sinks.progress import ProgressSink

        sinks.append(ProgressSink())
    rerun_sink = None
    if outputs is not None and outputs.any:
        from lcv_replay.sinks.rerun_sink import RerunSink

        rerun_sink = RerunSink(rerun_config, outputs)
        sinks.append(rerun_sink)
    sinks.append(SummarySink(stream=sys.stdout, json_path=summary_json))
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

        typer.echo(f"serving the recording at {self.rerun_sink.served_url} — press Ctrl-C to stop", err=True)
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass

    def close(self) -> None:
        pass


@app.command("replay", hidden=True, help="Replay LOG.mcap through retrieval and incremental verification, logging every step to Rerun.")
def replay_command(
    log: Path = typer.Argument(..., metavar="LOG.mcap", help="An lcv-replay MCAP log (written by 'lcv-replay record')."),
    rate: str = typer.Option("max", "--rate", "-r", help="Playback rate: 1.0 = real time by the log's timestamps; 'max' = as fast as possible."),
    start_offset: float = typer.Option(0.0, "--start-offset", help="Start this many seconds into the log."),
    duration: Optional[float] = typer.Option(None, "--duration", help="Replay only this many seconds."),
    method: Optional[str] = typer.Option(None, "--method", "-m", help="Verifier: ilv (the paper), ilv+, none, ir-only, dcs, gm, cauchy, gnc, oracle (default: the config's verification.method)."),
    constraints: Optional[ConstraintChoice] = typer.Option(None, "--constraints", case_sensitive=False, help="Loop constraints from our retrieval on the images, the log's /loop_candidates, or both (default: log if it has candidates, else images)."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="TOML config over the paper defaults (unknown keys are refused)."),
    seed: Optional[int] = typer.Option(None, "--seed", help="Seed of retrieval and verification (default: the config's)."),
    save: Optional[Path] = typer.Option(None, "--save", help="Write the Rerun recording here, overwriting it (default: LOG.rrd next to the log, or in the current folder if that one is not writable)."),
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
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
    recover: bool = typer.Option(False, "--recover", help="Read the complete chunks of a truncated log."),
) -> None:
    import dataclasses

    from lcv_replay.config import load_config
    from lcv_replay.pacing import parse_rate
    from lcv_replay.replay import ReplayOptions, replay

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
    )
    if not log.exists():  # before any output is touched
        from lcv_replay.errors import LogFormatError

        raise LogFormatError("file not found", path=log, fix="check the path")
    outputs = None
    if not no_rerun:
        from lcv_replay.sinks.config import RerunOutputs

        outputs = RerunOutputs(
            save=None if no_save else (save if save is not None else default_save_path(log)),
            spawn=spawn, connect=connect, serve=serve, grpc_port=grpc_port, web_port=web_port,
            memory_limit=memory_limit,
        )
    sinks = build_sinks(rerun_config=replay_config.rerun, outputs=outputs, summary_json=summary_json, quiet=quiet)
    summary = replay(options, sinks)
    if summary.interrupted:
        raise typer.Exit(130)
