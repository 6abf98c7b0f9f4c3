"""Python twins of the generated robot programs (``robots/<brand>/``, ``vgripd robot-program``).

Robot-side syntax cannot run here, so each program's message exchange is emulated: a twin reads
its settings (port, scale, timeouts, BUSY retry, attempts, frame words) from the program text
that ``vgripd robot-program`` wrote, and then does what the program does, step by step:

- the request bytes: the program's own LOCATE word, its request id (+1 per request, wrapping
  to 1 after 2**31-2), the recipe and a 0 word, big-endian;
- its connection habit (``RobotBrand.connection``): ``kept`` (KUKA EKI, ABB, Staubli: open once,
  close after a failure), ``per_request`` (UR ``socket_open``, FANUC Karel: open, one request,
  close) or ``robot_server`` (Yaskawa MotoPlus: the twin listens, vgripd dials in; a new
  connection replaces the old one);
- how it reads: 64-byte frames, answers of other request ids skipped, CAPTURED noted, anything
  that is not an answer word ends the request; its timeout either per frame (RAPID
  ``SocketReceive \\Time``, ``socket_read_binary_integer``, VAL3 ``sioGet``, MotoPlus
  ``SO_RCVTIMEO``) or for the whole request (KRL ``$TIMER``, Karel's loop);
- what it does with the status: 1/2 decode the pose (int32 / scale, or float32 for RAPID) after
  checking the scale word; 40 BUSY ask again after the busy wait with a new id, at most
  ``VG_BUSY_TRIES`` times; no answer: drop the connection and ask again with a new id, and after
  ``VG_ATTEMPTS`` in a row stop (``ProgramStopped``: KRL HALT, RAPID Stop, Karel ABORT, URScript
  halt) or return -1 (VAL3 and the MotoPlus task, whose callers decide).

``next()`` is the program's ``vg_next`` (``vgNext``, VG_NEXT.ls, VGNEXT.JBI): the following
object of the last locate's pick list (command 3 NEXT, docs/robot_socket.md), with the
program's own NEXT word, recipe word 0 and the same retries, timeouts and BUSY handling as its
locate (every program sends both through one request routine).

``walk(arm)`` is the program's walk routine (docs/calibration-handeye.md, "Walked
calibration") moving a :class:`~vgripd.sim.arm.SimulatedArm`: NEXT for a target; NOT_FOUND
ends the walk, any other status but 1/2 stops it; a target the arm cannot reach is answered
NEXT with recipe 1 (skipped; the first NEXT has recipe 0: vgripd answers a target still
pending again, so a restarted program skips nothing), a reachable one is moved to at the
program's speed, the program waits its settle time and sends CAPTURE_AT (command 4, 44
bytes) with the pose the arm reports, in the brand's convention and its encoding (int32 x
scale from the controller's own resolution for MotoPlus, float32 for RAPID), then reads
CAPTURED and the RESULT with the next target.
The walk's requests are retried as every other request of the program.

The conveyor routines (docs/robot_socket.md, "Conveyor"), for programs that have them:
``locate_at``, ``next_at`` and ``predict`` send the counted requests (24 bytes, the encoder
count and frame id) and read the BELT frame before the final one (``Outcome.belt``).
``intercept(belt, arm, lead)`` is the program's intercept routine for a robot without a
tracking option: NEXT at the count now, PREDICT at the count now + ``lead``, move there, wait
until the encoder reaches that count, grip. ``track(belt, arm, tracker)`` is its tracking
routine: NEXT at the count now, the pose and its RESULT_COUNT handed to the controller's own
tracking (``tracker``: the controller's belt, which adds the travel since that count), the
arm follows and grips when the part is at the window's middle. ``belt`` is the test's
simulated belt (``count()``, ``advance(counts)``): the twin reads and waits on it as the
program reads its encoder input.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
import struct
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vgripd.geometry.vendors import convention, transform_from_vendor, vendor_from_transform
from vgripd.peer.socket_frames import ANSWER_SIZE, BRANDS, N_VALUES, RobotBrand
from vgripd.sim.arm import ArmState

NO_ANSWER = -1
BUSY = 40
NOT_FOUND = 10
WALK_SKIP = 1  # the walk routines' NEXT recipe for "the target given cannot be reached"
AT_ELSEWHERE = -2  # MotoPlus: the flange pose read is not the target (tool file 0 not the flange)
#: Pose resolution of the controller's own position data where the program sends it as read
#: (MotoPlus: 0.001 mm, 0.0001 deg); other controllers read REAL/num values.
CONTROLLER_RESOLUTION = {"yaskawa": (1e-3, 1e-4)}
MAX_ID = 2147483646  # the programs wrap their request id to 1 after this
PER_FRAME_TIMEOUT = {"abb", "staubli", "ur", "yaskawa"}  # others: one timer per request
RETURNS_ON_GIVING_UP = {"staubli", "yaskawa"}  # others stop the robot program
DEFAULT_CONNECT_TIMEOUT_S = 3.0

_NUMBER = r"(-?\d+(?:\.\d+)?)"
_ASSIGNED = re.compile(r"\b(VG_[A-Z0-9_]+)\s*(?::=|=)?\s*" + _NUMBER + r"(?![\w.])")
_DTX_VALUE = re.compile(r'name="(VG_[A-Z0-9_]+)"[^>]*>\s*<Value key="0" value="' + _NUMBER)


class ProgramStopped(Exception):
    """The robot program stopped itself (HALT, Stop, ABORT, halt), saying why."""


@dataclass(frozen=True)
class ProgramSettings:
    """What a generated program says about its exchange (parsed from its text)."""

    brand: RobotBrand
    scale: float  # 0: float32 values
    timeout_s: float
    connect_timeout_s: float
    busy_wait_s: float
    busy_tries: int
    attempts: int
    words: dict[str, int]  # LOCATE, NEXT, CAPTURED, RESULT, REFUSED, CAPTURE_AT
    walk_speed_mm_s: float = 0.0  # the walk routine's linear speed
    walk_settle_s: float = 0.0  # its standstill before CAPTURE_AT
    at_bytes: int = 44  # the length of its CAPTURE_AT request
    #: (mm, deg): the walk checks the flange pose read against the target (MotoPlus), or None
    at_tolerance: tuple[float, float] | None = None
    #: The conveyor's words (LOCATE_AT, NEXT_AT, PREDICT, BELT) where the program has them
    belt_words: dict[str, int] = field(default_factory=dict)

    @classmethod
    def parse(cls, brand: str | RobotBrand, texts: dict[str, str]) -> ProgramSettings:
        """From the program files (name -> text) that ``vgripd robot-program`` wrote."""
        b = BRANDS[brand] if isinstance(brand, str) else brand
        text = "\n".join(texts.values())
        values: dict[str, float] = {}
        for pattern in (_DTX_VALUE, _ASSIGNED):
            for name, number in pattern.findall(text):
                values.setdefault(name, float(number))

        def seconds(name: str, default: float | None = None) -> float:
            if f"{name}_S" in values:
                return values[f"{name}_S"]
            if f"{name}_MS" in values:
                return values[f"{name}_MS"] / 1000
            if default is None:
                raise ValueError(f"{b.name} program states no {name}_S or {name}_MS")
            return default

        connect_ms = re.search(r'<TIMEOUT Connect="(\d+)"', text)  # the EKI channel's
        connect_default = (int(connect_ms.group(1)) / 1000 if connect_ms
                           else 2.0 if b.name == "ur" else DEFAULT_CONNECT_TIMEOUT_S)
        try:
            words = {k: int(values[f"VG_{k}"]) for k in ("LOCATE", "NEXT", "CAPTURED",
                                                        "RESULT", "REFUSED", "CAPTURE_AT")}
            speed = (values["VG_WALK_SPEED_M_S"] * 1000 if "VG_WALK_SPEED_M_S" in values
                     else values["VG_WALK_SPEED_MM_S"])
            belt = {k: int(values[f"VG_{k}"]) for k in ("LOCATE_AT", "NEXT_AT", "PREDICT",
                                                        "BELT") if f"VG_{k}" in values}
            return cls(b, values["VG_SCALE"], seconds("VG_TIMEOUT"),
                       seconds("VG_CONNECT_TIMEOUT", connect_default), seconds("VG_BUSY_WAIT"),
                       int(values["VG_BUSY_TRIES"]), int(values["VG_ATTEMPTS"]), words,
                       speed, seconds("VG_WALK_SETTLE"), int(values["VG_AT_BYTES"]),
                       (values["VG_AT_TOL_UM"] / 1000, values["VG_AT_TOL_DEG4"] / 10000)
                       if "VG_AT_TOL_UM" in values else None, belt)
        except KeyError as err:
            raise ValueError(f"{b.name} program states no {err.args[0]}") from None

    @property
    def n_values(self) -> int:
        """Pose values the program expects in a result (6, or 7 for the ABB quaternion)."""
        return 7 if self.brand.convention == "abb" else 6


@dataclass
class Outcome:
    """What the program is left with after ``vg_locate``: the status (-1: gave up), and for 1
    or 2 the pose values it decoded."""

    status: int
    values: tuple[float, ...] = ()
    job_id: int = 0
    warnings: int = 0
    captured: bool = False
    request_ids: list[int] = field(default_factory=list)
    remaining: int = 0  # answer word 15: pickable objects after this one
    #: A counted request's BELT frame: RESULT_COUNT, LATCH_SOURCE, QUEUED (u32 as read)
    belt: tuple[int, int, int] | None = None
    #: ... and LATCH_ERR_MM, ALONG, ACROSS, THETA (mm, deg)
    belt_values: tuple[float, ...] = ()


@dataclass
class WalkOutcome:
    """What the walk routine ends with: the last status (10 NOT_FOUND: complete), the targets
    it moved to and skipped (as received), and the flange poses it sent (as sent, decoded)."""

    status: int
    reached: list[tuple[float, ...]] = field(default_factory=list)
    skipped: list[tuple[float, ...]] = field(default_factory=list)
    sent_poses: list[tuple[float, ...]] = field(default_factory=list)
    moves: list[tuple[tuple[float, ...], float]] = field(default_factory=list)  # (target, mm/s)
    pending: tuple[float, ...] = ()  # stopped (``stop_after``): the target received, not moved to


class ProgramTwin:
    """One robot program's exchange with vgripd. ``host``/``port``: where the program dials
    (for ``robot_server`` brands: where it listens; port 0 = any free one, see ``port``)."""

    def __init__(self, settings: ProgramSettings, host: str, port: int) -> None:
        self.s = settings
        self.host = host
        self.port = port
        self.vg_id = 0
        self.sent: list[bytes] = []  # every request frame, in order
        self.connects = 0
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._server: asyncio.Server | None = None
        self._connected = asyncio.Event()

    async def __aenter__(self) -> ProgramTwin:
        if self.s.brand.connection == "robot_server":
            self._server = await asyncio.start_server(self._accepted, self.host, self.port)
            self.port = self._server.sockets[0].getsockname()[1]
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self._drop()
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()

    async def locate(self, recipe: int = 0) -> Outcome:
        """``vg_locate(recipe)`` of the program; ``ProgramStopped`` where it stops itself."""
        return await self._ask(self.s.words["LOCATE"], recipe)

    async def next(self) -> Outcome:
        """``vg_next()`` of the program: the following object of the last locate's pick list
        (its NEXT word, recipe 0), asked and retried as its locate is."""
        return await self._ask(self.s.words["NEXT"], 0)

    async def locate_at(self, recipe: int, count: int, frame: int = 0) -> Outcome:
        """``vgLocateAt``: a locate with the encoder count latched at the image."""
        return await self._ask(self.s.belt_words["LOCATE_AT"], recipe, count=(count, frame))

    async def next_at(self, count: int) -> Outcome:
        """``vgNextAt``: the next part of the conveyor's queue at the count now."""
        return await self._ask(self.s.belt_words["NEXT_AT"], 0, count=(count, 0))

    async def predict(self, count: int) -> Outcome:
        """``vgPredict``: where the part last served will be at ``count``."""
        return await self._ask(self.s.belt_words["PREDICT"], 0, count=(count, 0))

    async def intercept(self, belt: Any, arm: Any, lead: int) -> tuple[Outcome, int]:
        """The intercept routine: NEXT now, PREDICT at now + ``lead``, move there (the arm),
        wait for the encoder to reach that count (the belt moves), grip. The answer the move
        went to and the count at the grip; a status other than 1/2 returns at once."""
        out = await self.next_at(belt.count())
        if out.status not in (1, 2):
            return out, belt.count()
        target = (belt.count() + lead) & 0xFFFFFFFF
        out = await self.predict(target)
        if out.status not in (1, 2):
            return out, belt.count()
        arm.move(transform_from_vendor(self.s.brand.convention, out.values))
        while arm.step() is not ArmState.SETTLED:
            belt.advance(1)
        while ((belt.count() - target) & 0xFFFFFFFF) >= 1 << 31:  # the program's wait
            belt.advance(1)
        return out, belt.count()

    async def track(self, belt: Any, arm: Any, tracker: Any) -> tuple[Outcome, int]:
        """The tracking routine: NEXT now; the pose at its RESULT_COUNT into the controller's
        tracking (``tracker.moved(T, count_from, count_to)``), the arm follows it until the
        part reaches ``tracker.grip_along_mm``, grip. The answer and the count at the grip."""
        out = await self.next_at(belt.count())
        if out.status not in (1, 2) or out.belt is None:
            return out, belt.count()
        T = transform_from_vendor(self.s.brand.convention, out.values)
        while True:
            now = belt.count()
            arm.move(tracker.moved(T, out.belt[0], now))
            while arm.step() is not ArmState.SETTLED:
                pass
            if tracker.along_mm(arm.T_true) >= tracker.grip_along_mm:
                return out, now
            belt.advance(tracker.step_counts)

    async def capture_at(self, T: Any) -> Outcome:
        """The walk routine's CAPTURE_AT alone, for flange pose ``T`` (mm): what vgripd does
        with it outside a walk (a locate whose job gets the flange pose)."""
        return await self._ask(self.s.words["CAPTURE_AT"], 0, self.flange_values(T))

    async def walk(self, arm: Any, stop_after: int | None = None) -> WalkOutcome:
        """The walk routine with ``arm`` (``SimulatedArm``); ``stop_after``: the operator stops
        the program after that many targets were handled (moved to or skipped), the next one
        received and not yet moved to (vgripd holds it pending)."""
        conv = convention(self.s.brand.convention)
        outcome = await self.next()  # recipe 0: a target (the pending one, after a restart)
        walked = WalkOutcome(outcome.status)
        while outcome.status in (1, 2):
            target = outcome.values[:len(conv.fields)]
            if stop_after is not None and len(walked.reached) + len(walked.skipped) >= stop_after:
                walked.pending = target
                return walked
            T = transform_from_vendor(conv.name, target)
            if not arm.reachable(T):  # the language's reach check: skip, ask for the next
                walked.skipped.append(target)
                outcome = await self._ask(self.s.words["NEXT"], WALK_SKIP)
                walked.status = outcome.status
                continue
            arm.move(T)
            walked.moves.append((target, self.s.walk_speed_mm_s))
            walked.reached.append(target)
            while arm.step() is not ArmState.SETTLED:  # the motion instruction returns
                pass
            await asyncio.sleep(self.s.walk_settle_s)
            pose = self.flange_values(arm.reported_pose())
            if not self._at_target(pose, target):
                walked.status = AT_ELSEWHERE  # the MotoPlus task sends nothing: VGWALK pauses
                return walked
            walked.sent_poses.append(pose)
            outcome = await self._ask(self.s.words["CAPTURE_AT"], 0, pose)
            walked.status = outcome.status
        return walked

    def _at_target(self, pose: tuple[float, ...], target: tuple[float, ...]) -> bool:
        """The MotoPlus task's check (``vgAtTarget``): the pose read (tool file 0) within its
        tolerance of the target moved to (the selected tool), angles wrapped; True for the
        programs without the check."""
        if self.s.at_tolerance is None:
            return True
        mm, deg = self.s.at_tolerance
        for i, (a, b) in enumerate(zip(pose, target, strict=False)):
            d = a - b if i < 3 else (a - b + 180.0) % 360.0 - 180.0
            if abs(d) > (mm if i < 3 else deg):
                return False
        return True

    def flange_values(self, T: Any) -> tuple[float, ...]:
        """The 7 values the program sends for flange pose ``T`` (as its controller reads
        them: rounded to its resolution where it has one; 0 as the 7th of 6)."""
        values = list(vendor_from_transform(self.s.brand.convention, np.asarray(T)))
        res = CONTROLLER_RESOLUTION.get(self.s.brand.name)
        if res is not None:
            values = [round(v / res[i >= 3]) * res[i >= 3] for i, v in enumerate(values)]
        return tuple(values) + (0.0,) * (N_VALUES - len(values))

    async def _ask(self, command_word: int, recipe: int, pose: tuple[float, ...] = (),
                   count: tuple[int, int] | None = None) -> Outcome:
        unanswered = busy = 0
        ids: list[int] = []
        while True:
            self.vg_id = 1 if self.vg_id >= MAX_ID else self.vg_id + 1
            ids.append(self.vg_id)
            outcome = await self._request(command_word, recipe, pose, count)
            outcome.request_ids = ids
            if self.s.brand.connection == "per_request" or outcome.status == NO_ANSWER:
                await self._drop()
            if outcome.status == NO_ANSWER:
                unanswered += 1
                if unanswered >= self.s.attempts:
                    if self.s.brand.name in RETURNS_ON_GIVING_UP:
                        return outcome
                    raise ProgramStopped(f"{self.s.brand.name}: no answer to {unanswered} "
                                         f"requests in a row")
            elif outcome.status == BUSY and busy < self.s.busy_tries:
                busy += 1
                await asyncio.sleep(self.s.busy_wait_s)
            else:
                return outcome

    # -- one request ---------------------------------------------------------------------

    async def _request(self, command_word: int, recipe: int, pose: tuple[float, ...] = (),
                       count: tuple[int, int] | None = None) -> Outcome:
        if not await self._connect():
            return Outcome(NO_ANSWER)
        assert self._writer is not None
        assert self._reader is not None
        frame = struct.pack(">4I", command_word, self.vg_id, recipe, 0)
        if command_word == self.s.words["CAPTURE_AT"]:
            if self.s.scale:
                frame += struct.pack(">7i", *(round(v * self.s.scale) for v in pose))
            else:
                frame += struct.pack(">7f", *pose)
            assert len(frame) == self.s.at_bytes
        if count is not None:
            frame += struct.pack(">2I", count[0] & 0xFFFFFFFF, count[1] & 0xFFFFFFFF)
        self.sent.append(frame)
        try:
            self._writer.write(frame)
            await self._writer.drain()
        except OSError:
            return Outcome(NO_ANSWER)
        captured = False
        belt: tuple[int, int, int] | None = None
        belt_values: tuple[float, ...] = ()
        deadline = time.monotonic() + self.s.timeout_s
        while True:
            wait_s = (self.s.timeout_s if self.s.brand.name in PER_FRAME_TIMEOUT
                      else max(0.0, deadline - time.monotonic()))
            try:
                answer = await asyncio.wait_for(self._reader.readexactly(ANSWER_SIZE), wait_s)
            except (TimeoutError, asyncio.IncompleteReadError, OSError):
                return Outcome(NO_ANSWER, captured=captured)
            w = struct.unpack(">16i", answer)
            if w[0] not in (self.s.words["CAPTURED"], self.s.words["RESULT"],
                            self.s.words["REFUSED"], self.s.belt_words.get("BELT")):
                return Outcome(NO_ANSWER, captured=captured)  # out of step
            if w[1] != self.vg_id:
                continue  # an answer to an earlier request
            if w[0] == self.s.words["CAPTURED"]:
                captured = True
                continue
            if w[0] == self.s.belt_words.get("BELT"):
                u = struct.unpack(">16I", answer)
                belt = (u[2], u[3], u[8])
                belt_values = tuple(v / self.s.scale if self.s.scale else v for v in
                                    (w[4:8] if self.s.scale else
                                     struct.unpack(">4f", answer[16:32])))
                continue
            values: tuple[float, ...] = ()
            if w[5] == self.s.n_values:
                if w[14] != self.s.scale:
                    if self.s.brand.name == "yaskawa":
                        return Outcome(NO_ANSWER, captured=captured)
                    raise ProgramStopped(f"{self.s.brand.name}: scale word {w[14]}, the "
                                         f"program reads {self.s.scale:g}")
                raw = answer[24:24 + 4 * self.s.n_values]
                if self.s.scale:
                    values = tuple(v / self.s.scale
                                   for v in struct.unpack(f">{self.s.n_values}i", raw))
                else:
                    values = struct.unpack(f">{self.s.n_values}f", raw)
            return Outcome(w[2], values, w[3], w[4], captured, remaining=w[15], belt=belt,
                           belt_values=belt_values)

    # -- connections ---------------------------------------------------------------------

    async def _connect(self) -> bool:
        if self._writer is not None and not self._writer.is_closing():
            return True
        if self.s.brand.connection == "robot_server":  # wait for vgripd to dial in
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._connected.wait(), self.s.timeout_s)
            return self._writer is not None and not self._writer.is_closing()
        try:
            self._reader, self._writer = await asyncio.wait_for(
                asyncio.open_connection(self.host, self.port), self.s.connect_timeout_s)
        except (TimeoutError, OSError):
            return False
        self.connects += 1
        return True

    async def _drop(self) -> None:
        writer, self._writer, self._reader = self._writer, None, None
        self._connected.clear()
        if writer is not None:
            writer.close()
            with contextlib.suppress(OSError):
                await writer.wait_closed()

    async def _accepted(self, reader: asyncio.StreamReader,
                        writer: asyncio.StreamWriter) -> None:
        await self._drop()  # a new connection from vgripd replaces the old one
        self._reader, self._writer = reader, writer
        self.connects += 1
        self._connected.set()
