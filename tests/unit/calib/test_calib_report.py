"""The calibration PNG report: written where asked, the expected size, and the drawing shows
what it claims (arrows where the residuals are, red bars for outlier images).

The PNG is read back with OpenCV's decoder (independent of our encoder call) and pixels are
checked at positions computed from the layout constants.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vgripd.calib import report
from vgripd.calib.report import ImageResiduals, auto_scale, write_report
from vgripd.errors import CalibrationError

SIZE = (640, 480)


def grid_images(n: int, rms: list[float]) -> list[ImageResiduals]:
    """``n`` images of a 9x6 grid with residuals of exactly the given RMS (all along +x)."""
    xs, ys = np.meshgrid(np.linspace(60, 580, 9), np.linspace(60, 420, 6))
    px = np.column_stack([xs.ravel(), ys.ravel()])
    return [ImageResiduals(f"left{i + 1:02d}.jpg", px, np.tile([rms[i], 0.0], (len(px), 1)))
            for i in range(n)]


def bar_row(canvas: np.ndarray, i: int) -> np.ndarray:
    """The pixels of bar row ``i`` (middle line), right of the labels."""
    s = min(report.PANEL_PX / SIZE[0], report.PANEL_PX / SIZE[1])
    rx = report.MARGIN + round(SIZE[0] * s) + 2 * report.MARGIN
    y = report.TITLE_PX + report.MARGIN + report.ROW_PX * (i + 1) + report.ROW_PX // 2
    return canvas[y, rx + 14 + 150:]


def has_colour(pixels: np.ndarray, bgr: tuple[int, int, int]) -> bool:
    return bool((np.abs(pixels.astype(int) - bgr).sum(axis=-1) == 0).any())


def test_png_written_with_expected_size(tmp_path):
    out = write_report(tmp_path / "r.png", "calibrate intrinsics", SIZE,
                       grid_images(3, [0.2, 0.25, 0.3]), ["fx 600 +- 1"])
    assert out == tmp_path / "r.png"
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    img = cv2.imread(str(out))
    # 640x480 scaled by 1.25 fills the 800 px box: 800 x 600 frame plus the bar panel
    width = report.MARGIN + 800 + 2 * report.MARGIN + report.BAR_PANEL_PX + report.MARGIN
    height = report.TITLE_PX + 600 + 2 * report.MARGIN
    assert img.shape == (height, width, 3)
    assert not list(tmp_path.glob("*.tmp"))


def test_many_images_make_the_report_taller(tmp_path):
    img = cv2.imread(str(write_report(tmp_path / "r.png", "t", SIZE,
                                      grid_images(60, [0.2] * 60))))
    assert img.shape[0] > report.TITLE_PX + 60 * report.ROW_PX


def test_outlier_bar_is_red_and_others_are_not(tmp_path):
    rms = [0.2, 0.22, 0.9, 0.21, 0.19]
    img = cv2.imread(str(write_report(tmp_path / "r.png", "t", SIZE, grid_images(5, rms))))
    for i in range(5):
        row = bar_row(img, i)
        assert has_colour(row, report.BAR_OUTLIER) == (i == 2), i
        assert has_colour(row, report.BAR_OK) == (i != 2), i


def test_arrow_drawn_along_the_residual(tmp_path):
    """One point at the image centre, residual (4, 0) px, scale 10: a 40 image-px arrow to the
    right (50 canvas px at 1.25); pixels along it change, the same span to the left does not."""
    centre = np.array([[319.5, 239.5]])
    im = ImageResiduals("a.png", centre, np.array([[4.0, 0.0]]))
    img = cv2.imread(str(write_report(tmp_path / "r.png", "t", SIZE, [im], scale=10)))
    x0 = report.MARGIN + 400  # frame origin + centre of the 800 px wide frame
    y = report.TITLE_PX + report.MARGIN + 300
    right = img[y, x0 + 5:x0 + 45]
    left = img[y, x0 - 45:x0 - 5]
    background = np.array(report.FRAME_BG)
    assert (np.abs(right.astype(int) - background).sum(axis=1) > 60).all()
    assert (left == background).all()


def test_auto_scale_keeps_the_longest_arrow_near_five_percent():
    residuals = [np.array([[0.3, 0.4], [0.1, 0.0]])]  # longest 0.5 px
    scale = auto_scale(640, residuals)  # 5 % of 640 = 32 px -> 64x -> 1-2-5 step 50
    assert scale == 50
    assert 0.5 * scale <= 0.05 * 640 < 0.5 * scale * 2.5
    assert auto_scale(640, [np.zeros((3, 2))]) == 1.0


def test_bad_scale_is_refused(tmp_path):
    with pytest.raises(CalibrationError, match="scale"):
        write_report(tmp_path / "r.png", "t", SIZE, grid_images(1, [0.1]), scale=0)


def test_unwritable_path_names_it(tmp_path):
    bad = tmp_path / "missing-dir" / "r.png"
    with pytest.raises(CalibrationError, match="missing-dir"):
        write_report(bad, "t", SIZE, grid_images(1, [0.1]))


def test_bad_residuals_name_the_image(tmp_path):
    im = ImageResiduals("Image7.tif", np.zeros((3, 2)), np.array([[0, 0], [np.nan, 0], [0, 0]]))
    with pytest.raises(CalibrationError, match=r"Image7\.tif: point 1"):
        write_report(tmp_path / "r.png", "t", SIZE, [im])
    im = ImageResiduals("Image8.tif", np.zeros((3, 2)), np.zeros((2, 2)))
    with pytest.raises(CalibrationError, match=r"Image8\.tif"):
        write_report(tmp_path / "r.png", "t", SIZE, [im])
    with pytest.raises(CalibrationError, match="image size"):
        write_report(tmp_path / "r.png", "t", (0, 480), [])
