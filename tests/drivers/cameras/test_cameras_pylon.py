"""The pylon driver against pylon's own camera emulation (``PYLON_CAMEMU``: three "Basler
Emulation" cameras, serials 0815-0000 to 0815-0002, fed image files through ImageFilename)."""

from __future__ import annotations

import asyncio
import importlib.util
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

# pylon's waits end early when pytest-timeout's SIGALRM timer runs in this process (its signal
# method then reports a timeout after a second): the thread method leaves signals alone.
pytestmark = pytest.mark.timeout(120, method="thread")
os.environ["PYLON_CAMEMU"] = "3"  # read when pylon's transport layers load

from drivers.cameras.pylon import PylonCamera, PylonStack  # noqa: E402
from tests.conftest import REPO, need  # noqa: E402
from vgripd.config import Config  # noqa: E402
from vgripd.errors import CameraError  # noqa: E402

SAMPLES = REPO / "config" / "samples"
LEFT, RIGHT = SAMPLES / "left_00.png", SAMPLES / "right_00.png"


@pytest.fixture(autouse=True)
def _pypylon() -> None:
    need(importlib.util.find_spec("pypylon") is not None,
         "needs pypylon: pip install vgripd[pylon]")


def feed(path: Path) -> dict[str, Any]:
    return {"TestImageSelector": "Off", "ImageFileMode": "On", "ImageFilename": str(path)}


def camera(**options: Any) -> PylonCamera:
    options.setdefault("cameras", [{"serial": "0815-0000", "features": feed(LEFT)}])
    options.setdefault("roi", {"width": 1280, "height": 1024})
    return PylonCamera(PylonCamera.Options.model_validate(options), Config())


def test_the_emulation_lists_two_cameras() -> None:
    found = PylonStack().discover()
    assert [d.serial for d in found][:2] == ["0815-0000", "0815-0001"]
    assert all(d.model == "Emulation" for d in found)


@pytest.mark.parametrize("fmt", ["Mono8", "Mono10", "Mono12", "Mono16", "RGB8Packed",
                                 "BGR8Packed"])
async def test_each_pixel_format_delivers_the_fed_image(fmt: str) -> None:
    cam = camera(pixel_format=fmt)
    await cam.open()
    try:
        pair = await cam.grab(5.0)
    finally:
        await cam.close()
    np.testing.assert_array_equal(pair.left, cv2.imread(str(LEFT), cv2.IMREAD_GRAYSCALE))
    assert cam.applied == []  # closed
    assert pair.right is None
    assert pair.meta["serials"] == ["0815-0000"]


async def test_a_stereo_pair_is_both_cameras_each_with_its_file_and_settings_read_back() -> None:
    cam = camera(cameras=[{"serial": "0815-0000", "features": feed(LEFT)},
                          {"serial": "0815-0001", "features": feed(RIGHT)}],
                 exposure_us=4000, gain_db=6.0, packet_size=1500)
    await cam.open()
    try:
        applied = [dict(a) for a in cam.applied]
        pairs = [await cam.grab(5.0) for _ in range(2)]
    finally:
        await cam.close()
    for pair in pairs:
        np.testing.assert_array_equal(pair.left, cv2.imread(str(LEFT), cv2.IMREAD_GRAYSCALE))
        np.testing.assert_array_equal(pair.right, cv2.imread(str(RIGHT), cv2.IMREAD_GRAYSCALE))
        assert pair.meta["cameras"] == ["left", "right"]
    for got in applied:
        assert got["ExposureTime"] == pytest.approx(4000.0)
        assert got["Gain"] == pytest.approx(6.0, abs=0.1)
        assert got["GevSCPSPacketSize"] == 1500
        assert (got["TriggerMode"], got["TriggerSource"]) == ("On", "Software")


