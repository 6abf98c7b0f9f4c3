"""A camera grab that hangs for ever (a wedged SDK call), in the daemon with a PLC on the Modbus
server link and systemd's watchdog socket bound by the test:

- the job answers CAMERA_ERROR; the daemon abandons the stuck driver thread and opens the
  camera again, and the next job runs normally; the watchdog keeps pinging;
- when opening it again fails (or hangs too), the camera is faulty: the watchdog stops pinging
  (systemd restarts the service), ``healthy()`` is False and the status says why; later jobs
  answer CAMERA_ERROR at once;
- the web view's grabs go through the same supervisor: a preview grab that hangs has the
  camera opened again as a job's would; page grabs that fail at once mark nothing for the jobs;
  a camera slower than the page's wait but within its grab time is never reopened by previews,
  and a job triggered while such a grab runs takes its own, later frame.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import threading
import time
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path
from typing import Any

import aiohttp
import numpy as np
import pytest

from drivers.cameras.base import CameraDriver, DriverOptions
from tests.integration.test_daemon import Plc
from vgripd.config import Config, config_from_dict
from vgripd.errors import CameraError
from vgripd.service.daemon import Daemon
from vgripd.service.web.context import PREVIEW_GRAB_TIMEOUT_S
from vgripd.service.worker.cameras import DOWN_AFTER_FAILURES
from vgripd.types import ImagePair, JobResult, Status

pytestmark = pytest.mark.timeout(90)
JOB_TIMEOUT_S = 1.0
WAIT_S = 60.0  # the longest a test waits for a state
# A camera slower than a page waits (and than that wait plus the hang check's grace), well
# within the job's time that it is given.
SLOW_GRAB_S = 2 * PREVIEW_GRAB_TIMEOUT_S
SLOW_JOB_TIMEOUT_S = 4 * SLOW_GRAB_S


class HangingCamera(CameraDriver):
    """Its first grab blocks until the test ends (or its first ``failures`` grabs fail at
    once); opening it again does ``reopen``."""

    Options = DriverOptions
    type_name = "hanging"

    def __init__(self, config: Config, reopen: str = "ok", failures: int = 0) -> None:
        super().__init__(DriverOptions(), config)
        self.release = threading.Event()
        self.reopen = reopen  # "ok", "fail" or "hang"
        self.failures = failures  # > 0: so many first grabs fail at once, none hangs
        self.opens = 0
        self.grabs = 0

    def _open_blocking(self) -> None:
        self.opens += 1
        if self.opens > 1 and self.reopen == "fail":
            raise CameraError("hanging: device gone")
        if self.opens > 1 and self.reopen == "hang":
            self.release.wait()

    def _grab_blocking(self, timeout_s: float) -> ImagePair:
        self.grabs += 1
        if self.grabs <= self.failures:
            raise CameraError("hanging: frame lost")
        if self.grabs == 1 and not self.failures:
            self.release.wait()  # the wedged device call
        return ImagePair(left=np.zeros((4, 4), np.uint8), right=None,
                         t_mono_ns=time.monotonic_ns(), source="hanging")


class SlowCamera(CameraDriver):
    """Every grab takes ``grab_s`` (a long exposure) and delivers; a device takes one grab at a
    time, so a grab started while another still runs fails."""

    Options = DriverOptions
    type_name = "slow"

    def __init__(self, config: Config, grab_s: float) -> None:
        super().__init__(DriverOptions(), config)
        self.grab_s = grab_s
        #: The first grab also lasts until this is set (the test has triggered a job).
        self.hold_first = threading.Event()
        self.hold_first.set()
        self.release = threading.Event()  # the test's end: a grab in flight ends at once
        self.opens = 0
        self.grabs = 0
        self.running = 0  # grabs in the device now
        self.overlaps = 0
        self._lock = threading.Lock()

    def _open_blocking(self) -> None:
        self.opens += 1

    def _grab_blocking(self, timeout_s: float) -> ImagePair:
        with self._lock:
            self.grabs += 1
            self.running += 1
            busy = self.running > 1
            self.overlaps += busy
        try:
            if busy:
                raise CameraError("slow: the device is busy with another grab")
            exposed_ns = time.monotonic_ns()
            self.release.wait(self.grab_s)
            if self.grabs == 1:
                self.hold_first.wait(WAIT_S)
            return ImagePair(left=np.zeros((4, 4), np.uint8), right=None,
                             t_mono_ns=exposed_ns, source="slow")
        finally:
            with self._lock:
                self.running -= 1


class Stub:
    """The processing step (in-process): every pair is answered NOT_FOUND at once; the
    capture time of each job's pair is kept in ``exposed``."""

    def __init__(self) -> None:
        self.exposed: dict[int, int] = {}

    def process(self, pair: ImagePair, job_id: int) -> JobResult:
        self.exposed[job_id] = pair.t_mono_ns
        return JobResult(job_id=job_id, status=Status.NOT_FOUND, message="stub")


