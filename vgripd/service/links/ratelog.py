"""Logging that a peer cannot flood: at most one line per (client, kind) per interval.

A network server logs what its peers do wrong (malformed frames, unknown function codes,
evictions). Written one line per event, a misbehaving or hostile peer decides how much the
journal grows. ``RateLimitedLog`` writes the first event of a (client, kind) at once, counts
the ones that follow within ``interval_s`` without formatting them, and reports the count with
the next line for that key (or from ``flush()``, which a server calls periodically, so a burst
that stops is still reported once).

The number of keys is bounded (``max_keys``): when full, quiet keys are forgotten first, and a
client that still finds no room is counted under the client ``"*"`` (all other clients).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

OTHER_CLIENTS = "*"


@dataclass
class _Entry:
    emitted_at: float  # when the last line for this key was written
    level: int = logging.INFO
    held: int = 0  # events since that line, not written
    last: tuple[str, tuple[Any, ...]] = ("", ())  # the latest held event (msg, args)


class RateLimitedLog:
    """``log(level, client, kind, msg, *args)`` writes ``msg % args`` unless a line for
    ``(client, kind)`` was written less than ``interval_s`` ago; then it only counts it.

    ``clock`` is injectable for tests (monotonic seconds).
    """

    def __init__(self, logger: logging.Logger, interval_s: float = 60.0, max_keys: int = 256,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if interval_s <= 0 or max_keys < 1:
            raise ValueError("interval_s must be > 0 and max_keys >= 1")
        self.logger = logger
        self.interval_s = interval_s
        self.max_keys = max_keys
        self._clock = clock
        self._entries: dict[tuple[str, str], _Entry] = {}
        self.lines = 0  # lines written (for tests and diagnostics)
        self.events = 0  # events seen, written or not

    def log(self, level: int, client: str, kind: str, msg: str, *args: Any) -> bool:
        """Write or count one event; True when a line was written."""
        self.events += 1
        if not self.logger.isEnabledFor(level):
            return False
        now = self._clock()
        key = self._key(client, kind, now)
        entry = self._entries.get(key)
        if entry is not None and now - entry.emitted_at < self.interval_s:
            entry.held += 1
            entry.level = max(entry.level, level)
            entry.last = (msg, args)
            return False
        suffix = ""
        if entry is not None and entry.held:
            suffix = (f" (and {entry.held} more like it from {key[0]} in the last "
                      f"{now - entry.emitted_at:.0f} s)")
        self._entries[key] = _Entry(emitted_at=now, level=level)
        self._write(level, key, msg, args, suffix)
        return True

    def info(self, client: str, kind: str, msg: str, *args: Any) -> bool:
        return self.log(logging.INFO, client, kind, msg, *args)

    def warning(self, client: str, kind: str, msg: str, *args: Any) -> bool:
        return self.log(logging.WARNING, client, kind, msg, *args)

    def flush(self, force: bool = False) -> int:
        """Report held events whose interval is over (all of them with ``force``) and forget
        quiet keys; returns the number of lines written."""
        now = self._clock()
        written = 0
        for key, entry in list(self._entries.items()):
            if not force and now - entry.emitted_at < self.interval_s:
                continue
            if entry.held:
                msg, args = entry.last
                self._write(entry.level, key, msg, args,
                            f" ({entry.held} like it from {key[0]} in the last "
                            f"{now - entry.emitted_at:.0f} s; this is the latest)")
                written += 1
                self._entries[key] = _Entry(emitted_at=now, level=entry.level)
            else:
                del self._entries[key]
        return written

    def _key(self, client: str, kind: str, now: float) -> tuple[str, str]:
        key = (client, kind)
        if key in self._entries or len(self._entries) < self.max_keys:
            return key
        for old, entry in list(self._entries.items()):  # forget keys with nothing held
            if not entry.held and now - entry.emitted_at >= self.interval_s:
                del self._entries[old]
        if len(self._entries) < self.max_keys:
            return key
        return (OTHER_CLIENTS, kind)

    def _write(self, level: int, key: tuple[str, str], msg: str, args: tuple[Any, ...],
               suffix: str) -> None:
        text = msg % args if args else msg
        if key[0] == OTHER_CLIENTS:
            text = f"(other clients) {text}"
        self.logger.log(level, "%s%s", text, suffix)
        self.lines += 1
