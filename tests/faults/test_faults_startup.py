"""Start-up with a UR controller that accepts TCP and never answers (listed first): the camera
and the links open at once, so the PLC's Modbus server and the status endpoint answer while the UR
link is still waiting for its controller; READY follows when
every link has reported its first outcome (the UR link: DOWN after its connect_timeout_s)."""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from pymodbus.client import AsyncModbusTcpClient

from tests.conftest import lo, stop_task
from vgripd.config import config_from_dict
from vgripd.peer.registers import CHECK_U16, MAP_SIZE, Reg
from vgripd.service.daemon import Daemon, RunState
from vgripd.service.links.protocol import LinkState

pytestmark = pytest.mark.timeout(120)
SILENT_HOST = lo("127.0.8.1")
CONNECT_TIMEOUT_S = 8.0  # seconds a loaded machine may take to open the PLC link


@pytest.fixture
async def silent_controller() -> AsyncIterator[str]:
    """A TCP listener on SILENT_HOST:30004 that accepts and never sends a byte."""
    held: list[asyncio.StreamWriter] = []

    async def hold(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        held.append(writer)

    server = await asyncio.start_server(hold, SILENT_HOST, 30004)
    try:
        yield SILENT_HOST
    finally:
        server.close()
        for writer in held:
            writer.close()
        await server.wait_closed()


async def read_map(port: int) -> list[int] | None:
    client = AsyncModbusTcpClient("127.0.0.1", port=port, timeout=0.5, retries=0,
                                  reconnect_delay=0)
    try:
        if not await client.connect():
            return None
        rr = await client.read_holding_registers(0, count=MAP_SIZE)
        return None if rr.isError() else list(rr.registers)
    finally:
        client.close()


async def get_status(port: int) -> dict[str, object]:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        writer.write(b"GET /status HTTP/1.0\r\nHost: localhost\r\n\r\n")
        await writer.drain()
        raw = await reader.read()
    finally:
        writer.close()
    body = raw.split(b"\r\n\r\n", 1)[1]
    status: dict[str, object] = json.loads(body)
    return status


async def test_silent_ur_controller_delays_neither_the_plc_nor_the_status(
        silent_controller: str, tmp_path: Path) -> None:
    config = config_from_dict({
        "camera": {"type": "synthetic", "seed": 11, "max_tilt_deg": 2.0},
        "output": {"vendor": "ur"},
        "links": [{"type": "ur_rtde", "host": silent_controller,
                   "connect_timeout_s": CONNECT_TIMEOUT_S},
                  {"type": "modbus_server", "host": "127.0.0.1", "port": 0}],
        "status": {"port": 0},
    })
    daemon = Daemon(config)
    ur, plc = daemon.rooms.links.links.values()
    t0 = time.monotonic()
    starting = asyncio.create_task(daemon.start())
    try:
        words = None
        status: dict[str, object] = {}
        ur_waiting = []  # the UR link's state each time the PLC or the status answered
        while not starting.done() and (words is None or not status):
            if words is None and plc.health().state is LinkState.UP:
                words = await read_map(plc.port)  # type: ignore[attr-defined]
                ur_waiting.append(ur.health().state)
            server = daemon.status_server
            if not status and server is not None:
                try:
                    port = server.port
                except RuntimeError:  # not listening yet
                    port = 0
                if port:
                    status = await get_status(port)
                    ur_waiting.append(ur.health().state)
            await asyncio.sleep(0.01)  # a poller's period
        # both answered while the UR link still waited for its controller (no time bound:
        # a busy machine may take seconds to start, but never waits for the silent peer)
        assert words is not None, time.monotonic() - t0
        assert status, time.monotonic() - t0
        assert ur_waiting[-1] is LinkState.CONNECTING, ur_waiting
        assert words[Reg.CHECK_U16] == CHECK_U16
        assert status["run_state"] == "starting"
        assert not starting.done()  # READY waits for the UR link's first outcome
        assert daemon.run_state is RunState.STARTING

        await starting
        ready_s = time.monotonic() - t0
        assert CONNECT_TIMEOUT_S <= ready_s < CONNECT_TIMEOUT_S + 10
        assert daemon.run_state is RunState.RUNNING
        # the first attempt's outcome, or (a machine so busy that the attempt overran the
        # wait that open() gives it: connect_timeout_s + 5 s) the outcome that follows
        health = await ur.wait_state(LinkState.DOWN, timeout_s=60)
        assert f"did not complete the RTDE setup within {CONNECT_TIMEOUT_S} s" in health.last_error
    finally:
        if not starting.done():
            await stop_task(starting)
        await daemon.stop()
