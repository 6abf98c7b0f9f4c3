"""The web view's accept path: the daemon's connection manager (``vgripd.service.links.gate``) in
front of aiohttp, and the HTTP read timeouts aiohttp does not have.

aiohttp's server has no header or body read timeout: a client that sends half a request line
(slow loris) or nothing at all holds its socket until ``keepalive_timeout`` would apply, which
it never does before a first request. ``GuardedSite`` listens like ``web.TCPSite`` but wraps
each connection's ``RequestHandler`` in ``_Guard``, which

- asks the gate at accept (``allow``, ``max_connections``; a newcomer evicts the oldest
  connection that never completed a request, then the longest-idle one between requests; a
  connection with a request in flight, such as a live event stream, is never evicted);
- closes a connection whose request headers are not complete within ``header_timeout_s`` of
  connecting or of the end of its previous request (so also an idle keep-alive connection);
- with ``middleware`` (added to the application), reads a request body within
  ``body_timeout_s`` before the handler runs, or closes the connection.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable
from typing import Any

from aiohttp import web

from vgripd.service.links.gate import WEB_SURFACE, Gate
from vgripd.service.web.daemonview import DaemonView

log = logging.getLogger(__name__)

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]
BODY_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})


class WebGuard:
    """The gate of the web view and its timeouts; one per ``WebServer``."""

    def __init__(self, cap: int, header_timeout_s: float, body_timeout_s: float,
                 allow: list[str] | None = None) -> None:
        self.gate = Gate("web view", cap, allow=allow, reclaim_idle=True, logger=log)
        self.header_timeout_s = header_timeout_s
        self.body_timeout_s = body_timeout_s
        self._by_transport: dict[asyncio.BaseTransport, _Guard] = {}

    @web.middleware
    async def middleware(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        guard = self._by_transport.get(request.transport) if request.transport else None
        if guard is not None:
            guard.request_started()
        try:
            if request.method in BODY_METHODS and request.body_exists:
                try:
                    async with asyncio.timeout(self.body_timeout_s):
                        await request.read()  # kept by aiohttp for the handler's read()
                except TimeoutError:
                    host = guard.host if guard is not None else (request.remote or "?")
                    self.gate.fault(host, "slow_body", logging.WARNING,
                                    "web view: %s: request body not complete within %g s "
                                    "(body_timeout_s), closed", host, self.body_timeout_s)
                    if request.transport is not None:
                        request.transport.abort()
                    raise web.HTTPRequestTimeout() from None
            return await handler(request)
        finally:
            if guard is not None:
                guard.request_finished()

    def connected(self, transport: asyncio.BaseTransport, connection: _Guard) -> None:
        """An admitted connection, found again by its transport when a request comes."""
        self._by_transport[transport] = connection

    def disconnected(self, transport: asyncio.BaseTransport) -> None:
        self._by_transport.pop(transport, None)

    def start(self) -> None:
        self.gate.start()

    async def stop(self) -> None:
        await self.gate.stop()


class _Guard(asyncio.Protocol):
    """One connection: the gate's view of it around aiohttp's own protocol."""

    def __init__(self, guard: WebGuard, inner: asyncio.Protocol) -> None:
        self.guard = guard
        self.inner = inner
        self.host = "?"
        self.client = "?"
        self.transport: asyncio.BaseTransport | None = None
        self.admitted = False
        self.requests = 0
        self._in_flight = 0
        self._data = False  # bytes arrived since the last request ended
        self._timer: asyncio.TimerHandle | None = None

    # asyncio.Protocol, forwarded to aiohttp once admitted ---------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport
        peer = transport.get_extra_info("peername")
        if isinstance(peer, tuple) and len(peer) >= 2:
            self.host, self.client = str(peer[0]), f"{peer[0]}:{peer[1]}"
        if not self.guard.gate.admit(self):
            transport.close()  # nothing written yet: closes at once
            return
        self.admitted = True
        self.guard.connected(transport, self)
        self.inner.connection_made(transport)
        self._arm()

    def data_received(self, data: bytes) -> None:
        if self.admitted:
            self._data = True
            self.inner.data_received(data)

    def eof_received(self) -> bool | None:
        return self.inner.eof_received() if self.admitted else False

    def pause_writing(self) -> None:
        if self.admitted:
            self.inner.pause_writing()

    def resume_writing(self) -> None:
        if self.admitted:
            self.inner.resume_writing()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        if self.transport is not None:
            self.guard.disconnected(self.transport)
        self.guard.gate.forget(self)
        if self.admitted:
            self.admitted = False
            self.inner.connection_lost(exc)

    # the gate's and the middleware's ------------------------------------------------------

    def shut(self, reason: str) -> None:
        self._disarm()
        if self.transport is not None:
            self.transport.close()

    def request_started(self) -> None:
        self._disarm()
        self.requests += 1
        self._in_flight += 1
        self.guard.gate.activity(self, valid=True)
        self.guard.gate.busy(self, True)

    def request_finished(self) -> None:
        self._in_flight = max(0, self._in_flight - 1)
        if not self._in_flight:
            self.guard.gate.busy(self, False)
            self._data = False
            self._arm()

    def _arm(self) -> None:
        self._disarm()
        if self.admitted:
            self._timer = asyncio.get_running_loop().call_later(
                self.guard.header_timeout_s, self._timed_out)

    def _disarm(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _timed_out(self) -> None:
        self._timer = None
        if not self.admitted or self._in_flight or self.transport is None:
            return
        if isinstance(self.transport, asyncio.WriteTransport) and (
                self.transport.get_write_buffer_size()):
            self._arm()  # the last answer is still going out to a slow reader
            return
        gate, timeout_s = self.guard.gate, self.guard.header_timeout_s
        if self._data:
            gate.fault(self.host, "slow_header", logging.WARNING,
                       "web view: %s: request headers not complete within %g s "
                       "(header_timeout_s), closed", self.client, timeout_s)
        else:
            gate.fault(self.host, "idle", logging.INFO,
                       "web view: %s: no request within %g s (header_timeout_s), closed",
                       self.client, timeout_s)
        gate.forget(self)
        self.transport.close()


class GuardedSite(web.TCPSite):
    """``web.TCPSite`` whose connections go through ``WebGuard`` (and its accept backlog)."""

    def __init__(self, runner: web.BaseRunner, host: str | None, port: int,
                 guard: WebGuard, **kwargs: Any) -> None:
        super().__init__(runner, host, port, backlog=guard.gate.backlog, **kwargs)
        self.guard = guard

    async def start(self) -> None:
        await web.BaseSite.start(self)  # registers the site with its runner
        server = self._runner.server
        assert server is not None
        guard = self.guard
        self._server = await asyncio.get_running_loop().create_server(
            lambda: _Guard(guard, server()), self._host, self._port, backlog=self._backlog,
            reuse_address=self._reuse_address, reuse_port=self._reuse_port)
        self._bound_port = (self._server.sockets[0].getsockname()[1] if self._server.sockets
                            else self._port)


def make_guard(daemon: DaemonView) -> WebGuard:
    """The guard of ``daemon``'s web view: ``[status]``'s options, the cap the file budget
    gave it (``rooms.links.fd_budget``) when there is one."""
    st = daemon.config.status
    budget = daemon.rooms.links.fd_budget
    cap = budget.caps.get(WEB_SURFACE, st.max_connections) if budget is not None \
        else st.max_connections
    return WebGuard(cap, st.header_timeout_s, st.body_timeout_s, st.allow)
