"""What runs in the worker process (``vgripd.service.worker.process`` has the daemon's side and
the why): the camera driver, one processor per recipe and the recorder (``_Worker``), the request
loop (``worker_main``, the spawn target), and the wire both sides share: ``HEADER`` (payload
length, request id) before each pickled request or answer.

A recipe whose processor cannot be built is not the worker's end: ``NotCalibratedError`` (what
the daemon's readiness judge also said) or anything the judges did not foresee leaves that
recipe without a processor and its reason in ``problems``; its jobs fail naming it, the other
recipes run.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import importlib
import itertools
import logging
import os
import pickle
import socket
import struct
import time
import traceback
from collections.abc import Callable
from multiprocessing import shared_memory
from typing import Any, Protocol

from vgripd.config import Config
from vgripd.errors import CameraError, CameraSettingError, NotCalibratedError
from vgripd.service.host.children import ChildSetup, start_child
from vgripd.service.worker.camera import Camera
from vgripd.service.worker.imageshm import SHM_DIR as SHM_DIR  # where tests look for segments
from vgripd.service.worker.imageshm import (
    ImageLayout,
    WorkerError,
    _pair_fields,
    _pair_of,
    images_nbytes,
    read_images,
    write_images,
)
from vgripd.types import CaptureView, ImagePair, JobResult

log = logging.getLogger("vgripd.worker")

#: Payload length (bytes) and request id; id 0 is the worker's "ready" message.
HEADER = struct.Struct("!IQ")

#: After SIGTERM (systemd stopping the whole unit) a child process leaves the daemon this long to
#: stop it in order, then ends by itself (the unit's TimeoutStopSec is 15 s).
TERM_GRACE_S = 5

#: The worker's niceness: at least WORKER_NICE levels below the daemon's, and at least
#: WORKER_NICE_FLOOR, so when they compete for a core the daemon's event loop (answering a PLC)
#: wins at once; alone on the machine the worker still gets all of it. Under the unit (daemon
#: at nice -10, systemd/vgripd.service) and by hand (nice 0) the worker runs at nice 5: not 15
#: levels below ordinary programs, where it would get 1/36 of their share of a busy core.
WORKER_NICE = 5
WORKER_NICE_FLOOR = 5


class Processor(Protocol):
    """What the daemon and the worker need from the vision pipeline
    (``vgripd.vision.pipeline.Pipeline``)."""

    def process(self, pair: ImagePair, job_id: int) -> JobResult: ...


# --- wire format -------------------------------------------------------------------------------

def _wire_result(result: JobResult) -> JobResult:
    """The result with its mappings as plain dicts (picklable), the pick list's too."""
    return dataclasses.replace(
        result, residuals=dict(result.residuals), timings_ms=dict(result.timings_ms),
        instances=tuple(dataclasses.replace(i, residuals=dict(i.residuals))
                        for i in result.instances))


def _frame(req_id: int, payload: bytes) -> bytes:
    return HEADER.pack(len(payload), req_id) + payload


# --- the worker process --------------------------------------------------------------------------

def _recv_exact(sock: socket.socket, n: int) -> bytes | None:
    buf = bytearray(n)
    view = memoryview(buf)
    got = 0
    while got < n:
        k = sock.recv_into(view[got:])
        if k == 0:
            return None
        got += k
    return bytes(buf)


def _load_processor(path: str, config: Config, problems: dict[int, str],
                    recipe: int) -> Processor | None:
    """The processor class at ``module:Class`` built from ``config``; None (and the reason in
    ``problems``) if it cannot be built: its jobs answer NOT_CALIBRATED, the other recipes and
    the worker run on."""
    module_name, _, class_name = path.partition(":")
    cls = getattr(importlib.import_module(module_name), class_name)
    try:
        processor: Processor = cls(config)
    except NotCalibratedError as err:
        problems[recipe] = str(err)  # the daemon judged it too (vision.readiness)
        return None
    except Exception as err:  # what the config's judges did not foresee: this recipe only
        problems[recipe] = f"its pipeline cannot be built: {type(err).__name__}: {err}"
        log.exception("worker: recipe %d: %s", recipe, problems[recipe])
        return None
    return processor


