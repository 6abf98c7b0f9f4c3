"""Conveyor tracking rules without I/O: the latch of a job and the part queue (docs/conveyor.md).

The latch says where the belt was at the exposure, in encoder counts, and where that number
came from (``LatchSource``, the value of the LATCH_SOURCE register):

- ``LINK`` (1): the PLC or robot latched the count with the trigger and wrote it with the
  request; error: the encoder's resolution.
- ``FRAME_ID`` (2): the camera is triggered by an encoder divider; the PLC reports the count it
  latched for each frame id (``FrameLatches``), matched with the frame's id from the camera.
- ``TIMESTAMP`` (3): no latch. The last count the link reported, carried to the exposure's
  device timestamp at the belt speed; the error is speed x the timestamps' uncertainty, stated
  with every result.

``PartQueue``: the parts seen, in belt order, each with its pose at its own latched count.
A part seen again in a later image (matched by its pose carried to the new count: position
within ``match_sigmas`` sigmas of the two positions' uncertainty, rotation within
``match_deg``) is counted a duplicate and not queued again; a part that leaves the pick window
downstream before it is served is dropped and counted; ``next`` serves the most downstream part
still in reach (the first to leave), once.
"""

from __future__ import annotations

import enum
import math
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from vgripd.geometry.belt import Belt
from vgripd.geometry.transforms import rotation_angle
from vgripd.types import FloatArray


class LatchSource(enum.IntEnum):
    NONE = 0  # no belt: the part stands still
    LINK = 1
    FRAME_ID = 2
    TIMESTAMP = 3


@dataclass(frozen=True)
class Latch:
    """The belt at a job's exposure: ``count``, its ``source`` and the one-sigma position
    error it leaves along the belt (mm)."""

    count: int
    source: LatchSource
    error_mm: float


def latch_from_link(belt: Belt, count: int) -> Latch:
    """Source (a): the count the peer latched and wrote with the trigger."""
    return Latch(count % (1 << belt.bits), LatchSource.LINK, 0.5 / belt.counts_per_mm)


def latch_from_timestamp(belt: Belt, count: int, t_count_ns: int, t_exposure_ns: int,
                         speed_mm_s: float, timestamp_error_ms: float) -> Latch:
    """Source (c): ``count`` reported at ``t_count_ns`` carried to the exposure at
    ``t_exposure_ns`` (one clock) at ``speed_mm_s``. Error: the speed times the timestamps'
    uncertainty, plus the encoder's resolution."""
    travel_mm = speed_mm_s * (t_exposure_ns - t_count_ns) * 1e-9
    carried = (count + round(travel_mm * belt.counts_per_mm)) % (1 << belt.bits)
    error = math.hypot(speed_mm_s * timestamp_error_ms * 1e-3, 0.5 / belt.counts_per_mm)
    return Latch(carried, LatchSource.TIMESTAMP, error)


class FrameLatches:
    """Source (b): counts the PLC latched per camera frame id, kept for the last ``keep``
    frames; ``match`` pairs a frame with its count, or says why it cannot."""

    def __init__(self, belt: Belt, keep: int = 64) -> None:
        self.belt = belt
        self.keep = keep
        self._counts: OrderedDict[int, int] = OrderedDict()

    def report(self, frame_id: int, count: int) -> None:
        self._counts[frame_id] = count % (1 << self.belt.bits)
        self._counts.move_to_end(frame_id)
        while len(self._counts) > self.keep:
            self._counts.popitem(last=False)

    def match(self, frame_id: int) -> Latch | None:
        count = self._counts.get(frame_id)
        if count is None:
            return None
        return Latch(count, LatchSource.FRAME_ID, 0.5 / self.belt.counts_per_mm)

    def missing(self, frame_id: int) -> str:
        known = list(self._counts)
        return (f"frame {frame_id}: no latched count from the PLC (latched frames "
                f"{known[0]}..{known[-1]})" if known else
                f"frame {frame_id}: no latched count from the PLC yet")


