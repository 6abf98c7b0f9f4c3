"""A stand-in for a robot controller's own Modbus/TCP server (e.g. Universal Robots, port 502).

Cells without a PLC let vgripd write straight into the robot: the robot exposes general-purpose
holding registers (UR: 128-255) and its program polls them. ``MockRobotModbus`` is that server,
run by pymodbus on 127.0.0.1 (a free port unless one is given):

- holding registers ``first .. first+count-1`` only; any other address or table answers with
  the Modbus exception ILLEGAL_DATA_ADDRESS, as UR's server does;
- a simulated robot program on ``vgripd.peer.registers``'s map (``run_job``, or ``start_program``
for
  a loop on an asyncio task): writes a new request sequence, waits until vgripd acknowledges
  (or refuses) it, snapshots the block and checks the byte-order words;
- misbehaviour switches: ``go_offline``/``come_back`` (drop every connection and stop
  listening, then listen again on the same port), ``drop_connections`` (drop, keep listening),
  ``RobotMode.SILENT`` (accept TCP, never answer) and ``RobotMode.REFUSE`` (answer every request
  with an exception code).

Every network write is logged (address and words, in arrival order) so tests can check what was
written in which order, e.g. that the acknowledge word came last in its own transaction.
"""

from __future__ import annotations

import asyncio
import enum
from collections.abc import Sequence
from dataclasses import dataclass

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from vgripd.errors import LinkError
from vgripd.peer.jobcore import Command
from vgripd.peer.registers import CHECK_U16, CHECK_U32, MAP_SIZE, Reg, ValueCodec

UR_FIRST_REGISTER = 128
UR_REGISTER_COUNT = 128

_HOLDING_CODES = frozenset({3, 6, 16, 22, 23})
_WRITE_CODES = frozenset({6, 16, 22, 23})


class RobotMode(enum.Enum):
    NORMAL = "normal"
    SILENT = "silent"  # TCP accepted, requests never answered (a hung controller)
    REFUSE = "refuse"  # every request answered with ``refuse_code``


@dataclass(frozen=True)
class RegisterWrite:
    """One write transaction as the robot received it."""

    address: int
    values: tuple[int, ...]


@dataclass(frozen=True)
class JobSeen:
    """What the simulated robot program saw for one job.

    ``words``: the map block (``MAP_SIZE`` words, index = map offset) at the moment ACK_SEQ or
    REJECT_SEQ matched; ``writes``: the write transactions received while the job ran.
    """

    seq: int
    words: tuple[int, ...]
    writes: tuple[RegisterWrite, ...]


