"""Conveyor tracking end to end over the client links: the daemon in-process with a conveyor
recipe and a map version 4 link it writes into the PLC with, the S7 link (snap7's own server
in a child process as the PLC, the mock PLC program a snap7 client) and the Modbus client link
(a pymodbus server standing for the PLC, the mock program writing its registers).

The PLC latches the encoder count with each request (across the 32-bit counter's wrap), walks
the part queue with NEXT and asks PREDICT for an intercept. The belt is the shared conveyor
cell's (tests/integration/belt_cell.py: simulated independently of the code under test,
images rendered at chosen travels); every answer is checked against its truth at the count
the answer names: the pose, ALONG/ACROSS/THETA, RESULT_COUNT, each part served once and
downstream first, a part seen in two images served once, a part past the window dropped,
PREDICT answered inside the window and refused past it.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.integration.belt_cell import (
    COUNTS_PER_MM,
    MAP_WORDS,
    PARTS,
    WINDOW,
    conveyor_data,
    count_at,
    f32,
    render,
    travel_of,
    u32,
    visible,
    which,
)
from tests.integration.test_daemon import Run, running
from vgripd.config import config_from_dict
from vgripd.peer.jobcore import Command
from vgripd.peer.registers import Reg, ValueCodec
from vgripd.sim.robot_modbus import UR_FIRST_REGISTER, MockRobotModbus
from vgripd.sim.s7_plc import MockS7Plc, S7PlcServer, words_of
from vgripd.types import Status
from vgripd.vision.scene import T_base_obj_ref

pytestmark = pytest.mark.timeout(300)

FRAMES = [0.0, 150.0, 300.0]  # the count wraps at travel 300 mm (belt_cell.COUNT0)
ANSWER_S = 60.0  # a request's answer, the first job's included, on a busy machine
DB = 10

#: One request of the PLC program: (command, count) -> the block's words after its answer.
Request = Callable[[int, int], Awaitable[list[int]]]


async def walk_the_belt(request: Request, T_ref: np.ndarray, run: Run) -> None:
    """Three images, then NEXT and PREDICT, each answer against the belt's truth."""

    async def trigger(frame: int) -> None:
        words = await request(Command.TRIGGER, count_at(FRAMES[frame]))
        assert words[Reg.STATUS] == Status.OK, words[Reg.STATUS]
        assert words[Reg.MAP_VERSION] == 4
        assert u32(words, Reg.RESULT_COUNT) == count_at(FRAMES[frame])
        assert words[Reg.LATCH_SOURCE] == 1
        assert f32(words, Reg.LATCH_ERR_MM) == pytest.approx(0.5 / COUNTS_PER_MM, abs=1e-4)
        assert words[Reg.COUNT] == len(visible(FRAMES[frame]))
        assert which(words, FRAMES[frame], T_ref) in visible(FRAMES[frame])

    async def next_part(travel_now: float) -> int | None:
        words = await request(Command.NEXT, count_at(travel_now))
        if words[Reg.STATUS] == Status.NOT_FOUND:
            assert words[Reg.N_VALUES] == 0
            return None
        assert words[Reg.STATUS] == Status.OK, words[Reg.STATUS]
        at = travel_of(u32(words, Reg.RESULT_COUNT))  # its own image's count
        assert at in FRAMES
        part = which(words, at, T_ref)
        assert PARTS[part][0] + travel_now <= WINDOW[1]  # still in reach now
        return part

    await trigger(0)  # parts 0 and 1
    await trigger(1)  # parts 1 (again) and 2
    await trigger(2)  # parts 2 (again) and 3, the count past the wrap
    # at travel 350 part 0 is at 1050, past the window's end (1000): dropped, not served
    assert await next_part(350.0) == 1
    words = await request(Command.PREDICT, count_at(380.0))  # part 1 inside the window
    assert words[Reg.STATUS] == Status.OK
    assert u32(words, Reg.RESULT_COUNT) == count_at(380.0)
    assert which(words, 380.0, T_ref) == 1
    words = await request(Command.PREDICT, count_at(500.0))  # past the window's end by then
    assert (words[Reg.STATUS], words[Reg.N_VALUES]) == (Status.OUT_OF_WORKSPACE, 0)
    assert [await next_part(455.0) for _ in range(3)] == [2, 3, None]
    conveyor = run.daemon.snapshot()["conveyor"]["0"]
    sightings = sum(len(visible(t)) for t in FRAMES)
    assert conveyor["seen"] == sightings == 6
    assert conveyor["duplicates"] == 2
    assert (conveyor["dropped"], conveyor["served"], conveyor["queued"]) == (1, 3, 0)


def belt_config(folder: Path, link: dict[str, Any]) -> Any:
    data = conveyor_data({"type": "replay", "folder": str(folder), "left_glob": "left_*.png",
                          "right_glob": "right_*.png"})
    data["links"] = [link]
    return config_from_dict(data)


async def test_a_belt_through_the_s7_link(tmp_path: Path) -> None:
    await render(tmp_path, FRAMES)
    async with S7PlcServer(DB, size=2 * MAP_WORDS) as server:
        config = belt_config(tmp_path, {"type": "s7", "host": server.host, "port": server.port,
                                        "db": DB, "poll_ms": 5, "map_version": 4})
        seq = 0

        async with running(config) as run, MockS7Plc(server.host, server.port, DB,
                                                     size=2 * MAP_WORDS) as plc:

            async def request(command: int, count: int) -> list[int]:
                nonlocal seq
                seq += 1
                seen = await plc.run_job(seq, ANSWER_S, command=command, latch=count)
                assert seen.words[Reg.ACK_SEQ] == seq, seen.words
                return list(words_of(seen.raw))

            await walk_the_belt(request, T_base_obj_ref(config), run)


async def test_a_belt_through_the_modbus_client_link(tmp_path: Path) -> None:
    await render(tmp_path, FRAMES)
    robot = MockRobotModbus()  # the PLC's Modbus server: holding registers 128-255
    await robot.start()
    try:
        config = belt_config(tmp_path, {"type": "modbus_client", "host": robot.host,
                                        "port": robot.port, "base_address": UR_FIRST_REGISTER,
                                        "poll_interval_s": 0.005, "map_version": 4})
        seq = 0
        codec = ValueCodec("ABCD", "float32")

        async with running(config) as run:

            async def request(command: int, count: int) -> list[int]:
                nonlocal seq
                seq += 1
                seen = await robot.run_job(seq, ANSWER_S, command=command, latch=count,
                                           codec=codec, size=MAP_WORDS)
                assert seen.words[Reg.ACK_SEQ] == seq, seen.words
                # vgripd never wrote the program's latch (it wrote it itself, unlogged)
                latch = range(UR_FIRST_REGISTER + Reg.LATCH_COUNT,
                              UR_FIRST_REGISTER + Reg.RESULT_COUNT)
                assert not [w for w in seen.writes if w.address < latch.stop
                            and w.address + len(w.values) > latch.start], seen.writes
                return list(seen.words)

            await walk_the_belt(request, T_base_obj_ref(config), run)
    finally:
        await robot.stop()
