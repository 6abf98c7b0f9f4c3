"""Conveyor tracking over the robot socket link: the daemon in-process with a conveyor recipe
and a robot_socket link; a robot (raw TCP frames, built here from docs/robot_socket.md, not
with the link's codec) sends counted LOCATEs with the encoder count latched at each image,
walks the part queue with counted NEXTs and asks PREDICT for an intercept.

The belt is the shared conveyor cell (tests/integration/belt_cell.py), simulated independently
of the code under test; every answer is checked against its truth at the count the BELT frame
names: the pose, RESULT_COUNT, LATCH_SOURCE, LATCH_ERR_MM, ALONG/ACROSS/THETA and QUEUED."""

from __future__ import annotations

import asyncio
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.integration.belt_cell import (
    COUNTS_PER_MM,
    PARTS,
    WINDOW,
    conveyor_data,
    count_at,
    part_of,
    render,
    travel_of,
    visible,
)
from tests.integration.test_daemon import running
from vgripd.config import config_from_dict
from vgripd.geometry.vendors import transform_from_vendor
from vgripd.types import Status
from vgripd.vision.scene import T_base_obj_ref

pytestmark = pytest.mark.timeout(300)
WAIT_S = 60.0
SCALE = 10000
# docs/robot_socket.md: word 0 is "VG", version 1, then the command or the answer kind
LOCATE, NEXT, PREDICT, COUNTED = 1, 3, 5, 0x40
CAPTURED, RESULT, REFUSED, BELT = 0x81, 0x82, 0x83, 0x84


def word0(code: int) -> int:
    return 0x56470100 | code


@dataclass
class Answer:
    kind: int
    status: int
    job_id: int
    values: tuple[float, ...]
    remaining: int
    captured: bool
    belt: tuple[int, ...] | None  # BELT words 2, 3 and 8: RESULT_COUNT, LATCH_SOURCE, QUEUED
    belt_mm: tuple[float, ...]  # BELT words 4-7: LATCH_ERR_MM, ALONG, ACROSS, THETA


class Robot:
    """A robot program's side of the link, byte by byte."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.seq = 0

    async def __aenter__(self) -> Robot:
        self.reader, self.writer = await asyncio.open_connection("127.0.0.1", self.port)
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.writer.close()

    async def ask(self, command: int, count: int | None = None, frame: int = 0,
                  recipe: int = 0) -> Answer:
        self.seq += 1
        if count is None:
            self.writer.write(struct.pack(">4I", word0(command), self.seq, recipe, 0))
        else:
            self.writer.write(struct.pack(">6I", word0(command | COUNTED), self.seq, recipe, 0,
                                          count, frame))
        captured, belt, belt_mm = False, None, ()
        async with asyncio.timeout(WAIT_S):
            while True:
                raw = await self.reader.readexactly(64)
                w = struct.unpack(">16i", raw)
                u = struct.unpack(">16I", raw)
                assert u[0] >> 8 == 0x564701, hex(u[0])
                assert w[1] == self.seq
                kind = u[0] & 0xFF
                if kind == CAPTURED:
                    captured = True
                elif kind == BELT:
                    assert belt is None, "one BELT frame per request"
                    assert u[14] == SCALE
                    belt = (u[2], u[3], u[8])
                    belt_mm = tuple(v / SCALE for v in w[4:8])
                else:
                    assert kind in (RESULT, REFUSED), hex(kind)
                    assert u[14] == SCALE
                    values = tuple(v / SCALE for v in w[6:6 + w[5]])
                    return Answer(kind, w[2], u[3], values, u[15], captured, belt, belt_mm)


def socket_config(camera: dict[str, Any]) -> Any:
    data = conveyor_data(camera)
    data["links"] = [{"type": "robot_socket", "host": "127.0.0.1", "port": 0}]
    return config_from_dict(data)


def checked(a: Answer, travel_mm: float, T_ref: np.ndarray) -> int:
    """The part the answer's pose is (1 mm, 0.5 deg of its truth), its belt terms checked."""
    T = transform_from_vendor("kuka", a.values) @ T_ref  # output.mode offset
    part, mm, deg = part_of(T, travel_mm)
    assert mm < 1.0
    assert deg < 0.5, (part, mm, deg)
    x, y, theta = PARTS[part]
    _, along, across, turn = a.belt_mm
    assert along == pytest.approx(x + travel_mm, abs=1.0)
    assert across == pytest.approx(y, abs=1.0)
    assert turn == pytest.approx(theta, abs=0.5)
    return part