class _Worker:
    """The worker's state: camera driver, processor, recorder, attached segments, last pair."""

    def __init__(self, config: Config, processor: str) -> None:
        from vgripd.registry import CAMERAS, load_class, validate_options
        from vgripd.service.worker.recorder import Recorder

        self.loop = asyncio.new_event_loop()  # the camera drivers' API is async
        cls = load_class(CAMERAS, "camera", config.camera.type)
        self.camera: Camera = cls(validate_options(cls, config.camera, "camera"), config)
        self.camera_open = False
        # One processor per recipe (config.recipes), so a recipe switch costs nothing.
        self.problems: dict[int, str] = {}
        self.processors = {n: _load_processor(processor, config.for_recipe(n), self.problems, n)
                           for n in config.recipe_numbers()}
        self.warmed = self._warm_up()
        self.recorder: Recorder | None = None
        rec = config.record
        if rec.enabled:
            self.recorder = Recorder(rec.folder, int(rec.max_mb * 1e6),
                                     config.model_dump(mode="json", exclude_none=True))
            self.recorder.start()
        self.segment: shared_memory.SharedMemory | None = None
        self.held: tuple[int, ImagePair] | None = None
        self._tokens = itertools.count(1)

    def _warm_up(self) -> dict[int, float]:
        """Run each recipe's pipeline once (``vgripd.vision.warmup.warm_up``) before
        the worker reports ready, so the first real job costs what the tenth does; the results
        are dropped. Recipe number -> milliseconds it took."""
        from vgripd.vision.pipeline import Pipeline
        from vgripd.vision.warmup import warm_up

        warmed: dict[int, float] = {}
        for number, processor in self.processors.items():
            if not isinstance(processor, Pipeline):  # another processor: nothing to warm
                continue
            t0 = time.perf_counter()
            try:
                warm_up(processor)
            except Exception:  # a warm-up is an optimisation: it never keeps the worker down
                log.exception("worker: warming up recipe %d failed (its jobs still run)", number)
                continue
            warmed[number] = round((time.perf_counter() - t0) * 1e3, 1)
        if warmed:
            log.info("worker: pipelines warmed up before ready (recipe: ms) %s", warmed)
        return warmed

    # segments: one attached at a time, the one the daemon names in the request
    def _buf(self, name: str) -> memoryview:
        if self.segment is None or self.segment.name.lstrip("/") != name:
            self._detach()
            # Attaching registers the name with the resource tracker the daemon shares with
            # this process; the daemon unregisters it when it unlinks.
            self.segment = shared_memory.SharedMemory(name=name)
        buf = self.segment.buf
        assert buf is not None
        return buf

    def _detach(self) -> None:
        if self.segment is not None:
            self.segment.close()
            self.segment = None

    def _hold(self, pair: ImagePair) -> int:
        token = next(self._tokens)
        self.held = (token, pair)
        return token

    def _pair(self, ref: tuple[int, dict[str, Any], str | None, ImageLayout | None]) -> ImagePair:
        """The pair a request names: the held one (by token) or new images in the segment."""
        token, fields, segment, layout = ref
        if segment is not None and layout is not None:
            pair = _pair_of(read_images(self._buf(segment), layout), fields)
            self.held = (token, pair)
            return pair
        if self.held is None or self.held[0] != token:
            raise WorkerError(f"the worker no longer holds the images of pair {token}")
        return ImagePair.of_views(self.held[1].views, **fields)

    # requests
    def open_camera(self) -> None:
        if not self.camera_open:
            self.loop.run_until_complete(self.camera.open())
            self.camera_open = True

    def grab(self, timeout_s: float, segment: str | None, view: CaptureView | None = None,
             recipe: int = 0
             ) -> tuple[int, dict[str, Any], ImageLayout | None, int]:
        """Grab (opening the camera first if needed) for a job of ``recipe``; images into the
        segment if they fit.

        Returns (token, fields, layout or None, bytes the images need)."""
        self.open_camera()
        pair: ImagePair = self.loop.run_until_complete(
            self.camera.grab(timeout_s, view, recipe))
        token = self._hold(pair)
        return (token, _pair_fields(pair), *self._put(pair, segment))

    def put(self, token: int, segment: str) -> ImageLayout:
        if self.held is None or self.held[0] != token:
            raise WorkerError(f"the worker no longer holds the images of pair {token}")
        layout, need = self._put(self.held[1], segment)
        if layout is None:
            raise WorkerError(f"shared memory {segment} too small for {need} bytes")
        return layout

    def _put(self, pair: ImagePair, segment: str | None) -> tuple[ImageLayout | None, int]:
        images = pair.views
        need = images_nbytes(images)
        if segment is None:
            return None, need
        buf = self._buf(segment)
        if need > len(buf):
            return None, need
        return write_images(buf, images), need

    def camera_settings(self, exposure_us: float | None, gain_db: float | None
                        ) -> dict[str, Any]:
        """The driver's ``set_settings`` (opening the camera first if needed)."""
        self.open_camera()
        settings: dict[str, Any] = self.loop.run_until_complete(
            self.camera.set_settings(exposure_us, gain_db))
        return settings

    def camera_focus(self, value: float | None) -> dict[str, Any]:
        """The driver's ``focus`` (opening the camera first if needed)."""
        self.open_camera()
        focus: dict[str, Any] = self.loop.run_until_complete(self.camera.focus(value))
        return focus

    def close_camera(self) -> None:
        if self.camera_open:
            self.camera_open = False
            self.loop.run_until_complete(self.camera.close())

    def process(self, ref: Any, job_id: int, recipe: int = 0) -> JobResult:
        processor = self.processors.get(recipe)
        if processor is None:
            raise NotCalibratedError(f"recipe {recipe}: " + self.problems.get(
                recipe, "the worker has no pipeline for it"))
        return _wire_result(processor.process(self._pair(ref), job_id))

    def reconfigure(self, config: Config, processor: str) -> list[int]:
        """Rebuild every recipe's processor from ``config`` (a reload, ``ops.reload``); the camera
        and the recorder stay. Returns the recipes that are not calibrated."""
        self.problems = {}
        self.processors = {n: _load_processor(processor, config.for_recipe(n), self.problems, n)
                           for n in config.recipe_numbers()}
        return [n for n, p in self.processors.items() if p is None]

    def record(self, ref: Any, result: JobResult) -> bool:
        if self.recorder is None:
            return False
        return self.recorder.submit(self._pair(ref), result)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.close_camera()
        if self.recorder is not None:
            self.recorder.close()  # queued writes finish
        self._detach()
        self.loop.close()


