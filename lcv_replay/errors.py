"""One exception hierarchy for lcv-replay.

Every user-facing error derives from :class:`LcvError`. The CLI catches ``LcvError`` in one place,
prints ``error: <message>`` on one line and exits with :attr:`LcvError.exit_code` (2 for bad input).
Messages name the file or value, the problem, and the fix, e.g.::

    raise LogFormatError(path, "the file ends inside a chunk (truncated)",
                         fix="re-run with --recover to salvage the complete chunks")
"""

from __future__ import annotations

import numbers
from pathlib import Path
from typing import Any


class LcvError(Exception):
    """Base class of every error lcv-replay reports to a user.

    Args:
        message: what is wrong, naming the bad value.
        path: the file concerned, if any; it is put first in the message.
        fix: what the user should do next.
    """

    exit_code: int = 2

    def __init__(self, message: str, *, path: str | Path | None = None, fix: str | None = None):
        self.message = message
        self.path = None if path is None else Path(path)
        self.fix = fix
        super().__init__(self.format())

    def format(self) -> str:
        text = self.message
        if self.path is not None:
            text = f"{self.path}: {text}"
        if self.fix:
            text = f"{text} ({self.fix})"
        return text


class ConfigError(LcvError):
    """A config file or option is invalid (unknown key, wrong type, out of range)."""


def require(condition: bool, key: str, value: Any, expected: str) -> None:
    """Raise :class:`ConfigError` naming config ``key`` unless ``condition`` holds.

    The config sections call it in ``__post_init__``, e.g.
    ``require(self.top_k >= 1, "retrieval.top_k", self.top_k, "an integer >= 1")``.
    """
    if not condition:
        raise ConfigError(f"config key '{key}' = {value!r} is out of range", fix=f"use {expected}")


#: Seeds are integers in ``[0, 2**63)``: what numpy's generators, TOML and JSON (int64) all hold.
SEED_LIMIT = 2**63


def require_seed(value: Any, name: str) -> int:
    """The one rule for every seed (``--seed``, ``[verification] seed``, ``[retrieval] seed``,
    ``record g2o --seed``, suite files, ...): an integer ``0 <= seed < 2**63``.

    ``name`` says where the seed came from (``"--seed"``, ``"config key 'verification.seed'"``).
    Raises :class:`ConfigError` with the one message for a bad seed.
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or not 0 <= value < SEED_LIMIT:
        raise ConfigError(f"invalid seed {value!r} for {name}", fix="a seed is an integer from 0 to 2**63 - 1")
    return int(value)


class LogFormatError(LcvError):
    """An MCAP log cannot be read or does not follow the lcv-replay log format."""


class RecorderError(LcvError):
    """A recorder's source dataset is missing, malformed or inconsistent."""


class OutputError(LcvError):
    """An output path cannot be written (exists without --force, unwritable folder, ...)."""


class RetrievalError(LcvError):
    """Place recognition cannot run (missing model package, log too short for warm-up, ...)."""


class VerificationError(LcvError):
    """Loop-closure verification got invalid input (singular information matrix, ...)."""


class OdometryError(LcvError):
    """Visual odometry cannot run (no right images, calibration mismatch, ...)."""


class ReplayError(LcvError):
    """The replay cannot start (no odometry, neither images nor candidates, ...)."""


class FleetError(LcvError):
    """A batch or compare cannot start (no logs matched, a bad run folder, an unreachable cluster, ...)."""


class NotImplementedYetError(LcvError):
    """A documented feature is not implemented yet."""

    exit_code = 3
