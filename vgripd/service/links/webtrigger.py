"""The web view's 'test trigger' as a link: a job started from the browser goes through the
daemon's own trigger path (BUSY while a job runs, counted, recorded, published) and its answer
comes back here instead of to a PLC, so no robot ever sees a test job's result.

The daemon adds it to its links (named ``WEB_LINK``) only when ``status.allow_trigger`` is set.
"""

from __future__ import annotations

import asyncio
import time
from typing import ClassVar

from pydantic import BaseModel

from vgripd.registry import LinkCapabilities
from vgripd.service.links.protocol import LinkHealth, LinkState, RobotLink, Trigger, TriggerHandler
from vgripd.types import JobResult, Status

WEB_LINK = "web"


class _NoOptions(BaseModel):
    pass


class WebTriggerLink(RobotLink):
    """Triggers from ``POST /api/trigger``; each waits for its own answer by ``seq``."""

    Options: ClassVar[type[BaseModel]] = _NoOptions
    # Results stay in the process: any convention, any number of values.
    capabilities: ClassVar[LinkCapabilities] = LinkCapabilities(max_values=1 << 16)

    def __init__(self, name: str = WEB_LINK) -> None:
        super().__init__(name, _NoOptions())
        self._on_trigger: TriggerHandler | None = None
        self._seq = 0
        self._waiting: dict[int, asyncio.Future[JobResult]] = {}
        self._state = LinkState.STOPPED

    async def open(self, on_trigger: TriggerHandler) -> None:
        self._on_trigger = on_trigger
        self._state = LinkState.UP
        self.health_changed()

    async def close(self) -> None:
        self._state = LinkState.STOPPED
        self.health_changed()
        for fut in self._waiting.values():
            fut.cancel()
        self._waiting.clear()

    def health(self) -> LinkHealth:
        return LinkHealth(state=self._state, peer="web view")

    async def image_captured(self, seq: int, job_id: int) -> None:
        pass

    async def publish(self, seq: int, result: JobResult) -> Status:
        fut = self._waiting.pop(seq, None)
        if fut is not None and not fut.done():
            fut.set_result(result)
        return result.status

    async def trigger(self, timeout_s: float, recipe: int = 0) -> JobResult:
        """Start a job of ``recipe`` and wait for its answer (a BUSY refusal is an answer
        too)."""
        if self._on_trigger is None or self._state is not LinkState.UP:
            raise RuntimeError("the web trigger link is not open")
        self._seq += 1
        seq = self._seq
        fut: asyncio.Future[JobResult] = asyncio.get_running_loop().create_future()
        self._waiting[seq] = fut
        try:
            self._on_trigger(Trigger(link=self.name, seq=seq, command=1,
                                     t_mono_ns=time.monotonic_ns(), recipe=recipe))
            async with asyncio.timeout(timeout_s):
                return await fut
        finally:
            self._waiting.pop(seq, None)
