"""The robot socket message format (``robot_socket`` link, docs/robot_socket.md), with no I/O.

A robot program and vgripd exchange fixed-length binary frames over one TCP connection: the
robot sends 16-byte requests (44 bytes for CAPTURE_AT, which carries a pose; 24 for a counted
request, which carries the conveyor's encoder count), vgripd answers with 64-byte frames.
Every field is a 32-bit big-endian word, so a robot language that reads integers more easily
than bytes (KRL through EthernetKRL, Karel, URScript's ``socket_read_binary_integer``,
MotoPlus C) reads a request or an answer as 4 or 16 integers. Pose values are int32
fixed-point (``raw = round(value * scale)``, scale a power of ten) or, for languages that
unpack IEEE floats directly (RAPID's ``UnpackRawBytes \\Float4``), float32.

Request, robot -> vgripd (16 bytes; CAPTURE_AT 44 bytes; counted requests 24 bytes)::

    word  bytes  field
       0   0-3   header: "V" "G" version command (0x56 0x47 0x01 cc); command 1 LOCATE,
                 2 CLEAR, 3 NEXT (the next object of the last LOCATE's pick list),
                 4 CAPTURE_AT (LOCATE with the flange pose the robot reached)
       1   4-7   request id, 1 .. 2**31-1, echoed in every answer to this request
       2   8-11  recipe, 0 .. 65535 (0 = default), handed to the job like the RECIPE register
       3  12-15  reserved, 0
     4-10 16-43  CAPTURE_AT only: the flange pose in the base frame (no tool), 7 values in the
                 output vendor's convention and units and in the link's value encoding, as
                 answer words 6-12 (6-value conventions send 0 as the 7th)
       4  16-19  counted requests only (command + 0x40: LOCATE 0x41, NEXT 0x43, PREDICT 0x45):
                 the encoder count (u32; LOCATE: latched at the exposure, NEXT: now, PREDICT:
                 the count N to predict the served part for)
       5  20-23  counted requests only: the camera frame id the count belongs to
                 (``conveyor.latch = "frame_id"``), else 0

Answer, vgripd -> robot (64 bytes)::

    word  bytes  field
       0   0-3   header: "V" "G" version kind; kind 0x81 CAPTURED, 0x82 RESULT, 0x83 REFUSED
       1   4-7   request id of the request answered
       2   8-11  status (``vgripd.types.Status``)
       3  12-15  job id (u32; 0 when no job ran)
       4  16-19  warnings (``vgripd.peer.registers.Warnings`` bits, live)
       5  20-23  count: valid pose values, 0, 6 or 7
       6  24-51  7 values in the output vendor's convention and units (int32 scaled or float32)
      13  52-55  fit RMS in mm, same encoding; -1 = unknown
      14  56-59  scale of the int32 values; 0 = the values are float32
      15  60-63  remaining objects: pickable objects of the job after the one in this
                 answer (0 without a pick list, on the last one and past the end)

A request is answered exactly once with a final frame (RESULT or REFUSED), for LOCATE preceded by
CAPTURED once the images are taken (the robot may move on). The final frame of a counted request
is preceded by one BELT frame (kind 0x84; docs/robot_socket.md, "Conveyor"): the request id,
RESULT_COUNT, LATCH_SOURCE, LATCH_ERR_MM, ALONG, ACROSS, THETA and QUEUED of register map
version 4 (all 0 when no job ran or the part stands still), so every answer stays 64 bytes.
REFUSED means no job ran: BUSY (a job is running), BAD_REQUEST (unknown command, id 0, recipe
> 65535, reserved word not 0, NEXT without a pick list, PREDICT without a count or a
conveyor), or the daemon's own refusal. NEXT is answered RESULT without CAPTURED (no
image is taken): the following pickable object of the last LOCATE, with that job's id, or
NOT_FOUND without a pose once the list is used up. CAPTURE_AT is a LOCATE whose job gets the
flange pose (``Trigger.T_base_flange``: a robot-mounted camera's pose; in a walked hand-eye
calibration the pose recorded with the image); a pose that is not a transform (a value not
finite, a quaternion whose norm is off 1, a 7th value not 0 for a 6-value convention) is
REFUSED BAD_REQUEST. A frame that is not a request at all (wrong magic or version) ends the
connection: the stream cannot be trusted after it. The length of a request follows from its
command byte, so a CAPTURE_AT sent short stalls (the link's ``frame_timeout_s`` closes the
connection) and one sent long leaves bytes that are not a request (closed too).
"""

from __future__ import annotations

import enum
import math
import struct
from dataclasses import dataclass
from typing import Literal

