"""Modbus/TCP server link against real peers: the pymodbus client (through the mock PLC and
directly), raw sockets, and mbpoll (Debian's Modbus master, installed in CI). What a hostile or
broken network does to it (malformed frames, floods, clients that do not read, fuzzing) is in
tests/faults/.

A stand-in daemon drives the link directly (image_captured/publish) so each handshake step is
under the test's control; the end-to-end daemon tests live with the daemon.
"""

from __future__ import annotations

import asyncio
import random
import re
import struct
import time
from collections.abc import AsyncIterator

import pytest
from pymodbus.client import AsyncModbusTcpClient

from drivers.links.modbus_server import ModbusServerLink
from tests.conftest import need_tool
from vgripd.errors import LinkError
from vgripd.peer.jobcore import Command, next_answer
from vgripd.peer.registers import CHECK_F32, MAP_SIZE, BlockWrite, Reg, Warnings
from vgripd.service.links.protocol import LinkState, Trigger
from vgripd.sim.plc import MockPlc, PlcCheckError
from vgripd.types import JobResult, PickInstance, RobotTarget, Status

KUKA = ("X", "Y", "Z", "A", "B", "C")
POSE = (612.5, -98.125, 10.75, 2.5, -0.75, 179.5)  # exactly representable in float32


def ok(job_id: int, values: tuple[float, ...] = POSE) -> JobResult:
    return JobResult(job_id=job_id, status=Status.OK,
                     target=RobotTarget("kuka", KUKA[: len(values)] + ("q",) * (len(values) - 6), values),
                     residuals={"fit_rms_mm": 0.375})


class Harness:
    def __init__(self, link: ModbusServerLink) -> None:
        self.link = link
        self.triggers: asyncio.Queue[Trigger] = asyncio.Queue()

    async def next_trigger(self) -> Trigger:
        return await asyncio.wait_for(self.triggers.get(), 5)


async def open_link(**options: object) -> tuple[ModbusServerLink, Harness]:
    link = ModbusServerLink("plc", ModbusServerLink.Options(host="127.0.0.1", port=0, **options))
    harness = Harness(link)
    await link.open(harness.triggers.put_nowait)
    return link, harness


@pytest.fixture
async def served() -> AsyncIterator[Harness]:
    link, harness = await open_link()
    yield harness
    await link.close()
    assert link.health().state is LinkState.STOPPED


@pytest.mark.parametrize("order", ["ABCD", "CDAB"])
async def test_byte_order_words(order: str) -> None:
    link, _ = await open_link(word_order=order)
    try:
        async with MockPlc("127.0.0.1", link.port, word_order=order) as plc:  # type: ignore[arg-type]
            await plc.check_byte_order()
            w = await plc.read()
            f32 = struct.pack(">f", CHECK_F32)
            hi, lo = int.from_bytes(f32[:2], "big"), int.from_bytes(f32[2:], "big")
            assert w[Reg.CHECK_F32:Reg.CHECK_F32 + 2] == ([hi, lo] if order == "ABCD" else [lo, hi])
        other = "CDAB" if order == "ABCD" else "ABCD"
        async with MockPlc("127.0.0.1", link.port, word_order=other) as wrong:  # type: ignore[arg-type]
            with pytest.raises(LinkError, match="word order mismatch"):
                await wrong.check_byte_order()
    finally:
        await link.close()


async def test_cycle_trigger_capture_publish(served: Harness) -> None:
    link = served.link

    async def daemon() -> None:
        t = await served.next_trigger()
        assert (t.link, t.command, t.recipe) == ("plc", 1, 4)
        await link.image_captured(t.seq, job_id=1001)
        await link.publish(t.seq, ok(1001))

    async with MockPlc("127.0.0.1", link.port, poll_s=0.002) as plc:
        stand_in = asyncio.create_task(daemon())
        result = await plc.cycle(recipe=4)
        await stand_in
    assert (result.seq, result.status, result.rejected, result.job_id) == (1, Status.OK, False, 1001)
    assert result.values == POSE
    assert result.fit_rms == 0.375
    assert result.captured_seen


