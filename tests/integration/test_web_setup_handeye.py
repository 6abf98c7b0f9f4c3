"""The setup page's hand-eye from the captured sets, clicked in headless Chromium: ViSP's Franka
eye-in-hand set (8 board images, each with the flange pose the robot reported) replayed as the
camera of ``vgripd demo --setup``'s cell, every image kept as a set with its flange pose
("Capture this set"), the camera calibrated and accepted, then "Solve from the captured sets"
(``vgripd calibrate handeye`` on those sets in a child) and "Use this hand-eye", written through
the judged transaction. The solved ``T_flange_camera`` lands near ViSP's published eMc."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

from tests.integration.setup_browser import click, demo_setup, open_page, text, until
from tests.integration.test_calib_handeye_data import VISP, VISP_EMC
from tests.integration.test_web import _chromium
from vgripd.cli.demo_setup import write_cell
from vgripd.geometry.transforms import make_transform, matrix_from_rotvec, pose_error
from vgripd.serialize import toml_from_dict

pytestmark = pytest.mark.slow(minutes=3)

BOARD = "chessboard:9x6:23.6"
IMAGES = 8


def _replay_cell(folder: Path, datasets: Path) -> None:
    """The learning cell's layout with ViSP's images replayed as its one camera, each frame
    with its flange pose (mm, rotation vector), an object of four markers, the cameras step
    done."""
    write_cell(folder, 0, 0)
    src = datasets / VISP
    lines = []
    for i in range(1, IMAGES + 1):
        values = [float(v) for v in re.findall(
            r"- \[([^\]]+)\]", (src / f"franka_pose_rPe_{i}.yaml").read_text())]
        lines.append(" ".join(f"{v:.9f}" for v in [*(np.multiply(values[:3], 1000.0)),
                                                   *values[3:]]))
    poses = folder / "franka-flange.txt"
    poses.write_text("\n".join(lines) + "\n")
    (folder / "camera.toml").write_text(toml_from_dict({"camera": {
        "type": "replay", "folder": str(src), "glob": "franka_image-*.png", "loop": True,
        "flange_poses": str(poses)}}))
    # a one-camera cell is judged with its object (PnP needs 4 identified features): four
    # ArUco markers, as the config defines them (the page's object step needs a stereo pair)
    (folder / "cell.toml").write_text(toml_from_dict({"object": {"name": "tags", "features": [
        {"name": f"t{k}", "kind": "aruco", "marker_id": k, "size_mm": 20.0,
         "xyz_mm": [60.0 * (k % 2), 40.0 * (k // 2) + 5.0 * k, 0.0]} for k in range(4)]}}))
    (folder / "setup").mkdir()
    (folder / "setup" / "progress.json").write_text('{"done": {"cameras": 1.0}}')


@pytest.mark.timeout(1200)
async def test_the_hand_eye_is_solved_from_the_captured_sets_flange_poses(
        tmp_path: Path, datasets: Path) -> None:
    folder = tmp_path / "cell"
    _replay_cell(folder, datasets)
    async with demo_setup(folder) as cell, _chromium(tmp_path, cell.url) as evaluate:
        await open_page(evaluate, cell.token)
        await until(evaluate, "!document.getElementById('step-calibration').hidden", 60.0)
        await evaluate(f"document.getElementById('calib-board').value = '{BOARD}', true")
        for n in range(1, IMAGES + 1):
            await evaluate(click("btn-calib-keep"))
            await until(evaluate, f"{text('calib-sets')}.startsWith('{n} set')", 120.0)
        sets = await evaluate(text("calib-set-list"))
        assert sets.count("; flange ") == IMAGES, sets
        await evaluate(click("btn-calib-run"))
        await until(evaluate, f"{text('calib-progress')}.startsWith('calibrated in')", 600.0)
        await evaluate(click("btn-calib-accept"))
        await until(evaluate, f"{text('calib-accepted')}.startsWith('ACCEPTED')", 60.0)

        await evaluate(click("nav-handeye"))
        await until(evaluate, "!document.getElementById('step-handeye').hidden", 60.0)
        await evaluate("document.getElementById('he-mode').value = 'eye-in-hand', true")
        await evaluate(click("btn-he-solve"))
        await until(evaluate, f"/^(solved in|the solve failed|REFUSED)/.test("
                              f"{text('he-solve-progress')})", 600.0)
        solved = await evaluate(text("he-solve-result"))
        assert (await evaluate(text("he-solve-progress"))).startswith("solved in"), solved
        assert f"eye-in-hand (robot), {IMAGES} sets" in solved, solved
        assert "T_flange_camera" in solved, solved
        await evaluate(click("btn-he-use"))
        used = await until(evaluate, f"/^(APPLIED|REFUSED)/.test({text('he-use-result')}) && "
                                     f"{text('he-use-result')}", 300.0)
        assert used.startswith("APPLIED"), used
    hand_eye = tomllib.loads((folder / "handeye.toml").read_text())["calibration"]["hand_eye"]
    assert hand_eye["mounting"] == "robot"
    pose = hand_eye["T_flange_camera"]
    X = make_transform(matrix_from_rotvec(pose["rotvec_rad"]), pose["translation_mm"])
    mm, deg = pose_error(X, VISP_EMC)
    # the camera calibrated here from the same 8 images (ViSP used its factory intrinsics):
    # within a few mm and a degree of the published eMc
    assert mm < 10.0, mm
    assert deg < 1.0, deg
    assert "left" in tomllib.loads((folder / "rig.toml").read_text())["calibration"]
    assert (folder / "setup" / "handeye-poses.txt").read_text().count("# set") == IMAGES
