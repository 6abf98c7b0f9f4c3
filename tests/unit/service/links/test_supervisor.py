"""The links' shared health cell, outage policy and back-off options (vgripd/service/links/supervisor.py)."""

from __future__ import annotations

import asyncio
import logging

import pytest
from hypothesis import given
from hypothesis import strategies as st

from tests.conftest import stop_task
from vgripd.service.links.protocol import LinkState
from vgripd.service.links.supervisor import (
    Ended,
    HealthCell,
    OutagePolicy,
    Reconnector,
    end_task,
)


def test_cell_moves_since_only_with_the_state() -> None:
    cell = HealthCell("plc:502")
    cell.set(LinkState.DOWN, "refused")
    since = cell.since_mono_ns
    cell.set(LinkState.DOWN, "timed out")
    assert (cell.since_mono_ns, cell.last_error) == (since, "timed out")
    cell.set(LinkState.UP, reconnect=True)
    h = cell.health(peers=2)
    assert (h.state, h.last_error, h.reconnects, h.peer, h.peers) == (
        LinkState.UP, "", 1, "plc:502", 2)
    assert h.since_mono_ns >= since


def test_cell_keeps_the_error_when_told_none() -> None:
    cell = HealthCell()
    cell.set(LinkState.FAILED, "port in use")
    cell.set(LinkState.STOPPED, None)
    assert cell.health().last_error == "port in use"


async def test_wait_wakes_every_waiter_at_the_state() -> None:
    cell = HealthCell()
    waiters = [asyncio.create_task(cell.wait({LinkState.UP, LinkState.FAILED}, 60))
               for _ in range(3)]
    cell.set(LinkState.CONNECTING)  # not wanted: they keep waiting
    await asyncio.sleep(0)
    assert not any(w.done() for w in waiters)
    cell.set(LinkState.UP)
    await asyncio.gather(*waiters)


async def test_wait_times_out_without_the_state() -> None:
    cell = HealthCell()
    with pytest.raises(TimeoutError):
        await cell.wait(LinkState.UP, 0.01)


# --- the outage policy ---------------------------------------------------------------------

EVENTS = st.lists(st.tuples(st.sampled_from(["fail", "back"]),
                            st.floats(0, 5, allow_nan=False)), max_size=40)


@given(EVENTS, st.floats(0.01, 2), st.floats(1, 8))
def test_back_off_doubles_from_initial_up_to_max_and_each_outage_is_logged_once(
        events: list[tuple[str, float]], initial_s: float, factor: float) -> None:
    policy = OutagePolicy(initial_s, initial_s * factor)
    now = 0.0
    expected_delay, failures, began, outages, logged = initial_s, 0, 0.0, 0, 0
    for kind, dt in events:
        now += dt
        if kind == "back":
            assert policy.recovered() is (failures > 0)
            expected_delay, failures = initial_s, 0
            continue
        retry = policy.failed(now)
        if failures == 0:
            outages, began = outages + 1, now
        failures += 1
        logged += retry.first
        assert retry.delay_s == pytest.approx(expected_delay)
        assert retry.delay_s <= policy.max_s
        assert retry.at == pytest.approx(now + retry.delay_s)
        assert (retry.first, retry.attempt) == (failures == 1, failures)
        assert retry.outage_s == pytest.approx(now - began)
        assert policy.in_outage
        expected_delay = min(2 * expected_delay, policy.max_s)
    assert logged == outages


@pytest.mark.parametrize(("initial_s", "max_s"), [(0, 1), (-1, 1), (2, 1)])
def test_policy_refuses_a_back_off_that_cannot_work(initial_s: float, max_s: float) -> None:
    with pytest.raises(ValueError, match="back-off"):
        OutagePolicy(initial_s, max_s)


# --- the reconnect loop ----------------------------------------------------------------------


async def test_reconnector_logs_once_per_outage_counts_reconnects_and_waits_the_policy(
        caplog: pytest.LogCaptureFixture) -> None:
    """Sessions: fail, fail, up then lost, fail, up. Two outages: two WARNING lines, one DEBUG
    line for each outage's second failure, two reconnects counted (the first up ends an outage
    that began at the start: it counts too), DOWN with the last reason in between."""
    caplog.set_level(logging.DEBUG, "test.link")
    cell = HealthCell("robot:1")
    clock = [0.0]
    rec = Reconnector("r1", cell, OutagePolicy(0.001, 0.004), logging.getLogger("test.link"),
                      clock=lambda: clock[0])
    script = ["refused", "refused", "up", "refused", "up"]
    seen: list[tuple[LinkState, str]] = []
    done = asyncio.Event()

    async def session() -> Ended:
        seen.append((cell.state, cell.last_error))
        step = script.pop(0)
        clock[0] += 1.0
        if step == "up":
            rec.up()
            if not script:
                done.set()
                await asyncio.Event().wait()  # serves until cancelled
            return Ended("lost")
        return Ended(step)

    task = asyncio.create_task(rec.run(session))
    await asyncio.wait_for(done.wait(), 60)
    await stop_task(task)
    assert seen == [(LinkState.STOPPED, ""), (LinkState.DOWN, "refused"),
                    (LinkState.DOWN, "refused"), (LinkState.DOWN, "lost"),
                    (LinkState.DOWN, "refused")]
    assert (cell.state, cell.reconnects) == (LinkState.UP, 2)
    lines = [(r.levelno, r.getMessage()) for r in caplog.records if r.name == "test.link"]
    assert lines == [
        (logging.WARNING, "r1: refused; retrying with back-off up to 0.0 s"),
        (logging.DEBUG, "r1: still down (attempt 2): refused"),
        (logging.WARNING, "r1: lost; retrying with back-off up to 0.0 s"),
        (logging.DEBUG, "r1: still down (attempt 2): refused"),
    ]


async def test_end_task_ends_a_supervisor_that_lost_a_cancel() -> None:
    """A supervisor whose first cancel is lost (as Python 3.11's ``wait_for`` drops one that
    comes with a result) runs on; ``end_task`` cancels it again until it has ended, and its
    end is the cancel, not an error left unretrieved."""
    lost = 0

    async def supervisor() -> None:
        nonlocal lost
        while True:
            try:
                await asyncio.sleep(0.01)
            except asyncio.CancelledError:
                if lost:
                    raise
                lost += 1  # the first cancel dropped, as the library under the link did

    task = asyncio.create_task(supervisor())
    await asyncio.sleep(0.05)
    async with asyncio.timeout(10):
        await end_task(task)
    assert task.cancelled()
    assert lost == 1
