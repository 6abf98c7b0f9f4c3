"""The cameras of a multi-camera cell, each on its own driver, grabbed together.

Options (``[camera]`` with ``type = "multi"``)::

    [[camera.cameras]]            # one driver per camera (or per stereo pair), in the order of
    type = "genicam"              # calibration.cameras
    cti = "/opt/mvIMPACT/lib/x86_64/mvGenTLProducer.cti"
    left_serial = "N1L"
    right_serial = "N1R"          # a hardware-triggered pair stays one driver: two images
    [[camera.cameras]]
    type = "opencv"
    left = "rtsp://10.0.0.21/stream"

Each entry is a complete camera driver with its own options (validated by that driver, errors
named ``camera.cameras.<i>``) and its own executor thread, so a device SDK handle is still only
touched from one thread; a job grabs all of them concurrently (``asyncio.gather``), and the
acquisition takes as long as the slowest camera, not the sum. The images of every driver are
concatenated in order into ``ImagePair.views``; their number must equal the number of
``calibration.cameras``. The capture time is the earliest of the drivers'; the flange pose the
first one delivered (robot-mounted cameras).
"""

from __future__ import annotations

import asyncio
from typing import Any

from pydantic import Field

from drivers.cameras.base import CameraDriver, DriverOptions
from vgripd.config import MAX_CAMERAS, Config, DriverSection
from vgripd.errors import CameraError, ConfigError
from vgripd.types import CaptureView, ImagePair


class MultiOptions(DriverOptions):
    cameras: tuple[dict[str, Any], ...] = Field(min_length=1, max_length=MAX_CAMERAS)


class MultiCamera(CameraDriver):
    """Several camera drivers as one: their grabs run concurrently, their images in order."""

    Options = MultiOptions
    type_name = "multi"
    options: MultiOptions

    def __init__(self, options: MultiOptions, config: Config) -> None:
        super().__init__(options, config)
        from vgripd.registry import CAMERAS, load_class, validate_options

        self.drivers: list[CameraDriver] = []
        for i, entry in enumerate(options.cameras):
            where = f"camera.cameras.{i}"
            try:
                section = DriverSection.model_validate(entry)
            except ValueError as err:
                raise ConfigError(f"{where}: needs type = \"<driver>\" ({err})") from None
            if section.type == self.type_name:
                raise ConfigError(f"{where}: a multi camera cannot hold another")
            cls = load_class(CAMERAS, where, section.type)
            self.drivers.append(cls(validate_options(cls, section, where), config))
        cameras = config.calibration.cameras if config.calibration is not None else None
        self.expected = len(cameras) if cameras is not None else None
        self.names = tuple(c.name for c in cameras) if cameras is not None else None

    def describe(self) -> str:
        return " + ".join(d.describe() for d in self.drivers)

    async def open(self) -> None:
        opened: list[CameraDriver] = []
        try:
            for i, driver in enumerate(self.drivers):
                try:
                    await driver.open()
                except CameraError as err:
                    raise CameraError(f"camera.cameras.{i} ({driver.type_name}): {err}") from None
                opened.append(driver)
        except BaseException:
            for driver in reversed(opened):
                await driver.close()
            raise

    async def grab(self, timeout_s: float, view: CaptureView | None = None,
                   recipe: int = 0) -> ImagePair:
        if timeout_s <= 0:
            raise CameraError(f"multi: grab timeout must be > 0 s, got {timeout_s}")
        results = await asyncio.gather(*(d.grab(timeout_s, view, recipe) for d in self.drivers),
                                       return_exceptions=True)
        for i, result in enumerate(results):
            if isinstance(result, BaseException):
                if isinstance(result, CameraError):
                    raise CameraError(f"camera.cameras.{i} ({self.drivers[i].type_name}"
                                      f"{self._which(i, results)}): {result}") from None
                raise result
        pairs = [r for r in results if isinstance(r, ImagePair)]
        views = [image for pair in pairs for image in pair.views]
        if self.expected is not None and len(views) != self.expected:
            raise CameraError(f"multi: the drivers delivered {len(views)} images for the "
                              f"{self.expected} cameras of calibration.cameras")
        flange = next((p.T_base_flange for p in pairs if p.T_base_flange is not None), None)
        return ImagePair.of_views(
            views, min(p.t_mono_ns for p in pairs),
            source=" + ".join(p.source for p in pairs),
            meta={"cameras": [dict(p.meta) for p in pairs]}, T_base_flange=flange)

    def _which(self, failed: int, results: list[Any]) -> str:
        """The calibrated camera names a failed driver stands for (', camera north_left'),
        so the message names the camera the integrator knows. Its images are the slots left
        between the other drivers' images: known when it is the only driver that failed
        (each driver may deliver one image or a pair), '' otherwise."""
        if self.names is None:
            return ""
        counts = [len(r.views) if isinstance(r, ImagePair) else None for r in results]
        if sum(c is None for c in counts) != 1:
            return ""
        start = sum(c for c in counts[:failed] if c is not None)
        count = len(self.names) - sum(c for c in counts if c is not None)
        names = self.names[start:start + count]
        if not names:
            return ""
        return f", camera{'s' if len(names) > 1 else ''} {', '.join(names)}"

    def stuck_s(self) -> float:
        return max(d.stuck_s() for d in self.drivers)

    async def close(self) -> None:
        for driver in reversed(self.drivers):
            await driver.close()

    def _grab_blocking(self, timeout_s: float) -> ImagePair:  # pragma: no cover - see grab
        raise NotImplementedError("MultiCamera.grab runs its drivers' grabs")
