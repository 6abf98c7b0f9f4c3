"""A tiny read-only HTTP endpoint: ``GET /status`` returns the daemon's status as JSON.

Served with ``asyncio.start_server`` on the daemon's own loop (no dependency, no thread), bound
to 127.0.0.1 by default: it exposes no control, only what ``vgripd status`` prints. A request is
answered from an in-memory snapshot, so it is fast even while a job is processed.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
from collections.abc import Callable
from typing import Any

from vgripd.errors import VgripError

log = logging.getLogger(__name__)

_REQUEST_TIMEOUT_S = 2.0
_MAX_HEADER_LINES = 100


class StatusEndpointError(VgripError):
    """The status endpoint cannot listen (port in use, address not on this host): the daemon
    does not start (exit 1, like a link that cannot listen)."""


class StatusServer:
    def __init__(self, host: str, port: int, snapshot: Callable[[], dict[str, Any]]) -> None:
        self.host = host
        self._requested_port = port
        self._snapshot = snapshot
        self._server: asyncio.Server | None = None

    @property
    def port(self) -> int:
        """The bound port (the real one when configured as 0)."""
        if self._server is None:
            raise RuntimeError("status server not started")
        port: int = self._server.sockets[0].getsockname()[1]
        return port

    async def start(self) -> None:
        """Listen; ``StatusEndpointError`` in one line naming the address and the config keys."""
        try:
            self._server = await asyncio.start_server(self._serve, self.host,
                                                      self._requested_port)
        except OSError as err:
            reason = os.strerror(err.errno) if err.errno else str(err)
            raise StatusEndpointError(
                f"status endpoint cannot listen on {self.host}:{self._requested_port}: {reason} "
                f"(set [status] port = another port or 0 for any free one, [status] host, or "
                f"[status] enabled = false)") from None
        log.info("status: http://%s:%d/status", self.host, self.port)

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()
            self._server = None

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            async with asyncio.timeout(_REQUEST_TIMEOUT_S):
                request = (await reader.readline()).decode("latin-1").split()
                for _ in range(_MAX_HEADER_LINES):
                    if (await reader.readline()).strip() == b"":
                        break
            if len(request) >= 2 and request[0] == "GET" and request[1].split("?")[0] in (
                "/status", "/"
            ):
                body = json.dumps(self._snapshot(), indent=1).encode()
                head = "200 OK"
            else:
                body = b'{"error": "only GET /status"}'
                head = "404 Not Found"
            writer.write(
                f"HTTP/1.0 {head}\r\nContent-Type: application/json\r\n"
                f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n".encode() + body
            )
            await writer.drain()
        except (TimeoutError, ConnectionError, UnicodeDecodeError) as err:
            log.debug("status: request dropped: %r", err)
        finally:
            writer.close()
            with contextlib.suppress(ConnectionError):
                await writer.wait_closed()
