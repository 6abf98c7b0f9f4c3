"""RateLimitedLog: one line per (client, kind) per interval, with the count of the held ones."""

from __future__ import annotations

import logging

import pytest

from vgripd.service.links.ratelog import RateLimitedLog


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


Logged = tuple[RateLimitedLog, Clock, pytest.LogCaptureFixture]


@pytest.fixture
def logged(caplog: pytest.LogCaptureFixture) -> Logged:
    caplog.set_level(logging.INFO, "ratelog-test")
    clock = Clock()
    rl = RateLimitedLog(logging.getLogger("ratelog-test"), interval_s=10.0, max_keys=3,
                        clock=clock)
    return rl, clock, caplog


def lines(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records]


def test_one_line_per_client_and_kind_per_interval(
        logged: Logged) -> None:
    rl, clock, caplog = logged
    assert rl.warning("10.0.0.5", "malformed", "bad frame %d", 1)
    for i in range(500):
        assert not rl.warning("10.0.0.5", "malformed", "bad frame %d", i + 2)
    assert rl.info("10.0.0.5", "unit", "unit %d", 9)  # another kind
    assert rl.warning("10.0.0.6", "malformed", "bad frame %d", 7)  # another client
    assert lines(caplog) == ["bad frame 1", "unit 9", "bad frame 7"]
    clock.t += 10.0
    assert rl.warning("10.0.0.5", "malformed", "bad frame %d", 999)
    assert lines(caplog)[-1] == "bad frame 999 (and 500 more like it from 10.0.0.5 in the last 10 s)"
    assert (rl.lines, rl.events) == (4, 504)


def test_flush_reports_a_burst_that_stopped(
        logged: Logged) -> None:
    rl, clock, caplog = logged
    for i in range(3):
        rl.info("h", "idle", "closed %d", i)
    assert rl.flush() == 0  # the interval is not over
    clock.t += 11
    assert rl.flush() == 1
    assert lines(caplog) == ["closed 0", "closed 2 (2 like it from h in the last 11 s; this is the "
                                       "latest)"]
    clock.t += 11
    assert rl.flush() == 0  # nothing held: the key is forgotten
    assert rl.info("h", "idle", "closed %d", 3)
    assert rl.flush(force=True) == 0  # (closing) nothing held: forgotten at once
    assert rl.info("h", "idle", "closed %d", 4)
    assert not rl.info("h", "idle", "closed %d", 5)
    assert rl.flush(force=True) == 1
    assert lines(caplog)[-1] == "closed 5 (1 like it from h in the last 0 s; this is the latest)"


def test_keys_are_bounded(logged: Logged) -> None:
    rl, clock, caplog = logged
    for i in range(3):
        rl.info(f"10.0.0.{i}", "connected", "c %d", i)
    assert rl.info("10.0.0.9", "connected", "c %d", 9)  # no room: counted as other clients
    assert not rl.info("10.0.0.10", "connected", "c %d", 10)
    assert lines(caplog)[-1] == "(other clients) c 9"
    clock.t += 20  # quiet keys make room again
    assert rl.info("10.0.0.11", "connected", "c %d", 11)
    assert lines(caplog)[-1] == "c 11"


def test_disabled_levels_write_nothing(logged: Logged) -> None:
    rl, _, caplog = logged
    assert not rl.log(logging.DEBUG, "h", "k", "x")
    assert len(caplog.records) == 0
    with pytest.raises(ValueError, match="interval_s"):
        RateLimitedLog(logging.getLogger("x"), interval_s=0)
