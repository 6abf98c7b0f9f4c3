"""Industrial cameras through a GenICam SDK: the layer the pylon and aravis drivers share.

Everything that is GenICam and not SDK lives here: the options, choosing devices by serial
number, user-defined name or IP address, applying the settings at open and reading them back,
triggering every camera together, the skew check on the device timestamps, converting pixel
formats (``drivers.cameras.pixels``), and the outage handling (reopen with back-off). An SDK
module (``pylon.py``, ``aravis.py``) only implements ``Stack`` (discover, open) and ``Device``
(features, stream, trigger, one frame) of ``gencam_sdk.py``, where the settings check lives.

Options (``[camera]`` with ``type = "pylon"`` or ``"aravis"``)::

    [[camera.cameras]]                # one per camera, in the order of calibration.cameras
    name = "left"                     # label in messages (default left, right, cam2, ...)
    serial = "40012345"               # exactly one of serial, user_name, ip
    # user_name = "cell3-left"        # DeviceUserID, set with the vendor's tool
    # ip = "192.168.10.11"            # GigE Vision only
    features = { ImageFilename = "/data/left.png" }   # this camera's own features
    [[camera.cameras]]
    name = "right"
    serial = "40012346"

    [camera]                          # (the keys below sit before the [[camera.cameras]])
    trigger = "software"              # software | hardware | free_run
    trigger_line = "Line1"            # the input line of trigger = "hardware"
    exposure_us = 8000                # ExposureTime (ExposureTimeAbs on older GigE cameras)
    gain_db = 0                       # Gain
    pixel_format = "Mono8"            # drivers/cameras/pixels.py FORMATS
    roi = { x = 0, y = 0, width = 1280, height = 1024 }
    packet_size = 1500                # GevSCPSPacketSize, bytes (GigE)
    inter_packet_delay = 0            # GevSCPD, ticks (GigE)
    features = { }                    # any other feature, on every camera, in this order
    max_skew_ms = 2.0                 # refuse a set whose device timestamps differ more
    frame_timeout_s = 2.0             # longest wait for one frame (capped by the job's time)
    no_frame_limit = 2                # grabs in a row without a frame: closed and reopened
    incomplete_retries = 1            # a set with an incomplete frame taken again (not hardware)
    buffers = 4
    reopen_backoff_s = 1.0            # first wait before reopening a camera that is gone
    reopen_backoff_max_s = 30.0       # doubling up to this
    grayscale = true                  # deliver 8-bit grey (else BGR for colour formats)

Each setting is checked against what the device reports before it is written (the feature
exists, is writable, the value is within the device's range and increment, an enumeration
entry exists) and read back after; anything else is a ``SettingError`` naming the camera, the
feature and the device's range: at ``vgripd check`` a config error, in the daemon a
``CAMERA_ERROR`` of every job until the config is fixed.

A grab drains what the stream holds (no stale frame is ever returned), fires the software
trigger of every camera back to back (``trigger = "software"``), or waits for the next frame
(``hardware``: the external trigger pulse; ``free_run``: the next streamed frame), then takes
one whole frame per camera. A frame the SDK reports incomplete (lost packets that the resend
did not recover) is refused, never returned half filled. With a software trigger or free run
the whole set is taken again, up to ``incomplete_retries`` times while the grab's time lasts
(one exposure and transfer more instead of a failed job); with a hardware trigger the pulse
cannot be repeated and the grab fails at once. A camera that stops answering is
closed, the grab fails ``CAMERA_ERROR`` naming it, and every later grab tries to reopen it,
first after ``reopen_backoff_s``, the wait doubling up to ``reopen_backoff_max_s``; the
outage is logged once when it starts and once when the camera is back.

A camera that answers but gives no frame to ``no_frame_limit`` grabs in a row (software trigger
or free run; with a hardware trigger a missing frame is a missing pulse) is an outage too,
whatever its feature reads say: its stream is stale (a process that died holding the camera
left it streaming elsewhere). All cameras are closed and the next grab reopens them at once,
then with back-off as above.
"""

from __future__ import annotations

import logging
import threading
import time
from abc import abstractmethod
from collections.abc import Sequence
from typing import Any, Literal

from pydantic import Field, StrictBool, field_validator, model_validator

