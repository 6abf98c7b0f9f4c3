"""URRtdeLink end to end: the real ur_rtde client (in the link's child process) against the mock UR
controller (its own process), with the mock's simulated robot program as the robot.

Each test uses its own loopback address (ur_rtde has no port argument), so tests can run side by
side. Tear-down: the link (and with it the IO interface) closes before the mock stops.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from drivers.links.ur_rtde import URRtdeLink, URRtdeOptions
from vgripd.mock.ur_controller import URController
from vgripd.protocol import LinkState, Trigger
from vgripd.types import JobResult, RobotTarget, Status

pytestmark = pytest.mark.timeout(60)

UR_FIELDS = ("x", "y", "z", "rx", "ry", "rz")
# Values with full binary64 mantissas, so float-exactness is really tested.
OFFSET = (0.0123456789012345, -0.0034567890123456, 0.1 / 3, 0.01 * np.pi, -0.2 / 7, 1.0 / 9)
TCP = (0.4123, -0.1987, 0.5021, 2.2214, -2.2214, 0.0123)
TAUGHT = (0.30, 0.10, 0.20, 0.0, 3.1, 0.05)


class Triggers:
    def __init__(self) -> None:
        self.queue: asyncio.Queue[Trigger] = asyncio.Queue()

    def __call__(self, trigger: Trigger) -> None:
        self.queue.put_nowait(trigger)

    async def next(self, timeout_s: float = 5.0) -> Trigger:
        return await asyncio.wait_for(self.queue.get(), timeout_s)


@contextlib.asynccontextmanager
async def connected(host: str, **options: object) -> AsyncIterator[tuple[URController, URRtdeLink, Triggers]]:
    """A mock controller at ``host`` and an open link to it; the link closes first."""
    with URController(host) as robot:
        robot.set_tcp_pose(TCP)
        link = URRtdeLink("ur", URRtdeOptions(host=host, **options))
        triggers = Triggers()
        await link.open(triggers)
        try:
            yield robot, link, triggers
        finally:
            await link.close()  # before the mock stops (RTDE.md section 6)


def ur_result(job_id: int, values: tuple[float, ...] = OFFSET) -> JobResult:
    return JobResult(job_id, Status.OK, target=RobotTarget("ur", UR_FIELDS, tuple(values)))


async def run_job(robot: URController, link: URRtdeLink, triggers: Triggers, job_id: int,
                  command: int = 1, upper: bool = False) -> tuple[Trigger, dict]:
    seq = robot.start_program(command, upper=upper, taught_pose=TAUGHT)
    trigger = await triggers.next()
    assert trigger.seq == seq
    await link.image_captured(seq, job_id)
    await link.publish(seq, ur_result(job_id))
    # The rotation page is handed over between the link's child and the robot; nothing here.
    return trigger, robot.program_result(seq)


async def test_trigger_pose_result_roundtrip() -> None:
    async with connected("127.0.5.1") as (robot, lnk, triggers):
        assert lnk.health().state is LinkState.UP
        assert lnk.health().peer == "127.0.5.1:30004"
        log_start = len(robot.input_log())

        trigger, result = await run_job(robot, lnk, triggers, job_id=17, command=3)

        assert trigger.link == "ur"
        assert trigger.command == 3
        expected = np.eye(4)
        expected[:3, :3] = Rotation.from_rotvec(TCP[3:]).as_matrix()
        expected[:3, 3] = np.array(TCP[:3]) * 1000.0
        assert trigger.T_base_flange is not None
        np.testing.assert_allclose(trigger.T_base_flange, expected, atol=1e-9)

        assert result["error"] is None
        assert (result["status"], result["job_id"], result["captured"]) == (1, 17, trigger.seq)
        assert result["offset"] == OFFSET  # float-exact through the registers
        oracle = (Rotation.from_rotvec(TAUGHT[3:]) * Rotation.from_rotvec(OFFSET[3:]))
        np.testing.assert_allclose(result["target"][3:], oracle.as_rotvec(), atol=1e-12)
        np.testing.assert_allclose(
            result["target"][:3],
            np.array(TAUGHT[:3]) + Rotation.from_rotvec(TAUGHT[3:]).apply(OFFSET[:3]), atol=1e-12)

        # Ordering on the wire: every data write before its acknowledge.
        log = robot.input_log(log_start)
        names = [n for n, _ in log]
        ack = log.index(("input_int_register_18", trigger.seq))
        page_ack = log.index(("input_int_register_22", trigger.seq))
        translation = [log.index((f"input_double_register_{18 + i}", OFFSET[i])) for i in range(3)]
        rotation = [log.index((f"input_double_register_{18 + i}", OFFSET[3 + i])) for i in range(3)]
        assert max(translation) < ack < min(rotation)
        assert max(rotation) < page_ack
        status_at = max(i for i, n in enumerate(names[:ack]) if n == "input_int_register_19")
        assert log[status_at][1] == 1
        assert "input_int_register_12" not in names  # never writes the robot's registers


async def test_failed_job_answers_status_without_pose() -> None:
    async with connected("127.0.5.2") as (robot, lnk, triggers):
        seq = robot.start_program(1)
        await triggers.next()
        await lnk.publish(seq, JobResult(5, Status.NOT_FOUND, message="no features"))
        result = robot.program_result(seq)
        assert (result["status"], result["job_id"], result["offset"]) == (10, 5, None)
        # The next job still works and its sequence follows.
        trigger, result = await run_job(robot, lnk, triggers, job_id=6)
        assert trigger.seq == seq + 1
        assert result["offset"] == OFFSET


async def test_valid_status_without_ur_target_answers_internal() -> None:
    async with connected("127.0.5.3") as (robot, lnk, triggers):
        seq = robot.start_program(1)
        await triggers.next()
        kuka = RobotTarget("kuka", ("X", "Y", "Z", "A", "B", "C"), (1.0, 2.0, 3.0, 0.0, 0.0, 0.0))
        with pytest.raises(Exception, match="needs a 'ur' target"):
            await lnk.publish(seq, JobResult(8, Status.OK, target=kuka))
        result = robot.program_result(seq)
        assert (result["status"], result["offset"]) == (int(Status.INTERNAL), None)


async def test_upper_range_registers() -> None:
    async with connected("127.0.5.4", use_upper_range_registers=True) as (robot, lnk, triggers):
        log_start = len(robot.input_log())
        trigger, result = await run_job(robot, lnk, triggers, job_id=2, upper=True)
        assert result["offset"] == OFFSET
        assert result["status"] == 1
        written = {n for n, _ in robot.input_log(log_start)}
        assert {"input_int_register_42", "input_int_register_46", "input_double_register_42"} <= written
        assert not {n for n in written if n.endswith(("_18", "_19", "_20", "_21", "_22"))}
        assert robot.inputs("input_int_register_42")["input_int_register_42"] == trigger.seq


async def test_pending_request_at_first_connect_is_not_served() -> None:
    with URController("127.0.5.5") as robot:
        robot.set_outputs(output_int_register_12=41, output_int_register_13=1)
        lnk = URRtdeLink("ur", URRtdeOptions(host=robot.host))
        triggers = Triggers()
        await lnk.open(triggers)
        try:
            seq = robot.start_program(1)  # max(41, ack 0) + 1
            assert seq == 42
            assert (await triggers.next()).seq == 42
            assert triggers.queue.empty()
        finally:
            await lnk.close()
