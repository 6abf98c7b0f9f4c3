"""URRtdeLink end to end: the real ur_rtde client (in the link's child process) against the mock UR
controller (its own process), with the mock's simulated robot program as the robot.

Each test uses its own loopback address (ur_rtde has no port argument), so tests can run side by
side. Tear-down: the link (and with it the IO interface) closes before the mock stops.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import multiprocessing
import re
from collections.abc import AsyncIterator, Iterator

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from drivers.links.ur_rtde import URRtdeLink, URRtdeOptions
from tests.conftest import lo, stop_task
from vgripd.errors import LinkError
from vgripd.peer.jobcore import Command, next_answer
from vgripd.peer.registers import Warnings
from vgripd.peer.ur_registers import URRegisterMap
from vgripd.service.links.protocol import LinkState, Trigger, robot_pose_now
from vgripd.service.links.webtrigger import WebTriggerLink
from vgripd.sim.ur_controller import URController
from vgripd.types import JobResult, PickInstance, RobotTarget, Status

pytestmark = [pytest.mark.timeout(60), pytest.mark.slow]

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
    async with connected(lo("127.0.5.1")) as (robot, lnk, triggers):
        assert lnk.health().state is LinkState.UP
        assert lnk.health().peer == lo("127.0.5.1") + ":30004"
        log_start = len(robot.input_log())

        trigger, result = await run_job(robot, lnk, triggers, job_id=17, command=1)

        assert trigger.link == "ur"
        assert trigger.command == 1
        expected = np.eye(4)
        expected[:3, :3] = Rotation.from_rotvec(TCP[3:]).as_matrix()
        expected[:3, 3] = np.array(TCP[:3]) * 1000.0
        assert trigger.T_base_flange is not None
        np.testing.assert_allclose(trigger.T_base_flange, expected, atol=1e-9)

        assert result["error"] is None
        assert (result["status"], result["job_id"], result["captured"]) == (1, 17, trigger.seq)
        assert result["offset"] == OFFSET  # float-exact through the registers
        # The robot moves to offset * taught (base-frame offset, applied on the left).
        oracle = Rotation.from_rotvec(OFFSET[3:]) * Rotation.from_rotvec(TAUGHT[3:])
        np.testing.assert_allclose(Rotation.from_rotvec(result["target"][3:]).as_matrix(),
                                   oracle.as_matrix(), atol=1e-12)
        np.testing.assert_allclose(
            result["target"][:3],
            np.array(OFFSET[:3]) + Rotation.from_rotvec(OFFSET[3:]).apply(TAUGHT[:3]), atol=1e-12)

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
    async with connected(lo("127.0.5.2")) as (robot, lnk, triggers):
        seq = robot.start_program(1)
        await triggers.next()
        await lnk.publish(seq, JobResult(5, Status.NOT_FOUND, message="no features"))
        result = robot.program_result(seq)
        assert (result["status"], result["job_id"], result["offset"]) == (10, 5, None)
        # The next job still works and its sequence follows.
        trigger, result = await run_job(robot, lnk, triggers, job_id=6)
        assert trigger.seq == seq + 1
        assert result["offset"] == OFFSET


async def test_valid_status_without_ur_target_answers_internal(caplog: pytest.LogCaptureFixture) -> None:
    """Defensive only: a config whose output.vendor is not "ur" is refused when it is loaded
    (URRtdeLink.capabilities), so no job of a running daemon gets here."""
    async with connected(lo("127.0.5.3")) as (robot, lnk, triggers):
        seq = robot.start_program(1)
        await triggers.next()
        kuka = RobotTarget("kuka", ("X", "Y", "Z", "A", "B", "C"), (1.0, 2.0, 3.0, 0.0, 0.0, 0.0))
        with caplog.at_level(logging.ERROR, logger="vgripd.link.ur_rtde"):
            told = await lnk.publish(seq, JobResult(8, Status.OK, target=kuka))
        assert told is Status.INTERNAL  # the daemon counts what the robot was told
        assert "needs a 'ur' target" in caplog.text
        result = robot.program_result(seq)
        assert (result["status"], result["offset"]) == (int(Status.INTERNAL), None)


async def test_publish_returns_the_status_the_robot_got() -> None:
    async with connected(lo("127.0.5.41")) as (robot, lnk, triggers):
        seq = robot.start_program(1, taught_pose=TAUGHT)
        await triggers.next()
        assert await lnk.publish(seq, ur_result(4)) is Status.OK
        assert robot.program_result(seq)["status"] == int(Status.OK)


def test_capabilities_carry_only_the_ur_convention() -> None:
    from vgripd.geometry.vendors import CONVENTIONS
    caps = URRtdeLink.capabilities
    carried = [name for name, conv in CONVENTIONS.items() if caps.refusal(conv) is None]
    assert carried == ["ur"]
    assert "in m" in caps.units
    assert "in rad" in caps.units


async def test_upper_range_registers() -> None:
    async with connected(lo("127.0.5.4"), use_upper_range_registers=True) as (robot, lnk, triggers):
        log_start = len(robot.input_log())
        trigger, result = await run_job(robot, lnk, triggers, job_id=2, upper=True)
        assert result["offset"] == OFFSET
        assert result["status"] == 1
        written = {n for n, _ in robot.input_log(log_start)}
        assert {"input_int_register_42", "input_int_register_46", "input_double_register_42"} <= written
        assert not {n for n in written if n.endswith(("_18", "_19", "_20", "_21", "_22"))}
        assert robot.inputs("input_int_register_42")["input_int_register_42"] == trigger.seq


async def test_pending_request_at_first_connect_is_served() -> None:
    """A request the robot made before vgripd (re)started and nobody answered (its sequence
    differs from the acknowledge register the controller kept) runs at the first connect."""
    with URController(lo("127.0.5.5")) as robot:
        robot.set_outputs(output_int_register_12=41, output_int_register_13=1)
        robot.set_inputs(input_int_register_18=40)  # the last answer an earlier vgripd gave
        lnk = URRtdeLink("ur", URRtdeOptions(host=robot.host))
        triggers = Triggers()
        await lnk.open(triggers)
        try:
            trigger = await triggers.next()
            assert (trigger.seq, trigger.command) == (41, 1)
            await lnk.publish(41, ur_result(7))
            assert robot.wait_input("input_int_register_18", 41)
            seq = robot.start_program(1)  # max(41, ack 41) + 1
            assert seq == 42
            assert (await triggers.next()).seq == 42
            assert triggers.queue.empty()
        finally:
            await lnk.close()


async def test_answered_request_is_not_run_again_after_a_restart() -> None:
    """vgripd restarts after answering request 5: the robot's sequence equals the acknowledge,
    so the new link instance does not run it again."""
    with URController(lo("127.0.5.6")) as robot:
        async with contextlib.AsyncExitStack() as stack:
            first = URRtdeLink("ur", URRtdeOptions(host=robot.host))
            triggers = Triggers()
            await first.open(triggers)
            stack.push_async_callback(first.close)
            trigger, result = await run_job(robot, first, triggers, job_id=1)
            assert result["offset"] == OFFSET
        again = URRtdeLink("ur", URRtdeOptions(host=robot.host))
        triggers = Triggers()
        await again.open(triggers)
        try:
            with pytest.raises(TimeoutError):
                await triggers.next(timeout_s=0.5)
            seq = robot.start_program(1)
            assert seq == trigger.seq + 1
            assert (await triggers.next()).seq == seq
        finally:
            await again.close()


@pytest.mark.parametrize("command", [7, 0, -1])
async def test_unknown_command_is_bad_request_without_a_job(command: int) -> None:
    async with connected(lo(f"127.0.5.{22 + command}")) as (robot, lnk, triggers):
        seq = robot.start_program(command, taught_pose=TAUGHT)
        result = await asyncio.to_thread(robot.program_result, seq)  # the link answers meanwhile
        assert result["error"] is None
        assert (result["status"], result["job_id"], result["offset"]) == (
            int(Status.BAD_REQUEST), 0, None) == (32, 0, None)
        assert triggers.queue.empty()  # no job for the daemon
        assert lnk.refusals() == {"BAD_REQUEST": 1}
        # A good request afterwards runs normally.
        trigger, result = await run_job(robot, lnk, triggers, job_id=3)
        assert trigger.seq == seq + 1
        assert result["offset"] == OFFSET


async def test_busy_answer_is_asked_again_after_a_pause() -> None:
    """The robot program's BUSY handling: it waits and asks again with a new sequence."""
    async with connected(lo("127.0.5.24")) as (robot, lnk, triggers):
        first = robot.start_program(1, taught_pose=TAUGHT, busy_wait_s=0.05)
        await triggers.next()
        await lnk.publish(first, JobResult(0, Status.BUSY, message="refused: BUSY"))
        again = await triggers.next()
        assert again.seq == first + 1
        await lnk.image_captured(again.seq, 5)
        await lnk.publish(again.seq, ur_result(5))
        result = robot.program_result(first)
        assert result["error"] is None
        assert (result["status"], result["busy"], result["requests"]) == (1, 1, [first, first + 1])
        assert result["offset"] == OFFSET


