"""Raw Modbus/TCP for the fault tests: frames built and parsed by hand (no client library
between the test and the wire), and a link opened on a free loopback port."""

from __future__ import annotations

import asyncio
import contextlib
import struct

from drivers.links.modbus_server import ModbusServerLink
from vgripd.service.links.protocol import Trigger

WAIT_S = 5.0


def mbap(tid: int, pdu: bytes, unit: int = 1, protocol: int = 0,
         length: int | None = None) -> bytes:
    """One Modbus/TCP frame; ``length`` overrides the MBAP length field (malformed frames)."""
    return struct.pack(">HHHB", tid, protocol, len(pdu) + 1 if length is None else length,
                       unit) + pdu


def read_request(tid: int, address: int, count: int, unit: int = 1) -> bytes:
    return mbap(tid, struct.pack(">BHH", 3, address, count), unit)


async def recv_frame(reader: asyncio.StreamReader) -> tuple[int, int, bytes]:
    """The next answer: (transaction id, unit id, PDU). The MBAP header is checked."""
    async with asyncio.timeout(WAIT_S):
        head = await reader.readexactly(7)
        tid, protocol, length, unit = struct.unpack(">HHHB", head)
        assert protocol == 0, head
        assert 2 <= length <= 254, head
        return tid, unit, await reader.readexactly(length - 1)


async def closed_by_server(reader: asyncio.StreamReader, within_s: float = WAIT_S) -> bool:
    """True when the server closes (EOF or reset) within ``within_s``; answers still queued
    before the close are skipped."""
    try:
        async with asyncio.timeout(within_s):
            while await reader.read(4096):
                pass
    except TimeoutError:
        return False
    except ConnectionError:
        pass
    return True


async def silent(reader: asyncio.StreamReader, for_s: float = 0.3) -> bool:
    """True when nothing arrives for ``for_s`` (and the connection stays open)."""
    try:
        async with asyncio.timeout(for_s):
            data = await reader.read(1)
    except TimeoutError:
        return True
    assert data, "connection closed"
    return False


async def close_quietly(writer: asyncio.StreamWriter) -> None:
    writer.close()
    with contextlib.suppress(ConnectionError, TimeoutError):
        async with asyncio.timeout(WAIT_S):
            await writer.wait_closed()


class Served:
    """A ``ModbusServerLink`` on 127.0.0.1 (free port) and the triggers it hands out."""

    def __init__(self, link: ModbusServerLink) -> None:
        self.link = link
        self.triggers: asyncio.Queue[Trigger] = asyncio.Queue()

    @classmethod
    async def open(cls, **options: object) -> Served:
        link = ModbusServerLink("plc", ModbusServerLink.Options.model_validate(
            {"host": "127.0.0.1", "port": 0, **options}))
        served = cls(link)
        await link.open(served.triggers.put_nowait)
        return served

    async def connect(self) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        return await asyncio.open_connection("127.0.0.1", self.link.port)

    async def until(self, predicate: object, within_s: float = WAIT_S) -> None:
        assert callable(predicate)
        async with asyncio.timeout(within_s):
            while True:  # polled: the link's state has no event to wait on
                if predicate():
                    return
                await asyncio.sleep(0.01)
