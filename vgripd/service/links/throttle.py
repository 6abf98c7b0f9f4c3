"""Failed logins per client address, slowed and then locked out: one policy for every surface
that checks a secret (the OPC UA link's sessions, the web view's ``/login`` and ``Bearer``
token). No I/O and no clock of its own: times are passed in, so every rule is tested by
feeding failures.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

#: Client addresses the throttle remembers (the oldest idle one is forgotten first).
MAX_TRACKED = 4096


@dataclass
class _Client:
    failures: int = 0  # failed logins in a row (forgotten after lockout_s without one)
    last_failure: float = 0.0
    next_answer: float = 0.0  # the earliest time the next failure may be answered
    locked_until: float = 0.0


class LoginThrottle:
    """Failed logins per client address: each failure is answered no sooner than
    ``1 / rate_per_s`` after the address's previous one (so no client learns more than
    ``rate_per_s`` answers a second, however many connections it opens); ``max_failures``
    failures in a row (none older than ``lockout_s`` apart, a successful login resets the
    count) lock the address out for ``lockout_s``: its logins are then refused unchecked.
    Times are ``time.monotonic()`` seconds, passed in."""

    def __init__(self, max_failures: int, rate_per_s: float, lockout_s: float,
                 max_tracked: int = MAX_TRACKED) -> None:
        self.max_failures = max_failures
        self.interval_s = 1.0 / rate_per_s
        self.lockout_s = lockout_s
        self.max_tracked = max_tracked
        self._clients: OrderedDict[str, _Client] = OrderedDict()

    def locked(self, host: str, now: float) -> float:
        """Seconds of lockout left for ``host`` (0: it may try)."""
        client = self._clients.get(host)
        return max(0.0, client.locked_until - now) if client is not None else 0.0

    def failed(self, host: str, now: float) -> tuple[float, bool]:
        """Count a failed login of ``host``: (seconds to hold the answer back, whether this
        failure started a lockout)."""
        client = self._clients.pop(host, None) or _Client()
        self._clients[host] = client  # most recently active last
        if now - client.last_failure > self.lockout_s:
            client.failures = 0
        client.failures += 1
        client.last_failure = now
        slot = max(now, client.next_answer)
        client.next_answer = slot + self.interval_s
        locked = client.failures >= self.max_failures and client.locked_until <= now
        if locked:
            client.locked_until = slot + self.lockout_s
            client.failures = 0
        self._forget(now)
        return slot - now, locked

    def succeeded(self, host: str) -> None:
        client = self._clients.get(host)
        if client is not None and not client.locked_until:
            del self._clients[host]
        elif client is not None:
            client.failures = 0

    def _forget(self, now: float) -> None:
        """Drop addresses that are neither locked nor failed recently; then the oldest."""
        if len(self._clients) <= self.max_tracked:
            return
        for host, client in list(self._clients.items()):
            if client.locked_until <= now and now - client.last_failure > self.lockout_s:
                del self._clients[host]
        while len(self._clients) > self.max_tracked:
            self._clients.popitem(last=False)

    def __len__(self) -> int:
        return len(self._clients)
