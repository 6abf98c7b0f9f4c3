"""The daemon as the web view and its metrics read it.

The web view is built by the daemon and reads it back (status, links, recorder, counters). It
types the daemon by this protocol instead of importing ``vgripd.service.daemon``, so the two do
not import each other: the daemon sits above the web view and hands itself in.
"""

from __future__ import annotations

import enum
from collections import Counter
from collections.abc import Callable, Mapping, Set
from pathlib import Path
from typing import Any, Protocol

from vgripd.config import Config
from vgripd.service.jobs.jobrecord import EpipolarMonitor, JobListener
from vgripd.service.links.gate import Budget
from vgripd.service.links.protocol import RobotLink
from vgripd.service.ops.reload import Reloader
from vgripd.service.worker.camera import Camera
from vgripd.service.worker.process import WorkerRecorder
from vgripd.service.worker.recorder import Recorder


class WalksView(Protocol):
    """What the walk pages use of the daemon's hand-eye walk (``vgripd.service.jobs.walkmode``)."""

    solution: dict[str, Any] | None

    @property
    def listeners(self) -> list[Callable[[dict[str, Any]], None]]: ...

    @property
    def walking(self) -> bool: ...

    def snapshot(self) -> dict[str, Any]: ...

    def start(self, config_path: Path, plan: str | Path, link_index: int) -> dict[str, Any]: ...

    async def stop(self, why: str = ...) -> dict[str, Any]: ...

    async def solve(self, config_path: Path) -> dict[str, Any]: ...


class DaemonView(Protocol):
    """What ``WebServer``, its routes and ``Metrics`` use of ``vgripd.service.daemon.Daemon``
    (the job and run states as plain enums: their classes live above this module)."""

    config: Config
    reloader: Reloader | None

    @property
    def camera(self) -> Camera: ...

    @property
    def state(self) -> enum.Enum: ...

    @property
    def views(self) -> object | None: ...

    @property
    def run_state(self) -> enum.Enum: ...

    @property
    def walks(self) -> WalksView: ...

    @property
    def untaught(self) -> Set[int]: ...

    @property
    def recipe_problems(self) -> Mapping[int, str]: ...

    @property
    def fd_budget(self) -> Budget | None: ...

    @property
    def listeners(self) -> list[JobListener]: ...

    @property
    def record_dropped(self) -> int: ...

    @property
    def epipolar(self) -> EpipolarMonitor: ...

    @property
    def links(self) -> Mapping[str, RobotLink]: ...

    @property
    def recorder(self) -> Recorder | WorkerRecorder | None: ...

    @property
    def undelivered(self) -> Mapping[str, int]: ...

    def answered(self) -> tuple[Counter[str], Counter[str]]: ...

    def healthy(self) -> bool: ...

    def recipe_snapshot(self) -> dict[str, Any]: ...

    def snapshot(self) -> dict[str, Any]: ...
