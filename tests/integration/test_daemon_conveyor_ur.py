"""Conveyor tracking over UR RTDE: the daemon in-process with a conveyor recipe and a
``ur_rtde`` link with ``map_version = 4``; the robot is the mock UR controller (its own
process) running the twin of robots/urscript/vgripd.script's conveyor functions, talking to the
real ur_rtde client in the link's child process.

The belt and its truth are the shared conveyor cell (tests/integration/belt_cell.py): five parts
on a straight belt, images rendered at chosen travels, the 32-bit counter wrapping between the
second and the third image. The robot's encoder (``set_encoder``) stands at the image's count for
each locate: the latch goes with the trigger. Every answer is checked against the belt's truth
at the count it names: the grip pose the robot computes, RESULT_COUNT, LATCH_SOURCE,
LATCH_ERR_MM, ALONG/ACROSS/THETA, QUEUED; NEXT in belt order; the tracking routine's grip where
tracking starts and while the belt moves on; PREDICT's intercept, and past the window refused.
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.conftest import lo
from tests.integration.belt_cell import (
    COUNTS_PER_MM,
    WINDOW,
    check_belt_terms,
    conveyor_data,
    count_at,
    part_at,
    render,
    travel_of,
    visible,
)
from tests.integration.test_daemon import WAIT_S, running
from vgripd.config import config_from_dict
from vgripd.geometry.vendors import transform_from_vendor, vendor_from_transform
from vgripd.peer.jobcore import Command
from vgripd.service.links.protocol import LinkState
from vgripd.sim.ur_belt import tracked, travel_m
from vgripd.sim.ur_controller import URController
from vgripd.types import Status
from vgripd.vision.scene import T_base_obj_ref

pytestmark = [pytest.mark.timeout(300), pytest.mark.slow]

TICKS_PER_M = COUNTS_PER_MM * 1000.0  # track_conveyor_linear's ticks_per_meter
DIRECTION = (1.0, 0.0, 0.0)


def ur_config(folder: Path, host: str) -> Any:
    data = conveyor_data({"type": "replay", "folder": str(folder), "left_glob": "left_*.png",
                          "right_glob": "right_*.png"})
    data["links"] = [{"type": "ur_rtde", "host": host, "map_version": 4}]
    data["output"] = {"vendor": "ur"}
    return config_from_dict(data)


def grip_of(result: dict[str, Any], key: str = "target") -> np.ndarray:
    """The robot's grip pose (``pose_trans(offset, taught)``) as a base-frame transform, mm."""
    return transform_from_vendor("ur", result[key])


def check_belt(result: dict[str, Any], travel_mm: float, source: int = 1) -> int:
    """The answer's grip is a part's true pose at ``travel_mm``; its belt block agrees."""
    belt = result["belt"]
    assert belt["count"] == count_at(travel_mm)
    assert belt["source"] == source
    part = part_at(grip_of(result), travel_mm)
    check_belt_terms(part, travel_mm, belt["along_mm"], belt["across_mm"], belt["theta_deg"])
    return part