async def test_a_camera_that_does_not_exist_is_named_with_what_was_found() -> None:
    cam = camera(cameras=[{"serial": "40099999"}])
    with pytest.raises(CameraError, match=r"pylon: camera: no device with serial "
                                          r"40099999 \(found: .*serial 0815-0000"):
        await cam.open()


async def test_one_device_for_two_cameras_is_refused() -> None:
    cam = camera(cameras=[{"serial": "0815-0000"}, {"name": "again", "ip": "nowhere"}])
    with pytest.raises(CameraError, match="camera again: no device with IP nowhere"):
        await cam.open()


async def test_skew_cannot_be_judged_without_device_timestamps() -> None:
    """The emulation stamps every frame 0: a max_skew_ms cannot be kept, so every set is
    refused, naming the cameras (never passed unchecked)."""
    cam = camera(cameras=[{"serial": "0815-0000", "features": feed(LEFT)},
                          {"serial": "0815-0001", "features": feed(RIGHT)}], max_skew_ms=1.0)
    await cam.open()
    try:
        with pytest.raises(CameraError, match="max_skew_ms needs device timestamps, camera "
                                              "left, right reports none"):
            await cam.grab(5.0)
    finally:
        await cam.close()


async def test_a_grab_with_a_hardware_trigger_that_never_comes_times_out_naming_the_line() -> None:
    cam = camera(trigger="hardware", trigger_line="Line1", frame_timeout_s=0.3)
    await cam.open()
    try:
        with pytest.raises(CameraError, match=r"pylon: camera \(.*0815-0000\): no frame within "
                                              r".* s \(waiting for the trigger on Line1\)"):
            await cam.grab(5.0)
        assert cam.outage == ""  # the camera answers: a missing pulse is not an outage
    finally:
        await cam.close()


async def test_refused_settings_name_the_camera_the_feature_and_the_devices_range() -> None:
    cam = camera(cameras=[{"name": "left", "serial": "0815-0000",
                           "features": {"SensorWidth": 100, "NoSuch": 1}}],
                 exposure_us=5e8, roi={"width": 1280, "height": 1024, "x": 3000})
    with pytest.raises(CameraError) as info:
        await cam.open()
    lines = str(info.value).splitlines()
    where = "camera left (Basler Emulation, serial 0815-0000)"
    assert f"{where}: ExposureTime = 5e+08 is out of the device's range 1 .. 1e+07" \
        in "\n".join(lines)
    assert any(line.startswith(f"{where}: OffsetX = 3000 is out of the device's range 0 .. ")
               for line in lines), lines
    assert f"{where}: SensorWidth is read-only" in lines
    assert f"{where}: feature NoSuch does not exist on this device" in lines


def _check(tmp_path: Path, camera_toml: str) -> subprocess.CompletedProcess[str]:
    example = (REPO / "config" / "example.toml").read_text()
    head, _, rest = example.partition("[camera]\n")
    rest = rest[rest.index("# --- calibration"):]
    cfg = tmp_path / "cell.toml"
    cfg.write_text(head + camera_toml + "\n" + rest)
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYLON_CAMEMU": "2"}
    return subprocess.run([sys.executable, "-m", "vgripd", "check", "-c", str(cfg)],
                          capture_output=True, text=True, cwd=REPO, env=env, timeout=120,
                          check=False)


