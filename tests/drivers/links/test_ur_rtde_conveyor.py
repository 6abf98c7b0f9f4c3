"""URRtdeLink with ``map_version = 4`` (docs/ur_rtde.md, "Conveyor"): the real ur_rtde client (in
the link's child process) against the mock UR controller, whose simulated robot program writes
the latch with each request and reads the belt block with each answer."""

from __future__ import annotations

import asyncio
import logging

import pytest

from drivers.links.ur_rtde import URRtdeLink, URRtdeOptions
from tests.conftest import lo
from tests.drivers.links.test_ur_rtde import TAUGHT, Triggers, connected, ur_result
from vgripd.peer.jobcore import Command
from vgripd.peer.ur_registers import URRegisterMap
from vgripd.service.links.protocol import LinkState
from vgripd.sim.ur_controller import URController
from vgripd.types import BeltPose, JobResult, Status

pytestmark = [pytest.mark.timeout(60), pytest.mark.slow]

WRAPPING = (1 << 32) - 7  # a count with the top bit set: negative as UR's int32


async def test_the_latch_comes_with_the_trigger_and_the_belt_block_with_the_answer() -> None:
    async with connected(lo("127.0.9.1"), map_version=4) as (robot, link, triggers):
        robot.set_encoder(WRAPPING)
        seq = robot.start_program(1, taught_pose=TAUGHT, conveyor=True)
        trigger = await triggers.next()
        assert (trigger.seq, trigger.latch_count) == (seq, WRAPPING)
        belt = BeltPose(WRAPPING, 1, 0.05, 512.25, -3.5, 12.75, 3)
        result = ur_result(9)
        await link.publish(seq, JobResult(9, Status.OK, target=result.target, belt=belt))
        answer = robot.program_result(seq)
        assert answer["status"] == Status.OK
        assert answer["belt"] == {"count": WRAPPING, "raw_count": -7, "source": 1, "queued": 3,
                                  "error_mm": 0.05, "along_mm": 512.25, "across_mm": -3.5,
                                  "theta_deg": 12.75}
        regs = URRegisterMap(conveyor=True)
        assert robot.inputs(regs.belt_names[0])[regs.belt_names[0]] == seq

        # PREDICT is a request with its count N; a refusal still gets a block of its own
        robot.set_predict_count(5)
        seq = robot.start_program(int(Command.PREDICT), conveyor=True)
        trigger = await triggers.next()
        assert (trigger.command, trigger.latch_count) == (Command.PREDICT, 5)
        await link.publish(seq, JobResult(0, Status.OUT_OF_WORKSPACE,
                                          belt=BeltPose(5, 0, 0.0, queued=2)))
        answer = robot.program_result(seq)
        assert (answer["status"], answer["offset"]) == (Status.OUT_OF_WORKSPACE, None)
        assert (answer["belt"]["count"], answer["belt"]["queued"]) == (5, 2)

        seq = robot.start_program(7, conveyor=True)  # unknown: the link refuses it itself
        answer = await asyncio.to_thread(robot.program_result, seq)
        assert answer["status"] == Status.BAD_REQUEST
        assert answer["belt"]["count"] == 0
        assert link.refusals() == {"BAD_REQUEST": 1}


async def test_without_map_version_4_predict_is_refused_and_no_latch_is_read() -> None:
    async with connected(lo("127.0.9.2")) as (robot, link, triggers):
        robot.set_outputs(output_int_register_16=1234)  # a conveyor program's latch
        seq = robot.start_program(1, taught_pose=TAUGHT)
        trigger = await triggers.next()
        assert trigger.latch_count is None
        await link.publish(seq, ur_result(1))
        assert robot.program_result(seq)["status"] == Status.OK
        seq = robot.start_program(int(Command.PREDICT))
        answer = await asyncio.to_thread(robot.program_result, seq)
        assert answer["status"] == Status.BAD_REQUEST
        assert triggers.queue.empty()
        names = URRegisterMap(conveyor=True).belt_names
        assert set(robot.inputs(*names).values()) == {0}  # the block is never written


async def test_a_belt_register_in_use_is_an_outage_naming_it(
        caplog: pytest.LogCaptureFixture) -> None:
    with URController(lo("127.0.9.3")) as robot:
        robot.set_in_use("input_double_register_25")
        link = URRtdeLink("ur", URRtdeOptions(host=robot.host, map_version=4,
                                              backoff_initial_s=0.05, backoff_max_s=0.2))
        try:
            with caplog.at_level(logging.INFO, logger="vgripd.link.ur_rtde"):
                await link.open(Triggers())
                health = await link.wait_state(LinkState.DOWN, 45)
                assert "input_double_register_25 IN_USE" in health.last_error
                assert "map_version = 4" in health.last_error
                robot.set_in_use()
                await link.wait_state(LinkState.UP, 45)
            levels = [r.levelname for r in caplog.records if r.name == "vgripd.link.ur_rtde"]
            assert levels[0] == "ERROR"
        finally:
            await link.close()
