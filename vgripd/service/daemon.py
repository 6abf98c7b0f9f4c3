"""The asyncio service: robot links in, one job at a time, results out. The composition root.

``Daemon`` builds and wires the rooms, each owning one job:

- ``links.LinkSupervisor``: the robot links, opened at once, the file budget, calls with a
  bound time (publish, image captured, warnings);
- ``cameras.CameraSupervisor``: opening the camera, grabbing, recovery after a hang (and
  ``cameras.watchdog``, the systemd watchdog pinged while ``health_problem()`` is "");
- ``jobs.JobRunner``: trigger admission (``jobcore.JobCore``), several-view capture,
  processing, publishing and refusing, the counters (its module docstring has the job rules);
- ``status.StatusBoard``: the status line and snapshot read from the others;
- ``walkmode.WalkMode``: a walked hand-eye calibration: its link's requests go to the walk,
  the others' are answered BUSY meanwhile (every trigger passes it first);
- ``travel.BeltTravel``: a conveyor with ``trigger = "travel"``: the belt's count in, a job
  every trigger distance (docs/conveyor.md, "Triggering by travel");
- ``web.WebServer``: the web view, /api/status, /metrics.

The daemon hands its rooms out by name (``rooms``, an ``ops.rooms.Rooms``): the web view, the
reload and tests read each room's state there (``daemon.rooms.jobs.counters``,
``daemon.rooms.cameras.fault``); the daemon keeps only what is its own: the lifecycle, the
recipes that cannot run, waiting on state, health and the snapshot.

A trigger goes link -> ``JobRunner.on_trigger`` -> camera -> worker -> link; the runner
reaches the daemon only through ``changed`` (the status line and ``wait_for``'s waiters).
Lifecycle (start, READY, stop, shutdown order) stays here.

- Grabbing, processing and recording run in a worker process (``vgripd.service.worker.process``:
  images through shared memory, the rest pickled), so the event loop's interpreter only
  handles links and state and answers a poll in about a millisecond while a job runs. A worker
  that dies is replaced: a job in its processing ends ``INTERNAL`` naming why ("worker process
  exited with signal 9 (SIGKILL)"), one in its grab is grabbed again on the new worker, and
  the camera it held is opened again in the new one at once (``CameraSupervisor.lost``).
  ``daemon.worker = false`` (or a ``Processor`` object passed in) keeps the old in-process
  path: driver thread, single-thread job executor.
- The recipes that cannot run (``recipe_problems``, ``untaught``) are judged at construction
  by ``vgripd.vision.readiness``, which builds no pipeline: the pipelines are built where they
  run, in the worker, or here, once, on the in-process path.
- Start-up opens the camera and every link at once (a silent controller delays no other link
  and not the status endpoint); a link that cannot start is shown FAILED while the others
  serve. READY=1 follows the first outcome of each.
- A grab that runs out of time and still hangs in the driver is abandoned and the camera opened
  again; if that fails or hangs too, ``rooms.cameras.fault`` says why and the watchdog stops pinging
  (``health_problem``), so systemd restarts the service.
- Shutdown (SIGTERM/SIGINT) aborts the job in flight (unless it is already publishing), so the
  PLC gets ``ABORTED`` for its trigger at once instead of waiting; the links stay up for
  ``ABORT_LINGER_S`` so a polling PLC can read it, then links, the camera, the recorder and the
  job thread or worker process are closed (the worker writes queued recordings first). A CPU
  step already running in the worker is ended by killing it; in-process it cannot be
  interrupted: the process exits when it ends, its result is discarded.
"""

from __future__ import annotations

import asyncio
import enum
import errno
import logging
import os
import time
from collections import Counter
from collections.abc import Callable, Mapping
from typing import Any

