"""`lcv-replay info LOG.mcap [--json] [--recover]`: inspect a log, like ``ros2 bag info``."""

from __future__ import annotations

from pathlib import Path

import typer

from lcv_replay.cli.app import app


@app.command("info", help="Show a log's topics, counts, rates, frames and contents (like 'ros2 bag info').")
def info_command(
    log: Path = typer.Argument(..., help="An lcv-replay MCAP log."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object (stable keys; see docs/log-format.md)."),
    recover: bool = typer.Option(False, "--recover", help="Salvage the complete chunks of a truncated or damaged file."),
    check: bool = typer.Option(
        True, "--check/--no-check", help="Verify every chunk's CRC and decode odometry and candidates (default on)."
    ),
) -> None:
    import json

    from lcv_replay.log.inspect import format_info, info_to_json
    from lcv_replay.log.reader import open_log

    with open_log(log, recover=recover) as reader:
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
