"""`lcv-replay LOG.mcap`: the replay (default command)."""

from __future__ import annotations

from pathlib import Path

import typer

from lcv_replay.cli.app import app
from lcv_replay.errors import NotImplementedYetError


@app.command("replay", hidden=True, help="Replay LOG.mcap through retrieval and incremental verification.")
def replay_command(log: Path = typer.Argument(..., help="An lcv-replay MCAP log.")) -> None:
    raise NotImplementedYetError(
        "the replay is not implemented yet", path=log, fix="use 'lcv-replay info' to inspect the log"
    )