from vgripd.peer.jobcore import PickPosition, pick_position
from vgripd.peer.registers import FIT_RMS_KEY
from vgripd.types import BeltPose, JobResult, Status

VERSION = 1
MAGIC = 0x5647  # "VG"
REQUEST_SIZE = 16
CAPTURE_AT_SIZE = REQUEST_SIZE + 4 * 7  # the request and 7 pose value words
COUNTED = 0x40  # command flag: the request carries the encoder count and frame id
COUNTED_SIZE = REQUEST_SIZE + 4 * 2
ANSWER_SIZE = 64
N_VALUES = 7
MAX_REQUEST_ID = 2**31 - 1
MAX_RECIPE = 0xFFFF
UNKNOWN_RMS = -1.0

#: Any 6- or 7-value convention: the robot program reads plain numbers in its own convention.

ValueFormat = Literal["int32", "float32"]


class SocketCommand(enum.IntEnum):
    LOCATE = 1
    CLEAR = 2
    NEXT = 3  # the next object of the last LOCATE's pick list (``Command.NEXT``)
    CAPTURE_AT = 4  # LOCATE with the flange pose reached (``Command.TRIGGER`` + the pose)
    PREDICT = 5  # a conveyor part's pose at count N (``Command.PREDICT``); counted only


class AnswerKind(enum.IntEnum):
    CAPTURED = 0x81
    RESULT = 0x82
    REFUSED = 0x83
    BELT = 0x84  # a counted request's belt words, before its final frame


def header_word(code: int) -> int:
    """Word 0 of a frame: "VG", the version and a command or answer kind."""
    return (MAGIC << 16) | (VERSION << 8) | (code & 0xFF)


class FrameError(ValueError):
    """Bytes that are not a frame of this protocol (the connection is closed)."""


class ValueOverflowError(ValueError):
    """A value that the answer's value format cannot represent."""


def request_size(header: bytes) -> int:
    """The length of the request whose first bytes (at least 4) are ``header``: 44 for
    CAPTURE_AT, 24 for a command byte with the ``COUNTED`` flag, 16 for every other command
    (an unknown one is refused as a request of that length)."""
    if header[3] == SocketCommand.CAPTURE_AT:
        return CAPTURE_AT_SIZE
    return COUNTED_SIZE if header[3] & COUNTED else REQUEST_SIZE


@dataclass(frozen=True)
class Request:
    command: int
    request_id: int
    recipe: int = 0
    reserved: int = 0
    #: CAPTURE_AT: the 7 pose values (decoded with the link's encoding)
    values: tuple[float, ...] = ()
    #: A counted request (``COUNTED``): the encoder count (u32) and the frame id; None: none
    count: int | None = None
    frame: int = 0

    def encode(self, encoding: ValueEncoding | None = None) -> bytes:
        """The frame; CAPTURE_AT with its 7 values in ``encoding`` (default int32 x 10000), a
        counted request (``count`` not None) with its command flagged and its two words."""
        code = self.command | (COUNTED if self.count is not None else 0)
        head = struct.pack(">4I", header_word(code), self.request_id, self.recipe,
                           self.reserved)
        if self.count is not None:
            return head + struct.pack(">2I", self.count & 0xFFFFFFFF, self.frame & 0xFFFFFFFF)
        if self.command != SocketCommand.CAPTURE_AT:
            return head
        enc = encoding or ValueEncoding()
        values = tuple(self.values) + (0.0,) * (N_VALUES - len(self.values))
        return head + b"".join(enc.encode(v, f"value {i}") for i, v in enumerate(values))

    def refusal(self) -> Status | None:
        """``BAD_REQUEST`` when the request is well framed but cannot be served; else None."""
        if self.count is not None:  # the conveyor's commands; PREDICT needs its count
            if self.command not in (SocketCommand.LOCATE, SocketCommand.NEXT,
                                    SocketCommand.PREDICT):
                return Status.BAD_REQUEST
        elif self.command not in (SocketCommand.LOCATE, SocketCommand.CLEAR, SocketCommand.NEXT,
                                  SocketCommand.CAPTURE_AT):
            return Status.BAD_REQUEST
        if not 1 <= self.request_id <= MAX_REQUEST_ID:
            return Status.BAD_REQUEST
        if not 0 <= self.recipe <= MAX_RECIPE or self.reserved != 0:
            return Status.BAD_REQUEST
        return None


