"""Modbus RTU server link on a serial line: the register map and handshake of the TCP server
(``RegisterServerLink``: every request PDU is answered by ``vgripd.peer.modbus_pdu`` through
``answer_pdu``), framed here for RTU over pyserial.

An RTU slave answers only its own unit id; frames for other units (and broadcasts, unit 0) are
left unanswered. FC23 is all or nothing as on TCP.

Framing: ``vgripd.peer.rtu.RtuFramer`` (no I/O; this module feeds it what the port delivered
and when). A frame is unit id, PDU, CRC-16; a CRC error or noise costs only itself, and 3.5
character times of silence end a partial frame.

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
from typing import Any, Literal

import serial
from pydantic import Field

from drivers.links.modbus_server import RegisterServerLink
from vgripd.errors import LinkError
from vgripd.peer.modbus_pdu import Malformed
from vgripd.peer.registers import RegisterOptions
from vgripd.peer.rtu import RtuFramer, char_time_s, silence_s, with_crc
from vgripd.service.links.protocol import LinkState, TriggerHandler
from vgripd.service.links.supervisor import (
    BackoffOptions,
    Ended,
    OutagePolicy,
    Reconnector,
    backoff_initial,
    backoff_max,
    end_task,
)

log = logging.getLogger(__name__)

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
            await end_task(task)
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
        reply, decision = self.answer_pdu(frame[1:-2], self.options.port)
        if isinstance(decision, Malformed):
            # The CRC was right, the request is not: the reply is exception 03 (illegal value).
            self.fault(self.options.port, "malformed", logging.INFO,
                       "%s: malformed request answered with exception 03: %s",
                       self.options.port, decision.detail)
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