async def test_int32_scaled_quaternion_cycle() -> None:
    link, harness = await open_link(value_format="int32", scale=10000, word_order="CDAB")
    values = (612.34567, -98.1, 10.0, 0.7071068, 0.0, 0.7071068, 0.0)
    try:
        async with MockPlc("127.0.0.1", link.port, word_order="CDAB", value_format="int32",
                           scale=10000, poll_s=0.002) as plc:
            seq = await plc.trigger()
            t = await harness.next_trigger()
            await link.image_captured(t.seq, 5)
            await link.publish(t.seq, ok(5, values))
            result = await plc.wait_answer(seq)
    finally:
        await link.close()
    assert len(result.values) == 7
    assert result.values == pytest.approx(values, abs=0.5e-4)


async def test_trigger_while_busy_is_refused_and_running_job_completes(served: Harness) -> None:
    link = served.link
    async with MockPlc("127.0.0.1", link.port, poll_s=0.002) as plc:
        first = await plc.trigger()
        t = await served.next_trigger()
        await link.image_captured(t.seq, 77)
        second = await plc.trigger()
        refused = await plc.wait_answer(second)
        assert (refused.rejected, refused.status) == (True, Status.BUSY)
        assert served.triggers.empty()
        w = await plc.read()
        assert (w[Reg.ACK_SEQ], w[Reg.STATE], w[Reg.CAPTURED_SEQ]) == (0, 2, first)
        await link.publish(t.seq, ok(77))
        done = await plc.wait_answer(first)
        assert (done.status, done.job_id, done.values) == (Status.OK, 77, POSE)
        # the refused sequence stays refused: a retry needs a new one
        third = await plc.trigger()
        t3 = await served.next_trigger()
        assert t3.seq == third == 3


async def test_bad_writes_and_reads_get_exception_responses(served: Harness) -> None:
    client = AsyncModbusTcpClient("127.0.0.1", port=served.link.port, retries=0)
    await client.connect()
    try:
        for address, values in [(Reg.ACK_SEQ, [9]), (2, [1, 2]), (MAP_SIZE, [1]), (1000, [1])]:
            r = await client.write_registers(address, values, device_id=1)
            assert (r.isError(), r.exception_code) == (True, 2), (address, values)
        r = await client.write_register(Reg.STATUS, 1, device_id=1)
        assert (r.isError(), r.exception_code) == (True, 2)
        r = await client.read_holding_registers(MAP_SIZE - 1, count=2, device_id=1)
        assert (r.isError(), r.exception_code) == (True, 2)
        r = await client.read_holding_registers(0, count=MAP_SIZE, device_id=1)
        assert r.registers[Reg.ACK_SEQ:Reg.STATUS + 1] == [0, 0]
        r = await client.read_coils(0, count=1, device_id=1)
        assert (r.isError(), r.exception_code) == (True, 1)
        r = await client.read_input_registers(0, count=1, device_id=1)
        assert (r.isError(), r.exception_code) == (True, 1)
        # the command area is writable, one register at a time too
        assert not (await client.write_register(Reg.RECIPE, 3, device_id=1)).isError()
        assert not (await client.write_register(Reg.CMD, 1, device_id=1)).isError()
        assert served.triggers.empty()  # no sequence change yet
        assert not (await client.write_register(Reg.REQ_SEQ, 12, device_id=1)).isError()
        t = await served.next_trigger()
        assert (t.seq, t.command, t.recipe) == (12, 1, 3)
    finally:
        client.close()


