"""Modbus/TCP client link: vgripd writes into the robot controller's own Modbus server.

Cells without a PLC: the robot (e.g. Universal Robots, port 502, general-purpose holding
registers 128-255) serves the registers and its program polls them; vgripd is the client. The
register block is ``vgripd.peer.registers``'s map (46 words; 62 with ``map_version = 4``, the
conveyor's; same offsets, encoding and handshake as the Modbus server link), placed at
``base_address`` in the robot's register space: the robot program writes the command area (CMD,
REQ_SEQ, RECIPE) and in map version 4 the latch (LATCH_COUNT, LATCH_FRAME: 46-49) before or
with REQ_SEQ; vgripd writes the rest and never those words.

The link keeps a mirror of the block in a ``RegisterBank`` (the same handshake and image code
the server link uses) and copies its changes to the robot, in the bank's order:

- the robot's command area is polled every ``poll_interval_s`` (map version 4: words 0-49 in
  one read, so a request's latch is of the same moment as its REQ_SEQ); a change goes through
  the bank's handshake: a new request sequence calls ``on_trigger``, a refusal writes REJECT_*;
- ``image_captured``/``publish``/the heartbeat change the mirror and wake the supervisor, which
  writes the changed words with as few ``write_registers`` as the order allows (pieces a few
  untouched words apart join, carrying those words' unchanged values); ACK_SEQ always
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

Every error is retried, whatever the robot did. A register of the block the robot refuses
(ILLEGAL_ADDRESS or ILLEGAL_FUNCTION: a wrong ``base_address``, a robot whose Modbus setup is
being changed) is logged once at ERROR, naming the register, and retried like any outage;
other exception codes (busy, device failure) and answers that are not Modbus are outages too.

RESULT_AGE_MS is live on the server link; here it is refreshed with every heartbeat. WARNINGS
(map register 40) is written when the daemon changes it, like any other mirror change.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
from collections.abc import Awaitable, Callable, Sequence

from pydantic import Field, model_validator
from pymodbus.client import AsyncModbusTcpClient
from pymodbus.constants import ExcCodes
from pymodbus.exceptions import ModbusException
from pymodbus.pdu import ModbusPDU

from drivers.links.mirror_client import MirrorClientLink, without_peer_words
from vgripd.errors import LinkError
from vgripd.peer.registers import (
    COMMAND_AREA,
    MAP_SIZE,
    BlockWrite,
    Reg,
    RegisterOptions,
    map_size,
)
from vgripd.registry import REGISTER_CAPABILITIES
from vgripd.service.links.supervisor import BackoffOptions

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


class ModbusClientOptions(RegisterOptions, BackoffOptions):
    """Options of ``type = "modbus_client"``; word order, value format and heartbeat as for
    every register link (``RegisterOptions``), back-off as every link that reconnects
    (``BackoffOptions``)."""

    host: str = Field(min_length=1)
    port: int = Field(502, ge=1, le=65535)
    unit_id: int = Field(1, ge=0, le=255)
    base_address: int = Field(128, ge=0, le=65536 - MAP_SIZE)
    poll_interval_s: float = Field(0.02, gt=0, le=10)
    timeout_s: float = Field(1.0, gt=0, le=60)  # connect, and each request

    @model_validator(mode="after")
    def _fits(self) -> ModbusClientOptions:
        size = map_size(self.map_version)
        if self.base_address + size > 65536:
            raise ValueError(f"base_address {self.base_address}: the block of map version "
                             f"{self.map_version} ({size} registers) must end at register 65535;"
                             f" base_address at most {65536 - size}")
        return self


class RegisterRefused(LinkError):
    """The robot answered a request with a Modbus exception (``code``)."""

    def __init__(self, message: str, code: int) -> None:
        super().__init__(message)
        self.code = code

    @property
    def permanent(self) -> bool:
        """The block is not there (as opposed to a busy or failing device)."""
        return self.code in (ExcCodes.ILLEGAL_FUNCTION, ExcCodes.ILLEGAL_ADDRESS)


#: The most untouched words a write may carry to join two pieces into one transaction.
MAX_GAP_WORDS = 8


def plan_writes(journal: Sequence[BlockWrite], peer: Sequence[range] = (COMMAND_AREA,),
                image: Sequence[int] | None = None) -> list[BlockWrite]:
    """The bank's block writes (map offsets) as few robot writes as their order allows.

    Words in the ``peer`` areas (the command area; in map version 4 the latch too) are the
    robot's and are dropped. Consecutive writes merge when the next starts where the previous
    ends (or inside it); a write touching ACK_SEQ never merges, so the acknowledge stays a
    transaction of its own at its place in the order. With ``image`` (the mirror's words, the
    journal applied), two pieces a few words apart merge too, the words between them taken from
    ``image``: only words no write of this journal touches (the robot already holds exactly
    those values, so writing them again changes nothing it can see), never ACK_SEQ or a peer
    word. A publish's data and pick-list words either side of WARNINGS are then one write.
    """
    touched = {a for w in journal for a in range(w.address, w.address + len(w.words))}

    def fills(start: int, stop: int) -> bool:
        return (image is not None and 0 < stop - start <= MAX_GAP_WORDS
                and not any(a in touched or a == Reg.ACK_SEQ or any(a in area for area in peer)
                            for a in range(start, stop)))

    plan: list[BlockWrite] = []
    for piece in (p for w in journal for p in without_peer_words(w, peer)):
        address, words = piece.address, piece.words
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
            if not last_is_ack and fills(end, address):
                assert image is not None
                plan[-1] = BlockWrite(last.address,
                                      (*last.words, *image[end:address], *words))
                continue
        plan.append(BlockWrite(address, tuple(words)))
    return plan


def full_image_writes(words: Sequence[int],
                      peer: Sequence[range] = (COMMAND_AREA,)) -> list[BlockWrite]:
    """The whole block except the ``peer`` areas: data first, ACK_SEQ last."""
    return [
        *without_peer_words(BlockWrite(0, tuple(words[:Reg.ACK_SEQ])), peer),
        *without_peer_words(BlockWrite(Reg.STATUS, tuple(words[Reg.STATUS:])), peer),
        BlockWrite(Reg.ACK_SEQ, (words[Reg.ACK_SEQ],)),
    ]


class ModbusClientLink(MirrorClientLink[AsyncModbusTcpClient]):
    Options = ModbusClientOptions
    capabilities = REGISTER_CAPABILITIES
    options: ModbusClientOptions
    peer_kind = "robot"
    _log = log

    def __init__(self, name: str, options: ModbusClientOptions) -> None:
        super().__init__(name, options)
        self._lost: asyncio.Future[None] | None = None

    # -- MirrorClientLink hooks ----------------------------------------------------------------

    def _starting(self) -> None:
        quiet_pymodbus()

    @property
    def _poll_s(self) -> float:
        return self.options.poll_interval_s

    def _new_client(self) -> AsyncModbusTcpClient:
        opt = self.options
        return AsyncModbusTcpClient(
            opt.host, port=opt.port, timeout=opt.timeout_s, retries=0,
            reconnect_delay=0,  # the supervisor is the only reconnect loop
            trace_connect=self._on_connection_change,
        )

    async def _connect(self, client: AsyncModbusTcpClient) -> None:
        self._lost = asyncio.get_running_loop().create_future()
        if not await client.connect():
            raise LinkError(f"cannot connect to {self._peer} (refused, or no answer "
                            f"within {self.options.timeout_s} s)")

    def _drop(self, client: AsyncModbusTcpClient) -> None:
        client.close()
        self._lost = None

    def _refusal_hint(self, err: LinkError) -> str | None:
        if isinstance(err, RegisterRefused) and err.permanent:
            return f"{err}; check base_address against the robot's register range"
        return None

    def _transport_error(self, err: Exception) -> str | None:
        if isinstance(err, (OSError, ModbusException)):  # transport trouble pymodbus let through
            return f"{self._peer}: {err}"
        return None

    def _on_connection_change(self, connected: bool) -> None:
        if not connected and self._lost is not None and not self._lost.done():
            self._lost.set_result(None)

    async def _write_mirror(self, client: AsyncModbusTcpClient, words: list[int]) -> None:
        """The whole mirror, whatever the robot has."""
        self._journal.clear()
        await self._write_plan(client, full_image_writes(self.bank.image.words,
                                                         self._peer_areas))

    async def _read_block(self, client: AsyncModbusTcpClient) -> list[int]:
        """The whole block; if refused, find and name the first register the robot refuses."""
        base, size = self.options.base_address, self.bank.image.size
        try:
            return await self._read(client, base, size)
        except RegisterRefused:
            for offset in range(size):
                try:
                    await self._read(client, base + offset, 1)
                except RegisterRefused as err:
                    name = next(r.name for r in reversed(Reg) if r.value <= offset)
                    raise RegisterRefused(
                        f"{err} (block base {base} + {offset}, map register {name})", err.code
                    ) from None
            raise

    async def _exchange(self, client: AsyncModbusTcpClient) -> list[int]:
        await self._flush(client)
        end = max(area.stop for area in self._peer_areas)  # from CMD through the latch
        return await self._read(client, self.options.base_address, end)

    async def _write_changes(self, client: AsyncModbusTcpClient) -> None:
        plan = plan_writes(self._journal, self._peer_areas, self.bank.image.words)
        self._journal.clear()
        await self._write_plan(client, plan)

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
