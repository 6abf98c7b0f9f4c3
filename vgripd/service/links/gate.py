"""The one connection manager of every server surface facing the cell network.

Modbus/TCP (``drivers.links.modbus_server``), the robot socket (``drivers.links.robot_socket``),
OPC UA (``drivers.links.opcua``, at accept) and the web view (``vgripd.service.web.guard``) each
keep one ``Gate``. A surface is a listening socket; its gate decides, for every connection:

- **allow**: a client address outside the surface's ``allow`` list is closed at accept.
- **cap**: at most ``cap`` connections. When full, a newcomer takes the place of the oldest
  connection that never completed a valid request; when every connection has completed one (a
  PLC that polls, a robot that has talked, a browser with a request in flight), the newcomer is
  refused. So a flood of newcomers that never send anything valid evicts only itself, never
  the PLC or the robot.
- **timeouts**: a connection that has not completed a valid request within
  ``pending_timeout_s`` of connecting is closed (0 = never); one without activity for
  ``idle_timeout_s`` is closed (0 = never), unless it is ``busy`` (a robot waiting for its
  result, an HTTP request in flight).
- **log**: every fault (refused, evicted, idle, malformed, ...) is counted per kind and logged
  through one ``RateLimitedLog``: one line per client address and kind per interval.

``Slots`` is the policy, without sockets, tasks or clocks (time is an argument), tested by
feeding it events; ``Gate`` is the thin shell that asks a connection to ``shut`` and runs the
periodic sweep; ``set_keepalive`` is the TCP keepalive every TCP server link sets on the
connections its gate admits. ``plan_budget`` splits the process's file limit (RLIMIT_NOFILE)
between the surfaces and a reserve (docs/daemon.md, "File budget").
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import logging
import os
import resource
import socket
import time
from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

from vgripd.service.links.ratelog import RateLimitedLog

log = logging.getLogger(__name__)

Network = ipaddress.IPv4Network | ipaddress.IPv6Network
#: The web view's name in the file budget (the links go by their names).
WEB_SURFACE = "web view"


class Guarded(Protocol):
    """What a gate needs of a connection: who it is and how to close it."""

    host: str  # the client's address (the log's key, the allow-list's subject)
    client: str  # address:port, for messages

    def shut(self, reason: str) -> None:
        """Close the connection (the gate has logged why)."""


# --- the policy --------------------------------------------------------------------------


@dataclass
class Slot:
    opened: float  # when it connected (monotonic s)
    last: float  # last activity: a complete request, valid or not, or the connect
    valid: bool = False  # completed at least one valid request
    busy: bool = False  # something in flight for it: not idle, evicted never


@dataclass
class Admission:
    """``admit``'s decision: ``accepted`` or not, and whom to evict for it."""

    accepted: bool
    victims: list[Any] = field(default_factory=list)


