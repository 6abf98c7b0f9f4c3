"""What every link driver shares about its own health and, for the links that reconnect, its
outages.

``HealthCell`` holds a link's ``LinkHealth`` (state, since when, the last error, reconnects) and
wakes whoever waits for a state. Setting it is synchronous, so a link may change its health
from a callback as well as from a task. ``SupervisedLink`` is the base of the links that keep
one: their ``health`` and ``wait_state``.

``OutagePolicy`` is what a link does about a lost peer, without sockets, tasks or clocks (time
is an argument): wait ``backoff_initial_s`` before the first retry, double the wait after each
failure up to ``backoff_max_s``, log the outage once (its first failure), start over once the
peer is back. ``Reconnector`` is the one loop that runs it for every link that reconnects: it
runs the link's session (connect, serve until the connection ends), then marks the link DOWN,
logs the outage's one line and waits the policy's delay before the next session.

``BackoffOptions`` is the back-off part of those links' options: one pair of bounds, one set of
defaults, one check; a link whose documented defaults differ keeps them with
``backoff_initial(...)``/``backoff_max(...)`` on its own fields.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable
from collections.abc import Set as AbstractSet
from dataclasses import dataclass
from typing import Any, NoReturn

from pydantic import BaseModel, Field, ValidationInfo, field_validator

from vgripd.service.links.protocol import LinkHealth, LinkState, RobotLink


class HealthCell:
    """A link's health and the waiters for its changes.

    ``since_mono_ns`` moves only when the state does. ``set`` without a change (same state,
    same error, no reconnect) wakes nobody; a change also calls ``changed``.
    """

    def __init__(self, peer: str = "") -> None:
        self.peer = peer
        self.state = LinkState.STOPPED
        self.since_mono_ns = time.monotonic_ns()
        self.last_error = ""
        self.reconnects = 0
        self._changed: asyncio.Event | None = None
        #: Called after every change (``SupervisedLink``: its ``health_changed``).
        self.changed: Callable[[], None] | None = None

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
        if self.changed is not None:
            self.changed()

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
        self.cell.changed = lambda: self.health_changed()  # read at call: set after this

    def health(self) -> LinkHealth:
        return self.cell.health()

    async def wait_state(self, states: set[LinkState] | LinkState, timeout_s: float) -> LinkHealth:
        """Wait until ``health().state`` is one of ``states``; ``TimeoutError`` otherwise."""
        await self.cell.wait(states, timeout_s)
        return self.health()


# --- options -------------------------------------------------------------------------------


def backoff_initial(default_s: float = 0.1) -> Any:
    """The ``backoff_initial_s`` field (s), with a link's own default."""
    return Field(default_s, gt=0, le=60)


def backoff_max(default_s: float = 5.0) -> Any:
    """The ``backoff_max_s`` field (s), with a link's own default."""
    return Field(default_s, gt=0, le=600)


class BackoffOptions(BaseModel):
    """``backoff_initial_s``: the wait before the first retry after a failure; it doubles
    after each further failure, up to ``backoff_max_s`` (not below ``backoff_initial_s``)."""

    backoff_initial_s: float = backoff_initial()
    backoff_max_s: float = backoff_max()

    @field_validator("backoff_max_s")
    @classmethod
    def _not_below_initial(cls, value: float, info: ValidationInfo) -> float:
        initial = info.data.get("backoff_initial_s")
        if initial is not None and value < initial:
            raise ValueError(f"{value:g} is below backoff_initial_s = {initial:g}")
        return value


# --- outages -------------------------------------------------------------------------------


@dataclass(frozen=True)
class Retry:
    """``OutagePolicy.failed``'s decision: wait ``delay_s`` (until ``at``, the caller's clock)
    before the next attempt. ``first``: this failure begins an outage (log it); ``attempt``:
    the failures of this outage so far, this one included; ``outage_s``: how long it lasts."""

    delay_s: float
    at: float
    first: bool
    attempt: int
    outage_s: float