async def test_unanswered_request_is_asked_again_then_given_up() -> None:
    async with connected(lo("127.0.5.25")) as (robot, lnk, triggers):
        # The robot stops waiting for its first request after 0.3 s and asks again; while the
        # first one's job still runs the retry is answered BUSY by the link (as every link's
        # handshake does), and the robot asks once more after its BUSY wait.
        first = robot.start_program(1, timeout_s=0.3, busy_wait_s=5.0)
        assert (await triggers.next()).seq == first  # answered only after the retry
        assert await asyncio.to_thread(robot.wait_input, "input_int_register_18", first + 1,
                                       60.0)
        assert robot.inputs("input_int_register_19")["input_int_register_19"] == Status.BUSY
        assert lnk.refusals() == {"BUSY": 1}
        await lnk.publish(first, ur_result(5))  # too late: the robot waits for its retry
        third = await triggers.next(timeout_s=60.0)  # after the robot's BUSY wait
        assert third.seq == first + 2
        await lnk.publish(third.seq, ur_result(6))
        result = robot.program_result(first, timeout_s=60.0)
        assert (result["status"], result["unanswered"], result["busy"], result["seq"]) == (
            1, 1, 1, third.seq)

        await lnk.close()  # vgripd gone: nobody answers
        gave_up = robot.start_program(1, timeout_s=0.2, attempts=2)
        result = robot.program_result(gave_up)
        assert result["requests"] == [gave_up, gave_up + 1]
        assert result["error"] == (f"no answer to 2 requests (popup, halt): timeout waiting for "
                                   f"input_int_register_18 == {gave_up + 1}")


