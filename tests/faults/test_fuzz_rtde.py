"""A seeded fuzzer over the robot's RTDE registers: the mock controller streams random request
sequences (int32 extremes, 0, repeats) with random commands and page requests, as a confused or
hostile robot program would. The link (real ur_rtde client in its child process) must stay up,
log nothing with a traceback, hand the daemon exactly the new non-zero sequences with command 1,
answer every other new sequence BAD_REQUEST without a job, and afterwards a normal program run
reads a bit-exact pose.

``VGRIPD_FUZZ_SEED`` replays another sequence.
"""

from __future__ import annotations

import asyncio
import logging
import os
import random

import pytest

from drivers.links.ur_rtde import URRtdeLink, URRtdeOptions
from tests.conftest import lo
from vgripd.service.links.protocol import LinkState, Trigger
from vgripd.sim.ur_controller import URController
from vgripd.types import JobResult, RobotTarget, Status

pytestmark = pytest.mark.timeout(180)
SEED = int(os.environ.get("VGRIPD_FUZZ_SEED", "2718"))
CASES = 60
INT32 = (-(2**31), 2**31 - 1)
OFFSET = (0.0125, -0.25, 0.375, 0.01, -0.02, 0.03)


def ur_result(job_id: int) -> JobResult:
    return JobResult(job_id, Status.OK,
                     target=RobotTarget("ur", ("x", "y", "z", "rx", "ry", "rz"), OFFSET))


async def test_fuzzed_robot_registers(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    rng = random.Random(SEED)
    triggers: asyncio.Queue[Trigger] = asyncio.Queue()
    with URController(lo("127.0.8.40")) as robot:
        link = URRtdeLink("ur", URRtdeOptions(host=robot.host))
        await link.open(triggers.put_nowait)
        last = 0  # the sequence the link has seen (0 at the first connect)
        zeroed = False  # a 0 was written since the last request
        jobs = refused = 0
        try:
            for i in range(CASES):
                seq = rng.choice([rng.randint(*INT32), *INT32, 0, -1, last, last + 1
                                  if last < INT32[1] else 1])
                command = rng.choice([1, 1, 1, 0, -1, 2, 7, *INT32, rng.randint(*INT32)])
                if seq == last and zeroed:
                    # The old sequence after a 0 is a new request if the link sampled the 0
                    # (an edge) and none if the next write came first: a race in this test,
                    # not a fault of the link. A 0 again is no request either way.
                    seq = 0
                zeroed = zeroed or seq == 0
                where = f"seed {SEED} case {i}: seq {seq} command {command}"
                robot.set_outputs(output_int_register_12=seq, output_int_register_13=command,
                                  output_int_register_14=rng.choice([seq, last, 0]))
                if seq == 0 or seq == last:
                    continue  # not a request: nothing may happen (checked at the end)
                last, zeroed = seq, False
                if command == 1:
                    trigger = await asyncio.wait_for(triggers.get(), 10)
                    assert (trigger.seq, trigger.command) == (seq, 1), where
                    jobs += 1
                    await link.publish(seq, ur_result(jobs))
                    status = int(Status.OK)
                else:
                    refused += 1
                    status = int(Status.BAD_REQUEST)
                assert await asyncio.to_thread(robot.wait_input, "input_int_register_18", seq,
                                               10.0), where
                got = robot.inputs("input_int_register_19")["input_int_register_19"]
                assert got == status, where
                assert link.health().state is LinkState.UP, where
            assert triggers.empty()
            assert link.refusals() == ({"BAD_REQUEST": refused} if refused else {})

            # The registers still work: a normal program run reads an exact pose.
            robot.set_outputs(output_int_register_14=0)
            start = robot.start_program(1)
            trigger = await asyncio.wait_for(triggers.get(), 10)
            await link.publish(trigger.seq, ur_result(jobs + 1))
            result = await asyncio.to_thread(robot.program_result, start)
        finally:
            await link.close()
    assert jobs > 0, (jobs, refused)
    assert refused > 0, (jobs, refused)
    assert result["error"] is None
    assert (result["status"], result["offset"]) == (1, OFFSET)
    assert all(r.exc_info is None and "Traceback" not in r.getMessage()
               for r in caplog.records)
    assert link.health().reconnects == 0
