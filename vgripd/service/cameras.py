"""Camera supervision: opening the camera (in the worker process by default, where the driver
then runs), grabbing with a deadline, recovery after a hung grab, and the systemd watchdog.

- Start-up opens the camera alongside the links. A camera that cannot open is not fatal: the
  next job tries again and answers ``CAMERA_ERROR`` meanwhile. One whose open hangs longer
  than ``open_timeout_s`` is a camera fault.
- A grab that runs out of time and still hangs in the driver is abandoned and the camera opened
  again; if that fails or hangs too, ``fault`` says why and the watchdog stops pinging
  (``Daemon.health_problem``), so systemd restarts the service.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import time
from collections.abc import Callable
from typing import Any

from vgripd.config import Config
from vgripd.errors import CameraError
from vgripd.service.protocol import Trigger
from vgripd.service.sdnotify import Notifier
from vgripd.service.tasks import Background
from vgripd.types import CaptureView, ImagePair

log = logging.getLogger("vgripd")

# Opening the camera longer than this is a hang (the daemon's ``camera_open_timeout_s``).
CAMERA_OPEN_TIMEOUT_S = 30.0
# Closing a camera that hung (its driver abandons a stuck thread; the worker's close is bounded).
CAMERA_CLOSE_TIMEOUT_S = 10.0
# A grab that ran out of time and is still running this much later is hung, not just late.
CAMERA_HUNG_GRACE_S = 1.0


class CameraSupervisor:
    """The camera, whether it is open, and why not.

    ``changed`` is called when the status line should show a change (open again, a fault).
    """

    def __init__(self, config: Config, camera: Any, background: Background, *,
                 changed: Callable[[], None]) -> None:
        self.config = config
        self.camera = camera
        self.is_open = False
        self.error = ""  # why the last open failed
        #: Why the camera cannot be used any more (a grab hung and opening it again failed or
        #: hung too): the watchdog stops pinging, so systemd restarts the service.
        self.fault = ""
        self.open_timeout_s = CAMERA_OPEN_TIMEOUT_S
        self._lock = asyncio.Lock()  # one open/close of the camera at a time
        self._recovery: asyncio.Task[None] | None = None
        self._background = background
        self._changed = changed
        #: Whether the service takes jobs (no recovery while stopping; set by the daemon).
        self.accepting = False

    async def open(self, fault_on_hang: bool = True) -> None:
        """Open the camera unless it is open; one open at a time. A camera that cannot open is
        not fatal (the next job tries again and answers CAMERA_ERROR meanwhile); one whose
        open hangs longer than ``open_timeout_s`` is a camera fault (``fault_on_hang``;
        otherwise the caller judges it by ``error``)."""
        async with self._lock:
            if self.is_open:
                return
            kind = self.name()
            try:
                async with asyncio.timeout(self.open_timeout_s):
                    await self.camera.open()
            except TimeoutError:
                self.error = (f"opening it hung for more than "
                              f"{self.open_timeout_s:g} s")
                if fault_on_hang:
                    self._set_fault(f"camera {kind}: {self.error}")
                return
            except CameraError as err:
                self.error = str(err)
                log.error("camera %s cannot open: %s", kind, err)
                return
            self.is_open = True
            self.error = ""
            log.info("camera %s open", kind)

    async def close(self) -> None:
        if self.is_open:
            try:
                await self.camera.close()
            except Exception:
                log.exception("camera: close failed")
            self.is_open = False

    def name(self) -> str:
        return str(getattr(self.camera, "type_name", "") or self.config.camera.type)

    def _set_fault(self, why: str) -> None:
        self.fault = why
        log.error("%s: the camera is unusable; the watchdog stops pinging so that systemd "
                  "restarts vgripd", why)
        self._changed()  # status line and waiters see it

    def _ran_out(self, waited_s: float) -> None:
        """A grab did not deliver in time: check in the background whether it hangs."""
        if not self.accepting:
            return
        if self._recovery is None or self._recovery.done():
            self._recovery = self._background.spawn(self._recover(waited_s),
                                                    name="vgripd-camera-recovery")

    async def _recover(self, waited_s: float) -> None:
        """After a grab ran out of time: if the driver's call still hangs (or, in the worker
        process, cannot be seen), abandon it and open the camera again; when that fails or
        hangs too, the camera is faulty (``fault``) and the watchdog stops."""
        camera, kind = self.camera, self.name()
        stuck_s = getattr(camera, "stuck_s", None)
        if callable(stuck_s):
            await asyncio.sleep(CAMERA_HUNG_GRACE_S)  # a late grab may still return meanwhile
            if stuck_s() == 0:
                return
            what = f"a grab has been stuck in the driver for {stuck_s():.1f} s"
        else:
            what = f"no image within {waited_s:.1f} s"
        log.error("camera %s: %s; closing it and opening it again", kind, what)
        async with self._lock:
            self.is_open = False
            try:
                async with asyncio.timeout(CAMERA_CLOSE_TIMEOUT_S):
                    await camera.close()
            except (TimeoutError, CameraError) as err:
                log.warning("camera %s: close after the hang failed: %r", kind, err)
        await self.open(fault_on_hang=False)
        if self.is_open:
            log.info("camera %s open again after the hang", kind)
            self._changed()  # status line and waiters see it
        elif not self.fault:
            self._set_fault(f"camera {kind}: {what}, and opening it again failed: "
                            f"{self.error}")

    async def acquire(self, trigger: Trigger, deadline_ns: int,
                      view: CaptureView | None = None) -> ImagePair:
        """One grab for ``trigger`` within ``deadline_ns``, with the flange pose it (or the
        view) carries; ``CameraError`` when the camera is faulty, not open or fails."""
        recovery = self._recovery
        if recovery is not None and not recovery.done():
            await asyncio.shield(recovery)  # the camera is being opened again
        if self.fault:
            raise CameraError(f"camera {self.config.camera.type} is unusable: "
                              f"{self.fault}")
        if not self.is_open:
            await self.open()
            if not self.is_open:
                raise CameraError(f"camera {self.config.camera.type} is not open")
        remaining_s = max(0.0, (deadline_ns - time.monotonic_ns()) / 1e9)
        t0 = time.monotonic()
        try:
            # Only a view or a recipe passes its hint: any driver (or stand-in) of the
            # one-image contract keeps working unchanged.
            hints: dict[str, Any] = {"view": view} if view is not None else {}
            if trigger.recipe:
                hints["recipe"] = trigger.recipe
            pair: ImagePair = await self.camera.grab(remaining_s, **hints)
        except (CameraError, asyncio.CancelledError):
            waited_s = time.monotonic() - t0
            if remaining_s > 0 and waited_s >= 0.9 * remaining_s:  # out of time: hung?
                self._ran_out(waited_s)
            raise
        flange = trigger.T_base_flange if view is None else view.T_base_flange
        if pair.T_base_flange is None and flange is not None:
            pair = dataclasses.replace(pair, T_base_flange=flange)
        return pair


async def watchdog(period_s: float, health_problem: Callable[[], str],
                   notifier: Notifier) -> None:
    """Ping systemd's watchdog every ``period_s`` while ``health_problem()`` is "" (healthy);
    logged once when it stops, once when it pings again."""
    unhealthy = False
    while True:
        problem = health_problem()
        if not problem:
            notifier.watchdog()
            if unhealthy:
                log.info("watchdog: healthy again, pinging systemd")
        elif not unhealthy:
            log.error("watchdog: not pinging systemd (it will restart vgripd): %s", problem)
        unhealthy = bool(problem)
        await asyncio.sleep(period_s)