async def test_garbage_frames_do_not_stop_the_server(served: Harness) -> None:
    rng = random.Random(4)
    frames = [
        bytes(rng.randrange(256) for _ in range(rng.randrange(1, 64))) for _ in range(20)
    ] + [
        b"\x00\x01\x00\x00\x00\x06\x01\x03\x00\x00",  # truncated request
        b"\x00\x02\x00\x00\xff\xff\x01\x03\x00\x00\x00\x01",  # absurd MBAP length
        b"\x00\x03\x00\x00\x00\x06\x01\x63\x00\x00\x00\x01",  # unknown function 0x63
        b"\x00\x04\x00\x00\x00\x06\x01\x03\x00\x00\x00\x00",  # count 0
        b"\x00\x05\x00\x00\x00\x06\x01\x03\x00\x00\x07\xd0",  # count 2000
        b"\x00\x06\x00\x00\x00\x09\x01\x10\x00\x00\x00\x10\x02\x00\x01",  # bad byte count
    ]
    for frame in frames:
        reader, writer = await asyncio.open_connection("127.0.0.1", served.link.port)
        writer.write(frame)
        await writer.drain()
        writer.close()
        await writer.wait_closed()
        del reader
    async with MockPlc("127.0.0.1", served.link.port) as plc:
        await plc.check_byte_order()
        seq = await plc.trigger()
        t = await served.next_trigger()
        assert t.seq == seq
    assert served.link.health().state is LinkState.UP


async def test_client_disconnect_mid_job_then_result_is_readable(served: Harness) -> None:
    link = served.link
    async with MockPlc("127.0.0.1", link.port) as plc:
        seq = await plc.trigger()
        t = await served.next_trigger()
    await link.image_captured(t.seq, 8)
    await link.publish(t.seq, ok(8))
    async with MockPlc("127.0.0.1", link.port) as again:
        again.seq = seq  # the same PLC program after a reconnect
        result = await again.wait_answer(seq)
    assert (result.status, result.values, result.job_id) == (Status.OK, POSE, 8)


async def test_health_counts_peers_and_heartbeat_runs() -> None:
    link, _ = await open_link(heartbeat_ms=100)
    try:
        assert link.health().peers == 0
        async with MockPlc("127.0.0.1", link.port) as a, MockPlc("127.0.0.1", link.port) as b:
            beats = {(await a.read(Reg.HEARTBEAT, 1))[0]}
            async with asyncio.timeout(5):  # a PLC watches the heartbeat by polling it
                while len(beats) < 3:
                    beats.add((await b.read(Reg.HEARTBEAT, 1))[0])
                    await asyncio.sleep(0.01)
            assert link.health().peers == 2
        health = link.health()
        assert health.state is LinkState.UP
        assert health.peer == f"127.0.0.1:{link.port}"
    finally:
        await link.close()
    assert not [t for t in asyncio.all_tasks() if "heartbeat" in t.get_name()]


async def test_port_in_use_is_a_link_error_naming_address_and_port(served: Harness) -> None:
    busy_port = served.link.port
    other = ModbusServerLink("plc2", ModbusServerLink.Options(host="127.0.0.1", port=busy_port))
    with pytest.raises(LinkError, match=rf"plc2: cannot listen on 127\.0\.0\.1:{busy_port}: "
                       r"Address already in use \(check host and port of this \[\[links\]\] entry\)"):
        await other.open(lambda t: None)
    assert other.health().state is LinkState.FAILED
    await other.close()


# --- mbpoll, a third-party Modbus master --------------------------------------------------



async def mbpoll_run(port: int, *args: str) -> tuple[int | None, str]:
    """Run mbpoll once with 0-based references; return its exit code and stdout + stderr."""
    proc = await asyncio.create_subprocess_exec(
        need_tool("mbpoll"), "-m", "tcp", "-a", "1", "-0", "-1", "-o", "2", "-p", str(port), *args,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
    )
    out, err = await proc.communicate()
    return proc.returncode, out.decode() + err.decode()


async def mbpoll(port: int, *args: str) -> dict[int, str]:
    """Run mbpoll once; return {reference: printed value}."""
    code, text = await mbpoll_run(port, *args)
    assert code == 0, text
    return {int(m[1]): m[2] for m in re.finditer(r"^\[(\d+)\]:\s+(\S+)", text, re.M)}


