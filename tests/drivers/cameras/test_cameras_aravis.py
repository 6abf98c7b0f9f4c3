"""The aravis driver against Aravis' fake GigE Vision camera (``arv-fake-gv-camera-0.8`` from
Debian's aravis-tools: real GVCP control and GVSP stream over UDP on a loopback address).

One camera on 127.0.0.1; a second on 127.0.0.2 (``ip addr add 127.0.0.2/32 dev lo``: needs
root, which CI is). Faults: stream packet loss (``-r``: the fake answers no resend request, so
a frame that lost a packet must be refused), the camera killed mid-run and started again, a
camera another process controls, a camera that does not exist."""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import importlib.util
import logging
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from typing import Any

import pytest

from drivers.cameras.aravis import AravisCamera, AravisStack
from tests.conftest import REPO, need, need_tool
from vgripd.config import Config
from vgripd.errors import CameraError, CameraSettingError

FAKE = "arv-fake-gv-camera-0.8"
WAIT_S = 20.0


def _aravis() -> None:
    need(importlib.util.find_spec("gi") is not None,
         "needs PyGObject: pip install vgripd[aravis]")
    try:
        AravisStack()
    except CameraError as err:
        need(False, f"needs Aravis: {err}")


class FakeCamera:
    """One ``arv-fake-gv-camera-0.8`` process: start, kill, start again."""

    def __init__(self, address: str, serial: str, loss_per_mille: int = 0) -> None:
        self.address, self.serial, self.loss = address, serial, loss_per_mille
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> FakeCamera:
        args = [need_tool(FAKE, "aravis-tools"), "-i", self.address, "-s", self.serial]
        if self.loss:
            args += ["-r", str(self.loss)]
        self.proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        wait_until(lambda: any(d.serial == self.serial for d in AravisStack().discover()),
                   f"{FAKE} {self.serial} on {self.address} discovered")
        return self

    def kill(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait(timeout=WAIT_S)
            self.proc = None


@contextlib.contextmanager
def gige_exclusive() -> Iterator[None]:
    """Hold the machine's fake GigE cameras alone while a test's fakes live: they listen on
    fixed loopback addresses (127.0.0.1/.2, the GVCP port) and discovery sees every one, so
    tests in parallel processes (pytest-xdist) take turns. An exclusive lock on a file."""
    path = os.path.join(tempfile.gettempdir(), "vgripd-fake-gige.lock")
    with open(path, "a+b") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def wait_until(ok: Any, what: str) -> None:
    """Poll the condition ``ok()`` (a discovery, a grab) until true; fail after WAIT_S."""
    deadline = time.monotonic() + WAIT_S
    while not ok():
        assert time.monotonic() < deadline, f"not within {WAIT_S} s: {what}"
        time.sleep(0.05)


@contextlib.contextmanager
def one_fake() -> Iterator[FakeCamera]:
    """The fake camera GV01 on 127.0.0.1, the machine's only one while it lives."""
    _aravis()
    with gige_exclusive():
        camera = FakeCamera("127.0.0.1", "GV01").start()
        try:
            yield camera
        finally:
            camera.kill()


@pytest.fixture
def fake() -> Iterator[FakeCamera]:
    with one_fake() as camera:
        yield camera


def second_loopback() -> None:
    """127.0.0.2 on lo for the second fake camera (adding it needs root)."""
    shown = subprocess.run(["ip", "-4", "addr", "show", "dev", "lo"], capture_output=True,
                           text=True, check=False).stdout
    if "127.0.0.2/" in shown:
        return
    need(os.geteuid() == 0, "needs root for a second loopback address: "
                            "ip addr add 127.0.0.2/32 dev lo")
    subprocess.run(["ip", "addr", "add", "127.0.0.2/32", "dev", "lo"], check=True)


@contextlib.contextmanager
def two_fake_cameras() -> Iterator[tuple[FakeCamera, FakeCamera]]:
    """The fake cameras GV01 on 127.0.0.1 and GV02 on 127.0.0.2, the machine's only ones while
    they live (a stereo pair for the daemon's tests)."""
    _aravis()
    second_loopback()
    with gige_exclusive():
        first = FakeCamera("127.0.0.1", "GV01").start()
        try:
            second = FakeCamera("127.0.0.2", "GV02").start()
            try:
                yield first, second
            finally:
                second.kill()
        finally:
            first.kill()


@pytest.fixture
def two_fakes() -> Iterator[tuple[FakeCamera, FakeCamera]]:
    with two_fake_cameras() as cameras:
        yield cameras


def camera(**options: Any) -> AravisCamera:
    options.setdefault("cameras", [{"serial": "GV01"}])
    return AravisCamera(AravisCamera.Options.model_validate(options), Config())


async def test_one_fake_camera_by_serial_ip_or_device_id(fake: FakeCamera) -> None:
    for entry in ({"serial": "GV01"}, {"ip": "127.0.0.1"}, {"user_name": "Aravis-Fake-GV01"}):
        cam = camera(cameras=[entry], exposure_us=2000, pixel_format="Mono8", packet_size=1400,
                     inter_packet_delay=0)
        await cam.open()
        try:
            applied = dict(cam.applied[0])
            pair = await cam.grab(5.0)
        finally:
            await cam.close()
        assert pair.left.shape == (512, 512)
        assert pair.right is None
        assert pair.meta["serials"] == ["GV01"]
        assert pair.meta["device_timestamps_ns"][0] > 0
        assert applied["ExposureTimeAbs"] == pytest.approx(2000.0)
        assert applied["GevSCPSPacketSize"] == 1400
        assert (applied["TriggerMode"], applied["TriggerSource"]) == ("On", "Software")


async def test_bayer_and_rgb_formats_arrive_as_grey(fake: FakeCamera) -> None:
    for fmt in ("BayerRG8", "RGB8", "Mono16"):
        cam = camera(pixel_format=fmt)
        await cam.open()
        try:
            pair = await cam.grab(5.0)
        finally:
            await cam.close()
        assert pair.left.shape == (512, 512), fmt
        assert pair.left.dtype.name == "uint8"
        assert 20 < pair.left.mean() < 235, fmt  # the fake's ramp, not black or saturated


async def test_refused_settings_name_camera_feature_and_range(fake: FakeCamera) -> None:
    cam = camera(cameras=[{"name": "top", "serial": "GV01", "features": {"SensorWidth": 10}}],
                 gain_db=3.0, roi={"width": 4096, "height": 100})
    with pytest.raises(CameraError) as info:
        await cam.open()
    text = str(info.value)
    where = "camera top (Aravis Fake, serial GV01, 127.0.0.1)"
    assert f"{where}: feature Gain does not exist on this device" in text
    assert f"{where}: SensorWidth is read-only" in text
    assert f"{where}: Width = 4096 is out of the device's range 1 .. " in text


async def test_a_device_that_does_not_exist(fake: FakeCamera) -> None:
    cam = camera(cameras=[{"ip": "127.0.0.9"}])
    with pytest.raises(CameraError, match=r"aravis: camera: no device with IP 127.0.0.9 "
                                          r"\(found: .*serial GV01"):
        await cam.open()


def test_a_camera_held_by_another_process_is_refused_saying_so(fake: FakeCamera) -> None:
    holder = subprocess.Popen([need_tool("arv-camera-test-0.8", "aravis-tools"), "-n",
                               "Aravis-Fake-GV01"], stdout=subprocess.PIPE,
                              stderr=subprocess.DEVNULL)
    try:
        assert holder.stdout is not None
        holder.stdout.readline()  # it has the camera once it reports
        cam = camera()
        with pytest.raises(CameraError, match=r"cannot open .*GV01.* \(held by another "
                                              r"process\)"):
            asyncio.run(cam.open())
    finally:
        holder.kill()
        holder.wait(timeout=WAIT_S)


async def test_two_cameras_triggered_together_with_their_device_timestamps(
        two_fakes: tuple[FakeCamera, FakeCamera]) -> None:
    cam = camera(cameras=[{"serial": "GV01"}, {"serial": "GV02"}], max_skew_ms=1000.0)
    await cam.open()
    try:
        pairs = [await cam.grab(5.0) for _ in range(3)]
    finally:
        await cam.close()
    for pair in pairs:
        assert pair.right is not None
        assert pair.meta["serials"] == ["GV01", "GV02"]
        left_ns, right_ns = pair.meta["device_timestamps_ns"]
        assert abs(left_ns - right_ns) < 1e9
    stamps = [p.meta["device_timestamps_ns"][0] for p in pairs]
    assert stamps == sorted(set(stamps))  # a new exposure each grab, never a stale frame


async def test_a_set_exposed_too_far_apart_is_refused_naming_cameras_and_skew(
        two_fakes: tuple[FakeCamera, FakeCamera]) -> None:
    """Two separate fake processes expose microseconds to milliseconds apart: a limit of a
    nanosecond refuses the set, naming both cameras and the measured skew."""
    cam = camera(cameras=[{"name": "north", "serial": "GV01"},
                          {"name": "south", "ip": "127.0.0.2"}], max_skew_ms=1e-6)
    await cam.open()
    try:
        with pytest.raises(CameraError, match=r"aravis: cameras (north and south|south and "
                                              r"north) exposed \d+\.\d{3} ms apart "
                                              r"\(max_skew_ms = 1e-06\)"):
            await cam.grab(5.0)
    finally:
        await cam.close()


async def grab_many(cam: AravisCamera, count: int, timeout_s: float) -> tuple[int, list[str]]:
    """``count`` grabs: how many delivered a whole 512x512 frame, and why the others failed."""
    delivered, refused = 0, []
    for _ in range(count):
        try:
            pair = await cam.grab(timeout_s)
        except CameraError as err:
            refused.append(str(err))
            continue
        assert pair.left.shape == (512, 512)
        delivered += 1
    return delivered, refused


async def test_packet_loss_frames_are_refused_never_returned_half(
        two_fakes: tuple[FakeCamera, FakeCamera]) -> None:
    """The fake drops 3 of every 1000 stream packets and answers no resend: a frame that lost
    one is refused CAMERA_ERROR; every frame delivered is whole."""
    _, second = two_fakes
    second.kill()
    lossy = FakeCamera("127.0.0.2", "GV02", loss_per_mille=3).start()
    cam = camera(cameras=[{"serial": "GV02"}], frame_timeout_s=1.0, incomplete_retries=0)
    await cam.open()
    try:
        delivered, refused = await grab_many(cam, 30, 5.0)
    finally:
        await cam.close()
        lossy.kill()
    assert refused, "no frame lost a packet in 30 (3 per 1000 packets, ~180 per frame)"
    assert delivered, refused
    for why in refused:
        assert "incomplete frame refused" in why or "no frame within" in why, why
    assert cam.outage == ""  # the camera answered throughout: lost frames are no outage


async def test_a_set_with_an_incomplete_frame_is_taken_again_while_retries_last(
        two_fakes: tuple[FakeCamera, FakeCamera]) -> None:
    """The same lossy camera (about 4 frames in 10 lose a packet) with ``incomplete_retries =
    5``: the driver takes the set again instead of failing the grab, so (nearly) every grab
    delivers a whole frame and the retries are counted."""
    _, second = two_fakes
    second.kill()
    lossy = FakeCamera("127.0.0.2", "GV02", loss_per_mille=3).start()
    cam = camera(cameras=[{"serial": "GV02"}], frame_timeout_s=1.0, incomplete_retries=5)
    await cam.open()
    try:
        delivered, refused = await grab_many(cam, 30, 10.0)
    finally:
        await cam.close()
        lossy.kill()
    assert cam.incomplete_retried > 0, "no set was taken again in 30 grabs"
    assert delivered >= 25, refused


async def test_a_camera_killed_and_restarted_is_reopened_with_backoff_logged_once(
        fake: FakeCamera, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="vgripd.camera")
    cam = camera(frame_timeout_s=0.5, reopen_backoff_s=0.2, reopen_backoff_max_s=0.8)
    await cam.open()
    try:
        before = await cam.grab(5.0)
        fake.kill()  # unplugged
        with pytest.raises(CameraError, match=r"aravis: camera \(.*GV01.*\): (software "
                                              r"trigger failed|no frame within)"):
            await cam.grab(5.0)
        assert cam.outage == "camera stopped answering"
        for _ in range(3):  # still gone: each grab says so at once, reopening with back-off
            with pytest.raises(CameraError, match="camera stopped answering"):
                await cam.grab(5.0)
        fake.start()  # plugged in again

        failures: list[str] = []

        async def grab_again() -> Any:
            async with asyncio.timeout(WAIT_S):
                while True:
                    try:
                        return await cam.grab(5.0)
                    except CameraError as err:
                        failures.append(str(err))
                        await asyncio.sleep(0.05)  # the next job's trigger
        after = await grab_again()
        # until it is back each grab says so; a frame that lost packets right after the
        # replug (a loaded machine) is refused as incomplete, never returned half
        assert all("camera stopped answering" in f or "incomplete frame refused" in f
                   for f in failures), failures
    finally:
        await cam.close()
    assert after.meta["device_timestamps_ns"][0] > before.meta["device_timestamps_ns"][0]
    messages = [r.getMessage() for r in caplog.records if r.name == "vgripd.camera"]
    assert sum("stopped answering; closing it" in m for m in messages) == 1, messages
    assert sum("camera back after" in m for m in messages) == 1, messages


def hold_and_wait() -> None:
    """A process that opens GV01, grabs a frame, says so and waits to be killed (run with -c).
    A loaded machine may lose a frame's packets: it grabs until one frame is whole."""
    cam = camera()
    loop = asyncio.new_event_loop()
    loop.run_until_complete(cam.open())
    deadline = time.monotonic() + WAIT_S
    while True:
        try:
            loop.run_until_complete(cam.grab(5.0))
            break
        except CameraError:
            if time.monotonic() > deadline:
                raise
    print("holding", flush=True)
    time.sleep(WAIT_S * 3)


def killed_holder() -> None:
    """Start ``hold_and_wait`` in another process and SIGKILL it once it holds the camera: its
    GigE control channel and its acquisition are left behind on the device."""
    holder = subprocess.Popen([sys.executable, "-c", "from tests.drivers.cameras.test_cameras_aravis "
                               "import hold_and_wait; hold_and_wait()"], cwd=REPO,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        assert holder.stdout is not None
        said = holder.stdout.readline()
    finally:
        holder.kill()
        _, err = holder.communicate(timeout=WAIT_S)
    assert said == b"holding\n", err.decode(errors="replace")[-3000:]


async def test_a_camera_whose_holder_was_killed_gives_frames_to_the_next_process(
        fake: FakeCamera) -> None:
    """The dead holder's acquisition still streams to its dead port: opening right after the
    kill waits out its control channel (the device's heartbeat timeout), stops that stale
    acquisition and streams to this process; the first grab gets a new frame."""
    killed_holder()
    cam = camera(frame_timeout_s=2.0)
    refused: list[str] = []
    async with asyncio.timeout(WAIT_S):
        while True:  # a loaded machine may need more than one try at the control channel
            try:
                await cam.open()
                break
            except CameraError as err:
                refused.append(str(err))
    assert all("held by another process" in r for r in refused), refused
    try:
        pair = await cam.grab(5.0)
    finally:
        await cam.close()
    assert pair.left.shape == (512, 512)


async def test_a_camera_that_answers_but_gives_no_frames_is_reopened_logged_once(
        fake: FakeCamera, caplog: pytest.LogCaptureFixture) -> None:
    """The stream sent elsewhere behind the driver's back (as a dead holder's stream is): the
    feature reads still answer, yet no frame comes. After ``no_frame_limit`` grabs without one
    the camera is closed, and the next grab reopens it and gets a frame. Each failure says
    how long it waited."""
    caplog.set_level(logging.INFO, logger="vgripd.camera")
    cam = camera(frame_timeout_s=0.5, no_frame_limit=2)
    await cam.open()
    try:
        await cam.grab(5.0)
        device = cam._devices[0]
        raw = device._cam  # type: ignore[attr-defined]
        raw.stop_acquisition()
        # stream channel 0's host port (GigE Vision bootstrap register): the discard port
        device._dev.write_register(0x0D00, 9)  # type: ignore[attr-defined]
        raw.start_acquisition()
        for _ in range(2):
            with pytest.raises(CameraError, match=r"aravis: camera \(Aravis Fake, serial GV01, "
                                                  r"127\.0\.0\.1\): no frame within 0\.5 s$"):
                await cam.grab(5.0)
        assert cam.outage == "camera gave no frame to 2 grabs in a row"
        pair = await cam.grab(5.0)
        assert cam.outage == ""
    finally:
        await cam.close()
    assert pair.left.shape == (512, 512)
    messages = [r.getMessage() for r in caplog.records if r.name == "vgripd.camera"]
    assert sum("gave no frame to 2 grabs in a row although it answers" in m
               for m in messages) == 1, messages
    assert sum("camera back after" in m for m in messages) == 1, messages


async def test_focus_where_the_device_has_a_focus_feature_else_why_not(fake: FakeCamera) -> None:
    """The setup page's focus control: the fake has no lens, so none of the GenICam focus
    features, said naming the camera; a lens controller under another name is
    ``focus_feature`` (the fake's TestRegister stands in for one): written, refused out of its
    range naming camera, feature and range, nothing changed then."""
    cam = camera(cameras=[{"name": "top", "serial": "GV01"}])
    await cam.open()
    try:
        none = await cam.focus(None)
    finally:
        await cam.close()
    assert none["available"] is False
    assert none["reason"].startswith("camera top (Aravis Fake, serial GV01, 127.0.0.1): none "
                                     "of the GenICam focus features FocusPos, FocusPosition")

    cam = camera(cameras=[{"name": "top", "serial": "GV01"}], focus_feature="TestRegister")
    await cam.open()
    try:
        written = await cam.focus(1234)
        with pytest.raises(CameraSettingError) as info:
            await cam.focus(-5)
    finally:
        await cam.close()
    assert written["available"] is True
    assert written["cameras"][0]["feature"] == "TestRegister"
    assert written["cameras"][0]["value"] == 1234
    assert "camera top (Aravis Fake, serial GV01, 127.0.0.1): TestRegister = -5 is out of " \
           "the device's range 0 .. " in str(info.value)