def worker_setup(log_level: str) -> ChildSetup:
    """How the worker starts (``start_child``; called by the daemon as it starts one): it
    holds the camera and the recorder, so SIGTERM leaves the daemon ``TERM_GRACE_S`` to stop
    it in order; below the daemon."""
    return ChildSetup.here(nice_below=WORKER_NICE, nice_floor=WORKER_NICE_FLOOR,
                           term_grace_s=TERM_GRACE_S, log_level=log_level)


def worker_main(sock: socket.socket, config: Config, processor: str,
                setup: ChildSetup) -> None:
    """Entry point of the worker process (its ``multiprocessing`` target)."""
    start_child(setup)
    try:
        worker = _Worker(config, processor)
    except BaseException as err:
        msg = f"{type(err).__name__}: {err}"
        with contextlib.suppress(OSError):
            sock.sendall(_frame(0, pickle.dumps((False, ("start", msg, traceback.format_exc()),
                                                 0))))
        raise SystemExit(1) from None
    handlers: dict[str, Callable[..., Any]] = {
        "camera_open": worker.open_camera, "camera_grab": worker.grab,
        "camera_put": worker.put, "camera_close": worker.close_camera,
        "camera_settings": worker.camera_settings, "camera_focus": worker.camera_focus,
        "process": worker.process, "record": worker.record,
        "reconfigure": worker.reconfigure,
    }

    def answer(req_id: int, ok: bool, value: Any) -> None:
        rec_bytes = worker.recorder.total_bytes if worker.recorder is not None else 0
        try:
            payload = pickle.dumps((ok, value, rec_bytes), pickle.HIGHEST_PROTOCOL)
        except Exception as err:  # an answer that cannot be pickled fails its request only
            payload = pickle.dumps((False, ("error", f"cannot send the answer: "
                                            f"{type(err).__name__}: {err}", ""), rec_bytes))
        sock.sendall(_frame(req_id, payload))

    try:
        answer(0, True, {"pid": os.getpid(), "warmed": worker.warmed})  # ready
        while True:
            head = _recv_exact(sock, HEADER.size)
            if head is None:
                break  # the daemon is gone
            length, req_id = HEADER.unpack(head)
            payload = _recv_exact(sock, length)
            if payload is None:
                break
            try:
                op, args = pickle.loads(payload)
            except Exception as err:
                answer(req_id, False, ("error", f"the worker cannot read the request: "
                                       f"{type(err).__name__}: {err}", traceback.format_exc()))
                continue
            if op == "stop":
                worker.close()
                answer(req_id, True, None)
                break
            try:
                value = handlers[op](*args)
            except CameraError as err:
                kind = "setting" if isinstance(err, CameraSettingError) else "camera"
                answer(req_id, False, (kind, str(err), ""))
            except Exception as err:
                answer(req_id, False, ("error", f"{type(err).__name__}: {err}",
                                       traceback.format_exc()))
            else:
                if req_id:
                    answer(req_id, True, value)
    except (BrokenPipeError, ConnectionResetError):
        pass  # the daemon is gone
    finally:
        worker.close()
        sock.close()