@pytest.mark.parametrize(("order", "flags"), [("ABCD", ["-B"]), ("CDAB", [])])
async def test_mbpoll_reads_byte_order_words(order: str, flags: list[str]) -> None:
    link, _ = await open_link(word_order=order)
    try:
        u16 = await mbpoll(link.port, "-t", "4:hex", "-r", str(Reg.CHECK_U16), "-c", "1", "127.0.0.1")
        assert u16 == {Reg.CHECK_U16: "0x1234"}
        i32 = await mbpoll(link.port, "-t", "4:int", *flags, "-r", str(Reg.CHECK_U32), "-c", "1", "127.0.0.1")
        assert i32 == {Reg.CHECK_U32: str(0x12345678)}
        f32 = await mbpoll(link.port, "-t", "4:float", *flags, "-r", str(Reg.CHECK_F32), "-c", "1", "127.0.0.1")
        assert float(f32[Reg.CHECK_F32]) == pytest.approx(CHECK_F32, abs=1e-3)
        wrong = await mbpoll(link.port, "-t", "4:float", *(["-B"] if not flags else []), "-r",
                             str(Reg.CHECK_F32), "-c", "1", "127.0.0.1")
        assert float(wrong[Reg.CHECK_F32]) != pytest.approx(CHECK_F32, abs=1)
    finally:
        await link.close()


async def test_mbpoll_triggers_and_reads_published_pose(served: Harness) -> None:
    link = served.link
    await mbpoll(link.port, "-t", "4", "-r", "0", "127.0.0.1", "1", "42", "0")
    t = await served.next_trigger()
    assert t.seq == 42
    await link.image_captured(42, 3)
    await link.publish(42, ok(3))
    head = await mbpoll(link.port, "-t", "4", "-r", str(Reg.ACK_SEQ), "-c", "2", "127.0.0.1")
    assert head == {Reg.ACK_SEQ: "42", Reg.STATUS: str(int(Status.OK))}
    pose = await mbpoll(link.port, "-t", "4:float", "-B", "-r", str(Reg.VALUES), "-c", "6", "127.0.0.1")
    assert [float(pose[Reg.VALUES + 2 * i]) for i in range(6)] == pytest.approx(POSE, abs=1e-3)


async def test_mbpoll_is_served_past_the_connection_cap() -> None:
    """Idle connections beyond max_connections evict the longest-idle ones; a third-party
    master connecting afterwards is served (tests/faults has the rest of the network faults)."""
    link, _ = await open_link(max_connections=2)
    idle = [await asyncio.open_connection("127.0.0.1", link.port) for _ in range(6)]
    try:
        for _ in range(3):
            u16 = await mbpoll(link.port, "-t", "4:hex", "-r", str(Reg.CHECK_U16), "-c", "1",
                               "127.0.0.1")
            assert u16 == {Reg.CHECK_U16: "0x1234"}
        assert link.peers() <= 2
        assert link.faults["evicted"] >= 4
    finally:
        for _, writer in idle:
            writer.close()
        await link.close()


def pose_for(seq: int) -> tuple[float, ...]:
    return tuple(float(seq * 8 + i) for i in range(6))


async def test_concurrent_reader_never_sees_ack_with_other_data(served: Harness) -> None:
    """A second client reads ACK..VALUES continuously while jobs are triggered and published:
    every read with ACK_SEQ = k must carry exactly job k's pose, every read with ACK_SEQ = 0 none."""
    link = served.link
    stop = asyncio.Event()
    seen: dict[int, int] = {}

    async def reader() -> None:
        async with MockPlc("127.0.0.1", link.port) as spy:
            while not stop.is_set():
                w = await spy.read(Reg.ACK_SEQ, Reg.FIT_RMS - Reg.ACK_SEQ)
                ack, n = w[0], w[Reg.N_VALUES - Reg.ACK_SEQ]
                vals = [spy._value(w[i:i + 2]) for i in range(Reg.VALUES - Reg.ACK_SEQ, len(w), 2)]
                if ack == 0:
                    assert (n, vals) == (0, [0.0] * 7)
                else:
                    assert (n, tuple(vals[:6])) == (6, pose_for(ack)), ack
                seen[ack] = seen.get(ack, 0) + 1

    spy_task = asyncio.create_task(reader())
    async with MockPlc("127.0.0.1", link.port, poll_s=0.001) as plc:
        for _ in range(40):
            seq = await plc.trigger()
            t = await served.next_trigger()
            await link.image_captured(t.seq, seq)
            await asyncio.sleep(0)  # let the reader interleave between each step
            await link.publish(t.seq, ok(seq, pose_for(seq)))
            await plc.wait_answer(seq)
    stop.set()
    await spy_task
    assert len(seen) > 10  # the reader did interleave with many jobs


