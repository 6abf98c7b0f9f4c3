"""The generated programs' conveyor routines (docs/robot_socket.md, "Conveyor"), run by their
twins against the daemon with a conveyor recipe: parts picked off the shared conveyor cell's
belt (tests/integration/belt_cell.py), simulated here independently of the code under test.

- The intercept routine (robots without a tracking option): NEXT at the count now, PREDICT
  ``lead`` counts ahead, the arm moves there, the belt runs on until the encoder reaches that
  count, grip. The pick error is the gripped pose against the part's truth at the grip count.
- The tracking routine: NEXT at the count now hands the pose and its RESULT_COUNT to the
  controller's own tracking, simulated here from the test's belt (the controller's conveyor
  calibration), which the arm follows until the part reaches the grip line.

Every robot-socket brand but UR (whose conveyor runs over RTDE, docs/ur_rtde.md) is run
(``BELT_BRANDS``); the twin reads each program's own command words from its text, and
``INTERCEPT`` checks that each program's intercept does the twin's steps in the twin's order."""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.integration.belt_cell import (
    COUNTS_PER_MM,
    conveyor_data,
    count_at,
    part_of,
    render,
    travel_of,
)
from tests.integration.test_daemon import running
from tests.integration.test_robot_programs import free_port, program
from vgripd.config import config_from_dict
from vgripd.peer.socket_frames import BRANDS, COUNTED_SIZE
from vgripd.sim.arm import SimulatedArm
from vgripd.sim.robot_socket_client import ProgramSettings, ProgramTwin
from vgripd.types import Status
from vgripd.vision.scene import T_base_obj_ref

pytestmark = pytest.mark.timeout(300)
BELT_BRANDS = ["kuka", "abb", "fanuc", "staubli", "yaskawa"]
#: Each program's intercept, per file, in the order the program does it: NEXT at the count
#: now, PREDICT at now + lead, the move to the predicted grip, the wait for that count.
INTERCEPT = {
    "kuka": {"vgripd.src": ["vgSt = vgNextAt(VG_ENCODER)", "vgN = VG_ENCODER + vgLead",
                            "vgSt = vgPredict(vgN)", "LIN vgOffset : vgGrip",
                            "IF VG_ENCODER - vgN >= 0 THEN"]},
    "abb": {"VgripdSocket.mod": ["vgStatus := vgNextAt(vgEncoderNow());",
                                 "vgN := vgEncoderNow() + vgLead;",
                                 "vgStatus := vgPredict(vgN);",
                                 "vgP := PoseMult(vgOffset, [vgGrip.trans, vgGrip.rot]);",
                                 "MoveL vgTarget, vgSpeed, fine, vgTool",
                                 "WHILE NOT vgReached(vgEncoderNow(), vgN) DO"]},
    "fanuc": {"VG_CATCH.ls": ["CALL VGRIPD(0,7,AR[1])", "L PR[52] 500mm/sec FINE Offset,PR[50]",
                              "CALL VGRIPD(0,8)"],
              "vgripd.kl": ["vg_cmd = VG_NEXT_AT -- the next part at the count now",
                            "vg_count = vg_reg(VG_REG + 19)",
                            "WHILE NOT vg_reached(vg_reg(VG_REG + 19), vg_reg(VG_REG + 12)) DO",
                            "vg_cmd = VG_PREDICT -- the intercept",
                            "vg_count = vg_plus(vg_reg(VG_REG + 19), vg_arg)"]},
    "staubli": {"vgIntercept.pgx": ["call vgNextAt(aioGet(vgEncoder), x_vgStatus)",
                                    "l_vgN = aioGet(vgEncoder) + x_vgLead",
                                    "call vgPredict(l_vgN, x_vgStatus)",
                                    "movel(l_vgTarget, x_vgTool, x_vgDesc)",
                                    "l_vgD = aioGet(vgEncoder) - l_vgN"]},
    "yaskawa": {"VGCATCH.JBI": ["SET I054 5", "MOVL P051", "SET I054 6"],
                "vgripd_task.c": ["vgCount = vgEncoderNow();\n    vgStatus = vgAsk(VG_NEXT_AT, 0, 0);",
                                  "vgCount = (LONG)((unsigned int)vgEncoderNow() + (unsigned int)"
                                  "vgGet(MP_RESTYPE_VAR_D, VG_VAR + 9));\n    return vgAsk(VG_PREDICT",
                                  ]},
}
PICK_MM, PICK_DEG = 1.0, 0.5  # the allowed pick error (the cell's pose check)


class Belt:
    """The belt's encoder: a count that only the test moves."""

    def __init__(self, travel_mm: float) -> None:
        self.c = count_at(travel_mm)

    def count(self) -> int:
        return self.c

    def advance(self, counts: int) -> None:
        self.c = (self.c + counts) % (1 << 32)


