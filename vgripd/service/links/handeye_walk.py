"""Serving a walked hand-eye calibration to the robot program over the cell's own link.

The robot program walks; vgripd answers. The exchange uses the link's ordinary requests and
answers (docs/calibration-handeye.md, "Walked calibration"), so every link that carries a pose
can carry it:

- ``NEXT`` (3), recipe 0: "give me the target": the one pending (again: a program restarted,
  or an answer lost, asks again and nothing is skipped), else the next one (the start of a
  walk, and of a resumed one);
- ``TRIGGER`` (1) with a target pending: "I am there and settled: take the image". The flange
  pose recorded is the one the link read from the robot with the request (RTDE's
  ``actual_TCP_pose``; robot socket: CAPTURE_AT's); the image is taken, ``image_captured``
  answered, the corners recorded;
- ``NEXT`` (3), recipe 1 (``SKIP``) with a target pending: "I cannot reach it": recorded as
  unreachable, skipped.

Each answer is ``OK`` with the next target (the flange pose in ``vendor``'s convention, base
frame, absolute: the robot program moves there as given, with its own speed limit), or
``NOT_FOUND`` (10) without a pose when every target has a record: the walk is complete. A
``TRIGGER`` with no target pending, and a request that is no walk request
(``walk_request_refusal``), is ``BAD_REQUEST`` (32); an image that cannot be taken is
``CAMERA_ERROR`` (30); either way nothing is recorded and the target stays pending (the robot
asks again).

A request the program sends again because its answer came too late or got lost (its timeout,
then the same request with a new id) gets the same answer again, recording nothing:

- an image request whose flange pose is within ``REPEAT_MM`` / ``REPEAT_DEG`` of a pose
  already recorded: the robot has not moved, so it repeats the request of that target (when
  the pending target is within twice that of the recorded one, the two cannot be told apart
  and the request is a new capture);
- a skip of a pending target the program was never told (its answer not delivered, or the
  request sent before that answer went out): it repeats the skip before it.

Every answer carries job id 0: a walk runs no job, and the daemon's job counter does not move
(a robot socket sends the answers that leave the walk unchanged as REFUSED). The record is
the :class:`~vgripd.calib.handeye.walk.Walk` file, saved after every target, so a walk whose
link was lost or whose robot stopped resumes with a new ``NEXT``. An answer the link cannot
deliver (the peer gone, the link hanging past ``ANSWER_TIMEOUT_S``) is logged and the walk
goes on: the robot asks again.

No motion is commanded here: only answers to the robot's requests.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Awaitable, Callable
from typing import Any

import numpy as np

from vgripd.calib.handeye.walk import Walk
from vgripd.errors import VgripError
from vgripd.geometry.transforms import pose_error
from vgripd.geometry.vendors import convention, vendor_from_transform
from vgripd.peer.jobcore import Command
from vgripd.service.links.protocol import RobotLink, Trigger
from vgripd.types import JobResult, RobotTarget, Status

log = logging.getLogger("vgripd.calib.walk")

#: The recipe word of a NEXT that skips the pending target ("I cannot reach it").
SKIP = 1
#: A link's answer that takes longer is given up (logged): the robot asks again.
ANSWER_TIMEOUT_S = 2.0
#: An image request whose flange pose is this close to one already recorded (mm, deg) repeats
#: that target's request: a robot standing still reads its pose within micrometres.
REPEAT_MM, REPEAT_DEG = 0.5, 0.1

Grab = Callable[[], Awaitable[np.ndarray]]


def walk_request_refusal(command: int, recipe: int, flange_pose: bool) -> str | None:
    """Why a request of the walk link is no walk request (answered ``BAD_REQUEST``, the walk
    unchanged: nothing recorded, the pending target still pending); None when it is one.

    NEXT with recipe 0 (ask) or 1 (skip); TRIGGER (robot socket: CAPTURE_AT) with the flange
    pose and recipe 0 (the walk runs no job, so no recipe applies); CLEAR, which the links
    answer themselves and which changes nothing in the walk."""
    if command == Command.NEXT:
        if recipe in (0, SKIP):
            return None
        return (f"NEXT with recipe {recipe} in a walk: recipe 0 asks for the target, "
                f"{SKIP} skips it")
    if command == Command.TRIGGER:
        if not flange_pose:
            return ("an image request without the flange pose in a walk (robot socket: send "
                    "CAPTURE_AT, not LOCATE); the pending target stays pending")
        if recipe != 0:
            return (f"recipe {recipe} with the image request of a walk: it runs no job, "
                    "the recipe word must be 0")
        return None
    if command == Command.CLEAR:
        return None
    return f"command {command} in a walk"


def walk_refusal(link: RobotLink, where: str) -> str | None:
    """Why ``link`` cannot carry a walk (its requests bring no flange pose); None when it can."""
    caps = getattr(link, "capabilities", None)
    if caps is not None and caps.flange_pose:
        return None
    return (f"{where} ({type(link).__name__}) cannot carry a walked calibration: its requests "
            "bring no flange pose with them; walk over a ur_rtde link (actual_TCP_pose) or a "
            "robot_socket link (CAPTURE_AT)")


class WalkServer:
    """Answers one robot program's walk requests over ``link`` (see the module docstring).

    ``grab`` takes one image (8-bit, grey or BGR). ``serve`` returns when the walk is complete
    (the ``NOT_FOUND`` answer given); cancel it to stop (the record stays): ``waiting()``
    then lists the requests left without an answer. ``on_answer`` (optional) is called after
    every request handled (the running daemon's status and event stream).
    """

    def __init__(self, walk: Walk, link: RobotLink, grab: Grab, vendor: str) -> None:
        self.walk = walk
        self.link = link
        self.grab = grab
        self.vendor = vendor
        self.fields = tuple(convention(vendor).fields)
        self.pending: int | None = None
        #: NOT_FOUND answered: the walk is over, later requests are no longer the walk's
        self.complete = False
        self._queue: asyncio.Queue[Trigger] = asyncio.Queue()
        link.set_vendor(vendor)  # robot_socket: CAPTURE_AT's pose is in this convention
        link.set_walking(True)  # a link refusing NEXT without a pick list lets it through
        self.current: Trigger | None = None  # the request being answered
        self.on_answer: Callable[[], None] | None = None
        #: the target the program was last told (an answer with it delivered), None: not yet
        self._told: int | None = None
        self._told_ns = 0  # when that answer went out (monotonic)
        self._last: int | None = None  # the target the latest image request recorded

    def on_trigger(self, trigger: Trigger) -> None:
        self._queue.put_nowait(trigger)

    async def serve(self) -> None:
        while True:
            trigger = await self._queue.get()
            self.current = trigger
            answer = asyncio.ensure_future(self._answer(trigger))
            try:
                done = await asyncio.shield(answer)
            except asyncio.CancelledError:
                # Stopped while answering: the answer goes out whole (a grab is bounded by
                # the camera's timeout), so the request is not also answered ABORTED.
                with contextlib.suppress(Exception):
                    await answer
                    self.current = None  # answered; one that failed is left to waiting()
                raise
            self.current = None
            if self.on_answer is not None:
                self.on_answer()
            if done:
                return

    def waiting(self) -> list[Trigger]:
        """The requests not answered (after ``serve`` was cancelled), taken from the queue."""
        out = [] if self.current is None else [self.current]
        self.current = None
        while not self._queue.empty():
            out.append(self._queue.get_nowait())
        return out

    def repeats_last(self, trigger: Trigger) -> bool:
        """After the walk (``complete``): ``trigger`` repeats the image request that completed
        it (its answer, NOT_FOUND, came too late or got lost); ``answer_again`` answers it."""
        return (self.complete and self._last is not None
                and trigger.command == Command.TRIGGER and trigger.recipe == 0
                and trigger.T_base_flange is not None
                and self.repeats(trigger.T_base_flange) == self._last)

    async def answer_again(self, trigger: Trigger) -> None:
        """The last answer of the walk again: image taken, NOT_FOUND (job id 0)."""
        log.info("walk target %d: its image request again after the walk (%s): answered "
                 "NOT_FOUND again", self._last, trigger.peer or trigger.link)
        await self._captured(trigger.seq)
        await self._say(trigger.seq, JobResult(0, Status.NOT_FOUND, "walk complete"))

    def repeats(self, T_base_flange: Any) -> int | None:
        """The recorded target whose image request one with ``T_base_flange`` repeats (the
        robot has not moved since), or None: a new capture."""
        for index, record in sorted(self.walk.records.items()):
            if record.T_base_flange is None:
                continue
            mm, deg = pose_error(T_base_flange, record.T_base_flange)
            if mm > REPEAT_MM or deg > REPEAT_DEG:
                continue
            if self.pending is not None:  # moved from there to the pending target: apart?
                mm, deg = pose_error(self.walk.target(self.pending), self.walk.target(index))
                if mm <= 2 * REPEAT_MM and deg <= 2 * REPEAT_DEG:
                    continue
            return index
        return None

    async def _answer(self, trigger: Trigger) -> bool:
        seq = trigger.seq
        if trigger.t_mono_ns < self._told_ns:
            self._told = None  # sent before that answer went out: the program gave it up
        refusal = walk_request_refusal(trigger.command, trigger.recipe,
                                       trigger.T_base_flange is not None)
        if refusal is not None:
            await self._say(seq, JobResult(0, Status.BAD_REQUEST, refusal))
            return False
        repeat = (None if trigger.command != Command.TRIGGER
                  else self.repeats(trigger.T_base_flange))
        if repeat is not None:
            log.info("walk target %d: its image request again (%s; the answer came too late "
                     "or got lost): answered again, nothing recorded", repeat,
                     trigger.peer or trigger.link)
            await self._captured(seq)
        elif trigger.command == Command.TRIGGER:
            if self.pending is None:
                await self._say(seq, JobResult(0, Status.BAD_REQUEST,
                                               "no target pending: ask NEXT first"))
                return False
            try:
                image = await self.grab()
            except (VgripError, OSError) as err:
                log.warning("walk target %d: no image: %s", self.pending, err)
                await self._say(seq, JobResult(0, Status.CAMERA_ERROR, str(err)))
                return False
            await self._captured(seq)
            record = await asyncio.to_thread(self.walk.capture, self.pending,
                                             trigger.T_base_flange, image, "", trigger.peer)
            log.info("walk target %d: %s (%s)", record.index, record.status,
                     trigger.peer or trigger.link)
            self.pending, self._last = None, record.index
        elif self.pending is not None:  # NEXT
            if trigger.recipe == SKIP and self._told != self.pending:
                log.info("walk target %d: a skip before the program was told this target (the "
                         "answer to its skip came too late or got lost): answered again, not "
                         "skipped", self.pending)
            elif trigger.recipe == SKIP:
                self.walk.unreachable(self.pending, "the robot program reported it unreachable",
                                      trigger.peer)
                log.info("walk target %d: unreachable, skipped (%s)", self.pending,
                         trigger.peer or trigger.link)
                self.pending = None
            else:
                log.info("walk target %d: asked for again (the program restarted, or lost the "
                         "answer)", self.pending)
        if self.pending is None:
            self.pending = self.walk.next_index()
        if self.pending is None:
            self.complete = True
            self.link.set_walking(False)  # what comes after the last answer is no walk's
            await self._say(seq, JobResult(0, Status.NOT_FOUND, "walk complete"))
            return True
        values = tuple(float(v) for v in vendor_from_transform(self.vendor,
                                                               self.walk.target(self.pending)))
        told = await self._say(seq, JobResult(0, Status.OK, f"target {self.pending}",
                                              target=RobotTarget(self.vendor, self.fields,
                                                                 values)))
        self._told, self._told_ns = (self.pending if told else None), time.monotonic_ns()
        return False

    async def _say(self, seq: int, result: JobResult) -> bool:
        """Answer request ``seq``; False when the link cannot deliver it (logged: the robot
        asks again), which does not end the walk."""
        try:
            async with asyncio.timeout(ANSWER_TIMEOUT_S):
                await self.link.publish(seq, result)
        except Exception as err:
            log.warning("walk: the answer to request %d (%s) was not delivered: %r", seq,
                        result.status.name, err)
            return False
        return True

    async def _captured(self, seq: int) -> None:
        try:
            async with asyncio.timeout(ANSWER_TIMEOUT_S):
                await self.link.image_captured(seq, 0)
        except Exception as err:
            log.warning("walk: request %d: 'image taken' not delivered: %r", seq, err)
