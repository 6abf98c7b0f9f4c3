"""GigE Vision and USB3 Vision cameras of any vendor through Aravis (LGPL), via PyGObject.

Needs Debian's ``gir1.2-aravis-0.8`` (libaravis and its typelib) and the optional extra
``pip install vgripd[aravis]`` (PyGObject; building it needs ``libgirepository1.0-dev
libcairo2-dev pkg-config gcc``: docs/cameras.md). The options, the settings check, triggering,
pixel formats and outages are the shared GenICam layer's (``drivers/cameras/gencam.py``); this
module is only the Aravis calls.

Selecting a camera: ``serial`` and ``ip`` as Aravis discovers them; ``user_name`` is compared
with Aravis' device id (Aravis lists no user-defined name without opening the device). Stream
packets that are lost are asked for again (Aravis' packet resend, on by default); a frame
still incomplete after that is refused.
"""

from __future__ import annotations

import contextlib
from typing import Any

from drivers.cameras.gencam import GenICamStackCamera
from drivers.cameras.gencam_sdk import Device, DeviceInfo, FeatureInfo, Frame, Stack
from vgripd.errors import CameraError

MISSING = ("aravis driver needs Aravis and PyGObject: apt-get install gir1.2-aravis-0.8 "
           "libgirepository1.0-dev libcairo2-dev pkg-config gcc (Aravis, and what PyGObject "
           "builds with); pip install 'vgripd[aravis]' (docs/cameras.md, \"Aravis\")")


def _sdk() -> Any:
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis
    except (ImportError, ValueError) as err:
        raise CameraError(f"{MISSING} ({err})") from None
    return Aravis


class AravisDevice(Device):
    def __init__(self, info: DeviceInfo, camera: Any) -> None:
        super().__init__(info)
        self._ar = _sdk()
        self._cam = camera
        self._dev = camera.get_device()
        self._stream: Any = None
        self._lost = False
        self._kinds: dict[str, str] = {}
        self._handler = self._dev.connect("control-lost", self._on_control_lost)

    def _on_control_lost(self, *_: Any) -> None:  # Aravis' heartbeat thread
        self._lost = True

    def feature(self, name: str) -> FeatureInfo | None:
        ar, dev = self._ar, self._dev
        node = dev.get_feature(name)
        if node is None or not node.is_implemented() or not node.is_available():
            return None
        mode = dev.get_feature_access_mode(name)
        readable = mode in (ar.GcAccessMode.RO, ar.GcAccessMode.RW)
        writable = mode in (ar.GcAccessMode.WO, ar.GcAccessMode.RW)
        info: FeatureInfo
        if isinstance(node, ar.GcEnumeration):
            symbols = dev.dup_available_enumeration_feature_values_as_strings(name) or []
            info = FeatureInfo("enum", readable, writable, symbols=tuple(symbols))
        elif isinstance(node, ar.GcCommand):
            info = FeatureInfo("command", readable, writable)
        elif isinstance(node, ar.GcBoolean):
            info = FeatureInfo("bool", readable, writable)
        elif isinstance(node, ar.GcInteger):
            lo, hi = dev.get_integer_feature_bounds(name)
            info = FeatureInfo("int", readable, writable, lo, hi,
                               dev.get_integer_feature_increment(name))
        elif isinstance(node, ar.GcFloat):
            lo, hi = dev.get_float_feature_bounds(name)
            info = FeatureInfo("float", readable, writable, lo, hi)
        else:
            info = FeatureInfo("str", readable, writable)
        self._kinds[name] = info.kind
        return info

    def _kind(self, name: str) -> str:
        if name not in self._kinds:
            self.feature(name)
        return self._kinds.get(name, "str")

    def read(self, name: str) -> Any:
        dev, kind = self._dev, self._kind(name)
        if kind == "int":
            return dev.get_integer_feature_value(name)
        if kind == "float":
            return dev.get_float_feature_value(name)
        if kind == "bool":
            return dev.get_boolean_feature_value(name)
        return dev.get_string_feature_value(name)

    def write(self, name: str, value: Any) -> None:
        dev, kind = self._dev, self._kind(name)
        if kind == "int":
            dev.set_integer_feature_value(name, int(value))
        elif kind == "float":
            dev.set_float_feature_value(name, float(value))
        elif kind == "bool":
            dev.set_boolean_feature_value(name, bool(value))
        else:
            dev.set_string_feature_value(name, str(value))

    def start(self, buffers: int) -> None:
        self._stream = self._cam.create_stream(None, None)
        size = self._cam.get_payload()
        for _ in range(buffers):
            self._stream.push_buffer(self._ar.Buffer.new_allocate(size))
        self._cam.start_acquisition()

    def drain(self) -> int:
        dropped = 0
        while (buffer := self._stream.try_pop_buffer()) is not None:
            self._stream.push_buffer(buffer)
            dropped += 1
        return dropped

    def trigger(self, timeout_s: float) -> None:
        try:
            self._cam.software_trigger()
        except Exception as err:  # GLib.Error
            # Aravis retried the write for ~2.5 s: the control channel is gone; asking the
            # device again (alive) would cost as much once more
            self._lost = self._lost or "timeout" in str(err)
            raise

    def fetch(self, timeout_s: float) -> Frame | None:
        buffer = self._stream.timeout_pop_buffer(max(1, int(timeout_s * 1e6)))
        if buffer is None:
            return None
        try:
            status = buffer.get_status()
            if status != self._ar.BufferStatus.SUCCESS:
                return Frame(b"", 0, 0, "", None, complete=False,
                             problem=f"Aravis buffer status {status.value_nick}")
            return Frame(bytes(buffer.get_data()), buffer.get_image_width(),
                         buffer.get_image_height(), "", buffer.get_timestamp() or None)
        finally:
            self._stream.push_buffer(buffer)

    def alive(self) -> bool:
        if self._lost:
            return False
        try:
            self._dev.get_integer_feature_value("Width")
        except Exception:  # GLib.Error: the control channel does not answer
            return False
        return True

    def close(self) -> None:
        if self._cam is None:
            return
        self._dev.disconnect(self._handler)
        if not self._lost:  # each call to a camera that is gone waits out Aravis' retries
            with contextlib.suppress(Exception):
                self._cam.stop_acquisition()
            if hasattr(self._dev, "leave_control"):  # GigE: another application may take it
                with contextlib.suppress(Exception):
                    self._dev.leave_control()
        # the last references: GObject releases the stream and the device
        self._stream = self._dev = self._cam = None


