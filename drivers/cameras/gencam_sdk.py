"""The contract between the shared GenICam layer (``gencam.py``) and an SDK module (``pylon.py``,
``aravis.py``), and the settings check that needs nothing but it.

An SDK module implements ``Stack`` (discover, open one device) and ``Device`` (describe, read and
write a feature; start, drain, trigger, fetch a frame; say whether the device still answers;
close). ``check_value`` and ``apply_settings`` judge a configured value against what the device
reports about the feature (``FeatureInfo``) before writing it, and read it back after.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar

from vgripd.errors import CameraSettingError


class SettingError(CameraSettingError):
    """A configured GenICam setting that the device refuses (names camera, feature, range)."""


@dataclass(frozen=True)
class DeviceInfo:
    """One device a stack discovered. ``key`` is what the stack opens it by."""

    stack: str
    key: str
    serial: str
    model: str
    vendor: str = ""
    address: str = ""  # IP address (GigE Vision) or the transport's own id
    user_name: str = ""

    def label(self) -> str:
        parts = [f"{self.vendor} {self.model}".strip(), f"serial {self.serial}"]
        if self.address:
            parts.append(self.address)
        return ", ".join(parts)


@dataclass(frozen=True)
class FeatureInfo:
    """What a device says about one feature: kind int | float | enum | bool | str | command."""

    kind: str
    readable: bool
    writable: bool
    minimum: float | None = None
    maximum: float | None = None
    increment: float | None = None
    symbols: tuple[str, ...] = ()

    def range_text(self) -> str:
        if self.kind == "enum":
            return f"one of {', '.join(self.symbols)}"
        if self.minimum is not None and self.maximum is not None:
            step = (f" in steps of {self.increment:g}"
                    if self.increment not in (None, 0, 1) else "")
            return f"{self.minimum:g} .. {self.maximum:g}{step}"
        return f"a {self.kind}"


@dataclass(frozen=True)
class Frame:
    """One frame as the SDK delivered it; ``payload`` is a copy the SDK no longer owns."""

    payload: bytes | Any
    width: int
    height: int
    pixel_format: str
    timestamp_ns: int | None  # device clock; None when the device reports none
    complete: bool = True
    problem: str = ""  # why it is incomplete, in the SDK's words


class Device(ABC):
    """One open camera of an SDK; only ever called from its driver's thread."""

    def __init__(self, info: DeviceInfo) -> None:
        self.info = info

    @abstractmethod
    def feature(self, name: str) -> FeatureInfo | None:
        """What the device reports about ``name``; None when it has no such feature."""

    @abstractmethod
    def read(self, name: str) -> Any: ...

    @abstractmethod
    def write(self, name: str, value: Any) -> None: ...

    @abstractmethod
    def start(self, buffers: int) -> None:
        """Start streaming (acquisition on)."""

    @abstractmethod
    def drain(self) -> int:
        """Drop every frame the stream holds; how many."""

    @abstractmethod
    def trigger(self, timeout_s: float) -> None:
        """Fire the software trigger."""

    @abstractmethod
    def fetch(self, timeout_s: float) -> Frame | None:
        """The next frame, or None when none came within ``timeout_s``."""

    @abstractmethod
    def alive(self) -> bool:
        """Whether the device still answers (False: unplugged, powered off, link lost)."""

    @abstractmethod
    def close(self) -> None:
        """Stop streaming and release the device; never raises."""


class Stack(ABC):
    """An SDK: what it discovers and how it opens one device."""

    name: ClassVar[str]

    @abstractmethod
    def discover(self) -> list[DeviceInfo]: ...

    @abstractmethod
    def open(self, info: DeviceInfo) -> Device:
        """``CameraError`` saying why (held by another process, access denied, ...)."""


# ---------------------------------------------------------------------------- settings
def _matches(info: FeatureInfo, want: Any, got: Any) -> bool:
    if info.kind == "float":
        tol = max(abs(float(want)) * 0.01, info.increment or 0.0, 1e-9)
        return abs(float(got) - float(want)) <= tol
    if info.kind == "bool":
        return bool(got) == bool(want)
    return str(got) == str(want)


def check_value(info: FeatureInfo, value: Any) -> str | None:
    """Why ``value`` cannot be written to a feature described by ``info``; None if it can."""
    if not info.writable:
        return "is read-only" if info.readable else "is not writable now"
    if info.kind == "command":
        return "is a command, not a setting"
    if info.kind == "enum":
        if str(value) not in info.symbols:
            return f"= {value!r} is not {info.range_text()}"
        return None
    if info.kind == "bool":
        return None if isinstance(value, bool) else f"= {value!r}: the device takes true or false"
    if info.kind == "str":
        return None if isinstance(value, str) else f"= {value!r}: the device takes a string"
    if isinstance(value, bool) or not isinstance(value, int | float):
        return f"= {value!r}: the device takes a number ({info.range_text()})"
    if info.kind == "int" and value != int(value):
        return f"= {value!r}: the device takes an integer ({info.range_text()})"
    lo, hi = info.minimum, info.maximum
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        return f"= {value:g} is out of the device's range {info.range_text()}"
    inc = info.increment
    if info.kind == "int" and inc and inc > 1 and lo is not None and (value - lo) % inc:
        return f"= {value:g} is not on the device's steps: {info.range_text()}"
    return None


def camera_label(name: str) -> str:
    """``camera left`` in messages; the single unnamed camera is just ``camera``."""
    return "camera" if name == "camera" else f"camera {name}"


def apply_settings(label: str, device: Device, writes: list[tuple[str, Any]]) -> dict[str, Any]:
    """Write and read back each setting; ``SettingError`` listing every one refused, each
    naming the camera, the feature and the range the device reports. Returns what the
    device reports after the writes (for the frame's ``meta``)."""
    problems: list[str] = []
    applied: dict[str, Any] = {}
    where = f"{camera_label(label)} ({device.info.label()})"
    for name, value in writes:
        info = device.feature(name)
        if info is None:
            problems.append(f"{where}: feature {name} does not exist on this device")
            continue
        why = check_value(info, value)
        if why is not None:
            problems.append(f"{where}: {name} {why}")
            continue
        try:
            device.write(name, int(value) if info.kind == "int" else value)
            got = device.read(name) if info.readable else value
        except Exception as err:  # SDK exceptions share no base class with ours
            problems.append(f"{where}: {name} = {value!r} refused by the device: {err}")
            continue
        if not _matches(info, value, got):
            problems.append(f"{where}: {name} set to {value!r}, the device reports {got!r} "
                            f"(range {info.range_text()})")
            continue
        applied[name] = got
    if problems:
        raise SettingError("\n".join(problems))
    return applied
