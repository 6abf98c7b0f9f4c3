"""The walked hand-eye calibration inside the running daemon (docs/calibration-handeye.md,
"Walked calibration", "In the running daemon").

``WalkMode`` sits between the links and the job runner. While a walk runs (started with a plan
file inside the config's folder and the index of the link the robot program uses):

- that link's requests go to a :class:`~vgripd.service.links.handeye_walk.WalkServer` (NEXT,
  TRIGGER, NEXT for "unreachable"; ``NOT_FOUND`` ends the walk), whose images are taken through the
  daemon's own camera supervisor, the path every job's image takes (in the worker process when
  there is one): the camera is never opened a second time; the board's corners are found in
  a helper process of its own (``_detect``), not on the loop's interpreter;
- every other link's request (and the web view's test trigger) is answered ``BUSY`` (40) with
  job id 0, as a trigger during a job is: nothing queued, nothing answered late;
- a walk starts only while no job runs and no several-view job waits for a view.

It ends complete (``NOT_FOUND`` answered), or stopped (the web view's stop, or the daemon
stopping): the request being answered gets its answer whole; one still waiting is answered
``ABORTED`` (41). The record (``<plan stem>.walk.json`` beside the plan) is saved after every
target, so starting the same plan again resumes it. After a complete walk, the image request
that completed it sent again (its ``NOT_FOUND`` came too late for the program) before any other
request of the walk link is answered ``NOT_FOUND`` again, not run as a job.

Solving runs ``vgripd calibrate handeye --samples WALK --intrinsics CONFIG`` in a child process
(the solver with its plausibility checks; the loop keeps serving the PLC) and writes the
include file ``<plan stem>.handeye.toml`` beside the config; a refusal keeps the solver's reason
and writes nothing. Applying it is the web view's accept (``web.walking``): only when told.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import json
import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from vgripd.calib.boards import Board, Detection, detect
from vgripd.calib.handeye.plan import load_plan, plan_inside
from vgripd.calib.handeye.walk import NOT_SEEN, SEEN, UNREACHABLE, Walk
from vgripd.errors import CalibrationError, CameraError, ConfigError, VgripError
from vgripd.geometry.camera_model import CameraModel
from vgripd.peer.jobcore import Command
from vgripd.service.host import children
from vgripd.service.host.children import ChildSetup, end_pool, start_child
from vgripd.service.host.commands import CommandTimeout, run_vgripd
from vgripd.service.host.tasks import Background
from vgripd.service.jobs.runner import JobRunner
from vgripd.service.links.handeye_walk import WalkServer, walk_refusal
from vgripd.service.links.protocol import Trigger
from vgripd.service.links.supervision import LinkSupervisor, link_names
from vgripd.service.worker.cameras import CameraSupervisor
from vgripd.service.worker.child import WORKER_NICE, WORKER_NICE_FLOOR
from vgripd.types import JobResult, Status

log = logging.getLogger("vgripd.calib.walk")

#: The solver in its child process gets this long.
SOLVE_TIMEOUT_S = 600.0


#: A board search still running when the walk ends gets this long, then its process is ended.
FINDER_STOP_S = 30.0


def _finder_setup() -> ChildSetup:
    """The board finder's process: ends with the daemon, runs below the daemon as the worker
    does (its SIGTERM ends it at once: it holds nothing)."""
    return ChildSetup.here(nice_below=WORKER_NICE, nice_floor=WORKER_NICE_FLOOR)


class WalkRefused(VgripError):
    """A walk action that cannot be done now (the message says why); nothing changed."""


class WalkState(enum.Enum):
    IDLE = "idle"  # no walk since the start
    WALKING = "walking"
    COMPLETE = "complete"  # every target has a record
    STOPPED = "stopped"  # stopped before the end: start the same plan again to resume
    FAILED = "failed"  # the record could not be saved (``message``)


def solved_file(config_path: Path, plan: str) -> Path:
    """Where the solved hand-eye goes: ``<plan stem>.handeye.toml`` beside the config."""
    return config_path.absolute().parent / (Path(plan).stem + ".handeye.toml")


class WalkMode:
    """The walk of one plan over one link, served by the running daemon (module docstring)."""

    def __init__(self, runner: JobRunner, links: LinkSupervisor, cameras: CameraSupervisor,
                 background: Background, changed: Callable[[], None]) -> None:
        self.runner = runner
        self.links = links
        self.cameras = cameras
        self._background = background
        self._changed = changed
        self.state = WalkState.IDLE
        self.message = ""
        self.link = ""  # the walk link's name
        self.link_index = -1
        self.server: WalkServer | None = None
        self.walk: Walk | None = None
        self.task: asyncio.Task[None] | None = None
        #: The last solve: ``{"ok", "file", "summary" | "reason", "walk"}`` (None: not solved).
        self.solution: dict[str, Any] | None = None
        self.solving = False
        #: Called with the snapshot after every change (the web view's event stream).
        self.listeners: list[Callable[[dict[str, Any]], None]] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self._loop_thread = 0
        self._finder: ProcessPoolExecutor | None = None
        #: the walk is complete and no other request of its link came since: the request
        #: that completed it, sent again, gets its answer again (``WalkServer.repeats_last``)
        self._after_walk = False

    def bind(self) -> None:
        """Bind to the running loop (links may call ``on_trigger`` from their threads)."""
        self._loop = asyncio.get_running_loop()
        self._loop_thread = threading.get_ident()

    @property
    def walking(self) -> bool:
        return self.state is WalkState.WALKING

    # --- requests -------------------------------------------------------------------------

    def on_trigger(self, trigger: Trigger) -> None:
        """Every link's requests come here first: the walk's, BUSY for others, else a job."""
        if self._loop is not None and threading.get_ident() != self._loop_thread:
            self._loop.call_soon_threadsafe(self.on_trigger, trigger)
            return
        server = self.server
        if server is not None and server.complete and trigger.link == self.link:
            if self._after_walk and server.repeats_last(trigger):
                self._background.spawn(server.answer_again(trigger))
                return
            self._after_walk = False  # the program goes on: its requests are jobs again
        if not self.walking or server is None or server.complete:
            self.runner.on_trigger(trigger)
        elif trigger.link == self.link:
            server.on_trigger(trigger)
        else:
            log.warning("request seq %d from %s refused: BUSY (a hand-eye walk runs on %s)",
                        trigger.seq, trigger.link, self.link)
            self.runner.refuse(trigger, Status.BUSY, f"a hand-eye walk runs on link {self.link}")

    # --- start and stop -------------------------------------------------------------------

    def start(self, config_path: Path, plan: str | Path, link_index: int) -> dict[str, Any]:
        """Start (or resume) walking ``plan`` over link ``link_index``; ``WalkRefused`` why not."""
        if self.walking:
            raise WalkRefused(f"a walk runs already ({self._plan_name()} on {self.link}): "
                              "stop it first")
        if self.solving:
            raise WalkRefused("a solve runs: wait for it")
        if self.runner.job is not None or self.runner.views is not None:
            raise WalkRefused("a job runs: start the walk between jobs")
        config = self.runner.config
        names = link_names(config)
        if not 0 <= link_index < len(names):
            raise WalkRefused(f"link {link_index}: the config has {len(names)} [[links]]")
        if config.calibration is None:
            raise WalkRefused("no [calibration]: calibrate the camera first (the order is: "
                              "cameras/rig -> hand-eye -> teach)")
        refusal = walk_refusal(self.links.links[names[link_index]], f"links.{link_index}")
        if refusal is not None:
            raise WalkRefused(refusal)
        path = plan_inside(config_path, plan)
        left = config.calibration.left
        camera = CameraModel(left.fx, left.fy, left.cx, left.cy, left.skew, left.dist,
                             left.width, left.height)
        try:
            loaded = load_plan(str(path))
            walk = Walk(path.with_suffix(".walk.json"), loaded, Board.parse(loaded.board),
                        camera)
        except (CalibrationError, ConfigError, OSError) as err:
            raise WalkRefused(str(err)) from None
        walk.detect = self._detect
        self.walk, self.link, self.link_index = walk, names[link_index], link_index
        self.server = WalkServer(walk, self.links.links[self.link], self._grab,
                                 config.output.vendor)
        self.server.on_answer = self._answered
        self._after_walk = True
        self.state, self.message = WalkState.WALKING, ""
        self.solution = None
        start = walk.next_index()
        log.info("walk %s: %d targets, %s; serving the robot program on link %s", walk.path,
                 len(loaded.poses), "complete already" if start is None else
                 f"from target {start}", self.link)
        self.task = self._background.spawn(self._serve(self.server), name="vgripd-walk")
        self._announce()
        return self.snapshot()

    async def _serve(self, server: WalkServer) -> None:
        try:
            await server.serve()
        except asyncio.CancelledError:
            raise
        except Exception as err:  # the record could not be saved: stop, say why
            log.exception("walk: stopped by an error")
            self._ended(WalkState.FAILED, f"{type(err).__name__}: {err}")
            await self._abort_waiting(server, f"walk failed: {err}")
            await self._close_finder()
            return
        self._ended(WalkState.COMPLETE, "every target has a record")
        await self._close_finder()

    def _ended(self, state: WalkState, message: str) -> None:
        if self.state is WalkState.WALKING:
            self.state, self.message = state, message
            link = self.links.links.get(self.link)
            if link is not None:  # NEXT is a pick-list request again
                link.set_walking(False)
            log.info("walk %s: %s (%s)", self._plan_name(), state.value, message)
            self._announce()

    async def stop(self, why: str = "stopped") -> dict[str, Any]:
        """Stop the walk (the record stays): the walk link's waiting requests answered
        ABORTED; later requests of any link are jobs again."""
        task, server = self.task, self.server
        if not self.walking or task is None or server is None:
            return self.snapshot()
        self._ended(WalkState.STOPPED, why)  # from here every link's request is a job again
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        await self._abort_waiting(server, f"walk {why}")
        await self._close_finder()
        return self.snapshot()

    async def shutdown(self) -> bool:
        """The daemon stops: stop a running walk (True when there was one)."""
        walking = self.walking
        await self.stop("stopped by the daemon's stop")
        return walking

    async def _abort_waiting(self, server: WalkServer, why: str) -> None:
        for trigger in server.waiting():
            result = JobResult(0, Status.ABORTED, f"refused: ABORTED: {why}",
                               t_done_mono_ns=time.monotonic_ns())
            told = await self.links.publish(trigger.link, trigger.seq, result)
            self.runner.count(Status.ABORTED, told, refusal=True)

    async def _grab(self) -> np.ndarray:
        """One image through the daemon's camera (the path of a job's), as 8-bit array."""
        config = self.runner.config
        timeout_s = config.daemon.job_timeout_s
        trigger = Trigger(self.link, 0, int(Command.TRIGGER), time.monotonic_ns())
        try:
            async with asyncio.timeout(timeout_s + 1.0):
                pair = await self.cameras.acquire(trigger, trigger.t_mono_ns
                                                  + int(timeout_s * 1e9))
        except TimeoutError:
            raise CameraError(f"no image within daemon.job_timeout_s = {timeout_s:g} s") from None
        return np.array(pair.left, copy=True)  # the worker's shared memory is reused

    def _detect(self, board: Board, image: np.ndarray, name: str) -> Detection:
        """The board finder in a helper process, so that the CPU work of finding corners does
        not hold the event loop's interpreter (called on the walk's record thread)."""
        if self._finder is None:
            self._finder = ProcessPoolExecutor(1, mp_context=children.context(),
                                               initializer=start_child,
                                               initargs=(_finder_setup(),))
        return self._finder.submit(detect, board, image, name).result()

    async def _close_finder(self) -> None:
        finder, self._finder = self._finder, None
        if finder is not None:  # waits for a search still running (off the loop)
            await asyncio.to_thread(end_pool, finder, FINDER_STOP_S)

    def _answered(self) -> None:
        self._announce()

    # --- solving --------------------------------------------------------------------------

    async def solve(self, config_path: Path) -> dict[str, Any]:
        """Solve the walk's record with ``vgripd calibrate handeye`` in a child process: the
        include file beside the config, or the solver's refusal (nothing written)."""
        if self.walking:
            raise WalkRefused("the walk runs: wait until it is complete, or stop it")
        if self.solving:
            raise WalkRefused("a solve runs already")
        walk = self.walk
        if walk is None or not walk.path.exists():
            raise WalkRefused("no walk record: start a walk first")
        out = solved_file(config_path, walk.plan.path)
        self.solving = True
        self._announce()
        try:
            rc, stdout, stderr = await run_vgripd(
                ["calibrate", "handeye", "--samples", str(walk.path), "--intrinsics",
                 str(config_path), "-o", str(out), "--json"], SOLVE_TIMEOUT_S)
        except CommandTimeout as err:
            rc, stdout, stderr = 1, "", str(err)
        finally:
            self.solving = False
        if rc == 0:
            try:
                summary = json.loads(stdout)
            except ValueError:
                summary = {}
            self.solution = {"ok": True, "file": str(out), "walk": str(walk.path),
                             "summary": summary}
            log.info("walk %s: solved, written %s", walk.path, out)
        else:
            lines = [ln.removeprefix("error: ").removeprefix("vgripd: ")
                     for ln in stderr.strip().splitlines() if ln]
            reason = "\n".join(lines[-20:]) or f"the solver exited with {rc}"
            self.solution = {"ok": False, "file": None, "walk": str(walk.path),
                             "reason": reason}
            log.warning("walk %s: solve refused: %s", walk.path, reason)
        self._announce()
        return self.snapshot()

    # --- what the status and the pages show -------------------------------------------------

    def _plan_name(self) -> str:
        return "" if self.walk is None else str(self.walk.plan.path)

    def snapshot(self) -> dict[str, Any]:
        """The walk as ``/api/status`` shows it (``walk``)."""
        walk = self.walk
        out: dict[str, Any] = {"state": self.state.value, "message": self.message,
                               "link": self.link or None, "solving": self.solving,
                               "solution": self.solution}
        if walk is None:
            return out
        statuses = [r.status for r in walk.records.values()]
        out.update(plan=str(walk.plan.path), record=str(walk.path),
                   targets=len(walk.plan.poses), index=walk.next_index(),
                   pending=None if self.server is None else self.server.pending,
                   seen=statuses.count(SEEN), not_seen=statuses.count(NOT_SEEN),
                   unreachable=statuses.count(UNREACHABLE),
                   records=[{"target": r.index, "status": r.status, "reason": r.reason,
                             "corners": 0 if r.px is None else len(r.px)}
                            for _, r in sorted(walk.records.items())])
        return out

    def _announce(self) -> None:
        data = self.snapshot()
        for listener in list(self.listeners):
            try:
                listener(data)
            except Exception:
                log.exception("walk listener failed")
        self._changed()