from drivers.cameras.base import CameraDriver, DriverOptions
from drivers.cameras.gencam_sdk import (
    Device,
    DeviceInfo,
    SettingError,
    Stack,
    apply_settings,
    camera_label,
    check_value,
)
from drivers.cameras.pixels import FORMATS, PixelError, to_image
from vgripd.config import MAX_CAMERAS, Config
from vgripd.errors import CameraError
from vgripd.types import ImagePair

log = logging.getLogger("vgripd.camera")

FeatureValue = StrictBool | int | float | str


class Roi(DriverOptions):
    x: int = Field(default=0, ge=0)
    y: int = Field(default=0, ge=0)
    width: int = Field(gt=0)
    height: int = Field(gt=0)


class CameraEntry(DriverOptions):
    name: str | None = Field(default=None, min_length=1)
    serial: str | None = Field(default=None, min_length=1)
    user_name: str | None = Field(default=None, min_length=1)
    ip: str | None = Field(default=None, min_length=1)
    features: dict[str, FeatureValue] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _one_key(self) -> CameraEntry:
        keys = [k for k in ("serial", "user_name", "ip") if getattr(self, k) is not None]
        if len(keys) != 1:
            raise ValueError("give exactly one of serial, user_name or ip "
                             f"(got {', '.join(keys) or 'none'})")
        return self

    def selector(self) -> str:
        if self.serial is not None:
            return f"serial {self.serial}"
        if self.user_name is not None:
            return f"user name {self.user_name}"
        return f"IP {self.ip}"


class GenICamStackOptions(DriverOptions):
    cameras: tuple[CameraEntry, ...] = Field(min_length=1, max_length=MAX_CAMERAS)
    trigger: Literal["software", "hardware", "free_run"] = "software"
    trigger_line: str = Field(default="Line1", min_length=1)
    exposure_us: float | None = Field(default=None, gt=0)
    gain_db: float | None = Field(default=None, ge=0)
    pixel_format: str | None = None
    roi: Roi | None = None
    packet_size: int | None = Field(default=None, gt=0)
    inter_packet_delay: int | None = Field(default=None, ge=0)
    features: dict[str, FeatureValue] = Field(default_factory=dict)
    #: The lens controller's focus feature when it is none of ``FOCUS_FEATURES``.
    focus_feature: str | None = Field(default=None, min_length=1, max_length=64)
    max_skew_ms: float | None = Field(default=None, gt=0)
    frame_timeout_s: float = Field(default=2.0, gt=0)
    no_frame_limit: int = Field(default=2, ge=1)
    incomplete_retries: int = Field(default=1, ge=0, le=5)
    buffers: int = Field(default=4, ge=2, le=64)
    reopen_backoff_s: float = Field(default=1.0, gt=0)
    reopen_backoff_max_s: float = Field(default=30.0, gt=0)
    grayscale: bool = True

    @field_validator("pixel_format")
    @classmethod
    def _known_format(cls, value: str | None) -> str | None:
        if value is not None and value not in FORMATS:
            raise ValueError(f"{value!r} is not a supported pixel format "
                             f"(supported: {', '.join(FORMATS)})")
        return value

    @model_validator(mode="after")
    def _unique_names(self) -> GenICamStackOptions:
        names = camera_names(self.cameras)
        if len(set(names)) != len(names):
            raise ValueError(f"cameras: names must differ (got {', '.join(names)})")
        return self


#: GenICam features a motorised or liquid lens is focused with, looked for in this order (a
#: lens controller under another name: ``camera.focus_feature``).
FOCUS_FEATURES = ("FocusPos", "FocusPosition", "Focus", "LensFocus", "FocalPower")


def camera_names(entries: Sequence[CameraEntry]) -> list[str]:
    """Each camera's label: its ``name``, else left/right (two), cam0.. (otherwise)."""
    default = ["left", "right"] if len(entries) == 2 else [
        "camera" if len(entries) == 1 else f"cam{i}" for i in range(len(entries))]
    return [e.name or default[i] for i, e in enumerate(entries)]


