"""The Modbus request PDU answered from a register bank, with no I/O: (PDU, bank, time) in,
(reply PDU, decision) out.

Served: FC 3 read, 6 write single, 16 write multiple, 22 mask write and 23 read/write multiple
holding registers (a write reads back what it wrote for its reply). The answerer never raises
for what a peer sends; every request ends in exactly one decision that tells the shell (the
TCP or RTU link) what is left to do:

- ``Answered``: nothing (a read).
- ``Written``: registers were written; ``outcome`` is what the bank decided about it (the
  handshake: start a job, refuse a request, nothing), which the shell carries out.
- ``Refused``: answered with a Modbus exception (``reply`` is the exception PDU); the shell
  logs it with the function code, the register range and the client.
- ``Malformed``: not a well-formed request (a function code 0 or >= 0x80, a PDU length its
  function code contradicts). A stream transport cannot trust what follows and closes; a
  frame transport (RTU, CRC checked) answers ``reply``, exception 03.

Exception codes: a quantity out of range (FC3 1..125, FC16 1..123, FC23 read 1..125 and
write 1..121, byte count = 2 x quantity) is 03; a register range outside the map or a write
the bank refuses (outside the writable areas) 02; any other function code 01. FC23 is all or
nothing: the read range is checked before anything is written.

The bank (``vgripd.peer.registers.RegisterBank``) is typed here by what the answerer uses
of it (``Bank``); it refuses a read or write with a ``RegisterAccessError`` naming the
register. Time
(``now_ns``, monotonic) is passed in: reads serve ``RESULT_AGE_MS`` as of it.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Generic, Protocol, TypeAlias, TypeVar

from vgripd.peer.registers import RegisterAccessError

ILLEGAL_FUNCTION = 1
ILLEGAL_ADDRESS = 2
ILLEGAL_VALUE = 3

# Quantity limits of the Modbus application protocol (V1.1b3), per function.
MAX_READ = 125
MAX_WRITE = 123
MAX_RW_WRITE = 121

SERVED = (3, 6, 16, 22, 23)

Outcome = TypeVar("Outcome")
Outcome_co = TypeVar("Outcome_co", covariant=True)


class Image(Protocol):
    """The word block of a bank, as the answerer reads it."""

    @property
    def size(self) -> int: ...

    @property
    def words(self) -> Sequence[int]: ...

    def check_read(self, address: int, count: int) -> None:
        """``RegisterAccessError`` unless ``address .. address+count-1`` lies in the map."""


class Bank(Protocol[Outcome_co]):
    """A register bank: reads, and writes that return the bank's decision (the handshake)."""

    @property
    def image(self) -> Image: ...

    def read(self, address: int, count: int, now_ns: int) -> list[int]: ...

    def write(self, address: int, values: Sequence[int]) -> Outcome_co:
        """Write ``values`` at ``address``; ``RegisterAccessError`` naming the refused one."""
        ...


@dataclass(frozen=True)
class Answered:
    """Served; nothing left for the shell."""

    function: int


@dataclass(frozen=True)
class Written(Generic[Outcome]):
    """``values`` written at ``address``; ``outcome``: the bank's decision about it."""

    function: int
    address: int
    values: tuple[int, ...]
    outcome: Outcome


@dataclass(frozen=True)
class Refused:
    """Answered with exception ``code``. ``address``/``count``: the range asked for (the
    write range for a refused FC23 write; None for a function not served); ``detail`` says
    why, for the log."""

    function: int
    code: int
    address: int | None
    count: int | None
    detail: str


@dataclass(frozen=True)
class Malformed:
    """Not a well-formed request; ``detail`` says what is wrong."""

    function: int | None
    detail: str


Decision: TypeAlias = Answered | Written[Outcome] | Refused | Malformed


class _Refusal(Exception):
    def __init__(self, code: int, address: int | None, count: int | None, detail: str) -> None:
        super().__init__(detail)
        self.code, self.address, self.count = code, address, count


class _Bad(Exception):
    pass


def answer(pdu: bytes, bank: Bank[Outcome], now_ns: int) -> tuple[bytes, Decision[Outcome]]:
    """The reply PDU to request ``pdu`` (function code first) and what the shell does next.

    Never raises for any ``pdu``. The reply of ``Malformed`` is the exception 03 a frame
    transport sends; the reply of ``Refused`` is its exception PDU.
    """
    function = pdu[0] if pdu else None
    try:
        if function is None or function == 0 or function & 0x80:
            shown = "missing" if function is None else function
            raise _Bad(f"function code {shown} is not a request")
        if function == 3:
            return _read_holding(pdu, bank, now_ns)
        if function == 6:
            return _write_single(pdu, bank)
        if function == 16:
            return _write_multiple(pdu, bank)
        if function == 22:
            return _mask_write(pdu, bank)
        if function == 23:
            return _read_write(pdu, bank, now_ns)
        raise _Refusal(ILLEGAL_FUNCTION, None, None, f"function code {function} is not served")
    except _Refusal as refusal:
        assert function is not None
        return (bytes((function | 0x80, refusal.code)),
                Refused(function, refusal.code, refusal.address, refusal.count, str(refusal)))
    except _Bad as bad:
        return bytes(((function or 0) | 0x80, ILLEGAL_VALUE)), Malformed(function, str(bad))