def decode_request(frame: bytes, encoding: ValueEncoding | None = None) -> Request:
    """A request frame (CAPTURE_AT's values decoded with ``encoding``, default int32 x 10000);
    ``FrameError`` when it is not one (magic, version, a size its command does not have)."""
    if len(frame) < 4:
        raise FrameError(f"a request is at least {REQUEST_SIZE} bytes, got {len(frame)}")
    size = request_size(frame)
    if len(frame) != size:
        raise FrameError(f"a request with command {frame[3]} is {size} bytes, got {len(frame)}")
    header, request_id, recipe, reserved = struct.unpack_from(">4I", frame)
    check_header(header, "request")
    values: tuple[float, ...] = ()
    if size == CAPTURE_AT_SIZE:
        enc = encoding or ValueEncoding()
        values = tuple(enc.decode(frame[16 + 4 * i:20 + 4 * i]) for i in range(N_VALUES))
    if size == COUNTED_SIZE:
        count, frame_id = struct.unpack_from(">2I", frame, REQUEST_SIZE)
        return Request(header & 0xFF & ~COUNTED, request_id, recipe, reserved, (), count,
                       frame_id)
    return Request(header & 0xFF, request_id, recipe, reserved, values)


def flange_values(request: Request, n_fields: int) -> tuple[float, ...]:
    """The pose values of a CAPTURE_AT for a convention of ``n_fields`` values;
    ``ValueError`` naming the word when a 6-value convention's 7th value is not 0."""
    extra = request.values[n_fields:]
    for i, v in enumerate(extra, start=n_fields):
        if v != 0:
            raise ValueError(f"word {4 + i} (value {i}) is {v:g}: the convention has "
                             f"{n_fields} values, the rest must be 0")
    return request.values[:n_fields]


def check_header(header: int, what: str) -> None:
    magic, version = header >> 16, (header >> 8) & 0xFF
    if magic != MAGIC:
        raise FrameError(f"{what} starts with {header >> 16:#06x}, not 'VG' (0x5647)")
    if version != VERSION:
        raise FrameError(f"{what} has protocol version {version}, this is version {VERSION}")


@dataclass(frozen=True)
class ValueEncoding:
    """How pose values travel: ``int32`` scaled (``raw = round(value * scale)``) or float32."""

    value_format: ValueFormat = "int32"
    scale: int = 10000

    def __post_init__(self) -> None:
        if self.value_format == "int32" and not is_power_of_ten(self.scale):
            raise ValueError(f"scale {self.scale} must be a power of ten, 1 .. 1e9")

    @property
    def scale_word(self) -> int:
        return self.scale if self.value_format == "int32" else 0

    def encode(self, value: float, where: str = "value") -> bytes:
        if not math.isfinite(value):
            raise ValueOverflowError(f"{where}: {value} is not a finite number")
        if self.value_format == "float32":
            try:
                return struct.pack(">f", value)
            except OverflowError:
                raise ValueOverflowError(f"{where}: {value} exceeds the float32 range") from None
        raw = round(value * self.scale)
        if not -(2**31) <= raw < 2**31:
            raise ValueOverflowError(
                f"{where}: {value} x {self.scale} = {raw} does not fit an int32")
        return struct.pack(">i", raw)

    def decode(self, raw: bytes) -> float:
        if self.value_format == "float32":
            value: float = struct.unpack(">f", raw)[0]
            return value
        return int(struct.unpack(">i", raw)[0]) / self.scale


def is_power_of_ten(n: int) -> bool:
    return n in {10**e for e in range(10)}


@dataclass(frozen=True)
class Answer:
    kind: AnswerKind
    request_id: int
    status: int
    job_id: int = 0
    warnings: int = 0
    values: tuple[float, ...] = ()
    fit_rms_mm: float = UNKNOWN_RMS
    remaining: int = 0

    def encode(self, encoding: ValueEncoding) -> bytes:
        """The 64-byte frame; ``ValueOverflowError`` when a pose value does not fit (the fit
        RMS does not fail an answer: it becomes -1)."""
        if len(self.values) > N_VALUES:
            raise ValueOverflowError(f"{len(self.values)} pose values, the answer holds "
                                     f"{N_VALUES}")
        values = b"".join(encoding.encode(v, f"word {6 + i} (value {i})")
                          for i, v in enumerate(self.values))
        values += encoding.encode(0.0) * (N_VALUES - len(self.values))
        try:
            rms = encoding.encode(self.fit_rms_mm, "fit RMS")
        except ValueOverflowError:
            rms = encoding.encode(UNKNOWN_RMS)
        return (struct.pack(">6I", header_word(self.kind), self.request_id, self.status,
                            self.job_id & 0xFFFFFFFF, self.warnings, len(self.values))
                + values + rms + struct.pack(">2I", encoding.scale_word, self.remaining))


