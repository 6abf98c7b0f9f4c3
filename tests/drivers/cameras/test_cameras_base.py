"""CameraDriver base: grab timeout, executor thread lifecycle, open/close misuse."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from drivers.cameras.base import CameraDriver, DriverOptions
from vgripd.config import config_from_dict
from vgripd.errors import CameraError
from vgripd.types import ImagePair


class GatedCamera(CameraDriver):
    """Blocks in grab until the test opens the gate: a device that stops delivering."""

    Options = DriverOptions
    type_name = "gated"

    def __init__(self) -> None:
        super().__init__(DriverOptions(), config_from_dict({}))
        self.gate = threading.Event()
        self.closed_on: str | None = None
        self.grab_threads: set[str] = set()

    def _grab_blocking(self, timeout_s: float) -> ImagePair:
        self.grab_threads.add(threading.current_thread().name)
        assert self.gate.wait(30.0)
        return ImagePair(left=np.zeros((2, 2), np.uint8), right=None, t_mono_ns=1)

    def _close_blocking(self) -> None:
        self.closed_on = threading.current_thread().name


async def test_timeout_is_a_camera_error_and_the_thread_is_joined() -> None:
    camera = GatedCamera()
    await camera.open()
    with pytest.raises(CameraError, match="gated: no image from gated within 0.05 s"):
        await camera.grab(0.05)
    camera.gate.set()  # the device comes back: the stuck read finishes, the next one works
    pair = await camera.grab(5.0)
    assert pair.left.shape == (2, 2)
    await camera.close()
    await camera.close()  # idempotent
    # Everything ran on the one executor thread, never on the event loop's thread.
    assert camera.grab_threads == {camera.closed_on}
    assert camera.closed_on is not None
    assert camera.closed_on.startswith("camera-gated")


async def test_misuse() -> None:
    camera = GatedCamera()
    with pytest.raises(CameraError, match="not open"):
        await camera.grab(1.0)
    await camera.open()
    try:
        with pytest.raises(CameraError, match="already open"):
            await camera.open()
        with pytest.raises(CameraError, match="timeout must be > 0"):
            await camera.grab(0)
    finally:
        await camera.close()


async def test_a_hung_call_is_abandoned_by_close_and_open_starts_a_fresh_thread() -> None:
    """A device call that never returns: ``stuck_s`` shows it, ``close`` does not queue behind
    it (it would wait for ever), the stuck thread is a daemon thread (it cannot keep the process
    alive), and ``open`` again serves on a new thread."""
    camera = GatedCamera()
    await camera.open()
    try:
        assert camera.stuck_s() == 0.0
        with pytest.raises(CameraError, match="within 0.05 s"):
            await camera.grab(0.05)
        assert camera.stuck_s() > 0.0
        stuck = next(t for t in threading.enumerate() if t.name in camera.grab_threads)
        assert stuck.daemon
        t0 = time.monotonic()
        await camera.close()
        assert time.monotonic() - t0 < 1.0
        assert camera.closed_on is None  # the close was not queued behind the hung grab
        assert camera.stuck_s() == 0.0

        await camera.open()
        camera.gate.set()
        pair = await camera.grab(5.0)
        assert pair.left.shape == (2, 2)
        stuck.join(5.0)  # released, the abandoned thread finishes its call and ends
        assert not stuck.is_alive()
    finally:
        camera.gate.set()
        await camera.close()
