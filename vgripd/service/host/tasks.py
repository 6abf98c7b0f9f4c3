"""The daemon's background tasks (a link's warnings call, a NEXT's answer, a refusal, the camera
recovery, the watchdog), kept by strong reference so none is collected half way, and cancelled
together at shutdown. One set, shared by the rooms the daemon wires (links, cameras, jobs)."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Coroutine
from typing import Any


class Background:
    """Tasks that outlive the call that started them; ``cancel()`` ends them at shutdown."""

    def __init__(self) -> None:
        self.tasks: set[asyncio.Task[Any]] = set()

    def spawn(self, coro: Coroutine[Any, Any, Any], name: str | None = None) -> asyncio.Task[Any]:
        task = asyncio.create_task(coro, name=name)
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)
        return task

    async def cancel(self) -> None:
        """Cancel every task and wait until each has ended."""
        for task in list(self.tasks):
            task.cancel()
        for task in list(self.tasks):
            with contextlib.suppress(asyncio.CancelledError):
                await task
