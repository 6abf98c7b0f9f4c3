"""Conveyor tracking rules without I/O: the latch of a job and the part queue (docs/conveyor.md).

The latch says where the belt was at the exposure, in encoder counts, and where that number
came from (``LatchSource``, the value of the LATCH_SOURCE register):

- ``LINK`` (1): the PLC or robot latched the count with the trigger and wrote it with the
  request; error: the encoder's resolution.
- ``FRAME_ID`` (2): the camera is triggered by an encoder divider; the PLC reports the count it
  latched for each frame id (``FrameLatches``), matched with the frame's id from the camera.
- ``TIMESTAMP`` (3): no latch. The last count the link reported, carried to the exposure's
  device timestamp at the belt speed; the error is speed x the timestamps' uncertainty, stated
  with every result. Where the link publishes the count all the time (``conveyor.trigger =
  "travel"``) the counts read just before and after the exposure are interpolated instead
  (``latch_from_counts``), at the speed they show.

``PartQueue``: the parts seen, in belt order, each with its pose at its own latched count.
A part seen again in a later image (matched by its pose carried to the new count: position
within ``match_sigmas`` sigmas of the two positions' uncertainty, rotation within
``match_deg``) is counted a duplicate and not queued again; a part that leaves the pick window
downstream before it is served is dropped and counted; ``next`` serves the most downstream part
still in reach (the first to leave), once.
"""

from __future__ import annotations

import bisect
import dataclasses
import enum
import math
from collections import OrderedDict, deque
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from vgripd.config import ConveyorConfig
from vgripd.geometry.belt import Belt, count_delta
from vgripd.geometry.transforms import rotation_angle
from vgripd.geometry.vendors import target_from_transform, transform_from_vendor
from vgripd.peer.belttravel import TravelRule
from vgripd.types import BeltPose, FloatArray, JobResult, PickInstance, Status


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


#: The longest gap (ns) between the two counts read around an exposure that is still
#: interpolated; a longer one leaves the exposure to the timestamp rule.
MAX_BRACKET_NS = 1_000_000_000


def latch_from_counts(belt: Belt, samples: Sequence[tuple[int, int]], t_exposure_ns: int,
                      timestamp_error_ms: float) -> Latch | None:
    """Source (c) where the link publishes the count continuously (``conveyor.trigger =
    "travel"``): the counts read just before and just after the exposure, ``samples`` of
    ``(t_mono_ns, count)`` in time order, interpolated to ``t_exposure_ns``. Error: the belt's
    speed between them times the timestamps' uncertainty, plus the encoder's resolution.
    None without a reading on both sides within ``MAX_BRACKET_NS``."""
    i = bisect.bisect_right(samples, t_exposure_ns, key=lambda s: s[0])
    if i == 0 or i == len(samples):
        return None
    (t0, c0), (t1, c1) = samples[i - 1], samples[i]
    if t1 - t0 > MAX_BRACKET_NS:
        return None
    delta = count_delta(c0, c1, belt.bits)
    frac = (t_exposure_ns - t0) / (t1 - t0) if t1 > t0 else 0.0
    count = (c0 + round(delta * frac)) % (1 << belt.bits)
    speed_mm_s = abs(delta) / belt.counts_per_mm / max((t1 - t0) * 1e-9, 1e-9)
    error = math.hypot(speed_mm_s * timestamp_error_ms * 1e-3, 0.5 / belt.counts_per_mm)
    return Latch(count, LatchSource.TIMESTAMP, error)


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
    """A part in the queue: ``T_base_obj`` at ``count`` (its latch), the job that saw it, and
    ``T_target`` (what the robot is told: the offset or grip transform of ``output.mode``; the
    part's pose when None). The belt carries both by the same translation."""

    uid: int
    T_base_obj: FloatArray
    count: int
    source: LatchSource
    error_mm: float
    job_id: int
    pick_id: int = 0
    score: float = -1.0
    sightings: int = 1
    T_target: FloatArray | None = None

    def at(self, belt: Belt, count: int) -> FloatArray:
        """Its pose at ``count``."""
        return belt.moved(self.T_base_obj, self.count, count)

    def target_at(self, belt: Belt, count: int) -> FloatArray:
        """Its target transform at ``count``."""
        T = self.T_base_obj if self.T_target is None else self.T_target
        return belt.moved(T, self.count, count)


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
            pick_ids: Sequence[int] = (), scores: Sequence[float] = (),
            targets: Sequence[FloatArray] = ()) -> Added:
        """The parts one image found (``poses`` in the base frame at ``latch.count``; their
        ``targets``, when given, are what the robot is told)."""
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
                                  scores[i] if i < len(scores) else -1.0,
                                  T_target=(np.array(targets[i], dtype=np.float64)
                                            if i < len(targets) else None)))
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