from vgripd.config import Config
from vgripd.registry import CAMERAS, load_class, validate_options
from vgripd.service.host.heap import freeze_start_up_heap
from vgripd.service.host.sdnotify import Notifier, watchdog_interval_s
from vgripd.service.host.tasks import Background
from vgripd.service.jobs.runner import JobRunner, Processor, recipe_label
from vgripd.service.jobs.travel import BeltTravel
from vgripd.service.jobs.walkmode import WalkMode
from vgripd.service.links.ratelog import RateLimitedLog
from vgripd.service.links.supervision import LinkSupervisor
from vgripd.service.ops.reload import Reloader
from vgripd.service.ops.rooms import Rooms
from vgripd.service.ops.status import StatusBoard
from vgripd.service.web.app import WebServer
from vgripd.service.worker.camera import Camera
from vgripd.service.worker.cameras import (
    CameraSupervisor,
    watchdog,
)
from vgripd.service.worker.process import DEFAULT_PROCESSOR, WorkerClient
from vgripd.service.worker.recorder import Recorder
from vgripd.vision.readiness import ready, recipe_readiness

log = logging.getLogger("vgripd")

# After publishing ABORTED on shutdown the links stay up this long, so that a polling PLC
# reads the answer to its trigger before the server goes away.
ABORT_LINGER_S = 1.0
# The watchdog stops pinging when a job runs this long past its timeout: the timeout should
# have ended it, so the job machinery is wedged and systemd should restart the service.
WATCHDOG_GRACE_S = 5.0


class RunState(enum.Enum):
    CREATED = "created"
    STARTING = "starting"
    RUNNING = "running"
    STOPPING = "stopping"
    STOPPED = "stopped"


def _in_process(config: Config) -> Processor:
    from vgripd.vision.checked import CheckedPipeline  # heavy (OpenCV); only in-process

    pipeline: Processor = CheckedPipeline(config)
    return pipeline