async def test_worker_output_goes_through_the_log(caplog: pytest.LogCaptureFixture) -> None:
    """ur_rtde prints its own errors on the child's stderr; they arrive as log records."""
    caplog.set_level(logging.INFO, "vgripd.link.ur_rtde")
    async with connected(lo("127.0.5.26"), **FAST) as (robot, lnk, triggers):
        robot.drop()  # ur_rtde's receive thread prints "... End of file"
        await lnk.wait_state(LinkState.DOWN, timeout_s=10)
        await lnk.wait_state(LinkState.UP, timeout_s=15)
    lines = [r.getMessage() for r in caplog.records if "ur_rtde: " in r.getMessage()]
    assert any("End of file" in line for line in lines), lines
    assert all(line.startswith("link ur: ur_rtde: ") and "\n" not in line for line in lines)


# --- faults: drop mid-job, refuse, silent, IN_USE, stream pause ------------------------------

FAST = {"backoff_initial_s": 0.05, "backoff_max_s": 0.4}


@pytest.fixture(autouse=True)
def no_leaked_processes() -> Iterator[None]:
    yield
    assert multiprocessing.active_children() == []


class LogEvent(logging.Handler):
    """Sets ``event`` when a record containing ``text`` is logged."""

    def __init__(self, text: str) -> None:
        super().__init__()
        self.text = text
        self.event = asyncio.Event()

    def emit(self, record: logging.LogRecord) -> None:
        if self.text in record.getMessage():
            self.event.set()