def _need_length(pdu: bytes, length: int) -> None:
    if len(pdu) != length:
        raise _Bad(f"function {pdu[0]} needs a {length}-byte PDU, got {len(pdu)}")


def _need_byte_count(pdu: bytes, fixed: int) -> int:
    """The byte count at ``pdu[fixed - 1]``, which must be what follows it in the PDU."""
    if len(pdu) < fixed:
        raise _Bad(f"function {pdu[0]}: PDU of {len(pdu)} bytes is truncated")
    byte_count = pdu[fixed - 1]
    if len(pdu) != fixed + byte_count:
        raise _Bad(f"function {pdu[0]}: byte count {byte_count} but {len(pdu) - fixed} data "
                   "bytes")
    return byte_count


def _check_read(bank: Bank[Outcome], address: int, count: int) -> None:
    if not 1 <= count <= MAX_READ:
        raise _Refusal(ILLEGAL_VALUE, address, count,
                       f"read of {count} registers (1..{MAX_READ})")
    try:
        bank.image.check_read(address, count)
    except RegisterAccessError as err:
        raise _Refusal(ILLEGAL_ADDRESS, address, count, str(err)) from None


def _write(function: int, bank: Bank[Outcome], address: int,
           values: Sequence[int]) -> Written[Outcome]:
    try:
        outcome = bank.write(address, values)
    except RegisterAccessError as err:
        raise _Refusal(ILLEGAL_ADDRESS, address, len(values), str(err)) from None
    return Written(function, address, tuple(values), outcome)


def _read_holding(pdu: bytes, bank: Bank[Outcome],
                  now_ns: int) -> tuple[bytes, Decision[Outcome]]:
    _need_length(pdu, 5)
    address, count = struct.unpack_from(">HH", pdu, 1)
    _check_read(bank, address, count)
    words = bank.read(address, count, now_ns)
    return struct.pack(f">BB{count}H", 3, 2 * count, *words), Answered(3)


def _write_single(pdu: bytes, bank: Bank[Outcome]) -> tuple[bytes, Decision[Outcome]]:
    _need_length(pdu, 5)
    address, value = struct.unpack_from(">HH", pdu, 1)
    return pdu, _write(6, bank, address, [value])


def _write_multiple(pdu: bytes, bank: Bank[Outcome]) -> tuple[bytes, Decision[Outcome]]:
    byte_count = _need_byte_count(pdu, 6)
    address, count = struct.unpack_from(">HH", pdu, 1)
    if not 1 <= count <= MAX_WRITE or byte_count != 2 * count:
        raise _Refusal(ILLEGAL_VALUE, address, count,
                       f"write of {count} registers in {byte_count} bytes (1..{MAX_WRITE})")
    written = _write(16, bank, address, struct.unpack_from(f">{count}H", pdu, 6))
    return struct.pack(">BHH", 16, address, count), written


def _mask_write(pdu: bytes, bank: Bank[Outcome]) -> tuple[bytes, Decision[Outcome]]:
    _need_length(pdu, 7)
    address, and_mask, or_mask = struct.unpack_from(">HHH", pdu, 1)
    if address >= bank.image.size:
        raise _Refusal(ILLEGAL_ADDRESS, address, 1, f"mask write at {address} outside the map")
    current = bank.image.words[address]
    value = (current & and_mask) | (or_mask & ~and_mask & 0xFFFF)
    return pdu, _write(22, bank, address, [value])


def _read_write(pdu: bytes, bank: Bank[Outcome],
                now_ns: int) -> tuple[bytes, Decision[Outcome]]:
    byte_count = _need_byte_count(pdu, 10)
    read_address, read_count, write_address, write_count = struct.unpack_from(">HHHH", pdu, 1)
    if (not 1 <= read_count <= MAX_READ or not 1 <= write_count <= MAX_RW_WRITE
            or byte_count != 2 * write_count):
        raise _Refusal(ILLEGAL_VALUE, read_address, read_count,
                       f"read {read_count} / write {write_count} registers in {byte_count} "
                       f"bytes (1..{MAX_READ} / 1..{MAX_RW_WRITE})")
    try:  # all or nothing: the read range is checked before anything is written
        bank.image.check_read(read_address, read_count)
    except RegisterAccessError as err:
        raise _Refusal(ILLEGAL_ADDRESS, read_address, read_count, str(err)) from None
    written = _write(23, bank, write_address, struct.unpack_from(f">{write_count}H", pdu, 10))
    words = bank.read(read_address, read_count, now_ns)
    return struct.pack(f">BB{read_count}H", 23, 2 * read_count, *words), written