class Slots:
    """Bookkeeping and eviction of one surface's connections; no I/O."""

    def __init__(self, cap: int, reclaim_idle: bool = False) -> None:
        if cap < 1:
            raise ValueError("cap must be >= 1")
        self.cap = cap
        #: when no never-valid connection is left, evict the longest-idle one that is not busy
        #: instead of refusing the newcomer (HTTP: a keep-alive connection between requests)
        self.reclaim_idle = reclaim_idle
        self._slots: dict[Any, Slot] = {}  # in order of arrival
        self._gone: dict[Any, bool] = {}  # the last admission's victims: were they valid

    def __len__(self) -> int:
        return len(self._slots)

    def __contains__(self, conn: object) -> bool:
        return conn in self._slots

    def connections(self) -> list[Any]:
        return list(self._slots)

    def slot(self, conn: Any) -> Slot | None:
        return self._slots.get(conn)

    def admit(self, conn: Any, now: float) -> Admission:
        """A new connection. Beyond the cap the oldest never-valid connections go; if all
        have been valid, the newcomer is refused (or, with ``reclaim_idle``, the longest-idle
        connection without anything in flight goes)."""
        victims: list[Any] = []
        self._gone.clear()
        while len(self._slots) - len(victims) >= self.cap:
            free = [c for c, s in self._slots.items() if not s.busy and c not in victims]
            pending = [c for c in free if not self._slots[c].valid]
            if pending:
                victims.append(min(pending, key=lambda c: self._slots[c].opened))
            elif self.reclaim_idle and free:
                victims.append(min(free, key=lambda c: self._slots[c].last))
            else:
                return Admission(False)
        for victim in victims:
            self._gone[victim] = self._slots.pop(victim).valid
        self._slots[conn] = Slot(opened=now, last=now)
        return Admission(True, victims)

    def was_valid(self, victim: Any) -> bool:
        """Whether an evicted connection had completed a valid request (for its log line)."""
        return self._gone.pop(victim, False)

    def activity(self, conn: Any, now: float, valid: bool) -> None:
        """A complete request arrived (``valid``: one the surface answered as such)."""
        s = self._slots.get(conn)
        if s is not None:
            s.last = now
            s.valid = s.valid or valid

    def set_busy(self, conn: Any, busy: bool, now: float) -> None:
        s = self._slots.get(conn)
        if s is not None:
            s.busy = busy
            s.last = now

    def forget(self, conn: Any) -> bool:
        return self._slots.pop(conn, None) is not None

    def expired(self, now: float, idle_timeout_s: float,
                pending_timeout_s: float) -> list[tuple[Any, str, float]]:
        """Connections past a timeout: (connection, ``"pending"`` or ``"idle"``, seconds)."""
        out: list[tuple[Any, str, float]] = []
        for conn, s in self._slots.items():
            if s.busy:
                continue
            if not s.valid and pending_timeout_s and now - s.opened > pending_timeout_s:
                out.append((conn, "pending", now - s.opened))
            elif idle_timeout_s and now - s.last > idle_timeout_s:
                out.append((conn, "idle", now - s.last))
        return out


def parse_allow(entries: Sequence[str] | None) -> list[Network] | None:
    """The networks of a validated ``allow`` list (vgripd.config.AllowList)."""
    if entries is None:
        return None
    return [ipaddress.ip_network(e, strict=False) for e in entries]


def allowed(networks: Sequence[Network] | None, host: str) -> bool:
    """Whether ``host`` is in ``networks`` (None: everyone). An IPv4 client seen on an IPv6
    socket (``::ffff:10.0.0.5``) is judged by its IPv4 address."""
    if networks is None:
        return True
    try:
        address = ipaddress.ip_address(host.split("%", 1)[0])
    except ValueError:
        return False
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        address = address.ipv4_mapped
    return any(address.version == n.version and address in n for n in networks)


# --- the shell ---------------------------------------------------------------------------


