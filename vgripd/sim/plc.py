"""A scripted PLC: the Modbus/TCP client side of the register handshake
(``vgripd.peer.registers``).

It triggers a job (command, recipe and a new request sequence in one write), polls until the
request is answered (acknowledged or refused), and checks what a careful PLC program would:
the acknowledged sequence is its own, the status is a known code, pose values are present only
under a pose-valid status, the image-captured sequence was seen, and the byte-order check words
decode correctly, and WARNINGS has no reserved bit set. 32-bit items are decoded with pymodbus'
own converters, not vgripd's codec, so the check is independent of the server's encoder.

Pick lists (map version 3): ``next()`` asks for the following instance of the last job
(``Command.NEXT``) and checks the answer against the job it continues: the same JOB_ID, COUNT
unchanged, INDEX one further (or ``COUNT + 1`` with ``NOT_FOUND`` and no pose past the end), a
pose exactly when 1 <= INDEX <= COUNT, and RESULT_AGE_MS not younger than the job's.
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass
from types import TracebackType
from typing import Literal

from pymodbus.client import AsyncModbusTcpClient
from pymodbus.client.mixin import ModbusClientMixin

from vgripd.errors import LinkError
from vgripd.peer.jobcore import Command, HandshakeState, capture_word
from vgripd.peer.registers import (
    CHECK_F32,
    CHECK_U16,
    CHECK_U32,
    MAP_SIZE,
    MAP_VERSIONS,
    Reg,
    ValueFormat,
    Warnings,
    WordOrder,
)
from vgripd.types import Status

_DT = ModbusClientMixin.DATATYPE


class PlcCheckError(LinkError):
    """The server broke the handshake or the register map (message says which register)."""


@dataclass(frozen=True)
class CycleResult:
    """One answered request. ``rejected``: refused (``status`` is then the reject code).

    ``values``: the pose in the vendor convention (empty unless ``status.pose_valid``).
    ``fit_rms``: FIT_RMS as published (-1 = unknown). ``age_ms``: RESULT_AGE_MS at the answer.
    ``cycle_ms``: trigger write to answer seen, on the PLC's clock. ``warnings``: the
    WARNINGS bits (``vgripd.peer.registers.Warnings``) in the read that saw the answer.
    """

    seq: int
    status: Status
    rejected: bool
    job_id: int
    values: tuple[float, ...]
    fit_rms: float
    captured_seen: bool
    age_ms: int
    polls: int
    cycle_ms: float
    warnings: Warnings = Warnings(0)
    count: int = 0  # COUNT: pickable instances of the job
    index: int = 0  # INDEX: the instance shown (0 none, count + 1 past the end)
    pick_id: int = 0
    score: float = -1.0


class MockPlc:
    def __init__(
        self,
        host: str,
        port: int,
        *,
        word_order: WordOrder = "ABCD",
        value_format: ValueFormat = "float32",
        scale: int = 10000,
        unit_id: int = 1,
        poll_s: float = 0.01,
        timeout_s: float = 15.0,
    ) -> None:
        self.client = AsyncModbusTcpClient(host, port=port, timeout=timeout_s, retries=0)
        self.where = f"{host}:{port}"
        self.word_order: Literal["big", "little"] = "big" if word_order == "ABCD" else "little"
        self.value_format = value_format
        self.scale = scale
        self.unit_id = unit_id
        self.poll_s = poll_s
        self.timeout_s = timeout_s
        self.seq = 0
        self.last_job: CycleResult | None = None  # the last acknowledged TRIGGER (or NEXT)

    async def __aenter__(self) -> MockPlc:
        await self.connect()
        return self

    async def __aexit__(self, exc_type: type[BaseException] | None,
                        exc: BaseException | None, tb: TracebackType | None) -> None:
        self.close()

    async def connect(self) -> None:
        if not await self.client.connect():
            raise LinkError(f"mock PLC: cannot connect to {self.where}")

    def close(self) -> None:
        self.client.close()

    async def read(self, address: int = 0, count: int = MAP_SIZE) -> list[int]:
        response = await self.client.read_holding_registers(
            address, count=count, device_id=self.unit_id
        )
        if response.isError():
            raise LinkError(
                f"mock PLC: read of {count} registers at {address} on {self.where} "
                f"refused, exception code {response.exception_code}"
            )
        return list(response.registers)

    async def write(self, address: int, values: list[int]) -> None:
        response = await self.client.write_registers(address, values, device_id=self.unit_id)
        if response.isError():
            raise LinkError(
                f"mock PLC: write at {address} on {self.where} refused, "
                f"exception code {response.exception_code}"
            )

    def _u32(self, words: list[int]) -> int:
        value = self.client.convert_from_registers(words, _DT.UINT32, self.word_order)
        assert isinstance(value, int)
        return value

    def _value(self, words: list[int]) -> float:
        if self.value_format == "float32":
            value = self.client.convert_from_registers(words, _DT.FLOAT32, self.word_order)
            assert isinstance(value, float)
            return value
        raw = self.client.convert_from_registers(words, _DT.INT32, self.word_order)
        assert isinstance(raw, int)
        return raw / self.scale

    async def check_byte_order(self) -> None:
        """Read the check words; raise ``PlcCheckError`` if this PLC's word order is wrong."""
        w = await self.read(Reg.MAP_VERSION, Reg.VALUE_FORMAT - Reg.MAP_VERSION)
        got_u32 = self._u32(w[Reg.CHECK_U32 - 3:Reg.CHECK_U32 - 1])
        got_f32 = self.client.convert_from_registers(
            w[Reg.CHECK_F32 - 3:Reg.CHECK_F32 - 1], _DT.FLOAT32, self.word_order
        )
        assert isinstance(got_f32, float)
        if w[0] not in MAP_VERSIONS or w[1] != CHECK_U16:
            raise PlcCheckError(f"map version/CHECK_U16 read as {w[0]}/{w[1]:#06x}")
        if got_u32 != CHECK_U32 or abs(got_f32 - CHECK_F32) > 1e-4:
            raise PlcCheckError(
                f"word order mismatch: CHECK_U32 = {got_u32:#010x}, CHECK_F32 = {got_f32} "
                f"with {self.word_order}-endian words"
            )

    def next_seq(self) -> int:
        self.seq = self.seq % 0xFFFF + 1  # 1..65535: 0 is never a request
        return self.seq

    async def trigger(self, recipe: int = 0, command: int = Command.TRIGGER) -> int:
        """Write command, sequence and recipe in one request; return the sequence used."""
        seq = self.next_seq()
        await self.write(Reg.CMD, [int(command), seq, recipe])
        return seq

    async def wait_answer(self, seq: int, t0_ns: int | None = None,
                          following: bool = False) -> CycleResult:
        """Poll until ``seq`` is acknowledged or refused; check what was read. ``following``:
        ``seq`` is a NEXT (no image is taken for it: CAPTURED_SEQ does not show it)."""
        t0_ns = time.monotonic_ns() if t0_ns is None else t0_ns
        deadline = time.monotonic() + self.timeout_s
        captured_seen = False
        polls = 0
        while True:
            w = await self.read()
            polls += 1
            captured_seen |= w[Reg.CAPTURED_SEQ] == seq
            if w[Reg.ACK_SEQ] == seq or w[Reg.REJECT_SEQ] == seq:
                break
            if time.monotonic() > deadline:
                raise PlcCheckError(
                    f"request {seq} not answered within {self.timeout_s} s (ACK_SEQ "
                    f"{w[Reg.ACK_SEQ]}, REJECT_SEQ {w[Reg.REJECT_SEQ]}, STATE {w[Reg.STATE]})"
                )
            await asyncio.sleep(self.poll_s)
        cycle_ms = (time.monotonic_ns() - t0_ns) / 1e6
        rejected = w[Reg.ACK_SEQ] != seq
        code = w[Reg.REJECT_CODE] if rejected else w[Reg.STATUS]
        try:
            status = Status(code)
        except ValueError:
            raise PlcCheckError(f"request {seq}: unknown status code {code}") from None
        n = w[Reg.N_VALUES]
        warnings = Warnings(w[Reg.WARNINGS])
        if warnings & ~sum(int(bit) for bit in Warnings):
            raise PlcCheckError(f"request {seq}: WARNINGS {w[Reg.WARNINGS]:#06x} sets a "
                                "reserved bit")
        if rejected:
            return CycleResult(seq, status, True, 0, (), -1.0, captured_seen, 0, polls, cycle_ms,
                               warnings)
        if status.pose_valid != (n > 0) or n not in (0, 6, 7):
            raise PlcCheckError(f"request {seq}: status {status.name} with N_VALUES = {n}")
        if status.pose_valid and not captured_seen and not following:
            raise PlcCheckError(f"request {seq}: pose acknowledged, CAPTURED_SEQ never showed it")
        count, index = w[Reg.COUNT], w[Reg.INDEX]
        if (status.pose_valid and not 1 <= index <= count) or index > count + 1:
            raise PlcCheckError(f"request {seq}: status {status.name} with INDEX {index} of "
                                f"COUNT {count}")
        values = tuple(
            self._value(w[Reg.VALUES + 2 * i:Reg.VALUES + 2 * i + 2]) for i in range(n)
        )
        return CycleResult(
            seq=seq,
            status=status,
            rejected=False,
            job_id=self._u32(w[Reg.JOB_ID:Reg.JOB_ID + 2]),
            values=values,
            fit_rms=self._value(w[Reg.FIT_RMS:Reg.FIT_RMS + 2]),
            captured_seen=captured_seen,
            age_ms=self._u32(w[Reg.RESULT_AGE_MS:Reg.RESULT_AGE_MS + 2]),
            polls=polls,
            cycle_ms=cycle_ms,
            warnings=warnings,
            count=count,
            index=index,
            pick_id=w[Reg.PICK_ID],
            score=self._value(w[Reg.SCORE:Reg.SCORE + 2]),
        )

    async def cycle(self, recipe: int = 0) -> CycleResult:
        """One job: trigger, then wait for the answer."""
        t0_ns = time.monotonic_ns()
        seq = await self.trigger(recipe)
        answer = await self.wait_answer(seq, t0_ns)
        if not answer.rejected:
            self.last_job = answer
        return answer

    async def capture_view(self, view: int, recipe: int = 0) -> CycleResult | None:
        """CAPTURE view ``view`` of a several-view job (docs/registers.md, "Several views per
        job"): write the request, poll until the view is taken or the request answered.

        Returns None when the view is taken (CAPTURED_SEQ shows it with STATE 4 VIEWS and no
        result: the robot moves on to the next view); otherwise the answer, checked as any (the
        last view's result, or the status that ended the job)."""
        seq = self.next_seq()
        t0_ns = time.monotonic_ns()
        await self.write(Reg.CMD, [capture_word(view), seq, recipe])
        deadline = time.monotonic() + self.timeout_s
        while True:
            w = await self.read()
            if w[Reg.ACK_SEQ] == seq or w[Reg.REJECT_SEQ] == seq:
                return await self.wait_answer(seq, t0_ns)
            if w[Reg.CAPTURED_SEQ] == seq and w[Reg.STATE] == HandshakeState.VIEWS:
                if w[Reg.ACK_SEQ] != 0 or w[Reg.N_VALUES] != 0:
                    raise PlcCheckError(f"view {view} (request {seq}): a result (ACK_SEQ "
                                        f"{w[Reg.ACK_SEQ]}, N_VALUES {w[Reg.N_VALUES]}) shows "
                                        "between the views")
                return None
            if time.monotonic() > deadline:
                raise PlcCheckError(f"view {view} (request {seq}) not taken within "
                                    f"{self.timeout_s} s (STATE {w[Reg.STATE]})")
            await asyncio.sleep(self.poll_s)

    async def views_cycle(self, views: int, recipe: int = 0) -> CycleResult:
        """A whole several-view job: CAPTURE views 1..``views`` in order (a real robot moves
        between them); the answer of the request that ended it."""
        for view in range(1, views + 1):
            answer = await self.capture_view(view, recipe)
            if answer is not None:
                if view < views and answer.status.pose_valid:
                    raise PlcCheckError(f"view {view} of {views} answered with a pose")
                self.last_job = answer
                return answer
        raise PlcCheckError(f"the last view ({views}) was taken without an answer")

    async def next(self) -> CycleResult:
        """NEXT: the following instance of the last job's pick list, checked against it (see
        the module docstring). A refusal (BAD_REQUEST without a list, BUSY) is returned as
        such (also the daemon's, acknowledged with job id 0); any other acknowledged answer
        becomes the position the next ``next()`` continues from."""
        t0_ns = time.monotonic_ns()
        seq = await self.trigger(command=Command.NEXT)
        answer = await self.wait_answer(seq, t0_ns, following=True)
        before = self.last_job
        if answer.rejected or before is None or answer.job_id == 0:
            return answer  # refused (by the handshake, or by the daemon: no job, job id 0)
        want = min(before.index + 1, before.count + 1)
        if (answer.job_id, answer.count, answer.index) != (before.job_id, before.count, want):
            raise PlcCheckError(
                f"NEXT {seq}: job {answer.job_id}, INDEX {answer.index} of COUNT {answer.count}"
                f" after job {before.job_id}, INDEX {before.index} of COUNT {before.count} "
                f"(expected INDEX {want} of the same job)")
        if answer.index > answer.count and (answer.status is not Status.NOT_FOUND
                                            or answer.values):
            raise PlcCheckError(f"NEXT {seq}: past the end answered {answer.status.name} with "
                                f"{len(answer.values)} values (expected NOT_FOUND, no pose)")
        if answer.age_ms < before.age_ms:
            raise PlcCheckError(f"NEXT {seq}: RESULT_AGE_MS {answer.age_ms} is younger than "
                                f"the job's {before.age_ms}: not the job's images")
        self.last_job = answer
        return answer
