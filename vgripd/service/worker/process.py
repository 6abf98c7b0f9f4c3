"""The worker process: camera driver, vision pipeline and recorder outside the daemon's interpreter.

Why a process: the event loop answers the robot links (a PLC polling at 100 Hz expects an answer
in about a millisecond). Rendering or grabbing images, finding features and encoding PNGs hold
the GIL for tens of milliseconds at a time, so a thread executor still stalls the loop. In the
worker they run under their own GIL; the daemon's interpreter only handles links and state.

What runs where::

    daemon (asyncio)                          worker process (spawned, long-lived)
    ----------------                          ------------------------------------
    WorkerCamera.open/grab/close    ------->  the configured camera driver
        <- images in shared memory, metadata pickled
    WorkerClient.process(pair, job_id, recipe) -> Pipeline.process (one per recipe, built once)
        <- JobResult (pickled, a few kB)
    WorkerRecorder.submit(pair, result) --->  Recorder (PNG encoding + writing, its own thread)

The daemon asks in two steps, grab then process, so the image-captured signal goes out as soon
as the grab returns. Images never travel through a pickle: the daemon owns one shared-memory
segment (``/dev/shm/vgripd-<pid>-<token>-<n>``, created at start, reused, replaced only when
images do not fit or a listener still holds the previous pair's images; always unlinked on close
and when replaced). The worker writes a grabbed pair into it; the daemon maps the images
read-only without copying (``ImageSegment.view_images``) for its listeners. A pair the worker
did not grab itself (a test, a replayed pair) goes the other way through the same segment. The
worker keeps the last pair it grabbed or received, so ``process`` and ``record`` name it by a
token instead of sending the pixels again.

Requests and answers are length-prefixed pickles on a Unix socket pair: ``HEADER`` (payload
length, request id) then the payload. One request runs at a time in the worker, in order.

Failures:

- The worker dies (killed, segfault, out of memory): the request in flight fails with
  ``WorkerError("worker process exited with signal 9 (SIGKILL)")``, a new worker is started at
  once, the next request waits for it. A grab is tried once more on the new worker, and when
  the dead one held the camera ``camera_lost`` tells the daemon, which opens it again there.
  A worker that dies before it is ready is restarted with doubling back-off (1 s .. 60 s);
  requests meanwhile fail at once naming the reason.
- The daemon abandons a request (job timeout, shutdown): the worker cannot be interrupted, so
  it is killed (SIGKILL) and restarted. This is what bounds a stuck computation or a hung
  camera driver now.
- An exception in the worker (a camera failure is re-raised as ``CameraError``, anything else
  as ``WorkerError`` with the remote type, message and traceback) or a request or answer that
  cannot be unpickled fails that request only; the worker stays.

The worker ends with its daemon, whatever way the daemon ends:

- The daemon stops it after the links (``close``), so queued recordings are written; it also
  exits when the daemon's end of the socket closes.
- SIGINT is ignored (a terminal sends it to the whole process group on Ctrl-C; the daemon stops
  the worker itself). SIGTERM (systemd signals the whole control group on stop) leaves the
  daemon ``TERM_GRACE_S`` to stop the worker in order; after that the kernel ends it (an
  ``alarm``, which needs no Python code to run), and at once when the daemon is already gone.
- The daemon killed (SIGKILL, a crash): the kernel sends the worker SIGKILL
  (``PR_SET_PDEATHSIG``, ``die_with_daemon``), even in the middle of a computation.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import itertools
import logging
import os
import pickle
import secrets
import signal
import socket
import time
import weakref
from collections.abc import Callable
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import Any

from vgripd.config import Config
from vgripd.errors import CameraError, CameraSettingError
from vgripd.service.host import children
from vgripd.service.host.children import end_process, wait_exit
from vgripd.service.worker.child import HEADER, _frame, _wire_result, worker_main, worker_setup
from vgripd.service.worker.imageshm import SHM_DIR as SHM_DIR  # where tests look for segments
from vgripd.service.worker.imageshm import (
    ImageLayout,
    ImageSegment,
    WorkerError,
    _aligned,
    _pair_fields,
    _pair_of,
    images_nbytes,
    segments_of,
    sweep_stale_segments,
    write_images,
)
from vgripd.types import CaptureView, ImagePair, JobResult

log = logging.getLogger("vgripd.worker")

#: The processor the worker builds from the config (``module:Class``, called with the Config).
DEFAULT_PROCESSOR = "vgripd.vision.checked:CheckedPipeline"
#: Requests after which the worker may hold the camera (until a ``camera_close``).
_CAMERA_OPS = frozenset({"camera_open", "camera_grab", "camera_settings", "camera_focus"})
#: Spawn, imports, pipeline and recorder set-up; a worker not ready by then is killed.
START_TIMEOUT_S = 60.0
#: A graceful stop waits this long for queued recordings before the worker is killed.
STOP_TIMEOUT_S = 15.0
#: Closing the camera through the worker (the driver's own close waits up to 5 s).
CAMERA_CLOSE_TIMEOUT_S = 7.0
#: Back-off for a worker that dies before it is ready: doubling from the first to the last.
RESTART_BACKOFF_S = (1.0, 60.0)


def describe_exit(exitcode: int | None) -> str:
    """``worker process exited with signal 9 (SIGKILL)`` / ``... with code 1``."""
    if exitcode is None:
        return "worker process closed its connection"
    if exitcode < 0:
        try:
            name = signal.Signals(-exitcode).name
        except ValueError:
            name = "unknown signal"
        return f"worker process exited with signal {-exitcode} ({name})"
    return f"worker process exited with code {exitcode}"


# --- the daemon side -------------------------------------------------------------------------

@dataclasses.dataclass(eq=False)
class _Generation:
    """One worker process and its connection."""

    proc: BaseProcess
    pid: int
    reader: asyncio.StreamReader
    writer: asyncio.StreamWriter
    ready: asyncio.Future[Any]  # the worker's ready answer: pid and warmed recipes
    pending: dict[int, asyncio.Future[Any]] = dataclasses.field(default_factory=dict)
    reader_task: asyncio.Task[None] | None = None
    killed_because: str = ""
    exited: bool = False
    #: The worker may hold the camera: asked to open, grab or set it, not closed since.
    holds_camera: bool = False

    def is_ready(self) -> bool:
        return self.ready.done() and self.ready.exception() is None

    def start_error(self) -> BaseException | None:
        return self.ready.exception() if self.ready.done() else None


class WorkerClient:
    """The daemon's handle on its worker process (one at a time, restarted when it dies).
    ``config`` is sent to the worker, which builds the camera driver, the processor
    (``processor``: ``module:Class`` called with the config) and, when ``record.enabled``, the
    recorder from it. Uses no thread in the daemon: the socket is read by a loop task and the
    worker's exit is seen on its sentinel file descriptor."""

    def __init__(self, config: Config, processor: str = DEFAULT_PROCESSOR,
                 describe_camera: str = "") -> None:
        self.config = config
        self.processor = processor
        # Unique per daemon (pid) and per client (token): names of the shared memory.
        self.prefix = f"vgripd-{os.getpid()}-{secrets.token_hex(3)}-"
        self.camera = WorkerCamera(self, config.camera.type, describe_camera)
        self.recorder = WorkerRecorder(self, config.record.folder)
        self.record_bytes = 0  # the worker's Recorder.total_bytes, with every answer
        self.restarts = 0
        self.last_exit = ""
        #: Called with the reason when a worker that held the camera died and is replaced.
        self.camera_lost: Callable[[str], None] | None = None
        self._ctx = children.context()
        self._gen: _Generation | None = None
        self._starting: asyncio.Task[None] | None = None
        self._next_start_mono = 0.0
        self._backoff_s = 0.0
        self._closing = False
        self._stopping = False  # ``stopping()``: no new worker after a death
        self._ids = itertools.count(1)
        self._segment_ids = itertools.count(1)
        self._segment: ImageSegment | None = None
        # The pair the current worker holds: generation, token, weak references to the daemon's
        # arrays (a pair handed back is named by its token).
        self._held: tuple[_Generation, int, tuple[weakref.ref[Any], ...]] | None = None

    # --- life cycle --------------------------------------------------------------------

    async def start(self) -> None:
        """Create the shared memory and spawn the worker; requests wait until it is ready."""
        self._closing = self._stopping = False
        swept = sweep_stale_segments()
        if swept:
            log.warning("removed shared memory left by vgripd daemons that no longer run: %s",
                        ", ".join(swept))
        size = _initial_segment_bytes(self.config)
        if size:
            self._new_segment(size)
        self._spawn_soon(0.0)

    async def wait_ready(self) -> None:
        """Wait until a worker is ready (WorkerError when it cannot start)."""
        await self._ready_generation()

    def _new_segment(self, size: int) -> ImageSegment:
        old, self._segment = self._segment, None
        if old is not None:
            old.close()  # unlinked; images still viewed keep their own mapping
        self._segment = ImageSegment(f"{self.prefix}{next(self._segment_ids)}", size)
        return self._segment

    def _writable_segment(self, need: int = 0) -> ImageSegment | None:
        """The segment to put the next images in: the current one unless it is too small or
        images viewed from it are still alive (a listener kept a pair), else a new one."""
        segment = self._segment
        if segment is not None and segment.size >= need and not segment.in_use():
            return segment
        size = max(need, segment.size if segment is not None else 0)
        return self._new_segment(size) if size else None

    def _hold(self, gen: _Generation, token: int, pair: ImagePair) -> None:
        self._held = (gen, token, tuple(weakref.ref(image) for image in pair.views))

    def _holds(self, gen: _Generation, pair: ImagePair) -> int | None:
        """The token under which ``gen`` holds ``pair``'s images, if it does."""
        held = self._held
        if held is None or held[0] is not gen or len(held[2]) != len(pair.views):
            return None
        same = all(image is ref() for image, ref in zip(pair.views, held[2], strict=True))
        return held[1] if same else None

    async def close(self) -> None:
        """Stop the worker (queued recordings are written first), unlink the shared memory."""
        self._closing = True
        try:
            if self._starting is not None:
                self._starting.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await self._starting
            gen = self._gen
            if gen is not None:
                await self._stop(gen)
        finally:
            if self._segment is not None:
                self._segment.close()
                self._segment = None
            for name in segments_of(self.prefix):  # left behind by a crash (never, so far)
                with contextlib.suppress(OSError):
                    ImageSegment.unlink_name(name)

    async def _stop(self, gen: _Generation) -> None:
        """Ask the worker to stop (it closes the camera, writes queued recordings, answers and
        exits); kill it when it is busy or does not exit in time. ``_read`` reaps it."""
        if gen.is_ready() and not gen.pending and not gen.exited:
            self._send(gen, "stop", ())
        else:
            self._kill(gen, "stopped")
        assert gen.reader_task is not None
        try:
            async with asyncio.timeout(STOP_TIMEOUT_S):
                await asyncio.shield(gen.reader_task)
        except TimeoutError:
            self._kill(gen, f"did not stop within {STOP_TIMEOUT_S:g} s")
            await gen.reader_task

    def stopping(self) -> None:
        """The daemon is shutting down: a worker that dies from now on (killed with the job
        it abandons) is not replaced; ``close`` follows."""
        self._stopping = True

    def _spawn_soon(self, delay_s: float) -> None:
        if self._closing or self._stopping or self._starting is not None:
            return
        self._next_start_mono = time.monotonic() + delay_s
        self._starting = asyncio.create_task(self._spawn(delay_s), name="vgripd-worker-start")
        self._starting.add_done_callback(_consume)

    async def _spawn(self, delay_s: float) -> None:
        proc: BaseProcess | None = None
        parent: socket.socket | None = None
        try:
            if delay_s:
                await asyncio.sleep(delay_s)
            parent, child = socket.socketpair()
            try:
                # The server ready off the event loop (its imports take seconds on a busy
                # machine); then the start, a fork of it, takes milliseconds.
                await asyncio.to_thread(children.start_server)
                proc = self._ctx.Process(
                    target=worker_main, name="vgripd-worker", daemon=True,
                    args=(child, self.config, self.processor,
                          worker_setup(self.config.daemon.log_level)))
                proc.start()
            finally:
                child.close()
            reader, writer = await asyncio.open_connection(sock=parent)
            assert proc.pid is not None
            gen = _Generation(proc, proc.pid, reader, writer,
                              asyncio.get_running_loop().create_future())
            gen.ready.add_done_callback(_consume)
            proc = parent = None  # owned by the generation now
            self._gen = gen
            gen.reader_task = asyncio.create_task(self._read(gen), name="vgripd-worker-read")
            log.info("worker process %d started", gen.pid)
        finally:
            self._starting = None
            if proc is not None and proc.pid is not None:  # cancelled half way
                end_process(proc)
            if parent is not None:
                parent.close()

    async def _ready_generation(self) -> _Generation:
        """The worker once it is ready; WorkerError when there is none to wait for."""
        while True:
            if self._closing:
                raise WorkerError("the worker process is stopped")
            gen = self._gen
            if gen is None:
                if self._starting is None:
                    self._spawn_soon(0.0)
                elif self._backoff_s and time.monotonic() < self._next_start_mono - 0.05:
                    raise WorkerError(f"{self.last_exit}; next start in "
                                      f"{self._next_start_mono - time.monotonic():.0f} s")
                assert self._starting is not None
                await asyncio.shield(self._starting)
                continue
            if (gen.killed_because or gen.start_error()) and gen.reader_task is not None:
                await asyncio.shield(gen.reader_task)  # on its way out: see what comes next
                continue
            try:
                async with asyncio.timeout(START_TIMEOUT_S):
                    await asyncio.shield(gen.ready)
            except TimeoutError:
                self._kill(gen, f"not ready within {START_TIMEOUT_S:g} s")
                raise WorkerError(f"worker process not ready within {START_TIMEOUT_S:g} s"
                                  ) from None
            if gen is self._gen:
                return gen

    async def _read(self, gen: _Generation) -> None:
        """Hand out the worker's answers until its end closes, then reap it."""
        try:
            while True:
                head = await gen.reader.readexactly(HEADER.size)
                length, req_id = HEADER.unpack(head)
                self._dispatch(gen, req_id, await gen.reader.readexactly(length))
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            gen.writer.close()
            if not await wait_exit(gen.proc, 2.0):  # alive but closed its end: a bug
                self._kill(gen, "closed its connection")
                await wait_exit(gen.proc, 10.0)
            exitcode = gen.proc.exitcode
            gen.exited = exitcode is not None
            if gen.exited:
                gen.proc.close()
            self._died(gen, describe_exit(exitcode))

    def _dispatch(self, gen: _Generation, req_id: int, payload: bytes) -> None:
        error: BaseException | None = None
        try:
            ok, value, rec_bytes = pickle.loads(payload)
        except Exception as err:
            ok, value = False, None
            error = WorkerError(f"cannot read the worker's answer: {type(err).__name__}: {err}")
        else:
            self.record_bytes = rec_bytes
            if not ok:
                error = _remote_error(value)
        if req_id == 0:  # "ready" (or failed to start), or a failed request that wanted no answer
            fut = None if gen.ready.done() else gen.ready
        else:
            fut = gen.pending.pop(req_id, None)
        if fut is None:  # nobody waits for it (a recording)
            if error is not None:
                log.error("worker: %s", error)
        elif error is None:
            _resolve(fut, value)
        else:
            _fail(fut, error)

    def _died(self, gen: _Generation, reason: str) -> None:
        start_error = gen.start_error()
        was_ready = gen.ready.done() and start_error is None
        if start_error is not None:
            reason = f"{start_error} ({reason})"
        self.last_exit = reason
        err = WorkerError(reason)
        for fut in gen.pending.values():
            _fail(fut, err)
        gen.pending.clear()
        _fail(gen.ready, err)
        if self._gen is gen:
            self._gen = None
        if self._held is not None and self._held[0] is gen:
            self._held = None
        if self._closing:
            return
        if self._stopping:
            log.info("%s; not replaced, vgripd is stopping", reason)
            return
        self.restarts += 1
        if gen.holds_camera and self.camera_lost is not None:
            self.camera_lost(reason)
        if was_ready:
            self._backoff_s = 0.0
        else:
            lo, hi = RESTART_BACKOFF_S
            self._backoff_s = min(hi, max(lo, 2 * self._backoff_s))
        log.warning("%s%s; starting a new one%s", reason,
                    f" (killed: {gen.killed_because})" if gen.killed_because else "",
                    f" in {self._backoff_s:g} s" if self._backoff_s else "")
        self._spawn_soon(self._backoff_s)

    def _kill(self, gen: _Generation, because: str) -> None:
        """SIGKILL a worker (busy with what nobody waits for); ``_read`` reaps and replaces it."""
        if gen.exited or gen.killed_because:
            return
        gen.killed_because = because
        if because != "stopped":
            log.warning("killing worker process %d: %s", gen.pid, because)
        gen.proc.kill()

    # --- requests --------------------------------------------------------------------------

    def _send(self, gen: _Generation, op: str, args: tuple[Any, ...],
              reply: bool = True) -> asyncio.Future[Any]:
        """Write one request; the future gets the answer (done at once when ``reply=False``)."""
        req_id = next(self._ids) if reply else 0
        fut: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        if reply:
            gen.pending[req_id] = fut
        else:
            fut.set_result(None)
        gen.writer.write(_frame(req_id, pickle.dumps((op, args), pickle.HIGHEST_PROTOCOL)))
        return fut

    async def _call(self, gen: _Generation, op: str, args: tuple[Any, ...], what: str) -> Any:
        """Send one request and wait for its answer. Cancelled while the worker is on it, the
        worker is killed (there is no other way to interrupt it) and replaced."""
        gen.holds_camera = op in _CAMERA_OPS or (gen.holds_camera and op != "camera_close")
        fut = self._send(gen, op, args)
        try:
            return await asyncio.shield(fut)
        except asyncio.CancelledError:
            if not fut.done():
                fut.cancel()
                self._kill(gen, f"{what} abandoned")
            raise

    async def call(self, op: str, *args: Any, what: str = "") -> Any:
        return await self._call(await self._ready_generation(), op, args, what or op)

    def _ref(self, gen: _Generation, pair: ImagePair
             ) -> tuple[int, dict[str, Any], str | None, ImageLayout | None]:
        """How a request names ``pair``: by token when the worker holds its images, else the
        images go into the shared memory now."""
        token = self._holds(gen, pair)
        if token is not None:
            return token, _pair_fields(pair), None, None
        images = pair.views
        segment = self._writable_segment(images_nbytes(images))
        assert segment is not None
        layout = write_images(segment.buf, images)
        token = next(self._ids)
        self._hold(gen, token, pair)
        return token, _pair_fields(pair), segment.name, layout

    async def process(self, pair: ImagePair, job_id: int, recipe: int = 0) -> JobResult:
        """``Processor.process(pair, job_id)`` in the worker, by the pipeline of ``recipe``."""
        gen = await self._ready_generation()
        result: JobResult = await self._call(gen, "process",
                                             (self._ref(gen, pair), job_id, recipe),
                                             f"job {job_id}")
        return result

    async def grab(self, timeout_s: float, view: CaptureView | None = None,
                   recipe: int = 0) -> ImagePair:
        """The camera driver's ``grab`` in the worker; the images come through shared memory.

        A worker that died while idle is only noticed when the next request fails; a grab
        touches nothing on the robot's side, so it is tried once more on the new worker
        instead of failing the job of a PLC that triggered just after the death."""
        deadline = time.monotonic() + timeout_s
        gen = await self._ready_generation()
        segment = self._writable_segment()
        args = (timeout_s, None if segment is None else segment.name, view, recipe)
        try:
            token, fields, layout, need = await self._call(gen, "camera_grab", args, "grab")
        except WorkerError:
            if self._gen is gen or gen.killed_because:  # not a death, or one we caused
                raise
            log.warning("grab: the worker process had died (%s); grabbing on a new one",
                        self.last_exit)
            gen = await self._ready_generation()
            # the time left of the job's, after the new worker has started
            args = (max(0.0, deadline - time.monotonic()), *args[1:])
            token, fields, layout, need = await self._call(gen, "camera_grab", args, "grab")
        if layout is None:  # no segment yet, or too small: a bigger one, then fetch again
            segment = self._new_segment(need)
            layout = await self._call(gen, "camera_put", (token, segment.name), "grab")
        assert segment is not None
        pair = _pair_of(segment.view_images(layout), fields)
        self._hold(gen, token, pair)
        return pair

    async def reconfigure(self, config: Config) -> list[int]:
        """Rebuild the worker's processors from ``config`` (camera and recorder stay); a worker
        started later is built from it too. Requests sent after this one use the new
        processors (the worker answers in order). Returns the recipes not calibrated."""
        self.config = config
        return list(await self.call("reconfigure", config, self.processor, what="reconfigure"))

    def record(self, pair: ImagePair, result: JobResult) -> bool:
        """Queue ``pair`` and ``result`` for the worker's recorder; never waits."""
        gen = self._gen
        if gen is None or not gen.is_ready():
            log.warning("record: job %d not recorded, the worker process is restarting",
                        result.job_id)
            return False
        self._send(gen, "record", (self._ref(gen, pair), _wire_result(result)), reply=False)
        return True

    async def close_camera(self) -> None:
        """Close the driver in the worker; a worker busy with a request (a hung grab) is
        killed instead, which closes it too."""
        gen = self._gen
        if gen is None or not gen.is_ready():
            return  # a new worker opens the camera when it is next used
        if gen.pending:
            self._kill(gen, "camera closed while busy")
            return
        try:
            async with asyncio.timeout(CAMERA_CLOSE_TIMEOUT_S):
                await self._call(gen, "camera_close", (), "camera close")
        except (TimeoutError, WorkerError, CameraError) as err:
            log.error("camera close in the worker failed: %s", err)

    @property
    def pid(self) -> int | None:
        return self._gen.pid if self._gen is not None else None

    def snapshot(self) -> dict[str, Any]:
        gen = self._gen
        ready = gen is not None and gen.is_ready()
        return {"pid": None if gen is None else gen.pid, "ready": ready,
                # recipe -> ms of its pipeline's warm-up, done before the worker was ready
                "warmed": gen.ready.result()["warmed"] if gen is not None and ready else None,
                "restarts": self.restarts, "last_exit": self.last_exit or None,
                "shm": None if self._segment is None else self._segment.name}