async def test_drop_mid_job_reconnects_and_answers(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG, "vgripd.link.ur_rtde")
    async with connected(lo("127.0.5.11"), **FAST) as (robot, link, triggers):
        seq = robot.start_program(1)
        await triggers.next()
        robot.drop(refuse=True)  # the controller goes away mid-job
        down = await link.wait_state(LinkState.DOWN, timeout_s=10)
        assert lo("127.0.5.11") + ":30004" in down.last_error
        with pytest.raises(LinkError, match="written at the reconnect"):
            await link.publish(seq, ur_result(3))
        retried = LogEvent("still down")
        logging.getLogger("vgripd.link.ur_rtde").addHandler(retried)
        try:
            await asyncio.wait_for(retried.event.wait(), 10)  # a second attempt failed too
        finally:
            logging.getLogger("vgripd.link.ur_rtde").removeHandler(retried)

        robot.listen()
        up = await link.wait_state(LinkState.UP, timeout_s=10)
        assert up.reconnects == 1
        # The result that could not be written is written after the reconnect.
        result = robot.program_result(seq)
        assert result["offset"] == OFFSET
        assert result["job_id"] == 3
        # ... and the next job works.
        trigger, result = await run_job(robot, link, triggers, job_id=4)
        assert trigger.seq == seq + 1
        assert result["offset"] == OFFSET
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1, [r.message for r in warnings]  # logged once per outage
    assert "down" in warnings[0].message


async def test_trigger_while_down_is_served_at_reconnect() -> None:
    async with connected(lo("127.0.5.12"), **FAST) as (robot, link, triggers):
        robot.drop(refuse=True)
        await link.wait_state(LinkState.DOWN, timeout_s=10)
        seq = robot.start_program(1)
        robot.listen()
        trigger = await triggers.next(timeout_s=10)
        assert (trigger.seq, trigger.command) == (seq, 1)
        await link.publish(seq, ur_result(9))
        assert robot.program_result(seq)["offset"] == OFFSET


async def test_silent_controller_does_not_block_the_loop() -> None:
    ticks = 0

    async def heartbeat() -> None:
        nonlocal ticks
        while True:
            await asyncio.sleep(0.01)
            ticks += 1

    with URController(lo("127.0.5.13")) as robot:
        robot.set_silent(True)
        beat = asyncio.create_task(heartbeat())
        link = URRtdeLink("ur", URRtdeOptions(host=robot.host, connect_timeout_s=1.0, **FAST))
        try:
            await link.open(Triggers())  # the child hangs in ur_rtde's constructor
            # open waits connect_timeout_s + 5 s for the first attempt's outcome, then goes on
            # (a busy machine can take longer to start the child): the outcome is awaited here.
            health = await link.wait_state({LinkState.DOWN, LinkState.UP}, timeout_s=45)
            assert health.state is LinkState.DOWN
            assert "did not complete the RTDE setup within 1.0 s" in health.last_error
            # While the child hung for >= 1 s, the loop kept running (10 ms ticks).
            assert ticks >= 20

            robot.set_silent(False)
            # Recovery spawns fresh ur_rtde children after the hung one is killed: 11-17 s on a
            # loaded 2-core machine (before this session's changes too). A bound, not a target.
            await link.wait_state(LinkState.UP, timeout_s=45)
        finally:
            await link.close()
            await stop_task(beat)


async def test_register_in_use_is_an_outage_naming_it_until_released(
        caplog: pytest.LogCaptureFixture) -> None:
    """A register another client owns can be freed on the robot while vgripd runs: DOWN naming
    it, one ERROR line, retried, UP once it is free (never FAILED for good)."""
    with URController(lo("127.0.5.14")) as robot:
        robot.set_in_use("input_int_register_19")
        link = URRtdeLink("ur", URRtdeOptions(host=robot.host, backoff_initial_s=0.05,
                                              backoff_max_s=0.2))
        try:
            with caplog.at_level(logging.INFO, logger="vgripd.link.ur_rtde"):
                await link.open(Triggers())
                health = await link.wait_state({LinkState.DOWN, LinkState.FAILED}, 45)
                assert health.state is LinkState.DOWN
                assert "input_int_register_19 IN_USE" in health.last_error
                assert lo("127.0.5.14") + ":30004" in health.last_error
                assert "input_int_register_20" not in health.last_error
                robot.set_in_use()
                await link.wait_state(LinkState.UP, 45)
            levels = [r.levelname for r in caplog.records if r.name == "vgripd.link.ur_rtde"]
            assert levels[0] == "ERROR"
            assert "WARNING" not in levels  # logged once per outage
        finally:
            await link.close()


