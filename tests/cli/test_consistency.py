"""One CLI: the same ideas have the same flags in every command, and help shows no Python types."""

from __future__ import annotations

import re

import pytest
import typer
from typer.testing import CliRunner

from lcv_replay.cli import app


def _commands() -> dict[str, object]:
    """Every leaf command by its words, e.g. ``"bench verify"``; the replay is ``"LOG.mcap"``."""
    root = typer.main.get_command(app)
    out = {}

    def walk(group, prefix):
        for name, command in group.commands.items():
            words = f"{prefix} {name}".strip()
            if hasattr(command, "commands"):
                walk(command, words)
            else:
                out["x.mcap" if words == "replay" else words] = command

    walk(root, "")
    return out


COMMANDS = _commands()
OUTPUT_FLAGS = {"--out", "--output", "--json", "--save", "--summary-json", "--export", "--report"}
#: ``batch --out RUN_DIR`` is a run folder that resumes (--resume/--no-resume), not a file to overwrite.
RESUMABLE = {"batch"}
#: Typer's type labels, and required arguments in braces: what a user must not see.
PYTHON_TYPES = re.compile(r"<(?:path|int|float|str|bool|list\[[^>]*\]|\w+ range)>|\{[A-Za-z.]+\}")


def _flags(command) -> set[str]:
    return {opt for param in command.params for opt in (*param.opts, *param.secondary_opts)}


def _writes_files(command) -> bool:
    """Whether the command takes an output path (``info --json`` only prints)."""
    return any(set(param.opts) & OUTPUT_FLAGS and not getattr(param, "is_flag", False) for param in command.params)


def _help(words: str) -> str:
    result = CliRunner().invoke(app, [*words.split(), "--help"])
    assert result.exit_code == 0, result.output
    return result.output


def test_every_command_is_found():
    assert {"x.mcap", "demo", "info", "vo", "record g2o", "record synthetic", "bench verify", "bench suite",
            "bench retrieval-index", "bench descriptor-speed", "bench log", "bench synthetic"} <= set(COMMANDS)


@pytest.mark.parametrize("words", sorted(COMMANDS))
def test_help_shows_plain_placeholders_and_the_shared_flags(words):
    text = _help(words)
    assert not PYTHON_TYPES.search(text), text  # no <list[Path]>, <int range>, {LOG.mcap}
    flags = _flags(COMMANDS[words])
    if "--config" in flags:
        assert "-c" in flags, words
    if _writes_files(COMMANDS[words]) and words not in RESUMABLE:
        assert {"-f", "--force"} <= flags, words


def test_top_level_help_names_the_replay_without_a_hidden_command():
    text = _help("")
    assert "lcv-replay LOG.mcap [OPTIONS]" in text and "'lcv-replay LOG.mcap --help'" in text
    assert "replay --help" not in text
    assert _help("x.mcap").startswith("Usage: lcv-replay LOG.mcap [OPTIONS]")


def test_old_ground_truth_spellings_still_parse():
    for words, old in (("record kitti", "--auto-ground-truth"), ("record euroc", "--ground-truth")):
        assert old in _flags(COMMANDS[words]) and "--no-ground-truth" in _flags(COMMANDS[words])
