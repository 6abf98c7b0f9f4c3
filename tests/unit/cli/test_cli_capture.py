"""``vgripd capture`` over the replay driver on rendered board images.

The frames are rendered by the board tests' renderer (``tests/unit/calib/test_calib_boards.py``,
independent of the capture code): a stereo pair of 640x480 cameras 120 mm apart, the board at
places across the view and tilted. A frame shown twice in a row is a board held still; shown
once, a board on the move.
"""

from __future__ import annotations

import contextlib
import io
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.unit.calib.test_calib_boards import SIZE, K, render
from vgripd.__main__ import main
from vgripd.calib.boards import Board

SPEC = "chessboard:7x5:20"
BOARD = Board.parse(SPEC)
BASELINE_MM = 120.0
# board centre in the left camera (mm) and its turn (rad about x, y)
PLACES = [((-15, -10, 480), (0.0, 0.0)), ((70, 45, 520), (0.35, 0.1)),
          ((-110, 55, 560), (-0.1, 0.45)), ((90, -70, 520), (0.05, -0.4)),
          ((-80, -75, 600), (-0.45, 0.0)), ((20, 80, 500), (0.2, -0.2))]


def pose(centre, turn, shift_x: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    R = cv2.Rodrigues(np.array([turn[0], turn[1], 0.0]))[0]
    t = np.asarray(centre, float) - R @ BOARD.object_points().mean(axis=0)
    t[0] -= shift_x
    return cv2.Rodrigues(R)[0].ravel(), t


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Each place rendered once: left_NN.png, right_NN.png, and a board-less blank.png."""
    folder = tmp_path_factory.mktemp("rendered")
    for i, (centre, turn) in enumerate(PLACES):
        cv2.imwrite(str(folder / f"left_{i:02d}.png"),
                    render(BOARD, *pose(centre, turn), K=K, size=SIZE, seed=i))
        cv2.imwrite(str(folder / f"right_{i:02d}.png"),
                    render(BOARD, *pose(centre, turn, BASELINE_MM), K=K, size=SIZE,
                           seed=100 + i))
    cv2.imwrite(str(folder / "blank.png"), np.full((SIZE[1], SIZE[0]), 200, np.uint8))
    return folder


def write_frames(rendered: Path, folder: Path, places: int, repeat: int = 2,
                 right_blank: bool = False) -> None:
    """A replay folder showing the first ``places`` places, each ``repeat`` times."""
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(places):
        right = rendered / ("blank.png" if right_blank else f"right_{i:02d}.png")
        for k in range(repeat):
            shutil.copy(rendered / f"left_{i:02d}.png", folder / f"left_{i:02d}_{k}.png")
            shutil.copy(right, folder / f"right_{i:02d}_{k}.png")


def config(tmp_path: Path, frames: Path) -> Path:
    path = tmp_path / "cell.toml"
    path.write_text(f'[camera]\ntype = "replay"\nfolder = "{frames}"\n'
                    'left_glob = "left_*.png"\nright_glob = "right_*.png"\n')
    return path


def capture(*args: str) -> tuple[int, str]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = main(["capture", *args])
    return rc, out.getvalue()


def test_still_boards_are_kept_as_synchronized_sets_with_their_coverage(tmp_path: Path,
        rendered: Path) -> None:
    frames = tmp_path / "frames"
    write_frames(rendered, frames, len(PLACES))
    out = tmp_path / "calib"
    rc, text = capture("-c", str(config(tmp_path, frames)), "--board", SPEC, "-o", str(out),
                       "--count", "4")
    assert rc == 0, text
    assert sorted(p.name for p in out.glob("*.png")) == [
        f"{side}_{i:03d}.png" for side in ("left", "right") for i in range(4)]
    # each kept image is the frame shown: the left one of place i
    for i in range(4):
        shown = cv2.imread(str(frames / f"left_{i:02d}_1.png"), cv2.IMREAD_GRAYSCALE)
        kept = cv2.imread(str(out / f"left_{i:03d}.png"), cv2.IMREAD_GRAYSCALE)
        assert np.array_equal(shown, kept)
    manifest = json.loads((out / "capture.json").read_text())
    assert manifest["board"] == SPEC
    assert manifest["cameras"] == ["left", "right"]
    assert [s["set"] for s in manifest["sets"]] == [0, 1, 2, 3]
    assert all(s["points"] == {"left": 35, "right": 35} for s in manifest["sets"])
    assert "set 0 kept" in text
    assert "waiting for it to be still" in text
    assert f"vgripd calibrate stereo --left '{out}/left_*.png'" in text
    assert "still missing" in text  # four places do not cover a 4x4 grid


def test_a_moving_board_is_never_kept(tmp_path: Path,
        rendered: Path) -> None:
    frames = tmp_path / "frames"
    write_frames(rendered, frames, 4, repeat=1)
    rc, text = capture("-c", str(config(tmp_path, frames)), "--board", SPEC, "-o",
                       str(tmp_path / "calib"), "--count", "2")
    assert rc == 1
    assert "only 0 of 2 sets kept (the camera: replay: no more images" in text
    assert not list((tmp_path / "calib").glob("*.png"))
    # without waiting for stillness (files, not a live camera) each place is a set
    rc, text = capture("-c", str(config(tmp_path, frames)), "--board", SPEC, "-o",
                       str(tmp_path / "calib"), "--count", "4", "--still-px", "0")
    assert rc == 0, text


def test_a_set_the_other_camera_misses_is_not_kept(tmp_path: Path,
        rendered: Path) -> None:
    frames = tmp_path / "frames"
    write_frames(rendered, frames, 2, right_blank=True)
    rc, text = capture("-c", str(config(tmp_path, frames)), "--board", SPEC, "-o",
                       str(tmp_path / "calib"), "--count", "1")
    assert rc == 1
    assert "board seen by 1 of 2 camera(s) (not in right)" in text
    rc, text = capture("-c", str(config(tmp_path, frames)), "--board", SPEC, "-o",
                       str(tmp_path / "calib2"), "--count", "2", "--min-cameras", "1")
    assert rc == 0, text
    manifest = json.loads((tmp_path / "calib2" / "capture.json").read_text())
    assert manifest["sets"][0]["points"] == {"left": 35, "right": 0}


def test_a_second_capture_goes_on_in_the_same_folder(tmp_path: Path,
        rendered: Path) -> None:
    frames = tmp_path / "frames"
    write_frames(rendered, frames, 4)
    cfg = str(config(tmp_path, frames))
    out = tmp_path / "calib"
    assert capture("-c", cfg, "--board", SPEC, "-o", str(out), "--count", "2")[0] == 0
    # the replay starts again at place 0: places 0 and 1 are kept already (nothing new)
    rc, text = capture("-c", cfg, "--board", SPEC, "-o", str(out), "--count", "2")
    assert rc == 0, text
    assert "2 set(s) in" in text
    assert "nothing new" in text
    manifest = json.loads((out / "capture.json").read_text())
    assert [s["set"] for s in manifest["sets"]] == [0, 1, 2, 3]
    third = cv2.imread(str(frames / "left_02_0.png"), cv2.IMREAD_GRAYSCALE)
    assert np.array_equal(cv2.imread(str(out / "left_002.png"), cv2.IMREAD_GRAYSCALE), third)
    # another board in the same folder is refused, naming the folder
    rc, text = capture("-c", cfg, "--board", "chessboard:9x6:20", "-o", str(out))
    assert rc == 78


def test_flange_file_lines_stay_one_per_set_or_the_file_is_left_out(tmp_path: Path) -> None:
    """flange.txt is read by line (line k = set k): with every set's pose it has one line per
    set; once a set comes without one (a robot link lost mid-capture) the file is left out and
    each set's pose stays in capture.json only."""
    from vgripd.calib.capturesets import Capture
    from vgripd.calib.coverage import Coverage

    image = np.zeros((40, 60), np.uint8)
    state = Capture(Board.parse("chessboard:9x6:30"), tmp_path, 0, 1.0, 20.0, ["left"],
                    [Coverage((60, 40))])
    pose = np.eye(4)
    for k in range(2):
        pose[:3, 3] = (100.0 * k, 0.0, 500.0)
        state.keep((image,), [None], "test", 0, pose.copy())
        state.write_manifest()
    lines = [line for line in (tmp_path / "flange.txt").read_text().splitlines()
             if not line.startswith("#")]
    assert [float(line.split()[0]) for line in lines] == [0.0, 100.0]
    said = state.keep((image,), [None], "test", 0, None)
    state.write_manifest()
    assert "no flange.txt" in said
    assert not (tmp_path / "flange.txt").exists()
    sets = json.loads((tmp_path / "capture.json").read_text())["sets"]
    assert ["flange" in s for s in sets] == [True, True, False]
