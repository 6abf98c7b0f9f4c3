"""Calibration coverage (``vgripd.calib.coverage``): image regions and the apparent tilt.

The oracle for the tilt is the board's true 3-D pose: the side whose points are nearer the
camera (smaller z) must be the side named, for any roll of the board in its plane; the pixels
come from ``cv2.projectPoints``."""

from __future__ import annotations

import cv2
import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from vgripd.calib.boards import Board, Detection
from vgripd.calib.coverage import TILTS, Coverage, moved_px, tilt_of

BOARD = Board.parse("chessboard:8x5:25")
K = np.array([[900.0, 0, 640.0], [0, 900.0, 512.0], [0, 0, 1]])
SIZE = (1280, 1024)


def seen(R: np.ndarray, centre_cam: np.ndarray) -> tuple[Detection, np.ndarray]:
    """The board with rotation R (board -> camera) and its centre at ``centre_cam`` (mm):
    the detection and the points in the camera frame."""
    obj = BOARD.object_points()
    t = centre_cam - R @ obj.mean(axis=0)
    cam = obj @ R.T + t
    px = cv2.projectPoints(obj, cv2.Rodrigues(R)[0], t, K, np.zeros(5))[0].reshape(-1, 2)
    return Detection("x", SIZE, np.arange(len(obj)), px), cam


def rotation(axis: str, angle: float, roll: float) -> np.ndarray:
    """Board turned by ``angle`` about the camera's x or y axis after a roll in its plane;
    the board's z points away from the camera (its printed face seen)."""
    turn = cv2.Rodrigues(np.array([angle, 0, 0] if axis == "x" else [0, angle, 0]))[0]
    return turn @ cv2.Rodrigues(np.array([0.0, 0.0, roll]))[0]


def test_a_board_facing_the_camera_is_flat() -> None:
    for roll in (0.0, 0.7, 2.0, -2.9):
        det, _ = seen(rotation("y", 0.0, roll), np.array([0.0, 0.0, 600.0]))
        assert tilt_of(BOARD, det) == "flat"


@given(axis=st.sampled_from("xy"), angle_deg=st.floats(25, 50),
       sign=st.sampled_from([-1.0, 1.0]), roll=st.floats(-np.pi, np.pi))
def test_the_nearer_side_is_named_whatever_the_roll(axis, angle_deg, sign, roll) -> None:
    det, cam = seen(rotation(axis, sign * np.radians(angle_deg), roll),
                    np.array([0.0, 0.0, 600.0]))
    tilt = tilt_of(BOARD, det)
    image_axis = 0 if axis == "y" else 1  # a turn about y moves the left/right sides
    lo, hi = np.argmin(det.px[:, image_axis]), np.argmax(det.px[:, image_axis])
    nearer_first = cam[lo, 2] < cam[hi, 2]
    expected = (("left" if nearer_first else "right") if image_axis == 0
                else ("top" if nearer_first else "bottom")) + " nearer"
    assert tilt == expected


def test_coverage_counts_regions_and_tilts_and_says_what_is_missing() -> None:
    cov = Coverage(SIZE, grid=4)
    centre, _ = seen(rotation("y", 0.0, 0.0), np.array([0.0, 0.0, 900.0]))
    assert cov.news(BOARD, centre) == [f"{len(cov.cells_of(centre))} new image region(s)",
                                       "tilt flat"]
    cov.add(BOARD, centre)
    assert cov.news(BOARD, centre) == []
    assert cov.cells == {(1, 1), (2, 1), (1, 2), (2, 2)}
    missing = cov.missing()
    assert "top-left, top-right, bottom-left, bottom-right corner(s)" in missing[0]
    assert missing[1] == "8 more image region(s) (of 4x4)"
    assert missing[2] == "the board tilted: " + ", ".join(TILTS[1:])
    corner, _ = seen(rotation("y", 0.0, 0.0), np.array([-400.0, -330.0, 900.0]))
    assert (0, 0) in cov.cells_of(corner)
    assert cov.news(BOARD, corner)[0].endswith("new image region(s)")


def test_moved_px_compares_the_shared_points() -> None:
    a, _ = seen(rotation("y", 0.0, 0.0), np.array([0.0, 0.0, 600.0]))
    b = Detection("y", SIZE, a.ids[:10], a.px[:10] + [3.0, 4.0])
    assert moved_px(a, b) == 5.0
    assert moved_px(a, Detection("z", SIZE, np.array([], np.int64), np.zeros((0, 2)))) == \
        float("inf")