async def test_read_write_multiple_in_one_transaction(served: Harness) -> None:
    """FC23: a PLC writes the command area and reads the status block in one request."""
    client = AsyncModbusTcpClient("127.0.0.1", port=served.link.port, retries=0)
    await client.connect()
    try:
        r = await client.readwrite_registers(
            read_address=Reg.STATE, read_count=5, write_address=Reg.CMD, values=[1, 77, 0], device_id=1
        )
        assert not r.isError()
        assert r.registers[0] == 1  # STATE already TRIGGERED in the same answer
        assert (await served.next_trigger()).seq == 77
        r = await client.readwrite_registers(
            read_address=0, read_count=1, write_address=Reg.STATUS, values=[1], device_id=1
        )
        assert (r.isError(), r.exception_code) == (True, 2)
    finally:
        client.close()


async def test_read_write_multiple_is_all_or_nothing(served: Harness) -> None:
    """FC23 with a valid write (a trigger) and an illegal read: exception 02 and nothing changed.

    pymodbus applies the write before it looks at the read; the link checks both ranges first.
    """
    client = AsyncModbusTcpClient("127.0.0.1", port=served.link.port, retries=0)
    await client.connect()
    try:
        before = (await client.read_holding_registers(0, count=MAP_SIZE, device_id=1)).registers
        for read_address, read_count in [(MAP_SIZE - 2, 5), (MAP_SIZE, 1), (0, MAP_SIZE + 1)]:
            r = await client.readwrite_registers(
                read_address=read_address, read_count=read_count, write_address=Reg.CMD,
                values=[1, 55, 3], device_id=1)
            assert (r.isError(), r.exception_code) == (True, 2), (read_address, read_count)
        after = (await client.read_holding_registers(0, count=MAP_SIZE, device_id=1)).registers
        assert after[Reg.CMD:Reg.RECIPE + 1] == [0, 0, 0]  # the write did not happen
        assert after[Reg.STATE] == before[Reg.STATE] == 0
        assert after[Reg.REJECT_SEQ:Reg.ACK_SEQ + 1] == [0, 0, 0]
        await asyncio.sleep(0.05)  # time passes: a job started by mistake would show here
        assert served.triggers.empty()  # no job was started
        # The same request with a legal read is the trigger, and its read sees it.
        r = await client.readwrite_registers(
            read_address=Reg.REQ_SEQ, read_count=2, write_address=Reg.CMD, values=[1, 55, 3],
            device_id=1)
        assert not r.isError()
        assert r.registers == [55, 3]
        t = await served.next_trigger()
        assert (t.seq, t.recipe) == (55, 3)
    finally:
        client.close()


# --- WARNINGS (register 40, map version 2) ------------------------------------------------

