"""The Modbus/TCP server link's encoder count for ``conveyor.trigger = "travel"``: a real
pymodbus client (the PLC) writes LATCH_COUNT, the link hands each whole count to the handler
the daemon set (``RobotLink.watch_count``) at once, with the time of the write."""

from __future__ import annotations

import struct
import time

import pytest
from pymodbus.client import AsyncModbusTcpClient

from drivers.links.modbus_server import ModbusServerLink
from vgripd.peer.registers import Reg

pytestmark = pytest.mark.timeout(120)


def words(count: int) -> list[int]:
    return list(struct.unpack(">2H", struct.pack(">I", count)))


async def test_each_whole_count_the_plc_writes_reaches_the_handler_at_once() -> None:
    link = ModbusServerLink("plc", ModbusServerLink.Options(host="127.0.0.1", port=0,
                                                            map_version=4))
    got: list[tuple[int, int]] = []
    link.watch_count(lambda count, t_ns: got.append((count, t_ns)))
    await link.open(lambda trigger: None)
    client = AsyncModbusTcpClient("127.0.0.1", port=link.port, timeout=5, retries=0)
    try:
        assert await client.connect()
        counts = [(1 << 32) - 2, (1 << 32) - 2, 3, 150_000]
        for count in counts:
            before = time.monotonic_ns()
            rr = await client.write_registers(Reg.LATCH_COUNT, words(count))
            assert not rr.isError(), rr
            assert got[-1][0] == count  # handed over within the write's answer
            assert got[-1][1] >= before
        # LATCH_COUNT and LATCH_FRAME in one write: the count is in it
        rr = await client.write_registers(Reg.LATCH_COUNT, [*words(42), 0, 7])
        assert not rr.isError(), rr
        assert got[-1][0] == 42
        # half a count (one word, FC6) is no count; nor is LATCH_FRAME alone
        n = len(got)
        rr = await client.write_register(Reg.LATCH_COUNT + 1, 9)
        assert not rr.isError(), rr
        rr = await client.write_registers(Reg.LATCH_FRAME, [0, 8])
        assert not rr.isError(), rr
        assert len(got) == n
        link.watch_count(None)  # stopped: nothing more
        rr = await client.write_registers(Reg.LATCH_COUNT, words(5))
        assert not rr.isError(), rr
        assert len(got) == n
    finally:
        client.close()
        await link.close()
    assert [c for c, _ in got] == [*counts, 42]


async def test_a_version_3_map_has_no_count_to_hand() -> None:
    link = ModbusServerLink("plc", ModbusServerLink.Options(host="127.0.0.1", port=0))
    got: list[int] = []
    link.watch_count(lambda count, t_ns: got.append(count))
    await link.open(lambda trigger: None)
    client = AsyncModbusTcpClient("127.0.0.1", port=link.port, timeout=5, retries=0)
    try:
        assert await client.connect()
        rr = await client.write_registers(Reg.LATCH_COUNT, words(5))
        assert rr.isError()  # exception 02: no such register in map version 3
    finally:
        client.close()
        await link.close()
    assert got == []
