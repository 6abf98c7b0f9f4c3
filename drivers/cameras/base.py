"""The camera driver contract shared by every acquisition back end.

A driver is built from its validated options and the whole vgripd config (``__init__`` does no
I/O), then ``await open()``, any number of ``await grab(timeout_s)``, ``await close()``.
All blocking work (file reads, device SDK calls, rendering) runs on the driver's own
single-thread executor: the event loop keeps serving the robot link while a frame is read, and
SDK handles that are not thread-safe are only ever touched from that one thread.
Every failure a driver expects (timeout, missing file, corrupt image, device gone) is a
``CameraError`` naming the file or device.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Any, ClassVar, TypeVar

from pydantic import BaseModel, ConfigDict

from vgripd.config import Config
from vgripd.errors import CameraError
from vgripd.types import ImagePair

R = TypeVar("R")


class DriverOptions(BaseModel):
    """Base of each driver's ``Options``: unknown keys are errors (typos name their field)."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class CameraDriver(ABC):
    """One image source delivering ``ImagePair`` values.

    Subclasses set ``Options`` (validated by ``vgripd.registry.validate_options``) and implement
    the blocking hooks; the async methods here run them on the driver's executor.
    """

    Options: ClassVar[type[DriverOptions]]
    #: The registry type name, used in messages and ``ImagePair.source``.
    type_name: ClassVar[str]

    def __init__(self, options: Any, config: Config) -> None:
        self.options = options
        self.config = config
        self._executor: concurrent.futures.ThreadPoolExecutor | None = None

    # ---------------------------------------------------------------- async API
    async def open(self) -> None:
        """Connect to the device or index the files; raises ``CameraError`` naming them."""
        if self._executor is not None:
            raise CameraError(f"{self.type_name}: camera is already open")
        self._executor = concurrent.futures.ThreadPoolExecutor(
            1, thread_name_prefix=f"camera-{self.type_name}"
        )
        try:
            await self._run(self._open_blocking)
        except BaseException:
            await self.close()
            raise

    async def grab(self, timeout_s: float) -> ImagePair:
        """Acquire one image pair (or single image); ``CameraError`` after ``timeout_s``."""
        if timeout_s <= 0:
            raise CameraError(f"{self.type_name}: grab timeout must be > 0 s, got {timeout_s}")
        try:
            return await asyncio.wait_for(self._run(self._grab_blocking, timeout_s), timeout_s)
        except TimeoutError:
            raise CameraError(
                f"{self.type_name}: no image from {self.describe()} within {timeout_s:g} s"
            ) from None

    async def close(self) -> None:
        """Release the device and stop the executor thread; safe to call more than once."""
        executor, self._executor = self._executor, None
        if executor is None:
            return
        try:
            future = asyncio.wrap_future(executor.submit(self._close_blocking))
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(future, 5.0)
        finally:
            # No work is pending any more (unless a device hangs), so the join is immediate.
            executor.shutdown(wait=future.done(), cancel_futures=True)

    # ---------------------------------------------------------------- blocking hooks
    def _open_blocking(self) -> None:  # noqa: B027 - optional hook
        """Runs on the executor in ``open()``."""

    @abstractmethod
    def _grab_blocking(self, timeout_s: float) -> ImagePair:
        """Runs on the executor in ``grab()``; returns one acquisition."""

    def _close_blocking(self) -> None:  # noqa: B027 - optional hook
        """Runs on the executor in ``close()``; releases handles."""

    def describe(self) -> str:
        """The device or files this driver reads, for messages."""
        return self.type_name

    # ---------------------------------------------------------------- helpers
    async def _run(self, fn: Callable[..., R], *args: Any) -> R:
        if self._executor is None:
            raise CameraError(f"{self.type_name}: camera is not open")
        return await asyncio.wrap_future(self._executor.submit(fn, *args))