# --- one conveyor recipe in the daemon ------------------------------------------------------

#: Counts read kept per travel-triggered line: 40 s at a 10 ms poll.
COUNT_SAMPLES = 4096

LATCH_KINDS = {"link": LatchSource.LINK, "frame_id": LatchSource.FRAME_ID,
               "timestamp": LatchSource.TIMESTAMP}


def belt_pose(belt: Belt, T_base: FloatArray, count: int, source: LatchSource, error_mm: float,
              queued: int) -> BeltPose:
    """``T_base`` (at ``count``) in belt terms: along, across (mm) and the rotation about the
    belt's normal (deg) of its x axis projected into the belt plane."""
    T = belt.in_belt(T_base)
    theta = math.degrees(math.atan2(T[1, 0], T[0, 0]))
    return BeltPose(count, int(source), error_mm, float(T[0, 3]), float(T[1, 3]), theta,
                    queued)


@dataclass
class BeltLine:
    """One conveyor recipe as the daemon runs it (docs/conveyor.md): each job's latch, its
    parts into the ``PartQueue``, NEXT served from the queue in belt order and PREDICT (a
    served part's pose at a later count). The queue places each part by its pose
    (``T_base_obj``: the window, the match, ALONG/ACROSS/THETA) and tells the robot its
    target (``output.vendor`` and ``output.mode``: an offset or a grip), both moved along the
    belt by the same travel."""

    belt: Belt
    queue: PartQueue
    vendor: str
    latch_kind: LatchSource = LatchSource.LINK
    speed_mm_s: float = 0.0
    timestamp_error_ms: float = 0.0
    frames: FrameLatches | None = None
    #: The part last served to each link (PREDICT predicts it).
    served: dict[str, QueuedPart] = field(default_factory=dict)
    #: The newest count any job or request reported (a NEXT without a count expires with it).
    last_count: int | None = None
    #: ms from each image's exposure to its parts' entry in the queue (the last 1000).
    latency_ms: deque[float] = field(default_factory=lambda: deque(maxlen=1000))
    #: ``trigger = "travel"``: when to take an image, and the counts the link published
    #: (``(t_mono_ns, count)``, the newest ``COUNT_SAMPLES``) that latch each image.
    travel: TravelRule | None = None
    counts: deque[tuple[int, int]] = field(default_factory=lambda: deque(maxlen=COUNT_SAMPLES))

    def count_read(self, count: int, t_ns: int) -> None:
        """A count the link published (``trigger = "travel"``): the newest count, kept."""
        self.counts.append((t_ns, count % (1 << self.belt.bits)))
        self.last_count = count % (1 << self.belt.bits)

    def latch(self, count: int | None, frame: int | None, t_request_ns: int,
              t_exposure_ns: int, frame_seen: int | None) -> Latch | str:
        """The latch of a job, or why there is none (the job's BAD_REQUEST message).

        ``count``/``frame``: what the link carried with the request; ``t_request_ns``: when
        the request came; ``t_exposure_ns``: the image's time (one clock); ``frame_seen``:
        the camera's frame id of the image (None when the camera reports none)."""
        if count is None:
            return ("conveyor: the link carries no encoder count with the request (Modbus, "
                    "RTU, S7 and UR RTDE: map_version = 4 and LATCH_COUNT written; robot "
                    "socket: a counted request; OPC UA: LatchCount written before the call)")
        if self.latch_kind is LatchSource.LINK:
            return latch_from_link(self.belt, count)
        if self.latch_kind is LatchSource.TIMESTAMP:
            read = latch_from_counts(self.belt, self.counts, t_exposure_ns,
                                     self.timestamp_error_ms) if self.travel else None
            return read or latch_from_timestamp(self.belt, count, t_request_ns, t_exposure_ns,
                                        self.speed_mm_s, self.timestamp_error_ms)
        if self.frames is None:
            self.frames = FrameLatches(self.belt)
        if frame is not None:
            self.frames.report(frame, count)
        if frame_seen is None:
            return "conveyor latch frame_id: the camera reports no frame id for its image"
        return self.frames.match(frame_seen) or self.frames.missing(frame_seen)

    def add(self, latch: Latch, result: JobResult) -> JobResult:
        """A job's parts into the queue; its answer with the latch and the first part in
        belt terms (``BeltPose.queued``: the queue's length after it)."""
        self.last_count = latch.count
        poses: list[FloatArray] = []  # where each part is (the belt's geometry)
        targets: list[FloatArray] = []  # what the robot is told (output.mode)
        pick_ids: list[int] = []
        scores: list[float] = []
        shown = [i for i in result.instances if i.status.pose_valid and i.target is not None
                 and i.T_base_obj is not None]
        if shown:
            for inst in shown:
                assert inst.target is not None
                assert inst.T_base_obj is not None
                poses.append(np.asarray(inst.T_base_obj, dtype=np.float64))
                targets.append(transform_from_vendor(inst.target.vendor, inst.target.values))
                pick_ids.append(inst.pick_id)
                scores.append(inst.score)
        elif (result.status.pose_valid and result.target is not None
              and result.T_base_obj is not None):
            poses.append(np.asarray(result.T_base_obj, dtype=np.float64))
            targets.append(transform_from_vendor(result.target.vendor, result.target.values))
        self.queue.add(latch, poses, result.job_id, pick_ids, scores, targets)
        first = belt_pose(self.belt, poses[0], latch.count, latch.source, latch.error_mm,
                          len(self.queue)) if poses else \
            BeltPose(latch.count, int(latch.source), latch.error_mm, queued=len(self.queue))
        return dataclasses.replace(result, belt=first)

    def _answer(self, part: QueuedPart, count: int, now_ns: int, message: str) -> JobResult:
        T = part.at(self.belt, count)
        target = target_from_transform(self.vendor, part.target_at(self.belt, count))
        inst = PickInstance(Status.OK, message, target, T, pick_id=part.pick_id,
                            score=max(part.score, 0.0))
        return JobResult(job_id=part.job_id, status=Status.OK, message=message, target=target,
                         T_base_obj=T, instances=(inst,), t_done_mono_ns=now_ns,
                         belt=belt_pose(self.belt, T, count, part.source, part.error_mm,
                                        len(self.queue)))

    def _empty(self, status: Status, why: str, count: int | None, now_ns: int) -> JobResult:
        belt = BeltPose(count or 0, 0, 0.0, queued=len(self.queue))
        return JobResult(job_id=0, status=status, message=why, t_done_mono_ns=now_ns, belt=belt)

    def _seen(self, count: int | None) -> int | None:
        if count is not None:
            self.last_count = count
        return self.last_count

    def next(self, link: str, count: int | None, now_ns: int) -> JobResult:
        """NEXT: the most downstream part still in the window at ``count`` (the request's;
        else the newest known), its pose at its own latched count (a tracking controller
        adds the travel since); ``NOT_FOUND`` when the queue has none."""
        at = self._seen(count)
        if at is None:
            return self._empty(Status.NOT_FOUND, "conveyor: no image latched yet", None,
                               now_ns)
        part = self.queue.next(at)
        if part is None:
            return self._empty(Status.NOT_FOUND, "conveyor: the part queue is empty", at, now_ns)
        self.served[link] = part
        return self._answer(part, part.count, now_ns, f"part {part.uid} of job {part.job_id}")

    def predict(self, link: str, count: int | None, now_ns: int) -> JobResult:
        """PREDICT: where the part last served to ``link`` will be at ``count``;
        ``OUT_OF_WORKSPACE`` without a pose when it is past the window's downstream end
        there, ``BAD_REQUEST`` without a served part or a count."""
        part = self.served.get(link)
        if part is None or count is None:
            why = ("conveyor PREDICT: no encoder count N with the request" if part is not None
                   else "conveyor PREDICT: no part served to this link yet (NEXT first)")
            return self._empty(Status.BAD_REQUEST, why, count, now_ns)
        self._seen(count)
        along = self.queue.along(part, count)
        if along > self.queue.window_mm[1]:
            return self._empty(Status.OUT_OF_WORKSPACE,
                               f"conveyor PREDICT: part {part.uid} is {along:.1f} mm along the "
                               f"belt at count {count}, past the pick window's end "
                               f"{self.queue.window_mm[1]:g} mm", count, now_ns)
        return self._answer(part, count, now_ns,
                            f"part {part.uid} of job {part.job_id} predicted to count {count}")


def line_of(conveyor: ConveyorConfig, vendor: str) -> BeltLine:
    """The ``BeltLine`` of a recipe's ``[conveyor]`` section, its poses in ``vendor``'s
    convention."""
    c = conveyor
    belt = Belt(c.direction, c.counts_per_mm, c.origin_mm, c.normal, c.encoder_bits)
    queue = PartQueue(belt, c.window_mm, c.sigma_mm, c.match_sigmas, c.match_deg)
    travel = TravelRule(c.counts_per_mm, c.trigger_distance_mm, c.speed_mm_s,
                        c.encoder_bits) if c.trigger == "travel" else None
    return BeltLine(belt, queue, vendor, LATCH_KINDS[c.latch], c.speed_mm_s,
                    c.timestamp_error_ms, travel=travel)