# ---------------------------------------------------------------------------- settings
def settings(options: GenICamStackOptions, entry: CameraEntry,
             device: Device) -> list[tuple[str, Any]]:
    """The (feature, value) writes of one camera's config, in the order they are made:
    pixel format, region of interest, GigE stream, exposure, gain, trigger, then the
    ``features`` of the driver and of the camera."""
    o = options
    out: list[tuple[str, Any]] = []

    def optional(name: str, value: Any) -> None:  # a helper feature a device may lack
        info = device.feature(name)
        if info is not None and info.writable:
            out.append((name, value))

    optional("AcquisitionMode", "Continuous")
    if o.pixel_format is not None:
        out.append(("PixelFormat", o.pixel_format))
    if o.roi is not None:
        optional("OffsetX", 0)  # first, so that the full width is allowed
        optional("OffsetY", 0)
        out += [("Width", o.roi.width), ("Height", o.roi.height),
                ("OffsetX", o.roi.x), ("OffsetY", o.roi.y)]
    if o.packet_size is not None:
        out.append(("GevSCPSPacketSize", o.packet_size))
    if o.inter_packet_delay is not None:
        out.append(("GevSCPD", o.inter_packet_delay))
    out += exposure_gain(device, o.exposure_us, o.gain_db)
    selector = device.feature("TriggerSelector")
    if selector is not None and "FrameStart" in selector.symbols:
        out.append(("TriggerSelector", "FrameStart"))
    if o.trigger == "free_run":
        out.append(("TriggerMode", "Off"))
    else:
        out += [("TriggerMode", "On"),
                ("TriggerSource", "Software" if o.trigger == "software" else o.trigger_line)]
    out += list(o.features.items()) + list(entry.features.items())
    return out


def exposure_gain(device: Device, exposure_us: float | None,
                  gain_db: float | None) -> list[tuple[str, Any]]:
    """The writes of exposure (us) and gain (dB), automatic modes off first (None: none)."""
    out: list[tuple[str, Any]] = []
    for value, auto, names in ((exposure_us, "ExposureAuto", ("ExposureTime", "ExposureTimeAbs")),
                               (gain_db, "GainAuto", ("Gain",))):
        if value is None:
            continue
        info = device.feature(auto)
        if info is not None and info.writable:
            out.append((auto, "Off"))
        out.append((next((n for n in names if device.feature(n)), names[-1]), float(value)))
    return out


def _chosen_by(device: DeviceInfo, entry: CameraEntry) -> bool:
    return ((entry.serial is not None and entry.serial == device.serial)
            or (entry.user_name is not None and entry.user_name == device.user_name)
            or (entry.ip is not None and entry.ip == device.address))


def select(entries: Sequence[CameraEntry], names: Sequence[str], found: Sequence[DeviceInfo],
           stack: str) -> list[DeviceInfo]:
    """The discovered device of each entry; ``CameraError`` naming the one not found."""
    chosen = []
    for entry, name in zip(entries, names, strict=True):
        hits = [d for d in found if _chosen_by(d, entry)]
        if not hits:
            seen = "; ".join(d.label() for d in found) or "none"
            raise CameraError(f"{stack}: {camera_label(name)}: no device with {entry.selector()} "
                              f"(found: {seen})")
        if len(hits) > 1:
            raise CameraError(f"{stack}: {camera_label(name)}: {len(hits)} devices with "
                              f"{entry.selector()}: {'; '.join(d.label() for d in hits)}")
        if hits[0] in chosen:
            raise CameraError(f"{stack}: {camera_label(name)}: {entry.selector()} is already "
                              "used by another camera of this config")
        chosen.append(hits[0])
    return chosen


# ---------------------------------------------------------------------------- the driver
class _NoFrame(CameraError):
    """A camera gave no frame within the grab's time."""


class _Incomplete(CameraError):
    """A camera gave a frame the SDK reports incomplete."""


