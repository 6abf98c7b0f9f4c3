"""The job runner: triggers admitted, images taken, processed, answers published.

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
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import enum
import logging
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from vgripd.config import Config, unknown_recipe
from vgripd.errors import CameraError, NotCalibratedError
from vgripd.peer.jobcore import (
    Admission,
    Admit,
    Command,
    JobCore,
    PickCursor,
    ViewsAt,
    ViewStep,
    pick_position,
    view_admission,
)
from vgripd.peer.registers import Warnings
from vgripd.service.host.tasks import Background
from vgripd.service.jobs.beltlines import belt_lines
from vgripd.service.jobs.jobrecord import EpipolarMonitor, JobListener, JobRecord
from vgripd.service.links.protocol import Trigger
from vgripd.service.links.supervision import LinkSupervisor
from vgripd.service.worker.cameras import CameraSupervisor
from vgripd.service.worker.child import Processor
from vgripd.service.worker.process import WorkerClient, WorkerError, WorkerRecorder
from vgripd.service.worker.recorder import Recorder
from vgripd.types import CaptureView, ImagePair, JobResult, Status

log = logging.getLogger("vgripd")


class JobState(enum.Enum):
    IDLE = "idle"
    TRIGGERED = "triggered"
    ACQUIRING = "acquiring"
    PROCESSING = "processing"
    PUBLISHING = "publishing"


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


def scene_pose(pose: Any) -> np.ndarray:
    """A config pose as a (4, 4) transform (the vision scene's reading of it)."""
    from vgripd.vision.scene import matrix_from_pose  # heavy (OpenCV); only jobs need it

    return matrix_from_pose(pose)


def admit(core: JobCore, trigger: Trigger, accepting: bool, busy: bool) -> Admission:
    """``JobCore.trigger`` for ``trigger`` (a conveyor's NEXT and PREDICT with its count)."""
    return core.trigger(trigger.link, trigger.command, accepting, busy, trigger.recipe,
                        trigger.latch_count, time.monotonic_ns())


def belt_job(core: JobCore, trigger: Trigger, pair: ImagePair | None,
             result: JobResult) -> JobResult:
    """A conveyor job's latch (the request's count, the image's time and frame id) and its
    parts into the recipe's queue (``JobCore.belt_result``); other jobs' results unchanged.
    The line keeps the ms from the exposure to the queue entry (``BeltLine.latency_ms``)."""
    line = core.lines.get(trigger.recipe)
    if line is None or pair is None:
        return result
    frame = pair.meta.get("frame")
    latch = line.latch(trigger.latch_count, trigger.latch_frame, trigger.t_mono_ns,
                       pair.t_mono_ns, frame if isinstance(frame, int) else None)
    out = core.belt_result(trigger.recipe, latch, result)
    line.latency_ms.append((time.monotonic_ns() - pair.t_mono_ns) / 1e6)
    return out


def recipe_label(config: Config, number: int) -> str:
    """``2 (plate-b)`` for logs and messages."""
    return f"{number} ({config.recipe_name(number)})"


def failure(job_id: int, status: Status, message: str) -> JobResult:
    """A job's result without a pose (logged)."""
    log.warning("job %d: %s: %s", job_id, status.name, message)
    return JobResult(job_id=job_id, status=status, message=message,
                     t_done_mono_ns=time.monotonic_ns())


class JobRunner:
    """Triggers in, one job at a time, answers out (the module docstring has the rules).

    Admission is ``JobCore``'s and ``view_admission``'s; the camera is ``cameras``'s, the
    answers go out through ``links``. Processing runs in ``worker`` when there is one, else
    on the job thread with ``pipelines`` (by recipe). ``changed`` is called on every state
    change (the daemon's status line and waiters), the one call back into the daemon.
    """

    def __init__(self, config: Config, links: LinkSupervisor, cameras: CameraSupervisor,
                 background: Background, *, worker: WorkerClient | None,
                 pipelines: dict[int, Processor], recipe_problems: dict[int, str],
                 changed: Callable[[], None]) -> None:
        self.config = config
        self.links = links
        self.cameras = cameras
        self.worker = worker
        self.pipelines = pipelines
        self.recipe_problems = recipe_problems
        self._background = background
        self._changed = changed
        #: Whether triggers start jobs (the service is starting or running; set by the daemon).
        self.accepting = False
        #: The recipe of the running or last job (None before the first).
        self.active_recipe: int | None = None
        self.state = JobState.IDLE
        self.listeners: list[JobListener] = []
        self.recorder: Recorder | WorkerRecorder | None = None
        # What the daemon's answers told the peers, by status name: job results as published
        # and the daemon's own refusals. `snapshot()` adds the links' own refusals.
        self.counters: Counter[str] = Counter()
        self.refusals: Counter[str] = Counter()  # the daemon's refusals among `counters`
        self.undelivered: Counter[str] = Counter()  # answers whose publish failed (job status)
        self.record_dropped = 0  # jobs the recorder refused because the disk was behind
        self.cycle_ms: deque[float] = deque(maxlen=config.daemon.stats_window)
        self.last_job: JobRecord | None = None
        self.core = JobCore(belt_lines(config))  # admission, pick list, conveyor queues
        #: A several-view job between two of its views (None otherwise).
        self.views: ViewJob | None = None
        self.next_answers: Counter[str] = Counter()  # NEXT answers, by the status told
        d = config.daemon
        self.epipolar = EpipolarMonitor(d.recalibrate_window, d.recalibrate_share,
                                        d.recalibrate_min_jobs, config.vision.epipolar_warn_px)
        self.job_seq = 0
        #: The running job: its id, trigger and task (None when idle).
        self.job: tuple[int, Trigger, asyncio.Task[None]] | None = None
        self.job_started_ns = 0
        self._executor: ThreadPoolExecutor | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._loop_thread = 0

    @property
    def pick_list(self) -> PickCursor | None:
        """The last job's pick list (None: no job yet, a job running, or nothing pickable)."""
        return self.core.pick_list

    def start(self) -> None:
        """Bind to the running loop (triggers from other threads are handed to it) and start
        the job thread of the in-process path."""
        self._loop = asyncio.get_running_loop()
        self._loop_thread = threading.get_ident()
        self._executor = ThreadPoolExecutor(1, thread_name_prefix="vgripd-job")

    def close_executor(self) -> None:
        if self._executor is not None:
            # Waits only for a CPU step already running (its result is discarded).
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None

    async def abort(self) -> bool:
        """Shutdown: abort the job in flight (unless it is already publishing) or the
        several-view job waiting for its next view, answered ABORTED; True when an answer
        went out that a polling peer should still be able to read."""
        if self.job is not None:
            task = self.job[2]
            aborting = self.state is not JobState.PUBLISHING
            if aborting:
                task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
            return aborting
        if self.views is not None and self.views.last is not None:  # between two views
            views, last = self.views, self.views.last
            await self._finish(views.ending(last), views.job_id, None, failure(
                views.job_id, Status.ABORTED, f"aborted by shutdown after view "
                f"{views.next_view - 1} of {views.count}"))
            return True
        return False

    def _set_state(self, state: JobState) -> None:
        self.state = state
        self._changed()

    # --- triggers -----------------------------------------------------------------------

    def on_trigger(self, trigger: Trigger) -> None:
        """Called by a link for every trigger; from any thread, never blocks."""
        assert self._loop is not None
        if threading.get_ident() != self._loop_thread:
            self._loop.call_soon_threadsafe(self.on_trigger, trigger)
            return
        if trigger.link not in self.links.links:
            log.error("trigger from unknown link %r ignored", trigger.link)
            return
        # Links open during start-up may trigger before READY: those jobs run normally.
        admission = admit(self.core, trigger, self.accepting, busy=self.job is not None)
        if admission.kind is Admit.REFUSE:
            what = "NEXT" if admission.status is Status.BAD_REQUEST else "trigger"
            log.warning("%s seq %d from %s refused: %s%s", what, trigger.seq, trigger.link,
                        admission.status.name, f" ({admission.why})" if admission.why else "")
            self._background.spawn(self._refuse(trigger, admission.status, admission.why))
            return
        if admission.kind is Admit.NEXT:  # answered from the list, no acquisition
            assert admission.answer is not None
            self._background.spawn(self._answer_next(trigger, admission.answer))
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
                                  recipe_label(self.config, trigger.recipe),
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
            self._background.spawn(self._refuse(trigger, decision.status, decision.why))
            return
        if decision.step is ViewStep.BEGIN:
            vision = self.config.for_recipe(trigger.recipe).vision
            self.job_seq += 1
            self.core.job_started()
            self.views = ViewJob(self.job_seq, trigger.link, trigger.recipe,
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
        self.job_started_ns = time.monotonic_ns()
        self.job = (views.job_id, trigger,
                    asyncio.create_task(self._run_job(trigger, views.job_id, views)))
        self._set_state(JobState.TRIGGERED)

    def _end_views(self, trigger: Trigger, why: str) -> None:
        """End the several-view job with BAD_REQUEST, answered to ``trigger`` (the request
        that broke the sequence); its images are dropped."""
        views = self.views
        assert views is not None
        result = failure(views.job_id, Status.BAD_REQUEST,
                         f"{why} (views job ended after view {views.next_view - 1} "
                         f"of {views.count})")
        self._finish_views(views.ending(trigger), result)

    def _finish_views(self, trigger: Trigger, result: JobResult) -> None:
        """End the waiting several-view job with ``result`` as a job of its own (BUSY for
        others while it is published)."""
        views = self.views
        assert views is not None
        assert self.job is None
        self.job_started_ns = time.monotonic_ns()
        self.job = (views.job_id, trigger, asyncio.create_task(
            self._finish(trigger, views.job_id, None, result)))

    def _views_timed_out(self, views: ViewJob) -> None:
        if self.views is not views or self.job is not None or views.last is None:
            return  # the next view came meanwhile
        timeout_s = self.config.for_recipe(views.recipe).vision.view_timeout_s
        self._finish_views(views.ending(views.last), failure(
            views.job_id, Status.CAMERA_ERROR,
            f"view {views.next_view} of {views.count} not requested within "
            f"vision.view_timeout_s = {timeout_s:g} s after the previous one"))

    def _start(self, trigger: Trigger) -> None:
        """Run a one-acquisition job for ``trigger``."""
        self.core.job_started()  # a new job: the old list is nobody's any more
        self.job_seq += 1
        job_id = self.job_seq
        log.info("job %d: trigger seq %d command %d recipe %d from %s", job_id, trigger.seq,
                 trigger.command, trigger.recipe, trigger.link)
        if trigger.recipe in self.config.recipe_numbers():
            self.active_recipe = trigger.recipe
        self.job_started_ns = time.monotonic_ns()
        self.job = (job_id, trigger, asyncio.create_task(self._run_job(trigger, job_id)))
        self._set_state(JobState.TRIGGERED)

    async def _answer_next(self, trigger: Trigger, answer: JobResult) -> None:
        told = await self.links.publish(trigger.link, trigger.seq, answer)
        self._count(answer.status, told)
        self.next_answers[(told or answer.status).name] += 1
        pos = pick_position(answer)
        log.info("job %d: NEXT seq %d from %s: instance %d of %d: %s%s", answer.job_id,
                 trigger.seq, trigger.link, pos.index, pos.count, answer.status.name,
                 "" if told is answer.status else
                 "; not delivered" if told is None else f"; published as {told.name}")
        self._changed()  # status line and waiters see it

    # --- a job: acquire, process, publish -----------------------------------------------

    async def _acquire_view(self, trigger: Trigger, deadline_ns: int,
                            views: ViewJob) -> ImagePair:
        """One view of a several-view job, with its flange pose (NOT_CALIBRATED without)."""
        flange = views.flange(trigger)
        if flange is None:
            raise NotCalibratedError(
                f"view {trigger.view} of {views.count}: no flange pose: link {trigger.link} "
                "does not report the robot's pose and vision.view_poses is not set")
        pair = await self.cameras.acquire(trigger, deadline_ns,
                                          CaptureView(trigger.view, views.count, flange))
        if len(pair.views) != 1:
            raise CameraError(f"view {trigger.view}: the camera delivered {len(pair.views)} "
                              "images, a view is one")
        return pair

    async def _view_taken(self, trigger: Trigger, views: ViewJob, pair: ImagePair) -> None:
        """A view before the last: keep its image, let the robot move on, wait for the next."""
        views.pairs.append(pair)
        views.last = trigger
        await self.links.call(trigger.link, "view_captured", trigger.seq, views.job_id)
        timeout_s = self.config.for_recipe(views.recipe).vision.view_timeout_s
        assert self._loop is not None
        views.timer = self._loop.call_later(timeout_s, self._views_timed_out, views)
        log.info("job %d: view %d of %d taken", views.job_id, trigger.view, views.count)
        self.job = None
        self._set_state(JobState.IDLE)

    async def _run_job(self, trigger: Trigger, job_id: int,
                       views: ViewJob | None = None) -> None:
        """Acquire, process and publish one job; with ``views``: one view of a several-view
        job, the last of which processes all of them."""
        known = self.config.recipe_numbers()
        if views is not None:
            trigger = views.ending(trigger)  # the job's recipe, its cycle from view 1
        if trigger.recipe not in known:  # answered like any job, without taking an image
            result = failure(job_id, Status.BAD_REQUEST, unknown_recipe(trigger.recipe, known))
            await self._finish(trigger, job_id, None, result)
            return
        timeout_s = self.config.daemon.job_timeout_s
        deadline_ns = self.job_started_ns + int(timeout_s * 1e9)
        pair: ImagePair | None = None
        try:
            try:
                async with asyncio.timeout(timeout_s):
                    self._set_state(JobState.ACQUIRING)
                    if views is None:
                        pair = await self.cameras.acquire(trigger, deadline_ns)
                    else:
                        view_pair = await self._acquire_view(trigger, deadline_ns, views)
                        if trigger.view < views.count:
                            await self._view_taken(trigger, views, view_pair)
                            return
                        views.pairs.append(view_pair)
                        pair = views.combined()
                    await self.links.call(trigger.link, "image_captured", trigger.seq, job_id)
                    self._set_state(JobState.PROCESSING)
                    result = await self._process(pair, job_id, trigger.recipe)
            except TimeoutError:
                stage = "acquisition" if pair is None else "processing"
                status = Status.CAMERA_ERROR if pair is None else Status.INTERNAL
                result = failure(job_id, status,
                                 f"{stage} exceeded daemon.job_timeout_s = {timeout_s} s")
            except CameraError as err:
                result = failure(job_id, Status.CAMERA_ERROR, str(err))
            except NotCalibratedError as err:
                result = failure(job_id, Status.NOT_CALIBRATED, str(err))
            except WorkerError as err:  # died during the grab; it logged its own traceback
                result = failure(job_id, Status.INTERNAL, str(err))
            except Exception as err:
                log.exception("job %d: unexpected error", job_id)
                result = failure(job_id, Status.INTERNAL, f"{type(err).__name__}: {err}")
        except asyncio.CancelledError:
            result = failure(job_id, Status.ABORTED, "aborted by shutdown")
            await self._finish(trigger, job_id, pair, result)
            raise
        await self._finish(trigger, job_id, pair, result)

    async def _process(self, pair: ImagePair, job_id: int, recipe: int = 0) -> JobResult:
        problem = self.recipe_problems.get(recipe)
        if problem:
            where = f"recipe {recipe_label(self.config, recipe)}: " if recipe else ""
            return failure(job_id, Status.NOT_CALIBRATED, where + problem)
        t0 = time.monotonic_ns()
        if self.worker is not None:
            try:
                result = await self.worker.process(pair, job_id, recipe)
            except WorkerError as err:  # died or raised; the worker logged the traceback
                return failure(job_id, Status.INTERNAL, str(err))
        else:
            assert self._loop is not None
            result = await self._loop.run_in_executor(
                self._executor, self.pipelines[recipe].process, pair, job_id)
        timings = {"acquire": (t0 - self.job_started_ns) / 1e6, **result.timings_ms,
                   "process": (time.monotonic_ns() - t0) / 1e6}
        return dataclasses.replace(
            result, job_id=job_id, timings_ms=timings,
            t_capture_mono_ns=result.t_capture_mono_ns or pair.t_mono_ns)

    async def _finish(self, trigger: Trigger, job_id: int, pair: ImagePair | None,
                      result: JobResult) -> None:
        self._set_state(JobState.PUBLISHING)
        if self.views is not None and self.views.job_id == job_id:  # its images are done
            if self.views.timer is not None:
                self.views.timer.cancel()
            self.views = None
        result = dataclasses.replace(result, recipe=trigger.recipe,
                                     t_done_mono_ns=result.t_done_mono_ns or time.monotonic_ns())
        result = belt_job(self.core, trigger, pair, result)  # a conveyor's parts: queued
        epipolar_px = result.residuals.get("epipolar_px")
        if epipolar_px is not None and self.epipolar.add(epipolar_px, result.t_done_mono_ns):
            if self.epipolar.warning:
                log.warning("RECALIBRATE: %s; the stereo rig may have moved, recalibrate it",
                            self.epipolar.describe())
            else:
                log.info("RECALIBRATE cleared: %s", self.epipolar.describe())
            await self.links.show_warnings(trigger.link, int(self.warning_bits()))
        told = await self.links.publish(trigger.link, trigger.seq, result)
        done_ns = time.monotonic_ns()
        record = JobRecord(job_id=job_id, link=trigger.link, seq=trigger.seq, result=result,
                           cycle_ms=(done_ns - trigger.t_mono_ns) / 1e6, t_done_mono_ns=done_ns,
                           published=told, recipe=trigger.recipe)
        self.last_job = record
        self.core.job_finished(trigger.link, trigger.seq, result, delivered=told is not None)
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
        self.job = None
        self._set_state(JobState.IDLE)

    def warning_bits(self) -> Warnings:
        """The warnings every link shows (``RobotLink.set_warnings``)."""
        return Warnings.RECALIBRATE if self.epipolar.warning else Warnings(0)

    # --- answers ------------------------------------------------------------------------

    def refuse(self, trigger: Trigger, status: Status, why: str = "") -> None:
        """Answer ``trigger`` with ``status`` and no job, in the background (a walk's BUSY)."""
        self._background.spawn(self._refuse(trigger, status, why))

    async def _refuse(self, trigger: Trigger, status: Status, why: str = "") -> None:
        """Answer a trigger that gets no job (BUSY, ABORTED, a NEXT's BAD_REQUEST) and count
        what the peer got."""
        refusal = JobResult(job_id=0, status=status,
                            message=f"refused: {status.name}" + (f": {why}" if why else ""),
                            t_done_mono_ns=time.monotonic_ns())
        try:
            told = await self.links.publish(trigger.link, trigger.seq, refusal)
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

    count = _count  # for the walk's answers (``walkmode``)
