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
"""

from __future__ import annotations

import asyncio
import contextlib
import re
import struct
import time
from dataclasses import dataclass, field

from vgripd.service.robot_socket_format import ANSWER_SIZE, BRANDS, RobotBrand

NO_ANSWER = -1
BUSY = 40
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
    words: dict[str, int]  # LOCATE, NEXT, CAPTURED, RESULT, REFUSED

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
                                                        "RESULT", "REFUSED")}
            return cls(b, values["VG_SCALE"], seconds("VG_TIMEOUT"),
                       seconds("VG_CONNECT_TIMEOUT", connect_default), seconds("VG_BUSY_WAIT"),
                       int(values["VG_BUSY_TRIES"]), int(values["VG_ATTEMPTS"]), words)
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

    async def _ask(self, command_word: int, recipe: int) -> Outcome:
        unanswered = busy = 0
        ids: list[int] = []
        while True:
            self.vg_id = 1 if self.vg_id >= MAX_ID else self.vg_id + 1
            ids.append(self.vg_id)
            outcome = await self._request(command_word, recipe)
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

    async def _request(self, command_word: int, recipe: int) -> Outcome:
        if not await self._connect():
            return Outcome(NO_ANSWER)
        assert self._writer is not None
        assert self._reader is not None
        frame = struct.pack(">4I", command_word, self.vg_id, recipe, 0)
        self.sent.append(frame)
        try:
            self._writer.write(frame)
            await self._writer.drain()
        except OSError:
            return Outcome(NO_ANSWER)
        captured = False
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
                            self.s.words["REFUSED"]):
                return Outcome(NO_ANSWER, captured=captured)  # out of step
            if w[1] != self.vg_id:
                continue  # an answer to an earlier request
            if w[0] == self.s.words["CAPTURED"]:
                captured = True
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
            return Outcome(w[2], values, w[3], w[4], captured, remaining=w[15])

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
