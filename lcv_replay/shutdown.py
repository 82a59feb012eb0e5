"""Ctrl-C and SIGTERM: stop after the current frame and finalise the outputs; a second signal aborts.

SIGTERM is what ``timeout``, systemd, Docker and Ray send; it is handled exactly like Ctrl-C
(SIGINT), and a command ends with exit code ``128 + signal number`` (130 for SIGINT, 143 for
SIGTERM):

* Commands with a frame loop (record, replay, vo, demo, bench fuzz and soak) hold a
  :class:`StopToken` inside :func:`stop_on_signals`. The first signal sets it: the loop stops after
  the current frame, and the command finalises its outputs with what was done so far (a shorter
  log, a recording and summary marked interrupted). A second signal raises :class:`Interrupted` at
  once: every atomic output removes its temp file on the way out, and nothing is written.
* Everywhere else (:func:`interrupt_on_signals`, installed by the CLI around every command) the
  first signal raises :class:`Interrupted` at once, with the same clean-up.

Frame loops that are not handed a token (the recorders' shared writing loop) ask
:func:`stop_requested`: signals are process-wide, and so is the question.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
from typing import Iterator

logger = logging.getLogger(__name__)

#: The signals handled (each like Ctrl-C).
STOP_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM)


def exit_code(signum: int) -> int:
    """The shell's exit code of a process ended by signal ``signum``: ``128 + signum``."""
    return 128 + int(signum)


def signal_name(signum: int) -> str:
    """``'SIGTERM'``; Ctrl-C is called ``'Ctrl-C (SIGINT)'``."""
    name = signal.Signals(signum).name
    return "Ctrl-C (SIGINT)" if signum == signal.SIGINT else name


class Interrupted(KeyboardInterrupt):
    """Raised by a signal that must stop the process at once (see the module docstring)."""

    def __init__(self, signum: int = signal.SIGINT):
        super().__init__(signal_name(signum))
        self.signum = int(signum)

    @property
    def exit_code(self) -> int:
        return exit_code(self.signum)


class StopToken:
    """Set by the first signal (or a test, or a caller) to stop a loop after the current frame."""

    def __init__(self) -> None:
        self._event = threading.Event()
        self.signum: int | None = None

    def request(self, signum: int = signal.SIGINT) -> None:
        if self.signum is None:
            self.signum = int(signum)
        self._event.set()

    @property
    def requested(self) -> bool:
        return self._event.is_set()

    @property
    def exit_code(self) -> int:
        """``128 + signum`` of the signal that set it (130 when set without a signal)."""
        return exit_code(self.signum if self.signum is not None else signal.SIGINT)


_active: list[StopToken] = []  # the tokens of the active stop_on_signals blocks, innermost last


def stop_requested() -> bool:
    """Whether the innermost active :func:`stop_on_signals` block has been asked to stop."""
    return bool(_active) and _active[-1].requested


def current_signal() -> int:
    """The signal that set the innermost active token (SIGINT when none did)."""
    return (_active[-1].signum if _active else None) or signal.SIGINT


def raise_if_stopped() -> None:
    """Raise :class:`Interrupted` if a stop was requested (for a loop that has done nothing to keep yet)."""
    if stop_requested():
        raise Interrupted(current_signal())


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


@contextlib.contextmanager
def _handlers(handler) -> Iterator[None]:
    previous = {s: signal.signal(s, handler) for s in STOP_SIGNALS}
    try:
        yield
    finally:
        for s, old in previous.items():
            signal.signal(s, old)


@contextlib.contextmanager
def stop_on_signals(token: StopToken, *, what: str = "stopping after this frame and finalising the outputs") -> Iterator[StopToken]:
    """While active, the first SIGINT or SIGTERM sets ``token``; a second raises :class:`Interrupted`.

    Only possible in the main thread; elsewhere only the token works (callers and tests set it).
    """
    _active.append(token)
    try:
        if not _in_main_thread():
            yield token
            return

        def handler(signum, frame):  # noqa: ARG001 - signal handler signature
            if token.requested:
                raise Interrupted(signum)
            token.request(signum)
            logger.warning("%s: %s (send it again to abort at once, writing nothing)", signal_name(signum), what)

        with _handlers(handler):
            yield token
    finally:
        _active.remove(token)


@contextlib.contextmanager
def interrupt_on_signals() -> Iterator[None]:
    """While active, SIGINT and SIGTERM raise :class:`Interrupted` (the default for CLI commands)."""
    if not _in_main_thread():
        yield
        return

    def handler(signum, frame):  # noqa: ARG001
        raise Interrupted(signum)

    with _handlers(handler):
        yield
