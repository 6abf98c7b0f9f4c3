"""Cameras that OpenCV's ``VideoCapture`` can open: V4L2/UVC devices, video files, RTSP streams,
GStreamer pipelines.

Options (``[camera]`` with ``type = "opencv"``)::

    left = 0                        # device index, file path, URL or GStreamer pipeline string
    right = 1                       # optional second camera for a stereo pair
    backend = "any"                 # any | v4l2 | gstreamer | ffmpeg
    width = 1280                    # optional: request a capture size
    height = 1024
    discard_frames = 0              # frames dropped before each grab (drain stale buffers)
    grayscale = true                # deliver 8-bit grey (else BGR as decoded)

A pair is taken by ``grab()``-ing both devices first and decoding afterwards, so the two
exposures are as close in time as the devices allow (true synchronisation needs a hardware
trigger: use the pylon or aravis driver, docs/cameras.md).
"""

from __future__ import annotations

import time
from typing import Literal

import cv2
import numpy as np
from pydantic import Field

from drivers.cameras.base import CameraDriver, DriverOptions
from vgripd.config import Config
from vgripd.errors import CameraError
from vgripd.types import ImagePair

_BACKENDS = {
    "any": cv2.CAP_ANY,
    "v4l2": cv2.CAP_V4L2,
    "gstreamer": cv2.CAP_GSTREAMER,
    "ffmpeg": cv2.CAP_FFMPEG,
}


class OpenCVOptions(DriverOptions):
    left: int | str
    right: int | str | None = None
    backend: Literal["any", "v4l2", "gstreamer", "ffmpeg"] = "any"
    width: int | None = Field(default=None, gt=0)
    height: int | None = Field(default=None, gt=0)
    discard_frames: int = Field(default=0, ge=0, le=100)
    grayscale: bool = True


class OpenCVCamera(CameraDriver):
    """One or two ``cv2.VideoCapture`` devices, used only from the driver's own thread."""

    Options = OpenCVOptions
    type_name = "opencv"
    options: OpenCVOptions

    def __init__(self, options: OpenCVOptions, config: Config) -> None:
        super().__init__(options, config)
        self._caps: list[tuple[int | str, cv2.VideoCapture]] = []

    def describe(self) -> str:
        return " + ".join(repr(d) for d in self._devices())

    def _devices(self) -> list[int | str]:
        o = self.options
        return [o.left] if o.right is None else [o.left, o.right]

    def _open_blocking(self) -> None:
        o = self.options
        for device in self._devices():
            cap = cv2.VideoCapture(device, _BACKENDS[o.backend])
            if not cap.isOpened():
                cap.release()
                raise CameraError(f"opencv: cannot open capture device {device!r} ({o.backend})")
            self._caps.append((device, cap))
            if o.width is not None:
                cap.set(cv2.CAP_PROP_FRAME_WIDTH, o.width)
            if o.height is not None:
                cap.set(cv2.CAP_PROP_FRAME_HEIGHT, o.height)

    def _grab_blocking(self, timeout_s: float) -> ImagePair:
        for _ in range(self.options.discard_frames + 1):
            for device, cap in self._caps:
                if not cap.grab():
                    raise CameraError(
                        f"opencv: no frame from {device!r} (end of stream or device gone)"
                    )
        t_mono_ns = time.monotonic_ns()
        images = [self._retrieve(device, cap) for device, cap in self._caps]
        return ImagePair(
            left=images[0],
            right=images[1] if len(images) > 1 else None,
            t_mono_ns=t_mono_ns,
            source=f"opencv:{self.describe()}",
            meta={"frame": int(self._caps[0][1].get(cv2.CAP_PROP_POS_FRAMES))},
        )

    def _retrieve(self, device: int | str, cap: cv2.VideoCapture) -> np.ndarray:
        ok, image = cap.retrieve()
        if not ok or image is None:
            raise CameraError(f"opencv: cannot decode the frame from {device!r}")
        if self.options.grayscale and image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        return np.asarray(image)

    def _close_blocking(self) -> None:
        for _, cap in self._caps:
            cap.release()
        self._caps = []
