"""Conveyor tracking end to end: the daemon in-process with a conveyor recipe, a PLC (a real
pymodbus client over TCP, map version 4) that latches the encoder count with each trigger,
walks the part queue with NEXT and asks PREDICT for an intercept.

The belt is simulated here, independently of the code under test: five parts at known places
along a straight belt at count ``COUNT0``, carried ``travel`` mm at each image; every image is
rendered (the synthetic camera's renderer, fixed poses) with the parts under the camera at that
travel and replayed to the daemon in order. Every answer is checked against this belt's truth at
the count the answer names: the pose in the registers, ALONG/ACROSS/THETA, each part served
once, a part seen in two images served once, a part past the window dropped, PREDICT answered
inside the window and refused past it."""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from tests.integration.test_daemon import CODEC, Plc, running, values
from vgripd.config import Config, config_from_dict, load_config
from vgripd.geometry.vendors import transform_from_vendor
from vgripd.registry import CAMERAS, load_class, validate_options
from vgripd.serialize import toml_from_dict
from vgripd.service.daemon import Daemon
from vgripd.service.protocol import Command, Reg
from vgripd.service.reload import Reloader
from vgripd.types import Status
from vgripd.vision.scene import T_base_obj_ref

pytestmark = pytest.mark.timeout(300)

COUNTS_PER_MM = 10.0
COUNT0 = (1 << 32) - 3000  # the 32-bit counter wraps during the run
BELT_Y, BELT_Z = 100.0, 10.0  # the belt runs along base +x through y = 100 at z = 10
WINDOW = (300.0, 1000.0)
#: The parts at travel 0: x (along the belt), y offset across (to the left = +y), rotation.
PARTS = [(700.0, 8.0, 12.0), (560.0, -12.0, -25.0), (380.0, 5.0, 30.0),
         (200.0, -6.0, -8.0), (40.0, 10.0, 20.0)]
#: Where the camera sees a whole part (its origin's x); the layout keeps clear of the edges.
VISIBLE = (460.0, 740.0)
MAP_WORDS = 62


def count_at(travel_mm: float) -> int:
    return (COUNT0 + round(travel_mm * COUNTS_PER_MM)) % (1 << 32)


def truth(part: int, travel_mm: float) -> np.ndarray:
    """Part ``part``'s pose in the base frame after the belt travelled ``travel_mm``."""
    x, y, theta = PARTS[part]
    t = math.radians(theta)
    T = np.eye(4)
    T[:2, :2] = [[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]]
    T[:3, 3] = (x + travel_mm, BELT_Y + y, BELT_Z)
    return T


def visible(travel_mm: float) -> list[int]:
    return [k for k, (x, _, _) in enumerate(PARTS) if VISIBLE[0] <= x + travel_mm <= VISIBLE[1]]


def conveyor_config(camera: dict[str, Any]) -> Config:
    return config_from_dict(conveyor_data(camera))


def conveyor_data(camera: dict[str, Any]) -> dict[str, Any]:
    demo = Config().calibration
    assert demo is not None
    return {
        "camera": camera,
        "links": [{"type": "modbus_server", "host": "127.0.0.1", "port": 0,
                   "map_version": 4}],
        "status": {"port": 0},
        "daemon": {"worker": False},
        "calibration": demo.model_dump(mode="json", exclude_none=True),
        "picking": {"max_objects": 4},
        "limits": {"max_translation_mm": 400.0, "max_rotation_deg": 60.0},
        "conveyor": {"counts_per_mm": COUNTS_PER_MM, "direction": [1.0, 0.0, 0.0],
                     "origin_mm": [0.0, BELT_Y, BELT_Z], "window_mm": list(WINDOW),
                     "trigger_distance_mm": 150.0, "speed_mm_s": 300.0, "sigma_mm": 0.5},
    }


async def render(folder: Path, frames: list[float]) -> None:
    """One stereo image per travel in ``frames``, the visible parts at their true poses."""
    cls = load_class(CAMERAS, "camera", "synthetic")
    for i, travel in enumerate(frames):
        poses = [truth(k, travel) for k in visible(travel)]
        assert poses, f"frame {i}: no part under the camera (the test's layout)"
        rot = [cv2.Rodrigues(T[:3, :3])[0].ravel().tolist() for T in poses]
        options = {"type": "synthetic", "seed": 100 + i,
                   "instances": [{"translation_mm": T[:3, 3].tolist(), "rotvec_rad": r}
                                 for T, r in zip(poses, rot, strict=True)]}
        cfg = conveyor_config(options)
        camera = cls(validate_options(cls, cfg.camera, "camera"), cfg)
        await camera.open()
        try:
            pair = await camera.grab(30.0)
        finally:
            await camera.close()
        assert pair.right is not None
        cv2.imwrite(str(folder / f"left_{i}.png"), pair.left)
        cv2.imwrite(str(folder / f"right_{i}.png"), pair.right)