class OutagePolicy:
    """Doubling back-off and one log line per outage; no I/O, no clock of its own."""

    def __init__(self, initial_s: float, max_s: float) -> None:
        if not 0 < initial_s <= max_s:
            raise ValueError(f"back-off needs 0 < initial ({initial_s}) <= max ({max_s})")
        self.initial_s = initial_s
        self.max_s = max_s
        self._failures = 0
        self._began = 0.0
        self._delay_s = initial_s

    @property
    def in_outage(self) -> bool:
        """A failure since the peer was last back (or since the start)."""
        return self._failures > 0

    def failed(self, now: float) -> Retry:
        """An attempt failed or a connection ended at ``now`` (seconds)."""
        if self._failures == 0:
            self._began = now
        self._failures += 1
        delay = self._delay_s
        self._delay_s = min(2 * delay, self.max_s)
        return Retry(delay, now + delay, self._failures == 1, self._failures, now - self._began)

    def recovered(self) -> bool:
        """The peer is back: the next failure is a new outage, waited from ``initial_s``.
        True when this ends an outage."""
        was = self._failures > 0
        self._failures = 0
        self._delay_s = self.initial_s
        return was


async def end_task(task: asyncio.Task[Any]) -> None:
    """Cancel ``task`` (a link's supervisor) and wait until it has ended; its error, if any, is
    dropped (the link reported it). A cancel can be lost: Python 3.11's ``asyncio.wait_for`` in
    a library under a link returns a result that came with the cancel and drops the cancel, and
    the task runs on; a plain ``await`` then waits for ever (an S7 link's close hung a test for
    its 300 s limit). So the task is cancelled again every second until it ends."""
    while not task.done():
        task.cancel()
        await asyncio.wait({task}, timeout=1.0)
    if not task.cancelled():
        task.exception()  # retrieved: no "never retrieved" warning


@dataclass(frozen=True)
class Ended:
    """How a session ended: the link's ``error`` (its health's ``last_error``) and the level of
    the outage's one log line (ERROR when it needs a person, such as a refused register)."""

    error: str
    level: int = logging.WARNING


class Reconnector:
    """The reconnect loop of a link whose peer comes and goes (``run``), on an
    ``OutagePolicy`` and the link's ``HealthCell``.

    ``down_line`` is the outage's one line (arguments: link name, error, ``backoff_max_s``);
    every later failure of the same outage is a DEBUG line ``still_line`` (link name, attempt,
    error)."""

    def __init__(self, name: str, cell: HealthCell, policy: OutagePolicy, log: logging.Logger,
                 down_line: str = "%s: %s; retrying with back-off up to %.1f s",
                 still_line: str = "%s: still down (attempt %d): %s",
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.name = name
        self.cell = cell
        self.policy = policy
        self.log = log
        self.down_line = down_line
        self.still_line = still_line
        self.clock = clock
        self._retry: Retry | None = None

    def up(self, reconnect: bool | None = None, recovered: bool = True) -> bool:
        """The peer answers: the link is UP. ``reconnect``: count a reconnection (default: when
        an outage was on); ``recovered``: the outage is over now (False: the caller says so
        later with ``recovered``, once the connection proved itself). True when an outage
        was on."""
        outage = self.policy.in_outage
        self.cell.set(LinkState.UP, "", reconnect=outage if reconnect is None else reconnect)
        if recovered:
            self.recovered()
        return outage

    def recovered(self) -> None:
        self.policy.recovered()
        self._retry = None

    def failed(self, ended: Ended) -> Retry:
        """The link is DOWN for ``ended``: log the outage's first failure, plan the retry (the
        next ``run`` round waits for it)."""
        retry = self._retry = self.policy.failed(self.clock())
        if retry.first:
            self.log.log(ended.level, self.down_line, self.name, ended.error, self.policy.max_s)
        else:
            self.log.debug(self.still_line, self.name, retry.attempt, ended.error)
        self.cell.set(LinkState.DOWN, ended.error)
        return retry

    async def run(self, session: Callable[[], Awaitable[Ended]]) -> NoReturn:
        """Run ``session`` again and again, each after the back-off its predecessor's end (or
        the failure the link reported at its start) asks for."""
        while True:
            if self._retry is not None:
                await asyncio.sleep(self._retry.delay_s)
            self.failed(await session())