class GenICamStackCamera(CameraDriver):
    """One or more cameras of one SDK, triggered together, grabbed as one acquisition."""

    Options = GenICamStackOptions
    options: GenICamStackOptions

    def __init__(self, options: GenICamStackOptions, config: Config) -> None:
        super().__init__(options, config)
        self.stack = self.make_stack()  # CameraError when the SDK is not installed
        self.names = camera_names(options.cameras)
        self._devices: list[Device] = []
        self.applied: list[dict[str, Any]] = []
        self.formats: list[str] = []
        #: Each camera's image size (Width, Height) as the device reports it after the settings.
        self.sizes: list[tuple[int, int]] = []
        #: Why the cameras are down (an outage), "" when they work.
        self.outage = ""
        self._outage_since = 0.0
        self._backoff_s = options.reopen_backoff_s
        self._next_try = 0.0
        #: Grabs in a row in which a camera gave no frame (``no_frame_limit``).
        self._misses = 0
        #: Sets taken again because a frame was incomplete (``incomplete_retries``).
        self.incomplete_retried = 0
        #: Closes the devices of an outage in the background (an SDK may wait out its
        #: retries for each call to a device that is gone); a reopen waits for it.
        self._releasing: threading.Thread | None = None

    @staticmethod
    def names_of(options: GenICamStackOptions) -> list[str]:
        """The cameras' labels (``camera_names``), for a caller that has only the class."""
        return camera_names(options.cameras)

    @classmethod
    @abstractmethod
    def make_stack(cls) -> Stack:
        """The SDK; ``CameraError`` naming the extra to install when it is missing."""

    def describe(self) -> str:
        return f"{self.type_name} " + " + ".join(
            f"{n} ({e.selector()})" for n, e in zip(self.names, self.options.cameras,
                                                    strict=True))

    # ---------------------------------------------------------------- open / close
    def _open_blocking(self) -> None:
        self._open_devices()

    def _open_devices(self) -> None:
        self._misses = 0
        found = self.stack.discover()
        infos = select(self.options.cameras, self.names, found, self.type_name)
        refused: list[str] = []  # every camera's refused settings, reported together
        try:
            for name, entry, info in zip(self.names, self.options.cameras, infos, strict=True):
                device = self.stack.open(info)
                self._devices.append(device)
                try:
                    self.applied.append(
                        apply_settings(name, device, settings(self.options, entry, device)))
                except SettingError as err:
                    refused.append(str(err))
                    continue
                fmt = str(device.read("PixelFormat"))
                if fmt not in FORMATS:
                    raise SettingError(f"{camera_label(name)} ({info.label()}): PixelFormat {fmt} "
                                       f"is not one vgripd converts (set pixel_format to one "
                                       f"of {', '.join(FORMATS)})")
                self.formats.append(fmt)
                self.sizes.append((int(device.read("Width")), int(device.read("Height"))))
            if refused:
                raise SettingError("\n".join(refused))
            for device in self._devices:
                device.start(self.options.buffers)
        except CameraError as err:
            self._close_devices()
            if isinstance(err, SettingError):
                raise
            raise CameraError(f"{self.type_name}: {err}") from None
        except Exception as err:  # an SDK call outside the settings
            self._close_devices()
            raise CameraError(f"{self.type_name}: cannot open {self.describe()}: {err}") from None

    def _close_devices(self) -> None:
        for device in self._devices:
            device.close()
        self._devices, self.applied, self.formats, self.sizes = [], [], [], []

    def _close_blocking(self) -> None:
        self._close_devices()


    def _settings_blocking(self, exposure_us: float | None, gain_db: float | None
                           ) -> dict[str, Any]:
        """Exposure and gain of every camera, checked on all of them before any is written
        (a refused value changes nothing), then written and read back as at open. The options
        keep the new values, so a reopen after an outage applies them again."""
        if not self._devices:
            raise CameraError(f"{self.type_name}: {self.outage or 'the cameras are not open'}")
        plans = [(name, device, exposure_gain(device, exposure_us, gain_db))
                 for name, device in zip(self.names, self._devices, strict=True)]
        refused = []
        for name, device, writes in plans:
            for feature, value in writes:
                info = device.feature(feature)
                why = (f"feature {feature} does not exist on this device" if info is None
                       else check_value(info, value))
                if why is not None:
                    refused.append(f"{camera_label(name)} ({device.info.label()}): "
                                   + (why if info is None else f"{feature} {why}"))
        if refused:
            raise SettingError("\n".join(refused))
        applied = {name: apply_settings(name, device, writes) for name, device, writes in plans}
        for i, name in enumerate(self.names):
            self.applied[i].update(applied[name])
        update = {k: v for k, v in (("exposure_us", exposure_us), ("gain_db", gain_db))
                  if v is not None}
        self.options = self.options.model_copy(update=update)
        return applied

    def _focus_blocking(self, value: float | None) -> dict[str, Any]:
        """The focus feature of every camera (``focus_feature``, else the first of
        ``FOCUS_FEATURES`` the device has): read, or written on all of them and read back;
        not available, naming the camera and what was looked for, where a device has none."""
        if not self._devices:
            raise CameraError(f"{self.type_name}: {self.outage or 'the cameras are not open'}")
        names = (self.options.focus_feature,) if self.options.focus_feature else FOCUS_FEATURES
        found = []
        for name, device in zip(self.names, self._devices, strict=True):
            feature = next((n for n in names if device.feature(n) is not None), None)
            if feature is None:
                looked = (f"the feature {names[0]} (camera.focus_feature)"
                          if self.options.focus_feature else
                          f"none of the GenICam focus features {', '.join(names)}")
                return {"available": False, "reason": (
                    f"{camera_label(name)} ({device.info.label()}): {looked} on this device "
                    "(a fixed-focus lens: turn its ring, the preview's focus figure guides; a "
                    "lens controller under another name: camera.focus_feature)")}
            found.append((name, device, feature))
        if value is not None:
            refused = [f"{camera_label(n)} ({d.info.label()}): {f} {why}"
                       for n, d, f in found
                       if (why := check_value(d.feature(f), value)) is not None]  # type: ignore[arg-type]
            if refused:
                raise SettingError("\n".join(refused))
            for name, device, feature in found:
                apply_settings(name, device, [(feature, value)])
        cameras = []
        for name, device, feature in found:
            info = device.feature(feature)
            assert info is not None
            now = device.read(feature) if info.readable else value
            cameras.append({"name": name, "feature": feature, "value": now,
                            "range": info.range_text(), "writable": info.writable})
        return {"available": True, "cameras": cameras}

    async def check_settings(self) -> list[tuple[int, int]]:
        """Open (which applies and reads back every setting) and close again: `vgripd check`.
        Returns each camera's image size (Width, Height) as configured."""
        await self.open()
        sizes = list(self.sizes)
        await self.close()
        return sizes

    # ---------------------------------------------------------------- grab
    def _grab_blocking(self, timeout_s: float) -> ImagePair:
        if self.outage:
            self._reopen()
        # Leave the daemon time to tell a failed grab from a hung one (it takes a grab that
        # used 90 % of the job's time for a hang and reopens the camera itself).
        deadline = time.monotonic() + min(self.options.frame_timeout_s, 0.75 * timeout_s)
        try:
            pair = self._acquire_whole(deadline)
        except _NoFrame:
            self._misses += 1
            self._judge_outage()
            raise
        except CameraError:
            self._judge_outage()
            raise
        self._misses = 0
        return pair

    def _acquire_whole(self, deadline: float) -> ImagePair:
        """A set of whole frames: a set with an incomplete frame is taken again (software
        trigger and free run) while retries and the grab's time last."""
        retries = 0 if self.options.trigger == "hardware" else self.options.incomplete_retries
        for attempt in range(retries + 1):
            try:
                return self._acquire(deadline)
            except _Incomplete as err:
                if attempt == retries or time.monotonic() >= deadline:
                    raise
                self.incomplete_retried += 1
                log.warning("%s; taking the set again (%d of %d)", err, attempt + 1, retries)
        raise AssertionError("unreachable")

    def _acquire(self, deadline: float) -> ImagePair:
        o = self.options
        t0 = time.monotonic()
        for device in self._devices:
            device.drain()  # no frame taken before this request is ever returned
        if o.trigger == "software":
            for device in self._devices:  # back to back: the pair is as close as SDK calls
                try:
                    device.trigger(max(0.0, deadline - time.monotonic()))
                except CameraError:
                    raise  # already names the camera and why
                except Exception as err:  # the SDK's own error types
                    raise CameraError(f"{self._cam(device)}: software trigger failed: "
                                      f"{err}") from None
        images = []
        stamps: list[int | None] = []
        for device, fmt in zip(self._devices, self.formats, strict=True):
            frame = device.fetch(max(0.0, deadline - time.monotonic()))
            if frame is None:
                raise _NoFrame(f"{self._cam(device)}: no frame within "
                               f"{time.monotonic() - t0:.1f} s"
                                  + (f" (waiting for the trigger on {o.trigger_line})"
                                     if o.trigger == "hardware" else ""))
            if not frame.complete:
                raise _Incomplete(f"{self._cam(device)}: incomplete frame refused "
                                  f"({frame.problem})")
            try:
                images.append(to_image(frame.payload, frame.width, frame.height,
                                       frame.pixel_format or fmt, o.grayscale))
            except PixelError as err:
                raise CameraError(f"{self._cam(device)}: frame refused: {err}") from None
            stamps.append(frame.timestamp_ns)
        t_mono_ns = time.monotonic_ns()
        self._check_skew(stamps)
        meta: dict[str, Any] = {
            "cameras": list(self.names),
            "serials": [d.info.serial for d in self._devices],
            "device_timestamps_ns": stamps,
        }
        return ImagePair.of_views(images, t_mono_ns, source=f"{self.type_name}:"
                                  + "+".join(d.info.serial for d in self._devices), meta=meta)

    def _cam(self, device: Device) -> str:
        i = self._devices.index(device)
        return f"{self.type_name}: {camera_label(self.names[i])} ({device.info.label()})"

    def _check_skew(self, stamps: list[int | None]) -> None:
        limit = self.options.max_skew_ms
        if limit is None or len(stamps) < 2:
            return
        missing = [n for n, s in zip(self.names, stamps, strict=True) if not s]
        if missing:
            raise CameraError(f"{self.type_name}: max_skew_ms needs device timestamps, camera "
                              f"{', '.join(missing)} reports none")
        known = [s for s in stamps if s]
        first = self.names[stamps.index(min(known))]
        last = self.names[stamps.index(max(known))]
        skew_ms = (max(known) - min(known)) / 1e6
        if skew_ms > limit:
            raise CameraError(f"{self.type_name}: cameras {first} and {last} exposed "
                              f"{skew_ms:.3f} ms apart (max_skew_ms = {limit:g})")

    # ---------------------------------------------------------------- outages
    def _judge_outage(self) -> None:
        """After a failed grab: a camera that no longer answers starts an outage (all
        cameras closed, reopened later with back-off), and so does one that gave no frame to
        ``no_frame_limit`` grabs in a row (reopened at the next grab); otherwise only this
        grab failed."""
        if self.outage:
            return
        o = self.options
        dead = [n for n, d in zip(self.names, self._devices, strict=True) if not d.alive()]
        self._outage_since = now = time.monotonic()
        self._backoff_s = o.reopen_backoff_s
        if dead:
            self.outage = f"{camera_label(', '.join(dead))} stopped answering"
            self._next_try = now + self._backoff_s
            log.error("%s: %s; closing it, reopening with back-off from %g s (logged once "
                      "until it is back)", self.type_name, self.outage, self._backoff_s)
        elif self._misses >= o.no_frame_limit and o.trigger != "hardware":
            self.outage = (f"{camera_label(', '.join(self.names))} gave no frame to "
                           f"{self._misses} grabs in a row")
            self._next_try = now  # it answers: reopen at the next grab
            log.error("%s: %s although it answers; closing it, reopening at the next grab "
                      "(logged once until it is back)", self.type_name, self.outage)
        else:
            return
        self._misses = 0
        devices, self._devices = self._devices, []
        self.applied, self.formats, self.sizes = [], [], []
        if not dead:  # they answer: closing takes no retries, done before the next grab
            for device in devices:
                device.close()
            return

        def release() -> None:
            for device in devices:
                device.close()

        self._releasing = threading.Thread(target=release, daemon=True,
                                           name=f"camera-{self.type_name}-release")
        self._releasing.start()

    def _reopen(self) -> None:
        now = time.monotonic()
        if self._releasing is not None and self._releasing.is_alive():
            raise CameraError(f"{self.type_name}: {self.outage} {now - self._outage_since:.1f} s "
                              "ago; its lost handle is still being released")
        if now < self._next_try:
            raise CameraError(f"{self.type_name}: {self.outage} {now - self._outage_since:.1f} s "
                              f"ago; next reopen in {self._next_try - now:.1f} s")
        try:
            self._open_devices()
        except CameraError as err:
            self._backoff_s = min(2 * self._backoff_s, self.options.reopen_backoff_max_s)
            self._next_try = time.monotonic() + self._backoff_s
            raise CameraError(f"{self.type_name}: {self.outage} "
                              f"{now - self._outage_since:.1f} s ago; reopening failed "
                              f"(next try in {self._backoff_s:g} s): {err}") from None
        log.info("%s: camera back after %.1f s (%s)", self.type_name, now - self._outage_since,
                 self.outage)
        self.outage = ""