class BeltPlc(Plc):
    """The PLC with the conveyor's registers: LATCH_COUNT with every request."""

    seq = 0

    async def request(self, command: int, count: int) -> list[int]:
        rr = await self.client.write_registers(Reg.LATCH_COUNT, CODEC.u32(count))
        assert not rr.isError(), rr
        self.seq += 1
        rr = await self.client.write_registers(Reg.CMD, [command, self.seq])
        assert not rr.isError(), rr
        return await self.result(self.seq)

    async def read(self) -> list[int]:
        rr = await self.client.read_holding_registers(0, count=MAP_WORDS)
        assert not rr.isError(), rr
        return list(rr.registers)


def u32(words: list[int], reg: int) -> int:
    return CODEC.decode_u32(words[reg:reg + 2])


def f32(words: list[int], reg: int) -> float:
    return CODEC.decode_value(words[reg:reg + 2])


def which(words: list[int], travel_mm: float, T_ref: np.ndarray) -> int:
    """The part whose true pose at ``travel_mm`` the answer's pose is (checked to 1 mm and
    0.5 deg), its belt terms checked too."""
    T_offset = transform_from_vendor("kuka", values(words))
    T = T_offset @ T_ref  # output.mode offset: T_base_obj = T_offset @ T_base_obj_ref
    near = min(range(len(PARTS)),
               key=lambda k: float(np.linalg.norm(truth(k, travel_mm)[:3, 3] - T[:3, 3])))
    want = truth(near, travel_mm)
    assert np.linalg.norm(want[:3, 3] - T[:3, 3]) < 1.0, (near, travel_mm, T[:3, 3])
    turn = math.degrees(math.acos(np.clip((np.trace(want[:3, :3].T @ T[:3, :3]) - 1) / 2,
                                          -1, 1)))
    assert turn < 0.5
    x, y, theta = PARTS[near]
    assert f32(words, Reg.ALONG) == pytest.approx(x + travel_mm, abs=1.0)
    assert f32(words, Reg.ACROSS) == pytest.approx(y, abs=1.0)
    assert f32(words, Reg.THETA) == pytest.approx(theta, abs=0.5)
    return near


def travel_of(count: int) -> float:
    return ((count - COUNT0) % (1 << 32)) / COUNTS_PER_MM


async def test_a_belt_served_once_per_part_in_belt_order_at_the_latched_counts(
        tmp_path: Path) -> None:
    frames = [0.0, 150.0, 300.0, 450.0, 600.0]
    await render(tmp_path, frames)
    config = conveyor_config({"type": "replay", "folder": str(tmp_path),
                              "left_glob": "left_*.png", "right_glob": "right_*.png"})
    T_ref = T_base_obj_ref(config)
    served: list[int] = []

    async def trigger(frame: int) -> None:
        words = await plc.request(Command.TRIGGER, count_at(frames[frame]))
        assert words[Reg.STATUS] == Status.OK, words[Reg.STATUS]
        assert u32(words, Reg.RESULT_COUNT) == count_at(frames[frame])
        assert words[Reg.LATCH_SOURCE] == 1
        assert f32(words, Reg.LATCH_ERR_MM) == pytest.approx(0.5 / COUNTS_PER_MM, abs=1e-4)
        assert words[Reg.COUNT] == len(visible(frames[frame]))
        assert which(words, frames[frame], T_ref) in visible(frames[frame])

    async def next_part(travel_now: float) -> int | None:
        words = await plc.request(Command.NEXT, count_at(travel_now))
        if words[Reg.STATUS] == Status.NOT_FOUND:
            assert words[Reg.N_VALUES] == 0
            return None
        assert words[Reg.STATUS] == Status.OK, words[Reg.STATUS]
        # the pose at its own latched count: a count of an image, not the count now
        at = travel_of(u32(words, Reg.RESULT_COUNT))
        assert at in frames
        part = which(words, at, T_ref)
        assert PARTS[part][0] + travel_now <= WINDOW[1]  # still in reach now
        served.append(part)
        return part

    async with running(config) as run, BeltPlc(run.port()) as plc:
        await trigger(0)  # parts 0 and 1
        await trigger(1)  # parts 1 (again) and 2
        await trigger(2)  # parts 2 (again) and 3
        # at travel 350 part 0 is at 1050, past the window's end (1000): dropped, not served
        assert await next_part(350.0) == 1
        # PREDICT: where part 1 will be at travel 380 (inside the window), and at 500 (past)
        words = await plc.request(Command.PREDICT, count_at(380.0))
        assert words[Reg.STATUS] == Status.OK
        assert u32(words, Reg.RESULT_COUNT) == count_at(380.0)
        assert which(words, 380.0, T_ref) == 1
        words = await plc.request(Command.PREDICT, count_at(500.0))
        assert (words[Reg.STATUS], words[Reg.N_VALUES]) == (Status.OUT_OF_WORKSPACE, 0)
        await trigger(3)  # parts 3 (again) and 4
        assert [await next_part(455.0) for _ in range(3)] == [2, 3, 4]
        await trigger(4)  # part 4 again, already served: not queued again
        assert await next_part(610.0) is None
        conveyor = run.daemon.snapshot()["conveyor"]["0"]
    assert served == [1, 2, 3, 4]  # each once, downstream first; part 0 missed
    sightings = sum(len(visible(t)) for t in frames)
    assert conveyor["seen"] == sightings == 9
    assert conveyor["duplicates"] == sightings - len(PARTS) == 4
    assert (conveyor["dropped"], conveyor["served"], conveyor["queued"]) == (1, 4, 0)


