"""Pacing a replay like ``ros2 bag play --rate``, against an injectable clock.

``rate`` 1.0 is real time by the log's timestamps, ``None`` as fast as possible. Tests inject a
fake :class:`Clock`, so nothing here sleeps for real in the suite. Falling behind the requested rate
is reported (achieved versus requested), never silent.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Protocol

from lcv_replay.errors import ConfigError

logger = logging.getLogger(__name__)

#: Falling behind the requested rate by more than this is reported.
PACING_LAG_WARN_S = 0.5
#: While behind, the report is repeated at most this often (wall seconds).
PACING_REPORT_EVERY_S = 30.0


class Clock(Protocol):
    """Monotonic time in seconds and a way to wait (a fake in tests: no real sleeps)."""

    def now(self) -> float: ...

    def sleep(self, seconds: float) -> None: ...


class SystemClock:
    """The wall clock: ``time.monotonic`` and ``time.sleep``."""

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)


@dataclass(frozen=True)
class PacingReport:
    """How a paced replay kept up: requested and achieved rate (log seconds per wall second)."""

    requested: float | None
    achieved: float | None
    max_lag_s: float
    behind_reports: int

    def warn_if_slow(self) -> None:
        """Warn when the run as a whole fell more than 5 % short of the requested rate."""
        if self.requested is not None and self.achieved is not None and self.achieved < 0.95 * self.requested:
            logger.warning(
                "replay ran at %.2f× real time, slower than the requested %g× (max lag %.1f s)",
                self.achieved, self.requested, self.max_lag_s,
            )


class Pacer:
    """Paces frames to ``rate`` × their log timestamps, like ``ros2 bag play --rate``.

    Frame ``k`` is due at ``t0 + (stamp_k − stamp_0) / rate`` on the clock, where ``t0`` is when the
    first frame was released. Early frames wait; late frames are released at once and the lag is
    measured. When the lag exceeds :data:`PACING_LAG_WARN_S` a warning names the achieved and the
    requested rate (repeated every :data:`PACING_REPORT_EVERY_S` while behind).
    """

    def __init__(self, rate: float | None, clock: Clock):
        self.rate = rate
        self.clock = clock
        self._t0: float | None = None
        self._stamp0: int | None = None
        self._last_stamp: int | None = None
        self._max_lag_s = 0.0
        self._last_report: float | None = None
        self.behind_reports = 0

    def wait(self, stamp_ns: int) -> float:
        """Block until the frame stamped ``stamp_ns`` is due; returns its lag in seconds (>= 0)."""
        now = self.clock.now()
        if self._t0 is None:
            self._t0, self._stamp0 = now, int(stamp_ns)
        self._last_stamp = int(stamp_ns)
        if self.rate is None:
            return 0.0
        due = self._t0 + (int(stamp_ns) - self._stamp0) / 1e9 / self.rate
        if due > now:
            self.clock.sleep(due - now)
            return 0.0
        lag = now - due
        self._max_lag_s = max(self._max_lag_s, lag)
        if lag > PACING_LAG_WARN_S and (self._last_report is None or now - self._last_report >= PACING_REPORT_EVERY_S):
            self._last_report = now
            self.behind_reports += 1
            achieved = self.achieved_rate(now)
            logger.warning(
                "pacing cannot keep up: achieved %.2f× real time, requested %g× (%.1f s behind); "
                "lower --rate or use --rate max",
                achieved if achieved is not None else float("nan"), self.rate, lag,
            )
        return lag

    def achieved_rate(self, now: float | None = None) -> float | None:
        """Log seconds released per clock second so far."""
        if self._t0 is None or self._last_stamp is None:
            return None
        now = self.clock.now() if now is None else now
        wall = now - self._t0
        log_s = (self._last_stamp - self._stamp0) / 1e9
        return log_s / wall if wall > 0 else None

    def report(self) -> PacingReport:
        return PacingReport(self.rate, self.achieved_rate(), self._max_lag_s, self.behind_reports)


def parse_rate(text: str) -> float | None:
    """``"max"`` -> ``None``; otherwise a positive number (1.0 = real time)."""
    if text.strip().lower() == "max":
        return None
    try:
        value = float(text)
    except ValueError:
        raise ConfigError(f"--rate {text!r} is not a number", fix="pass e.g. --rate 1.0, --rate 2 or --rate max") from None
    if not (math.isfinite(value) and value > 0):
        raise ConfigError(f"--rate {text} is out of range", fix="pass a number > 0, e.g. 1.0 for real time, or max")
    return value
