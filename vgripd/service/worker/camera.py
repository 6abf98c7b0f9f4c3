"""What the service uses of a camera: the ``Camera`` protocol.

Two kinds of object meet it: a camera driver (``drivers/cameras/base.CameraDriver`` and every
driver built on it, running in this process or in the worker process) and
``vgripd.service.worker.process.WorkerCamera``, the daemon's handle on the driver that runs in
the worker process. ``CameraSupervisor`` owns the one the daemon uses; the web view reaches it
through the supervisor.

It lives in the worker room, the camera's owner: the supervisor and the worker process type
their camera by it, and the rooms above (jobs, web) may import it; the link room below knows
nothing of cameras. ``vgripd/`` never imports ``drivers/``, so the drivers meet it by shape
(tests/unit/service/worker/test_camera_protocol.py checks that they do).
"""

from __future__ import annotations

from typing import Any, Protocol

from vgripd.types import CaptureView, ImagePair


class Camera(Protocol):
    """One image source, opened before use: ``open``, any number of ``grab``, ``close``.

    Every failure the camera expects (timeout, device gone, not open) is a ``CameraError``.
    """

    @property
    def type_name(self) -> str:
        """The registry type name (``config.camera.type``), for messages."""
        ...

    def describe(self) -> str:
        """The device or files the camera reads, for messages."""
        ...

    async def open(self) -> None: ...

    async def close(self) -> None:
        """Release the device; safe to call more than once, and after a hung grab (a stuck
        call is abandoned, not waited for)."""
        ...

    async def grab(self, timeout_s: float, view: CaptureView | None = None,
                   recipe: int = 0) -> ImagePair:
        """One acquisition within ``timeout_s``; ``view`` and ``recipe`` are hints (the
        driver contract in drivers/cameras/base.py says who uses them)."""
        ...

    async def set_settings(self, exposure_us: float | None, gain_db: float | None
                           ) -> dict[str, Any]:
        """Exposure and gain of the open camera (None: leave it), read back per camera;
        ``CameraSettingError`` names the feature and the range."""
        ...

    async def focus(self, value: float | None) -> dict[str, Any]:
        """The lens focus: read (``value`` None) or written and read back; ``{"available":
        False, "reason": ...}`` where there is none."""
        ...

    def stuck_s(self) -> float | None:
        """How long the current device call has been running (s; 0 when idle), or None when
        this process cannot see it (the driver runs in the worker process): after a grab ran
        out of time, a value that keeps growing means the device hangs."""
        ...
