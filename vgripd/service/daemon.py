"""The asyncio service: robot links in, one job at a time, results out.

Life of a job (``JobState``)::

    IDLE -> TRIGGERED -> ACQUIRING -> PROCESSING -> PUBLISHING -> IDLE

- A trigger while a job runs is refused with ``Status.BUSY`` (published to the link that sent
  it, for its ``seq``, with ``job_id = 0``: no job was created); the running job is unaffected.
- ``daemon.job_timeout_s`` bounds acquisition plus processing. Running out while acquiring is
  ``CAMERA_ERROR``; while processing it is ``INTERNAL``. With the worker process
  (``daemon.worker``, the default) the busy worker is killed and a new one started; in-process
  the stale computation cannot be interrupted (it finishes on the job thread, result discarded).
- The image-captured signal goes to the triggering link as soon as ``grab()`` returns; the
  result goes only to the link that triggered (each link has its own handshake and sequence).
- Grabbing, processing and recording run in a worker process (``vgripd.service.worker``:
  images through shared memory, the rest pickled), so the event loop's interpreter only
  handles links and state and answers a poll in about a millisecond while a job runs. A worker
  that dies fails the job in flight with ``INTERNAL`` naming why ("worker process exited with
  signal 9 (SIGKILL)") and is replaced. ``daemon.worker = false`` (or a ``Processor`` object
  passed in) keeps the old in-process path: driver thread, single-thread job executor.
- Every job ends with exactly one ``Status``: a camera failure is ``CAMERA_ERROR``, an
  unexpected exception ``INTERNAL`` (logged with its traceback), shutdown ``ABORTED``.
- Counters count what the peers were told: ``publish`` returns the status the link actually
  gave its peer (normally the job's), and an answer whose publish failed is counted apart
  (``undelivered``, by the job's status). Refusals a register link makes on its own handshake
  (``RobotLink.refusals``: BUSY, BAD_REQUEST) are added to the daemon's own in the status.
- Pick lists (``JobResult.instances``, map version 3; the rules are ``jobcore.JobCore``'s):
  the last job's result is kept with the link that triggered it (``PickCursor``) when it has a
  pickable instance and was delivered. A NEXT (``Command.NEXT``, the same code on every link)
  is answered from it through the same publish path: the following instance
  (``next_answer``), no acquisition, the job's id and age; past the end ``NOT_FOUND`` without
  a pose and INDEX = COUNT + 1 (a single-object job is a list of one). Any new job drops the
  list at its trigger, so a NEXT can never hand out a pose of an earlier job; a NEXT with no
  list of its link's is answered ``BAD_REQUEST`` (job id 0), one while a job runs ``BUSY``.
  NEXT answers are counted with the answers (``counters``) and apart (``next_answers``), and
  logged one line each.
- RECALIBRATE (``EpipolarMonitor``): the median epipolar residual of every stereo job goes
  into a window of ``daemon.recalibrate_window`` jobs; while more than ``recalibrate_share``
  of them exceed ``vision.epipolar_warn_px`` the status carries the warning (logged once when
  it rises and once when it clears) and every link shows it (``RobotLink.set_warnings``: the
  WARNINGS register, UR input_double_register 21). The chapter's sign that the rig has moved.
  The job that changes it is counted before it is published, so the triggering link's warning
  bits are in place before its acknowledge.
- Start-up opens the camera and every link at once (a silent controller delays no other link
  and not the status endpoint); a link that cannot start is shown FAILED while the others
  serve. READY=1 follows the first outcome of each.
- A grab that runs out of time and still hangs in the driver is abandoned and the camera opened
  again; if that fails or hangs too, ``camera_fault`` says why and the watchdog stops pinging
  (``health_problem``), so systemd restarts the service.
- Recipes (docs/recipes.md): a trigger names one (``Trigger.recipe``, 0 = the top-level config).
  A pipeline is built per recipe at start (in the worker process too), so switching costs
  nothing. An unknown number ends its job with ``BAD_REQUEST`` before any image is taken; a
  recipe that is not calibrated or taught answers ``NOT_CALIBRATED`` for its own jobs only.
  The recipe of the running or last job is the active one (``snapshot()["recipe"]``).
- Several views per job (``vision.views`` = N > 1, docs/multicamera.md "Several views per
  job"): one robot-mounted camera, moved by the robot through N poses. Each view is a request
  of its own (``Command.CAPTURE``, ``Trigger.view`` = 1..N) and an acquisition run like a job
  (BUSY for others meanwhile), with the view's flange pose (the robot's, else the taught
  ``vision.view_poses``) handed to the camera. Views 1..N-1 are answered ``view_captured`` (the
  robot moves on); the last view's request runs one fit over the N images (each with its own
  flange pose) and gets the job's result. Between views a ``ViewJob`` holds the images. The
  job ends, answered to the request that ended it, with one status: ``BAD_REQUEST`` for a
  view out of order or repeated, or a TRIGGER of the same link in the middle;
  ``NOT_CALIBRATED`` for a view without a flange pose; ``CAMERA_ERROR`` for a failed grab or,
  answered under the last view taken, no next view within ``vision.view_timeout_s``. A view
  k > 1 without a job (after any of these) is refused ``BAD_REQUEST``: start again at view 1.
  So the images of an unfinished job never reach a fit, and no pose mixes two jobs.
- Shutdown (SIGTERM/SIGINT) aborts the job in flight (unless it is already publishing), so the
  PLC gets ``ABORTED`` for its trigger at once instead of waiting; the links stay up for
  ``ABORT_LINGER_S`` so a polling PLC can read it, then links, the camera, the recorder and the
  job thread or worker process are closed (the worker writes queued recordings first). A CPU
  step already running in the worker is ended by killing it; in-process it cannot be
  interrupted: the process exits when it ends, its result is discarded.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import enum
import errno
import logging
import os
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Protocol

import numpy as np

from vgripd.config import Config, unknown_recipe
from vgripd.errors import CameraError, ConfigError, LinkError, NotCalibratedError
from vgripd.registry import CAMERAS, LINKS, load_class, validate_options
from vgripd.service.gate import WEB_SURFACE, Budget, Gate, file_limit, open_files, plan_budget
from vgripd.service.heap import freeze_start_up_heap
from vgripd.service.jobcore import (
    Admit,
    JobCore,
    PickCursor,
    ViewsAt,
    ViewStep,
    view_admission,
)
from vgripd.service.jobrecord import EpipolarMonitor, JobListener, JobRecord
from vgripd.service.protocol import (
    Command,
    RobotLink,
    Trigger,
    Warnings,
    pick_position,
)
from vgripd.service.ratelog import RateLimitedLog
from vgripd.service.recorder import Recorder
from vgripd.service.sdnotify import Notifier, watchdog_interval_s
from vgripd.service.web import WEB_LINK, WebServer, WebTriggerLink
from vgripd.service.worker import DEFAULT_PROCESSOR, WorkerClient, WorkerError, WorkerRecorder
from vgripd.types import CaptureView, ImagePair, JobResult, Status

log = logging.getLogger("vgripd")

# A link call (image_captured/publish) that takes longer is abandoned and logged.
LINK_CALL_TIMEOUT_S = 2.0
# After publishing ABORTED on shutdown the links stay up this long, so that a polling PLC
# reads the answer to its trigger before the server goes away.
ABORT_LINGER_S = 1.0
# The watchdog stops pinging when a job runs this long past its timeout: the timeout should
# have ended it, so the job machinery is wedged and systemd should restart the service.
WATCHDOG_GRACE_S = 5.0
# Opening the camera longer than this is a hang (the daemon's ``camera_open_timeout_s``).
CAMERA_OPEN_TIMEOUT_S = 30.0
# Closing a camera that hung (its driver abandons a stuck thread; the worker's close is bounded).
CAMERA_CLOSE_TIMEOUT_S = 10.0
# A grab that ran out of time and is still running this much later is hung, not just late.
CAMERA_HUNG_GRACE_S = 1.0


class JobState(enum.Enum):
    IDLE = "idle"
    TRIGGERED = "triggered"
    ACQUIRING = "acquiring"
    PROCESSING = "processing"
    PUBLISHING = "publishing"


class RunState(enum.Enum):
    CREATED = "created"
    STARTING = "starting"
    RUNNING = "running"
    STOPPING = "stopping"
    STOPPED = "stopped"


class Processor(Protocol):
    """What the daemon needs from the vision pipeline (``vgripd.vision.pipeline.Pipeline``)."""

    def process(self, pair: ImagePair, job_id: int) -> JobResult: ...


@dataclasses.dataclass
class ViewJob:
    """A several-view job between its views (``vision.views``).

    ``pairs``: the images taken so far, one per view in order; ``last``: the trigger of the
    last view taken (its request is the one a timeout is answered under); ``first_ns``: view
    1's trigger time (the job's cycle time counts from it); ``timer``: the wait for the next
    view (``vision.view_timeout_s``).
    """

    job_id: int
    link: str
    recipe: int
    count: int
    first_ns: int
    taught: tuple[np.ndarray, ...] = ()
    pairs: list[ImagePair] = dataclasses.field(default_factory=list)
    last: Trigger | None = None
    timer: asyncio.TimerHandle | None = None

    @property
    def next_view(self) -> int:
        return len(self.pairs) + 1

    def flange(self, trigger: Trigger) -> np.ndarray | None:
        """The flange pose of the view ``trigger`` asks for: the robot's, else the taught."""
        if trigger.T_base_flange is not None:
            return np.asarray(trigger.T_base_flange, dtype=np.float64)
        return self.taught[trigger.view - 1] if self.taught else None

    def ending(self, trigger: Trigger) -> Trigger:
        """``trigger`` (the request that ends the job) as the job's: its sequence, the job's
        recipe and view 1's time."""
        return dataclasses.replace(trigger, recipe=self.recipe, t_mono_ns=self.first_ns)

    def combined(self) -> ImagePair:
        """The N views as one acquisition: images in view order, an (N, 4, 4) stack of their
        flange poses (``scene.views_config`` makes each view a camera of its own)."""
        first = self.pairs[0]
        flanges = [p.T_base_flange for p in self.pairs]
        assert all(f is not None for f in flanges)  # _acquire_view refused the view otherwise
        return ImagePair.of_views(
            [p.left for p in self.pairs], first.t_mono_ns, source=first.source,
            meta={"views": [dict(p.meta) for p in self.pairs]},
            T_base_flange=np.stack([np.asarray(f, dtype=np.float64) for f in flanges]),
            truth=dict(first.truth))


