"""Basler cameras (GigE, USB3 Vision, CoaXPress through GenTL) through ``pypylon``.

Needs the optional extra ``pip install vgripd[pylon]``: the ``pypylon`` wheel bundles the pylon
runtime, so nothing else is installed. The options, the settings check, triggering, pixel
formats and outages are the shared GenICam layer's (``drivers/cameras/gencam.py``, where the
options are listed); this module is only the pylon calls.

pylon's camera emulation (``PYLON_CAMEMU=N`` in the environment of the daemon: N cameras
"Basler Emulation", serials ``0815-0000``, ``0815-0001``, ...) delivers a file per camera with
``features = { TestImageSelector = "Off", ImageFileMode = "On", ImageFilename = "left.png" }``;
the tests run the whole daemon on it (docs/cameras.md).
"""

from __future__ import annotations

from typing import Any

from drivers.cameras.gencam import GenICamStackCamera
from drivers.cameras.gencam_sdk import Device, DeviceInfo, FeatureInfo, Frame, Stack
from vgripd.errors import CameraError

MISSING = "pylon driver needs the 'pypylon' package: pip install vgripd[pylon]"


def _sdk() -> tuple[Any, Any]:
    try:
        from pypylon import genicam, pylon
    except ImportError:
        raise CameraError(MISSING) from None
    return pylon, genicam


class PylonDevice(Device):
    def __init__(self, info: DeviceInfo, camera: Any) -> None:
        super().__init__(info)
        self._pylon, self._genicam = _sdk()
        self._cam = camera
        self._nodes = camera.GetNodeMap()
        tick = self.feature("GevTimestampTickFrequency")
        # GigE cameras count in ticks of this frequency; USB3 Vision and the emulation in ns
        self._tick_hz = int(self.read("GevTimestampTickFrequency")) if tick and tick.readable \
            else 1_000_000_000

    def feature(self, name: str) -> FeatureInfo | None:
        g = self._genicam
        node = self._nodes.GetNode(name)
        if node is None or not g.IsImplemented(node) or not g.IsAvailable(node):
            return None
        readable, writable = bool(g.IsReadable(node)), bool(g.IsWritable(node))
        if isinstance(node, g.IInteger):
            return FeatureInfo("int", readable, writable, node.GetMin(), node.GetMax(),
                               node.GetInc())
        if isinstance(node, g.IFloat):
            inc = node.GetInc() if node.HasInc() else None
            return FeatureInfo("float", readable, writable, node.GetMin(), node.GetMax(), inc)
        if isinstance(node, g.IEnumeration):
            return FeatureInfo("enum", readable, writable, symbols=tuple(node.GetSymbolics()))
        if isinstance(node, g.IBoolean):
            return FeatureInfo("bool", readable, writable)
        if isinstance(node, g.ICommand):
            return FeatureInfo("command", readable, writable)
        return FeatureInfo("str", readable, writable)

    def read(self, name: str) -> Any:
        return self._nodes.GetNode(name).Value

    def write(self, name: str, value: Any) -> None:
        self._nodes.GetNode(name).Value = value

    def start(self, buffers: int) -> None:
        self._cam.MaxNumBuffer.Value = buffers
        self._cam.StartGrabbing(self._pylon.GrabStrategy_OneByOne)

    def drain(self) -> int:
        dropped = 0
        while True:
            result = self._cam.RetrieveResult(0, self._pylon.TimeoutHandling_Return)
            if not result.IsValid():
                return dropped
            result.Release()
            dropped += 1

    def trigger(self, timeout_s: float) -> None:
        p = self._pylon
        if not self._cam.WaitForFrameTriggerReady(int(timeout_s * 1000),
                                                  p.TimeoutHandling_Return):
            raise CameraError(f"pylon: camera {self.info.label()} not ready for a trigger "
                              f"within {timeout_s:.3g} s")
        self._cam.ExecuteSoftwareTrigger()

    def fetch(self, timeout_s: float) -> Frame | None:
        result = self._cam.RetrieveResult(int(timeout_s * 1000),
                                          self._pylon.TimeoutHandling_Return)
        if not result.IsValid():
            return None
        try:
            if not result.GrabSucceeded():
                return Frame(b"", 0, 0, "", None, complete=False,
                             problem=f"error {result.GetErrorCode():#x}: "
                                     f"{result.GetErrorDescription()}")
            stamp = int(result.GetTimeStamp())
            return Frame(result.GetBuffer(), int(result.GetWidth()), int(result.GetHeight()),
                         "", stamp * 1_000_000_000 // self._tick_hz if stamp else None)
        finally:
            result.Release()

    def alive(self) -> bool:
        return not self._cam.IsCameraDeviceRemoved()

    def close(self) -> None:
        cam = self._cam
        for step in (cam.StopGrabbing, cam.Close, cam.DestroyDevice):
            try:
                step()
            except Exception:  # release what can be released
                continue


class PylonStack(Stack):
    name = "pylon"

    def __init__(self) -> None:
        self._pylon, _ = _sdk()

    def discover(self) -> list[DeviceInfo]:
        found = []
        for d in self._pylon.TlFactory.GetInstance().EnumerateDevices():
            address = d.GetIpAddress() if d.IsIpAddressAvailable() else ""
            found.append(DeviceInfo("pylon", d.GetFullName(), d.GetSerialNumber(),
                                    d.GetModelName(), d.GetVendorName(), address,
                                    d.GetUserDefinedName()))
        return found

    def open(self, info: DeviceInfo) -> Device:
        p = self._pylon
        wanted = p.CDeviceInfo()
        wanted.SetFullName(info.key)
        try:
            camera = p.InstantCamera(p.TlFactory.GetInstance().CreateDevice(wanted))
            camera.Open()
        except Exception as err:  # pylon's RuntimeException and friends
            text = " ".join(str(err).split())
            held = any(w in text.lower() for w in ("exclusive", "another", "access denied",
                                                   "controlled by"))
            raise CameraError(f"cannot open {info.label()}"
                              + (" (held by another process)" if held else "")
                              + f": {text}") from None
        return PylonDevice(info, camera)


class PylonCamera(GenICamStackCamera):
    """Basler cameras through pypylon (``drivers/cameras/gencam.py`` has the options)."""

    type_name = "pylon"

    @classmethod
    def make_stack(cls) -> Stack:
        return PylonStack()
