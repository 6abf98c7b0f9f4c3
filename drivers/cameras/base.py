"""The camera driver contract shared by every acquisition back end.

A driver is built from its validated options and the whole vgripd config (``__init__`` does no
I/O), then ``await open()``, any number of ``await grab(timeout_s)``, ``await close()``.
``grab`` takes an optional ``recipe``: the recipe the job is for, a hint only a simulated camera
uses (the synthetic camera with ``recipe = "job"`` renders that recipe's object, so one daemon
can show each recipe's plate in turn); a real camera ignores it, as it sees whatever lies in the
cell. A driver that wants it overrides ``_grab_for`` instead of ``_grab_blocking``.
All blocking work (file reads, device SDK calls, rendering) runs on the driver's own
single-thread executor: the event loop keeps serving the robot link while a frame is read, and
SDK handles that are not thread-safe are only ever touched from that one thread.
Every failure a driver expects (timeout, missing file, corrupt image, device gone) is a
``CameraError`` naming the file or device.

A device call that never returns (a hung SDK) cannot be interrupted from Python. The executor's
thread is therefore a daemon thread (``DriverThread``): ``grab`` times out, ``stuck_s()`` says
how long the call has been running, and ``close()`` abandons a stuck thread instead of queueing
the close behind it (the daemon then opens the camera again on a fresh thread: docs/cameras.md,
"A camera that hangs"). An abandoned thread never keeps the process from exiting.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import queue
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from typing import Any, ClassVar, TypeVar

from pydantic import BaseModel, ConfigDict

from vgripd.config import Config
from vgripd.errors import CameraError, CameraSettingError
from vgripd.types import CaptureView, ImagePair

R = TypeVar("R")

#: Threads a driver uses for the cameras of one multi-camera acquisition.
MAX_HELPERS = 8


class DriverThread:
    """A single-thread executor on a daemon thread: calls run one at a time, in order.

    Unlike ``ThreadPoolExecutor`` (whose threads the interpreter joins at exit), a thread stuck
    in a device call forever does not keep the process alive; ``shutdown(wait=False)`` leaves it
    behind. ``running_since`` is the monotonic time the current call started (None when idle).
    """

    def __init__(self, name: str) -> None:
        self._calls: queue.SimpleQueue[tuple[concurrent.futures.Future[Any], Callable[..., Any],
                                             tuple[Any, ...]] | None] = queue.SimpleQueue()
        self.running_since: float | None = None
        self._shut = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    @property
    def name(self) -> str:
        return self._thread.name

    def submit(self, fn: Callable[..., R], *args: Any) -> concurrent.futures.Future[R]:
        if self._shut:
            raise RuntimeError(f"{self.name}: shut down")
        future: concurrent.futures.Future[R] = concurrent.futures.Future()
        self._calls.put((future, fn, args))
        return future

    def _run(self) -> None:
        while (item := self._calls.get()) is not None:
            future, fn, args = item
            if not future.set_running_or_notify_cancel():
                continue
            self.running_since = time.monotonic()
            try:
                result = fn(*args)
            except BaseException as err:
                self.running_since = None  # before the waiter wakes: it may ask stuck_s()
                future.set_exception(err)
            else:
                self.running_since = None
                future.set_result(result)

    def shutdown(self, wait: bool = True, cancel_futures: bool = False) -> None:
        """No more calls; pending ones are cancelled with ``cancel_futures``; ``wait`` joins."""
        self._shut = True
        if cancel_futures:
            with contextlib.suppress(queue.Empty):
                while True:
                    item = self._calls.get_nowait()
                    if item is not None:
                        item[0].cancel()
        self._calls.put(None)
        if wait:
            self._thread.join()


class DriverOptions(BaseModel):
    """Base of each driver's ``Options``: unknown keys are errors (typos name their field)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class CameraDriver(ABC):
    """One image source delivering ``ImagePair`` values.

    Subclasses set ``Options`` (validated by ``vgripd.registry.validate_options``) and implement
    the blocking hooks; the async methods here run them on the driver's executor.
    """

    Options: ClassVar[type[DriverOptions]]
    #: The registry type name, used in messages and ``ImagePair.source``.
    type_name: ClassVar[str]
    #: Why a camera of this type has no focus to drive (a driver with one overrides
    #: ``_focus_blocking``): the setup page shows it.
    no_focus: ClassVar[str] = "this camera type has no focus control"

    def __init__(self, options: Any, config: Config) -> None:
        self.options = options
        self.config = config
        #: The view of a several-view job being grabbed (``grab``'s ``view``), or None.
        self.view: CaptureView | None = None
        self._executor: DriverThread | None = None
        self._helpers: concurrent.futures.ThreadPoolExecutor | None = None

    # ---------------------------------------------------------------- async API
    async def open(self) -> None:
        """Connect to the device or index the files; raises ``CameraError`` naming them."""
        if self._executor is not None:
            raise CameraError(f"{self.type_name}: camera is already open")
        self._executor = DriverThread(f"camera-{self.type_name}")
        try:
            await self._run(self._open_blocking)
        except BaseException:
            await self.close()
            raise

    async def grab(self, timeout_s: float, view: CaptureView | None = None,
                   recipe: int = 0) -> ImagePair:
        """Acquire one image pair (or single image); ``CameraError`` after ``timeout_s``.

        ``view``: the view of a several-view job this image is (``self.view`` while the
        blocking hook runs); ``recipe``: the recipe of the job (0 = the top-level config).
        Both are hints that drivers of real cameras ignore (see the module docstring)."""
        if timeout_s <= 0:
            raise CameraError(f"{self.type_name}: grab timeout must be > 0 s, got {timeout_s}")
        self.view = view
        try:
            return await asyncio.wait_for(self._run(self._grab_for, timeout_s, recipe),
                                          timeout_s)
        except TimeoutError:
            raise CameraError(
                f"{self.type_name}: no image from {self.describe()} within {timeout_s:g} s"
            ) from None

    async def set_settings(self, exposure_us: float | None, gain_db: float | None
                           ) -> dict[str, Any]:
        """Change exposure (us) and gain (dB) of the open camera between jobs (None: leave
        it), with the checks ``open`` makes; returns what the device reads back per camera.
        ``CameraSettingError`` names the camera, the feature and the device's range. Optional:
        a driver without the hook refuses."""
        return await self._run(self._settings_blocking, exposure_us, gain_db)

    async def focus(self, value: float | None) -> dict[str, Any]:
        """The lens focus where the camera has a focus control: ``value`` None reads it, else
        it is written (between jobs: the caller's part) and read back. ``{"available": False,
        "reason": ...}`` where there is none; per camera ``name``, ``feature``, ``value`` and
        ``range`` where there is. A refused value raises ``CameraSettingError`` naming the
        camera, the feature and the range."""
        return await self._run(self._focus_blocking, value)

    def stuck_s(self) -> float:
        """How long the executor's current call has been running (s); 0 when it is idle.

        After a ``grab`` timed out, a value that keeps growing means the device call hangs."""
        since = self._executor.running_since if self._executor is not None else None
        return 0.0 if since is None else time.monotonic() - since

    async def close(self) -> None:
        """Release the device and stop the executor thread; safe to call more than once.

        A thread stuck in a device call is abandoned (the close could only queue behind it):
        the device is then released when the process exits."""
        executor, self._executor = self._executor, None
        if executor is None:
            return
        helpers, self._helpers = self._helpers, None
        if helpers is not None:  # idle between grabs: its threads end at once
            helpers.shutdown(wait=executor.running_since is None, cancel_futures=True)
        if executor.running_since is not None:
            executor.shutdown(wait=False, cancel_futures=True)
            return
        future = asyncio.wrap_future(executor.submit(self._close_blocking))
        try:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(asyncio.shield(future), 5.0)
        finally:
            # No work is pending any more (unless a device hangs), so the join is immediate.
            executor.shutdown(wait=future.done(), cancel_futures=True)

    # ---------------------------------------------------------------- blocking hooks
    def _open_blocking(self) -> None:  # noqa: B027 - optional hook
        """Runs on the executor in ``open()``."""

    @abstractmethod
    def _grab_blocking(self, timeout_s: float) -> ImagePair:
        """Runs on the executor in ``grab()``; returns one acquisition."""

    def _grab_for(self, timeout_s: float, recipe: int) -> ImagePair:
        """Runs on the executor in ``grab()``: a driver that uses the recipe hint overrides
        this; every other driver grabs what is in view."""
        return self._grab_blocking(timeout_s)

    def _settings_blocking(self, exposure_us: float | None, gain_db: float | None
                           ) -> dict[str, Any]:
        """Runs on the executor in ``set_settings``; a driver with live settings overrides."""
        raise CameraSettingError(f"{self.type_name}: this camera type has no exposure or gain "
                                 "to set")

    def _focus_blocking(self, value: float | None) -> dict[str, Any]:
        """Runs on the executor in ``focus``; a driver with a focus control overrides."""
        return {"available": False, "reason": f"{self.type_name}: {self.no_focus}"}

    def _close_blocking(self) -> None:  # noqa: B027 - optional hook
        """Runs on the executor in ``close()``; releases handles."""

    def describe(self) -> str:
        """The device or files this driver reads, for messages."""
        return self.type_name

    # ---------------------------------------------------------------- helpers
    def _per_camera(self, fn: Callable[[Any], R], items: Sequence[Any]) -> list[R]:
        """``fn`` over ``items`` (one per camera) concurrently, results in order; called from
        a blocking hook. A multi-camera acquisition takes all cameras' images at once: the
        time of one job is the slowest camera's, not the sum (image decoding, rendering and
        most device SDK calls release the GIL)."""
        if len(items) < 2:
            return [fn(item) for item in items]
        if self._helpers is None:
            self._helpers = concurrent.futures.ThreadPoolExecutor(
                max_workers=min(len(items), MAX_HELPERS),
                thread_name_prefix=f"camera-{self.type_name}-view")
        return list(self._helpers.map(fn, items))

    async def _run(self, fn: Callable[..., R], *args: Any) -> R:
        if self._executor is None:
            raise CameraError(f"{self.type_name}: camera is not open")
        return await asyncio.wrap_future(self._executor.submit(fn, *args))