class MockRobotModbus:
    """Mock robot Modbus/TCP server; ``start``/``stop`` from the test's event loop."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        first: int = UR_FIRST_REGISTER,
        count: int = UR_REGISTER_COUNT,
    ) -> None:
        self.host = host
        self.port = port
        self.first = first
        self.count = count
        self.mode = RobotMode.NORMAL
        self.refuse_code: int = ExcCodes.ILLEGAL_ADDRESS
        self.writes: list[RegisterWrite] = []
        self.requests = 0
        self._regs = [0] * count
        self._server: ModbusTcpServer | None = None
        self._changed = asyncio.Condition()
        self._release_silent = asyncio.Event()
        self._program: asyncio.Task[None] | None = None
        self.jobs_done = 0

    # -- lifecycle ---------------------------------------------------------------------------

    async def start(self) -> None:
        """Listen; with ``port=0`` a free port is chosen and kept for ``come_back``."""
        device = SimDevice(
            id=0,
            simdata=[
                SimData(self.first, count=self.count, values=0, datatype=DataType.REGISTERS)
            ],
            action=self._action,
        )
        server = ModbusTcpServer(device, address=(self.host, self.port))
        await server.serve_forever(background=True)
        self._server = server
        if self.port == 0:
            sockets = getattr(server.transport, "sockets", None)
            if not sockets:
                raise LinkError(f"mock robot: cannot tell which port {self.host} listens on")
            self.port = int(sockets[0].getsockname()[1])
        self._release_silent.clear()

    async def stop(self) -> None:
        await self.stop_program()
        await self.go_offline()

    async def go_offline(self) -> None:
        """Drop every connection and stop listening (a controller reboot or pulled cable)."""
        self._release_silent.set()  # let held (silent) handlers finish before the sockets go
        if self._server is not None:
            server, self._server = self._server, None
            await server.shutdown()

    async def come_back(self) -> None:
        """Listen again on the same port, registers kept."""
        await self.start()

    def drop_connections(self) -> None:
        """Close every client connection; keep listening."""
        if self._server is not None:
            for conn in list(self._server.active_connections.values()):
                conn.close()

    @property
    def connections(self) -> int:
        return 0 if self._server is None else len(self._server.active_connections)

    # -- register access for tests and the simulated program ---------------------------------

    def read(self, address: int, count: int = 1) -> list[int]:
        i = self._index(address, count)
        return self._regs[i : i + count]

    async def write(self, address: int, values: Sequence[int]) -> None:
        """Write as the robot program does (not a network write: not logged)."""
        i = self._index(address, len(values))
        self._regs[i : i + len(values)] = [int(v) & 0xFFFF for v in values]
        async with self._changed:
            self._changed.notify_all()

    async def changed(self) -> None:
        """Wait for the next register change (a network write or the program's own)."""
        async with self._changed:
            await self._changed.wait()

    def _index(self, address: int, count: int) -> int:
        if address < self.first or address + count > self.first + self.count:
            last = self.first + self.count - 1
            raise ValueError(
                f"registers {address}..{address + count - 1} outside the robot's"
                f" {self.first}..{last}"
            )
        return address - self.first

    # -- simulated robot program -------------------------------------------------------------

    async def run_job(
        self, seq: int, timeout_s: float, base: int = UR_FIRST_REGISTER,
        command: int = Command.TRIGGER, recipe: int = 0, codec: ValueCodec | None = None,
        latch: int | None = None, size: int = MAP_SIZE,
    ) -> JobSeen:
        """One cycle of the robot program on ``vgripd.peer.registers``'s map at ``base``.

        Sets CMD and RECIPE (and with ``latch``, map version 4: LATCH_COUNT, the encoder count
        latched or PREDICT's N, in ``codec``'s word order), then raises REQ_SEQ to ``seq``;
        waits until ACK_SEQ or REJECT_SEQ equals ``seq``; snapshots the block (``size`` words)
        and checks the byte-order words (``codec``: the word order the program expects, ABCD
        float32 by default). Raises ``LinkError`` when the check words are wrong and
        ``TimeoutError`` when no answer comes.
        """
        codec = codec or ValueCodec()
        start = len(self.writes)
        await self.write(base + Reg.CMD, [command])
        await self.write(base + Reg.RECIPE, [recipe])
        if latch is not None:
            await self.write(base + Reg.LATCH_COUNT, codec.u32(latch & 0xFFFFFFFF))
        await self.write(base + Reg.REQ_SEQ, [seq])
        ack, reject = base + Reg.ACK_SEQ, base + Reg.REJECT_SEQ
        async with asyncio.timeout(timeout_s), self._changed:
            await self._changed.wait_for(
                lambda: seq in (self._regs[ack - self.first], self._regs[reject - self.first])
            )
        words = tuple(self.read(base, size))  # the map's words: 46, or 62 in version 4
        check = (words[Reg.CHECK_U16], codec.decode_u32(words[Reg.CHECK_U32:Reg.CHECK_U32 + 2]))
        if check != (CHECK_U16, CHECK_U32):
            raise LinkError(f"robot program: check words {check} at base {base} are not "
                            f"({CHECK_U16:#x}, {CHECK_U32:#x}) in word order {codec.word_order}")
        self.jobs_done += 1
        return JobSeen(seq, words, tuple(self.writes[start:]))

    def start_program(self, timeout_s: float, base: int = UR_FIRST_REGISTER) -> None:
        """Run jobs back to back on a task until ``stop_program`` (benchmarks, soak tests)."""

        async def loop() -> None:
            seq = 1
            while True:
                await self.run_job(seq, timeout_s, base)
                seq = seq % 0xFFFF + 1

        self._program = asyncio.create_task(loop(), name="mock robot program")

    async def stop_program(self) -> None:
        task, self._program = self._program, None
        if task is not None:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    # -- pymodbus hook -----------------------------------------------------------------------

    async def _action(
        self,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        current_registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        """Called by pymodbus for every valid request; our ``_regs`` is the truth.

        pymodbus reads its own list after this returns, so reads are served by copying our
        words into it; writes are logged and applied to ours.
        """
        self.requests += 1
        if function_code not in _HOLDING_CODES:
            return ExcCodes.ILLEGAL_ADDRESS  # only holding registers exist
        if self.mode is RobotMode.SILENT:
            await self._release_silent.wait()
            return ExcCodes.DEVICE_BUSY
        if self.mode is RobotMode.REFUSE:
            return ExcCodes(self.refuse_code)  # pymodbus only recognises the enum
        base = self.first - start_address
        if function_code in _WRITE_CODES and set_values is not None:
            words = tuple(int(v) for v in set_values)
            self.writes.append(RegisterWrite(address, words))
            i = address - self.first
            self._regs[i : i + len(words)] = list(words)
            async with self._changed:
                self._changed.notify_all()
        current_registers[base : base + self.count] = self._regs
        return None
