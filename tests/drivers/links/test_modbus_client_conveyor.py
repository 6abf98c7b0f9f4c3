"""The Modbus client link on map version 4 (the conveyor's latch and belt result) against the
mock robot/PLC Modbus server (pymodbus, holding registers 128-255), over TCP on 127.0.0.1.

The program side decodes with ``struct`` at the map's offsets, not with vgripd's codec. The
daemon is stood in for (the conveyor end to end with the real daemon:
tests/integration/test_daemon_conveyor_links.py).
"""

from __future__ import annotations

import asyncio
import struct
from collections.abc import AsyncIterator, Sequence

import pytest

from drivers.links.modbus_client import (
    ModbusClientOptions,
    full_image_writes,
    plan_writes,
)
from tests.drivers.links.test_modbus_client import Daemon, make_link
from vgripd.peer.jobcore import Command
from vgripd.peer.registers import COMMAND_AREA, LATCH_AREA, MAP_SIZE_V4, BlockWrite, Reg
from vgripd.service.links.protocol import LinkState, Trigger
from vgripd.sim.robot_modbus import UR_FIRST_REGISTER, MockRobotModbus, RegisterWrite
from vgripd.types import BeltPose, JobResult, RobotTarget, Status

pytestmark = pytest.mark.timeout(300)  # a busy machine

BASE = UR_FIRST_REGISTER
WAIT_S = 30.0
PEER = (COMMAND_AREA, LATCH_AREA)
LATCH = range(BASE + LATCH_AREA.start, BASE + LATCH_AREA.stop)  # robot registers 174-177


@pytest.fixture
async def robot() -> AsyncIterator[MockRobotModbus]:
    r = MockRobotModbus()
    await r.start()
    yield r
    await r.stop()


def belt_result(trigger: Trigger) -> JobResult:
    assert trigger.latch_count is not None
    target = RobotTarget("ur", ("x", "y", "z", "rx", "ry", "rz"),
                         (0.5, -0.125, 0.25, 0.0, 3.14, 0.0))
    belt = BeltPose(count=trigger.latch_count, source=1, error_mm=0.05, along_mm=640.5,
                    across_mm=-3.25, theta_deg=-12.0, queued=2)
    return JobResult(job_id=trigger.seq, status=Status.OK, target=target, belt=belt)


def u32(words: tuple[int, ...], reg: int) -> int:
    value: int = struct.unpack(">I", struct.pack(">2H", *words[reg:reg + 2]))[0]
    return value


def f32(words: tuple[int, ...], reg: int) -> float:
    value: float = struct.unpack(">f", struct.pack(">2H", *words[reg:reg + 2]))[0]
    return value


def into_latch(writes: Sequence[RegisterWrite]) -> list[RegisterWrite]:
    return [w for w in writes
            if w.address < LATCH.stop and w.address + len(w.values) > LATCH.start]


async def test_the_latch_travels_with_the_request_and_survives_a_reconnect(
        robot: MockRobotModbus) -> None:
    """TRIGGER, NEXT and PREDICT each carry the count the program latched, across the 32-bit
    wrap; the answer has RESULT_COUNT and the belt fields. After a dropped connection the link
    writes its whole mirror again, and still not the program's latch."""
    link = make_link(robot, map_version=4)
    link.set_conveyor(True)
    daemon = Daemon(link, belt_result)
    await link.open(daemon.on_trigger)
    counts = [(1 << 32) - 2, 3, 77]
    commands = [Command.TRIGGER, Command.NEXT, Command.PREDICT]
    try:
        seen = [await robot.run_job(seq, WAIT_S, command=command, latch=count,
                                    size=MAP_SIZE_V4)
                for seq, (command, count) in enumerate(zip(commands, counts, strict=True),
                                                      start=1)]
        triggers = [daemon.triggers.get_nowait() for _ in seen]
        # the program latches the next count ahead; the connection drops and comes back
        await robot.write(BASE + Reg.LATCH_COUNT, [0xCAFE, 0xF00D])
        before = len(robot.writes)
        robot.drop_connections()
        await link.wait_state(LinkState.DOWN, WAIT_S)
        await link.wait_state(LinkState.UP, WAIT_S)
        async with asyncio.timeout(WAIT_S):  # the whole mirror written again, ACK_SEQ last
            while not [w for w in robot.writes[before:] if w.address == BASE + Reg.ACK_SEQ]:
                await robot.changed()
        assert robot.read(BASE + Reg.LATCH_COUNT, 2) == [0xCAFE, 0xF00D]
        assert robot.read(BASE + Reg.MAP_VERSION)[0] == 4
    finally:
        await link.close()
    assert [(t.command, t.latch_count) for t in triggers] == list(zip(commands, counts,
                                                                      strict=True))
    for s, count in zip(seen, counts, strict=True):
        w = s.words
        assert (w[Reg.ACK_SEQ], w[Reg.STATUS], w[Reg.MAP_VERSION]) == (s.seq, Status.OK, 4)
        assert u32(w, Reg.RESULT_COUNT) == count
        assert (w[Reg.LATCH_SOURCE], w[Reg.QUEUED]) == (1, 2)
        assert f32(w, Reg.LATCH_ERR_MM) == pytest.approx(0.05)
        assert (f32(w, Reg.ALONG), f32(w, Reg.ACROSS), f32(w, Reg.THETA)) == (
            640.5, -3.25, -12.0)
    assert not into_latch(robot.writes), into_latch(robot.writes)