def decode_answer(frame: bytes) -> Answer:
    """An answer frame, values decoded by its own scale word; ``FrameError`` when it is not
    one. What a robot program reads, for tests and the emulation clients."""
    if len(frame) != ANSWER_SIZE:
        raise FrameError(f"an answer is {ANSWER_SIZE} bytes, got {len(frame)}")
    header, request_id, status, job_id, warnings, count = struct.unpack_from(">6I", frame)
    check_header(header, "answer")
    try:
        kind = AnswerKind(header & 0xFF)
    except ValueError:
        raise FrameError(f"answer kind {header & 0xFF:#04x} is not 0x81..0x84") from None
    if kind is AnswerKind.BELT:
        raise FrameError("a BELT frame (0x84) is read with decode_belt")
    scale, remaining = struct.unpack_from(">2I", frame, 56)
    if count > N_VALUES:
        raise FrameError(f"answer count {count} exceeds {N_VALUES}")
    encoding = ValueEncoding("int32", scale) if scale else ValueEncoding("float32")
    values = tuple(encoding.decode(frame[24 + 4 * i:28 + 4 * i]) for i in range(count))
    return Answer(kind, request_id, status, job_id, warnings, values,
                  encoding.decode(frame[52:56]), remaining)


@dataclass(frozen=True)
class BeltFrame:
    """The BELT frame (kind 0x84) before a counted request's final frame: register map
    version 4's belt result (``vgripd.types.BeltPose``), lengths in mm and angles in deg in
    the link's value encoding whatever ``output.vendor``'s units are.

    Words: 0 header, 1 request id, 2 RESULT_COUNT (u32), 3 LATCH_SOURCE, 4 LATCH_ERR_MM,
    5 ALONG, 6 ACROSS, 7 THETA, 8 QUEUED, 9-13 reserved 0, 14 the scale word, 15 reserved 0.
    """

    request_id: int
    count: int = 0
    source: int = 0
    error_mm: float = 0.0
    along_mm: float = 0.0
    across_mm: float = 0.0
    theta_deg: float = 0.0
    queued: int = 0

    @classmethod
    def of(cls, request_id: int, belt: BeltPose | None) -> BeltFrame:
        if belt is None:
            return cls(request_id)
        return cls(request_id, belt.count & 0xFFFFFFFF, belt.source, belt.error_mm,
                   belt.along_mm, belt.across_mm, belt.theta_deg, belt.queued)

    def encode(self, encoding: ValueEncoding) -> bytes:
        """The 64-byte frame; ``ValueOverflowError`` naming the word that does not fit."""
        values = b"".join(encoding.encode(v, f"BELT word {4 + i} ({name})") for i, (name, v) in
                          enumerate((("LATCH_ERR_MM", self.error_mm), ("ALONG", self.along_mm),
                                     ("ACROSS", self.across_mm), ("THETA", self.theta_deg))))
        return (struct.pack(">4I", header_word(AnswerKind.BELT), self.request_id, self.count,
                            self.source) + values
                + struct.pack(">7I", min(self.queued, 0xFFFFFFFF), 0, 0, 0, 0, 0,
                              encoding.scale_word) + bytes(4))


def decode_belt(frame: bytes) -> BeltFrame:
    """A BELT frame, values decoded by its own scale word; ``FrameError`` when it is not one."""
    if len(frame) != ANSWER_SIZE:
        raise FrameError(f"a BELT frame is {ANSWER_SIZE} bytes, got {len(frame)}")
    header, request_id, count, source = struct.unpack_from(">4I", frame)
    check_header(header, "BELT frame")
    if header & 0xFF != AnswerKind.BELT:
        raise FrameError(f"answer kind {header & 0xFF:#04x} is not BELT (0x84)")
    scale = struct.unpack_from(">I", frame, 56)[0]
    encoding = ValueEncoding("int32", scale) if scale else ValueEncoding("float32")
    err, along, across, theta = (encoding.decode(frame[16 + 4 * i:20 + 4 * i])
                                 for i in range(4))
    queued = struct.unpack_from(">I", frame, 32)[0]
    return BeltFrame(request_id, count, source, err, along, across, theta, queued)


