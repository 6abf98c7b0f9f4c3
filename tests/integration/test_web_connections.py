"""The web view's connections against raw sockets on loopback: partial
headers and silent connections are closed by ``header_timeout_s``, a slow body by
``body_timeout_s``, the cap evicts connections that never sent a request and never the live
event stream, and ``allow`` closes other addresses at accept. The daemon-process flood (file
limit, a PLC job during it) is tests/faults/test_daemon_network_faults.py."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import socket
from typing import Any

import aiohttp
import pytest

from tests.integration.test_daemon import Plc, Run, make_config, running
from vgripd.peer.registers import Reg
from vgripd.types import Status

WAIT_S = 30.0


def _config(**status: Any) -> Any:
    return make_config(status={"port": 0, **status}, daemon={"worker": False})


def _port(run: Run) -> int:
    assert run.daemon.status_server is not None
    return run.daemon.status_server.port


async def _connect(port: int, source: str = "127.0.0.1") -> tuple[
        asyncio.StreamReader, asyncio.StreamWriter]:
    sock = socket.socket()
    sock.bind((source, 0))
    sock.setblocking(False)
    await asyncio.get_running_loop().sock_connect(sock, ("127.0.0.1", port))
    return await asyncio.open_connection(sock=sock)


async def _closed_by_server(reader: asyncio.StreamReader) -> bytes:
    """Everything the server sent before it closed the connection (a timeout fails)."""
    got = b""
    with contextlib.suppress(ConnectionError):
        async with asyncio.timeout(WAIT_S):
            while chunk := await reader.read(4096):
                got += chunk
    return got


async def _get(port: int, path: str = "/api/status", source: str = "127.0.0.1") -> bytes:
    reader, writer = await _connect(port, source)
    writer.write(f"GET {path} HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n".encode())
    answer = await _closed_by_server(reader)
    writer.close()
    return answer


async def test_partial_headers_and_silent_connections_are_closed_by_the_header_timeout(
        caplog: pytest.LogCaptureFixture) -> None:
    """Today: 1,000 idle and 1,000 slow-loris connections were all still open after 90 s."""
    caplog.set_level(logging.INFO)
    async with running(_config(header_timeout_s=1.0, max_connections=64)) as run:
        port = _port(run)
        conns = [await _connect(port) for _ in range(40)]
        for i, (_, writer) in enumerate(conns):
            if i % 2:  # half of them send a request line and part of a header, then stall
                writer.write(b"GET /api/status HTTP/1.1\r\nHost: 127.0.0.1\r\nX-slow: ")
        answers = await asyncio.gather(*(_closed_by_server(r) for r, _ in conns))
        assert answers == [b""] * 40  # closed without an answer
        guard = run.daemon.status_server.guard  # type: ignore[union-attr]
        assert guard.gate.faults["slow_header"] == 20
        assert guard.gate.faults["idle"] == 20
        assert (await _get(port)).startswith(b"HTTP/1.0 200")
        assert len([r for r in caplog.records if "header_timeout_s" in r.getMessage()]) <= 2
        for _, writer in conns:
            writer.close()


async def test_a_keep_alive_connection_serves_requests_and_then_times_out() -> None:
    async with running(_config(header_timeout_s=1.0)) as run:
        reader, writer = await _connect(_port(run))
        for _ in range(3):
            writer.write(b"GET /api/status HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), WAIT_S)
            assert head.startswith(b"HTTP/1.1 200")
            length = int(next(line.split(b":")[1] for line in head.split(b"\r\n")
                              if line.lower().startswith(b"content-length")))
            json.loads(await reader.readexactly(length))
        assert await _closed_by_server(reader) == b""
        writer.close()


async def test_a_slow_body_is_closed_by_the_body_timeout() -> None:
    async with running(_config(body_timeout_s=1.0, header_timeout_s=30.0)) as run:
        reader, writer = await _connect(_port(run))
        writer.write(b"POST /status HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 100\r\n\r\n"
                     b"0123456789")
        await _closed_by_server(reader)
        guard = run.daemon.status_server.guard  # type: ignore[union-attr]
        assert guard.gate.faults["slow_body"] == 1
        writer.close()


async def test_the_cap_evicts_never_valid_connections_and_keeps_the_live_view() -> None:
    """A flood of connections that never send a request evicts only itself: the operator's
    live event stream (a request in flight) keeps receiving, and new requests are served."""
    async with running(_config(max_connections=4, header_timeout_s=60.0)) as run, \
            Plc(run.port()) as plc, aiohttp.ClientSession() as http:
        port = _port(run)
        async with http.get(f"http://127.0.0.1:{port}/api/events") as stream:
            assert stream.status == 200
            flood = [await _connect(port) for _ in range(60)]
            guard = run.daemon.status_server.guard  # type: ignore[union-attr]
            await run.daemon.wait_for(lambda: guard.gate.faults["evicted"] >= 50, WAIT_S)
            assert len(guard.gate) <= 4
            assert (await _get(port)).startswith(b"HTTP/1.0 200")
            await plc.trigger(1)
            assert (await plc.result(1))[Reg.STATUS] == Status.OK
            async with asyncio.timeout(WAIT_S):  # the stream still delivers
                async for raw in stream.content:
                    if raw.startswith(b"event: job"):
                        break
            for _, writer in flood:
                writer.close()


async def test_allow_list_closes_other_addresses_at_accept(
        caplog: pytest.LogCaptureFixture) -> None:
    async with running(_config(allow=["127.0.0.1"])) as run:
        port = _port(run)
        for _ in range(5):
            assert await _get(port, source="127.0.0.2") == b""
        assert (await _get(port)).startswith(b"HTTP/1.0 200")
        guard = run.daemon.status_server.guard  # type: ignore[union-attr]
        assert guard.gate.faults["not_allowed"] == 5
        assert len([r for r in caplog.records if "not in allow" in r.getMessage()]) == 1
