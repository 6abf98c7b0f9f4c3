"""Board specs and detection, on boards rendered through a known camera.

The renderer maps every image pixel back through OpenCV's distortion model onto the board plane
and samples a drawing of the board there, so the true image point of every corner is
``cv2.projectPoints`` of its board coordinates (the independent oracle).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vgripd.calib.boards import Board, detect, detect_files
from vgripd.errors import CalibrationError

SIZE = (640, 480)
K = np.array([[600.0, 0, 322.0], [0, 600.0, 238.0], [0, 0, 1]])
NO_DIST = np.zeros(5)
PPM = 1.5  # texture px per mm, about the imaged scale: bilinear sampling then acts like area sampling


def texture(board: Board) -> tuple[np.ndarray, np.ndarray]:
    """The printed board (white paper) and the 3x3 map from board mm (x, y, 1) to texture px.

    Chessboard: square (i, j), i = 0..cols, j = 0..rows, spans x in [(i-1)p, ip], y in
    [(j-1)p, jp] and is black when i + j is even, so the square diagonal from corner 0 is black.
    """
    p = board.pitch_mm
    margin = 2 * p
    if board.kind == "charuco":
        w_mm, h_mm = board.cols * p, board.rows * p
        ppm = PPM
        cb = cv2.aruco.CharucoBoard((board.cols, board.rows), p, board.marker_mm,
                                    cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary)))
        m = int(margin * ppm)
        img = cb.generateImage((int(w_mm * ppm) + 2 * m, int(h_mm * ppm) + 2 * m), marginSize=m)
        # OpenCV's ChArUco corner k sits at ((c+1)p, (r+1)p) from the board's outer corner;
        # ours at (cp, rp): shift by one square plus the margin
        off = m + p * ppm
    else:
        pts = board.object_points()
        w_mm = pts[:, 0].max() + 2 * margin
        h_mm = pts[:, 1].max() + 2 * margin
        img = np.full((int(h_mm * PPM), int(w_mm * PPM)), 255, np.uint8)
        off = margin * PPM
        ppm = PPM
        if board.kind == "chessboard":
            for i in range(board.cols + 1):
                for j in range(board.rows + 1):
                    if (i + j) % 2 == 0:
                        x0, y0 = off + (i - 1) * p * PPM, off + (j - 1) * p * PPM
                        img[int(round(y0)):int(round(y0 + p * PPM)),
                            int(round(x0)):int(round(x0 + p * PPM))] = 0
        else:
            r = p * (0.25 if board.kind == "circles" else 0.35)
            shift = 4  # draw with sub-pixel centres
            for x, y, _ in pts:
                c = (int(round((off + x * PPM - 0.5) * 2**shift)),
                     int(round((off + y * PPM - 0.5) * 2**shift)))
                cv2.circle(img, c, int(round(r * PPM * 2**shift)), 0, -1, cv2.LINE_AA, shift)
    # texture pixel u covers mm [(u - off)/ppm, (u + 1 - off)/ppm]: centre u <-> (u + 0.5 - off)/ppm
    A = np.array([[ppm, 0, off - 0.5], [0, ppm, off - 0.5], [0, 0, 1]])
    return img, A


def render(board: Board, rvec, tvec, K=K, dist=NO_DIST, size=SIZE, noise=1.0, seed=0) -> np.ndarray:
    """8-bit image of ``board`` at pose (rvec, tvec) (board -> camera, mm) through (K, dist)."""
    img, A = texture(board)
    w, h = size
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pix = np.stack([xs.ravel(), ys.ravel()], axis=1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)
    norm = cv2.undistortPoints(pix, K, np.asarray(dist, float), None, None, None, crit).reshape(-1, 2)
    R, _ = cv2.Rodrigues(np.asarray(rvec, float))
    Hn = np.column_stack([R[:, 0], R[:, 1], np.asarray(tvec, float).ravel()])
    board_h = np.linalg.solve(Hn, np.column_stack([norm, np.ones(len(norm))]).T)
    tex = A @ (board_h / board_h[2])
    mx = tex[0].reshape(h, w).astype(np.float32)
    my = tex[1].reshape(h, w).astype(np.float32)
    out = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=255)
    out = cv2.GaussianBlur(out.astype(np.float32), (0, 0), 0.8)
    out += np.random.default_rng(seed).normal(0, noise, out.shape)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def truth(board: Board, rvec, tvec, K=K, dist=NO_DIST) -> np.ndarray:
    px, _ = cv2.projectPoints(board.object_points(), np.asarray(rvec, float),
                              np.asarray(tvec, float), K, np.asarray(dist, float))
    return px.reshape(-1, 2)


def pose_facing(roll_deg: float, tilt=(0.15, -0.1), distance=420.0, board: Board | None = None):
    """A pose that puts the board centre on the optical axis, rolled by ``roll_deg``."""
    board = board or Board.parse("chessboard:9x6:30")
    centre = board.object_points().mean(axis=0)
    R = (cv2.Rodrigues(np.array([tilt[0], tilt[1], 0.0]))[0]
         @ cv2.Rodrigues(np.array([0, 0, np.radians(roll_deg)]))[0])
    t = np.array([0, 0, distance]) - R @ centre
    return cv2.Rodrigues(R)[0].ravel(), t


# ---------------------------------------------------------------- specs


@pytest.mark.parametrize(("spec", "expected"), [
    ("chessboard:13x12:30", Board("chessboard", 13, 12, 30.0)),
    ("circles:4x11:20", Board("circles", 4, 11, 20.0)),
    ("ACircles:4X11:20.5", Board("acircles", 4, 11, 20.5)),
    ("charuco:5x7:30:22", Board("charuco", 5, 7, 30.0, 22.0, "DICT_4X4_50")),
    ("charuco:5x7:30:22:dict_5x5_100", Board("charuco", 5, 7, 30.0, 22.0, "DICT_5X5_100")),
])
def test_parse(spec, expected):
    board = Board.parse(spec)
    assert board == expected
    assert Board.parse(board.spec) == board


@pytest.mark.parametrize(("spec", "names"), [
    ("checkers:9x6:30", "unknown kind 'checkers'"),
    ("chessboard:9-6:30", "size '9-6'"),
    ("chessboard:9x2:30", "at least 3x3"),
    ("chessboard:9x6:-3", "pitch '-3'"),
    ("chessboard:9x6:nan", "pitch 'nan'"),
    ("chessboard:9x6", "expected chessboard:COLSxROWS:PITCH_MM"),
    ("charuco:5x7:30", "expected charuco:COLSxROWS:SQUARE_MM:MARKER_MM"),
    ("charuco:5x7:30:31", "marker size 31 mm must be smaller"),
    ("charuco:5x7:30:22:DICT_9X9_1", "unknown ArUco dictionary 'DICT_9X9_1'"),
    ("charuco:12x12:30:22:DICT_4X4_50", "needs 72 markers, DICT_4X4_50 has 50"),
])
def test_parse_errors_name_the_bad_part(spec, names):
    with pytest.raises(CalibrationError, match="board .*" + names.replace("(", r"\(")):
        Board.parse(spec)


def test_object_points():
    pts = Board.parse("chessboard:4x3:25").object_points()
    assert pts.shape == (12, 3)
    np.testing.assert_array_equal(pts[5], [25, 25, 0])  # row 1, column 1
    acirc = Board.parse("acircles:4x11:20").object_points()
    # OpenCV's calibration sample: ((2j + i % 2) s, i s, 0) for row i, column j
    np.testing.assert_array_equal(acirc[4 * 3 + 2], [(2 * 2 + 1) * 20, 3 * 20, 0])
    board = Board.parse("charuco:5x7:30:22")
    cb = cv2.aruco.CharucoBoard((5, 7), 30, 22, cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50))
    np.testing.assert_allclose(board.object_points(), cb.getChessboardCorners() - [30, 30, 0])


# ---------------------------------------------------------------- detection


@pytest.mark.parametrize("spec", ["chessboard:9x6:30", "circles:5x4:30", "acircles:4x7:18",
                                  "charuco:7x5:30:22"])
def test_detection_matches_projection(spec):
    board = Board.parse(spec)
    rvec, tvec = pose_facing(8.0, board=board)
    gray = render(board, rvec, tvec)
    det = detect(board, gray, "synthetic.png")
    assert det.size == SIZE
    assert det.image == "synthetic.png"
    expected = truth(board, rvec, tvec)[det.ids]
    if board.kind == "charuco":
        assert len(det.ids) == board.n_points
    else:
        np.testing.assert_array_equal(det.ids, np.arange(board.n_points))
    err = np.linalg.norm(det.px - expected, axis=1)
    assert err.max() < 0.15, f"max corner error {err.max():.3f} px"


@pytest.mark.parametrize("roll_deg", [0, 60, 100, 150, 180, 230, 290, 340])
def test_colour_asymmetric_chessboard_order_is_the_physical_one(roll_deg):
    """9x6 inner corners = 10x7 squares: a 180 degree turn swaps the colours, so corner 0 is the
    same physical corner (diagonal square black) at any roll, and the board z axis points away."""
    board = Board.parse("chessboard:9x6:30")
    rvec, tvec = pose_facing(roll_deg, board=board)
    det = detect(board, render(board, rvec, tvec), "rolled")
    err = np.linalg.norm(det.px - truth(board, rvec, tvec), axis=1)
    assert err.max() < 0.15


@pytest.mark.parametrize("roll_deg", [-30, 20, 160, 200])
def test_colour_symmetric_chessboard_corner_0_nearest_top_left(roll_deg):
    """8x6 inner corners = 9x7 squares look the same turned by 180 degrees: corner 0 is the
    candidate nearest the image's top-left pixel (documented ambiguity)."""
    board = Board.parse("chessboard:8x6:30")
    rvec, tvec = pose_facing(roll_deg, board=board)
    det = detect(board, render(board, rvec, tvec), "symmetric")
    true_px = truth(board, rvec, tvec)
    straight = np.linalg.norm(det.px - true_px, axis=1).max()
    turned = np.linalg.norm(det.px - true_px[::-1], axis=1).max()
    upright = abs(roll_deg) < 90 or roll_deg > 270
    assert (straight if upright else turned) < 0.15
    assert np.hypot(*det.px[0]) < np.hypot(*det.px[-1])