class Daemon:
    """One vgripd service instance. Construction validates drivers and judges each recipe
    (``vgripd.vision.readiness``; reading template files is its only I/O). It builds the
    pipelines only when they run in this process.

    Raises ``ConfigError`` for a bad driver type or options. A missing/invalid calibration
    (``NotCalibratedError``) does not stop the service: every job then answers
    ``NOT_CALIBRATED``, so the PLC sees why (``not_calibrated`` says so). The same holds per
    recipe: a recipe not taught yet answers ``NOT_CALIBRATED``, the others run.

    ``pipeline``: a ``Processor`` object runs in this process (on the job thread, camera
    included); a ``"module:Class"`` path names one built from the config in the worker process.
    Default: the vision ``Pipeline``, in the worker unless ``daemon.worker = false``.
    """

    def __init__(
        self,
        config: Config,
        *,
        pipeline: Processor | str | None = None,
        env: Mapping[str, str] | None = None,
    ) -> None:
        self.config = config
        self._env = dict(os.environ if env is None else env)
        cam_cls = load_class(CAMERAS, "camera", config.camera.type)
        camera: Camera = cam_cls(validate_options(cam_cls, config.camera, "camera"), config)
        self._background = Background()
        self._links = LinkSupervisor(config, self._background, changed=self._changed)
        #: Why a recipe cannot run (not calibrated or taught), by number; its jobs answer
        #: NOT_CALIBRATED with it.
        self.recipe_problems: dict[int, str] = {}
        #: The recipes among them whose only lack is the taught reference.
        self.untaught: set[int] = set()
        pipelines: dict[int, Processor] = {}
        self._worker: WorkerClient | None = None
        if pipeline is not None and not isinstance(pipeline, str):
            pipelines = dict.fromkeys(config.recipe_numbers(), pipeline)  # taken as it is
        elif pipeline is not None or config.daemon.worker:  # judged here, built there
            _, problems, untaught = recipe_readiness(config, ready)
            self.recipe_problems.update(problems)
            self.untaught |= untaught
            self._worker = WorkerClient(config, pipeline or DEFAULT_PROCESSOR, camera.describe())
            camera = self._worker.camera  # the driver runs in the worker
        else:  # built here, once (each pipeline judges its recipe as readiness does)
            pipelines, problems, untaught = recipe_readiness(config, _in_process)
            self.recipe_problems.update(problems)
            self.untaught |= untaught

        self.run_state = RunState.CREATED
        self.freeze_heap_at_ready = False  # `vgripd run` sets it (a process of its own)
        self.notifier = Notifier(self._env)
        self.status_server: WebServer | None = None  # the web view, /api/status, /metrics
        self._cameras = CameraSupervisor(config, camera, self._background,
                                         changed=self._changed)
        if self._worker is not None:  # a worker that dies holding the camera: reopen it
            self._worker.camera_lost = self._cameras.lost
        self._runner = JobRunner(config, self._links, self._cameras, self._background,
                                 worker=self._worker, pipelines=pipelines,
                                 recipe_problems=self.recipe_problems,
                                 changed=self._changed)
        self._walks = WalkMode(self._runner, self._links, self._cameras, self._background,
                               self._changed)
        self._status = StatusBoard(config, self._runner, self._links, self._cameras,
                                   self._worker)
        #: The rooms by name: what the web view, the reload and tests read and change.
        self.rooms = Rooms(links=self._links, cameras=self._cameras, jobs=self._runner,
                           walks=self._walks,
                           travel=BeltTravel(self._runner, self._links, self._walks),
                           status=self._status, worker=self._worker)
        self.reloader: Reloader | None = None  # set by whoever knows the config file (run)
        self._resource_log = RateLimitedLog(log, interval_s=10.0)
        self._opening: list[asyncio.Task[Any]] = []  # start(): camera and links, concurrently
        self._loop: asyncio.AbstractEventLoop | None = None
        # asyncio.Event binds to the running loop on first use, not here.
        self._wake = asyncio.Event()
        #: State changes so far (``next_change``: the web view's pushed status waits on it).
        self.changes = 0
        self._stop_requested = asyncio.Event()
        self._t_start_ns = 0

    @property
    def not_calibrated(self) -> str:
        """Why the top-level config (recipe 0) cannot run ("" when it can)."""
        return self.recipe_problems.get(0, "")

    def recipe_label(self, number: int) -> str:
        """``2 (plate-b)`` for logs and messages."""
        return recipe_label(self.config, number)

    # --- lifecycle --------------------------------------------------------------------

    async def start(self) -> None:
        """Open everything; READY=1 once the links serve. Raises (after cleanup) on failure."""
        self._loop = asyncio.get_running_loop()
        self._loop.set_exception_handler(self._loop_exception)
        self._t_start_ns = time.monotonic_ns()
        self._set_run_state(RunState.STARTING)
        self._runner.start()
        self._walks.bind()
        try:
            for number, problem in self.recipe_problems.items():
                log.error("recipe %s not calibrated, its jobs will answer NOT_CALIBRATED: %s",
                          self.recipe_label(number), problem)
            if self._worker is not None:
                await self._worker.start()  # the camera open below waits until it is ready
            rec = self.config.record
            if rec.enabled:
                recorder = self._worker.recorder if self._worker is not None else Recorder(
                    rec.folder, int(rec.max_mb * 1e6),
                    self.config.model_dump(mode="json", exclude_none=True))
                self._runner.recorder = recorder
                recorder.start()
                log.info("recording jobs to %s (max %.0f MB)", rec.folder, rec.max_mb)
            interval_s = watchdog_interval_s(self._env)
            if interval_s is not None:  # pinged during a long start-up too
                self._background.spawn(watchdog(interval_s / 2, self.watchdog_problem,
                                                self.notifier))
            self._links.plan_files()
            self._begin_opening()  # camera and links at once; the status endpoint meanwhile
            st = self.config.status
            if st.enabled:
                self.status_server = WebServer(self)
                await self.status_server.start()
            await self._opened()
        except BaseException:
            await self._shutdown()
            raise
        self._set_run_state(RunState.RUNNING)
        if self.freeze_heap_at_ready:  # vgripd/service/host/heap.py: no 100 ms pass on a poll
            log.debug("%d start-up objects frozen", freeze_start_up_heap())
        self.notifier.ready(self.status_line())
        log.info("ready: %s", self.status_line())

    def _begin_opening(self) -> None:
        """Open the camera and every link at once (tasks; ``_opened`` waits for them), so a
        silent controller or a slow camera delays nothing else: a PLC link serves at once."""
        self._opening = list(self._links.begin_opening(self._walks.on_trigger))
        self._opening.append(asyncio.create_task(self._cameras.open(),
                                                 name="vgripd-open-camera"))

    async def _opened(self) -> None:
        """Wait until the camera and every link have reported their first outcome
        (``LinkSupervisor.judge_opened``)."""
        results = await asyncio.gather(*self._opening)
        self._opening = []
        self._links.judge_opened(results)

    #: Errors of a server's accept() that mean "out of file descriptors or memory": asyncio
    #: pauses accepting for a second and tries again; nothing is broken in vgripd.
    _RESOURCE_ERRNOS = frozenset({errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM})

    def _loop_exception(self, loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        """The event loop's error handler: a connection flood that exhausts the file limit
        (asyncio's "socket.accept() out of system resource") is one rate-limited line, not a
        traceback per accept; everything else goes to asyncio's default handler."""
        exc = context.get("exception")
        if isinstance(exc, OSError) and exc.errno in self._RESOURCE_ERRNOS:
            self._resource_log.warning(
                "*", "accept", "%s (%s): new connections wait (docs/registers.md, \"Connections\")",
                context.get("message", "out of system resource"), errno.errorcode.get(
                    exc.errno or 0, exc.errno))
            return
        loop.default_exception_handler(context)

    def request_stop(self) -> None:
        """Ask ``serve()`` to stop (signal handlers call this; also before start finished)."""
        self._stop_requested.set()

    async def serve(self) -> None:
        """Start, run until ``request_stop()``, then stop cleanly."""
        await self.start()
        try:
            await self._stop_requested.wait()
        finally:
            await self.stop()

    async def stop(self) -> None:
        if self.run_state in (RunState.STOPPING, RunState.STOPPED):
            return
        self._set_run_state(RunState.STOPPING)
        self.notifier.stopping("stopping")
        log.info("stopping")
        await self._shutdown()

    async def _shutdown(self) -> None:
        if self._worker is not None:  # a worker killed with the aborted job stays dead
            self._worker.stopping()
        opening, self._opening = self._opening, []  # start-up failed half way
        for task in opening:
            task.cancel()
        await asyncio.gather(*opening, return_exceptions=True)
        walked = await self._walks.shutdown()  # its record stays: resumable
        if (await self._runner.abort() or walked) and self._links.links:
            await asyncio.sleep(ABORT_LINGER_S)
        await self._background.cancel()
        if self.status_server is not None:
            await self.status_server.close()
        await self._links.close()
        await self._cameras.close()
        if self._runner.recorder is not None:
            self._runner.recorder.close()
        if self._worker is not None:
            # Writes the recordings still queued, then unlinks the shared memory.
            await self._worker.close()
        self._runner.close_executor()
        self.notifier.close()
        self._resource_log.flush(force=True)
        if self._loop is not None and self._loop.get_exception_handler() == self._loop_exception:
            self._loop.set_exception_handler(None)  # the loop may outlive this daemon
        self._set_run_state(RunState.STOPPED)
        log.info("stopped")

    # --- a reloaded config (vgripd.service.ops.reload) --------------------------------------

    def use_config(self, config: Config, pipelines: dict[int, Processor] | None) -> None:
        """Every room reads ``config`` from now on (between jobs; the worker reports its
        recipe problems again)."""
        self.config = config
        for room in (self._links, self._cameras, self._runner, self._status):
            room.config = config
        self.recipe_problems.clear()
        if pipelines is not None:
            self._runner.pipelines = pipelines

    def show_state(self) -> None:  # the status line and the waiters see it (a reload)
        self._runner._set_state(self._runner.state)

    # --- waiting on state (for callers and tests) --------------------------------------

    async def wait_for(self, predicate: Callable[[], bool], timeout_s: float) -> None:
        """Wait until ``predicate()`` holds (checked on every state change); TimeoutError."""
        async with asyncio.timeout(timeout_s):
            while not predicate():
                await self._wake.wait()

    async def next_change(self, seen: int) -> int:
        """Wait until the state has changed since ``changes`` was ``seen``; the count now."""
        while self.changes == seen:
            await self._wake.wait()
        return self.changes

    def _notify_changed(self) -> None:
        # Count it, wake every waiter once, then hand later waiters a fresh event.
        self.changes += 1
        self._wake.set()
        self._wake = asyncio.Event()

    def _set_run_state(self, state: RunState) -> None:
        self.run_state = state
        # Links open during start-up may trigger before READY: those jobs run normally.
        accepting = state in (RunState.STARTING, RunState.RUNNING)
        self._runner.accepting = self._cameras.accepting = accepting
        self._notify_changed()

    def _changed(self) -> None:
        """The rooms' one way back: the job state, the camera or a NEXT answer changed, so
        the status line and the waiters see it."""
        self.notifier.status(self.status_line())
        self._notify_changed()

    # --- health and status ----------------------------------------------------------------

    def health_problem(self) -> str:
        """Why the service is not healthy ("" when it is): the camera is faulty
        (``rooms.cameras.fault``), no job can get a frame (the camera is down), or a job has
        outlived its timeout by ``WATCHDOG_GRACE_S`` (wedged)."""
        return self._cameras.fault or self._cameras.down_problem() or self._wedged_job()

    def watchdog_problem(self) -> str:
        """Why the watchdog stops pinging, so that systemd restarts the service ("" while it
        pings): as ``health_problem``, but a camera down only once it has been down longer
        than ``daemon.camera_down_restart_s`` (recovering on its own failed)."""
        return (self._cameras.fault or self._wedged_job()
                or self._cameras.down_problem(self.config.daemon.camera_down_restart_s))

    def _wedged_job(self) -> str:
        job = self._runner.job
        if job is None:
            return ""
        age_s = (time.monotonic_ns() - self._runner.job_started_ns) / 1e9
        limit_s = self.config.daemon.job_timeout_s + WATCHDOG_GRACE_S
        if age_s < limit_s:
            return ""
        return (f"job {job[0]} running for {age_s:.1f} s (daemon.job_timeout_s + "
                f"{WATCHDOG_GRACE_S:g} s = {limit_s:g} s): the job machinery is wedged")

    def healthy(self) -> bool:
        """False when the service is not healthy (``health_problem`` says why)."""
        return not self.health_problem()

    def cycle_percentiles_ms(self) -> dict[str, float]:
        return self._status.cycle_percentiles_ms()

    def link_refusals(self) -> dict[str, Counter[str]]:
        """Per link, the requests it refused on its own handshake, by status name."""
        return self._links.refusals()

    def answered(self) -> tuple[Counter[str], Counter[str]]:
        """All answers the peers were told and the refusals among them, by status name: the
        daemon's (``rooms.jobs.counters``, ``.refusals``) plus the links' own refusals."""
        return self._status.answered()

    def status_line(self) -> str:
        """One line for ``systemctl status`` (sd_notify STATUS=)."""
        return self._status.line()

    def recipe_snapshot(self) -> dict[str, Any]:
        """The active recipe and every configured one with whether it can run."""
        return self._status.recipe_snapshot()

    def snapshot(self) -> dict[str, Any]:
        """The status as JSON data (served by ``GET /status``)."""
        return {**self._status.snapshot(self.run_state.value, self._t_start_ns,
                                        self.health_problem()), "walk": self._walks.snapshot()}
