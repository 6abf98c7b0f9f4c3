"""Modbus/TCP client link: vgripd writes into the robot controller's own Modbus server.

Cells without a PLC: the robot (e.g. Universal Robots, port 502, general-purpose holding
registers 128-255) serves the registers and its program polls them; vgripd is the client. The
register block is ``vgripd.service.protocol``'s map (``MAP_SIZE`` words, same offsets, encoding and
handshake as the Modbus server link), placed at ``base_address`` in the robot's register space:
the robot program writes the command area (CMD, REQ_SEQ, RECIPE), vgripd writes the rest.

The link keeps a mirror of the block in a ``RegisterBank`` (the same handshake and image code
the server link uses) and copies its changes to the robot, in the bank's order:

- the robot's command area is polled every ``poll_interval_s``; a change goes through the
  bank's handshake: a new request sequence calls ``on_trigger``, a refusal writes REJECT_*;
- ``image_captured``/``publish``/the heartbeat change the mirror and wake the supervisor, which
  writes the changed words with as few ``write_registers`` as the order allows; ACK_SEQ always
  travels alone, in the order the bank put it (last for a publish, first for a new job's
  retraction), so the robot never pairs an acknowledged sequence with other data;
- after every (re)connect the whole mirror is written (data, then ACK_SEQ), so a result
  published while the robot was away reaches it as soon as it is back.

One supervisor task owns the connection and is the only retry loop: pymodbus' own reconnect
and retries are off (``reconnect_delay=0``, ``retries=0``). After a drop it reconnects with
doubling back-off and logs once per outage (one WARNING line, no traceback: every way a
request can fail on a dropped or silent connection is a ``LinkError`` naming it);
``health()`` says DOWN with the reason (address, port, Modbus exception, register). pymodbus
logs its own line for each unanswered request and failed connect; ``quiet_pymodbus`` filters
exactly those (the link reports the outage itself) unless the ``pymodbus`` logger is set to
DEBUG for troubleshooting. A daemon call waiting for the robot (``publish``,
``image_captured``) is always released with the outage, never left to time out.

If the robot refuses a register of the block at the first contact (ILLEGAL_ADDRESS or
ILLEGAL_FUNCTION) the link is FAILED and not retried: a wrong ``base_address`` does not fix
itself; other exception codes (busy, device failure) are retried.

RESULT_AGE_MS is live on the server link; here it is refreshed with every heartbeat. WARNINGS
(map register 40) is written when the daemon changes it, like any other mirror change.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import time
from collections.abc import Awaitable, Callable, Mapping, Sequence

from pydantic import Field
from pymodbus.client import AsyncModbusTcpClient
from pymodbus.constants import ExcCodes
from pymodbus.exceptions import ModbusException
from pymodbus.pdu import ModbusPDU

from vgripd.errors import LinkError
from vgripd.service.protocol import (
    COMMAND_AREA,
    MAP_SIZE,
    REGISTER_CAPABILITIES,
    Action,
    BlockWrite,
    LinkHealth,
    LinkState,
    Reg,
    RegisterBank,
    RegisterOptions,
    RobotLink,
    Trigger,
    TriggerHandler,
    ValueCodec,
)
from vgripd.types import JobResult, Status

log = logging.getLogger(__name__)

MAX_WRITE_WORDS = 123  # Modbus limit of one write-multiple request

# pymodbus' own log lines for what the supervisor reports once per outage (client side).
PYMODBUS_NOISE = (
    "No response received after",
    "Failed to connect",
    "Cancel send, because not connected",
    "Not connected, trying to connect",
    "received pdu without a corresponding request",
)


class _PymodbusNoise(logging.Filter):
    """Drops pymodbus' per-request retry and connect lines (``PYMODBUS_NOISE``) unless the
    ``pymodbus`` logger is at DEBUG: the links log one line per outage themselves."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < logging.WARNING or logging.getLogger("pymodbus").isEnabledFor(
                logging.DEBUG):
            return True
        text = record.getMessage()
        return not any(noise in text for noise in PYMODBUS_NOISE)


_NOISE_FILTER = _PymodbusNoise()