@pytest.fixture
def watchdog_socket(tmp_path: Path) -> Iterator[tuple[str, socket.socket]]:
    path = str(tmp_path / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.setblocking(False)
    yield path, sock
    sock.close()


def drain(sock: socket.socket) -> None:
    """Forget what was sent so far (the daemon also sends STATUS= on every state change)."""
    with contextlib.suppress(BlockingIOError):
        while True:
            sock.recv(4096)


async def pings(sock: socket.socket, seconds: float) -> int:
    """WATCHDOG=1 messages received within ``seconds`` from now."""
    drain(sock)
    loop = asyncio.get_running_loop()
    count = 0
    with contextlib.suppress(TimeoutError):
        async with asyncio.timeout(seconds):
            while True:
                count += (await loop.sock_recv(sock, 4096)) == b"WATCHDOG=1"
    return count


@contextlib.asynccontextmanager
async def camera_daemon(notify: str, make_camera: Callable[[Config], Any],
                        job_timeout_s: float = JOB_TIMEOUT_S,
                        **cameras: Any) -> AsyncIterator[tuple[Daemon, Any]]:
    """A daemon on ``make_camera(config)`` (in-process, the ``Stub`` pipeline), with a PLC
    link and the web view."""
    config = config_from_dict({
        "camera": {"type": "synthetic", "seed": 1},
        "links": [{"type": "modbus_server", "host": "127.0.0.1", "port": 0}],
        "status": {"port": 0},
        "daemon": {"job_timeout_s": job_timeout_s},
    })
    d = Daemon(config, pipeline=Stub(),
               env={"NOTIFY_SOCKET": notify, "WATCHDOG_USEC": "200000"})  # ping every 0.1 s
    camera = make_camera(config)
    d.rooms.cameras.camera = camera
    for name, value in cameras.items():  # the camera room's settings
        setattr(d.rooms.cameras, name, value)
    await d.start()
    try:
        yield d, camera
    finally:
        camera.release.set()  # lets the abandoned thread end
        await d.stop()


@contextlib.asynccontextmanager
async def hanging_daemon(notify: str, reopen: str, failures: int = 0,
                         job_timeout_s: float = JOB_TIMEOUT_S,
                         **cameras: Any) -> AsyncIterator[tuple[Daemon, HangingCamera]]:
    async with camera_daemon(notify, lambda config: HangingCamera(config, reopen, failures),
                             job_timeout_s, **cameras) as (daemon, camera):
        yield daemon, camera


async def plc_job(daemon: Daemon, seq: int) -> list[int]:
    port: int = next(iter(daemon.rooms.links.links.values())).port  # type: ignore[attr-defined]
    async with Plc(port) as plc:
        await plc.trigger(seq)
        return await plc.result(seq)


async def test_hung_grab_camera_opened_again_next_job_runs(
        watchdog_socket: tuple[str, socket.socket]) -> None:
    path, sock = watchdog_socket
    async with hanging_daemon(path, "ok") as (daemon, camera):
        words = await plc_job(daemon, 1)
        assert words[18] == Status.CAMERA_ERROR
        await daemon.wait_for(lambda: camera.opens == 2 and daemon.snapshot()["camera"]["open"],
                              10)
        words = await plc_job(daemon, 2)
        assert words[18] == Status.NOT_FOUND  # the stub's answer: the grab worked
        assert camera.grabs == 2
        assert daemon.healthy()
        assert await pings(sock, 0.5) >= 2


@pytest.mark.parametrize("reopen", ["fail", "hang"])
async def test_camera_that_cannot_be_opened_again_stops_the_watchdog(
        watchdog_socket: tuple[str, socket.socket], reopen: str) -> None:
    path, sock = watchdog_socket
    async with hanging_daemon(path, reopen, open_timeout_s=1.0) as (daemon, camera):
        assert await pings(sock, 0.3) >= 1
        words = await plc_job(daemon, 1)
        assert words[18] == Status.CAMERA_ERROR
        await daemon.wait_for(lambda: bool(daemon.rooms.cameras.fault), 15)
        await asyncio.sleep(0.15)  # a ping already on its way (0.1 s period) has arrived
        assert await pings(sock, 0.6) == 0  # systemd will restart the service
        assert not daemon.healthy()
        status = daemon.snapshot()
        assert status["healthy"] is False
        problem = status["health_problem"]
        assert problem == status["camera"]["fault"]
        assert problem.startswith("camera hanging: a grab has been stuck in the driver")
        assert ("opening it again failed: hanging: device gone" if reopen == "fail"
                else "opening it hung for more than 1 s") in problem
        assert "CAMERA FAULT" in daemon.status_line()
        t0 = time.monotonic()
        words = await plc_job(daemon, 2)
        assert words[18] == Status.CAMERA_ERROR
        assert time.monotonic() - t0 < JOB_TIMEOUT_S  # at once, not after a timeout
        assert daemon.rooms.jobs.last_job is not None
        assert "unusable" in daemon.rooms.jobs.last_job.result.message


async def preview_status(daemon: Daemon, busy: list[str] | None = None) -> int:
    """GET camera 0's live picture from the daemon's web view: the HTTP status (the text of a
    503 appended to ``busy``)."""
    assert daemon.status_server is not None
    url = f"http://127.0.0.1:{daemon.status_server.port}/api/cameras/0/preview.jpg"
    async with aiohttp.ClientSession() as http, http.get(url) as response:
        if response.status == 503 and busy is not None:
            busy.append(await response.text())
        return response.status


async def test_preview_grab_that_hangs_is_recovered_as_a_jobs_would_be(
        watchdog_socket: tuple[str, socket.socket]) -> None:
    """The web view grabs through the camera supervisor: a preview grab that hangs has the
    camera opened again, without waiting for a job to find the wedged driver."""
    path, _ = watchdog_socket
    async with hanging_daemon(path, "ok", job_timeout_s=1.5 * PREVIEW_GRAB_TIMEOUT_S) as (
            daemon, camera):
        assert await preview_status(daemon) == 503  # the page stopped waiting
        await daemon.wait_for(lambda: camera.opens == 2 and daemon.snapshot()["camera"]["open"],
                              30)
        assert daemon.rooms.cameras.fault == ""
        words = await plc_job(daemon, 1)
        assert words[18] == Status.NOT_FOUND  # the first job's grab delivered
        assert camera.grabs == 2
        assert daemon.healthy()


async def test_preview_grabs_that_fail_mark_nothing_for_the_jobs(
        watchdog_socket: tuple[str, socket.socket]) -> None:
    """Page grabs that fail at once (as many in a row as mark the camera down when jobs'
    grabs fail) leave the camera up, not faulty and healthy; the next job runs."""
    path, _ = watchdog_socket
    async with hanging_daemon(path, "ok", failures=DOWN_AFTER_FAILURES) as (daemon, camera):
        assert daemon.status_server is not None
        turns = daemon.status_server.camera
        for _ in range(DOWN_AFTER_FAILURES):
            assert await turns.grab_between_jobs() is None  # failed, said so in the log
        assert camera.grabs == DOWN_AFTER_FAILURES
        assert daemon.rooms.cameras.down == ""
        assert daemon.rooms.cameras.fault == ""
        assert daemon.healthy()
        words = await plc_job(daemon, 1)
        assert words[18] == Status.NOT_FOUND  # the job's grab delivered
        assert await turns.grab_between_jobs() is not None


async def until(predicate: Callable[[], bool], what: str) -> None:
    """Poll ``predicate`` until it holds, within WAIT_S."""
    deadline = time.monotonic() + WAIT_S
    while not predicate():
        assert time.monotonic() < deadline, f"not within {WAIT_S:g} s: {what}"
        await asyncio.sleep(0.05)


async def test_a_camera_slower_than_the_page_is_not_reopened_by_previews(
        watchdog_socket: tuple[str, socket.socket]) -> None:
    """A grab that takes longer than the page waits, but not longer than the camera's grab
    time (a long exposure): the pages stop waiting, the grabs go on and deliver, the camera
    is never taken for a hung one and never opened again; later previews show the pictures."""
    path, _ = watchdog_socket
    async with camera_daemon(path, lambda config: SlowCamera(config, SLOW_GRAB_S),
                             SLOW_JOB_TIMEOUT_S) as (daemon, camera):
        codes: list[int] = []
        texts: list[str] = []
        deadline = time.monotonic() + 4 * WAIT_S
        while camera.grabs < 3 and time.monotonic() < deadline:
            codes.append(await preview_status(daemon, texts))
            await asyncio.sleep(0.1)  # a page's poll period
        await until(lambda: camera.running == 0, "the last preview grab ends")
        assert camera.grabs == 3
        assert camera.opens == 1  # never opened again
        assert camera.overlaps == 0
        assert 503 in codes  # the first page stopped waiting: no picture yet
        assert "camera slow is busy: no image within the page's 2 s" in texts[0]
        assert 200 in codes  # a later one took the grab that went on
        cameras = daemon.rooms.cameras
        assert (cameras.fault, cameras.down) == ("", "")
        assert daemon.healthy()


async def test_a_job_triggered_while_a_preview_grab_runs_takes_its_own_frame(
        watchdog_socket: tuple[str, socket.socket]) -> None:
    """A trigger that arrives after the page stopped waiting, while its grab still runs: the
    job waits for that grab (the device takes one at a time) and then grabs its own frame,
    exposed after the trigger; the camera is not opened again under it."""
    path, _ = watchdog_socket
    async with camera_daemon(path, lambda config: SlowCamera(config, SLOW_GRAB_S),
                             SLOW_JOB_TIMEOUT_S) as (daemon, camera):
        camera.hold_first.clear()  # the preview's grab lasts until the job has been triggered
        assert await preview_status(daemon) == 503  # the page stopped waiting
        assert camera.running == 1  # the grab goes on
        triggered_ns = time.monotonic_ns()
        port: int = next(iter(daemon.rooms.links.links.values())).port  # type: ignore[attr-defined]
        async with Plc(port) as plc:
            await plc.trigger(1)
            await until(lambda: daemon.rooms.jobs.state.value == "acquiring",
                        "the job waits for the camera")
            camera.hold_first.set()
            words = await plc.result(1)
        assert words[18] == Status.NOT_FOUND  # the stub's answer: the job's grab delivered
        job = daemon.rooms.jobs.last_job
        assert job is not None
        stub = daemon.rooms.jobs.pipelines[0]
        assert isinstance(stub, Stub)
        assert stub.exposed[job.result.job_id] > triggered_ns  # its own frame, not the page's
        assert (camera.grabs, camera.overlaps, camera.opens) == (2, 0, 1)
        assert daemon.healthy()


async def test_a_fresh_page_grab_never_takes_a_frame_exposed_before_it_asked(
        watchdog_socket: tuple[str, socket.socket]) -> None:
    """A trial or a calibration set taken with the robot's pose (``fresh``) while a preview's
    grab still runs: that grab is waited out, not taken; the frame is exposed after the call."""
    path, _ = watchdog_socket
    async with camera_daemon(path, lambda config: SlowCamera(config, SLOW_GRAB_S),
                             SLOW_JOB_TIMEOUT_S) as (daemon, camera):
        cameras = daemon.rooms.cameras
        with pytest.raises(CameraError, match="busy"):
            await cameras.grab_for_page(0.1)  # a preview that stopped waiting
        assert camera.running == 1
        asked_ns = time.monotonic_ns()
        pair = await cameras.grab_for_page(WAIT_S, fresh=True)
        assert pair.t_mono_ns > asked_ns
        assert (camera.grabs, camera.overlaps, camera.opens) == (2, 0, 1)
        taken = await cameras.grab_for_page(WAIT_S)  # a preview may share: here none runs
        assert taken.t_mono_ns > pair.t_mono_ns
