"""The setup page's calibration and hand-eye steps with a ``vgripd calibrate cameras`` result
that places the cameras in no base frame, clicked in headless Chromium against ``vgripd demo
--setup`` (the learning cell's pair, calibrated "as cameras"): the result is accepted, the page
says what the hand-eye step does with it, and the reference camera's pose typed there places
both cameras, written as ``[[calibration.cameras]]`` through the judged transaction."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from tests.integration.setup_browser import (
    capture_and_calibrate,
    click,
    demo_setup,
    open_page,
    text,
    until,
)
from tests.integration.test_web import _chromium
from vgripd.config import DEMO_CALIBRATION

pytestmark = pytest.mark.slow(minutes=5)


@pytest.mark.timeout(2400)
async def test_a_cameras_result_without_base_frame_is_placed_by_the_hand_eye_step(
        tmp_path: Path) -> None:
    folder = tmp_path / "cell"
    async with demo_setup(folder) as cell, _chromium(tmp_path, cell.url) as evaluate:
        await open_page(evaluate, cell.token)
        await evaluate(click("nav-calibration"))
        await until(evaluate, "!document.getElementById('step-calibration').hidden", 60.0)
        figures = await capture_and_calibrate(evaluate, "cameras")
        assert "poses relative to left" in figures, figures
        assert "no base frame yet" in figures, figures
        await evaluate(click("btn-calib-accept"))
        accepted = await until(evaluate, f"/^(ACCEPTED|REFUSED)/.test("
                                         f"{text('calib-accepted')}) && "
                                         f"{text('calib-accepted')}", 120.0)
        assert accepted.startswith("ACCEPTED"), accepted
        assert "relative to left" in accepted, accepted
        assert "hand-eye: left's pose in the robot base frame places every camera" in accepted

        await evaluate(click("nav-handeye"))
        told = await until(evaluate, f"{text('he-current')}.includes('relative to left') && "
                                     f"{text('he-current')}", 60.0)
        assert "[[calibration.cameras]]" in told, told
        await evaluate(click("btn-he-learning"))
        await evaluate(click("btn-he-save"))
        saved = await until(evaluate, f"/^(APPLIED|REFUSED)/.test({text('he-result')}) && "
                                      f"{text('he-result')}", 300.0)
        assert saved.startswith("APPLIED"), saved
    cameras = tomllib.loads((folder / "rig.toml").read_text())["calibration"]["cameras"]
    assert [c["name"] for c in cameras] == ["left", "right"]
    assert {c["mounting"] for c in cameras} == {"fixed"}
    truth = DEMO_CALIBRATION.hand_eye.T_base_camera
    assert truth is not None
    left = cameras[0]["T_base_camera"]
    assert np.allclose(left["translation_mm"], truth.translation_mm, atol=1e-6)
    baseline = np.linalg.norm(np.subtract(cameras[1]["T_base_camera"]["translation_mm"],
                                          left["translation_mm"]))
    assert abs(baseline - 150.0) < 5.0, baseline  # the truth pair: 149.18, 0.35, 15.68 mm
    assert abs(cameras[0]["intrinsics"]["fx"] - 1805.2) < 15.0
    handeye = tomllib.loads((folder / "handeye.toml").read_text())
    assert "hand_eye" not in handeye.get("calibration", {})  # each camera carries its pose
