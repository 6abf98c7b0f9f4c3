"""A conveyor cell run in belt time: the PLC triggers an image every trigger distance and
writes the latched count; a robot twin takes the queued parts with NEXT, asks PREDICT where
each will be when it gets there, and picks it at that later count. Every pick is judged
against the simulated belt's truth (``vgripd.sim.conveyor``), never against the daemon's own
numbers.

The belt's time is simulated: the belt stands while the daemon works, and the PLC and the
robot act at the belt counts of their moments in belt time (the order of events is that of a
real cell at the belt's speed). The robot plans with what the daemon tells it, as a
controller does: the part's ALONG at RESULT_COUNT carried to the count now; it picks
``approach_s`` later (or when the part enters the pick window, if it is upstream of it), then
needs ``place_s`` to put the part down and come back.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from vgripd.geometry.transforms import pose_error
from vgripd.geometry.vendors import transform_from_vendor
from vgripd.peer.jobcore import Command
from vgripd.sim.conveyor import BeltAnswer, BeltPlc, SimBelt
from vgripd.types import FloatArray, Status

#: A pick farther than this from every true part took nothing (mm).
GHOST_MM = 10.0


@dataclass(frozen=True)
class RobotTiming:
    """The robot twin's motion times (s): from NEXT to the grip, and from the grip back."""

    approach_s: float = 0.4
    place_s: float = 0.5


@dataclass(frozen=True)
class Pick:
    """One grip: the true part taken (-1: none within ``GHOST_MM``), the belt travel at the
    grip, and the grip pose's error against that part's truth there (mm, deg)."""

    part: int
    travel_mm: float
    error_mm: float
    error_deg: float
    along_error_mm: float


@dataclass
class BeltRun:
    """What happened on the belt, in truth."""

    parts: int
    frames: list[float] = field(default_factory=list)  # travel of each image (mm)
    shown: list[list[int]] = field(default_factory=list)  # true parts drawn in each image
    picks: list[Pick] = field(default_factory=list)
    late: int = 0  # parts served whose predicted grip lay past the window (PREDICT refused)
    answers: list[BeltAnswer] = field(default_factory=list)  # the TRIGGER answers

    @property
    def seen(self) -> set[int]:
        return {k for shown in self.shown for k in shown}

    def taken(self) -> dict[int, int]:
        out: dict[int, int] = {}
        for p in self.picks:
            if p.part >= 0:
                out[p.part] = out.get(p.part, 0) + 1
        return out

    @property
    def picked_once(self) -> int:
        return sum(1 for n in self.taken().values() if n == 1)

    @property
    def duplicated(self) -> int:
        """Parts gripped more than once (the second grip finds nothing)."""
        return sum(1 for n in self.taken().values() if n > 1)

    @property
    def ghosts(self) -> int:
        return sum(1 for p in self.picks if p.part < 0)

    @property
    def missed(self) -> int:
        return self.parts - len(self.taken())

    def errors(self) -> FloatArray:
        """(n, 3): position, rotation and along-the-belt error of each true grip."""
        return np.array([(p.error_mm, p.error_deg, p.along_error_mm)
                         for p in self.picks if p.part >= 0]).reshape(-1, 3)


#: The count (and frame id) the PLC writes with the trigger of image ``i`` rendered at travel
#: ``travel_mm``: a hardware latch writes the count of the exposure itself.
LatchFn = Callable[[int, float], tuple[int, int | None]]


async def run_belt(plc: BeltPlc, belt: SimBelt, frames: list[float], speed_mm_s: float,
                   window_mm: tuple[float, float], T_ref: FloatArray, vendor: str,
                   timing: RobotTiming = RobotTiming(), latch: LatchFn | None = None,
                   shown: list[list[int]] | None = None) -> BeltRun:
    """Run the cell over ``frames`` (the travel of each image, rendered beforehand).

    ``T_ref``: the taught reference (the answers are offsets, ``T_base_obj = T_offset @
    T_ref``); ``vendor``: the answers' convention. The run ends when every part is past the
    window's downstream end."""
    run = BeltRun(len(belt.parts), list(frames), list(shown or []))
    latch = latch or (lambda i, travel: (belt.count_at(travel), None))
    end_mm = window_mm[1] - min(p.along_mm for p in belt.parts) + 1.0
    t_frames = [f / speed_mm_s for f in frames]
    k, robot_t = 0, 0.0
    while robot_t * speed_mm_s <= end_mm:
        if k < len(frames) and t_frames[k] <= robot_t:
            count, frame = latch(k, frames[k])
            run.answers.append(await plc.request(Command.TRIGGER, count, frame))
            k += 1
            continue
        now = robot_t * speed_mm_s
        got = await plc.request(Command.NEXT, belt.count_at(now))
        if got.cycle.status is Status.NOT_FOUND:
            if k >= len(frames):
                break
            robot_t = t_frames[k]  # wait for the next image
            continue
        if not got.cycle.status.pose_valid:
            raise RuntimeError(f"NEXT answered {got.cycle.status.name}")
        # the robot's plan, from the daemon's numbers: where the part is now, when to grip
        along_now = got.along_mm + belt.travel_of(belt.count_at(now)) - belt.travel_of(
            got.result_count)
        wait_s = max(timing.approach_s, (window_mm[0] - along_now) / speed_mm_s)
        t_pick = robot_t + wait_s
        count = belt.count_at(t_pick * speed_mm_s)
        pred = await plc.request(Command.PREDICT, count)
        if pred.cycle.status is not Status.OK:
            run.late += 1  # past the window at the grip: the robot leaves it
            robot_t += 0.05
            continue
        run.picks.append(judge(belt, pred, count, T_ref, vendor))
        robot_t = t_pick + timing.place_s
    return run


def judge(belt: SimBelt, answer: BeltAnswer, count: int, T_ref: FloatArray,
          vendor: str) -> Pick:
    """The grip ``answer`` (PREDICT's, at ``count``) against the nearest true part there."""
    T = transform_from_vendor(vendor, list(answer.cycle.values)) @ T_ref
    travel = belt.travel_of(count)
    near = min(range(len(belt.parts)),
               key=lambda k: float(np.linalg.norm(belt.truth(k, travel)[:3, 3] - T[:3, 3])))
    truth = belt.truth(near, travel)
    dt, dr = pose_error(truth, T)
    if dt > GHOST_MM:
        return Pick(-1, travel, dt, dr, math.nan)
    along = float((T[:3, 3] - truth[:3, 3]) @ belt.frame[:3, 0])
    return Pick(near, travel, dt, dr, along)