def result_answer(request_id: int, result: JobResult, warnings: int, encoding: ValueEncoding,
                  captured: bool, kind: AnswerKind | None = None,
                  counted: bool = False) -> tuple[bytes, JobResult]:
    """The final frame for ``result`` and the result actually sent; for a ``counted``
    request the BELT frame (``result.belt``) and the final frame.

    A pose or belt value that does not fit the encoding turns the answer into
    ``OUT_OF_LIMITS`` without a pose (and with a BELT frame of zeros), more values than the
    frame holds (a bug: the config check refuses such a vendor) into ``INTERNAL``. ``kind``:
    the link's handshake says (``jobcore.answer_refused``); without it a request that never
    got a job (no images, job id 0: the daemon's BUSY or ABORTED refusal) is answered
    REFUSED, every other one RESULT.
    """
    if kind is None:
        kind = AnswerKind.RESULT if captured or result.job_id else AnswerKind.REFUSED
    values: tuple[float, ...] = ()
    if result.status.pose_valid and result.target is not None:
        values = result.target.values
    rms = result.residuals.get(FIT_RMS_KEY, UNKNOWN_RMS)
    answer = Answer(kind, request_id, int(result.status), result.job_id, warnings, values, rms,
                    remaining(pick_position(result)))
    try:
        belt = BeltFrame.of(request_id, result.belt).encode(encoding) if counted else b""
        return belt + answer.encode(encoding), result
    except ValueOverflowError as err:
        status = Status.INTERNAL if len(values) > N_VALUES else Status.OUT_OF_LIMITS
        failed = JobResult(job_id=result.job_id, status=status, message=str(err),
                           t_done_mono_ns=result.t_done_mono_ns, recipe=result.recipe)
        answer = Answer(kind, request_id, int(status), result.job_id, warnings, (), rms,
                        remaining(pick_position(result)))
        belt = BeltFrame(request_id).encode(encoding) if counted else b""
        return belt + answer.encode(encoding), failed


def remaining(position: PickPosition) -> int:
    """Answer word 15: pickable objects after the one shown (0 when none is shown)."""
    if not 1 <= position.index <= position.count:
        return 0
    return position.count - position.index


# --- robot programs (robots/<brand>/, ``vgripd robot-program``) ---------------------------


@dataclass(frozen=True)
class RobotBrand:
    """One brand's generated program: what it needs from the link and how it connects.

    ``convention``: the ``output.vendor`` its pose variable is in. ``value_format``: what its
    socket instructions unpack (int32 where integers are easier: KRL, Karel, URScript,
    MotoPlus, VAL3; float32 for RAPID, whose quaternion needs more than int32 x scale gives).
    ``mode``: the link mode it pairs with (``client`` when the robot runs the server).
    ``connection``: ``kept`` (connect once, reconnect after a failure), ``per_request``
    (connect for each locate, close after its answer) or ``robot_server`` (vgripd dials in).
    ``files``: the templates in ``robots/<name>/``. ``min_scale``: the smallest int32 scale
    the program converts without losing its controller's resolution.
    """

    name: str
    title: str
    convention: str
    value_format: ValueFormat
    mode: Literal["server", "client"]
    connection: Literal["kept", "per_request", "robot_server"]
    files: tuple[str, ...]
    min_scale: int = 1


BRANDS: dict[str, RobotBrand] = {b.name: b for b in (
    RobotBrand("kuka", "KUKA KRL with KUKA.EthernetKRL", "kuka", "int32", "server", "kept",
               ("vgripd.src", "vgripd.dat", "VgripdEki.xml")),
    RobotBrand("abb", "ABB RAPID socket messaging", "abb", "float32", "server", "kept",
               ("VgripdSocket.mod",)),
    RobotBrand("fanuc", "FANUC Karel socket messaging with a TP wrapper", "fanuc", "int32",
               "server", "per_request", ("vgripd.kl", "VG_LOCATE.ls", "VG_NEXT.ls", "VG_WALK.ls",
                                          "VG_BLOC.ls", "VG_CATCH.ls")),
    RobotBrand("staubli", "Staubli VAL3 socket (sio)", "staubli", "int32", "server", "kept",
               ("vgripd.pjx", "vgripd.dtx", "vgLocate.pgx", "vgNext.pgx", "vgAsk.pgx",
                "vgRequest.pgx", "vgWalk.pgx", "vgLocateAt.pgx", "vgNextAt.pgx",
                "vgPredict.pgx", "vgIntercept.pgx")),
    RobotBrand("yaskawa", "Yaskawa MotoPlus task with an INFORM job", "yaskawa", "int32",
               "client", "robot_server",
               ("vgripd_task.c", "VGLOCATE.JBI", "VGNEXT.JBI", "VGWALK.JBI", "VGBLOC.JBI",
                "VGCATCH.JBI"), 10000),
    RobotBrand("ur", "Universal Robots URScript socket_open", "ur", "int32", "server",
               "per_request", ("vgripd_socket.script",)),
)}