@dataclass
class QueuedPart:
    """A part in the queue: ``T_base_obj`` at ``count`` (its latch), the job that saw it."""

    uid: int
    T_base_obj: FloatArray
    count: int
    source: LatchSource
    error_mm: float
    job_id: int
    pick_id: int = 0
    score: float = -1.0
    sightings: int = 1

    def at(self, belt: Belt, count: int) -> FloatArray:
        """Its pose at ``count``."""
        return belt.moved(self.T_base_obj, self.count, count)


@dataclass(frozen=True)
class Added:
    """What one image added to the queue: the new parts and how many were seen before."""

    new: tuple[QueuedPart, ...]
    duplicates: int


@dataclass
class QueueStats:
    seen: int = 0
    duplicates: int = 0
    dropped: int = 0
    served: int = 0


@dataclass
class PartQueue:
    """The parts on the belt, ordered downstream first (docs/conveyor.md, "The part queue")."""

    belt: Belt
    window_mm: tuple[float, float]
    sigma_mm: float = 0.5
    match_sigmas: float = 6.0
    match_deg: float = 5.0
    parts: list[QueuedPart] = field(default_factory=list)
    #: Served parts still on the belt: a later image of one is a duplicate, not a new part.
    gone: list[QueuedPart] = field(default_factory=list)
    stats: QueueStats = field(default_factory=QueueStats)
    _uid: int = 0

    def along(self, part: QueuedPart, count: int) -> float:
        return self.belt.along_mm(part.at(self.belt, count)[:3, 3])

    def tolerance_mm(self, a: float, b: float) -> float:
        return self.match_sigmas * math.sqrt(2 * self.sigma_mm ** 2 + a ** 2 + b ** 2)

    def _same(self, part: QueuedPart, T: FloatArray, latch: Latch) -> bool:
        there = part.at(self.belt, latch.count)
        if np.linalg.norm(there[:3, 3] - T[:3, 3]) > self.tolerance_mm(part.error_mm,
                                                                       latch.error_mm):
            return False
        return math.degrees(rotation_angle(there[:3, :3].T @ T[:3, :3])) <= self.match_deg

    def add(self, latch: Latch, poses: Sequence[FloatArray], job_id: int,
            pick_ids: Sequence[int] = (), scores: Sequence[float] = ()) -> Added:
        """The parts one image found (``poses`` in the base frame at ``latch.count``)."""
        self.expire(latch.count)
        new: list[QueuedPart] = []
        dup = 0
        for i, T in enumerate(poses):
            self.stats.seen += 1
            known = next((p for p in [*self.parts, *self.gone, *new]
                          if self._same(p, T, latch)), None)
            if known is not None:
                known.sightings += 1
                dup += 1
                continue
            self._uid += 1
            new.append(QueuedPart(self._uid, np.array(T, dtype=np.float64), latch.count,
                                  latch.source, latch.error_mm, job_id,
                                  pick_ids[i] if i < len(pick_ids) else 0,
                                  scores[i] if i < len(scores) else -1.0))
        self.stats.duplicates += dup
        self.parts += new
        self.parts.sort(key=lambda p: -self.along(p, latch.count))
        return Added(tuple(new), dup)

    def expire(self, count: int) -> int:
        """Drop the parts past the window's downstream end at ``count``; how many."""
        down = self.window_mm[1]
        left = [p for p in self.parts if self.along(p, count) > down]
        self.parts = [p for p in self.parts if p not in left]
        self.gone = [p for p in self.gone if self.along(p, count) <= down + self.tolerance_mm(
            p.error_mm, p.error_mm)]
        self.gone += left
        self.stats.dropped += len(left)
        return len(left)

    def next(self, count: int) -> QueuedPart | None:
        """Serve the most downstream part still in reach at ``count`` (once), or None."""
        self.expire(count)
        if not self.parts:
            return None
        part = self.parts.pop(0)
        self.gone.append(part)
        self.stats.served += 1
        return part

    def __len__(self) -> int:
        return len(self.parts)
