"""The daemon as the web view and its metrics read it.

The web view is built by the daemon and reads it back: its rooms by name (``rooms``: links,
cameras, jobs, walks, ...) and what is the daemon's own (run state, recipes that cannot run,
health, snapshot). It types the daemon by this protocol instead of importing
``vgripd.service.daemon``, so the two do not import each other: the daemon sits above the web
view and hands itself in.
"""

from __future__ import annotations

import enum
from collections import Counter
from collections.abc import Mapping, Set
from typing import Any, Protocol

from vgripd.config import Config
from vgripd.service.ops.reload import Reloader
from vgripd.service.ops.rooms import Rooms


class DaemonView(Protocol):
    """What ``WebServer``, its routes and ``Metrics`` use of ``vgripd.service.daemon.Daemon``
    (the run state as a plain enum: its class lives above this module)."""

    config: Config
    reloader: Reloader | None
    changes: int  # state changes so far

    @property
    def rooms(self) -> Rooms: ...

    @property
    def run_state(self) -> enum.Enum: ...

    @property
    def untaught(self) -> Set[int]: ...

    @property
    def recipe_problems(self) -> Mapping[int, str]: ...

    def answered(self) -> tuple[Counter[str], Counter[str]]: ...

    def healthy(self) -> bool: ...

    def recipe_snapshot(self) -> dict[str, Any]: ...

    def snapshot(self) -> dict[str, Any]: ...

    async def next_change(self, seen: int) -> int: ...
