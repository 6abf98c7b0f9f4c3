"""The UR RTDE register map (``drivers/links/ur_rtde.py``, docs/ur_rtde.md), with no I/O: which
general-purpose registers carry the request, the answer, the pick list and the belt, and how
a pick position and an encoder count fit them."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from vgripd.errors import LinkError
from vgripd.peer.jobcore import MAX_VIEWS, Command, PickPosition, split_command
from vgripd.types import BeltPose, Status


@dataclass(frozen=True)
class URRegisterMap:
    """UR RTDE general-purpose registers used by the ``ur_rtde`` link (docs/ur_rtde.md).

    Numbers are for the lower range; ``upper=True`` adds 24 (ur_rtde's
    ``use_upper_range_registers``). The limits come from ur_rtde: its getters read only output
    registers 12..19 and its setters write only input registers 18..22 (23 is its own command
    word, overwritten on every write). A UR pose needs 6 doubles but only 5 input doubles are
    writable, so the pose travels in two pages of 3 (translation, then rotation vector), each
    written data first and its acknowledge last.

    Robot -> vgripd (output_int_register_N): ``seq`` (a change to a new non-zero value is a
    trigger), ``command``, ``page_request`` (= seq once the robot has read the translation),
    ``recipe`` (the job's recipe, read with the trigger; 0 = the default, docs/recipes.md).
    vgripd -> robot (input_int_register_N): ``ack`` (= seq, written last), ``status``,
    ``captured`` (seq whose images are taken), ``job_id``, ``page_ack`` (= seq once the rotation
    page is in place); input_double_register ``page`` (3 registers), ``warnings`` (the
    ``Warnings`` bits as a whole number, live like the Modbus WARNINGS register: every int
    input ur_rtde can write is taken, and a double holds a 16-bit field exactly) and ``pick``
    (the pick list: ``1000 * COUNT + INDEX`` as a whole number, ``pick_word``; written with
    the result, before ``ack``).

    ``conveyor`` (the link's ``map_version = 4``, docs/conveyor.md): the robot writes the
    encoder count it latched with the request into output_int_register ``latch`` (its 32 bits
    as UR's signed int32), and ``Command.PREDICT`` is a request too. The belt result goes
    into input registers ur_rtde cannot write, ``belt_first`` .. + 3 of both kinds, all in one
    RTDE data package of the link's own input recipe: ints ``belt_seq`` (the request the
    block answers), RESULT_COUNT (int32 bits), LATCH_SOURCE, QUEUED; doubles LATCH_ERR_MM,
    ALONG, ACROSS (mm), THETA (deg). Written before ``ack``.
    """

    upper: bool = False
    conveyor: bool = False

    #: Commands the robot program may write to ``command``: 1 = locate (run a job), 3 = next
    #: (the next instance of the last job's pick list, ``Command.NEXT``). Any other value (0,
    #: negative, unknown) is answered ``BAD_REQUEST`` without a job, as the Modbus handshake
    #: answers an unknown CMD.
    COMMANDS: ClassVar[frozenset[int]] = frozenset({1, int(Command.NEXT)})
    #: ``pick`` = PICK_BASE * COUNT + INDEX (both < PICK_BASE, ``pick_word``)
    PICK_BASE: ClassVar[int] = 1000

    def refusal(self, command: int) -> Status | None:
        """The status a request with ``command`` is refused with; None when it runs a job.
        A CAPTURE (``capture_word``: view * 256 + 4, view 1..8) is one view of a several-view
        job; the TCP pose read with it is the view's flange pose."""
        if command in self.COMMANDS or (self.conveyor and command == Command.PREDICT):
            return None
        kind, view = split_command(command)
        if kind == Command.CAPTURE and 1 <= view <= MAX_VIEWS:
            return None
        return Status.BAD_REQUEST

    def _n(self, n: int) -> int:
        return n + 24 if self.upper else n

    @property
    def seq(self) -> int:
        return self._n(12)

    @property
    def command(self) -> int:
        return self._n(13)

    @property
    def page_request(self) -> int:
        return self._n(14)

    @property
    def recipe(self) -> int:
        return self._n(15)

    @property
    def ack(self) -> int:
        return self._n(18)

    @property
    def status(self) -> int:
        return self._n(19)

    @property
    def captured(self) -> int:
        return self._n(20)

    @property
    def job_id(self) -> int:
        return self._n(21)

    @property
    def page_ack(self) -> int:
        return self._n(22)

    @property
    def page(self) -> tuple[int, int, int]:
        return (self._n(18), self._n(19), self._n(20))

    @property
    def warnings(self) -> int:
        return self._n(21)

    @property
    def pick(self) -> int:
        return self._n(22)

    @property
    def latch(self) -> int:
        return self._n(16)

    @property
    def belt_first(self) -> int:
        """First of the belt block's input registers: 24 (lower range), 30 (upper range);
        neither range's handshake uses 24..35, nor does ur_rtde's upper range (42..47)."""
        return 30 if self.upper else 24

    @property
    def belt_names(self) -> tuple[str, ...]:
        """The belt block's RTDE input names in the order of ``belt_values``."""
        b = self.belt_first
        return (*(f"input_int_register_{b + i}" for i in range(4)),
                *(f"input_double_register_{b + i}" for i in range(4)))

    @staticmethod
    def belt_values(seq: int, belt: BeltPose | None) -> tuple[int | float, ...]:
        """The belt block for the answer to ``seq``: all 0 (but ``seq``) without a belt."""
        if belt is None:
            return (seq, 0, 0, 0, 0.0, 0.0, 0.0, 0.0)
        return (seq, int32_bits(belt.count), belt.source, belt.queued, belt.error_mm,
                belt.along_mm, belt.across_mm, belt.theta_deg)

    def pick_word(self, position: PickPosition) -> float:
        """``pick`` register value: ``PICK_BASE * count + index`` (0 = no list). COUNT and
        INDEX beyond ``PICK_BASE - 1`` (a list longer than 998 instances) raise ``LinkError``."""
        if not (0 <= position.count < self.PICK_BASE and 0 <= position.index < self.PICK_BASE):
            raise LinkError(f"pick list count {position.count} / index {position.index} do not "
                            f"fit the pick register (each below {self.PICK_BASE})")
        return float(self.PICK_BASE * position.count + position.index)


def int32_bits(count: int) -> int:
    """A 32-bit encoder count as UR's signed int32 with the same bits (and back: ``& 0xFFFFFFFF``
    undoes it)."""
    count &= 0xFFFFFFFF
    return count - (1 << 32) if count >= 1 << 31 else count


