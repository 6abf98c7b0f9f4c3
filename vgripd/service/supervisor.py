"""What every link driver shares about its own health and, for the links that reconnect, its
outages.

``HealthCell`` holds a link's ``LinkHealth`` (state, since when, the last error, reconnects) and
wakes whoever waits for a state. Setting it is synchronous, so a link may change its health
from a callback as well as from a task. ``SupervisedLink`` is the base of the links that keep
one: their ``health`` and ``wait_state``.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Set as AbstractSet
from typing import Any

from vgripd.service.protocol import LinkHealth, LinkState, RobotLink


class HealthCell:
    """A link's health and the waiters for its changes.

    ``since_mono_ns`` moves only when the state does. ``set`` without a change (same state,
    same error, no reconnect) wakes nobody.
    """

    def __init__(self, peer: str = "") -> None:
        self.peer = peer
        self.state = LinkState.STOPPED
        self.since_mono_ns = time.monotonic_ns()
        self.last_error = ""
        self.reconnects = 0
        self._changed: asyncio.Event | None = None

    def set(self, state: LinkState, error: str | None = "", reconnect: bool = False) -> None:
        """Enter ``state`` with ``error`` as the last error ("" clears it, None keeps it);
        ``reconnect`` counts a reconnection."""
        error = self.last_error if error is None else error
        if state is self.state and error == self.last_error and not reconnect:
            return
        if state is not self.state:
            self.state = state
            self.since_mono_ns = time.monotonic_ns()
        self.last_error = error
        self.reconnects += int(reconnect)
        changed, self._changed = self._changed, None
        if changed is not None:
            changed.set()  # wakes every waiter once; later ones wait on a fresh event

    def health(self, peer: str | None = None, peers: int = 0) -> LinkHealth:
        """The health now (``peer``: where the link is now, if it differs from ``self.peer``;
        ``peers``: connected clients of a server link)."""
        return LinkHealth(self.state, peer=self.peer if peer is None else peer,
                          last_error=self.last_error, reconnects=self.reconnects,
                          since_mono_ns=self.since_mono_ns, peers=peers)

    async def wait(self, states: AbstractSet[LinkState] | LinkState, timeout_s: float) -> None:
        """Until the state is one of ``states``; ``TimeoutError`` after ``timeout_s``."""
        wanted = {states} if isinstance(states, LinkState) else states
        async with asyncio.timeout(timeout_s):
            while self.state not in wanted:
                if self._changed is None:
                    self._changed = asyncio.Event()
                await self._changed.wait()


class SupervisedLink(RobotLink):
    """A link whose health lives in ``self.cell``. A link that knows more than the cell
    (where it listens now, how many clients it has) overrides ``health``."""

    def __init__(self, name: str, options: Any, peer: str = "") -> None:
        super().__init__(name, options)
        self.cell = HealthCell(peer)

    def health(self) -> LinkHealth:
        return self.cell.health()

    async def wait_state(self, states: set[LinkState] | LinkState, timeout_s: float) -> LinkHealth:
        """Wait until ``health().state`` is one of ``states``; ``TimeoutError`` otherwise."""
        await self.cell.wait(states, timeout_s)
        return self.health()
