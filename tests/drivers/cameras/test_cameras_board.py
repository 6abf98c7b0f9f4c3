"""The learning cell's board camera (``drivers/cameras/board.py``): what it renders is the
board at the pose it reports, seen through the truth cameras (the oracle: OpenCV's
``projectPoints`` of the board's corners at the reported pose, through the truth camera's
``K`` and distortion); the operator holds still, moves, and keeps the board whole in view; and
``vgripd capture`` + ``vgripd calibrate stereo`` on it land on the truth within the reported
uncertainty."""

from __future__ import annotations

import asyncio
import contextlib
import io
import tomllib
from pathlib import Path

import cv2
import numpy as np
import pytest

from drivers.cameras.board import BoardCamera, BoardOptions
from vgripd.__main__ import main
from vgripd.calib.boards import Board, detect
from vgripd.config import Config
from vgripd.errors import CameraError

SPEC = "chessboard:9x6:25"
# the demo cell's cameras at half size (640x512), a converging pair 150 mm apart
TRUTH = """\
[calibration.left]
fx = 902.6
fy = 902.3
cx = 320.4
cy = 254.2
dist = [-0.08, 0.11, 0.0004, -0.0003, 0.0]
width = 640
height = 512

[calibration.right]
fx = 899.4
fy = 899.8
cx = 318.1
cy = 257.3
dist = [-0.075, 0.095, -0.0002, 0.0005, 0.0]
width = 640
height = 512

[calibration.stereo.T_right_left]
translation_mm = [-149.18, 0.35, 15.68]
rotvec_rad = [0.0021, 0.20944, -0.0032]
"""


def truth_file(tmp_path: Path) -> Path:
    path = tmp_path / "truth.toml"
    path.write_text(TRUTH)
    return path


def grabs(camera: BoardCamera, n: int) -> list:
    async def run() -> list:
        await camera.open()
        try:
            return [await camera.grab(30.0) for _ in range(n)]
        finally:
            await camera.close()
    return asyncio.run(run())


def test_the_rendered_corners_are_the_board_at_the_reported_pose(tmp_path: Path) -> None:
    options = BoardOptions(board=SPEC, truth=str(truth_file(tmp_path)), hold_frames=2,
                           move_frames=1)
    pairs = grabs(BoardCamera(options, Config()), 6)
    truth = tomllib.loads(TRUTH)["calibration"]
    board = Board.parse(SPEC)
    for pair in pairs:
        T = pair.truth["T_cam_board"]
        for image, side, T_cam in ((pair.left, "left", np.eye(4)),
                                   (pair.right, "right", pair.truth["T_right_left"])):
            cam = truth[side]
            K = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]])
            Tc = T_cam @ T
            expected = cv2.projectPoints(board.object_points(), cv2.Rodrigues(Tc[:3, :3])[0],
                                         Tc[:3, 3], K, np.array(cam["dist"]))[0].reshape(-1, 2)
            found = detect(board, image, side)
            error = np.linalg.norm(found.px - expected, axis=1)  # noise 1, blur 0.7
            assert np.max(error) < 0.25
            assert np.mean(error) < 0.08
    # held, held, moving, held, held, moving: the same place twice, then half way on
    assert [p.truth["still"] for p in pairs] == [True, True, False, True, True, False]
    assert [p.truth["place"] for p in pairs] == [0, 0, 0, 1, 1, 1]
    assert np.array_equal(pairs[0].truth["T_cam_board"], pairs[1].truth["T_cam_board"])
    assert not np.array_equal(pairs[1].truth["T_cam_board"], pairs[3].truth["T_cam_board"])


def test_only_chessboards_and_a_readable_truth_are_taken(tmp_path: Path) -> None:
    with pytest.raises(CameraError, match=r"camera.board .*chessboards only"):
        BoardCamera(BoardOptions(board="circles:4x11:20"), Config())
    camera = BoardCamera(BoardOptions(board=SPEC, truth=str(tmp_path / "none.toml")),
                         Config())
    with pytest.raises(CameraError, match=r"camera.truth .*none.toml"):
        grabs(camera, 1)
    # cameras looking apart (the right one turned by 90 degrees): no place both see whole
    apart = tmp_path / "apart.toml"
    apart.write_text(TRUTH.replace("rotvec_rad = [0.0021, 0.20944, -0.0032]",
                                   "rotvec_rad = [0.0, 1.5708, 0.0]"))
    camera = BoardCamera(BoardOptions(board=SPEC, truth=str(apart)), Config())
    with pytest.raises(CameraError, match="no place where every camera sees the whole"):
        grabs(camera, 1)


def run(*args: str) -> tuple[int, str]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        rc = main(list(args))
    return rc, out.getvalue()


