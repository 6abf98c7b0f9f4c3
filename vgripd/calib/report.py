"""PNG report of a calibration: where the residuals are and which images are bad.

An operator judges a calibration faster from a picture than from numbers. The report has

- a title band (the command's ``title`` and the residual magnification);
- left: the image frame scaled to fit ~800 px, every observed point as a dot and its residual
  (observed - projected) as an arrow magnified ``scale`` times, one colour per image.
  Systematic patterns (all arrows pointing outwards = wrong distortion model, one image's
  arrows all parallel = a bad board pose) show at a glance;
- right: one horizontal bar per image with its RMS reprojection error (px), a colour swatch
  matching its arrows, bars above ``OUTLIER_FACTOR`` x the median drawn red, and a vertical
  line at the overall RMS; below the bars the free text ``lines`` (parameters, warnings).

Drawn with OpenCV only (no matplotlib on a robot-cell PC). Pixel coordinates are OpenCV's
(centre of the top-left pixel = (0, 0)).
"""

from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from vgripd.errors import CalibrationError

OUTLIER_FACTOR = 2.0  # an image whose RMS exceeds this times the median RMS is drawn red
ARROW_FRACTION = 0.05  # automatic scale: the longest arrow is about this share of the width
PANEL_PX = 800  # the image frame is scaled to fit a PANEL_PX x PANEL_PX box
BAR_PANEL_PX = 460  # width of the right panel
MARGIN = 16
TITLE_PX = 44
ROW_PX = 18  # height of one image's bar row
LINE_PX = 18  # height of one text line

FONT = cv2.FONT_HERSHEY_SIMPLEX
WHITE = (255, 255, 255)
BLACK = (0, 0, 0)
GREY = (150, 150, 150)
FRAME_BG = (238, 238, 238)
BAR_OK = (170, 120, 60)  # BGR: steel blue
BAR_OUTLIER = (40, 40, 220)  # BGR: red
RMS_LINE = (0, 140, 0)


@dataclass
class ImageResiduals:
    """The reprojection residuals of one image.

    Parameters
    ----------
    name : image file name (shown in the bar label).
    px : (N, 2) observed image points, px, OpenCV convention.
    residual_px : (N, 2) observed - projected, px.
    """

    name: str
    px: NDArray[np.float64]
    residual_px: NDArray[np.float64]

    @property
    def rms_px(self) -> float:
        """Root mean square of the residual lengths (px); 0 for no points."""
        r = np.asarray(self.residual_px, dtype=float).reshape(-1, 2)
        return float(np.sqrt(np.mean(np.sum(r**2, axis=1)))) if len(r) else 0.0


def write_report(path: str | Path, title: str, image_size: tuple[int, int],
                 images: Sequence[ImageResiduals], lines: Sequence[str] = (),
                 scale: float | None = None) -> Path:
    """Draw the report (see the module docstring) and write it atomically as a PNG.

    Parameters
    ----------
    path : where to write the PNG.
    title : first line of the report (e.g. the command and the board).
    image_size : (width, height) of the calibration images, px.
    images : the residuals of every image used.
    lines : free text under the bars (ASCII; one entry per line).
    scale : residual magnification; None picks a 1-2-5 value that makes the longest arrow
        about ``ARROW_FRACTION`` of the image width.

    Returns the path written. Raises CalibrationError for malformed residuals (naming the image
    and point) or when the file cannot be written (naming the path).
    """
    w, h = _image_size(image_size)
    checked = [_checked(im) for im in images]
    if scale is None:
        scale = auto_scale(w, [r for _, r in checked])
    elif not (math.isfinite(scale) and scale > 0):
        raise CalibrationError(f"report {path}: scale {scale} must be a positive number")
    canvas = _draw(title, (w, h), images, checked, list(lines), scale)
    ok, png = cv2.imencode(".png", canvas)
    if not ok:  # pragma: no cover - imencode fails only without a PNG codec
        raise CalibrationError(f"{path}: cannot encode the report as PNG")
    p = Path(path)
    tmp = p.with_name(p.name + ".tmp")
    try:
        tmp.write_bytes(png.tobytes())
        os.replace(tmp, p)
    except OSError as err:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise CalibrationError(f"{p}: cannot write report: {err.strerror}") from None
    return p