async def test_second_client_gets_in_use() -> None:
    async with connected(lo("127.0.5.15")) as (robot, link, triggers):
        second = URRtdeLink("ur2", URRtdeOptions(host=robot.host))
        await second.open(Triggers())  # DOWN and retried: the first may go away
        health = await second.wait_state({LinkState.DOWN, LinkState.FAILED}, 45)
        assert health.state is LinkState.DOWN
        assert re.search("input_int_register_23.*IN_USE", health.last_error)
        assert "input_double_register_22" in health.last_error
        await second.close()
        # The first link is unaffected.
        trigger, result = await run_job(robot, link, triggers, job_id=1)
        assert result["offset"] == OFFSET


async def test_refused_then_controller_starts(caplog: pytest.LogCaptureFixture) -> None:
    link = URRtdeLink("ur", URRtdeOptions(host=lo("127.0.5.16"), **FAST))
    triggers = Triggers()
    try:
        await link.open(triggers)
        health = link.health()
        assert health.state is LinkState.DOWN
        assert lo("127.0.5.16") + ":30004 refused the connection" in health.last_error
        with URController(lo("127.0.5.16")) as robot:
            await link.wait_state(LinkState.UP, timeout_s=15)
            trigger, result = await run_job(robot, link, triggers, job_id=1)
            assert result["offset"] == OFFSET
            await link.close()
    finally:
        await link.close()


async def test_stream_pause_is_noticed_and_recovered() -> None:
    async with connected(lo("127.0.5.17"), stale_after_s=0.5, **FAST) as (robot, link, triggers):
        robot.pause_stream(True)
        down = await link.wait_state(LinkState.DOWN, timeout_s=10)
        assert "no new data package for 0.5 s" in down.last_error
        robot.pause_stream(False)
        up = await link.wait_state(LinkState.UP, timeout_s=15)
        assert up.reconnects == 1
        trigger, result = await run_job(robot, link, triggers, job_id=1)
        assert result["offset"] == OFFSET


async def test_warnings_register_live_and_rewritten_at_reconnect() -> None:
    """input_double_register_21 holds the Warnings bits: written at every connect, before the
    ack of a job published after it (the daemon's order), kept while the link is down."""
    name = f"input_double_register_{URRegisterMap().warnings}"
    assert name == "input_double_register_21"

    def ack_index(log: list[tuple[str, object]], seq: int) -> int:
        return log.index(("input_int_register_18", seq))

    async with connected(lo("127.0.5.18"), **FAST) as (robot, link, triggers):
        trigger, _ = await run_job(robot, link, triggers, job_id=1)
        log = robot.input_log()
        assert log.index((name, 0.0)) < ack_index(log, trigger.seq)  # the connect's write

        seq = robot.start_program(1)
        await triggers.next()
        await link.set_warnings(Warnings.RECALIBRATE)
        await link.publish(seq, ur_result(2))
        result = robot.program_result(seq)  # the robot saw the ack (TCP keeps the order)
        assert result["offset"] == OFFSET
        log = robot.input_log()
        assert log.index((name, 1.0), ack_index(log, trigger.seq)) < ack_index(log, seq)
        assert robot.inputs(name) == {name: 1.0}

        robot.drop(refuse=True)
        await link.wait_state(LinkState.DOWN, timeout_s=10)
        await link.set_warnings(0)  # no error: written at the reconnect
        start = len(robot.input_log())
        robot.listen()
        await link.wait_state(LinkState.UP, timeout_s=15)
        trigger, _ = await run_job(robot, link, triggers, job_id=3)
        log = robot.input_log(start)
        assert log.index((name, 0.0)) < ack_index(log, trigger.seq)
        assert robot.inputs(name) == {name: 0.0}


@pytest.mark.parametrize(("host", "upper"), [("127.0.5.40", False), ("127.0.5.41", True)])
async def test_recipe_register_reaches_the_trigger(host: str, upper: bool) -> None:
    """The script's VGRIPD_RECIPE (output_int_register 15, or 39 in the upper range) is the
    trigger's recipe; a program that never sets it asks for recipe 0."""
    async with connected(lo(host), use_upper_range_registers=upper) as (robot, lnk, triggers):
        for job_id, recipe in ((1, 2), (2, 0), (3, 65535)):
            seq = robot.start_program(1, upper=upper, taught_pose=TAUGHT, recipe=recipe)
            trigger = await triggers.next()
            assert (trigger.seq, trigger.recipe) == (seq, recipe)
            await lnk.image_captured(seq, job_id)
            await lnk.publish(seq, ur_result(job_id))
            assert robot.program_result(seq)["status"] == 1