def test_capture_and_calibrate_on_the_learning_cell_find_the_truth(tmp_path: Path) -> None:
    truth = truth_file(tmp_path)
    cell = tmp_path / "learn.toml"
    cell.write_text(f'[camera]\ntype = "board"\nboard = "{SPEC}"\ntruth = "{truth}"\n')
    calib = tmp_path / "calib"
    rc, text = run("capture", "-c", str(cell), "--board", SPEC, "-o", str(calib),
                   "--count", "10")
    assert rc == 0, text
    assert len(list(calib.glob("left_*.png"))) == 10
    rig = tmp_path / "rig.toml"
    rc, text = run("calibrate", "stereo", "--left", f"{calib}/left_*.png", "--right",
                   f"{calib}/right_*.png", "--board", SPEC, "-o", str(rig))
    assert rc == 0, text
    data = tomllib.loads(rig.read_text())
    expected = tomllib.loads(TRUTH)["calibration"]
    std = data["about"]["std"]
    for side in ("left", "right"):
        for key in ("fx", "fy", "cx", "cy"):
            got, want, sigma = data["calibration"][side][key], expected[side][key], \
                std[side][key]
            assert abs(got - want) < 4 * sigma + 0.2, (side, key, got, want, sigma)
    t = np.array(data["calibration"]["stereo"]["T_right_left"]["translation_mm"])
    want_t = np.array(expected["stereo"]["T_right_left"]["translation_mm"])
    assert np.all(np.abs(t - want_t) < 4 * np.array(std["translation_mm"]) + 0.05)


def test_the_robot_twins_board_and_then_the_plate_are_drawn_where_the_cell_has_them(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """With ``robot_state``: no file, the operator's board; the board on the flange, drawn at
    the arm's pose through the truth cameras placed by the truth's hand-eye (the oracle:
    OpenCV's projection of the corners at the flange pose, the mounting and the demo cell's
    T_base_camera composed here); board taken off, the config's object at ``plate_pose``."""
    from vgripd.geometry.transforms import make_transform, matrix_from_rotvec
    from vgripd.sim.robot_twin import write_state
    from vgripd.vision.scene import matrix_from_pose

    monkeypatch.chdir(tmp_path)
    spec = "chessboard:9x6:30"
    options = BoardOptions(board=spec, robot_state="robot.json", hold_frames=2,
                           board_offset_mm=(2.0, -3.0, 12.0), board_turn_deg=1.5,
                           plate_pose={"translation_mm": [605.0, 95.0, 10.0],
                                       "rotvec_rad": [0.0, 0.0, 0.1]})
    demo = Config()
    assert demo.calibration is not None
    T_base_camera = matrix_from_pose(demo.calibration.hand_eye.T_base_camera)
    board = Board.parse(spec)
    centre = board.object_points().mean(axis=0)
    # the flange 650 mm in front of the camera, the board's face to it, the flange tilted
    T_base_flange = (T_base_camera @ make_transform(matrix_from_rotvec([0.2, -0.1, 0.3]),
                                                    np.array([10.0, -20.0, 650.0]))
                     @ make_transform(matrix_from_rotvec([np.pi, 0.0, 0.0]), np.zeros(3)))
    mount = (make_transform(matrix_from_rotvec([0.0, 0.0, np.radians(1.5)]),
                            np.array([2.0, -3.0, 12.0]))
             @ make_transform(matrix_from_rotvec([np.pi, 0.0, 0.0]), np.zeros(3))
             @ make_transform(np.eye(3), -centre))
    camera = BoardCamera(options, Config())

    async def scenes() -> list:
        await camera.open()
        try:
            out = [await camera.grab(30.0)]  # no state file yet: the operator
            write_state(tmp_path / "robot.json", T_base_flange, True)
            out.append(await camera.grab(30.0))
            write_state(tmp_path / "robot.json", T_base_flange, False)
            out.append(await camera.grab(30.0))
            (tmp_path / "robot.json").write_text("{not json")
            with pytest.raises(CameraError, match=r"camera.robot_state robot.json"):
                await camera.grab(30.0)
            return out
        finally:
            await camera.close()

    operator, held, plate = asyncio.run(scenes())
    assert operator.truth["place"] == 0
    Tc = np.linalg.inv(T_base_camera) @ T_base_flange @ mount
    left = demo.calibration.left
    K = np.array([[left.fx, 0, left.cx], [0, left.fy, left.cy], [0, 0, 1]])
    expected = cv2.projectPoints(board.object_points(), cv2.Rodrigues(Tc[:3, :3])[0],
                                 Tc[:3, 3], K, np.array(left.dist))[0].reshape(-1, 2)
    found = detect(board, held.left, "left")
    assert np.max(np.linalg.norm(found.px - expected, axis=1)) < 0.25
    assert np.allclose(held.truth["T_base_flange"], T_base_flange)
    assert "T_cam_board" not in plate.truth
    assert np.allclose(plate.truth["T_base_obj"][:3, 3], [605.0, 95.0, 10.0])
    assert list(plate.truth["feature_names"]) == [f.name for f in demo.object.features]