class Gate:
    """One surface's connections: allow-list, cap and eviction (``Slots``), timeouts, and the
    rate-limited fault log. ``admit`` at ``connection_made``; False means the caller closes
    the newcomer at once (its fault is logged). ``forget`` at ``connection_lost``.

    ``lines``/``faults`` may be shared with the surface's own fault log (one line per client
    and kind per ``log_interval_s`` for everything the surface reports).
    """

    def __init__(self, surface: str, cap: int, *, allow: Sequence[str] | None = None,
                 idle_timeout_s: float = 0.0, pending_timeout_s: float = 0.0,
                 log_interval_s: float = 60.0, lines: RateLimitedLog | None = None,
                 faults: Counter[str] | None = None, logger: logging.Logger | None = None,
                 reclaim_idle: bool = False,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.surface = surface
        self.slots = Slots(cap, reclaim_idle)
        self.networks = parse_allow(allow)
        self.idle_timeout_s = idle_timeout_s
        self.pending_timeout_s = pending_timeout_s
        self.lines = lines if lines is not None else RateLimitedLog(logger or log,
                                                                     log_interval_s)
        #: faults by kind: not_allowed, full, evicted, pending, idle (and the surface's own)
        self.faults: Counter[str] = faults if faults is not None else Counter()
        self.configured_cap = cap
        self._clock = clock
        self._task: asyncio.Task[None] | None = None
        #: Called when the number of connections changes (a link's ``peers``: the link
        #: supervisor points it at the link's ``health_changed``).
        self.count_changed: Callable[[], None] | None = None

    # the budget ---------------------------------------------------------------------------

    @property
    def cap(self) -> int:
        return self.slots.cap

    @cap.setter
    def cap(self, value: int) -> None:
        self.slots.cap = max(1, value)

    @property
    def backlog(self) -> int:
        """The listen backlog: also how many sockets one accept round may take at once
        (asyncio accepts up to ``backlog`` per wake-up), so the budget counts it."""
        return backlog_for(self.cap)

    # connections --------------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self.slots)

    def connections(self) -> list[Any]:
        """Open connections, oldest first."""
        return self.slots.connections()

    def fault(self, host: str, kind: str, level: int, msg: str, *args: Any) -> None:
        """Count a fault and log it, at most once per client address and kind per interval."""
        self.faults[kind] += 1
        self.lines.log(level, host, kind, msg, *args)

    def admit(self, conn: Guarded) -> bool:
        if not allowed(self.networks, conn.host):
            self.fault(conn.host, "not_allowed", logging.WARNING,
                       "%s: %s refused: address not in allow", self.surface, conn.client)
            return False
        decision = self.slots.admit(conn, self._clock())
        if not decision.accepted:
            self.fault(conn.host, "full", logging.WARNING,
                       "%s: %s refused: all %d connections have completed requests "
                       "(max_connections)", self.surface, conn.client, self.cap)
            return False
        for victim in decision.victims:
            self.fault(victim.host, "evicted", logging.WARNING,
                       "%s: %s evicted for %s (max_connections = %d; %s)", self.surface,
                       victim.client, conn.client, self.cap,
                       "idle between requests" if self.slots.was_valid(victim)
                       else "it never completed a valid request")
            victim.shut(f"evicted for {conn.client} (max_connections = {self.cap})")
        self._counted()
        return True

    def activity(self, conn: Guarded, valid: bool = True) -> None:
        self.slots.activity(conn, self._clock(), valid)

    def busy(self, conn: Guarded, busy: bool) -> None:
        self.slots.set_busy(conn, busy, self._clock())

    def forget(self, conn: Guarded) -> bool:
        """The connection closed; True when the gate held it."""
        held = self.slots.forget(conn)
        if held:
            self._counted()
        return held

    def _counted(self) -> None:
        if self.count_changed is not None:
            self.count_changed()

    def sweep(self) -> None:
        """Close connections past ``pending_timeout_s`` / ``idle_timeout_s``."""
        for conn, kind, seconds in self.slots.expired(self._clock(), self.idle_timeout_s,
                                                      self.pending_timeout_s):
            self.slots.forget(conn)
            self._counted()
            if kind == "pending":
                what = (f"no valid request within {self.pending_timeout_s:g} s of connecting "
                        f"({seconds:.1f} s)")
            else:
                what = f"no request for {seconds:.1f} s (idle_timeout_s)"
            self.fault(conn.host, kind, logging.INFO, "%s: %s: %s, closed", self.surface,
                       conn.client, what)
            conn.shut(what)

    # the sweep task -----------------------------------------------------------------------

    def start(self) -> None:
        """Start the periodic sweep and log flush (on the running loop)."""
        if self._task is None:
            self._task = asyncio.get_running_loop().create_task(
                self._run(), name=f"{self.surface}-gate")

    async def stop(self) -> None:
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self.lines.flush(force=True)

    async def _run(self) -> None:
        timeouts = [t for t in (self.idle_timeout_s, self.pending_timeout_s) if t]
        period_s = min([1.0] + [t / 4 for t in timeouts])
        while True:
            await asyncio.sleep(period_s)
            self.sweep()
            self.lines.flush()


def backlog_for(cap: int) -> int:
    return max(8, min(64, cap))


# --- the file budget ---------------------------------------------------------------------


@dataclass(frozen=True)
class Budget:
    """How the file limit is split: ``caps`` by surface, and what the split left over."""

    limit: int  # RLIMIT_NOFILE (soft)
    in_use: int  # descriptors open when the plan was made
    reserve: int  # kept for PLC client links, the worker, shared memory, recordings
    caps: Mapping[str, int]
    backlogs: Mapping[str, int]
    scaled: bool  # the configured caps did not fit and were reduced

    @property
    def spare(self) -> int:
        return (self.limit - self.in_use - self.reserve - sum(self.caps.values())
                - sum(self.backlogs.values()))

    def describe(self) -> str:
        parts = ", ".join(f"{name} {cap}+{self.backlogs[name]}" for name, cap in
                          self.caps.items())
        return (f"file budget: limit {self.limit} (RLIMIT_NOFILE), {self.in_use} open at "
                f"start, {self.reserve} kept for PLC links, the worker and shared memory; "
                f"surfaces (connections+accept backlog): {parts or 'none'}; "
                f"{self.spare} spare")


def plan_budget(limit: int, in_use: int, reserve: int,
                wanted: Iterable[tuple[str, int]]) -> Budget:
    """Split ``limit`` file descriptors: ``in_use`` and ``reserve`` first, then each surface
    its wanted cap plus its accept backlog. When they do not fit, every cap is scaled down in
    proportion (at least 1 each; the backlogs shrink with them). Under a small limit the
    reserve takes at most half of what is free, so that the surfaces keep the other half."""
    wanted = list(wanted)
    reserve = max(0, min(reserve, (limit - in_use) // 2))
    free = limit - in_use - reserve
    caps = {name: cap for name, cap in wanted}
    need = sum(c + backlog_for(c) for c in caps.values())
    scaled = need > free
    if scaled and caps:
        share = max(free, 0) / need
        caps = {name: max(1, int(cap * share)) for name, cap in caps.items()}
        # the backlog of a smaller cap is smaller too; walk down until it fits (or all are 1)
        while (sum(c + backlog_for(c) for c in caps.values()) > free
               and any(c > 1 for c in caps.values())):
            biggest = max(caps, key=lambda n: caps[n])
            caps[biggest] -= 1
    return Budget(limit, in_use, reserve, caps, {n: backlog_for(c) for n, c in caps.items()},
                  scaled)


def open_files() -> int:
    """Descriptors this process holds now (0 where /proc is missing)."""
    try:
        return len(os.listdir("/proc/self/fd"))
    except OSError:
        return 0


def file_limit() -> int:
    soft, _hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    return soft if soft != resource.RLIM_INFINITY else 1 << 20


def set_keepalive(sock: Any, idle_s: int, interval_s: int, count: int) -> None:
    """TCP keepalive on ``sock``: probes after ``idle_s`` of silence, every ``interval_s``,
    ``count`` unanswered ones end the connection (Linux's per-socket timings where the
    platform has them). ``TCP_USER_TIMEOUT`` bounds, by the same total, how long unacknowledged
    answers keep a peer that vanished without a FIN."""
    settings = [(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)]
    for name, value in (("TCP_KEEPIDLE", idle_s), ("TCP_KEEPINTVL", interval_s),
                        ("TCP_KEEPCNT", count),
                        ("TCP_USER_TIMEOUT", 1000 * (idle_s + interval_s * count))):
        if hasattr(socket, name):
            settings.append((socket.IPPROTO_TCP, getattr(socket, name), value))
    for level, option, value in settings:
        with contextlib.suppress(OSError):
            sock.setsockopt(level, option, value)
