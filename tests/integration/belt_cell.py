"""The conveyor cell the conveyor tests share: a belt simulated independently of the code under
test (five parts at known places along a straight belt at count ``COUNT0``), its truth at any
travel, images rendered at chosen travels by the synthetic camera's renderer, the daemon's
config for it, and the map version 4 PLC (a real pymodbus client) that latches the count with
every request. Each link's conveyor test drives this one belt."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from tests.integration.test_daemon import CODEC, Plc, values
from vgripd.config import Config, config_from_dict
from vgripd.geometry.vendors import transform_from_vendor
from vgripd.peer.registers import Reg
from vgripd.registry import CAMERAS, load_class, validate_options

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
        # a job's budget for a test machine running two suites (10 s was exceeded once there)
        "daemon": {"worker": False, "job_timeout_s": 60.0},
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


def part_at(T: np.ndarray, travel_mm: float) -> int:
    """The part whose true pose at ``travel_mm`` the base-frame pose ``T`` (mm) is, checked to
    1 mm and 0.5 deg."""
    near, mm, deg = part_of(T, travel_mm)
    assert mm < 1.0, (near, travel_mm, T[:3, 3])
    assert deg < 0.5
    return near


def check_belt_terms(part: int, travel_mm: float, along: float, across: float,
                     theta: float) -> None:
    """ALONG/ACROSS/THETA of an answer against the part's truth at ``travel_mm``."""
    x, y, angle = PARTS[part]
    assert along == pytest.approx(x + travel_mm, abs=1.0)
    assert across == pytest.approx(y, abs=1.0)
    assert theta == pytest.approx(angle, abs=0.5)


def which(words: list[int], travel_mm: float, T_ref: np.ndarray) -> int:
    """The part whose true pose at ``travel_mm`` the answer's pose is (checked to 1 mm and
    0.5 deg), its belt terms checked too."""
    T_offset = transform_from_vendor("kuka", values(words))
    T = T_offset @ T_ref  # output.mode offset: T_base_obj = T_offset @ T_base_obj_ref
    near = part_at(T, travel_mm)
    check_belt_terms(near, travel_mm, f32(words, Reg.ALONG), f32(words, Reg.ACROSS),
                     f32(words, Reg.THETA))
    return near


def travel_of(count: int) -> float:
    return ((count - COUNT0) % (1 << 32)) / COUNTS_PER_MM


def part_of(T_base_obj: np.ndarray, travel_mm: float) -> tuple[int, float, float]:
    """The part nearest to an object pose in the base frame after ``travel_mm`` of belt travel:
    its index, the position error (mm) and the rotation error (deg) against its truth."""
    near = min(range(len(PARTS)),
               key=lambda k: float(np.linalg.norm(truth(k, travel_mm)[:3, 3] - T_base_obj[:3, 3])))
    want = truth(near, travel_mm)
    turn = math.degrees(math.acos(np.clip((np.trace(want[:3, :3].T @ T_base_obj[:3, :3]) - 1) / 2,
                                          -1, 1)))
    return near, float(np.linalg.norm(want[:3, 3] - T_base_obj[:3, 3])), turn


def located(pose: list[float], along: float, across: float, theta: float, travel_mm: float,
            T_ref: np.ndarray) -> int:
    """``which`` for a link that shows the pose as KUKA values and the belt terms as numbers of
    their own (OPC UA variables, socket fields): the part whose true pose at ``travel_mm`` the
    answer is (1 mm, 0.5 deg), its belt terms checked too."""
    T = transform_from_vendor("kuka", pose) @ T_ref  # output.mode offset
    near = part_at(T, travel_mm)
    check_belt_terms(near, travel_mm, along, across, theta)
    return near
