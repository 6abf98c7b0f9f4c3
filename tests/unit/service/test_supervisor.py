"""The links' shared health cell, outage policy and back-off options (vgripd/service/supervisor.py)."""

from __future__ import annotations

import asyncio

import pytest

from vgripd.service.protocol import LinkState
from vgripd.service.supervisor import HealthCell


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