async def test_warnings_word_live_for_pymodbus_and_mbpoll(served: Harness) -> None:
    link = served.link
    client = AsyncModbusTcpClient("127.0.0.1", port=link.port, retries=0)
    await client.connect()

    async def warnings_word() -> int:
        r = await client.read_holding_registers(Reg.WARNINGS, count=1, device_id=1)
        assert not r.isError(), r
        return int(r.registers[0])

    try:
        assert await mbpoll(link.port, "-t", "4", "-r", str(Reg.MAP_VERSION), "-c", "1",
                            "127.0.0.1") == {Reg.MAP_VERSION: "3"}
        assert await warnings_word() == 0
        # the whole map is one read; one register past it is refused
        r = await client.read_holding_registers(0, count=MAP_SIZE, device_id=1)
        assert (len(r.registers), r.registers[Reg.WARNINGS]) == (46, 0)
        r = await client.read_holding_registers(MAP_SIZE, count=1, device_id=1)
        assert (r.isError(), r.exception_code) == (True, 2)
        r = await client.write_register(Reg.WARNINGS, 1, device_id=1)  # read-only
        assert (r.isError(), r.exception_code) == (True, 2)

        await link.set_warnings(Warnings.RECALIBRATE)
        assert await warnings_word() == 1
        assert await mbpoll(link.port, "-t", "4:hex", "-r", str(Reg.WARNINGS), "-c", "1",
                            "127.0.0.1") == {Reg.WARNINGS: "0x0001"}
        code, text = await mbpoll_run(link.port, "-t", "4", "-r", str(MAP_SIZE), "-c",
                                      "1", "127.0.0.1")
        assert code != 0, text
        assert "Illegal data address" in text
        # a job (new request, publish) and a CLEAR leave it alone: it is not a result
        await client.write_registers(Reg.CMD, [1, 5, 0], device_id=1)
        t = await served.next_trigger()
        await link.image_captured(t.seq, 1)
        await link.publish(t.seq, ok(1))
        await client.write_registers(Reg.CMD, [2, 6, 0], device_id=1)
        r = await client.read_holding_registers(Reg.ACK_SEQ, count=MAP_SIZE - Reg.ACK_SEQ,
                                                device_id=1)
        assert (r.registers[0], r.registers[Reg.WARNINGS - Reg.ACK_SEQ]) == (6, 1)

        await link.set_warnings(0)
        assert await warnings_word() == 0
        with pytest.raises(LinkError, match="only bits 0x1"):
            await link.set_warnings(2)
        assert await warnings_word() == 0
    finally:
        client.close()


async def test_mock_plc_reports_warnings_and_refuses_reserved_bits(served: Harness) -> None:
    link = served.link

    async def answer(job_id: int) -> None:
        t = await served.next_trigger()
        await link.image_captured(t.seq, job_id)
        await link.publish(t.seq, ok(job_id))

    async with MockPlc("127.0.0.1", link.port, poll_s=0.002) as plc:
        stand_in = asyncio.create_task(answer(1))
        assert (await plc.cycle()).warnings == 0
        await stand_in
        await link.set_warnings(Warnings.RECALIBRATE)
        stand_in = asyncio.create_task(answer(2))
        assert (await plc.cycle()).warnings is Warnings.RECALIBRATE
        await stand_in
        # a server that broke the contract (vgripd's own bank refuses this) is caught
        link.bank.image.apply([BlockWrite(Reg.WARNINGS, (0x0003,))])
        stand_in = asyncio.create_task(answer(3))
        with pytest.raises(PlcCheckError, match="WARNINGS 0x0003 sets a reserved bit"):
            await plc.cycle()
        await stand_in


# --- pick lists (registers 41-45, Command.NEXT, map version 3) ----------------------------


def pallet(job_id: int, n: int) -> JobResult:
    """``n`` pickable instances (X = 100, 200, ... mm; pick ids 5, 6, ...; scores 0.9, 0.8,
    ...), the first one on top."""
    instances = tuple(PickInstance(Status.OK, target=RobotTarget(
        "kuka", KUKA, (100.0 * (i + 1), *POSE[1:])), pick_id=5 + i, score=0.9 - 0.1 * i,
        residuals={"fit_rms_mm": 0.25}) for i in range(n))
    return JobResult(job_id=job_id, status=Status.OK, target=instances[0].target,
                     residuals=instances[0].residuals, instances=instances,
                     t_done_mono_ns=time.monotonic_ns())