class Tracker:
    """A controller's conveyor tracking, set up from the test's own belt (direction +x,
    COUNTS_PER_MM): a target taken at one count moves with the belt to any later count."""

    def __init__(self, T_ref: np.ndarray, grip_along_mm: float, step_counts: int) -> None:
        self.T_ref = T_ref
        self.grip_along_mm = grip_along_mm
        self.step_counts = step_counts

    def moved(self, T: np.ndarray, count_from: int, count_to: int) -> np.ndarray:
        out = np.array(T, dtype=float)
        out[0, 3] += ((count_to - count_from) % (1 << 32)) / COUNTS_PER_MM
        return out

    def along_mm(self, T_offset: np.ndarray) -> float:
        return float((T_offset @ self.T_ref)[0, 3])


def belt_cell(brand: str, folder: Path, port: int) -> dict[str, Any]:
    b = BRANDS[brand]
    data = conveyor_data({"type": "replay", "folder": str(folder), "left_glob": "left_*.png",
                          "right_glob": "right_*.png"})
    data["output"] = {"vendor": b.convention}
    data["links"] = [{"type": "robot_socket", "host": "127.0.0.1", "port": port,
                      "mode": b.mode, "value_format": b.value_format, "scale": 10000}]
    data["daemon"]["job_timeout_s"] = 30.0
    return data


def pick_error(arm: SimulatedArm, T_ref: np.ndarray, count: int) -> tuple[int, float, float]:
    """The part under the gripper at ``count`` and how far the grip is from it (mm, deg)."""
    return part_of(arm.T_true @ T_ref, travel_of(count))


@pytest.mark.parametrize("brand", BELT_BRANDS)
async def test_the_intercept_and_tracking_routines_pick_parts_off_the_belt(
        brand: str, tmp_path: Path) -> None:
    await render(tmp_path, [0.0, 150.0])
    port = free_port()
    data = belt_cell(brand, tmp_path, port)
    settings = ProgramSettings.parse(brand, program(brand, data))
    config = config_from_dict(data)
    T_ref = T_base_obj_ref(config)
    belt = Belt(0.0)
    arm = SimulatedArm(np.eye(4), reach_mm=5000.0, settle_cycles=3)
    # the twin first: the Yaskawa task listens and vgripd dials it
    async with ProgramTwin(settings, "127.0.0.1", port) as twin, running(config):
        for travel in (0.0, 150.0):  # a camera trigger every 150 mm, the count latched with it
            while travel_of(belt.count()) < travel:
                belt.advance(10)
            out = await twin.locate_at(0, belt.count())
            assert out.status == Status.OK, out
            assert out.belt is not None
            assert out.belt[:2] == (belt.count(), 1)
        # intercept: part 0 (at 850 mm now) predicted 100 mm ahead, the grip there at that count
        out, gripped = await twin.intercept(belt, arm, lead=round(100 * COUNTS_PER_MM))
        assert out.status == Status.OK, out
        assert out.belt is not None
        assert out.belt[0] == gripped == count_at(250.0)
        part, mm, deg = pick_error(arm, T_ref, gripped)
        assert part == 0
        assert mm < PICK_MM
        assert deg < PICK_DEG
        # tracking: part 1 taken at its own latched count, followed until it is at 900 mm
        tracker = Tracker(T_ref, grip_along_mm=900.0, step_counts=50)
        out, gripped = await twin.track(belt, arm, tracker)
        assert out.status == Status.OK, out
        assert out.belt is not None
        assert travel_of(out.belt[0]) in (0.0, 150.0)  # the image's count, not the count now
        part, mm, deg = pick_error(arm, T_ref, gripped)
        assert part == 1
        assert mm < PICK_MM
        assert deg < PICK_DEG
        assert tracker.along_mm(arm.T_true) >= 900.0
    counted = [f for f in twin.sent if len(f) == COUNTED_SIZE]
    words = {struct.unpack(">I", f[:4])[0] for f in counted}
    assert words == {settings.belt_words[k] for k in ("LOCATE_AT", "NEXT_AT", "PREDICT")}


@pytest.mark.parametrize("brand", BELT_BRANDS)
def test_each_programs_intercept_does_the_twins_steps_in_order(brand: str) -> None:
    """What the twin's ``intercept`` does is what the program text does: NEXT at the count
    now, PREDICT ``lead`` counts later, the move, the wait for the count, in that order."""
    texts = program(brand, belt_cell(brand, Path("/nonexistent"), 50100))
    for name, steps in INTERCEPT[brand].items():
        text = texts[name]
        at = -1
        for step in steps:
            found = text.find(step, at + 1)
            assert found > at, f"{brand} {name}: {step!r} not after the step before it"
            at = found
