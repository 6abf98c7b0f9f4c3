"""Modbus client link faults against the mock robot Modbus server (real sockets):

- the robot's server drops the connection over and over while the link is idle (and while the
  daemon waits on a write): one WARNING line per outage, never a traceback or an "internal
  error", the link comes back each time, no waiter is lost (every daemon call ends within the
  link's own timeouts), and the next job's latency is bounded by the config;
- a silent robot: pymodbus' own per-request ERROR lines are filtered (the link logs the outage
  once itself), unless the pymodbus logger is set to DEBUG.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator

import pytest

from drivers.links.modbus_client import ModbusClientLink, ModbusClientOptions
from vgripd.errors import LinkError
from vgripd.peer.registers import Reg, Warnings
from vgripd.service.links.protocol import LinkState, Trigger
from vgripd.sim.robot_modbus import MockRobotModbus, RobotMode
from vgripd.types import JobResult, RobotTarget, Status

pytestmark = pytest.mark.timeout(120)
LOGGER = "drivers.links.modbus_client"
TIMEOUT_S = 0.3
POLL_S = 0.1  # long enough that a drop is seen between two polls (the link idle)


@pytest.fixture
async def robot() -> AsyncIterator[MockRobotModbus]:
    r = MockRobotModbus()
    await r.start()
    yield r
    await r.stop()


def make_link(robot: MockRobotModbus) -> ModbusClientLink:
    return ModbusClientLink("robot", ModbusClientOptions(
        host=robot.host, port=robot.port, timeout_s=TIMEOUT_S, backoff_initial_s=0.02,
        backoff_max_s=0.2, poll_interval_s=POLL_S))


def ur_result(job_id: int) -> JobResult:
    return JobResult(job_id, Status.OK, target=RobotTarget(
        "ur", ("x", "y", "z", "rx", "ry", "rz"), (400.0, -100.0, 250.0, 0.1, -2.9, 3.1)))


class Answerer:
    """The daemon's part: every trigger is captured and published at once."""

    def __init__(self, link: ModbusClientLink) -> None:
        self.link = link
        self.tasks: set[asyncio.Task[None]] = set()

    def __call__(self, trigger: Trigger) -> None:
        task = asyncio.create_task(self.answer(trigger))
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)

    async def answer(self, trigger: Trigger) -> None:
        await self.link.image_captured(trigger.seq, trigger.seq)
        await self.link.publish(trigger.seq, ur_result(trigger.seq))


async def test_drops_while_idle_one_line_each_no_traceback_no_lost_waiter(
        robot: MockRobotModbus, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    link = make_link(robot)
    await link.open(Answerer(link))
    drops = 15
    call_s: list[float] = []

    async def daemon_call(bits: int) -> None:
        """What the daemon does while the robot drops: set_warnings waits for the robot."""
        t0 = time.monotonic()
        with contextlib.suppress(LinkError):  # the robot was away: fine, kept for later
            async with asyncio.timeout(2 * TIMEOUT_S + 1.0):  # never the daemon's 2 s
                await link.set_warnings(bits)
        call_s.append(time.monotonic() - t0)

    try:
        for i in range(drops):
            await link.wait_state(LinkState.UP, 10)
            await asyncio.sleep(0.02)  # idle between two polls
            robot.drop_connections()
            await asyncio.sleep(0.02)  # the client has seen the drop; the link not yet
            await daemon_call(i % 2)  # the daemon writes to a link still shown UP
            await link.wait_state({LinkState.DOWN, LinkState.CONNECTING}, 10)
        await link.wait_state(LinkState.UP, 10)

        t0 = time.monotonic()
        seen = await robot.run_job(1, 5.0)
        latency_s = time.monotonic() - t0
    finally:
        await link.close()

    assert seen.words[Reg.ACK_SEQ] == 1
    assert seen.words[Reg.STATUS] == Status.OK
    # Trigger noticed within a poll (0.1 s), three writes for the capture and three for the
    # result: a lost waiter would add the daemon's 2 s link-call limit; a busy machine may
    # add a second of its own, so only the lost waiter's signature is a failure.
    assert latency_s < 2.0, latency_s
    assert len(call_s) == drops
    assert max(call_s) < 2 * TIMEOUT_S + 0.5, call_s
    assert all(r.exc_info is None for r in caplog.records)
    ours = [r for r in caplog.records if r.name == LOGGER]
    warnings = [r.getMessage() for r in ours if r.levelno >= logging.WARNING]
    assert len(warnings) == drops, warnings  # one line per outage
    assert all("lost" in w and "internal error" not in w for w in warnings), warnings
    assert link.health().reconnects == drops
    assert int(Warnings(0)) == 0


async def test_silent_robot_pymodbus_retry_lines_are_filtered(
        robot: MockRobotModbus, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    logging.getLogger("pymodbus").setLevel(logging.INFO)
    link = make_link(robot)
    await link.open(Answerer(link))
    try:
        robot.mode = RobotMode.SILENT
        await link.wait_state(LinkState.DOWN, 10)
        for _ in range(3):  # more unanswered requests, each would be a pymodbus ERROR line
            await link.wait_state(LinkState.CONNECTING, 10)
            await link.wait_state(LinkState.DOWN, 10)
        robot.mode = RobotMode.NORMAL
        await link.wait_state(LinkState.UP, 10)
    finally:
        await link.close()
        logging.getLogger("pymodbus").setLevel(logging.NOTSET)
    noisy = [r.getMessage() for r in caplog.records
             if r.name.startswith("pymodbus") and r.levelno >= logging.WARNING]
    assert noisy == []
    ours = [r for r in caplog.records if r.name == LOGGER and r.levelno >= logging.WARNING]
    assert len(ours) == 1
    assert f"no answer within {TIMEOUT_S} s" in ours[0].getMessage()


async def test_pymodbus_lines_stay_when_its_logger_is_at_debug(
        robot: MockRobotModbus, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG, "pymodbus")
    logging.getLogger("pymodbus").setLevel(logging.DEBUG)
    link = make_link(robot)
    await link.open(Answerer(link))
    try:
        robot.mode = RobotMode.SILENT
        await link.wait_state(LinkState.DOWN, 10)
        robot.mode = RobotMode.NORMAL
        await link.wait_state(LinkState.UP, 10)
    finally:
        await link.close()
        logging.getLogger("pymodbus").setLevel(logging.NOTSET)
    assert any("No response received" in r.getMessage() for r in caplog.records
               if r.name.startswith("pymodbus"))