def test_subpix_window_is_used():
    board = Board.parse("chessboard:9x6:30")
    rvec, tvec = pose_facing(10.0, board=board)
    gray = render(board, rvec, tvec)
    a = detect(board, gray, "a", subpix_window=2).px
    b = detect(board, gray, "b", subpix_window=9).px
    assert 1e-4 < np.abs(a - b).max() < 0.5
    with pytest.raises(CalibrationError, match="subpix window 0"):
        detect(board, gray, "c", subpix_window=0)


def test_not_found_reasons(tmp_path):
    board = Board.parse("chessboard:9x6:30")
    rvec, tvec = pose_facing(5.0, board=board)
    good = render(board, rvec, tvec)
    with pytest.raises(CalibrationError, match=r"^blank.png: board not found: no 9x6 corner grid found"):
        detect(board, np.full((480, 640), 200, np.uint8), "blank.png")
    covered = good.copy()
    covered[:, 330:] = 255  # hide the right half of the board
    with pytest.raises(CalibrationError, match=r"^covered: board not found: (only \d+ of 54 corners found|no 9x6)"):
        detect(board, covered, "covered")
    with pytest.raises(CalibrationError, match="floats: board not found: image unreadable"):
        detect(board, good.astype(np.float32), "floats")
    with pytest.raises(CalibrationError, match="board not found: no DICT_4X4_50 markers found"):
        detect(Board.parse("charuco:7x5:30:22"), good, "charuco")
    with pytest.raises(CalibrationError, match="no 5x4 circle grid found"):
        detect(Board.parse("circles:5x4:30"), good, "circles")

    paths = []
    for i, img in enumerate([good, render(board, *pose_facing(-20.0, board=board), seed=1), good]):
        paths.append(tmp_path / f"img{i}.png")
        cv2.imwrite(str(paths[-1]), img)
    cv2.imwrite(str(tmp_path / "small.png"), cv2.resize(good, (320, 240)))
    cv2.imwrite(str(tmp_path / "blank.png"), np.full((480, 640), 128, np.uint8))
    (tmp_path / "junk.png").write_bytes(b"not an image")
    names = [*paths, tmp_path / "small.png", tmp_path / "blank.png", tmp_path / "junk.png",
             tmp_path / "missing.png"]
    found, failed = detect_files(board, names)
    assert [d.image for d in found] == [str(p) for p in paths]
    reasons = dict(failed)
    assert reasons[str(tmp_path / "small.png")] == "image size 320x240 differs from the 640x480 of the other images"
    assert reasons[str(tmp_path / "blank.png")] == "board not found: no 9x6 corner grid found"
    assert reasons[str(tmp_path / "junk.png")].startswith("image unreadable")
    assert reasons[str(tmp_path / "missing.png")].startswith("image unreadable")