async def test_counted_frames_serve_the_belt_as_the_registers_do(tmp_path: Path) -> None:
    frames = [0.0, 150.0, 300.0, 450.0]
    await render(tmp_path, [frames[0], *frames])  # the first image goes to an old LOCATE
    config = socket_config({"type": "replay", "folder": str(tmp_path),
                            "left_glob": "left_*.png", "right_glob": "right_*.png"})
    T_ref = T_base_obj_ref(config)
    async with running(config) as run, Robot(run.port()) as robot:
        # an old 16-byte LOCATE on a conveyor recipe: the job ends BAD_REQUEST, nothing queued
        a = await robot.ask(LOCATE)
        assert (a.kind, a.status, a.values, a.belt) == (RESULT, Status.BAD_REQUEST, (), None)
        assert a.job_id
        assert a.captured

        for i, travel in enumerate(frames[:3]):
            a = await robot.ask(LOCATE, count_at(travel), frame=i)
            assert a.status == Status.OK
            assert a.captured
            assert a.belt is not None
            assert a.belt[:2] == (count_at(travel), 1)  # RESULT_COUNT, LATCH_SOURCE link
            assert a.belt_mm[0] == pytest.approx(0.5 / COUNTS_PER_MM, abs=1e-4)
            assert checked(a, travel, T_ref) in visible(travel)
            assert a.remaining == len(visible(travel)) - 1
        assert a.belt is not None
        assert a.belt[2] == 4  # QUEUED: parts 0..3, each seen once

        # NEXT at travel 350: part 0 is past the window (1050 > 1000), dropped; part 1 served
        # with its pose at its own latched count
        a = await robot.ask(NEXT, count_at(350.0))
        assert a.status == Status.OK
        assert not a.captured
        assert a.belt is not None
        at = travel_of(a.belt[0])
        assert at in frames
        assert checked(a, at, T_ref) == 1
        assert a.belt[2] == 2  # parts 2 and 3 wait

        # PREDICT: part 1 at travel 380 (inside the window), and at 500 (past its end)
        a = await robot.ask(PREDICT, count_at(380.0))
        assert (a.kind, a.status) == (RESULT, Status.OK)
        assert a.belt is not None
        assert a.belt[0] == count_at(380.0)
        assert checked(a, 380.0, T_ref) == 1
        assert PARTS[1][0] + 380.0 <= WINDOW[1]
        a = await robot.ask(PREDICT, count_at(500.0))
        assert (a.status, a.values) == (Status.OUT_OF_WORKSPACE, ())
        assert a.belt is not None
        assert a.belt[0] == count_at(500.0)

        # PREDICT without its count (a 16-byte frame of command 5): refused, nothing changes
        a = await robot.ask(PREDICT)
        assert (a.kind, a.status, a.belt) == (REFUSED, Status.BAD_REQUEST, None)
        # a counted command that carries no count (CLEAR + 0x40): refused with a BELT frame
        a = await robot.ask(2, count_at(380.0))
        assert (a.kind, a.status, a.belt) == (REFUSED, Status.BAD_REQUEST, (0, 0, 0))

        served = []
        for _ in range(3):
            a = await robot.ask(NEXT, count_at(455.0))
            if a.status == Status.NOT_FOUND:
                assert a.values == ()
                assert a.belt is not None
                assert a.belt[2] == 0
                break
            assert a.status == Status.OK
            assert a.belt is not None
            served.append(checked(a, travel_of(a.belt[0]), T_ref))
        assert served == [2, 3]
        conveyor = run.daemon.snapshot()["conveyor"]["0"]
    assert (conveyor["dropped"], conveyor["served"], conveyor["queued"]) == (1, 3, 0)


async def test_a_counted_locate_without_a_conveyor_is_a_plain_locate(tmp_path: Path) -> None:
    await render(tmp_path, [600.0])
    data = conveyor_data({"type": "replay", "folder": str(tmp_path),
                          "left_glob": "left_*.png", "right_glob": "right_*.png"})
    data.pop("conveyor")
    data["links"] = [{"type": "robot_socket", "host": "127.0.0.1", "port": 0}]
    config = config_from_dict(data)
    T_ref = T_base_obj_ref(config)
    async with running(config) as run, Robot(run.port()) as robot:
        a = await robot.ask(LOCATE, count_at(600.0))
        assert (a.kind, a.status) == (RESULT, Status.OK)
        assert a.belt == (0, 0, 0)
        assert a.belt_mm == (0.0, 0.0, 0.0, 0.0)  # LATCH_SOURCE 0
        T = transform_from_vendor("kuka", a.values) @ T_ref
        part, mm, _ = part_of(T, 600.0)
        assert part in visible(600.0)
        assert mm < 1.0
        a = await robot.ask(PREDICT, count_at(700.0))  # no conveyor: refused by the link
        assert (a.kind, a.status, a.belt) == (REFUSED, Status.BAD_REQUEST, (0, 0, 0))