def auto_scale(width: int, residuals: Sequence[NDArray[np.float64]]) -> float:
    """Residual magnification: the largest 1-2-5 step (..., 10, 20, 50, 100, ...) that keeps
    the longest residual at most ``ARROW_FRACTION`` of ``width``; 1 when all residuals are 0."""
    longest = max((float(np.max(np.hypot(r[:, 0], r[:, 1]))) for r in residuals if len(r)),
                  default=0.0)
    if longest <= 0:
        return 1.0
    target = ARROW_FRACTION * width / longest
    decade = 10.0 ** math.floor(math.log10(target))
    step = max(m for m in (1.0, 2.0, 5.0) if m * decade <= target * (1 + 1e-12))
    return step * decade


def _image_size(image_size: tuple[int, int]) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in image_size)
    except (TypeError, ValueError):
        raise CalibrationError(
            f"report: image size {image_size!r} is not (width, height)") from None
    if w <= 0 or h <= 0:
        raise CalibrationError(f"report: image size {w}x{h} must be positive")
    return w, h


def _checked(im: ImageResiduals) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    px = np.asarray(im.px, dtype=float)
    res = np.asarray(im.residual_px, dtype=float)
    if px.ndim != 2 or px.shape[1] != 2 or res.shape != px.shape:
        raise CalibrationError(
            f"report: image {im.name}: px {px.shape} and residual_px {res.shape} must both be "
            "(N, 2)")
    bad = ~np.isfinite(np.hstack([px, res])).all(axis=1)
    if bad.any():
        raise CalibrationError(
            f"report: image {im.name}: point {int(np.argmax(bad))} is not finite")
    return px, res


def _colours(n: int) -> list[tuple[int, int, int]]:
    """``n`` distinguishable BGR colours (hues spread round the circle, darkened for white)."""
    hsv = np.zeros((1, max(n, 1), 3), np.uint8)
    hsv[0, :, 0] = (np.arange(max(n, 1)) * 180 // max(n, 1)).astype(np.uint8)
    hsv[0, :, 1] = 230
    hsv[0, :, 2] = 200
    bgr = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0]
    return [(int(b), int(g), int(r)) for b, g, r in bgr[:n]]


def _text(img: NDArray[np.uint8], text: str, org: tuple[int, int], size: float = 0.45,
          colour: tuple[int, int, int] = BLACK, thick: int = 1) -> None:
    ascii_text = text.encode("ascii", "replace").decode("ascii")
    cv2.putText(img, ascii_text, org, FONT, size, colour, thick, cv2.LINE_AA)


def _fit(text: str, max_px: int, size: float) -> str:
    """``text`` cut from the left (file names differ at the end) to fit ``max_px``."""
    if cv2.getTextSize(text, FONT, size, 1)[0][0] <= max_px:
        return text
    for cut in range(1, len(text)):
        short = ".." + text[cut:]
        if cv2.getTextSize(short, FONT, size, 1)[0][0] <= max_px:
            return short
    return ""


_SHIFT = 4  # fixed-point bits for sub-pixel drawing
_ONE = 1 << _SHIFT


def _fixed(x: float, y: float) -> tuple[int, int]:
    return int(round(x * _ONE)), int(round(y * _ONE))


