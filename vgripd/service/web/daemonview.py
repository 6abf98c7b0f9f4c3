"""The daemon as the web view and its metrics read it.

The web view is built by the daemon and reads it back (status, links, recorder, counters). It
types the daemon by this protocol instead of importing ``vgripd.service.daemon``, so the two do
not import each other: the daemon sits above the web view and hands itself in.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping
from typing import Any, Protocol

from vgripd.config import Config
from vgripd.service.jobrecord import EpipolarMonitor, JobListener
from vgripd.service.protocol import RobotLink
from vgripd.service.recorder import Recorder
from vgripd.service.worker import WorkerRecorder


class DaemonView(Protocol):
    """What ``WebServer`` and ``Metrics`` use of ``vgripd.service.daemon.Daemon``."""

    config: Config

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
