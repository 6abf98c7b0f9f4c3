"""Modbus RTU server link over a pty pair made by socat: our server on one end, the pymodbus
serial client (and mbpoll in RTU mode) on the other.

Linux ptys refuse parity settings (tcsetattr EINVAL), so the line runs 8N1 here.
"""

from __future__ import annotations

import asyncio
import subprocess
import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import pytest
from pymodbus.client import AsyncModbusSerialClient
from pymodbus.exceptions import ModbusIOException

from drivers.links.modbus_rtu import ModbusRtuLink
from tests.conftest import need_tool
from vgripd.errors import LinkError
from vgripd.peer.jobcore import Command, HandshakeState, capture_word, next_answer
from vgripd.peer.registers import CHECK_F32, MAP_SIZE, MAP_VERSIONS, Reg, Warnings
from vgripd.service.links.protocol import LinkState, Trigger
from vgripd.types import JobResult, PickInstance, RobotTarget, Status

BAUD = 115200
POSE = (612.5, -98.125, 10.75, 2.5, -0.75, 179.5)


@pytest.fixture
def pty_pair(tmp_path: Path) -> Iterator[tuple[Path, Path]]:
    a, b = tmp_path / "a", tmp_path / "b"
    proc = subprocess.Popen(
        [need_tool("socat"), f"pty,raw,echo=0,link={a}", f"pty,raw,echo=0,link={b}"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 5
        while not (a.exists() and b.exists()):
            assert proc.poll() is None, "socat exited"
            assert time.monotonic() < deadline, "socat did not create the pty links"
            time.sleep(0.01)
        yield a, b
    finally:
        proc.terminate()
        proc.wait(5)


@pytest.fixture
async def rtu(pty_pair: tuple[Path, Path]) -> AsyncIterator[tuple[ModbusRtuLink, asyncio.Queue[Trigger], AsyncModbusSerialClient]]:
    server_end, client_end = pty_pair
    link = ModbusRtuLink("rtu", ModbusRtuLink.Options(port=str(server_end), baudrate=BAUD,
                                                      parity="N", unit_id=7))
    triggers: asyncio.Queue[Trigger] = asyncio.Queue()
    await link.open(triggers.put_nowait)
    client = AsyncModbusSerialClient(str(client_end), baudrate=BAUD, parity="N", timeout=0.5, retries=0)
    assert await client.connect()
    yield link, triggers, client
    client.close()
    await link.close()
    assert link.health().state is LinkState.STOPPED


async def test_rtu_cycle(rtu: tuple[ModbusRtuLink, asyncio.Queue[Trigger], AsyncModbusSerialClient]) -> None:
    link, triggers, client = rtu
    r = await client.read_holding_registers(0, count=MAP_SIZE, device_id=7)
    assert r.registers[Reg.CHECK_U16] == 0x1234
    assert client.convert_from_registers(r.registers[Reg.CHECK_F32:Reg.CHECK_F32 + 2],
                                         client.DATATYPE.FLOAT32) == pytest.approx(CHECK_F32, abs=1e-4)
    assert not (await client.write_registers(Reg.CMD, [1, 300, 2], device_id=7)).isError()
    t = await asyncio.wait_for(triggers.get(), 5)
    assert (t.link, t.seq, t.recipe) == ("rtu", 300, 2)
    await link.image_captured(300, 9)
    await link.publish(300, JobResult(job_id=9, status=Status.OK,
                                      target=RobotTarget("kuka", tuple("XYZABC"), POSE)))
    r = await client.read_holding_registers(0, count=MAP_SIZE, device_id=7)
    w = r.registers
    assert (w[Reg.ACK_SEQ], w[Reg.STATUS], w[Reg.N_VALUES], w[Reg.CAPTURED_SEQ]) == (300, 1, 6, 300)
    got = client.convert_from_registers(w[Reg.VALUES:Reg.VALUES + 12], client.DATATYPE.FLOAT32)
    assert got == list(POSE)


async def test_rtu_warnings_word(rtu: tuple[ModbusRtuLink, asyncio.Queue[Trigger], AsyncModbusSerialClient]) -> None:
    link, _, client = rtu
    r = await client.read_holding_registers(0, count=MAP_SIZE, device_id=7)
    assert (r.registers[Reg.MAP_VERSION], r.registers[Reg.WARNINGS]) == (MAP_VERSIONS[0], 0)
    await link.set_warnings(Warnings.RECALIBRATE)
    r = await client.read_holding_registers(Reg.WARNINGS, count=1, device_id=7)
    assert r.registers == [1]
    r = await client.read_holding_registers(Reg.SCORE, count=3, device_id=7)  # past the map
    assert (r.isError(), r.exception_code) == (True, 2)
    await link.set_warnings(0)
    r = await client.read_holding_registers(Reg.WARNINGS, count=1, device_id=7)
    assert r.registers == [0]


async def test_rtu_other_unit_is_not_answered(rtu: tuple[ModbusRtuLink, asyncio.Queue[Trigger], AsyncModbusSerialClient]) -> None:
    _, triggers, client = rtu
    with pytest.raises(ModbusIOException):
        await client.write_registers(Reg.CMD, [1, 5, 0], device_id=8)
    assert triggers.empty()
    r = await client.write_registers(Reg.ACK_SEQ, [5], device_id=7)
    assert (r.isError(), r.exception_code) == (True, 2)
    r = await client.read_holding_registers(Reg.HEARTBEAT, count=1, device_id=7)
    assert not r.isError()


async def test_mbpoll_rtu_reads_check_words(pty_pair: tuple[Path, Path]) -> None:
    server_end, client_end = pty_pair
    link = ModbusRtuLink("rtu", ModbusRtuLink.Options(port=str(server_end), baudrate=BAUD,
                                                      parity="N", word_order="CDAB"))
    await link.open(lambda t: None)
    try:
        proc = await asyncio.create_subprocess_exec(
            need_tool("mbpoll"), "-m", "rtu", "-b", str(BAUD), "-P", "none",
            "-a", "1", "-0", "-1", "-o", "2", "-t", "4:float", "-r", str(Reg.CHECK_F32),
            "-c", "1", str(client_end),
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
        )
        out, err = await proc.communicate()
    finally:
        await link.close()
    assert proc.returncode == 0, (out, err)
    line = next(ln for ln in out.decode().splitlines() if ln.startswith(f"[{Reg.CHECK_F32}]"))
    assert float(line.split()[-1]) == pytest.approx(CHECK_F32, abs=1e-3)  # mbpoll default: CDAB


async def test_missing_serial_port_is_down_and_retried(tmp_path: Path) -> None:
    """A USB adapter may be plugged in after vgripd started: DOWN with the reason, not FAILED."""
    link = ModbusRtuLink("rtu", ModbusRtuLink.Options(port=str(tmp_path / "ttyNONE")))
    await link.open(lambda t: None)
    try:
        health = link.health()
        assert health.state is LinkState.DOWN
        assert health.last_error == (f"cannot open serial port {tmp_path / 'ttyNONE'} "
                                     "(19200 8E1, unit 1): [Errno 2] No such file or directory")
    finally:
        await link.close()
    assert link.health().state is LinkState.STOPPED


async def test_a_port_that_is_not_a_tty_is_a_config_error(tmp_path: Path) -> None:
    not_a_tty = tmp_path / "ttyFILE"
    not_a_tty.write_text("")
    link = ModbusRtuLink("rtu", ModbusRtuLink.Options(port=str(not_a_tty)))
    with pytest.raises(LinkError, match=r"^link rtu: .*ttyFILE is not a serial port: "
                                        r"Could not configure port: \(25, 'Inappropriate ioctl"):
        await link.open(lambda t: None)
    assert link.health().state is LinkState.FAILED
    await link.close()


async def test_rtu_next_walks_a_pick_list(rtu: tuple[ModbusRtuLink, asyncio.Queue[Trigger], AsyncModbusSerialClient]) -> None:
    link, triggers, client = rtu
    instances = tuple(PickInstance(Status.OK, target=RobotTarget(
        "kuka", tuple("XYZABC"), (100.0 * (i + 1), *POSE[1:])), pick_id=3, score=0.5)
        for i in range(2))
    job = JobResult(job_id=9, status=Status.OK, target=instances[0].target, instances=instances)
    assert not (await client.write_registers(Reg.CMD, [Command.NEXT, 1, 0], device_id=7)).isError()
    r = await client.read_holding_registers(Reg.REJECT_SEQ, count=2, device_id=7)
    assert r.registers == [1, Status.BAD_REQUEST]  # no list yet: refused by the handshake
    assert not (await client.write_registers(Reg.CMD, [Command.TRIGGER, 2, 0], device_id=7)).isError()
    t = await asyncio.wait_for(triggers.get(), 5)
    await link.image_captured(t.seq, 9)
    await link.publish(t.seq, job)
    for seq, index, status in ((3, 2, Status.OK), (4, 3, Status.NOT_FOUND)):
        assert not (await client.write_registers(Reg.CMD, [Command.NEXT, seq, 0], device_id=7)).isError()
        t = await asyncio.wait_for(triggers.get(), 5)
        assert (t.seq, t.command) == (seq, Command.NEXT)
        await link.publish(seq, next_answer(job, index))
        w = (await client.read_holding_registers(0, count=MAP_SIZE, device_id=7)).registers
        assert (w[Reg.ACK_SEQ], w[Reg.STATUS], w[Reg.COUNT], w[Reg.INDEX]) == (
            seq, status, 2, index)
        x = client.convert_from_registers(w[Reg.VALUES:Reg.VALUES + 2], client.DATATYPE.FLOAT32)
        assert x == (200.0 if index == 2 else 0.0)


async def test_rtu_views_of_one_job(rtu: tuple[ModbusRtuLink, asyncio.Queue[Trigger], AsyncModbusSerialClient]) -> None:
    """CAPTURE (view * 256 + 4) over the serial line: a view before the last is answered by
    CAPTURED_SEQ and STATE 4 without a result; the last view gets the job's result."""
    link, triggers, client = rtu
    assert not (await client.write_registers(Reg.CMD, [capture_word(1), 400, 0],
                                             device_id=7)).isError()
    t = await asyncio.wait_for(triggers.get(), 5)
    assert (t.seq, t.command, t.view) == (400, Command.CAPTURE, 1)
    await link.view_captured(400, 12)
    w = (await client.read_holding_registers(0, count=MAP_SIZE, device_id=7)).registers
    assert (w[Reg.CAPTURED_SEQ], w[Reg.STATE], w[Reg.ACK_SEQ], w[Reg.N_VALUES]) == (
        400, HandshakeState.VIEWS, 0, 0)
    assert not (await client.write_registers(Reg.CMD, [capture_word(2), 401, 0],
                                             device_id=7)).isError()
    t = await asyncio.wait_for(triggers.get(), 5)
    assert (t.seq, t.command, t.view) == (401, Command.CAPTURE, 2)
    await link.image_captured(401, 12)
    await link.publish(401, JobResult(job_id=12, status=Status.OK,
                                      target=RobotTarget("kuka", tuple("XYZABC"), POSE)))
    w = (await client.read_holding_registers(0, count=MAP_SIZE, device_id=7)).registers
    assert (w[Reg.ACK_SEQ], w[Reg.STATUS], w[Reg.N_VALUES]) == (401, Status.OK, 6)
