"""Modbus RTU server link on a serial line: the register map and handshake of the TCP server
(``RegisterServerLink``: every request PDU is answered by ``answer_pdu``), framed here for RTU
over pyserial.

An RTU slave answers only its own unit id; frames for other units (and broadcasts, unit 0) are
left unanswered. FC23 is all or nothing as on TCP.

Framing (``RtuFramer``). A frame is unit id, PDU, CRC-16. Its length follows from the function
code (a byte count where the request has one); a function code without a known layout is a
frame once the whole buffer carries a valid CRC. A CRC error, or bytes that start no frame,
cost only themselves: the framer looks for the next valid frame one byte further on. Silence
ends a frame (Modbus over serial line, 2.5.1.1): when at least 3.5 character times (1.75 ms
above 19200 baud) pass with nothing on the line, a partial frame left in the buffer is dropped,
so one stray byte never spoils the next request. The silence is judged from when data arrives
minus the time the new bytes took on the wire; a USB adapter that hands over a frame in pieces
therefore does not lose it, and a piece that completes a valid frame is always kept.

Faults. A port that cannot take the configuration (not a tty, a parity or baud rate the
adapter refuses) is a config error: ``open()`` raises ``LinkError`` and the link is FAILED.
Anything else (device missing, unplugged, read/write errors, the port locked by another
program) takes the link DOWN with the reason in ``health().last_error``; one supervisor task
reopens the port with doubling back-off (``backoff_initial_s`` .. ``backoff_max_s``), logging
the outage once (WARNING) and the recovery once (INFO). A port missing at start is DOWN too:
a USB adapter may be plugged in later.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import os
import termios
import time
from collections.abc import Iterator
from typing import Any, Literal

import serial
from pydantic import Field

from drivers.links.modbus_server import MalformedFrame, RegisterServerLink
from vgripd.errors import LinkError
from vgripd.peer.registers import RegisterOptions
from vgripd.service.protocol import LinkState, TriggerHandler
from vgripd.service.supervisor import (
    BackoffOptions,
    Ended,
    OutagePolicy,
    Reconnector,
    backoff_initial,
    backoff_max,
)

log = logging.getLogger(__name__)

MAX_ADU = 256  # the longest RTU frame: unit id + 253-byte PDU + CRC
# Frame lengths by function code (unit id and CRC included), from the Modbus application
# protocol. An int is a fixed length; (at, fixed) a byte count at index ``at``: fixed + count.
# Requests are what this slave answers; responses are other slaves' answers on a shared line
# (and an adapter's echo of our own), recognised so that they are skipped whole, never answered.
Layout = int | tuple[int, int]
_REQUEST: dict[int, Layout] = {
    1: 8, 2: 8, 3: 8, 4: 8, 5: 8, 6: 8, 7: 4, 8: 8, 11: 4, 12: 4, 17: 4, 22: 10, 24: 6, 43: 7,
    15: (6, 9), 16: (6, 9), 20: (2, 5), 21: (2, 5), 23: (10, 13),
}
_RESPONSE: dict[int, Layout] = {
    1: (2, 5), 2: (2, 5), 3: (2, 5), 4: (2, 5), 23: (2, 5), 5: 8, 6: 8, 15: 8, 16: 8, 22: 10,
}
_EXCEPTION_LENGTH = 5  # unit, function | 0x80, exception code, CRC


def _crc_table() -> list[int]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)
    return table


_CRC_TABLE = _crc_table()


def crc16(data: bytes) -> int:
    """Modbus CRC-16 (polynomial 0xA001 reflected, start 0xFFFF); sent low byte first."""
    crc = 0xFFFF
    for byte in data:
        crc = (crc >> 8) ^ _CRC_TABLE[(crc ^ byte) & 0xFF]
    return crc


def with_crc(body: bytes) -> bytes:
    """``body`` (unit id + PDU) with its CRC appended."""
    return body + crc16(body).to_bytes(2, "little")


def crc_ok(frame: bytes) -> bool:
    return len(frame) >= 4 and crc16(frame[:-2]) == int.from_bytes(frame[-2:], "little")


def char_time_s(baudrate: int, parity: str, stopbits: int) -> float:
    """Time one character takes on the line: start bit, 8 data bits, parity bit, stop bits."""
    return (1 + 8 + (parity != "N") + stopbits) / baudrate


def silence_s(baudrate: int, parity: str, stopbits: int) -> float:
    """The 3.5-character inter-frame silence; fixed at 1.75 ms above 19200 baud (the spec)."""
    if baudrate > 19200:
        return 0.00175
    return 3.5 * char_time_s(baudrate, parity, stopbits)


def _length(buffer: bytes, start: int, layout: Layout) -> int | None:
    if isinstance(layout, int):
        return layout
    at, fixed = layout
    if len(buffer) - start <= at:
        return None
    return fixed + buffer[start + at]


class RtuFramer:
    """Bytes from the line in, complete frames with a valid CRC out (any unit id).

    ``feed(data, t)`` takes what one read returned and when (monotonic seconds) and returns the
    requests it completed, in order (other slaves' responses are skipped). Counters:
    ``garbage`` bytes skipped (CRC errors, noise, partial frames dropped at a silence),
    ``frames`` requests returned, ``responses`` responses skipped.
    """

    def __init__(self, char_s: float, silence: float) -> None:
        self.char_s = char_s
        self.silence = silence
        self.buffer = b""
        self.garbage = 0
        self.frames = 0
        self.responses = 0
        self._t_last: float | None = None

    def feed(self, data: bytes, t: float) -> list[bytes]:
        if self.buffer and self._t_last is not None:
            quiet = (t - self._t_last) - len(data) * self.char_s
            if quiet >= self.silence and self._frame_at(self.buffer + data, 0) is None:
                # The line was silent after these bytes: they were a partial frame or noise.
                self.garbage += len(self.buffer)
                self.buffer = b""
        self._t_last = t
        self.buffer += data
        return list(self._requests())

    def _requests(self) -> Iterator[bytes]:
        while self.buffer:
            found = self._first_frame()
            if found is None:
                if len(self.buffer) > MAX_ADU:  # no frame can start this early any more
                    self.garbage += len(self.buffer) - MAX_ADU
                    self.buffer = self.buffer[-MAX_ADU:]
                return
            start, length, is_request = found
            self.garbage += start
            frame = self.buffer[start:start + length]
            self.buffer = self.buffer[start + length:]
            if is_request:
                self.frames += 1
                yield frame
            else:
                self.responses += 1

    def _first_frame(self) -> tuple[int, int, bool] | None:
        for start in range(len(self.buffer) - 3):
            found = self._frame_at(self.buffer, start)
            if found is not None:
                return (start, *found)
        return None

    @staticmethod
    def _frame_at(buffer: bytes, start: int) -> tuple[int, bool] | None:
        """(length, is a request) of a complete, CRC-valid frame at ``start``, or None."""
        rest = len(buffer) - start
        if rest < 4:
            return None
        function = buffer[start + 1]
        candidates: list[tuple[Layout, bool]] = []
        if function & 0x80:
            candidates.append((_EXCEPTION_LENGTH, False))
        else:
            if function in _REQUEST:
                candidates.append((_REQUEST[function], True))
            if function in _RESPONSE:
                candidates.append((_RESPONSE[function], False))
            if not candidates and start == 0 and rest <= MAX_ADU:
                # A function without a known layout: a request if the whole buffer is one.
                candidates.append((rest, True))
        for layout, is_request in candidates:
            length = _length(buffer, start, layout)
            if length is not None and 4 <= length <= rest and crc_ok(
                    buffer[start:start + length]):
                return length, is_request
        return None


class PortFault(LinkError):
    """The serial port could not be opened or used. ``permanent``: retrying cannot help (the
    port refuses the configuration), a config error rather than a link fault."""

    def __init__(self, message: str, permanent: bool = False) -> None:
        super().__init__(message)
        self.permanent = permanent


class RtuOptions(RegisterOptions, BackoffOptions):
    """``port``: the serial device (``/dev/ttyUSB0``). ``parity``: N(one), E(ven), O(dd).
    ``unit_id``: this slave's address on the line (1-247). ``backoff_initial_s`` ..
    ``backoff_max_s``: reopen delay after the port is lost, doubling."""

    port: str = Field(min_length=1)
    baudrate: int = Field(19200, ge=1200, le=921600)
    parity: Literal["N", "E", "O"] = "E"
    stopbits: Literal[1, 2] = 1
    unit_id: int = Field(1, ge=1, le=247)
    # a serial adapter takes longer to come back than a TCP peer
    backoff_initial_s: float = backoff_initial(0.5)
    backoff_max_s: float = backoff_max(10.0)


def _reason(err: BaseException) -> str:
    if isinstance(err, termios.error) and len(err.args) == 2:
        return f"[Errno {err.args[0]}] {err.args[1]}"
    if isinstance(err, OSError) and err.errno:  # pyserial repeats the path: the errno says it
        return f"[Errno {err.errno}] {os.strerror(err.errno)}"
    return str(err) or type(err).__name__


def open_port(options: RtuOptions, describe: str) -> serial.Serial:
    """The configured port, open and non-blocking; ``PortFault`` saying why not."""
    port = serial.Serial(baudrate=options.baudrate, bytesize=8, parity=options.parity,
                         stopbits=options.stopbits, timeout=0, write_timeout=0, exclusive=True)
    port.port = options.port
    try:
        port.open()
    except (termios.error, ValueError) as err:
        # tcsetattr refused the settings (EINVAL: e.g. a parity this adapter cannot do)
        raise PortFault(f"serial port {describe} refuses the configuration: {_reason(err)} "
                        "(check baudrate, parity and stopbits for this adapter)",
                        permanent=True) from None
    except serial.SerialException as err:
        text = _reason(err)
        if "Could not configure port" in text or err.errno in (errno.ENOTTY, errno.EISDIR):
            raise PortFault(f"{options.port} is not a serial port: {text}",
                            permanent=True) from None
        raise PortFault(f"cannot open serial port {describe}: {text}") from None
    except OSError as err:
        raise PortFault(f"cannot open serial port {describe}: {_reason(err)}") from None
    return port


class _Line:
    """One open port on the event loop: reads feed the framer, answers are written back.

    ``lost`` completes with the reason when a read or write fails (device gone).
    """

    def __init__(self, link: ModbusRtuLink, port: serial.Serial) -> None:
        self.link = link
        self.port = port
        self.fd = port.fileno()
        self.loop = asyncio.get_running_loop()
        o = link.options
        self.framer = RtuFramer(char_time_s(o.baudrate, o.parity, o.stopbits),
                                silence_s(o.baudrate, o.parity, o.stopbits))
        self.lost: asyncio.Future[str] = self.loop.create_future()
        self._out = bytearray()
        self.loop.add_reader(self.fd, self._readable)

    def close(self) -> None:
        with contextlib.suppress(ValueError, OSError):
            self.loop.remove_reader(self.fd)
            self.loop.remove_writer(self.fd)
        with contextlib.suppress(OSError, serial.SerialException):
            self.port.close()

    def _fail(self, reason: str) -> None:
        with contextlib.suppress(ValueError, OSError):
            self.loop.remove_reader(self.fd)
            self.loop.remove_writer(self.fd)
        if not self.lost.done():
            self.lost.set_result(reason)

    def _readable(self) -> None:
        try:
            data = os.read(self.fd, 4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as err:
            self._fail(f"reading serial port {self.link.describe()}: {_reason(err)}")
            return
        if not data:  # readable but empty: the device is gone (hang-up)
            self._fail(f"serial port {self.link.describe()} hung up (device unplugged?)")
            return
        for frame in self.framer.feed(data, time.monotonic()):
            answer = self.link.answer_frame(frame)
            if answer:
                self._write(answer)

    def _write(self, data: bytes) -> None:
        self._out += data
        if len(self._out) == len(data):
            self._writable()

    def _writable(self) -> None:
        try:
            sent = os.write(self.fd, self._out)
        except (BlockingIOError, InterruptedError):
            sent = 0
        except OSError as err:
            self._fail(f"writing serial port {self.link.describe()}: {_reason(err)}")
            return
        del self._out[:sent]
        if self._out:
            self.loop.add_writer(self.fd, self._writable)
        else:
            self.loop.remove_writer(self.fd)


class ModbusRtuLink(RegisterServerLink):
    Options = RtuOptions
    options: RtuOptions

    def __init__(self, name: str, options: Any) -> None:
        super().__init__(name, options)
        self._line: _Line | None = None
        self._supervisor: asyncio.Task[None] | None = None
        self.frames_answered = 0
        self.frames_other_units = 0

    # -- RobotLink -----------------------------------------------------------------------

    async def open(self, on_trigger: TriggerHandler) -> None:
        """Open the port and serve. ``LinkError`` (FAILED) when the port refuses the
        configuration; a missing or failing device is DOWN and reopened in the background."""
        if self._supervisor is not None:
            raise LinkError(f"link {self.name}: already open")
        self._on_trigger = on_trigger
        self._loop = asyncio.get_running_loop()
        o = self.options
        reconnector = Reconnector(self.name, self.cell,
                                  OutagePolicy(o.backoff_initial_s, o.backoff_max_s), log,
                                  down_line="%s: %s; reopening with back-off up to %.1f s")
        try:
            self._line = _Line(self, open_port(o, self.describe()))
        except PortFault as fault:
            if fault.permanent:  # the caller (the daemon) reports it
                self.cell.set(LinkState.FAILED, str(fault))
                raise LinkError(f"link {self.name}: {fault}") from None
            reconnector.failed(Ended(str(fault)))  # DOWN; the supervisor waits, then reopens
        else:
            self.cell.set(LinkState.UP)
            log.info("%s: serving Modbus registers on %s", self.name, self.describe())
        self._heartbeat = asyncio.create_task(self._beat(), name=f"{self.name}-heartbeat")
        self._supervisor = asyncio.create_task(reconnector.run(lambda: self._session(reconnector)),
                                               name=f"{self.name}-supervisor")

    async def close(self) -> None:
        task, self._supervisor = self._supervisor, None
        if task is not None:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
        if self._line is not None:
            self._line.close()
            self._line = None
        await super().close()
        self.cell.set(LinkState.STOPPED)

    def peers(self) -> int:
        return 0  # a serial line has no connection to count

    def describe(self) -> str:
        o = self.options
        return f"{o.port} ({o.baudrate} 8{o.parity}{o.stopbits}, unit {o.unit_id})"

    def _describe(self) -> str:
        return self.describe()

    def _unit_id(self) -> int | None:
        return self.options.unit_id

    # -- frames ----------------------------------------------------------------------------

    def answer_frame(self, frame: bytes) -> bytes | None:
        """The answer ADU to a CRC-valid request frame; None when it is not for this unit."""
        unit = frame[0]
        if unit != self.options.unit_id:
            self.frames_other_units += 1
            return None
        pdu = frame[1:-2]
        try:
            reply = self.answer_pdu(pdu, self.options.port)
        except MalformedFrame as err:
            # The CRC was right, the request is not: answer it as an illegal data value.
            self.fault(self.options.port, "malformed", logging.INFO,
                       "%s: malformed request answered with exception 03: %s",
                       self.options.port, err)
            reply = bytes((pdu[0] | 0x80, 3))
        self.frames_answered += 1
        return with_crc(bytes((unit,)) + reply)

    # -- supervisor ------------------------------------------------------------------------

    async def _session(self, reconnector: Reconnector) -> Ended:
        """Reopen the port if it is closed, then serve until the line is lost; why it ended."""
        if self._line is None:
            try:
                self._line = _Line(self, open_port(self.options, self.describe()))
            except PortFault as fault:
                return Ended(str(fault))
            reconnector.up(reconnect=True)
            log.info("%s: serial port %s is back (reconnects %d)", self.name, self.describe(),
                     self.cell.reconnects)
        line = self._line
        reason = await line.lost
        line.close()
        self._line = None
        return Ended(reason)