def _draw(title: str, size: tuple[int, int], images: Sequence[ImageResiduals],
          checked: list[tuple[NDArray[np.float64], NDArray[np.float64]]],
          lines: list[str], scale: float) -> NDArray[np.uint8]:
    w, h = size
    s = min(PANEL_PX / w, PANEL_PX / h)
    fw, fh = max(int(round(w * s)), 1), max(int(round(h * s)), 1)
    n = len(images)
    bars_h = ROW_PX * max(n, 1) + 2 * ROW_PX  # rows + axis labels
    right_h = bars_h + LINE_PX * (len(lines) + 1)
    width = MARGIN + fw + 2 * MARGIN + BAR_PANEL_PX + MARGIN
    height = TITLE_PX + max(fh, right_h) + 2 * MARGIN
    canvas = np.full((height, width, 3), 255, np.uint8)

    _text(canvas, _fit(title, width - 2 * MARGIN, 0.6), (MARGIN, 26), 0.6, thick=1)
    _text(canvas, f"residuals x {scale:g} (image scaled {s:.3g})", (MARGIN, 40), 0.4, GREY)

    # left panel: the image frame, dots at the observed points, magnified residual arrows
    x0, y0 = MARGIN, TITLE_PX + MARGIN
    cv2.rectangle(canvas, (x0, y0), (x0 + fw - 1, y0 + fh - 1), FRAME_BG, -1)
    cv2.rectangle(canvas, (x0 - 1, y0 - 1), (x0 + fw, y0 + fh), GREY, 1)
    colours = _colours(n)
    frame = canvas[y0:y0 + fh, x0:x0 + fw]  # a view: drawing clips at the frame
    for (px, res), colour in zip(checked, colours, strict=True):
        # pixel centre (0, 0) sits half a canvas pixel-size in from the frame corner
        start = (px + 0.5) * s - 0.5
        end = start + res * scale * s
        for (ax, ay), (bx, by) in zip(start, end, strict=True):
            cv2.circle(frame, _fixed(ax, ay), 3 * _ONE // 2, colour, -1, cv2.LINE_AA, _SHIFT)
            if math.hypot(bx - ax, by - ay) >= 1.0:
                cv2.arrowedLine(frame, _fixed(ax, ay), _fixed(bx, by), colour, 1, cv2.LINE_AA,
                                _SHIFT, 0.25)

    # right panel: per-image RMS bars, the overall RMS, then the text lines
    rx = x0 + fw + 2 * MARGIN
    rms = np.array([im.rms_px for im in images])
    all_res = np.vstack([r for _, r in checked]) if n else np.zeros((0, 2))
    overall = float(np.sqrt(np.mean(np.sum(all_res**2, axis=1)))) if len(all_res) else 0.0
    limit = OUTLIER_FACTOR * float(np.median(rms)) if n else 0.0
    label_w, value_w = 150, 52
    bar_x = rx + 14 + label_w
    bar_w = BAR_PANEL_PX - 14 - label_w - value_w
    top = y0
    _text(canvas, "per-image RMS (px)", (rx, top + 12), 0.45)
    top += ROW_PX
    full = max(float(rms.max()) if n else 0.0, overall, 1e-12)
    for i, (im, colour) in enumerate(zip(images, colours, strict=True)):
        y = top + i * ROW_PX
        cv2.rectangle(canvas, (rx, y + 4), (rx + 9, y + 13), colour, -1)
        _text(canvas, _fit(im.name, label_w - 4, 0.4), (rx + 14, y + 13), 0.4)
        outlier = limit > 0 and rms[i] > limit
        length = int(round(bar_w * rms[i] / full))
        cv2.rectangle(canvas, (bar_x, y + 3), (bar_x + max(length, 1), y + ROW_PX - 3),
                      BAR_OUTLIER if outlier else BAR_OK, -1)
        _text(canvas, f"{rms[i]:.3f}", (bar_x + length + 4, y + 13), 0.38,
              BAR_OUTLIER if outlier else BLACK)
    if n == 0:
        _text(canvas, "no images", (rx + 14, top + 13), 0.4, GREY)
    rows_bottom = top + ROW_PX * max(n, 1)
    line_x = bar_x + int(round(bar_w * overall / full))
    cv2.line(canvas, (line_x, top), (line_x, rows_bottom), RMS_LINE, 1)
    _text(canvas, f"overall RMS {overall:.3f} px; red > {OUTLIER_FACTOR:g} x median",
          (rx, rows_bottom + 13), 0.4, RMS_LINE)
    for j, line in enumerate(lines):
        _text(canvas, _fit(line, BAR_PANEL_PX, 0.42), (rx, rows_bottom + ROW_PX + 13 + j * LINE_PX),
              0.42)
    return canvas