class WorkerCamera:
    """The camera driver as the daemon sees it when the driver runs in the worker process
    (a ``Camera``)."""

    def __init__(self, client: WorkerClient, type_name: str, description: str) -> None:
        self._client = client
        self.type_name = type_name
        self._description = description or type_name

    def describe(self) -> str:
        return self._description

    async def _call(self, op: str, *args: Any) -> Any:
        try:
            return await self._client.call(op, *args, what=op.replace("_", " "))
        except WorkerError as err:
            raise CameraError(f"{self.type_name}: {err}") from None

    async def open(self) -> None:
        await self._call("camera_open")

    async def grab(self, timeout_s: float, view: CaptureView | None = None,
                   recipe: int = 0) -> ImagePair:
        return await self._client.grab(timeout_s, view, recipe)

    async def set_settings(self, exposure_us: float | None, gain_db: float | None
                           ) -> dict[str, Any]:
        """The driver's ``set_settings`` in the worker (between jobs: the caller's part)."""
        settings: dict[str, Any] = await self._call("camera_settings", exposure_us, gain_db)
        return settings

    async def focus(self, value: float | None) -> dict[str, Any]:
        """The driver's ``focus`` in the worker (between jobs: the caller's part)."""
        focus: dict[str, Any] = await self._call("camera_focus", value)
        return focus

    def stuck_s(self) -> None:
        """None: the driver's calls run in the worker process, out of this one's sight."""
        return None

    async def close(self) -> None:
        await self._client.close_camera()