def _link_names(config: Config) -> list[str]:
    types = [s.type for s in config.links]
    return [t if types.count(t) == 1 else f"{t}.{i}" for i, t in enumerate(types)]


def scene_pose(pose: Any) -> np.ndarray:
    """A config pose as a (4, 4) transform (the vision scene's reading of it)."""
    from vgripd.vision.scene import matrix_from_pose  # heavy (OpenCV); only jobs need it

    return matrix_from_pose(pose)


def _make_pipeline(config: Config) -> Processor:
    from vgripd.vision.pipeline import Pipeline  # heavy (OpenCV); only the daemon needs it

    pipeline: Processor = Pipeline(config)
    return pipeline


class Daemon:
    """One vgripd service instance. Construction validates drivers and does no I/O.

    Raises ``ConfigError`` for a bad driver type or options. A missing/invalid calibration
    (``NotCalibratedError``) does not stop the service: every job then answers
    ``NOT_CALIBRATED``, so the PLC sees why (``not_calibrated`` says so). The same holds per
    recipe: a recipe not taught yet answers ``NOT_CALIBRATED`` (``recipe_problems``), the
    others run.

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
        self.camera = cam_cls(validate_options(cam_cls, config.camera, "camera"), config)
        self.links: dict[str, RobotLink] = {}
        for i, (name, section) in enumerate(zip(_link_names(config), config.links, strict=True)):
            link_cls = load_class(LINKS, "link", section.type)
            self.links[name] = link_cls(name, validate_options(link_cls, section, f"links.{i}"))
        if config.status.enabled and config.status.allow_trigger:  # the web view's test trigger
            self.links[WEB_LINK] = WebTriggerLink()
        recipes = {number: config.recipe_name(number) for number in config.recipe_numbers()}
        for link in self.links.values():
            link.set_recipes(recipes)
        #: Why a recipe cannot run (not calibrated or taught), by number; its jobs answer
        #: NOT_CALIBRATED with it.
        self.recipe_problems: dict[int, str] = {}
        self._pipelines: dict[int, Processor] = {}
        for number in config.recipe_numbers():
            if pipeline is None or isinstance(pipeline, str):
                try:  # judges each recipe's config here, once
                    self._pipelines[number] = _make_pipeline(config.for_recipe(number))
                except NotCalibratedError as err:
                    self.recipe_problems[number] = str(err)
                except ConfigError as err:  # a template file, an ArUco id: name the recipe
                    if not number:
                        raise
                    raise ConfigError(f"recipes.{number}.{err}") from None
            else:
                self._pipelines[number] = pipeline
        self._worker: WorkerClient | None = None
        if isinstance(pipeline, str) or (pipeline is None and config.daemon.worker):
            self._worker = WorkerClient(config, pipeline or DEFAULT_PROCESSOR,
                                        self.camera.describe())
            self.camera = self._worker.camera  # the driver runs in the worker
            self._pipelines = {}  # built above only to judge the config; the worker runs them
        #: The recipe of the running or last job (None before the first).
        self.active_recipe: int | None = None

        self.run_state = RunState.CREATED
        self.freeze_heap_at_ready = False  # `vgripd run` sets it (a process of its own)
        self.state = JobState.IDLE
        self.listeners: list[JobListener] = []
        self.notifier = Notifier(self._env)
        self.status_server: WebServer | None = None  # the web view, /api/status, /metrics
        self.recorder: Recorder | WorkerRecorder | None = None
        # What the daemon's answers told the peers, by status name: job results as published
        # and the daemon's own refusals. `snapshot()` adds the links' own refusals.
        self.counters: Counter[str] = Counter()
        self.refusals: Counter[str] = Counter()  # the daemon's refusals among `counters`
        self.undelivered: Counter[str] = Counter()  # answers whose publish failed (job status)
        self.record_dropped = 0  # jobs the recorder refused because the disk was behind
        self.cycle_ms: deque[float] = deque(maxlen=config.daemon.stats_window)
        self.last_job: JobRecord | None = None
        #: Admission and the last job's pick list (the rules, without I/O).
        self.jobs = JobCore()
        #: A several-view job between two of its views (None otherwise).
        self.views: ViewJob | None = None
        self.next_answers: Counter[str] = Counter()  # NEXT answers, by the status told
        d = config.daemon
        self.epipolar = EpipolarMonitor(d.recalibrate_window, d.recalibrate_share,
                                        d.recalibrate_min_jobs, config.vision.epipolar_warn_px)

        self._resource_log = RateLimitedLog(log, interval_s=10.0)
        #: How RLIMIT_NOFILE is split between the server surfaces and the reserve (at start).
        self.fd_budget: Budget | None = None
        self._job_seq = 0
        self._job: tuple[int, Trigger, asyncio.Task[None]] | None = None
        self._job_started_ns = 0
        self._camera_open = False
        self._camera_lock = asyncio.Lock()  # one open/close of the camera at a time
        self._camera_error = ""  # why the last open failed
        self._camera_recovery: asyncio.Task[None] | None = None
        #: Why the camera cannot be used any more (a grab hung and opening it again failed or
        #: hung too): the watchdog stops pinging, so systemd restarts the service.
        self.camera_fault = ""
        self.camera_open_timeout_s = CAMERA_OPEN_TIMEOUT_S
        self._opening: list[asyncio.Task[Any]] = []  # start(): camera and links, concurrently
        self._executor: ThreadPoolExecutor | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._loop_thread = 0
        # asyncio.Event binds to the running loop on first use, not here.
        self._changed = asyncio.Event()
        self._stop_requested = asyncio.Event()
        self._tasks: set[asyncio.Task[Any]] = set()
        self._t_start_ns = 0

    @property
    def pick_list(self) -> PickCursor | None:
        """The last job's pick list (None: no job yet, a job running, or nothing pickable)."""
        return self.jobs.pick_list

    @property
    def not_calibrated(self) -> str:
        """Why the top-level config (recipe 0) cannot run ("" when it can)."""
        return self.recipe_problems.get(0, "")

    def recipe_label(self, number: int) -> str:
        """``2 (plate-b)`` for logs and messages."""
        return f"{number} ({self.config.recipe_name(number)})"

    # --- lifecycle --------------------------------------------------------------------

    async def start(self) -> None:
        """Open everything; READY=1 once the links serve. Raises (after cleanup) on failure."""
        self._loop = asyncio.get_running_loop()
        self._loop_thread = threading.get_ident()
        self._loop.set_exception_handler(self._loop_exception)
        self._t_start_ns = time.monotonic_ns()
        self._set_run_state(RunState.STARTING)
        self._executor = ThreadPoolExecutor(1, thread_name_prefix="vgripd-job")
        try:
            for number, problem in self.recipe_problems.items():
                log.error("recipe %s not calibrated, its jobs will answer NOT_CALIBRATED: %s",
                          self.recipe_label(number), problem)
            if self._worker is not None:
                await self._worker.start()  # the camera open below waits until it is ready
            rec = self.config.record
            if rec.enabled:
                self.recorder = self._worker.recorder if self._worker is not None else Recorder(
                    rec.folder, int(rec.max_mb * 1e6),
                    self.config.model_dump(mode="json", exclude_none=True))
                self.recorder.start()
                log.info("recording jobs to %s (max %.0f MB)", rec.folder, rec.max_mb)
            interval_s = watchdog_interval_s(self._env)
            if interval_s is not None:  # pinged during a long start-up too
                self._spawn(self._watchdog(interval_s / 2))
            self.fd_budget = self._plan_files()
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
        if self.freeze_heap_at_ready:  # vgripd/service/heap.py: no 100 ms pass on a poll
            log.debug("%d start-up objects frozen", freeze_start_up_heap())
        self.notifier.ready(self.status_line())
        log.info("ready: %s", self.status_line())

    def _plan_files(self) -> Budget:
        """Split the file limit between the server surfaces (web view, each listening link)
        and ``daemon.fd_reserve`` (docs/daemon.md, "File budget"); set each gate's cap and
        log the split once."""
        gates: dict[str, Gate] = {}
        for name, link in self.links.items():
            gate = getattr(link, "gate", None)
            if isinstance(gate, Gate) and getattr(link.options, "mode", "server") == "server":
                gates[name] = gate
        wanted = [(name, gate.configured_cap) for name, gate in gates.items()]
        if self.config.status.enabled:
            wanted.insert(0, (WEB_SURFACE, self.config.status.max_connections))
        budget = plan_budget(file_limit(), open_files(), self.config.daemon.fd_reserve, wanted)
        for name, gate in gates.items():
            gate.cap = budget.caps[name]
        log.info("%s", budget.describe())
        if budget.scaled:
            log.warning("the configured max_connections do not fit the file limit %d: lowered "
                        "to %s (raise LimitNOFILE= in the unit, or lower max_connections or "
                        "daemon.fd_reserve)", budget.limit,
                        ", ".join(f"{n} {c}" for n, c in budget.caps.items()))
        return budget

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
        if self._job is not None:
            task = self._job[2]
            aborting = self.state is not JobState.PUBLISHING
            if aborting:
                task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
            if aborting and self.links:
                await asyncio.sleep(ABORT_LINGER_S)
        elif self.views is not None and self.views.last is not None:  # between two views
            views, last = self.views, self.views.last
            await self._finish(views.ending(last), views.job_id, None, self._failure(
                views.job_id, Status.ABORTED, f"aborted by shutdown after view "
                f"{views.next_view - 1} of {views.count}"))
            if self.links:
                await asyncio.sleep(ABORT_LINGER_S)
        for task in list(self._tasks):
            task.cancel()
        for task in list(self._tasks):
            with contextlib.suppress(asyncio.CancelledError):
                await task
        if self.status_server is not None:
            await self.status_server.close()
        for name, link in self.links.items():
            try:
                await link.close()
            except Exception:
                log.exception("link %s: close failed", name)
        if self._camera_open:
            try:
                await self.camera.close()
            except Exception:
                log.exception("camera: close failed")
            self._camera_open = False
        if self.recorder is not None:
            self.recorder.close()
        if self._worker is not None:
            # Writes the recordings still queued, then unlinks the shared memory.
            await self._worker.close()
        if self._executor is not None:
            # Waits only for a CPU step already running (its result is discarded).
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None
        self.notifier.close()
        self._resource_log.flush(force=True)
        if self._loop is not None and self._loop.get_exception_handler() == self._loop_exception:
            self._loop.set_exception_handler(None)  # the loop may outlive this daemon
        self._set_run_state(RunState.STOPPED)
        log.info("stopped")

    # --- waiting on state (for callers and tests) --------------------------------------

    async def wait_for(self, predicate: Callable[[], bool], timeout_s: float) -> None:
        """Wait until ``predicate()`` holds (checked on every state change); TimeoutError."""
        async with asyncio.timeout(timeout_s):
            while not predicate():
                await self._changed.wait()

    def _notify_changed(self) -> None:
        # Wake every waiter once, then hand later waiters a fresh event.
        self._changed.set()
        self._changed = asyncio.Event()

    def _set_run_state(self, state: RunState) -> None:
        self.run_state = state
        self._notify_changed()

    def _set_state(self, state: JobState) -> None:
        self.state = state
        self.notifier.status(self.status_line())
        self._notify_changed()

    # --- triggers and jobs --------------------------------------------------------------

    def _on_trigger(self, trigger: Trigger) -> None:
        """Called by a link for every trigger; from any thread, never blocks."""
        assert self._loop is not None
        if threading.get_ident() != self._loop_thread:
            self._loop.call_soon_threadsafe(self._on_trigger, trigger)
            return
        if trigger.link not in self.links:
            log.error("trigger from unknown link %r ignored", trigger.link)
            return
        # Links open during start-up may trigger before READY: those jobs run normally.
        accepting = self.run_state in (RunState.STARTING, RunState.RUNNING)
        admission = self.jobs.trigger(trigger.link, trigger.command, accepting,
                                      busy=self._job is not None)
        if admission.kind is Admit.REFUSE:
            what = "NEXT" if admission.status is Status.BAD_REQUEST else "trigger"
            log.warning("%s seq %d from %s refused: %s%s", what, trigger.seq, trigger.link,
                        admission.status.name, f" ({admission.why})" if admission.why else "")
            self._spawn(self._refuse(trigger, admission.status, admission.why))
            return
        if admission.kind is Admit.NEXT:  # answered from the list, no acquisition
            assert admission.answer is not None
            self._spawn(self._answer_next(trigger, admission.answer))
            return
        if trigger.command == Command.CAPTURE or self._views_of(trigger.recipe) > 1:
            self._capture(trigger)
            return
        self._start(trigger)

    def _views_of(self, recipe: int) -> int:
        """``vision.views`` of ``recipe`` (1 for a recipe not configured: its job answers
        BAD_REQUEST the usual way)."""
        if recipe not in self.config.recipe_numbers():
            return 1
        return self.config.for_recipe(recipe).vision.views

    def _capture(self, trigger: Trigger) -> None:
        """A CAPTURE (or a TRIGGER in a cell of several views): start, continue or end the
        several-view job (the module docstring has the rules)."""
        views = self.views
        at = None if views is None else ViewsAt(views.link, views.job_id, views.next_view,
                                                  views.count)
        decision = view_admission(trigger.command, trigger.view, trigger.link,
                                  self.recipe_label(trigger.recipe),
                                  trigger.recipe in self.config.recipe_numbers(),
                                  self._views_of(trigger.recipe), at)
        if decision.step is ViewStep.END:
            self._end_views(trigger, decision.why)
            return
        if decision.step is ViewStep.JOB:
            self._start(trigger)  # answered BAD_REQUEST like any job's unknown recipe
            return
        if decision.step is ViewStep.REFUSE:
            if trigger.command == Command.CAPTURE and decision.status is Status.BAD_REQUEST:
                log.warning("CAPTURE seq %d from %s refused: BAD_REQUEST (%s)", trigger.seq,
                            trigger.link, decision.why)
            self._spawn(self._refuse(trigger, decision.status, decision.why))
            return
        if decision.step is ViewStep.BEGIN:
            vision = self.config.for_recipe(trigger.recipe).vision
            self._job_seq += 1
            self.jobs.job_started()
            self.views = ViewJob(self._job_seq, trigger.link, trigger.recipe,
                                 self._views_of(trigger.recipe), trigger.t_mono_ns,
                                 tuple(scene_pose(p) for p in vision.view_poses))
            self.active_recipe = trigger.recipe
        views = self.views
        assert views is not None
        if views.timer is not None:
            views.timer.cancel()
            views.timer = None
        log.info("job %d: view %d of %d: seq %d from %s", views.job_id, trigger.view,
                 views.count, trigger.seq, trigger.link)
        self._job_started_ns = time.monotonic_ns()
        self._job = (views.job_id, trigger,
                     asyncio.create_task(self._run_job(trigger, views.job_id, views)))
        self._set_state(JobState.TRIGGERED)

    def _end_views(self, trigger: Trigger, why: str) -> None:
        """End the several-view job with BAD_REQUEST, answered to ``trigger`` (the request
        that broke the sequence); its images are dropped."""
        views = self.views
        assert views is not None
        result = self._failure(views.job_id, Status.BAD_REQUEST,
                               f"{why} (views job ended after view {views.next_view - 1} "
                               f"of {views.count})")
        self._finish_views(views.ending(trigger), result)

    def _finish_views(self, trigger: Trigger, result: JobResult) -> None:
        """End the waiting several-view job with ``result`` as a job of its own (BUSY for
        others while it is published)."""
        views = self.views
        assert views is not None
        assert self._job is None
        self._job_started_ns = time.monotonic_ns()
        self._job = (views.job_id, trigger, asyncio.create_task(
            self._finish(trigger, views.job_id, None, result)))

    def _views_timed_out(self, views: ViewJob) -> None:
        if self.views is not views or self._job is not None or views.last is None:
            return  # the next view came meanwhile
        timeout_s = self.config.for_recipe(views.recipe).vision.view_timeout_s
        self._finish_views(views.ending(views.last), self._failure(
            views.job_id, Status.CAMERA_ERROR,
            f"view {views.next_view} of {views.count} not requested within "
            f"vision.view_timeout_s = {timeout_s:g} s after the previous one"))

    def _start(self, trigger: Trigger) -> None:
        """Run a one-acquisition job for ``trigger``."""
        self.jobs.job_started()  # a new job: the old list is nobody's any more
        self._job_seq += 1
        job_id = self._job_seq
        log.info("job %d: trigger seq %d command %d recipe %d from %s", job_id, trigger.seq,
                 trigger.command, trigger.recipe, trigger.link)
        if trigger.recipe in self.config.recipe_numbers():
            self.active_recipe = trigger.recipe
        self._job_started_ns = time.monotonic_ns()
        self._job = (job_id, trigger, asyncio.create_task(self._run_job(trigger, job_id)))
        self._set_state(JobState.TRIGGERED)

    async def _answer_next(self, trigger: Trigger, answer: JobResult) -> None:
        told = await self._publish(trigger.link, trigger.seq, answer)
        self._count(answer.status, told)
        self.next_answers[(told or answer.status).name] += 1
        pos = pick_position(answer)
        log.info("job %d: NEXT seq %d from %s: instance %d of %d: %s%s", answer.job_id,
                 trigger.seq, trigger.link, pos.index, pos.count, answer.status.name,
                 "" if told is answer.status else
                 "; not delivered" if told is None else f"; published as {told.name}")
        self._set_state(self.state)  # status line and waiters see it

    def _begin_opening(self) -> None:
        """Open the camera and every link at once (tasks; ``_opened`` waits for them), so a
        silent controller or a slow camera delays nothing else: a PLC link serves at once."""
        self._opening = [asyncio.create_task(self._open_link(name, link),
                                             name=f"vgripd-open-link-{name}")
                         for name, link in self.links.items()]
        self._opening.append(asyncio.create_task(self._open_camera(), name="vgripd-open-camera"))

    async def _opened(self) -> None:
        """Wait until the camera and every link have reported their first outcome. A link that
        cannot start is logged and shown FAILED while the others serve; ``LinkError`` only
        when no link could start."""
        results = await asyncio.gather(*self._opening)
        self._opening = []
        failed = [r for r in results if isinstance(r, str)]
        if self.links and len(failed) == len(self.links):
            raise LinkError(failed[0] if len(failed) == 1 else
                            "no link could start: " + "; ".join(failed))
        for why in failed:
            log.error("%s; the other links serve without it", why)

    async def _open_link(self, name: str, link: RobotLink) -> str | None:
        """``link.open``; the error text when it cannot start (the link is FAILED)."""
        try:
            await link.open(self._on_trigger)
        except LinkError as err:
            return str(err)
        log.info("link %s open (%s)", name, link.health().state.value)
        return None

    async def _open_camera(self, fault_on_hang: bool = True) -> None:
        """Open the camera unless it is open; one open at a time. A camera that cannot open is
        not fatal (the next job tries again and answers CAMERA_ERROR meanwhile); one whose
        open hangs longer than ``camera_open_timeout_s`` is a camera fault (``fault_on_hang``;
        otherwise the caller judges it by ``_camera_error``)."""
        async with self._camera_lock:
            if self._camera_open:
                return
            kind = self._camera_name()
            try:
                async with asyncio.timeout(self.camera_open_timeout_s):
                    await self.camera.open()
            except TimeoutError:
                self._camera_error = (f"opening it hung for more than "
                                      f"{self.camera_open_timeout_s:g} s")
                if fault_on_hang:
                    self._set_camera_fault(f"camera {kind}: {self._camera_error}")
                return
            except CameraError as err:
                self._camera_error = str(err)
                log.error("camera %s cannot open: %s", kind, err)
                return
            self._camera_open = True
            self._camera_error = ""
            log.info("camera %s open", kind)

    def _camera_name(self) -> str:
        return str(getattr(self.camera, "type_name", "") or self.config.camera.type)

    def _set_camera_fault(self, why: str) -> None:
        self.camera_fault = why
        log.error("%s: the camera is unusable; the watchdog stops pinging so that systemd "
                  "restarts vgripd", why)
        self._set_state(self.state)  # status line and waiters see it

    def _camera_ran_out(self, waited_s: float) -> None:
        """A grab did not deliver in time: check in the background whether it hangs."""
        if self.run_state not in (RunState.STARTING, RunState.RUNNING):
            return
        if self._camera_recovery is None or self._camera_recovery.done():
            self._camera_recovery = asyncio.create_task(self._recover_camera(waited_s),
                                                        name="vgripd-camera-recovery")
            self._tasks.add(self._camera_recovery)
            self._camera_recovery.add_done_callback(self._tasks.discard)

    async def _recover_camera(self, waited_s: float) -> None:
        """After a grab ran out of time: if the driver's call still hangs (or, in the worker
        process, cannot be seen), abandon it and open the camera again; when that fails or
        hangs too, the camera is faulty (``camera_fault``) and the watchdog stops."""
        camera, kind = self.camera, self._camera_name()
        stuck_s = getattr(camera, "stuck_s", None)
        if callable(stuck_s):
            await asyncio.sleep(CAMERA_HUNG_GRACE_S)  # a late grab may still return meanwhile
            if stuck_s() == 0:
                return
            what = f"a grab has been stuck in the driver for {stuck_s():.1f} s"
        else:
            what = f"no image within {waited_s:.1f} s"
        log.error("camera %s: %s; closing it and opening it again", kind, what)
        async with self._camera_lock:
            self._camera_open = False
            try:
                async with asyncio.timeout(CAMERA_CLOSE_TIMEOUT_S):
                    await camera.close()
            except (TimeoutError, CameraError) as err:
                log.warning("camera %s: close after the hang failed: %r", kind, err)
        await self._open_camera(fault_on_hang=False)
        if self._camera_open:
            log.info("camera %s open again after the hang", kind)
            self._set_state(self.state)  # status line and waiters see it
        elif not self.camera_fault:
            self._set_camera_fault(f"camera {kind}: {what}, and opening it again failed: "
                                   f"{self._camera_error}")

    async def _acquire(self, trigger: Trigger, deadline_ns: int,
                       view: CaptureView | None = None) -> ImagePair:
        recovery = self._camera_recovery
        if recovery is not None and not recovery.done():
            await asyncio.shield(recovery)  # the camera is being opened again
        if self.camera_fault:
            raise CameraError(f"camera {self.config.camera.type} is unusable: "
                              f"{self.camera_fault}")
        if not self._camera_open:
            await self._open_camera()
            if not self._camera_open:
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
                self._camera_ran_out(waited_s)
            raise
        flange = trigger.T_base_flange if view is None else view.T_base_flange
        if pair.T_base_flange is None and flange is not None:
            pair = dataclasses.replace(pair, T_base_flange=flange)
        return pair

    async def _acquire_view(self, trigger: Trigger, deadline_ns: int,
                            views: ViewJob) -> ImagePair:
        """One view of a several-view job, with its flange pose (NOT_CALIBRATED without)."""
        flange = views.flange(trigger)
        if flange is None:
            raise NotCalibratedError(
                f"view {trigger.view} of {views.count}: no flange pose: link {trigger.link} "
                "does not report the robot's pose and vision.view_poses is not set")
        pair = await self._acquire(trigger, deadline_ns,
                                   CaptureView(trigger.view, views.count, flange))
        if len(pair.views) != 1:
            raise CameraError(f"view {trigger.view}: the camera delivered {len(pair.views)} "
                              "images, a view is one")
        return pair

    async def _view_taken(self, trigger: Trigger, views: ViewJob, pair: ImagePair) -> None:
        """A view before the last: keep its image, let the robot move on, wait for the next."""
        views.pairs.append(pair)
        views.last = trigger
        await self._link_call(trigger.link, "view_captured", trigger.seq, views.job_id)
        timeout_s = self.config.for_recipe(views.recipe).vision.view_timeout_s
        assert self._loop is not None
        views.timer = self._loop.call_later(timeout_s, self._views_timed_out, views)
        log.info("job %d: view %d of %d taken", views.job_id, trigger.view, views.count)
        self._job = None
        self._set_state(JobState.IDLE)

    async def _run_job(self, trigger: Trigger, job_id: int,
                       views: ViewJob | None = None) -> None:
        """Acquire, process and publish one job; with ``views``: one view of a several-view
        job, the last of which processes all of them."""
        known = self.config.recipe_numbers()
        if views is not None:
            trigger = views.ending(trigger)  # the job's recipe, its cycle from view 1
        if trigger.recipe not in known:  # answered like any job, without taking an image
            result = self._failure(job_id, Status.BAD_REQUEST,
                                   unknown_recipe(trigger.recipe, known))
            await self._finish(trigger, job_id, None, result)
            return
        timeout_s = self.config.daemon.job_timeout_s
        deadline_ns = self._job_started_ns + int(timeout_s * 1e9)
        pair: ImagePair | None = None
        try:
            try:
                async with asyncio.timeout(timeout_s):
                    self._set_state(JobState.ACQUIRING)
                    if views is None:
                        pair = await self._acquire(trigger, deadline_ns)
                    else:
                        view_pair = await self._acquire_view(trigger, deadline_ns, views)
                        if trigger.view < views.count:
                            await self._view_taken(trigger, views, view_pair)
                            return
                        views.pairs.append(view_pair)
                        pair = views.combined()
                    await self._link_call(trigger.link, "image_captured", trigger.seq, job_id)
                    self._set_state(JobState.PROCESSING)
                    result = await self._process(pair, job_id, trigger.recipe)
            except TimeoutError:
                stage = "acquisition" if pair is None else "processing"
                status = Status.CAMERA_ERROR if pair is None else Status.INTERNAL
                result = self._failure(job_id, status,
                                       f"{stage} exceeded daemon.job_timeout_s = {timeout_s} s")
            except CameraError as err:
                result = self._failure(job_id, Status.CAMERA_ERROR, str(err))
            except NotCalibratedError as err:
                result = self._failure(job_id, Status.NOT_CALIBRATED, str(err))
            except WorkerError as err:  # died during the grab; it logged its own traceback
                result = self._failure(job_id, Status.INTERNAL, str(err))
            except Exception as err:
                log.exception("job %d: unexpected error", job_id)
                result = self._failure(job_id, Status.INTERNAL, f"{type(err).__name__}: {err}")
        except asyncio.CancelledError:
            result = self._failure(job_id, Status.ABORTED, "aborted by shutdown")
            await self._finish(trigger, job_id, pair, result)
            raise
        await self._finish(trigger, job_id, pair, result)

    async def _process(self, pair: ImagePair, job_id: int, recipe: int = 0) -> JobResult:
        problem = self.recipe_problems.get(recipe)
        if problem:
            where = f"recipe {self.recipe_label(recipe)}: " if recipe else ""
            return self._failure(job_id, Status.NOT_CALIBRATED, where + problem)
        t0 = time.monotonic_ns()
        if self._worker is not None:
            try:
                result = await self._worker.process(pair, job_id, recipe)
            except WorkerError as err:  # died or raised; the worker logged the traceback
                return self._failure(job_id, Status.INTERNAL, str(err))
        else:
            assert self._loop is not None
            result = await self._loop.run_in_executor(
                self._executor, self._pipelines[recipe].process, pair, job_id)
        timings = {"acquire": (t0 - self._job_started_ns) / 1e6, **result.timings_ms,
                   "process": (time.monotonic_ns() - t0) / 1e6}
        return dataclasses.replace(
            result, job_id=job_id, timings_ms=timings,
            t_capture_mono_ns=result.t_capture_mono_ns or pair.t_mono_ns)

    @staticmethod
    def _failure(job_id: int, status: Status, message: str) -> JobResult:
        log.warning("job %d: %s: %s", job_id, status.name, message)
        return JobResult(job_id=job_id, status=status, message=message,
                         t_done_mono_ns=time.monotonic_ns())

    async def _finish(self, trigger: Trigger, job_id: int, pair: ImagePair | None,
                      result: JobResult) -> None:
        self._set_state(JobState.PUBLISHING)
        if self.views is not None and self.views.job_id == job_id:  # its images are done
            if self.views.timer is not None:
                self.views.timer.cancel()
            self.views = None
        result = dataclasses.replace(result, recipe=trigger.recipe,
                                     t_done_mono_ns=result.t_done_mono_ns or time.monotonic_ns())
        epipolar_px = result.residuals.get("epipolar_px")
        if epipolar_px is not None and self.epipolar.add(epipolar_px, result.t_done_mono_ns):
            if self.epipolar.warning:
                log.warning("RECALIBRATE: %s; the stereo rig may have moved, recalibrate it",
                            self.epipolar.describe())
            else:
                log.info("RECALIBRATE cleared: %s", self.epipolar.describe())
            await self._show_warnings(first=trigger.link)
        told = await self._publish(trigger.link, trigger.seq, result)
        done_ns = time.monotonic_ns()
        record = JobRecord(job_id=job_id, link=trigger.link, seq=trigger.seq, result=result,
                           cycle_ms=(done_ns - trigger.t_mono_ns) / 1e6, t_done_mono_ns=done_ns,
                           published=told, recipe=trigger.recipe)
        self.last_job = record
        self.jobs.job_finished(trigger.link, trigger.seq, result, delivered=told is not None)
        self._count(result.status, told)
        self.cycle_ms.append(record.cycle_ms)
        told_note = ("" if told is result.status else
                     "; not delivered" if told is None else f"; published as {told.name}")
        # A failed job's line ends with its top likely cause and the config key to check.
        why = f"; {result.diagnosis.summary()}" if result.diagnosis is not None else ""
        log.info("job %d: %s in %.1f ms%s%s%s", job_id, result.status.name, record.cycle_ms,
                 f" ({result.message})" if result.message else "", told_note, why)
        recorded = self.recorder is None or pair is None or self.recorder.submit(pair, result)
        self.record_dropped += not recorded
        for listener in self.listeners:
            try:
                listener(pair, record)
            except Exception:
                log.exception("job listener failed")
        self._job = None
        self._set_state(JobState.IDLE)

    def warning_bits(self) -> Warnings:
        """The warnings every link shows (``RobotLink.set_warnings``)."""
        return Warnings.RECALIBRATE if self.epipolar.warning else Warnings(0)

    async def _show_warnings(self, first: str) -> None:
        """Hand the warning bits to every link: ``first`` (about to publish) is waited for,
        the others run in the background so a slow link never delays another's result. Each
        link applies the bits in call order, so a later change cannot be overtaken."""
        bits = int(self.warning_bits())
        for name in self.links:
            if name != first:
                self._spawn(self._warnings_call(name, bits))
        await self._warnings_call(first, bits)

    async def _warnings_call(self, name: str, bits: int) -> None:
        try:
            async with asyncio.timeout(LINK_CALL_TIMEOUT_S):
                await self.links[name].set_warnings(bits)
        except Exception as err:
            log.error("link %s: set_warnings(%#x) failed: %r", name, bits, err)

    async def _link_call(self, name: str, method: str, seq: int, arg: Any) -> Any:
        """Call a link and return its answer; a failing or hanging link is logged (None) and
        never fails the job."""
        try:
            async with asyncio.timeout(LINK_CALL_TIMEOUT_S):
                return await getattr(self.links[name], method)(seq, arg)
        except Exception as err:
            log.error("link %s: %s(seq %d) failed: %r", name, method, seq, err)
            return None

    async def _publish(self, name: str, seq: int, result: JobResult) -> Status | None:
        """Publish through a link: the status its peer was told, None when it was not."""
        told = await self._link_call(name, "publish", seq, result)
        if told is None:  # failed, logged by _link_call
            return None
        if not isinstance(told, Status):
            log.error("link %s: publish(seq %d) returned %r, not a Status", name, seq, told)
            return None
        if told is not result.status:
            log.warning("link %s: seq %d: %s published as %s", name, seq, result.status.name,
                        told.name)
        return told

    async def _refuse(self, trigger: Trigger, status: Status, why: str = "") -> None:
        """Answer a trigger that gets no job (BUSY, ABORTED, a NEXT's BAD_REQUEST) and count
        what the peer got."""
        refusal = JobResult(job_id=0, status=status,
                            message=f"refused: {status.name}" + (f": {why}" if why else ""),
                            t_done_mono_ns=time.monotonic_ns())
        try:
            told = await self._publish(trigger.link, trigger.seq, refusal)
        except asyncio.CancelledError:  # shut down before the answer went out
            self._count(status, None)
            raise
        self._count(status, told, refusal=True)

    def _count(self, status: Status, told: Status | None, refusal: bool = False) -> None:
        """Count an answer by what the peer was told (``told``), or as undelivered."""
        if told is None:
            self.undelivered[status.name] += 1
            return
        self.counters[told.name] += 1
        if refusal:
            self.refusals[told.name] += 1

    # --- background tasks ---------------------------------------------------------------

    def _spawn(self, coro: Any) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def health_problem(self) -> str:
        """Why the service needs a restart ("" when healthy): the camera is faulty
        (``camera_fault``), or a job has outlived its timeout by ``WATCHDOG_GRACE_S`` (wedged)."""
        if self.camera_fault:
            return self.camera_fault
        if self._job is None:
            return ""
        age_s = (time.monotonic_ns() - self._job_started_ns) / 1e9
        limit_s = self.config.daemon.job_timeout_s + WATCHDOG_GRACE_S
        if age_s < limit_s:
            return ""
        return (f"job {self._job[0]} running for {age_s:.1f} s (daemon.job_timeout_s + "
                f"{WATCHDOG_GRACE_S:g} s = {limit_s:g} s): the job machinery is wedged")

    def healthy(self) -> bool:
        """False when the service needs a restart (``health_problem`` says why)."""
        return not self.health_problem()

    async def _watchdog(self, period_s: float) -> None:
        unhealthy = False  # logged once when it stops, once when it pings again
        while True:
            problem = self.health_problem()
            if not problem:
                self.notifier.watchdog()
                if unhealthy:
                    log.info("watchdog: healthy again, pinging systemd")
            elif not unhealthy:
                log.error("watchdog: not pinging systemd (it will restart vgripd): %s", problem)
            unhealthy = bool(problem)
            await asyncio.sleep(period_s)

    # --- status -------------------------------------------------------------------------

    def cycle_percentiles_ms(self) -> dict[str, float]:
        if not self.cycle_ms:
            return {}
        p50, p95, p99 = np.percentile(np.fromiter(self.cycle_ms, float), (50, 95, 99))
        return {"p50": float(p50), "p95": float(p95), "p99": float(p99),
                "max": max(self.cycle_ms)}

    def link_refusals(self) -> dict[str, Counter[str]]:
        """Per link, the requests it refused on its own handshake, by status name."""
        return {name: Counter(link.refusals()) for name, link in self.links.items()}

    def answered(self) -> tuple[Counter[str], Counter[str]]:
        """All answers the peers were told and the refusals among them, by status name: the
        daemon's (``counters``, ``refusals``) plus the links' own refusals."""
        by_links: Counter[str] = Counter()
        for counts in self.link_refusals().values():
            by_links.update(counts)
        return self.counters + by_links, self.refusals + by_links

    def status_line(self) -> str:
        """One line for ``systemctl status`` (sd_notify STATUS=)."""
        told, _ = self.answered()
        triggers = sum(told.values()) + sum(self.undelivered.values())
        counts = ", ".join(f"{k} {v}" for k, v in sorted(told.items()))
        if self.undelivered:
            counts += (", " if counts else "") + f"{sum(self.undelivered.values())} not delivered"
        line = f"{self.state.value}; {triggers} triggers" + (f" ({counts})" if counts else "")
        if self.last_job is not None:
            lj = self.last_job
            line += f"; last job {lj.job_id} {lj.result.status.name} {lj.cycle_ms:.0f} ms"
        if self.config.recipes and self.active_recipe is not None:
            line += f"; recipe {self.recipe_label(self.active_recipe)}"
        if self.pick_list is not None and self.pick_list.result.instances:  # several objects
            pl = self.pick_list
            line += f"; pick list {min(pl.index, pl.count)}/{pl.count}"
        if self.views is not None:
            line += f"; views {self.views.next_view - 1}/{self.views.count}"
        if self.epipolar.warning:
            line += "; RECALIBRATE"
        if self.camera_fault:
            line += "; CAMERA FAULT"
        return line

    def recipe_snapshot(self) -> dict[str, Any]:
        """The active recipe (the running or last job's; None before the first job) and every
        configured one with whether it can run."""
        active = self.active_recipe
        return {
            "active": active,
            "active_name": None if active is None else self.config.recipe_name(active),
            "recipes": [{"number": n, "name": self.config.recipe_name(n),
                         "object": self.config.for_recipe(n).object.name,
                         "problem": self.recipe_problems.get(n)}
                        for n in self.config.recipe_numbers()],
        }

    def snapshot(self) -> dict[str, Any]:
        """The status as JSON data (served by ``GET /status``)."""
        now = time.monotonic_ns()
        job = None
        if self._job is not None:
            job_id, trig, _ = self._job
            job = {"id": job_id, "link": trig.link, "seq": trig.seq, "recipe": trig.recipe,
                   "age_s": (now - self._job_started_ns) / 1e9}
        last = None
        if self.last_job is not None:
            lj = self.last_job
            last = {"id": lj.job_id, "link": lj.link, "seq": lj.seq, "recipe": lj.recipe,
                    "status": lj.result.status.name, "status_code": int(lj.result.status),
                    "published": None if lj.published is None else lj.published.name,
                    "message": lj.result.message, "cycle_ms": lj.cycle_ms,
                    "diagnosis": None if lj.result.diagnosis is None
                    else lj.result.diagnosis.as_dict(),
                    "age_s": (now - lj.t_done_mono_ns) / 1e9}
        links = []
        link_refusals = self.link_refusals()
        for name, link in self.links.items():
            h = link.health()
            links.append({"name": name, "state": h.state.value, "peer": h.peer,
                          "peers": h.peers, "last_error": h.last_error,
                          "reconnects": h.reconnects, "refusals": dict(link_refusals[name])})
        told, refused = self.answered()
        return {
            "pid": os.getpid(),
            "run_state": self.run_state.value,
            "state": self.state.value,
            "uptime_s": (now - self._t_start_ns) / 1e9 if self._t_start_ns else 0.0,
            "camera": {"type": self.config.camera.type, "open": self._camera_open,
                       "error": self._camera_error or None, "fault": self.camera_fault or None},
            "healthy": self.healthy(),
            "health_problem": self.health_problem() or None,
            "worker": None if self._worker is None else self._worker.snapshot(),
            "calibrated": not self.not_calibrated,
            "recipe": self.recipe_snapshot(),
            "job": job,
            "last_job": last,
            "pick_list": None if self.pick_list is None else {
                "job_id": self.pick_list.result.job_id, "link": self.pick_list.link,
                "count": self.pick_list.count, "index": self.pick_list.index,
                "instances": len(self.pick_list.result.instances)},
            "next_answers": dict(self.next_answers),
            "views": None if self.views is None else {
                "job_id": self.views.job_id, "link": self.views.link,
                "taken": self.views.next_view - 1, "count": self.views.count},
            "links": links,
            "counters": dict(told),
            "refusals": dict(refused),
            "undelivered": dict(self.undelivered),
            "cycle_ms": {"window": len(self.cycle_ms), **self.cycle_percentiles_ms()},
            "recalibrate": self.epipolar.snapshot(now),
            "record": None if self.recorder is None else {
                "folder": str(self.recorder.folder), "bytes": self.recorder.total_bytes},
        }
