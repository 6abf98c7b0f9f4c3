"""UR RTDE faults through the whole daemon (the real ur_rtde client in the link's child process,
the mock controller in its own process):

- the robot triggered before vgripd started (its request sequence differs from the acknowledge
  register the controller kept): the daemon serves it as soon as the link is up;
- a command the robot program may not send (7, 0, -1) is answered BAD_REQUEST (32) by the link,
  without a job, and the daemon's counters show it as a refusal.
"""

from __future__ import annotations

import asyncio
import logging

import pytest

from tests.conftest import lo
from tests.integration.test_daemon import running
from tests.integration.test_daemon_links import TAUGHT, link_state, make_config
from vgripd.service.links.protocol import LinkState
from vgripd.sim.ur_controller import URController
from vgripd.types import Status

pytestmark = pytest.mark.timeout(120)


async def test_request_pending_before_the_daemon_started_is_served(
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, "vgripd.link.ur_rtde")
    with URController(lo("127.0.8.11")) as robot:
        # The robot program triggered request 8 while vgripd was down; 7 was the last answer.
        robot.set_inputs(input_int_register_18=7)
        seq = robot.start_program(1, taught_pose=TAUGHT, timeout_s=60.0)
        assert seq == 8
        config = make_config([{"type": "ur_rtde", "host": robot.host}], vendor="ur")
        async with running(config) as run:
            _, record = await run.job_done(1)
            result = await asyncio.to_thread(robot.program_result, seq)
    assert record.seq == 8
    assert result["error"] is None
    assert (result["status"], result["job_id"], result["requests"]) == (
        int(record.result.status), record.job_id, [8])
    assert any("request 8 was pending at start" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("command", [7, 0, -1])
async def test_unknown_command_is_a_counted_bad_request(command: int) -> None:
    with URController(lo(f"127.0.8.{20 + command}")) as robot:
        config = make_config([{"type": "ur_rtde", "host": robot.host}], vendor="ur")
        async with running(config) as run:
            ur = next(iter(run.daemon.rooms.links.links))
            await run.daemon.wait_for(
                lambda: link_state(run.daemon.snapshot(), ur)["state"] == LinkState.UP.value, 30)
            seq = robot.start_program(command, taught_pose=TAUGHT)
            result = await asyncio.to_thread(robot.program_result, seq)
            snapshot = run.daemon.snapshot()
            assert run.jobs == []  # no job ran
    assert (result["status"], result["job_id"], result["offset"]) == (32, 0, None)
    assert int(Status.BAD_REQUEST) == 32
    assert snapshot["counters"] == {"BAD_REQUEST": 1}
    assert snapshot["refusals"] == {"BAD_REQUEST": 1}
    assert link_state(snapshot, ur)["refusals"] == {"BAD_REQUEST": 1}
