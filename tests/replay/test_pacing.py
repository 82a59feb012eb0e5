"""Pacing (``--rate``) with an injected clock: no wall-clock sleeps anywhere in these tests."""

from __future__ import annotations

import logging

import pytest

from lcv_replay.config import load_config
from lcv_replay.errors import ConfigError
from lcv_replay.pacing import PACING_LAG_WARN_S, Pacer, parse_rate
from lcv_replay.replay import ReplayOptions, replay
from lcv_replay.sinks.base import BaseSink
from tests.replay.helpers import FAST_CONFIG_TOML, FakeClock, record_square_route, write_config


@pytest.fixture(scope="module")
def square_log(tmp_path_factory):
    folder = tmp_path_factory.mktemp("pacing")
    log, route = record_square_route(folder, laps=2, side_poses=25)
    return log, route, load_config(write_config(folder / "fast.toml", FAST_CONFIG_TOML))


def test_pacer_sleeps_until_each_frame_is_due():
    clock = FakeClock()
    pacer = Pacer(2.0, clock)
    for k in range(11):  # 10 Hz stamps at 2x: one frame every 50 ms
        assert pacer.wait(k * 100_000_000) == 0.0
    assert clock.sleeps == pytest.approx([0.05] * 10)
    assert pacer.report().achieved == pytest.approx(2.0)


def test_pacer_max_rate_never_sleeps():
    clock = FakeClock()
    pacer = Pacer(None, clock)
    for k in range(5):
        pacer.wait(k * 1_000_000_000)
        clock.advance(0.01)
    assert clock.sleeps == []


def test_pacer_reports_when_it_cannot_keep_up(caplog):
    clock = FakeClock()
    pacer = Pacer(1.0, clock)
    with caplog.at_level(logging.WARNING, logger="lcv_replay.pacing"):
        for k in range(40):
            pacer.wait(k * 100_000_000)
            clock.advance(0.2)  # work takes 2x the frame period
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 1  # once, not per frame (repeated only every PACING_REPORT_EVERY_S)
    assert "achieved 0.5" in warnings[0] and "requested 1×" in warnings[0]
    report = pacer.report()
    assert report.achieved == pytest.approx(3.9 / 8.0)
    assert report.max_lag_s > PACING_LAG_WARN_S


@pytest.mark.parametrize("rate", [1.0, 4.0])
def test_replay_at_rate_takes_log_duration_over_rate_on_the_clock(square_log, rate):
    log, route, config = square_log
    clock = FakeClock()
    summary = replay(ReplayOptions(log_path=log, config=config, rate=rate), [], clock, handle_sigint=False)
    expected = (route.frames - 1) / 10.0 / rate
    assert sum(clock.sleeps) == pytest.approx(expected, rel=1e-6)
    assert summary.wall_time_s == pytest.approx(expected, rel=1e-6)
    assert summary.realtime_factor == pytest.approx(rate, rel=1e-6)


class SlowSink(BaseSink):
    """Stands for slow work: each frame costs ``seconds`` on the fake clock."""

    def __init__(self, clock: FakeClock, seconds: float):
        self.clock, self.seconds = clock, seconds

    def on_frame(self, update):
        self.clock.advance(self.seconds)


def test_replay_that_falls_behind_says_so_with_achieved_and_requested_rate(square_log, caplog):
    log, route, config = square_log
    clock = FakeClock()
    with caplog.at_level(logging.WARNING, logger="lcv_replay.replay"):
        summary = replay(ReplayOptions(log_path=log, config=config, rate=1.0), [SlowSink(clock, 0.3)], clock, handle_sigint=False)
    messages = [r.getMessage() for r in caplog.records]
    assert any("pacing cannot keep up" in m and "requested 1×" in m for m in messages)
    assert any(m.startswith("replay ran at 0.33× real time, slower than the requested 1×") for m in messages)
    assert summary.realtime_factor == pytest.approx(1 / 3, rel=0.02)


@pytest.mark.parametrize("text, expected", [("max", None), ("MAX", None), ("1", 1.0), ("0.5", 0.5)])
def test_parse_rate(text, expected):
    assert parse_rate(text) == expected


@pytest.mark.parametrize("text", ["0", "-1", "fast", "nan", "inf"])
def test_parse_rate_refuses_nonsense(text):
    with pytest.raises(ConfigError, match="--rate"):
        parse_rate(text)