async def test_a_ur_robot_latches_tracks_and_intercepts_across_the_wrap(
        tmp_path: Path) -> None:
    frames = [0.0, 150.0, 300.0, 450.0]
    await render(tmp_path, frames)
    assert count_at(frames[1]) > count_at(frames[2])  # the counter wraps between them
    with URController(lo("127.0.9.41")) as robot:
        config = ur_config(tmp_path, robot.host)
        taught = vendor_from_transform("ur", T_base_obj_ref(config))  # the grip taught

        async def locate(frame: int) -> dict[str, Any]:
            robot.set_encoder(count_at(frames[frame]))  # the belt at the trigger
            seq = robot.start_program(1, taught_pose=taught, conveyor=True)
            return await asyncio.to_thread(robot.program_result, seq, WAIT_S)

        async def track(travel_now: float) -> dict[str, Any]:
            robot.set_encoder(count_at(travel_now))
            return await asyncio.to_thread(robot.belt_track, taught, DIRECTION, TICKS_PER_M,
                                           timeout_s=WAIT_S)

        async with running(config) as run:
            link = next(iter(run.daemon.rooms.links.links.values()))
            await run.daemon.wait_for(lambda: link.health().state is LinkState.UP, WAIT_S)
            served = []
            for frame in range(3):
                result = await locate(frame)
                assert result["error"] is None
                assert result["status"] == Status.OK, result
                assert check_belt(result, frames[frame]) in visible(frames[frame])
                assert result["belt"]["error_mm"] == pytest.approx(0.5 / COUNTS_PER_MM)
                _, record = await run.job_done(frame + 1)
                assert record.result.belt is not None
                assert record.result.belt.count == count_at(frames[frame])  # the trigger's
                if frame == 0:
                    assert result["belt"]["queued"] == 2  # parts 0 and 1

            # NEXT at travel 350: part 0 is past the window's end (1000 mm), part 1 is served,
            # its grip at its own latched count; the routine carries it to the count now, where
            # tracking starts, and the controller moves it with the belt from there.
            result = await track(350.0)
            assert result["status"] == Status.OK, result
            at = travel_of(result["belt"]["count"])
            assert at in frames
            part = check_belt(result, at)
            served.append(part)
            assert result["start_count"] & 0xFFFFFFFF == count_at(350.0)
            start = transform_from_vendor("ur", result["start_grip"])
            assert part_at(start, 350.0) == part
            for later in (351.5, 362.0, 395.0):
                moved = tracked(result["start_grip"], result["start_count"],
                                count_at(later), DIRECTION, TICKS_PER_M)
                assert part_at(transform_from_vendor("ur", moved), later) == part

            # The fixed station's intercept: NEXT, then PREDICT for 30 mm of travel ahead.
            robot.set_encoder(count_at(360.0))
            lead = round(30.0 * COUNTS_PER_MM)
            result = await asyncio.to_thread(robot.belt_intercept, taught, lead,
                                             timeout_s=WAIT_S)
            assert result["next"]["status"] == Status.OK
            served.append(check_belt(result["next"], travel_of(
                result["next"]["belt"]["count"])))
            assert result["predict_count"] == count_at(390.0)
            assert result["status"] == Status.OK, result
            assert check_belt(result, 390.0) == served[-1]

            # PREDICT for a count past the window's end: refused, no pose.
            robot.set_predict_count(count_at(WINDOW[1] + 100.0))
            seq = robot.start_program(int(Command.PREDICT), taught_pose=taught, conveyor=True)
            result = await asyncio.to_thread(robot.program_result, seq, WAIT_S)
            assert (result["status"], result["offset"]) == (Status.OUT_OF_WORKSPACE, None)
            assert result["belt"]["count"] == count_at(WINDOW[1] + 100.0)

            # the last image, then the queue in belt order until it is empty
            assert (await locate(3))["status"] == Status.OK
            while (result := await track(455.0))["status"] == Status.OK:
                served.append(check_belt(result, travel_of(result["belt"]["count"])))
            assert result["status"] == Status.NOT_FOUND
            assert result["belt"]["queued"] == 0
            conveyor = run.daemon.snapshot()["conveyor"]["0"]
    assert served == [1, 2, 3, 4]  # each part once, downstream first; part 0 missed
    assert (conveyor["dropped"], conveyor["served"]) == (1, 4)


def test_travel_across_the_counters_wrap() -> None:
    """The script's vgripd_belt_travel: the shorter way round the 32-bit counter."""
    top = (1 << 31) - 5  # int32 bits just below the signed wrap
    assert travel_m(top, -(1 << 31) + 5, 1000.0) == pytest.approx(0.010)
    assert travel_m(-(1 << 31) + 5, top, 1000.0) == pytest.approx(-0.010)
    assert travel_m(65530, 4, 1000.0, bits=16) == pytest.approx(0.010)