def ur_pallet(job_id: int, n: int) -> JobResult:
    """A job result of ``n`` pickable instances (x = 0.1, 0.2, ... m), the first one on top."""
    instances = tuple(
        PickInstance(Status.OK, target=RobotTarget("ur", UR_FIELDS, (0.1 * (i + 1), *OFFSET[1:])),
                     pick_id=i + 1, score=0.9)
        for i in range(n))
    return JobResult(job_id, Status.OK, target=instances[0].target, instances=instances)


async def test_next_walks_the_pick_list_through_the_registers() -> None:
    """The robot program's locate (1) then next (3) until NOT_FOUND: each answer carries its
    pose and the pick register (1000 * count + index), written before the ack."""
    async with connected(lo("127.0.5.42")) as (robot, lnk, triggers):
        job = ur_pallet(21, 3)
        seq = robot.start_program(1)
        await triggers.next()
        await lnk.image_captured(seq, 21)
        await lnk.publish(seq, job)
        first = await asyncio.to_thread(robot.program_result, seq)
        assert (first["status"], first["count"], first["index"]) == (1, 3, 1)
        assert first["offset"][0] == 0.1
        log_start = len(robot.input_log())
        seen = []
        for index in (2, 3, 4):
            seq = robot.start_program(int(Command.NEXT))
            trigger = await triggers.next()
            assert (trigger.seq, trigger.command) == (seq, 3)
            await lnk.publish(seq, next_answer(job, index))
            seen.append(await asyncio.to_thread(robot.program_result, seq))
        assert [(r["status"], r["job_id"], r["count"], r["index"]) for r in seen] == [
            (1, 21, 3, 2), (1, 21, 3, 3), (10, 21, 3, 4)]
        assert [r["offset"][0] if r["offset"] else None for r in seen] == [0.1 * 2, 0.1 * 3, None]
        log = robot.input_log(log_start)
        ack = log.index(("input_int_register_18", seen[0]["seq"]))
        assert log.index(("input_double_register_22", 3002.0)) < ack  # pick word before the ack
        assert lnk.refusals() == {}  # NEXT is the daemon's to answer, not a link refusal


async def test_refusal_clears_the_pick_register() -> None:
    async with connected(lo("127.0.5.43")) as (robot, lnk, triggers):
        seq = robot.start_program(1)
        await triggers.next()
        await lnk.publish(seq, ur_pallet(4, 2))
        assert (await asyncio.to_thread(robot.program_result, seq))["count"] == 2
        seq = robot.start_program(9)  # unknown command: the link's own BAD_REQUEST
        result = await asyncio.to_thread(robot.program_result, seq)
        assert (result["status"], result["pick"]) == (32, 0.0)


def ur_matrix(pose: tuple[float, ...]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(pose[3:]).as_matrix()
    T[:3, 3] = np.array(pose[:3]) * 1000.0
    return T


async def test_robot_pose_is_the_controllers_actual_tcp_pose_now() -> None:
    """The setup's capture asks the links for the flange pose between requests: the UR link
    reads actual_TCP_pose at the call; a link without a robot pose answers None."""
    web = WebTriggerLink()
    assert await web.robot_pose() is None
    assert await robot_pose_now({"web": web}) is None
    async with connected(lo("127.0.5.68")) as (robot, lnk, _triggers):
        np.testing.assert_allclose(await lnk.robot_pose(), ur_matrix(TCP), atol=1e-9)
        moved = (0.25, 0.05, 0.40, 0.0, 3.0, 0.1)
        robot.set_tcp_pose(moved)
        loop = asyncio.get_running_loop()
        deadline = loop.time() + 30.0
        while not np.allclose(await lnk.robot_pose(), ur_matrix(moved), atol=1e-9):
            assert loop.time() < deadline, "the link never read the moved TCP pose"
            await asyncio.sleep(0.05)
        name, T = await robot_pose_now({"web": web, "ur": lnk}) or ("", None)
        assert name == "ur"
        np.testing.assert_allclose(T, ur_matrix(moved), atol=1e-9)
    assert await lnk.robot_pose() is None  # closed: no pose, no error