def test_plans_leave_out_the_programs_latch() -> None:
    words = list(range(MAP_SIZE_V4))
    full = full_image_writes(words, PEER)
    assert full[-1] == BlockWrite(Reg.ACK_SEQ, (Reg.ACK_SEQ,))
    covered = sorted(w.address + i for w in full for i in range(len(w.words)))
    assert covered == [a for a in range(MAP_SIZE_V4)
                       if a not in COMMAND_AREA and a not in LATCH_AREA]
    assert all(w.words == tuple(words[w.address:w.address + len(w.words)]) for w in full)
    # a bank write across the latch (a whole-block rewrite) is split around it
    plan = plan_writes([BlockWrite(40, tuple(range(40, 55)))], PEER)
    assert plan == [BlockWrite(40, tuple(range(40, 46))), BlockWrite(50, tuple(range(50, 55)))]
    assert plan_writes([BlockWrite(LATCH_AREA.start, (1, 2, 3, 4))], PEER) == []


def test_base_address_leaves_room_for_the_version_4_block() -> None:
    ok = ModbusClientOptions(host="h", base_address=65536 - MAP_SIZE_V4, map_version=4)
    assert ok.base_address == 65474
    assert ModbusClientOptions(host="h", base_address=65490).base_address == 65490  # version 3
    with pytest.raises(ValueError, match=r"base_address 65490: the block of map version 4 "
                                         r"\(62 registers\)"):
        ModbusClientOptions(host="h", base_address=65490, map_version=4)


async def test_a_robot_range_too_short_for_version_4_names_the_register() -> None:
    """UR's registers end at 255: a version 4 block from base 200 does not fit; DOWN at first
    contact naming the first map register the robot does not have."""
    robot = MockRobotModbus()
    await robot.start()
    link = make_link(robot, base_address=200, map_version=4)
    try:
        await link.open(Daemon(link).on_trigger)
        health = await link.wait_state({LinkState.DOWN, LinkState.FAILED}, WAIT_S)
        assert health.state is LinkState.DOWN
        assert "block base 200 + 56, map register ALONG" in health.last_error
    finally:
        await link.close()
        await robot.stop()


async def test_every_poll_hands_the_published_count_to_the_travel_trigger(
        robot: MockRobotModbus) -> None:
    """``conveyor.trigger = "travel"``: the PLC keeps LATCH_COUNT at the count now; the link
    hands the count of every poll (a standing count too, with its newer time) to the handler,
    across the 32-bit wrap, and never writes the PLC's latch."""
    link = make_link(robot, map_version=4)
    got: list[tuple[int, int]] = []
    read = asyncio.Event()

    def on_count(count: int, t_ns: int) -> None:
        got.append((count, t_ns))
        read.set()

    link.watch_count(on_count)
    await link.open(Daemon(link).on_trigger)
    try:
        for count in ((1 << 32) - 5, (1 << 32) - 5, 4, 1000):
            await robot.write(BASE + Reg.LATCH_COUNT,
                              list(struct.unpack(">2H", struct.pack(">I", count))))
            mark = len(got)
            async with asyncio.timeout(WAIT_S):  # two polls after the write: the second sees it
                while len(got) < mark + 2:
                    read.clear()
                    await read.wait()
            assert got[-1][0] == count
    finally:
        await link.close()
    counts = [c for c, _ in got]
    assert set(counts) >= {(1 << 32) - 5, 4, 1000}
    times = [t for _, t in got]
    assert times == sorted(times)
    assert not into_latch(robot.writes), into_latch(robot.writes)
