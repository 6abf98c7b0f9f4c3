"""GigE Vision / USB3 Vision industrial cameras through a GenTL producer and ``harvesters``.

Needs the optional extra: ``pip install vgripd[genicam]`` plus the camera vendor's GenTL
producer (a ``.cti`` file, e.g. from the vendor SDK). Without ``harvesters`` installed, choosing
this driver fails at construction with one clear ``CameraError``; the other drivers are
unaffected.

Options (``[camera]`` with ``type = "genicam"``)::

    cti = "/opt/vendor/lib/producer.cti"   # GenTL producer
    left_serial = "22FK019"                # serial numbers; left may be omitted for the
    right_serial = "22FK020"               # first camera found, right for single-camera mode
    trigger = "software"                   # software | hardware (Line0) | free_run
    exposure_us = 8000                     # optional: set ExposureTime (microseconds)

With ``trigger = "software"`` each grab fires ``TriggerSoftware`` on every camera and then waits
for the frames; with ``"hardware"`` the cameras expose on an external trigger on Line0 (a
truly synchronous stereo pair) and grab waits for it; ``"free_run"`` takes the next streamed
frame. All harvesters calls run on the driver's own thread.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field

from drivers.cameras.base import CameraDriver, DriverOptions
from vgripd.config import Config
from vgripd.errors import CameraError
from vgripd.types import ImagePair

MISSING = "genicam driver needs the 'harvesters' package: pip install vgripd[genicam]"


class GenICamOptions(DriverOptions):
    cti: str = Field(min_length=1)
    left_serial: str | None = None
    right_serial: str | None = None
    trigger: Literal["software", "hardware", "free_run"] = "software"
    exposure_us: float | None = Field(default=None, gt=0)


class GenICamCamera(CameraDriver):
    """One or two GenICam cameras (``harvesters`` image acquirers)."""

    Options = GenICamOptions
    type_name = "genicam"
    options: GenICamOptions

    def __init__(self, options: GenICamOptions, config: Config) -> None:
        super().__init__(options, config)
        try:
            from harvesters.core import Harvester
        except ImportError:
            raise CameraError(MISSING) from None
        self._harvester_cls = Harvester
        self._harvester: Any = None
        self._acquirers: list[tuple[str, Any]] = []

    def describe(self) -> str:
        o = self.options
        serials = [o.left_serial or "first camera"]
        if o.right_serial is not None:
            serials.append(o.right_serial)
        return f"{' + '.join(serials)} via {o.cti}"

    def _open_blocking(self) -> None:
        o = self.options
        if not Path(o.cti).is_file():
            raise CameraError(f"genicam: GenTL producer file {o.cti} does not exist")
        self._harvester = self._harvester_cls()
        try:
            self._harvester.add_file(o.cti)
            self._harvester.update()
        except Exception as err:  # harvesters raises plain and GenTL exceptions alike
            raise CameraError(f"genicam: cannot load GenTL producer {o.cti}: {err}") from None
        found = [d.serial_number for d in self._harvester.device_info_list]
        serials: list[str | None] = [o.left_serial]
        if o.right_serial is not None:
            serials.append(o.right_serial)
        for serial in serials:
            if serial is not None and serial not in found:
                raise CameraError(f"genicam: no camera with serial {serial} (found: {found})")
            if serial is None and not found:
                raise CameraError(f"genicam: no camera found through {o.cti}")
            acquirer = self._harvester.create({"serial_number": serial} if serial else 0)
            name = serial or found[0]
            self._acquirers.append((name, acquirer))
            self._configure(name, acquirer.remote_device.node_map)
            acquirer.start()

    def _configure(self, name: str, node_map: Any) -> None:
        o = self.options
        try:
            if o.trigger == "free_run":
                node_map.TriggerMode.value = "Off"
            else:
                node_map.TriggerSelector.value = "FrameStart"
                node_map.TriggerMode.value = "On"
                node_map.TriggerSource.value = "Software" if o.trigger == "software" else "Line0"
            if o.exposure_us is not None:
                node_map.ExposureTime.value = float(o.exposure_us)
        except Exception as err:  # GenApi access errors have no common base class
            raise CameraError(f"genicam: camera {name}: cannot configure: {err}") from None

    def _grab_blocking(self, timeout_s: float) -> ImagePair:
        if self.options.trigger == "software":
            for _, acquirer in self._acquirers:
                acquirer.remote_device.node_map.TriggerSoftware.execute()
        t_mono_ns = time.monotonic_ns()
        images = [self._fetch(name, acquirer, timeout_s) for name, acquirer in self._acquirers]
        return ImagePair(
            left=images[0],
            right=images[1] if len(images) > 1 else None,
            t_mono_ns=t_mono_ns,
            source=f"genicam:{self.describe()}",
            meta={"serials": tuple(name for name, _ in self._acquirers)},
        )

    @staticmethod
    def _fetch(name: str, acquirer: Any, timeout_s: float) -> np.ndarray:
        try:
            with acquirer.fetch(timeout=timeout_s) as buffer:
                component = buffer.payload.components[0]
                return np.array(component.data.reshape(component.height, component.width))
        except Exception as err:  # timeouts and transport errors from the GenTL producer
            raise CameraError(f"genicam: no frame from camera {name}: {err}") from None

    def _close_blocking(self) -> None:
        for _, acquirer in self._acquirers:
            acquirer.stop()
            acquirer.destroy()
        self._acquirers = []
        if self._harvester is not None:
            self._harvester.reset()
            self._harvester = None
