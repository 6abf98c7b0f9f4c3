"""Exposure and gain changed live (``set_settings``) on pylon's camera emulation: the same
checks as at open, against the range the device reports; a refused value changes no camera."""

from __future__ import annotations

import importlib.util
import os

import pytest

pytestmark = pytest.mark.timeout(120, method="thread")  # as test_cameras_pylon.py
os.environ["PYLON_CAMEMU"] = "3"  # read when pylon's transport layers load

from drivers.cameras.gencam_sdk import SettingError  # noqa: E402
from tests.conftest import need  # noqa: E402
from tests.drivers.cameras.test_cameras_pylon import LEFT, RIGHT, camera, feed  # noqa: E402


@pytest.fixture(autouse=True)
def _pypylon() -> None:
    need(importlib.util.find_spec("pypylon") is not None,
         "needs pypylon: pip install vgripd[pylon]")


async def test_exposure_and_gain_are_set_live_on_both_cameras_and_read_back() -> None:
    cam = camera(cameras=[{"serial": "0815-0000", "features": feed(LEFT)},
                          {"serial": "0815-0001", "features": feed(RIGHT)}],
                 exposure_us=4000, gain_db=0.0)
    await cam.open()
    try:
        got = await cam.set_settings(6000.0, 3.0)
        assert set(got) == {"left", "right"}
        for name in ("left", "right"):
            assert got[name]["ExposureTime"] == pytest.approx(6000.0, rel=0.01)
            assert got[name]["Gain"] == pytest.approx(3.0, abs=0.1)
        assert cam.applied[1]["ExposureTime"] == pytest.approx(6000.0, rel=0.01)
        assert (cam.options.exposure_us, cam.options.gain_db) == (6000.0, 3.0)  # a reopen

        # Out of the device's range: refused naming camera, feature and range; nothing written.
        with pytest.raises(SettingError) as err:
            await cam.set_settings(1e12, None)
        text = str(err.value)
        assert "camera left" in text
        assert "camera right" in text
        assert "ExposureTime" in text, text
        assert "out of the device's range" in text, text
        assert cam.applied[0]["ExposureTime"] == pytest.approx(6000.0, rel=0.01)
        assert (await cam.grab(5.0)).left is not None  # still grabbing
    finally:
        await cam.close()
