"""GenICam driver: what can be checked without a camera (missing package, options)."""

from __future__ import annotations

import os
import sys
from typing import Any

import pytest

from drivers.cameras.genicam import GenICamCamera
from vgripd.config import DriverSection, config_from_dict
from vgripd.errors import CameraError, ConfigError
from vgripd.registry import CAMERAS, load_class, validate_options

CFG = config_from_dict({})


def make_camera(**options: Any) -> GenICamCamera:
    cls = load_class(CAMERAS, "camera", "genicam")
    section = DriverSection.model_validate({"type": "genicam", **options})
    camera = cls(validate_options(cls, section, "camera"), CFG)
    assert isinstance(camera, GenICamCamera)
    return camera


def test_missing_harvesters_is_one_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    # Make the import fail whether or not harvesters happens to be installed here.
    monkeypatch.setitem(sys.modules, "harvesters", None)
    monkeypatch.setitem(sys.modules, "harvesters.core", None)
    with pytest.raises(CameraError) as info:
        make_camera(cti="/opt/producer.cti")
    assert str(info.value) == (
        "genicam driver needs the 'harvesters' package: pip install vgripd[genicam]")


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({}, "camera: cti: Field required"),
        ({"cti": "p.cti", "trigger": "line1"}, "camera: trigger: Input should be"),
        ({"cti": "p.cti", "exposure_us": 0}, "camera: exposure_us: Input should be greater than 0"),
        ({"cti": "p.cti", "gain": 2}, "camera: gain: Extra inputs are not permitted"),
    ],
)
def test_options_are_validated(options: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        make_camera(**options)


@pytest.mark.hardware
@pytest.mark.skipif(os.environ.get("VGRIPD_HARDWARE") != "1", reason="needs a GenICam camera")
async def test_grab_from_a_real_camera() -> None:
    """VGRIPD_HARDWARE=1 VGRIPD_GENICAM_CTI=/path/producer.cti [VGRIPD_GENICAM_SERIAL=...]"""
    camera = make_camera(cti=os.environ["VGRIPD_GENICAM_CTI"],
                         left_serial=os.environ.get("VGRIPD_GENICAM_SERIAL"))
    await camera.open()
    try:
        pair = await camera.grab(5.0)
    finally:
        await camera.close()
    assert pair.left.ndim == 2
    assert pair.left.size > 0
