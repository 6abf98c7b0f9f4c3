"""The web view's server-sent events: the streams (``EventHub``) and what the daemon pushes
into them (``StatusFeed``).

A page opens ``GET /api/events`` once and is told what changed; it asks ``/api/status`` only
while its stream fails. Events (docs/web.md, "Live updates"):

- ``status``: the status document (``/api/status``'s JSON) on connecting and after every change
  of the daemon's state: a job's progress, the camera, the run state, a link going up or down,
  a reconnect, a peer connecting. A burst of changes is coalesced: at most one document per
  ``PUSH_INTERVAL_S``, the last one always describing the state after the burst.
- ``links``: the status's ``links`` when a link's state, peer, reconnects or peers change.
- ``job`` (after each job) and ``walk`` are published by their rooms through ``publish``.

Bounds: a page that does not read is dropped (``MAX_EVENTS_QUEUED``); streams are counted
against the web view's connection cap (``stream_caps``), so that live pages never take every
slot from ordinary requests.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections import deque
from collections.abc import Callable
from typing import Any

from vgripd.redaction import redact
from vgripd.serialize import jsonable
from vgripd.service.web.daemonview import DaemonView

# Server-sent event streams: of clients without the token at once (all of them, and from one
# address), of token holders (the oldest is dropped for a new one: the operator is always
# served), and the events one may have unsent before it is dropped. The web view's connection
# cap lowers the first and the third (``stream_caps``).
MAX_EVENT_CLIENTS = 32
MAX_EVENT_CLIENTS_PER_ADDRESS = 4
MAX_HOLDER_STREAMS = 16
MAX_EVENTS_QUEUED = 64
#: A comment line on a quiet stream this often (proxies and browsers keep it open).
KEEPALIVE_S = 15.0
#: At most one pushed status document per this many seconds (a burst is coalesced).
PUSH_INTERVAL_S = 0.1
#: The reconnection delay the page's EventSource is told (ms).
RETRY_MS = 2000


def frame(event: str, data: Any) -> bytes:
    """One server-sent event: its name and its data as one line of JSON."""
    return f"event: {event}\ndata: {json.dumps(jsonable(data))}\n\n".encode()


def stream_caps(connections: int) -> tuple[int, int]:
    """``(anonymous, holder)`` stream caps for a web view of ``connections`` connection slots:
    at most half the slots for streams without the token and a quarter (at least one) for
    token holders, always leaving one slot for ordinary requests (an open stream holds its
    connection, and the gate never evicts a connection with a request in flight)."""
    holders = max(1, min(MAX_HOLDER_STREAMS, connections // 4))
    anonymous = max(0, min(MAX_EVENT_CLIENTS, connections // 2, connections - 1 - holders))
    return anonymous, holders


class _Client:
    def __init__(self, address: str = "", holder: bool = False) -> None:
        self.queue: asyncio.Queue[bytes | None] = asyncio.Queue(MAX_EVENTS_QUEUED)
        self.address = address
        self.holder = holder  # the request carried the token


class EventHub:
    """Server-sent events to every connected page; a page that does not read is dropped.

    Streams are bounded so that no crowd locks the operator out: clients without the token
    get at most ``anonymous`` streams in all (``MAX_EVENT_CLIENTS``) and
    ``MAX_EVENT_CLIENTS_PER_ADDRESS`` from one address; a token holder is always served, the
    oldest holder stream dropped beyond ``holders`` (``MAX_HOLDER_STREAMS``).
    """

    def __init__(self, anonymous: int = MAX_EVENT_CLIENTS,
                 holders: int = MAX_HOLDER_STREAMS) -> None:
        self.clients: set[_Client] = set()
        self.anonymous = anonymous
        self.holders = holders
        self._holders: deque[_Client] = deque()  # oldest first

    def admit(self, address: str, holder: bool) -> _Client | None:
        """A new stream's client, or None when its kind is full (answer 503)."""
        if holder:
            while self._holders and len(self._holders) >= self.holders:
                self._drop(self._holders[0])
        else:
            anonymous = [c for c in self.clients if not c.holder]
            if (len(anonymous) >= self.anonymous or sum(
                    c.address == address for c in anonymous) >= MAX_EVENT_CLIENTS_PER_ADDRESS):
                return None
        client = _Client(address, holder)
        self.clients.add(client)
        if holder:
            self._holders.append(client)
        return client

    def leave(self, client: _Client) -> None:
        self.clients.discard(client)
        with contextlib.suppress(ValueError):
            self._holders.remove(client)

    def publish(self, event: str, data: Any) -> None:
        self.publish_frame(frame(event, data))

    def publish_frame(self, data: bytes) -> None:
        for client in list(self.clients):
            try:
                client.queue.put_nowait(data)
            except asyncio.QueueFull:
                self._drop(client)

    def _drop(self, client: _Client) -> None:
        self.leave(client)
        with contextlib.suppress(asyncio.QueueEmpty):
            while True:
                client.queue.get_nowait()
        client.queue.put_nowait(None)  # ends its stream

    def close(self) -> None:
        for client in list(self.clients):
            self._drop(client)


class StatusFeed:
    """Pushes ``status`` (and ``links``) events into ``hub`` after the daemon's state changes:
    it waits on the daemon's change count (``DaemonView.next_change``), never on a timer."""

    def __init__(self, daemon: DaemonView, hub: EventHub,
                 document: Callable[[], dict[str, Any]]) -> None:
        self.daemon = daemon
        self.hub = hub
        self.document = document  # the status document, as /api/status answers it
        self.pushed = 0  # status documents pushed (to every stream at once)
        self.documented = 0  # the daemon's change count the last one was built at

    async def run(self) -> None:
        seen = self.daemon.changes
        links = self._links()
        while True:
            seen = await self.daemon.next_change(seen)
            now = self._links()
            if now != links:
                links = now
                if self.hub.clients:
                    self.hub.publish("links", redact(self.daemon.snapshot()["links"]))
            if self.hub.clients:  # an unwatched daemon builds no documents
                self.hub.publish("status", self.document())
                self.pushed += 1
                self.documented = seen
            # Coalescing: changes meanwhile are counted and sent as one document afterwards.
            await asyncio.sleep(PUSH_INTERVAL_S)

    def _links(self) -> list[tuple[Any, ...]]:
        return [(name, h.state.value, h.peer, h.reconnects, h.peers)
                for name, h in ((n, link.health())
                                for n, link in self.daemon.rooms.links.links.items())]
