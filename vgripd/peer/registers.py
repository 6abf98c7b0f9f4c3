"""The register map of register-based links (Modbus server and client, RTU, S7), with no I/O.

Modbus holding registers (16-bit words, zero-based addresses; ``docs/registers.md``
has the integrator's version). Only the command area (0-2) and, in map version 4, the latch area
(46-49) are writable; everything else is written by vgripd. 32-bit items (u32, int32, float32)
take two words in the configured word order:
``ABCD`` = high word first (default), ``CDAB`` = low word first. Bytes inside a word are always
big-endian (Modbus).

====  =============  ====  ======  =================================================================
addr  name           R/W   type    meaning
====  =============  ====  ======  =================================================================
   0  CMD            RW    u16     command: 1 TRIGGER (run a job), 2 CLEAR (reset the result area),
                                   3 NEXT (the next instance of the last job's pick list),
                                   view * 256 + 4 CAPTURE (view 1..8 of a several-view job)
   1  REQ_SEQ        RW    u16     request sequence: a request is a write that changes it to a
                                   non-zero value (edge on the sequence, not on the level)
   2  RECIPE         RW    u16     job parameter handed to the daemon with the trigger
   3  MAP_VERSION    R     u16     the link's ``map_version``: 4 (46-61, conveyor), 3 (0-45);
                                   2: 0-40 without the pick list; 1: also without WARNINGS
   4  CHECK_U16      R     u16     0x1234
   5  CHECK_U32      R     u32     0x12345678 in the configured word order
   7  CHECK_F32      R     f32     123.456 in the configured word order
   9  VALUE_FORMAT   R     u16     1 = float32 values, 2 = int32 values scaled by VALUE_SCALE
  10  VALUE_SCALE    R     u32     int32 mode: raw = round(value * scale); 0 in float32 mode
  12  HEARTBEAT      R     u16     +1 every ``heartbeat_ms`` while the link is healthy (wraps)
  13  STATE          R     u16     0 IDLE, 1 TRIGGERED, 2 BUSY (image captured), 3 DONE,
                                   4 VIEWS (a view taken, waiting for the next CAPTURE)
  14  CAPTURED_SEQ   R     u16     request whose image is taken: the robot may move on
  15  REJECT_SEQ     R     u16     last refused request (written after REJECT_CODE)
  16  REJECT_CODE    R     u16     why it was refused: 40 BUSY, 32 BAD_REQUEST
  17  ACK_SEQ        R     u16     request whose result is in 18-39; 0 = no result. Written LAST
  18  STATUS         R     u16     ``vgripd.types.Status`` of that result
  19  JOB_ID         R     u32     daemon job id (set at image capture, again at publish)
  21  RESULT_AGE_MS  R     u32     ms since the result was produced, live; 0xFFFFFFFF = none
  23  N_VALUES       R     u16     number of valid pose values: 0, 6 (XYZ + 3 angles) or 7 (XYZ+q)
  24  VALUES         R     7x32    pose in the output vendor's convention and units
  38  FIT_RMS        R     32      fit residual in mm (VALUE_FORMAT encoding); -1 = unknown
  40  WARNINGS       R     u16     live bit field (``Warnings``): bit 0 RECALIBRATE; others 0
  41  COUNT          R     u16     pickable instances of the job (1 or 0 for a single-object job)
  42  INDEX          R     u16     1-based index of the instance shown in 18-39 and 43-45; 0 = none
                                   (no pose), COUNT + 1 = past the end of the list (after NEXT)
  43  PICK_ID        R     u16     pick point id of the instance shown (0 = the object's grip)
  44  SCORE          R     32      detection score 0..1 of the instance shown; -1 = none/unknown
  46  LATCH_COUNT    RW    u32     encoder count the PLC latched for this request (PREDICT: N)
  48  LATCH_FRAME    RW    u32     ``latch = "frame_id"``: the camera frame that count belongs to
  50  RESULT_COUNT   R     u32     encoder count the pose shown belongs to
  52  LATCH_SOURCE   R     u16     0 none (still part), 1 link, 2 frame id, 3 timestamp
  53  LATCH_ERR_MM   R     32      one-sigma position error along the belt the latch leaves (mm)
  55  ALONG          R     32      the pose in belt terms at RESULT_COUNT: along the belt (mm),
  57  ACROSS         R     32      across it in its plane (mm),
  59  THETA          R     32      and its rotation about the belt's normal (deg)
  61  QUEUED         R     u16     parts waiting in the recipe's queue after this answer
====  =============  ====  ======  =================================================================

Handshake: a request is answered exactly once, either by ``ACK_SEQ == seq`` (the job ran or
the result area was cleared; ``STATUS`` tells the outcome) or by ``REJECT_SEQ == seq`` (refused,
``REJECT_CODE`` says why, nothing else changed: a running job keeps going and its result is later
acknowledged under its own sequence).

Ordering, so that a poller never pairs an acknowledged sequence with data of another request:
a publish writes all data first and ``ACK_SEQ`` last; a new job and CLEAR retract ``ACK_SEQ``
(0) first and only then clear the data (CLEAR then writes ``ACK_SEQ`` = seq last). The rules and
the handshake itself live in ``vgripd.peer.jobcore`` (``Handshake``: every link's plans of
writes); ``RegisterBank`` renders its steps as block writes. Servers apply each list of block
writes without yielding to readers; client links (S7, Modbus client) send them in order.

Pick lists (map version 3): a job that finds several instances (``JobResult.instances``)
publishes COUNT and the first pickable instance (INDEX 1) in the same places as a single
object, so a version 2 client that reads only 0-40 sees the first result. ``Command.NEXT``
asks for the following instance of the same job: answered from the daemon's copy of the list,
no acquisition, the same JOB_ID, RESULT_AGE_MS running from the original result (the images
are that old). Past the end it answers ``NOT_FOUND`` without a pose and INDEX = COUNT + 1.
NEXT is refused ``BAD_REQUEST`` (REJECT_SEQ/REJECT_CODE, nothing else changes) when the link
holds no list: after start, CLEAR, a new TRIGGER, or a job that found nothing; ``BUSY`` while
a request runs. The daemon refuses it too (answered ``BAD_REQUEST`` without a pose) when its
list is not this link's (a job of another link came in between). COUNT .. SCORE are part of
the result: cleared with it and written before ACK_SEQ.

Several views per job (``vision.views``; no new register, so the map version stays 3): CMD
= view * 256 + 4 (``capture_word``) asks for one view. A view before the last is answered by
CAPTURED_SEQ = seq with STATE 4 VIEWS and no ACK_SEQ (the handshake is free for the next
view; ``RobotLink.view_captured``); the last view's request is answered like a TRIGGER's with
the result over all views. A job the daemon ends between views (no next view in time) is
acknowledged under the last view's sequence, which the handshake still accepts until a new
request runs. A CAPTURE without a view 1..8 is refused BAD_REQUEST like an unknown command.

WARNINGS is not part of a result: it is the daemon's current state (like HEARTBEAT), changed
through ``RobotLink.set_warnings`` whenever a warning rises or clears, and neither a new job nor
CLEAR touches it. The daemon sets it before it publishes the job that changed it, so a peer that
sees ``ACK_SEQ == seq`` reads a WARNINGS that already counts that job.

Conveyor (map version 4, ``map_version = 4`` in the link's options; docs/conveyor.md): the
PLC writes LATCH_COUNT (and LATCH_FRAME) before or with the write that changes REQ_SEQ; the
request takes the values in place at that moment. ``Command.PREDICT`` (5) asks where the part
last served to this link will be at count N = LATCH_COUNT. 50-61 are part of the result (belt
fields, cleared with it, written before ACK_SEQ; all 0 for a part that stands still). A
version 3 link serves 0-45 as before and refuses addresses beyond.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import struct
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from vgripd.errors import LinkError
from vgripd.peer.jobcore import (
    UNKNOWN_SCORE,
    Action,
    Decision,
    Handshake,
    Part,
    PickPosition,
    Step,
    pick_position,
)
from vgripd.types import JobResult, Status


class Reg(enum.IntEnum):
    """Start address of each register (see the module docstring for types and meaning)."""

    CMD = 0
    REQ_SEQ = 1
    RECIPE = 2
    MAP_VERSION = 3
    CHECK_U16 = 4
    CHECK_U32 = 5
    CHECK_F32 = 7
    VALUE_FORMAT = 9
    VALUE_SCALE = 10
    HEARTBEAT = 12
    STATE = 13
    CAPTURED_SEQ = 14
    REJECT_SEQ = 15
    REJECT_CODE = 16
    ACK_SEQ = 17
    STATUS = 18
    JOB_ID = 19
    RESULT_AGE_MS = 21
    N_VALUES = 23
    VALUES = 24
    FIT_RMS = 38
    WARNINGS = 40
    COUNT = 41
    INDEX = 42
    PICK_ID = 43
    SCORE = 44
    LATCH_COUNT = 46
    LATCH_FRAME = 48
    RESULT_COUNT = 50
    LATCH_SOURCE = 52
    LATCH_ERR_MM = 53
    ALONG = 55
    ACROSS = 57
    THETA = 59
    QUEUED = 61


class Warnings(enum.IntFlag):
    """Bits of the WARNINGS register (and of ``RobotLink.set_warnings``). Unlisted bits are
    reserved and always 0."""

    RECALIBRATE = 1  # the daemon's rolling epipolar warning: the stereo rig may have moved


# 1 -> 2: WARNINGS (register 40) added; 2 -> 3: the pick list (41-45) and Command.NEXT.
# 3 -> 4: the conveyor's latch (46-49, writable) and belt result (50-61), Command.PREDICT.
# None moved or changed a register of the version before.
MAP_VERSION = 4
MAP_VERSIONS = (3, 4)
MAP_SIZE = 46  # map version 3 (the default ``map_version``)
MAP_SIZE_V4 = 62
#: The latch area (map version 4): written by the PLC with its request.
LATCH_AREA = range(Reg.LATCH_COUNT, Reg.RESULT_COUNT)
#: The belt result (map version 4), written with STATUS .. FIT_RMS and the pick list.
BELT_AREA = range(Reg.RESULT_COUNT, MAP_SIZE_V4)


def map_size(version: int) -> int:
    """Words of register map ``version`` (3 or 4)."""
    return MAP_SIZE_V4 if version >= 4 else MAP_SIZE


def register_name(address: int) -> str:
    """``"46 (LATCH_COUNT)"``: an address and the register it belongs to, for messages."""
    name = next((r.name for r in reversed(Reg) if r.value <= address), "?")
    return f"{address} ({name})"

#: The result area after WARNINGS (COUNT .. SCORE), written with STATUS .. FIT_RMS.
PICK_AREA = range(Reg.COUNT, MAP_SIZE)
MAX_VALUES = 7  # ABB/quaternion conventions: XYZ + 4; the others use 6
COMMAND_AREA = range(Reg.CMD, Reg.RECIPE + 1)
CHECK_U16 = 0x1234
CHECK_U32 = 0x12345678
CHECK_F32 = 123.456
NO_AGE = 0xFFFFFFFF
FIT_RMS_KEY = "fit_rms_mm"  # the JobResult.residuals entry shown in FIT_RMS


WordOrder = Literal["ABCD", "CDAB"]
ValueFormat = Literal["float32", "int32"]


class RegisterOptions(BaseModel):
    """Options every register-based link shares (a link's ``Options`` extends this model).

    ``word_order``: ``ABCD`` high word first (Siemens, most PLCs), ``CDAB`` low word first.
    ``value_format``: ``int32`` for PLCs without floats; raw = round(value * ``scale``).
    ``map_version``: 3 (0-45, the default: a block sized for it keeps working) or 4 (0-61:
    the conveyor's latch and belt result).
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    word_order: WordOrder = "ABCD"
    value_format: ValueFormat = "float32"
    scale: int = Field(10000, ge=1, le=1_000_000)
    heartbeat_ms: int = Field(500, ge=100, le=1000)
    map_version: Literal[3, 4] = 3


class RegisterAccessError(LinkError):
    """A peer addressed registers that do not exist or may not be written."""


class RegisterOverflowError(LinkError):
    """A value cannot be represented in the configured register format."""


class RegisterCapacityError(LinkError):
    """A result has more pose values than the VALUES registers hold (``REGISTER_CAPABILITIES``
    refuses such a config at load time, so this is a bug, not a job outcome)."""


@dataclass(frozen=True)
class BlockWrite:
    """``words`` written at ``address`` in one step."""

    address: int
    words: tuple[int, ...]


class ValueCodec:
    """Encodes 32-bit items into two words in the configured word order (and back, for tests
    and the mock PLC's own cross-checks)."""

    def __init__(self, word_order: WordOrder = "ABCD", value_format: ValueFormat = "float32",
                 scale: int = 10000) -> None:
        self.word_order = word_order
        self.value_format = value_format
        self.scale = scale

    def _words(self, raw: bytes) -> tuple[int, int]:
        hi, lo = struct.unpack(">HH", raw)
        return (hi, lo) if self.word_order == "ABCD" else (lo, hi)

    def _bytes(self, words: Sequence[int]) -> bytes:
        first, second = words
        hi, lo = (first, second) if self.word_order == "ABCD" else (second, first)
        return struct.pack(">HH", hi, lo)

    def u32(self, value: int) -> tuple[int, int]:
        return self._words(struct.pack(">I", value))

    def f32(self, value: float, where: str = "value") -> tuple[int, int]:
        if not math.isfinite(value):
            raise RegisterOverflowError(f"{where}: {value} is not a finite number")
        try:
            raw = struct.pack(">f", value)
        except OverflowError:
            raise RegisterOverflowError(f"{where}: {value} exceeds the float32 range") from None
        return self._words(raw)

    def i32_scaled(self, value: float, where: str = "value") -> tuple[int, int]:
        if not math.isfinite(value):
            raise RegisterOverflowError(f"{where}: {value} is not a finite number")
        raw = round(value * self.scale)
        if not -(2**31) <= raw < 2**31:
            raise RegisterOverflowError(
                f"{where}: {value} x {self.scale} = {raw} does not fit an int32"
            )
        return self._words(struct.pack(">i", raw))

    def value(self, value: float, where: str = "value") -> tuple[int, int]:
        """A pose/residual value in the configured ``value_format``."""
        if self.value_format == "float32":
            return self.f32(value, where)
        return self.i32_scaled(value, where)

    def decode_u32(self, words: Sequence[int]) -> int:
        result: int = struct.unpack(">I", self._bytes(words))[0]
        return result

    def decode_value(self, words: Sequence[int]) -> float:
        if self.value_format == "float32":
            result: float = struct.unpack(">f", self._bytes(words))[0]
            return result
        raw: int = struct.unpack(">i", self._bytes(words))[0]
        return raw / self.scale


class RegisterImage:
    """The word block a register server serves. Every change goes through ``apply``.

    ``journal``: when a list is given, every applied ``BlockWrite`` is appended to it (tests
    check the ordering rules with it).
    """

    def __init__(self, codec: ValueCodec, journal: list[BlockWrite] | None = None,
                 version: int = 3) -> None:
        self.codec = codec
        self.version = version
        self.size = map_size(version)
        self.words = [0] * self.size
        self.journal = journal
        self._t_result_ns: int | None = None
        fmt = 1 if codec.value_format == "float32" else 2
        scale = 0 if codec.value_format == "float32" else codec.scale
        self.apply([
            BlockWrite(Reg.MAP_VERSION, (version, CHECK_U16, *codec.u32(CHECK_U32),
                                         *codec.f32(CHECK_F32), fmt, *codec.u32(scale))),
            BlockWrite(Reg.RESULT_AGE_MS, codec.u32(NO_AGE)),
        ])

    def apply(self, writes: Sequence[BlockWrite]) -> None:
        for write in writes:
            end = write.address + len(write.words)
            if not (0 <= write.address < end <= self.size):
                raise RegisterAccessError(f"block write {write.address}..{end - 1} outside the map")
            self.words[write.address:end] = write.words
            if self.journal is not None:
                self.journal.append(write)

    def check_read(self, address: int, count: int) -> None:
        """``RegisterAccessError`` unless ``address .. address+count-1`` lies in the map."""
        if count < 1 or address < 0 or address + count > self.size:
            raise RegisterAccessError(
                f"read of {count} registers at {address} outside 0..{self.size - 1} (map "
                f"version {self.version})"
            )

    def read(self, address: int, count: int, now_ns: int) -> list[int]:
        """Words ``address .. address+count-1``, with ``RESULT_AGE_MS`` brought up to ``now_ns``."""
        self.check_read(address, count)
        if self._t_result_ns is not None:
            age_ms = min((now_ns - self._t_result_ns) // 1_000_000, NO_AGE - 1)
            self.words[Reg.RESULT_AGE_MS:Reg.RESULT_AGE_MS + 2] = self.codec.u32(max(age_ms, 0))
        return self.words[address:address + count]

    def set_result_time(self, t_ns: int | None) -> None:
        """Start (or with None, stop) the live ``RESULT_AGE_MS`` clock."""
        self._t_result_ns = t_ns

    def result_words(self, result: JobResult) -> tuple[int, ...]:
        """``STATUS .. FIT_RMS`` for ``result``; raises ``RegisterOverflowError`` when a value
        does not fit the register format and ``RegisterCapacityError`` when there are more
        values than registers (the caller then publishes a failure, never a wrapped number)."""
        values: tuple[float, ...] = ()
        if result.status.pose_valid and result.target is not None:
            values = result.target.values
            if len(values) > MAX_VALUES:
                raise RegisterCapacityError(
                    f"{len(values)} pose values ({result.target.vendor}) do not fit the "
                    f"{MAX_VALUES} VALUES registers"
                )
        value_words: list[int] = []
        for i, v in enumerate(values):
            value_words += self.codec.value(v, f"register {Reg.VALUES + 2 * i} (VALUES[{i}])")
        value_words += [0] * (2 * MAX_VALUES - len(value_words))
        rms = result.residuals.get(FIT_RMS_KEY, -1.0)
        return (
            int(result.status),
            *self.codec.u32(result.job_id & 0xFFFFFFFF),
            *self.codec.u32(0),  # RESULT_AGE_MS: restarted by set_result_time
            len(values),
            *value_words,
            *self.codec.value(rms, f"register {Reg.FIT_RMS} (FIT_RMS)"),
        )

    def empty_result_words(self) -> tuple[int, ...]:
        """``STATUS .. FIT_RMS`` meaning "no result"."""
        return (int(Status.IDLE), 0, 0, *self.codec.u32(NO_AGE), 0,
                *([0] * (Reg.WARNINGS - Reg.VALUES)))

    def pick_words(self, position: PickPosition) -> tuple[int, ...]:
        """``COUNT .. SCORE`` for ``position``; COUNT and INDEX beyond a word are a bug (the
        config bounds ``picking.max_objects``) and raise ``RegisterOverflowError``."""
        for name, v in (("COUNT", position.count), ("INDEX", position.index),
                        ("PICK_ID", position.pick_id)):
            if not 0 <= v <= 0xFFFF:
                raise RegisterOverflowError(f"register {Reg[name]} ({name}): {v} is not a u16")
        return (position.count, position.index, position.pick_id,
                *self.codec.value(position.score, f"register {Reg.SCORE} (SCORE)"))

    def empty_pick_words(self) -> tuple[int, ...]:
        """``COUNT .. SCORE`` meaning "no result" (all 0, like the result area)."""
        return (0,) * len(PICK_AREA)

    def belt_words(self, result: JobResult) -> tuple[int, ...]:
        """``RESULT_COUNT .. QUEUED`` (map version 4) for ``result``: all 0 without a belt."""
        belt = result.belt
        if belt is None:
            return (0,) * len(BELT_AREA)
        values: list[int] = []
        for reg, v in ((Reg.LATCH_ERR_MM, belt.error_mm), (Reg.ALONG, belt.along_mm),
                       (Reg.ACROSS, belt.across_mm), (Reg.THETA, belt.theta_deg)):
            values += self.codec.value(v, f"register {register_name(reg)}")
        return (*self.codec.u32(belt.count & 0xFFFFFFFF), belt.source & 0xFFFF, *values,
                min(belt.queued, 0xFFFF))

    def clear_result(self) -> list[BlockWrite]:
        """The writes that empty the whole result area (18-39, 41-45 and in map version 4
        50-61; WARNINGS stays)."""
        writes = [BlockWrite(Reg.STATUS, self.empty_result_words()),
                  BlockWrite(Reg.COUNT, self.empty_pick_words())]
        if self.version >= 4:
            writes.append(BlockWrite(Reg.RESULT_COUNT, (0,) * len(BELT_AREA)))
        return writes

    def result_writes(self, result: JobResult, position: PickPosition) -> list[BlockWrite]:
        """The data writes of a published result (before STATE and ACK_SEQ)."""
        writes = [BlockWrite(Reg.STATUS, self.result_words(result)),
                  BlockWrite(Reg.COUNT, self.pick_words(position))]
        if self.version >= 4:
            writes.append(BlockWrite(Reg.RESULT_COUNT, self.belt_words(result)))
        return writes


class RegisterBank:
    """Register image + handshake: everything a register server link does except the I/O.

    Each method changes the image in one call (no awaits in between), so a server that calls
    it on its event loop is atomic with respect to the read requests it serves on that loop.
    """

    def __init__(self, codec: ValueCodec, journal: list[BlockWrite] | None = None,
                 version: int = 3) -> None:
        self.image = RegisterImage(codec, journal, version)
        self.handshake = Handshake()
        self._heartbeat = 0
        #: requests refused by the handshake (REJECT_SEQ/REJECT_CODE), by status name
        self.refusals: Counter[str] = Counter()

    def read(self, address: int, count: int, now_ns: int) -> list[int]:
        return self.image.read(address, count, now_ns)

    def writable(self) -> tuple[range, ...]:
        """The areas a peer may write: the command area, and in map version 4 the latch."""
        return (COMMAND_AREA, LATCH_AREA) if self.image.version >= 4 else (COMMAND_AREA,)

    def write(self, address: int, values: Sequence[int]) -> Decision:
        """A peer's write. Only the command area (and in map version 4 the latch area) is
        writable, each write inside one of them; raises ``RegisterAccessError`` naming the
        first register that may not be written."""
        end = address + len(values)
        areas = self.writable()
        if not values or not any(a.start <= address and end <= a.stop for a in areas):
            bad = next((a for a in range(address, max(end, address + 1))
                        if not any(a in area for area in areas)), address)
            allowed = " and ".join(f"{a.start}..{a.stop - 1} ({n} area)"
                                   for a, n in zip(areas, ("command", "latch"), strict=False))
            what = ("a write spans two areas" if not values or bad >= end else
                    f"register {register_name(bad)} is read-only" if bad < self.image.size
                    else f"register {bad} is outside map version {self.image.version}")
            raise RegisterAccessError(
                f"write of {len(values)} registers at {address}: {what}; only {allowed} are "
                "writable"
            )
        if any(not 0 <= v <= 0xFFFF for v in values):
            raise RegisterAccessError(f"write at {address}: values must be 0..65535")
        self.image.apply([BlockWrite(address, tuple(values))])
        if not address <= Reg.REQ_SEQ < end:
            return Decision(Action.IGNORE)
        w = self.image.words
        decision = self.handshake.on_request(w[Reg.CMD], w[Reg.REQ_SEQ], w[Reg.RECIPE])
        self.apply(decision.steps)
        if decision.action is Action.REJECT:
            self.refusals[decision.code.name] += 1
        if self.image.version >= 4 and decision.action is Action.START:
            codec = self.image.codec
            decision = dataclasses.replace(
                decision, count=codec.decode_u32(w[Reg.LATCH_COUNT:Reg.LATCH_COUNT + 2]),
                frame=codec.decode_u32(w[Reg.LATCH_FRAME:Reg.LATCH_FRAME + 2]))
        return decision

    def published_count(self, address: int, words: Sequence[int]) -> int | None:
        """LATCH_COUNT in a peer's ``words`` (a write or a read starting at ``address``) when
        they hold both of its words, in map version 4; else None (half a count is none)."""
        i = Reg.LATCH_COUNT - address
        if self.image.version < 4 or i < 0 or i + 2 > len(words):
            return None
        return self.image.codec.decode_u32(words[i:i + 2])

    def view_captured(self, seq: int, job_id: int) -> None:
        """View request ``seq`` has its image: JOB_ID, STATE 4 VIEWS, then CAPTURED_SEQ."""
        self.apply(self.handshake.on_view_captured(seq, job_id))

    def captured(self, seq: int, job_id: int) -> None:
        """Request ``seq`` has its image: JOB_ID, STATE 2 BUSY, then CAPTURED_SEQ."""
        self.apply(self.handshake.on_captured(seq, job_id))

    def publish(self, seq: int, result: JobResult, now_ns: int) -> JobResult:
        """Publish ``result`` for request ``seq``: data, then ``STATE``, then ``ACK_SEQ``.

        A value that does not fit the register format turns the result into ``OUT_OF_LIMITS``
        without a pose; more values than registers (a bug: the config check refuses such a
        vendor) into ``INTERNAL``. Returns the result actually published.
        """
        self.handshake.check_running(seq, "publish")
        position = pick_position(result)
        try:
            self.image.result_writes(result, position)
        except (RegisterOverflowError, RegisterCapacityError) as err:
            status = (Status.OUT_OF_LIMITS if isinstance(err, RegisterOverflowError)
                      else Status.INTERNAL)
            result = JobResult(job_id=result.job_id, status=status, message=str(err),
                               t_done_mono_ns=result.t_done_mono_ns)
            # The list stays walkable past an instance the registers cannot show (its INDEX
            # still says which one it was); a bad COUNT/INDEX itself leaves no list.
            position = dataclasses.replace(position, score=UNKNOWN_SCORE)
            try:
                self.image.pick_words(position)
            except RegisterOverflowError:
                position = PickPosition(0, 0, 0, 0.0)  # the words of an empty pick area
        self.apply(self.handshake.publish(seq, result, position), now_ns)
        return result

    def apply(self, steps: Sequence[Step], now_ns: int = 0) -> None:
        """Write the handshake's ``steps`` into the image, in their order, in one call."""
        image = self.image
        writes: list[BlockWrite] = []
        t_result: int | None = None
        for step in steps:
            if step.part is Part.RETRACT:
                writes.append(BlockWrite(Reg.ACK_SEQ, (0,)))
            elif step.part is Part.CLEAR:
                writes += image.clear_result()
            elif step.part is Part.JOB_ID:
                writes.append(BlockWrite(Reg.JOB_ID, image.codec.u32(step.value & 0xFFFFFFFF)))
            elif step.part is Part.RESULT:
                assert step.result is not None
                assert step.position is not None
                writes += image.result_writes(step.result, step.position)
                t_result = step.result.t_done_mono_ns or now_ns
            elif step.part is Part.STATE:
                writes.append(BlockWrite(Reg.STATE, (step.value,)))
            elif step.part is Part.CAPTURED:
                writes.append(BlockWrite(Reg.CAPTURED_SEQ, (step.seq,)))
            elif step.part is Part.REJECT:
                writes += [BlockWrite(Reg.REJECT_CODE, (step.value,)),
                           BlockWrite(Reg.REJECT_SEQ, (step.seq,))]
            elif step.part is Part.ACK:
                writes.append(BlockWrite(Reg.ACK_SEQ, (step.seq,)))
        image.apply(writes)
        if any(step.part is Part.CLEAR for step in steps):
            image.set_result_time(None)
        if t_result is not None:
            image.set_result_time(t_result)

    def beat(self) -> int:
        self._heartbeat = (self._heartbeat + 1) & 0xFFFF
        self.image.apply([BlockWrite(Reg.HEARTBEAT, (self._heartbeat,))])
        return self._heartbeat

    def set_warnings(self, bits: int) -> None:
        """WARNINGS = ``bits``; ``LinkError`` for a bit that ``Warnings`` does not define."""
        self.image.apply([BlockWrite(Reg.WARNINGS, (checked_warnings(bits),))])


def checked_warnings(bits: int) -> int:
    """``bits`` as a WARNINGS word; ``LinkError`` when it sets a reserved bit."""
    known = sum(int(w) for w in Warnings)
    if not 0 <= bits <= 0xFFFF or bits & ~known:
        raise LinkError(f"warnings {bits:#x}: only bits {known:#x} (Warnings) are defined")
    return bits