def quiet_pymodbus() -> None:
    """Install the noise filter on pymodbus' logger (idempotent; affects the whole process,
    and only the lines in ``PYMODBUS_NOISE``)."""
    logger = logging.getLogger("pymodbus.logging")
    if _NOISE_FILTER not in logger.filters:
        logger.addFilter(_NOISE_FILTER)


class ModbusClientOptions(RegisterOptions):
    """Options of ``type = "modbus_client"``; word order, value format and heartbeat as for
    every register link (``RegisterOptions``)."""

    host: str = Field(min_length=1)
    port: int = Field(502, ge=1, le=65535)
    unit_id: int = Field(1, ge=0, le=255)
    base_address: int = Field(128, ge=0, le=65536 - MAP_SIZE)
    poll_interval_s: float = Field(0.02, gt=0, le=10)
    timeout_s: float = Field(1.0, gt=0, le=60)  # connect, and each request
    backoff_initial_s: float = Field(0.1, gt=0, le=60)
    backoff_max_s: float = Field(5.0, gt=0, le=600)


class RegisterRefused(LinkError):
    """The robot answered a request with a Modbus exception (``code``)."""

    def __init__(self, message: str, code: int) -> None:
        super().__init__(message)
        self.code = code

    @property
    def permanent(self) -> bool:
        """The block is not there (as opposed to a busy or failing device)."""
        return self.code in (ExcCodes.ILLEGAL_FUNCTION, ExcCodes.ILLEGAL_ADDRESS)


def plan_writes(journal: Sequence[BlockWrite]) -> list[BlockWrite]:
    """The bank's block writes (map offsets) as few robot writes as their order allows.

    Command-area words are the robot's and are dropped. Consecutive writes merge when the next
    starts where the previous ends (or inside it); a write touching ACK_SEQ never merges, so
    the acknowledge stays a transaction of its own at its place in the order.
    """
    plan: list[BlockWrite] = []
    for w in journal:
        address, words = w.address, w.words
        if address < COMMAND_AREA.stop:  # strip the robot's own words
            cut = min(COMMAND_AREA.stop - address, len(words))
            address, words = address + cut, words[cut:]
        if not words:
            continue
        is_ack = address <= Reg.ACK_SEQ < address + len(words)
        if plan and not is_ack:
            last = plan[-1]
            end = last.address + len(last.words)
            last_is_ack = last.address <= Reg.ACK_SEQ < end
            if not last_is_ack and last.address <= address <= end:
                merged = list(last.words[: address - last.address]) + list(words)
                merged += last.words[address - last.address + len(words):]
                plan[-1] = BlockWrite(last.address, tuple(merged))
                continue
        plan.append(BlockWrite(address, tuple(words)))
    return plan


def full_image_writes(words: Sequence[int]) -> list[BlockWrite]:
    """The whole block except the command area: data first, ACK_SEQ last."""
    first = COMMAND_AREA.stop
    return [
        BlockWrite(first, tuple(words[first:Reg.ACK_SEQ])),
        BlockWrite(Reg.STATUS, tuple(words[Reg.STATUS:MAP_SIZE])),
        BlockWrite(Reg.ACK_SEQ, (words[Reg.ACK_SEQ],)),
    ]


