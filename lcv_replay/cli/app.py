"""The typer application: ``lcv-replay LOG.mcap`` (replay) plus subcommands.

Commands only convert arguments into typed values and call one core function each. Heavy modules
(torch, gtsam, rerun, cv2) are imported inside the command bodies so that ``--help`` is instant.
"""

from __future__ import annotations

import logging
import sys

import typer
from typer.core import TyperGroup

from lcv_replay.errors import LcvError

_GROUP_OPTIONS = {"--help", "-h", "--version", "--install-completion", "--show-completion"}


class DefaultReplayGroup(TyperGroup):
    """A group whose default form ``lcv-replay LOG.mcap [options]`` runs the hidden ``replay``.

    It also maps :class:`LcvError` to one ``error:`` line on stderr and the error's exit code.
    """

    def parse_args(self, ctx: typer.Context, args: list[str]) -> list[str]:
        if args and args[0] not in self.commands and args[0] not in _GROUP_OPTIONS:
            args = ["replay", *args]
        return super().parse_args(ctx, args)

    def invoke(self, ctx: typer.Context):
        try:
            return super().invoke(ctx)
        except LcvError as exc:
            typer.echo(f"error: {exc.format()}", err=True)
            raise SystemExit(exc.exit_code) from None


app = typer.Typer(
    cls=DefaultReplayGroup,
    name="lcv-replay",
    help=(
        "Replay a robot log (MCAP) through place recognition and incremental loop-closure "
        "verification, logging every step to Rerun.\n\n"
        "Usage: lcv-replay LOG.mcap [options]   (see 'lcv-replay replay --help')"
    ),
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
)
record_app = typer.Typer(help="Record a dataset into an lcv-replay MCAP log.", no_args_is_help=True)
bench_app = typer.Typer(help="Benchmarks: print a table and write JSON.", no_args_is_help=True)
app.add_typer(record_app, name="record")
app.add_typer(bench_app, name="bench")


def _version_callback(value: bool) -> None:
    if value:
        from lcv_replay import __version__

        typer.echo(f"lcv-replay {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Debug logging."),
    version: bool = typer.Option(False, "--version", callback=_version_callback, is_eager=True, help="Print the version."),
) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    if not verbose:  # our own INFO lines; other libraries' only from WARNING up (-v: everything)
        for name in ("lcv_replay", "recorders"):
            logging.getLogger(name).setLevel(logging.INFO)
