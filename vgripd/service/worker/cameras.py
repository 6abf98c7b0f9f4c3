"""Camera supervision: opening the camera (in the worker process by default, where the driver
then runs), grabbing with a deadline, recovery after a hung grab, and the systemd watchdog.

- Start-up opens the camera alongside the links. A camera that cannot open is not fatal: the
  next job tries again and answers ``CAMERA_ERROR`` meanwhile. One whose open hangs longer
  than ``open_timeout_s`` is a camera fault.
- A grab that runs out of time and still hangs in the driver is abandoned and the camera opened
  again; if that fails or hangs too, ``fault`` says why and the watchdog stops pinging
  (``Daemon.health_problem``), so systemd restarts the service.
- The worker process died while it held the camera (``lost``): the camera is opened again in
  the new worker at once, in the background, with back-off until it opens, so the next job
  finds it open (a GigE camera first waits out the dead process's control channel).
- The web view's pages grab between jobs through ``grab_for_page``: the page waits its own
  short time, the grab is given a job's and judged by the same rule (a slow camera is never
  taken for a hung one), a job waits for it, a one-off failure marks nothing.
- ``down`` says why no job can get a frame: the camera was lost with its worker and is not
  open again yet, or ``DOWN_AFTER_FAILURES`` grabs in a row failed. Cleared when the camera is
  open again or a grab delivers. The daemon's health reports it at once; the watchdog stops
  only when it lasts longer than ``daemon.camera_down_restart_s``.
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
from vgripd.service.host.sdnotify import Notifier
from vgripd.service.host.tasks import Background
from vgripd.service.links.protocol import Trigger
from vgripd.service.worker.camera import Camera
from vgripd.types import CaptureView, ImagePair

log = logging.getLogger("vgripd")

# Opening the camera longer than this is a hang (the daemon's ``camera_open_timeout_s``).
CAMERA_OPEN_TIMEOUT_S = 30.0
# Closing a camera that hung (its driver abandons a stuck thread; the worker's close is bounded).
CAMERA_CLOSE_TIMEOUT_S = 10.0
# A grab that ran out of time and is still running this much later is hung, not just late.
CAMERA_HUNG_GRACE_S = 1.0
# Grabs in a row that failed before the camera counts as down (one failure may be one lost
# frame; the GenICam drivers reopen a camera after as many grabs without a frame).
DOWN_AFTER_FAILURES = 2
# Stopping: a page's grab still running is given this long to end, as the web view's requests
# are (then it is cancelled, as a job's grab is at shutdown).
PAGE_GRAB_STOP_WAIT_S = 1.0
# Opening the camera again after its worker died: first retry after the first, doubling up to
# the second (seconds).
REOPEN_BACKOFF_S = (0.5, 8.0)


class CameraSupervisor:
    """The camera, whether it is open, and why not.

    ``changed`` is called when the status line should show a change (open again, a fault).
    """

    def __init__(self, config: Config, camera: Camera, background: Background, *,
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
        self._reopening: asyncio.Task[None] | None = None
        self._page_grab: asyncio.Task[ImagePair] | None = None  # the web view's, see grab_for_page
        #: Why no job can get a frame now ("" while grabs can deliver); since when (monotonic).
        self.down = ""
        self.down_since = 0.0
        self._failures = 0  # grabs in a row that failed
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
        await self._end_page_grab()
        if self.is_open:
            try:
                await self.camera.close()
            except Exception:
                log.exception("camera: close failed")
            self.is_open = False

    def name(self) -> str:
        return self.camera.type_name or self.config.camera.type

    # --- whether a job can get a frame ---------------------------------------------------

    def down_problem(self, longer_than_s: float = 0.0) -> str:
        """``down`` with how long it has lasted ("" when not down, or down for no longer than
        ``longer_than_s``: then named as the limit ``daemon.camera_down_restart_s``)."""
        down_s = self.down_for_s()
        if not self.down or (longer_than_s and down_s <= longer_than_s):
            return ""
        return (f"camera {self.name()}: no frame for {down_s:.1f} s: {self.down}"
                + (f" (longer than daemon.camera_down_restart_s = {longer_than_s:g} s)"
                   if longer_than_s else ""))

    def down_for_s(self) -> float:
        return time.monotonic() - self.down_since if self.down else 0.0

    def _set_down(self, why: str) -> None:
        if not self.down:
            self.down_since = time.monotonic()
            log.error("camera %s: no job can get a frame: %s", self.name(), why)
        self.down = why
        self._changed()

    def _up(self, how: str) -> None:
        self._failures = 0
        if self.down:
            log.info("camera %s: %s, %.1f s after it went down (%s)", self.name(), how,
                     time.monotonic() - self.down_since, self.down)
            self.down = ""
            self._changed()

    def _grab_failed(self, err: BaseException) -> None:
        self._failures += 1
        if self._failures >= DOWN_AFTER_FAILURES and self.accepting:
            self._set_down(f"{self._failures} grabs in a row failed, the last: "
                           f"{str(err) or type(err).__name__}")

    def lost(self, reason: str) -> None:
        """The worker process that held the camera died (``reason``): open it again in the
        new one now, in the background, with back-off until it opens."""
        if not self.accepting:
            return
        self.is_open = False
        self._set_down(f"{reason}; opening the camera again in a new worker process")
        if self._reopening is None or self._reopening.done():
            self._reopening = self._background.spawn(self._reopen_lost(),
                                                     name="vgripd-camera-reopen")

    async def _reopen_lost(self) -> None:
        delay_s, (first_s, max_s) = 0.0, REOPEN_BACKOFF_S
        while self.accepting and not self.fault:
            await asyncio.sleep(delay_s)
            await self.open()
            if self.is_open:
                self._up("open again in the new worker process")
                return
            if self.down:  # the reason now: why the open failed
                self.down = f"opening it again failed: {self.error}"
            delay_s = min(max_s, max(first_s, 2 * delay_s))

    def _set_fault(self, why: str) -> None:
        self.fault = why
        log.error("%s: the camera is unusable; the watchdog stops pinging so that systemd "
                  "restarts vgripd", why)
        self._changed()  # status line and waiters see it

    def _judge_late(self, waited_s: float, timeout_s: float) -> None:
        """A grab given ``timeout_s`` failed after ``waited_s``: when it ran out of its time,
        check whether the camera hangs (the one rule for a job's grab and a page's)."""
        if timeout_s > 0 and waited_s >= 0.9 * timeout_s:
            self._ran_out(waited_s)

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
        if camera.stuck_s() is not None:  # the driver runs here: its call can be seen
            await asyncio.sleep(CAMERA_HUNG_GRACE_S)  # a late grab may still return meanwhile
            stuck_s = camera.stuck_s()
            if not stuck_s:
                return
            what = f"a grab has been stuck in the driver for {stuck_s:.1f} s"
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
        view) carries; ``CameraError`` when the camera is faulty, not open or fails. A page's
        grab still running is waited for first (within the job's time)."""
        await self._after_page_grab(deadline_ns)
        recovery = self._recovery
        if recovery is not None and not recovery.done():
            await asyncio.shield(recovery)  # the camera is being opened again
        if self.fault:
            raise CameraError(f"camera {self.config.camera.type} is unusable: "
                              f"{self.fault}")
        if not self.is_open:
            await self.open()
            if not self.is_open:
                err = CameraError(f"camera {self.config.camera.type} is not open")
                self._grab_failed(CameraError(self.error or str(err)))
                raise err
        remaining_s = max(0.0, (deadline_ns - time.monotonic_ns()) / 1e9)
        t0 = time.monotonic()
        try:
            # Only a view or a recipe passes its hint: any driver (or stand-in) of the
            # one-image contract keeps working unchanged.
            hints: dict[str, Any] = {"view": view} if view is not None else {}
            if trigger.recipe:
                hints["recipe"] = trigger.recipe
            pair: ImagePair = await self.camera.grab(remaining_s, **hints)
        except (CameraError, asyncio.CancelledError) as err:
            self._grab_failed(err)
            self._judge_late(time.monotonic() - t0, remaining_s)
            raise
        except Exception as err:  # the worker process died during the grab, twice
            self._grab_failed(err)
            raise
        self._up("a grab delivered again")
        flange = trigger.T_base_flange if view is None else view.T_base_flange
        if pair.T_base_flange is None and flange is not None:
            pair = dataclasses.replace(pair, T_base_flange=flange)
        return pair

    # --- the web view's grabs between jobs ---------------------------------------------

    def grab_timeout_s(self) -> float:
        """The longest a page's grab may take before it counts as run out: a job's whole time
        (``daemon.job_timeout_s``), the most a job's grab is given."""
        return float(self.config.daemon.job_timeout_s)

    async def grab_for_page(self, wait_s: float, *, fresh: bool = False) -> ImagePair:
        """One grab for a page of the web view between jobs (preview, trial, setup), waited
        for ``wait_s`` at most: the pages grab through here, so the camera has one owner.

        The grab itself is given ``grab_timeout_s()`` and judged as a job's is: only when it
        runs out of that time is the camera checked for a hang (a hung camera is opened again,
        or found faulty, whoever grabbed). A page that stops waiting earlier gets
        ``CameraError`` ("busy") while the grab goes on; the next page's call takes that same
        grab rather than starting another, and a job waits for it (one grab at a time). A
        failure does not count towards ``down`` (a page's one-off failure marks nothing for
        the jobs); a delivered frame clears it. ``CameraError`` also when the camera is
        faulty, not open, being opened again or fails.

        ``fresh``: the frame must be exposed after this call (a trial, a calibration set taken
        with the robot's pose): a grab already running is waited out, not taken, and a new
        one started, all within ``wait_s``."""
        t_end = time.monotonic() + wait_s
        grab = self._page_grab
        if fresh and grab is not None and not grab.done():
            await asyncio.wait({grab}, timeout=wait_s)
            if not grab.done():
                raise CameraError(f"camera {self.name()} is busy: an earlier grab for the web "
                                  f"view did not end within {wait_s:g} s")
            wait_s = max(0.0, t_end - time.monotonic())
            grab = self._page_grab  # one another page started meanwhile began after this call
        if grab is None or grab.done():
            recovery = self._recovery
            if recovery is not None and not recovery.done():
                raise CameraError(f"camera {self.name()}: being opened again after a hang")
            if self.fault:
                raise CameraError(f"camera {self.name()} is unusable: {self.fault}")
            if not self.is_open:
                raise CameraError(f"camera {self.name()} is not open"
                                  + (f": {self.error}" if self.error else ""))
            # Not a background task: it may end its device call at shutdown (``close``).
            grab = asyncio.create_task(self._page_grab_run(), name="vgripd-page-grab")
            grab.add_done_callback(_seen)
            self._page_grab = grab
        await asyncio.wait({grab}, timeout=wait_s)  # never cancels the grab
        if not grab.done():
            raise CameraError(f"camera {self.name()} is busy: no image within the page's "
                              f"{wait_s:g} s (the grab goes on, for up to daemon.job_timeout_s"
                              f" = {self.grab_timeout_s():g} s)")
        pair: ImagePair = grab.result()
        return pair

    async def _page_grab_run(self) -> ImagePair:
        timeout_s = self.grab_timeout_s()
        t0 = time.monotonic()
        try:
            pair: ImagePair = await self.camera.grab(timeout_s)
        except CameraError:
            self._judge_late(time.monotonic() - t0, timeout_s)
            raise
        self._up("a grab for the web view delivered")
        return pair

    async def _end_page_grab(self) -> None:
        """Stopping: a page's grab still running gets ``PAGE_GRAB_STOP_WAIT_S`` to end."""
        grab = self._page_grab
        if grab is None or grab.done():
            return
        await asyncio.wait({grab}, timeout=PAGE_GRAB_STOP_WAIT_S)
        grab.cancel()
        await asyncio.gather(grab, return_exceptions=True)

    async def _after_page_grab(self, deadline_ns: int) -> None:
        """A job's grab follows a page's grab still running (the camera takes one at a time),
        within the job's time; ``CameraError`` when the page's outlasts it."""
        grab = self._page_grab
        if grab is None or grab.done():
            return
        await asyncio.wait({grab}, timeout=max(0.0, (deadline_ns - time.monotonic_ns()) / 1e9))
        if not grab.done():
            err = CameraError(f"camera {self.name()}: a grab for the web view still ran at "
                              "the job's deadline")
            self._grab_failed(err)
            raise err


def _seen(task: asyncio.Task[Any]) -> None:
    """Mark a background grab's failure as read (the page that waited for it, if any, said
    it)."""
    if not task.cancelled():
        task.exception()


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