async def test_a_reload_applies_a_changed_added_and_removed_conveyor(tmp_path: Path) -> None:
    frames = [0.0, 150.0]
    await render(tmp_path, frames)
    data = conveyor_data({"type": "replay", "folder": str(tmp_path), "left_glob": "left_*.png",
                          "right_glob": "right_*.png"})
    main = tmp_path / "vgripd.toml"

    def write(conveyor: dict[str, Any] | None) -> None:
        d = copy.deepcopy(data)
        d.pop("conveyor")
        if conveyor is not None:
            d["conveyor"] = conveyor
        main.write_text(toml_from_dict(d))

    belt = dict(data["conveyor"])
    write(belt)
    daemon = Daemon(load_config(main))
    reloader = daemon.reloader = Reloader(daemon, main)
    await daemon.start()
    try:
        async with BeltPlc(list(daemon.links.values())[0].port) as plc:
            words = await plc.request(Command.TRIGGER, count_at(frames[0]))
            assert words[Reg.STATUS] == Status.OK
            assert words[Reg.QUEUED] == 2
            line = daemon._runner.core.lines[0]

            # a file whose belt did not change keeps the queue
            (tmp_path / "note.txt").write_text("unrelated")
            out = await reloader.reload("test")
            assert out.applied, out.message
            assert daemon._runner.core.lines[0] is line
            assert len(line.queue) == 2

            # a belt refused by the judge: the running one stays, queue and all
            write({**belt, "window_mm": [900.0, 300.0]})
            out = await reloader.reload("test")
            assert not out.applied
            assert "window_mm" in out.message
            assert daemon._runner.core.lines[0] is line

            # a changed window: applied, a new queue on the new belt
            write({**belt, "window_mm": [300.0, 700.0]})
            out = await reloader.reload("test")
            assert out.applied, out.message
            assert any(d.startswith("conveyor.window_mm") for d in out.diff), out.diff
            now = daemon._runner.core.lines[0]
            assert now.queue.window_mm == (300.0, 700.0)
            assert len(now.queue) == 0
            words = await plc.request(Command.TRIGGER, count_at(frames[1]))
            assert (words[Reg.STATUS], words[Reg.QUEUED]) == (Status.OK, 2)

            # removed: the recipe's jobs are a standing part's again (no latch, no queue)
            write(None)
            out = await reloader.reload("test")
            assert out.applied, out.message
            assert daemon._runner.core.lines == {}
            assert daemon.snapshot()["conveyor"] == {}

            # added back: a conveyor again, its queue empty; NEXT answers from it
            write(belt)
            out = await reloader.reload("test")
            assert out.applied, out.message
            assert len(daemon._runner.core.lines[0].queue) == 0
            words = await plc.request(Command.NEXT, count_at(200.0))
            assert words[Reg.STATUS] == Status.NOT_FOUND
            assert daemon.snapshot()["conveyor"]["0"]["queued"] == 0
    finally:
        await reloader.close()
        await daemon.stop()