def test_vgripd_check_refuses_an_out_of_range_setting_as_a_config_error(tmp_path: Path) -> None:
    base = """[camera]
type = "pylon"
roi = { width = 1280, height = 1024 }
[[camera.cameras]]
name = "left"
serial = "0815-0000"
[[camera.cameras]]
name = "right"
serial = "0815-0001"
"""
    good = _check(tmp_path, base.replace('type = "pylon"', 'type = "pylon"\nexposure_us = 800'))
    assert good.returncode == 0, good.stderr
    assert good.stdout.startswith("OK ")
    bad = _check(tmp_path, base.replace('type = "pylon"', 'type = "pylon"\ngain_db = 90'))
    assert bad.returncode == 78, bad.stderr
    for side, serial in (("left", "0815-0000"), ("right", "0815-0001")):
        assert (f"camera {side} (Basler Emulation, serial {serial}): Gain = 90 is out of the "
                "device's range 0 .. 48") in bad.stderr, bad.stderr
    # the emulation's default 1024 x 1040 images against the demo cell's 1280 x 1024
    unsized = _check(tmp_path, base.replace("roi = { width = 1280, height = 1024 }\n", ""))
    assert unsized.returncode == 78, unsized.stderr
    assert ("camera: camera left delivers 1024x1040 images (Width x Height after the settings) "
            "but calibration.left is calibrated for 1280x1024: set camera.roi") in unsized.stderr
    assert "camera right delivers 1024x1040 images" in unsized.stderr


def test_the_registry_refuses_a_camera_without_a_selector() -> None:
    with pytest.raises(ValueError, match="give exactly one of serial, user_name or ip"):
        PylonCamera.Options.model_validate({"cameras": [{"name": "left"}]})
    with pytest.raises(ValueError, match="'Mono9' is not a supported pixel format"):
        PylonCamera.Options.model_validate({"cameras": [{"serial": "1"}], "pixel_format": "Mono9"})


def test_grab_runs_off_the_event_loop() -> None:
    """The loop keeps turning while a frame is fetched (the SDK call is on the driver's
    thread): a ticker task advances during a grab."""
    async def main() -> int:
        cam = camera()
        await cam.open()
        ticks = 0

        async def ticker() -> None:
            nonlocal ticks
            while True:
                ticks += 1
                await asyncio.sleep(0)

        task = asyncio.create_task(ticker())
        try:
            await cam.grab(5.0)
        finally:
            task.cancel()
            await cam.close()
        return ticks

    assert asyncio.run(main()) > 1


async def test_free_run_takes_a_frame_streamed_after_the_request() -> None:
    cam = camera(trigger="free_run", features={"AcquisitionFrameRateEnable": True,
                                               "AcquisitionFrameRate": 50.0})
    await cam.open()
    try:
        applied = dict(cam.applied[0])
        pair = await cam.grab(5.0)
    finally:
        await cam.close()
    assert applied["TriggerMode"] == "Off"
    np.testing.assert_array_equal(pair.left, cv2.imread(str(LEFT), cv2.IMREAD_GRAYSCALE))


def test_vgripd_check_judges_the_pylon_entries_of_a_multi_camera(tmp_path: Path) -> None:
    entry = """[[camera.cameras]]
type = "pylon"
roi = {{ width = 1280, height = 1024 }}
gain_db = {gain}
cameras = [{{ name = "{name}", serial = "{serial}" }}]
"""
    multi = ('[camera]\ntype = "multi"\n' + entry.format(gain=1, name="left", serial="0815-0000")
             + entry.format(gain=60, name="right", serial="0815-0001"))
    proc = _check(tmp_path, multi)
    assert proc.returncode == 78, proc.stderr
    assert ("camera.cameras.1: camera right (Basler Emulation, serial 0815-0001): Gain = 60 is "
            "out of the device's range 0 .. 48") in proc.stderr
    assert "camera.cameras.0" not in proc.stderr


async def test_three_cameras_are_one_acquisition_in_config_order() -> None:
    files = [SAMPLES / "right_01.png", LEFT, RIGHT]
    cam = camera(cameras=[{"name": f"c{i}", "serial": f"0815-000{(i + 2) % 3}",
                           "features": feed(path)} for i, path in enumerate(files)])
    await cam.open()
    try:
        pair = await cam.grab(5.0)
    finally:
        await cam.close()
    assert len(pair.views) == 3
    assert pair.meta["serials"] == ["0815-0002", "0815-0000", "0815-0001"]
    for image, path in zip(pair.views, files, strict=True):
        np.testing.assert_array_equal(image, cv2.imread(str(path), cv2.IMREAD_GRAYSCALE))
