"""The typer application: ``lcv-replay LOG.mcap`` (replay) plus subcommands.

Commands only convert arguments into typed values and call one core function each. Heavy modules
(torch, gtsam, rerun, cv2) are imported inside the command bodies so that ``--help`` is instant.
"""

from __future__ import annotations

import logging
import re
import sys
from pathlib import Path
from typing import Any

import typer
from typer.core import TyperCommand, TyperGroup

from lcv_replay.errors import LcvError

_GROUP_OPTIONS = {"--help", "-h", "--version", "--install-completion", "--show-completion"}

#: Value placeholders in help, by typer's type label: no Python types (``<list[Path]>``,
#: ``<int range>``) reach a user.
_PLACEHOLDERS = {"path": "PATH", "int": "INTEGER", "int range": "INTEGER", "float": "NUMBER", "float range": "NUMBER", "str": "TEXT"}
_TYPE_LABEL = re.compile(r" <(?P<label>[^<>]*(?:<[^<>]*>)?[^<>]*)>(?:\.\.\.)?$")


def _placeholder(label: str) -> str:
    """``int range`` -> ``INTEGER``, ``list[Path]`` -> ``PATH``, ``png|jpeg|raw`` -> ``[png|jpeg|raw]``."""
    inner = re.fullmatch(r"list\[(.*)\]", label)
    label = inner.group(1) if inner else label
    if "|" in label:
        return f"[{label}]"
    return _PLACEHOLDERS.get(label.lower(), label.upper())


class LcvCommand(TyperCommand):
    """A command whose help shows plain placeholders (``PATH``, ``INTEGER``, ``[png|jpeg|raw]``) and
    whose usage line names arguments as ``LOG.mcap`` or ``LOGS...``, not ``{logs}...``."""

    def collect_usage_pieces(self, ctx):
        pieces = [self.options_metavar] if self.options_metavar else []
        for param in self.get_params(ctx):
            if param.param_type_name == "argument":
                name = _argument_name(param)
                pieces.append(name if param.required else f"[{name}]")
        return pieces

    def format_options(self, ctx, formatter) -> None:
        arguments, options = [], []
        for param in self.get_params(ctx):
            record = param.get_help_record(ctx)
            if record is None:
                continue
            names, help_text = record
            if param.param_type_name == "argument":
                arguments.append((_argument_name(param), help_text))
            else:
                options.append((_TYPE_LABEL.sub(lambda m: " " + _placeholder(m.group("label")), names), help_text))
        for title, rows in (("Arguments", arguments), ("Options", options)):
            if rows:
                with formatter.section(title):
                    formatter.write_dl(rows)


def _argument_name(param) -> str:
    name = param.metavar or param.name.upper()
    return f"{name}..." if param.nargs != 1 else name


def force_option(what: str = "the outputs") -> Any:
    """``-f/--force``: the one overwrite rule of every command that writes files."""
    return typer.Option(False, "--force", "-f", help=f"Overwrite {what} if present.")


def config_option(what: str) -> Any:
    """``-c/--config FILE.toml``: the one config tree, in every command that reads one."""
    return typer.Option(None, "--config", "-c", help=f"TOML config (lcv-replay's one config tree); {what}.")


def check_outputs(*paths: Path | None, force: bool, folder: Path | None = None) -> None:
    """Before any work: refuse an output that exists (without ``--force``) or cannot be written.

    ``folder`` is an output folder (``--export DIR``): refused when it already holds files.
    """
    from lcv_replay.errors import OutputError
    from lcv_replay.fileio import check_output_path

    for path in paths:
        if path is not None:
            check_output_path(path, force=force)
    if folder is not None and not force and folder.is_dir() and any(folder.iterdir()):
        raise OutputError("output folder is not empty", path=folder, fix="pass --force to overwrite its files, or name a new folder")


class LcvTyper(typer.Typer):
    """A typer application whose commands are :class:`LcvCommand`."""

    def command(self, *args, cls=None, **kwargs):
        return super().command(*args, cls=cls or LcvCommand, **kwargs)


class DefaultReplayGroup(TyperGroup):
    """A group whose default form ``lcv-replay LOG.mcap [OPTIONS]`` runs the ``replay`` command.

    It also maps :class:`LcvError` to one ``error:`` line on stderr and the error's exit code, and
    handles SIGTERM like Ctrl-C (:mod:`lcv_replay.shutdown`): exit ``128 + signal number``.
    """

    def format_usage(self, ctx, formatter) -> None:
        formatter.write_usage(ctx.command_path, "LOG.mcap [OPTIONS]")
        formatter.write_usage(ctx.command_path, "COMMAND [ARGS]...", prefix="   or: ")

    def parse_args(self, ctx: typer.Context, args: list[str]) -> list[str]:
        if args and args[0] not in self.commands and args[0] not in _GROUP_OPTIONS:
            args = ["replay", *args]
        return super().parse_args(ctx, args)

    def invoke(self, ctx: typer.Context):
        from lcv_replay.fileio import is_write_failure, write_error
        from lcv_replay.shutdown import exit_code, interrupt_on_signals, signal_name

        try:
            with interrupt_on_signals():  # SIGTERM like Ctrl-C; frame loops ask for a graceful stop
                return super().invoke(ctx)
        except KeyboardInterrupt as exc:  # a signal that stops at once (the temp files are gone)
            signum = getattr(exc, "signum", 2)
            typer.echo(f"interrupted by {signal_name(signum)}: stopped at once", err=True)
            raise SystemExit(exit_code(signum)) from None
        except LcvError as exc:
            typer.echo(f"error: {exc.format()}", err=True)
            raise SystemExit(exc.exit_code) from None
        except OSError as exc:  # a full disk or unwritable folder that no writer caught (mkdir, ...)
            if not (is_write_failure(exc) and exc.filename):
                raise
            error = write_error(exc.filename, exc, what="there")
            typer.echo(f"error: {error.format()}", err=True)
            raise SystemExit(error.exit_code) from None


app = LcvTyper(
    cls=DefaultReplayGroup,
    name="lcv-replay",
    help=(
        "Replay a robot log (MCAP) through place recognition and incremental loop-closure "
        "verification, logging every step to Rerun.\n\n"
        "\b\nlcv-replay LOG.mcap [OPTIONS]   replay a log; its options: 'lcv-replay LOG.mcap --help'\n"
        "lcv-replay COMMAND [ARGS]...    the commands below"
    ),
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
)
record_app = LcvTyper(help="Record a dataset into an lcv-replay MCAP log.", no_args_is_help=True)
bench_app = LcvTyper(help="Benchmarks: print a table and write JSON.", no_args_is_help=True)
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
