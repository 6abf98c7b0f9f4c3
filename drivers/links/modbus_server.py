"""Modbus/TCP server link: the PLC polls and writes vgripd's registers (map in
vgripd.peer.registers).

Every read and write is answered from a ``RegisterBank`` on the event loop, with no ``await``
inside one request. A write to the command area runs the handshake and, for a new job, schedules
the daemon's trigger handler (``dispatch``); ``publish`` changes the image in one call. A poller
therefore sees a result either entirely before or entirely after a publish.

The TCP server is this module's own asyncio protocol, not pymodbus' ``ModbusTcpServer``: the
link has to survive its network (docs/registers.md, "Connections"), and pymodbus 3.16's server
loop cannot be made to. It has no hook for a connection cap, an idle timeout, TCP keepalive or a
bound on unsent output; its ``FramerSocket`` answers a wrong protocol id or a lying length with
"wait for more data", so one malformed frame silences the connection for good; it decodes one
request per received segment (pipelined requests go unanswered); its decoder refuses a read of
0 or 126 registers at decode time, which the server answers with function code 0x80; and it
logs decode failures and datastore errors with tracebacks, one per frame. MBAP framing is seven
bytes and the register map is served by five function codes, so the link frames and answers
them itself (the framer ``vgripd.peer.mbap``, the answerer ``vgripd.peer.modbus_pdu``; this
module acts on the answerer's decisions and does the I/O):

- MBAP header: transaction id (echoed), protocol id 0, length 2..254 (unit id + PDU). Anything
  else is a malformed frame. So is a request whose PDU length does not match its function code
  (truncated, trailing bytes, a byte count the length contradicts) and a function code 0 or
  >= 0x80. A malformed frame closes its connection (the stream cannot be trusted after it).
- FC 3 read, 6 write single, 16 write multiple, 22 mask write, 23 read/write multiple holding
  registers. A quantity out of range (FC3 1..125, FC16 1..123, FC23 read 1..125 and write
  1..121, byte count = 2 x quantity) is exception 03; a register range outside the map or a
  write outside the command area exception 02; any other function code exception 01.
- Requests are answered in order, every request of a segment (pipelining), a batch at a time
  so that one client cannot hold the loop.
- Connections go through the daemon's one connection manager (``vgripd.service.links.gate``):
  addresses outside ``allow`` are closed at accept; at most ``max_connections`` (the daemon's
  file budget may lower it); beyond that a new connection evicts the oldest one that never got
  a normal answer, and is refused when every connection has (a flood of newcomers never evicts
  a polling PLC). ``idle_timeout_s`` without a complete request closes a connection; TCP
  keepalive finds peers that vanished without a FIN. A client whose unsent answers exceed
  ``max_unsent_bytes`` (it does not read) is dropped.
- Peer faults are logged through ``RateLimitedLog``: one line per client address and kind of
  fault per ``log_interval_s``, with a count of the ones held back; never a traceback.

FC23 is all or nothing: both ranges are checked before anything is written, so a request with
an illegal read range changes nothing and triggers nothing. The RTU link
(``drivers.links.modbus_rtu``) does its own serial framing and answers through the same
answerer (``RegisterServerLink.answer_pdu``).

The link carries up to ``MAX_VALUES`` pose values in any vendor convention
(``REGISTER_CAPABILITIES``); the config check refuses a vendor with more.

``RegisterServerLink`` holds everything but the transport; ``drivers.links.modbus_rtu`` reuses
it for the serial line.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time
from collections import Counter
from collections.abc import Mapping
from typing import Any

from pydantic import Field, model_validator

from vgripd.config import AllowList
from vgripd.errors import LinkError
from vgripd.peer import mbap, modbus_pdu
from vgripd.peer.jobcore import Action, Decision
from vgripd.peer.mbap import MalformedFrame
from vgripd.peer.modbus_pdu import Decision as PduDecision
from vgripd.peer.modbus_pdu import Malformed, Written
from vgripd.peer.modbus_pdu import Refused as PduRefused
from vgripd.peer.registers import (
    RegisterBank,
    RegisterOptions,
    ValueCodec,
)
from vgripd.registry import REGISTER_CAPABILITIES
from vgripd.service.links.gate import Gate, set_keepalive
from vgripd.service.links.protocol import (
    CountHandler,
    LinkHealth,
    LinkState,
    Trigger,
    TriggerHandler,
)
from vgripd.service.links.ratelog import RateLimitedLog
from vgripd.service.links.supervisor import SupervisedLink
from vgripd.types import JobResult, Status

log = logging.getLogger(__name__)

REQUESTS_PER_BATCH = 64  # pipelined requests answered before other clients get the loop


class RegisterServerLink(SupervisedLink):
    """A Modbus server link over some transport: register bank, heartbeat, handshake.

    Each transport starts with ``_start_serving`` and stops with ``_stop_serving``; every
    request, whatever its framing, is answered by ``answer_pdu``.
    """

    capabilities = REGISTER_CAPABILITIES
    options: RegisterOptions
    LOG_INTERVAL_S = 60.0  # peer faults: one log line per client and kind per interval

    def __init__(self, name: str, options: Any) -> None:
        super().__init__(name, options)
        self.bank = RegisterBank(
            ValueCodec(options.word_order, options.value_format, options.scale),
            version=options.map_version,
        )
        self.ratelog = RateLimitedLog(log, getattr(options, "log_interval_s", self.LOG_INTERVAL_S))
        #: peer faults by kind (malformed, exception 01/02/03, unit, evicted, idle, not_reading)
        self.faults: Counter[str] = Counter()
        self._serving = False
        self._heartbeat: asyncio.Task[None] | None = None
        self._on_trigger: TriggerHandler | None = None
        self._on_count: CountHandler | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    def _describe(self) -> str:
        """Where this link serves, for messages (``host:port``, ``/dev/ttyS0``)."""
        raise NotImplementedError

    def _unit_id(self) -> int | None:
        return None

    async def open(self, on_trigger: TriggerHandler) -> None:
        if self._serving:
            raise LinkError(f"link {self.name}: already open")
        self._on_trigger = on_trigger
        self._loop = asyncio.get_running_loop()
        try:
            await self._start_serving()
        except LinkError as err:
            self.cell.set(LinkState.FAILED, str(err) or None)
            raise LinkError(f"link {self.name}: {err}") from None
        self._serving = True
        self._heartbeat = asyncio.create_task(self._beat(), name=f"{self.name}-heartbeat")
        self.cell.set(LinkState.UP, None)
        log.info("%s: serving Modbus registers on %s", self.name, self._describe())

    async def _start_serving(self) -> None:
        """Start the transport; ``LinkError`` saying why it cannot."""
        raise NotImplementedError

    async def _stop_serving(self) -> None:
        """Stop the transport (nothing to stop for a link that manages its own, like RTU)."""

    async def close(self) -> None:
        if self._heartbeat is not None:
            self._heartbeat.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._heartbeat
            self._heartbeat = None
        await self._stop_serving()
        self._serving = False
        self.ratelog.flush(force=True)
        self.cell.set(LinkState.STOPPED, None)

    def health(self) -> LinkHealth:
        return self.cell.health(peer=self._describe(), peers=self.peers())

    def peers(self) -> int:
        """Connected peers (TCP clients); 0 where the transport has none to count."""
        return 0

    async def image_captured(self, seq: int, job_id: int) -> None:
        self.bank.captured(seq, job_id)

    takes_views = True

    async def view_captured(self, seq: int, job_id: int) -> None:
        self.bank.view_captured(seq, job_id)

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

    def set_conveyor(self, on: bool) -> None:
        self.bank.handshake.queue = on

    publishes_count = True

    def watch_count(self, handler: CountHandler | None) -> None:
        self._on_count = handler

    def dispatch(self, seq: int, command: int, recipe: int, view: int = 0,
                 count: int | None = None, frame: int | None = None) -> None:
        """Hand a new job to the daemon, outside the Modbus request that triggered it (an error
        in the handler must not become a Modbus exception response)."""
        assert self._loop is not None
        assert self._on_trigger is not None
        trigger = Trigger(link=self.name, seq=seq, command=command,
                          t_mono_ns=time.monotonic_ns(), recipe=recipe, view=view,
                          latch_count=count, latch_frame=frame)
        self._loop.call_soon(self._on_trigger, trigger)

    # --- requests -----------------------------------------------------------------------

    def fault(self, client: str, kind: str, level: int, msg: str, *args: Any) -> None:
        """Count a peer fault and log it, rate limited per ``client`` and ``kind``."""
        self.faults[kind] += 1
        self.ratelog.log(level, client, kind, f"%s: {msg}", self.name, *args)

    def answer_pdu(self, pdu: bytes, client: str) -> tuple[bytes, PduDecision[Decision]]:
        """The reply PDU to request ``pdu`` (function code first), answered from the bank by
        ``vgripd.peer.modbus_pdu``, and its decision, carried out here but for ``Malformed``,
        which the transport handles. ``client`` names the peer (its address) in the log,
        which is rate limited per client.
        """
        reply, decision = modbus_pdu.answer(pdu, self.bank, time.monotonic_ns())
        if isinstance(decision, Written):
            self._written(decision, client)
        elif isinstance(decision, PduRefused):
            self.fault(client, f"exception {decision.code:02d}", logging.INFO,
                       "%s: function %d answered with exception %02d: %s", client,
                       decision.function, decision.code, decision.detail)
        return reply, decision

    def _written(self, written: Written[Decision], client: str) -> None:
        """A peer's write went through the handshake: the belt's count, a new job, a refusal."""
        count = self.bank.published_count(written.address, written.values)
        if count is not None and self._on_count is not None:  # the belt's count now (travel)
            self._on_count(count, time.monotonic_ns())
        decision = written.outcome
        if decision.action is Action.START:
            self.dispatch(decision.seq, decision.command, decision.recipe, decision.view,
                          decision.count, decision.frame)
        elif decision.action is Action.REJECT:
            self.ratelog.info(client, "handshake", "%s: %s: request %d refused: %s", self.name,
                              client, decision.seq, decision.code.name)

    async def _beat(self) -> None:
        period_s = self.options.heartbeat_ms / 1000
        while True:
            await asyncio.sleep(period_s)
            self.bank.beat()


class TcpOptions(RegisterOptions):
    """``host``/``port``: where to listen (port 0 = any free port, see ``ModbusServerLink.port``).
    ``unit_id``: answer only this unit id (None = any); with ``unit_id_wildcards`` also 0 and
    255, the ids Modbus/TCP clients send to "the device behind this address".

    Connections (docs/registers.md, "Connections"): ``allow`` (client addresses and networks;
    unset = any), ``max_connections`` (beyond it the oldest connection that never got a normal
    answer is evicted for a new one; if every one has, the new one is refused),
    ``idle_timeout_s`` without a complete request closes a connection (0 = never), TCP
    keepalive (``keepalive_*``: probes after ``keepalive_idle_s`` of silence, every
    ``keepalive_interval_s``, ``keepalive_count`` unanswered ones end it), a client with more
    than ``max_unsent_bytes`` of answers it has not read is dropped. Peer
    faults are logged once per client and kind per ``log_interval_s``.
    """

    host: str = "0.0.0.0"
    port: int = Field(502, ge=0, le=65535)
    unit_id: int | None = Field(None, ge=0, le=255)
    unit_id_wildcards: bool = True
    max_connections: int = Field(16, ge=1, le=1000)
    idle_timeout_s: float = Field(60.0, ge=0.0, le=86400.0)
    keepalive: bool = True
    keepalive_idle_s: int = Field(10, ge=1, le=7200)
    keepalive_interval_s: int = Field(5, ge=1, le=600)
    keepalive_count: int = Field(3, ge=1, le=30)
    max_unsent_bytes: int = Field(65536, ge=1024, le=16 * 1024 * 1024)
    log_interval_s: float = Field(60.0, ge=0.1, le=3600.0)
    allow: AllowList = None

    @model_validator(mode="after")
    def _idle_timeout_off_or_sane(self) -> TcpOptions:
        if 0 < self.idle_timeout_s < 0.1:
            raise ValueError("idle_timeout_s must be 0 (off) or at least 0.1 s")
        return self


class ModbusTcpConnection(asyncio.Protocol):
    """One client connection: bytes through the MBAP framer (``vgripd.peer.mbap``), requests
    answered in order, output bounded."""

    def __init__(self, link: ModbusServerLink) -> None:
        self.link = link
        self.transport: asyncio.Transport | None = None
        self.host = "?"  # the client's address: the rate-limited log's key
        self.client = "?"  # address:port, for messages
        self.connected_at = time.monotonic()
        self.last_request = self.connected_at  # the idle clock: complete requests only
        self.requests = 0
        self.peak_unsent = 0  # the most answer bytes that ever waited for this client
        self.closing = False
        self.refused = False  # closed at accept by the gate (allow, full)
        self.framer = mbap.MbapFramer()
        self._paused = False
        self._continue: asyncio.Handle | None = None

    # asyncio.Protocol ------------------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        peer = transport.get_extra_info("peername")
        if isinstance(peer, tuple) and len(peer) >= 2:
            self.host = str(peer[0])
            self.client = f"{peer[0]}:{peer[1]}"
        self.link._admit(self)

    def data_received(self, data: bytes) -> None:
        if self.closing:
            return
        self.framer.feed(data)
        if not self._paused:
            self._answer_batch()

    def eof_received(self) -> bool:
        return False  # answers already written are flushed, then the transport closes

    def connection_lost(self, exc: Exception | None) -> None:
        self.closing = True
        if self._continue is not None:
            self._continue.cancel()
            self._continue = None
        self.link._forget(self)

    def shut(self, reason: str) -> None:
        """Closed by the gate (evicted, timed out; already logged)."""
        self.close(abort=False)

    # framing ---------------------------------------------------------------------------

    def _answer_batch(self) -> None:
        """Answer the complete requests the framer holds, at most a batch; when more remain,
        stop reading and go on after the loop has served the others."""
        framer, answered, more = self.framer, 0, False
        now = time.monotonic()
        try:
            while (frame := framer.next_frame()) is not None:
                answered += 1
                self.requests += 1
                self.last_request = now
                reply = self.link._answer(frame.unit, frame.pdu, self)
                if reply is not None and not self._send(frame.tid, frame.unit, reply):
                    return
                if answered == REQUESTS_PER_BATCH:
                    more = framer.has_frame()
                    break
        except MalformedFrame as err:
            self.link.fault(self.host, "malformed", logging.WARNING,
                            "%s: malformed frame, connection closed: %s", self.client, err)
            self.link._drop(self, abort=False)
            return
        if more:
            self._yield_loop()
        else:
            self._resume()

    def _send(self, tid: int, unit: int, reply: bytes) -> bool:
        """Write one answer; False when the client was dropped for not reading."""
        assert self.transport is not None
        self.transport.write(mbap.encode(tid, unit, reply))
        unsent = self.transport.get_write_buffer_size()
        if unsent > self.peak_unsent:
            self.peak_unsent = unsent
            self.link.peak_unsent = max(self.link.peak_unsent, unsent)
        if unsent <= self.link.options.max_unsent_bytes:
            return True
        self.link.fault(self.host, "not_reading", logging.WARNING,
                        "%s: %d bytes of answers unread (max_unsent_bytes = %d), client dropped",
                        self.client, unsent, self.link.options.max_unsent_bytes)
        self.link._drop(self, abort=True)
        return False

    def _yield_loop(self) -> None:
        assert self.transport is not None
        if not self._paused:
            self._paused = True
            self.transport.pause_reading()
        loop = asyncio.get_running_loop()
        self._continue = loop.call_soon(self._go_on)

    def _go_on(self) -> None:
        self._continue = None
        if not self.closing:
            self._answer_batch()

    def _resume(self) -> None:
        if self._paused and not self.closing and self._continue is None:
            self._paused = False
            assert self.transport is not None
            self.transport.resume_reading()

    def close(self, abort: bool) -> None:
        """Close (answers already written go out first) or, with ``abort`` or when answers are
        still waiting for a client that does not read them, reset the connection."""
        if self.closing or self.transport is None:
            return
        self.closing = True
        if abort or self.transport.get_write_buffer_size():
            self.transport.abort()
        else:
            self.transport.close()


class ModbusServerLink(RegisterServerLink):
    Options = TcpOptions
    options: TcpOptions

    def __init__(self, name: str, options: Any) -> None:
        super().__init__(name, options)
        self._listener: asyncio.Server | None = None
        o: TcpOptions = options
        #: the connections (in order of arrival), their cap, eviction, idle timeout, allow
        self.gate = Gate(name, o.max_connections, allow=o.allow, idle_timeout_s=o.idle_timeout_s,
                         lines=self.ratelog, faults=self.faults)
        #: the most answer bytes that ever waited in the link for one client
        self.peak_unsent = 0

    @property
    def port(self) -> int:
        """The bound port (the configured one, or the one chosen for port 0)."""
        if self._listener is not None and self._listener.sockets:
            port: int = self._listener.sockets[0].getsockname()[1]
            return port
        return self.options.port

    def connections(self) -> list[ModbusTcpConnection]:
        """The open client connections, oldest first."""
        return self.gate.connections()

    def _describe(self) -> str:
        return f"{self.options.host}:{self.port}"

    def _unit_id(self) -> int | None:
        return self.options.unit_id

    async def _start_serving(self) -> None:
        o = self.options
        loop = asyncio.get_running_loop()
        try:
            self._listener = await loop.create_server(
                lambda: ModbusTcpConnection(self), o.host, o.port, backlog=self.gate.backlog)
        except OSError as err:
            reason = os.strerror(err.errno) if err.errno else str(err)
            raise LinkError(f"cannot listen on {o.host}:{o.port}: {reason} (check host and "
                            f"port of this [[links]] entry)") from None
        self.gate.start()

    async def _stop_serving(self) -> None:
        await self.gate.stop()
        if self._listener is not None:
            self._listener.close()
            for conn in self.gate.connections():
                self.gate.forget(conn)
                conn.close(abort=True)
            await self._listener.wait_closed()
            self._listener = None

    def peers(self) -> int:
        return len(self.gate)

    # connections -------------------------------------------------------------------------

    def _admit(self, conn: ModbusTcpConnection) -> None:
        """A new connection: the gate admits it (evicting never-answered ones beyond the cap)
        or it is closed at once; then keepalive."""
        o = self.options
        if not self.gate.admit(conn):
            conn.refused = True
            conn.close(abort=True)
            return
        self.ratelog.info(conn.host, "connected", "%s: client %s connected (%d open)",
                          self.name, conn.client, len(self.gate))
        if o.keepalive and conn.transport is not None:
            sock = conn.transport.get_extra_info("socket")
            if sock is not None:
                set_keepalive(sock, o.keepalive_idle_s, o.keepalive_interval_s,
                              o.keepalive_count)

    def _drop(self, conn: ModbusTcpConnection, abort: bool) -> None:
        self.gate.forget(conn)
        conn.close(abort)

    def _forget(self, conn: ModbusTcpConnection) -> None:
        self.gate.forget(conn)

    def _answer(self, unit: int, pdu: bytes, conn: ModbusTcpConnection) -> bytes | None:
        """The response PDU, or None for a request to a unit id this link does not answer."""
        o = self.options
        if (o.unit_id is not None and unit != o.unit_id
                and not (o.unit_id_wildcards and unit in (0, 255))):
            self.fault(conn.host, "unit", logging.WARNING,
                       "%s: request for unit id %d not answered (this link is unit %d%s)",
                       conn.client, unit, o.unit_id,
                       ", 0 and 255" if o.unit_id_wildcards else "")
            self.gate.activity(conn, valid=False)
            return None
        reply, decision = self.answer_pdu(pdu, conn.host)
        if isinstance(decision, Malformed):
            raise MalformedFrame(decision.detail)
        # valid: answered normally (not an exception): what a polling PLC gets
        self.gate.activity(conn, valid=bool(reply) and reply[0] < 0x80)
        return reply