async def test_mbpoll_walks_a_pick_list_with_next(served: Harness) -> None:
    """The integrator's session of docs/registers.md: trigger, read COUNT/INDEX and the pose,
    then NEXT (CMD 3) with new sequences until INDEX = COUNT + 1, all with mbpoll."""
    link = served.link
    job = pallet(9, 2)

    async def read_pick() -> dict[int, str]:
        return await mbpoll(link.port, "-t", "4", "-r", str(Reg.COUNT), "-c", "3", "127.0.0.1")

    await mbpoll(link.port, "-t", "4", "-r", "0", "127.0.0.1", "1", "10", "0")
    t = await served.next_trigger()
    await link.image_captured(t.seq, 9)
    await link.publish(t.seq, job)
    assert await read_pick() == {Reg.COUNT: "2", Reg.INDEX: "1", Reg.PICK_ID: "5"}
    score = await mbpoll(link.port, "-t", "4:float", "-B", "-r", str(Reg.SCORE), "-c", "1",
                         "127.0.0.1")
    assert float(score[Reg.SCORE]) == pytest.approx(0.9, abs=1e-6)
    for seq, index in ((11, 2), (12, 3)):
        await mbpoll(link.port, "-t", "4", "-r", "0", "127.0.0.1", "3", str(seq), "0")
        t = await served.next_trigger()
        assert (t.seq, t.command) == (seq, Command.NEXT)
        await link.publish(seq, next_answer(job, index))
        head = await mbpoll(link.port, "-t", "4", "-r", str(Reg.ACK_SEQ), "-c", "2",
                            "127.0.0.1")
        job_id = await mbpoll(link.port, "-t", "4:int", "-B", "-r", str(Reg.JOB_ID), "-c", "1",
                              "127.0.0.1")
        x = await mbpoll(link.port, "-t", "4:float", "-B", "-r", str(Reg.VALUES), "-c", "1",
                         "127.0.0.1")
        pick = await read_pick()
        assert (head[Reg.ACK_SEQ], job_id[Reg.JOB_ID], pick[Reg.COUNT], pick[Reg.INDEX]) == (
            str(seq), "9", "2", str(index))
        if index == 2:
            assert head[Reg.STATUS] == str(int(Status.OK))
            assert float(x[Reg.VALUES]) == pytest.approx(200.0)
            assert pick[Reg.PICK_ID] == "6"
        else:  # past the end: NOT_FOUND, no pose
            assert head[Reg.STATUS] == str(int(Status.NOT_FOUND))
            assert float(x[Reg.VALUES]) == 0.0
            assert pick[Reg.PICK_ID] == "0"
    # CLEAR, then NEXT: refused BAD_REQUEST by the handshake, no trigger for the daemon
    await mbpoll(link.port, "-t", "4", "-r", "0", "127.0.0.1", "2", "13", "0")
    await mbpoll(link.port, "-t", "4", "-r", "0", "127.0.0.1", "3", "14", "0")
    refused = await mbpoll(link.port, "-t", "4", "-r", str(Reg.REJECT_SEQ), "-c", "3",
                           "127.0.0.1")
    assert refused == {Reg.REJECT_SEQ: "14", Reg.REJECT_CODE: str(int(Status.BAD_REQUEST)),
                       Reg.ACK_SEQ: "13"}
    assert served.triggers.empty()


async def test_mock_plc_next_checks_the_walk(served: Harness) -> None:
    link = served.link
    job = pallet(4, 3)

    async def answer(result_for: dict[int, JobResult]) -> None:
        while True:
            t = await served.next_trigger()
            if t.command == Command.TRIGGER:
                await link.image_captured(t.seq, 4)
                await link.publish(t.seq, job)
            else:
                await link.publish(t.seq, result_for[t.seq])

    async with MockPlc("127.0.0.1", link.port, poll_s=0.002) as plc:
        await plc.check_byte_order()  # MAP_VERSION 3
        first_next = plc.seq + 2
        answers = {first_next: next_answer(job, 2), first_next + 1: next_answer(job, 3),
                   first_next + 2: next_answer(job, 4),
                   first_next + 3: next_answer(job, 2)}  # a broken server: goes backwards
        stand_in = asyncio.create_task(answer(answers))
        try:
            got = await plc.cycle()
            assert (got.count, got.index, got.pick_id, got.values[0]) == (3, 1, 5, 100.0)
            assert got.score == pytest.approx(0.9)
            walked = [await plc.next() for _ in range(3)]
            assert [(a.status, a.index, a.job_id) for a in walked] == [
                (Status.OK, 2, 4), (Status.OK, 3, 4), (Status.NOT_FOUND, 4, 4)]
            assert [a.values[0] if a.values else None for a in walked] == [200.0, 300.0, None]
            with pytest.raises(PlcCheckError, match="expected INDEX 4 of the same job"):
                await plc.next()
        finally:
            stand_in.cancel()