class AravisStack(Stack):
    name = "aravis"

    def __init__(self) -> None:
        self._ar = _sdk()

    def discover(self) -> list[DeviceInfo]:
        ar = self._ar
        ar.update_device_list()
        return [DeviceInfo("aravis", ar.get_device_id(i), ar.get_device_serial_nbr(i) or "",
                           ar.get_device_model(i) or "", ar.get_device_vendor(i) or "",
                           ar.get_device_address(i) or "", ar.get_device_id(i))
                for i in range(ar.get_n_devices())]

    def open(self, info: DeviceInfo) -> Device:
        try:
            camera = self._ar.Camera.new(info.key)
        except Exception as err:  # GLib.Error
            text = getattr(err, "message", str(err))
            held = any(w in text.lower() for w in ("privilege", "access", "control"))
            raise CameraError(f"cannot open {info.label()}"
                              + (" (held by another process)" if held else "")
                              + f": {text}") from None
        device = camera.get_device()
        # GigE Vision: one application controls a camera; Aravis then opens it read-only
        if hasattr(device, "is_controller") and not device.is_controller():
            raise CameraError(f"cannot open {info.label()} (held by another process): another "
                              "application has its GigE Vision control channel")
        # A process that died holding the camera (the worker SIGKILLed) leaves its acquisition
        # running, streaming to its dead port; a device may keep that stream even after this
        # process took control. Stopping acquisition first makes the stream start afresh to us.
        with contextlib.suppress(Exception):  # GLib.Error: a device without AcquisitionStop
            camera.stop_acquisition()
        return AravisDevice(info, camera)


class AravisCamera(GenICamStackCamera):
    """GigE Vision / USB3 Vision cameras through Aravis (``gencam.py`` has the options)."""

    type_name = "aravis"

    @classmethod
    def make_stack(cls) -> Stack:
        return AravisStack()
