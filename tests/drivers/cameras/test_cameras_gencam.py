"""The shared GenICam layer's judgements that need no device: a value against what a device
reports about a feature, and choosing devices from what a stack discovered. (The same code
against real SDKs and emulated devices: test_cameras_pylon.py, test_cameras_aravis.py.)"""

from __future__ import annotations

import pytest

from drivers.cameras.gencam import CameraEntry, camera_names, select
from drivers.cameras.gencam_sdk import DeviceInfo, FeatureInfo, check_value
from vgripd.errors import CameraError

WIDTH = FeatureInfo("int", True, True, 16, 2448, 16)
EXPOSURE = FeatureInfo("float", True, True, 19.0, 1e7, None)
FORMAT = FeatureInfo("enum", True, True, symbols=("Mono8", "Mono12p"))


@pytest.mark.parametrize(("info", "value", "why"), [
    (WIDTH, 1280, None),
    (WIDTH, 1290, "= 1290 is not on the device's steps: 16 .. 2448 in steps of 16"),
    (WIDTH, 4096, "= 4096 is out of the device's range 16 .. 2448 in steps of 16"),
    (WIDTH, 12.5, "= 12.5: the device takes an integer (16 .. 2448 in steps of 16)"),
    (WIDTH, True, "= True: the device takes a number (16 .. 2448 in steps of 16)"),
    (EXPOSURE, 8000.0, None),
    (EXPOSURE, 5.0, "= 5 is out of the device's range 19 .. 1e+07"),
    (FORMAT, "Mono12p", None),
    (FORMAT, "Mono16", "= 'Mono16' is not one of Mono8, Mono12p"),
    (FeatureInfo("bool", True, True), "yes", "= 'yes': the device takes true or false"),
    (FeatureInfo("int", True, False, 0, 10, 1), 3, "is read-only"),
    (FeatureInfo("int", False, False, 0, 10, 1), 3, "is not writable now"),
    (FeatureInfo("command", False, True), 1, "is a command, not a setting"),
])
def test_a_value_is_judged_against_the_devices_own_description(info: FeatureInfo, value: object,
                                                               why: str | None) -> None:
    assert check_value(info, value) == why


FOUND = [DeviceInfo("aravis", "A-1", "S1", "M", "V", "10.0.0.1", "cell-left"),
         DeviceInfo("aravis", "A-2", "S2", "M", "V", "10.0.0.2", "cell-right")]


def test_devices_are_chosen_by_serial_user_name_or_ip() -> None:
    entries = [CameraEntry(ip="10.0.0.2"), CameraEntry(user_name="cell-left")]
    assert [d.key for d in select(entries, ["left", "right"], FOUND, "aravis")] == ["A-2", "A-1"]
    with pytest.raises(CameraError, match="camera right: IP 10.0.0.2 is already used by another "
                                          "camera of this config"):
        select([CameraEntry(serial="S2"), CameraEntry(ip="10.0.0.2")], ["left", "right"],
               FOUND, "aravis")


def test_default_names_follow_the_camera_count() -> None:
    assert camera_names([CameraEntry(serial="1")]) == ["camera"]
    assert camera_names([CameraEntry(serial="1"), CameraEntry(serial="2")]) == ["left", "right"]
    assert camera_names([CameraEntry(serial=str(i)) for i in range(3)]) == ["cam0", "cam1", "cam2"]
    assert camera_names([CameraEntry(serial="1", name="top")]) == ["top"]