class ModbusClientLink(RobotLink):
    Options = ModbusClientOptions
    capabilities = REGISTER_CAPABILITIES
    options: ModbusClientOptions

    def __init__(self, name: str, options: ModbusClientOptions) -> None:
        super().__init__(name, options)
        self._peer = f"{options.host}:{options.port}"
        self._journal: list[BlockWrite] = []
        self.bank = RegisterBank(
            ValueCodec(options.word_order, options.value_format, options.scale), self._journal
        )
        self._health = LinkHealth(LinkState.STOPPED, peer=self._peer)
        self._health_changed: asyncio.Condition | None = None
        self._on_trigger: TriggerHandler | None = None
        self._task: asyncio.Task[None] | None = None
        self._wake: asyncio.Event | None = None
        self._waiters: list[asyncio.Future[None]] = []
        self._lost: asyncio.Future[None] | None = None
        self._primed = False
        self.transactions = 0  # requests sent to the robot (benchmarks, tests)

    # -- RobotLink ---------------------------------------------------------------------------

    async def open(self, on_trigger: TriggerHandler) -> None:
        """Start the supervisor and wait for the outcome of its first contact.

        Raises ``LinkError`` (state FAILED) if the robot refuses a register of the block. An
        unreachable robot is not an error here: the supervisor keeps retrying (state DOWN).
        """
        if self._task is not None:
            raise LinkError(f"link {self.name}: already open")
        quiet_pymodbus()
        self._on_trigger = on_trigger
        self._health_changed = asyncio.Condition()
        self._wake = asyncio.Event()
        self._task = asyncio.create_task(self._supervise(), name=f"{self.name}-supervisor")
        # connect + one read each take at most timeout_s; a slower first contact stays with
        # the supervisor (CONNECTING) rather than failing the start
        with contextlib.suppress(TimeoutError):
            await self.wait_state({LinkState.UP, LinkState.DOWN, LinkState.FAILED},
                                  2 * self.options.timeout_s + 1.0)
        health = self._health
        if health.state is LinkState.FAILED:
            await self._stop_task()
            raise LinkError(f"link {self.name}: {health.last_error}")

    async def close(self) -> None:
        await self._stop_task()
        await self._set_health(LinkState.STOPPED)

    def health(self) -> LinkHealth:
        return self._health

    async def image_captured(self, seq: int, job_id: int) -> None:
        self.bank.captured(seq, job_id)
        await self._flushed()

    async def publish(self, seq: int, result: JobResult) -> Status:
        """Publish into the mirror, then wait until the robot has it; returns the status the
        robot got.

        Raises ``LinkError`` when the robot is not connected; the result stays in the mirror and
        is written (ACK_SEQ last) as soon as the robot is back.
        """
        published = self.bank.publish(seq, result, time.monotonic_ns())
        if published.status is not result.status:
            log.warning("%s: request %d published as %s instead of %s: %s", self.name, seq,
                        published.status.name, result.status.name, published.message)
        await self._flushed()
        return published.status

    def refusals(self) -> Mapping[str, int]:
        return dict(self.bank.refusals)

    async def set_warnings(self, bits: int) -> None:
        """Set WARNINGS in the mirror; while the robot is connected, wait until it has it.

        Unlike ``publish`` this does not raise while the robot is away: the mirror is written
        whole at the reconnect, WARNINGS included.
        """
        self.bank.set_warnings(bits)
        if self._health.state is LinkState.UP:
            await self._flushed()

    async def wait_state(self, states: set[LinkState] | LinkState, timeout_s: float) -> LinkHealth:
        """Wait until ``health().state`` is in ``states``; ``TimeoutError`` otherwise."""
        wanted = {states} if isinstance(states, LinkState) else states
        if self._health_changed is None:
            raise LinkError(f"link {self.name}: not open")
        async with asyncio.timeout(timeout_s), self._health_changed:
            await self._health_changed.wait_for(lambda: self._health.state in wanted)
        return self._health

    # -- helpers for the daemon-facing calls -------------------------------------------------

    async def _flushed(self) -> None:
        if self._health.state is not LinkState.UP or self._wake is None:
            raise LinkError(
                f"link {self.name}: robot {self._peer} is {self._health.state.value}"
                f" ({self._health.last_error or 'not connected'}); kept for the reconnect"
            )
        done = asyncio.get_running_loop().create_future()
        self._waiters.append(done)
        self._wake.set()
        await done

    def _release_waiters(self, error: Exception) -> None:
        waiters, self._waiters = self._waiters, []
        for w in waiters:
            if not w.done():
                w.set_exception(error)

    async def _stop_task(self) -> None:
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
        self._release_waiters(LinkError(f"link {self.name}: closed"))

    async def _set_health(self, state: LinkState, error: str = "", reconnect: bool = False) -> None:
        h = self._health
        if state is h.state and error == h.last_error:
            return
        self._health = LinkHealth(
            state,
            peer=self._peer,
            last_error=error,
            reconnects=h.reconnects + int(reconnect),
            since_mono_ns=time.monotonic_ns() if state is not h.state else h.since_mono_ns,
        )
        if self._health_changed is not None:
            async with self._health_changed:
                self._health_changed.notify_all()

    # -- supervisor --------------------------------------------------------------------------

    async def _supervise(self) -> None:
        opt = self.options
        delay = opt.backoff_initial_s
        error = ""
        outage_logged = False
        while True:
            await self._set_health(LinkState.CONNECTING, error)
            client = AsyncModbusTcpClient(
                opt.host, port=opt.port, timeout=opt.timeout_s, retries=0,
                reconnect_delay=0,  # the supervisor is the only reconnect loop
                trace_connect=self._on_connection_change,
            )
            try:
                self._lost = asyncio.get_running_loop().create_future()
                if not await client.connect():
                    raise LinkError(f"cannot connect to {self._peer} (refused, or no answer "
                                    f"within {opt.timeout_s} s)")
                await self._first_contact(client)
                await self._set_health(LinkState.UP, reconnect=outage_logged)
                if outage_logged:
                    log.info("%s: robot %s is back", self.name, self._peer)
                outage_logged = False
                delay = opt.backoff_initial_s
                await self._serve(client)
            except RegisterRefused as err:
                error = str(err)
                if err.permanent and not self._primed:
                    log.error("%s: %s", self.name, error)
                    await self._set_health(LinkState.FAILED, error)
                    return
            except LinkError as err:
                error = str(err)
            except (OSError, ModbusException) as err:  # transport trouble pymodbus let through
                error = f"{self._peer}: {err}"
            except Exception as err:  # a bug must not leave a dead link reporting UP
                log.exception("%s: unexpected error talking to %s", self.name, self._peer)
                error = f"internal error: {err!r}"
            finally:
                client.close()
                self._lost = None
            self._release_waiters(LinkError(f"link {self.name}: {error}"))
            if not outage_logged:
                log.warning("%s: %s; retrying with back-off up to %.1f s", self.name, error,
                            opt.backoff_max_s)
                outage_logged = True
            await self._set_health(LinkState.DOWN, error)
            await asyncio.sleep(delay)
            delay = min(2 * delay, opt.backoff_max_s)

    def _on_connection_change(self, connected: bool) -> None:
        if not connected and self._lost is not None and not self._lost.done():
            self._lost.set_result(None)

    async def _first_contact(self, client: AsyncModbusTcpClient) -> None:
        """Check the robot serves the whole block, adopt its command area, write the mirror."""
        words = await self._read_block(client)
        if not self._primed:
            # A request the robot made before this process ran counts only if it is still
            # unanswered (its ACK_SEQ differs); otherwise it would rerun an old job.
            cmd = tuple(words[COMMAND_AREA.start:COMMAND_AREA.stop])
            if words[Reg.ACK_SEQ] == words[Reg.REQ_SEQ]:
                self.bank.image.apply([BlockWrite(COMMAND_AREA.start, cmd)])
                self.bank.handshake.last_req_seq = words[Reg.REQ_SEQ]
            self._primed = True
        self._journal.clear()
        await self._write_plan(client, full_image_writes(self.bank.image.words))

    async def _read_block(self, client: AsyncModbusTcpClient) -> list[int]:
        """The whole block; if refused, find and name the first register the robot refuses."""
        base = self.options.base_address
        try:
            return await self._read(client, base, MAP_SIZE)
        except RegisterRefused:
            for offset in range(MAP_SIZE):
                try:
                    await self._read(client, base + offset, 1)
                except RegisterRefused as err:
                    name = next(r.name for r in reversed(Reg) if r.value <= offset)
                    raise RegisterRefused(
                        f"{err} (block base {base} + {offset}, map register {name})", err.code
                    ) from None
            raise

    async def _serve(self, client: AsyncModbusTcpClient) -> None:
        assert self._wake is not None
        period_s = self.options.heartbeat_ms / 1000
        next_beat = time.monotonic() + period_s
        while True:
            await self._flush(client)
            cmd = await self._read(client, self.options.base_address + COMMAND_AREA.start,
                                   len(COMMAND_AREA))
            if cmd != self.bank.image.words[COMMAND_AREA.start:COMMAND_AREA.stop]:
                self._on_command(cmd)
                continue  # write the handshake's answer (if any) before the next poll
            now = time.monotonic()
            if now >= next_beat:
                self.bank.beat()
                age = self.bank.read(Reg.RESULT_AGE_MS, 2, time.monotonic_ns())
                self.bank.image.apply([BlockWrite(Reg.RESULT_AGE_MS, tuple(age))])
                next_beat = max(next_beat + period_s, now)
                continue
            self._wake.clear()
            if self._waiters or self._journal:
                continue
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(min(self.options.poll_interval_s, next_beat - now)):
                    await self._wake.wait()

    def _on_command(self, cmd: list[int]) -> None:
        decision = self.bank.write(COMMAND_AREA.start, cmd)
        if decision.action is Action.START:
            assert self._on_trigger is not None
            trigger = Trigger(link=self.name, seq=decision.seq, command=decision.command,
                              t_mono_ns=time.monotonic_ns(), recipe=decision.recipe)
            asyncio.get_running_loop().call_soon(self._on_trigger, trigger)
        elif decision.action is Action.REJECT:
            log.info("%s: request %d refused: %s", self.name, decision.seq, decision.code.name)

    async def _flush(self, client: AsyncModbusTcpClient) -> None:
        """Write the mirror's changes since the last flush, then release who waited for them."""
        if not self._journal and not self._waiters:
            return
        waiters, self._waiters = self._waiters, []
        plan = plan_writes(self._journal)
        self._journal.clear()
        try:
            await self._write_plan(client, plan)
        except BaseException:
            self._waiters = waiters + self._waiters  # released with the outage's reason
            raise
        for w in waiters:
            if not w.done():
                w.set_result(None)

    async def _write_plan(self, client: AsyncModbusTcpClient, plan: Sequence[BlockWrite]) -> None:
        base, unit = self.options.base_address, self.options.unit_id
        for w in plan:
            for i in range(0, len(w.words), MAX_WRITE_WORDS):
                chunk = list(w.words[i:i + MAX_WRITE_WORDS])
                address = base + w.address + i
                await self._call(
                    "writing",
                    functools.partial(client.write_registers, address, chunk, device_id=unit),
                    address, len(chunk),
                )

    async def _read(self, client: AsyncModbusTcpClient, address: int, count: int) -> list[int]:
        unit = self.options.unit_id
        pdu = await self._call(
            "reading",
            lambda: client.read_holding_registers(address, count=count, device_id=unit),
            address, count,
        )
        words = list(pdu.registers)
        if len(words) != count:
            raise LinkError(f"{self._peer} returned {len(words)} words for holding registers "
                            f"{address}..{address + count - 1}")
        return words

    async def _call(self, what: str, request: Callable[[], Awaitable[ModbusPDU]],
                    address: int, count: int) -> ModbusPDU:
        """One request; a drop, silence or an exception answer becomes a ``LinkError``.

        pymodbus leaves a request whose connection dropped waiting for its full timeout; racing
        it against the connection-lost signal notices a drop at once.
        """
        assert self._lost is not None
        self.transactions += 1
        where = f"{what} holding registers {address}..{address + count - 1} on {self._peer}"
        if self._lost.done():
            raise LinkError(f"connection lost before {where}")
        try:
            task = asyncio.ensure_future(request())
        except ModbusException:  # pymodbus raises at once when its transport is already gone
            raise LinkError(f"connection lost before {where}") from None
        try:
            await asyncio.wait((task, self._lost), return_when=asyncio.FIRST_COMPLETED)
        finally:
            if not task.done():
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError, ModbusException):
                    await task
        if task.cancelled():
            raise LinkError(f"connection to {self._peer} lost while {where}")
        if (err := task.exception()) is not None:
            if not isinstance(err, ModbusException):
                raise err
            if self._lost.done():
                raise LinkError(f"connection to {self._peer} lost while {where}")
            raise LinkError(f"no answer within {self.options.timeout_s} s {where}")
        pdu = task.result()
        if pdu.isError():
            code = int(getattr(pdu, "exception_code", 0))
            try:
                name = ExcCodes(code).name
            except ValueError:
                name = "unknown"
            raise RegisterRefused(f"robot {self._peer} answered Modbus exception {code} "
                                  f"({name}) {where}", code)
        return pdu
