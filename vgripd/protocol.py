"""The robot-link contract, with no I/O.

Every link driver (``drivers/links/*``) implements ``RobotLink``; the daemon talks to links only
through it. A link turns its peer's trigger into a ``Trigger`` and hands it to the daemon's
handler; the daemon answers through ``image_captured`` and ``publish``.

Publishing rule for register-based links: all result data first, the acknowledged sequence last,
so a poller never sees a new sequence with old or partial data.
"""

from __future__ import annotations

import enum
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

from pydantic import BaseModel

from vgripd.types import FloatArray, JobResult


class LinkState(enum.Enum):
    STOPPED = "stopped"
    CONNECTING = "connecting"
    UP = "up"
    DOWN = "down"  # lost; the supervisor is retrying with doubling back-off
    FAILED = "failed"  # cannot start (bad address, port in use, register IN_USE): not retried


@dataclass(frozen=True)
class LinkHealth:
    state: LinkState
    peer: str = ""
    last_error: str = ""
    reconnects: int = 0
    since_mono_ns: int = 0


@dataclass(frozen=True)
class Trigger:
    """A request from the robot side. ``seq`` is the peer's request sequence number.

    ``T_base_flange`` is the robot's flange/TCP pose at trigger time (mm) when the link can read
    it (RTDE), for robot-mounted cameras.
    """

    link: str
    seq: int
    command: int
    t_mono_ns: int
    T_base_flange: FloatArray | None = None


TriggerHandler = Callable[[Trigger], None]


class RobotLink(ABC):
    """Base of every link driver. ``__init__`` does no I/O."""

    Options: ClassVar[type[BaseModel]]

    def __init__(self, name: str, options: Any) -> None:
        self.name = name
        self.options = options

    @abstractmethod
    async def open(self, on_trigger: TriggerHandler) -> None:
        """Start serving; raise ``LinkError`` saying exactly why if it cannot start."""

    @abstractmethod
    async def close(self) -> None:
        """Stop serving and release sockets/ports/threads/processes."""

    @abstractmethod
    def health(self) -> LinkHealth: ...

    @abstractmethod
    async def image_captured(self, seq: int, job_id: int) -> None:
        """The job for ``seq`` has its images: the robot may move on."""

    @abstractmethod
    async def publish(self, seq: int, result: JobResult) -> None:
        """Publish a finished job atomically (data first, acknowledged sequence last)."""