class WorkerRecorder:
    """The recorder as the daemon sees it when it runs in the worker process."""

    def __init__(self, client: WorkerClient, folder: Path) -> None:
        self._client = client
        self.folder = folder

    @property
    def total_bytes(self) -> int:
        return self._client.record_bytes

    def start(self) -> None:
        """The worker starts its recorder when it starts."""

    def submit(self, pair: ImagePair, result: JobResult) -> bool:
        return self._client.record(pair, result)

    def close(self) -> None:
        """The worker writes what is queued when it is stopped (``WorkerClient.close``)."""


# --- helpers ------------------------------------------------------------------------------

def _initial_segment_bytes(config: Config) -> int:
    """The first shared memory's size: 8-bit grey images of the calibrated size (colour or
    larger images grow it, once)."""
    cal = config.calibration
    if cal is None:
        return 0
    cams = [cal.left] + ([cal.right] if cal.right is not None else [])
    if cal.cameras is not None:
        cams = [cam.intrinsics for cam in cal.cameras]
    return sum(_aligned(c.width * c.height) for c in cams)


def _remote_error(value: Any) -> BaseException:
    kind, message, tb = value
    if kind == "camera":
        return CameraError(message)
    if kind == "setting":
        return CameraSettingError(message)
    if tb:
        log.error("worker: %s\n%s", message, tb.rstrip())
    if kind == "start":
        return WorkerError(f"worker process failed to start: {message}")
    return WorkerError(f"{message} (in the worker process)")


def _resolve(fut: asyncio.Future[Any], value: Any) -> None:
    if not fut.done():
        fut.set_result(value)


def _fail(fut: asyncio.Future[Any], err: BaseException) -> None:
    if not fut.done():
        fut.set_exception(err)


def _consume(fut: asyncio.Future[Any]) -> None:
    """Mark a future's exception as retrieved (nobody may be waiting for a ready message)."""
    if not fut.cancelled():
        fut.exception()
