"""Modbus/TCP server link: the PLC polls and writes vgripd's registers (map in
vgripd.service.protocol).

pymodbus (3.16) has no write callback and its datastores are not safe against concurrent
access, so the server is given ``RegisterContext``: its own datastore that answers every read
and write from a ``RegisterBank`` on the event loop, with no ``await`` inside one request. A
write to the command area runs the handshake and, for a new job, schedules the daemon's trigger
handler; ``publish`` changes the image in one call. pymodbus serves one request at a time on
the loop, so a poller sees a result either entirely before or entirely after a publish.

FC23 (read/write multiple registers) is all or nothing: pymodbus applies the write before it
looks at the read range, so the server decodes FC23 as ``AllOrNothingReadWrite``, which checks
the read range first; a request with an illegal range changes nothing and triggers nothing.

The link carries up to ``MAX_VALUES`` pose values in any vendor convention
(``REGISTER_CAPABILITIES``); the config check refuses a vendor with more.

``RegisterServerLink`` holds everything but the transport; ``drivers.links.modbus_rtu`` reuses
it for the serial line.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import time
from abc import abstractmethod
from collections.abc import Mapping, Sequence
from typing import Any

from pydantic import Field
from pymodbus.constants import ExcCodes
from pymodbus.datastore import ModbusServerContext
from pymodbus.exceptions import NoSuchIdException
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.pdu.register_message import ReadWriteMultipleRegistersRequest
from pymodbus.server import ModbusTcpServer
from pymodbus.server.base import ModbusBaseServer

from vgripd.errors import LinkError
from vgripd.service.protocol import (
    REGISTER_CAPABILITIES,
    Action,
    LinkHealth,
    LinkState,
    RegisterAccessError,
    RegisterBank,
    RegisterImage,
    RegisterOptions,
    RobotLink,
    Trigger,
    TriggerHandler,
    ValueCodec,
)
from vgripd.types import JobResult, Status

log = logging.getLogger(__name__)

# Holding-register function codes: 3 read, 6 write single, 16 write multiple, 22 mask write,
# 23 read/write multiple. Writes read back what they wrote (6, 22) for the response.
HOLDING_WRITE = {6, 16, 22, 23}
HOLDING_READ = {3} | HOLDING_WRITE


class RegisterContext(ModbusServerContext):
    """pymodbus datastore backed by a ``RegisterBank``; holding registers only.

    pymodbus 3.16 calls ``async_getValues``/``async_setValues`` of a ``ModbusServerContext``
    flagged ``old_simulator`` directly; the base ``__init__`` (which builds pymodbus' own
    simulated memory) is deliberately not called. Requests for another unit id raise
    ``NoSuchIdException``, which the server (``ignore_missing_devices=True``) leaves unanswered,
    as a Modbus RTU slave must.
    """

    def __init__(self, link: RegisterServerLink, unit_id: int | None) -> None:
        self.old_simulator = True
        self.simdevices = []
        self._link = link
        self._unit_id = unit_id

    def device_ids(self) -> list[int]:
        return [self._unit_id or 0]

    def _check(self, device_id: int, func_code: int, allowed: set[int]) -> ExcCodes | None:
        if self._unit_id is not None and device_id != self._unit_id:
            raise NoSuchIdException(f"unit id {device_id} (this link answers {self._unit_id})")
        if func_code not in allowed:
            return ExcCodes.ILLEGAL_FUNCTION
        return None

    def read_refusal(self, device_id: int, func_code: int, address: int,
                     count: int) -> ExcCodes | None:
        """The exception a read of ``address``/``count`` gets, without reading anything."""
        if exc := self._check(device_id, func_code, HOLDING_READ):
            return exc
        try:
            RegisterImage.check_read(address, count)
        except RegisterAccessError as err:
            log.debug("%s: %s", self._link.name, err)
            return ExcCodes.ILLEGAL_ADDRESS
        return None

    async def async_getValues(
        self, device_id: int, func_code: int, address: int, count: int = 1
    ) -> list[int] | list[bool] | ExcCodes:
        if exc := self.read_refusal(device_id, func_code, address, count):
            return exc
        return self._link.bank.read(address, count, time.monotonic_ns())

    async def async_setValues(
        self, device_id: int, func_code: int, address: int,
        values: Sequence[int] | Sequence[bool],
    ) -> ExcCodes | None:
        if exc := self._check(device_id, func_code, HOLDING_WRITE):
            return exc
        try:
            decision = self._link.bank.write(address, [int(v) for v in values])
        except RegisterAccessError as err:
            log.info("%s: refused %s", self._link.name, err)
            return ExcCodes.ILLEGAL_ADDRESS
        if decision.action is Action.START:
            self._link.dispatch(decision.seq, decision.command, decision.recipe)
        elif decision.action is Action.REJECT:
            log.info("%s: request %d refused: %s", self._link.name, decision.seq,
                     decision.code.name)
        return None


class AllOrNothingReadWrite(ReadWriteMultipleRegistersRequest):
    """FC23 whose read range is checked before the write is applied.

    pymodbus writes first and reads after; with an illegal read range it would answer exception
    02 although the write (perhaps a trigger) took effect. Here both ranges are checked before
    anything changes (the write's by ``RegisterBank.write``, which refuses before applying), and
    nothing awaits in between, so no other request runs between the write and the read.
    """

    async def datastore_update(self, context: ModbusServerContext, device_id: int) -> ModbusPDU:
        # Bad quantities are left to pymodbus (exception 03 comes before 02 in the spec).
        quantities_ok = (1 <= self.read_count <= self.MAX_READ_COUNT
                         and 1 <= self.write_count <= self.MAX_WRITE_COUNT)
        if isinstance(context, RegisterContext) and quantities_ok:
            exc = context.read_refusal(device_id, self.function_code, self.read_address,
                                       self.read_count)
            if exc is not None:
                return ExceptionResponse(self.function_code, exc)
        return await super().datastore_update(context, device_id)


class RegisterServerLink(RobotLink):
    """A Modbus server link over some transport: register bank, heartbeat, handshake."""

    capabilities = REGISTER_CAPABILITIES
    options: RegisterOptions

    def __init__(self, name: str, options: Any) -> None:
        super().__init__(name, options)
        self.bank = RegisterBank(
            ValueCodec(options.word_order, options.value_format, options.scale)
        )
        self._server: ModbusBaseServer | None = None
        self._heartbeat: asyncio.Task[None] | None = None
        self._on_trigger: TriggerHandler | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._state = LinkState.STOPPED
        self._since_ns = time.monotonic_ns()
        self._last_error = ""

    @abstractmethod
    def _make_server(self, context: RegisterContext) -> ModbusBaseServer:
        """The pymodbus server for this transport (created on the running loop)."""

    @abstractmethod
    def _describe(self) -> str:
        """Where this link serves, for messages (``host:port``, ``/dev/ttyS0``)."""

    def _unit_id(self) -> int | None:
        return None

    async def open(self, on_trigger: TriggerHandler) -> None:
        if self._server is not None:
            raise LinkError(f"link {self.name}: already open")
        self._on_trigger = on_trigger
        self._loop = asyncio.get_running_loop()
        server = self._make_server(RegisterContext(self, self._unit_id()))
        server.decoder.register(AllOrNothingReadWrite)
        try:
            await server.serve_forever(background=True)
        except RuntimeError:
            await server.shutdown()
            self._set_state(LinkState.FAILED, self._start_error())
            raise LinkError(f"link {self.name}: {self._last_error}") from None
        self._server = server
        self._heartbeat = asyncio.create_task(self._beat(), name=f"{self.name}-heartbeat")
        self._set_state(LinkState.UP)
        log.info("%s: serving Modbus registers on %s", self.name, self._describe())

    def _start_error(self) -> str:
        return f"cannot serve on {self._describe()}"

    async def close(self) -> None:
        if self._heartbeat is not None:
            self._heartbeat.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._heartbeat
            self._heartbeat = None
        if self._server is not None:
            await self._server.shutdown()
            self._server = None
        self._set_state(LinkState.STOPPED)

    def health(self) -> LinkHealth:
        return LinkHealth(
            state=self._state,
            peer=self._describe(),
            last_error=self._last_error,
            since_mono_ns=self._since_ns,
            peers=self.peers(),
        )

    def peers(self) -> int:
        return len(self._server.active_connections) if self._server is not None else 0

    async def image_captured(self, seq: int, job_id: int) -> None:
        self.bank.captured(seq, job_id)

    async def publish(self, seq: int, result: JobResult) -> Status:
        published = self.bank.publish(seq, result, time.monotonic_ns())
        if published.status is not result.status:
            log.warning("%s: request %d published as %s instead of %s: %s", self.name, seq,
                        published.status.name, result.status.name, published.message)
        return published.status

    def refusals(self) -> Mapping[str, int]:
        return dict(self.bank.refusals)

    async def set_warnings(self, bits: int) -> None:
        self.bank.set_warnings(bits)

    def dispatch(self, seq: int, command: int, recipe: int) -> None:
        """Hand a new job to the daemon, outside the Modbus request that triggered it (an error
        in the handler must not become a Modbus exception response)."""
        assert self._loop is not None
        assert self._on_trigger is not None
        trigger = Trigger(link=self.name, seq=seq, command=command,
                          t_mono_ns=time.monotonic_ns(), recipe=recipe)
        self._loop.call_soon(self._on_trigger, trigger)

    async def _beat(self) -> None:
        period_s = self.options.heartbeat_ms / 1000
        while True:
            await asyncio.sleep(period_s)
            self.bank.beat()

    def _set_state(self, state: LinkState, error: str = "") -> None:
        if state is not self._state:
            self._state = state
            self._since_ns = time.monotonic_ns()
        if error:
            self._last_error = error


class TcpOptions(RegisterOptions):
    """``host``/``port``: where to listen (port 0 = any free port, see ``ModbusServerLink.port``).
    ``unit_id``: answer only this unit id (None = any; most Modbus/TCP clients send 1 or 255)."""

    host: str = "0.0.0.0"
    port: int = Field(502, ge=0, le=65535)
    unit_id: int | None = Field(None, ge=0, le=255)


class ModbusServerLink(RegisterServerLink):
    Options = TcpOptions
    options: TcpOptions

    @property
    def port(self) -> int:
        """The bound port (the configured one, or the one chosen for port 0)."""
        transport = self._server.transport if self._server is not None else None
        if isinstance(transport, asyncio.Server) and transport.sockets:
            port: int = transport.sockets[0].getsockname()[1]
            return port
        return self.options.port

    def _make_server(self, context: RegisterContext) -> ModbusBaseServer:
        return ModbusTcpServer(
            context, address=(self.options.host, self.options.port), ignore_missing_devices=True
        )

    def _describe(self) -> str:
        return f"{self.options.host}:{self.port}"

    def _unit_id(self) -> int | None:
        return self.options.unit_id

    def _start_error(self) -> str:
        # pymodbus only logs why listen() failed; bind once more to name the reason.
        reason = "unknown reason"
        try:
            with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
                probe.bind((self.options.host, self.options.port))
        except OSError as err:
            reason = err.strerror or str(err)
        return f"cannot listen on {self.options.host}:{self.options.port}: {reason}"
