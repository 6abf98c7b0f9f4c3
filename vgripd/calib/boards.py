"""Calibration boards: their geometry and finding them in images.

A board spec is ``KIND:COLSxROWS:PITCH_MM[:MARKER_MM[:DICT]]``:

- ``chessboard:13x12:30``: 13 x 12 *inner* corners (a 14 x 13 square board), 30 mm squares.
- ``circles:4x11:20``: symmetric circle grid, 4 circles per row, 11 rows, centre pitch 20 mm.
- ``acircles:4x11:20``: OpenCV's asymmetric circle grid; row ``i`` is shifted by half a
  column when ``i`` is odd; ``PITCH_MM`` is the distance between adjacent rows (so circles
  in one row are ``2 * PITCH_MM`` apart), as in OpenCV's calibration sample.
- ``charuco:5x7:30:22[:DICT_4X4_50]``: a ChArUco board of 5 x 7 *squares* (as OpenCV's
  ``CharucoBoard`` counts them, so 4 x 6 inner corners), 30 mm squares, 22 mm markers.

Board frame (mm): corner/circle 0 at the origin, x along a row (``cols`` points), y from row to
row, z = 0 on the board and pointing into it (away from a camera that sees its printed face).
Point ``k`` sits at row ``k // cols``, column ``k % cols``.

Corner order. Calibrating stereo (point k left = point k right) and hand-eye (one board frame in
every image) needs the same physical corner to get the same index in every image. A detector
may return a grid in any order that maps the grid onto itself, so detections are put in a
canonical order:

1. handedness: rows run so that the board's z axis points away from the camera;
2. chessboards whose 180 degree rotation changes the colours (``cols + rows`` odd, e.g.
   13 x 12) are unambiguous: corner 0 is the one whose diagonal square is black;
3. otherwise (symmetric circle grids, chessboards with ``cols + rows`` even, square grids) the
   grid has several orders that look identical; corner 0 is then the candidate nearest the
   image's top-left pixel, which is consistent as long as the board is not rolled by more than
   about 90 degrees between views. Prefer a colour-asymmetric chessboard or ChArUco.

Asymmetric circle grids keep OpenCV's order; ChArUco corners carry their own ids.

Chessboard detectors, in order until one finds the full grid: ``findChessboardCornersSB``;
the same with its exhaustive, accurate search (Bouguet's Image18); the classic
``findChessboardCorners``.

Sub-pixel refinement (chessboards only; circle centres and ChArUco corners come refined from
their detectors): ``cv2.cornerSubPix`` with half-window ``w`` (window ``2w + 1`` px, Bouguet's
``wintx``). By default ``w`` is 35 % of the shortest distance between adjacent corners in that
image, clamped to 3..12 px: large enough to average the noise of the edge gradients, small
enough that the window never reaches a neighbouring corner under perspective. On Bouguet's two
examples this gives lower residuals than any single fixed window (his results used 5..9 px).
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from vgripd.errors import CalibrationError

KINDS = ("chessboard", "circles", "acircles", "charuco")
DEFAULT_DICTIONARY = "DICT_4X4_50"
MIN_CHARUCO_CORNERS = 6  # fewer gives a poorly conditioned board pose
SUBPIX_FRACTION = 0.35
SUBPIX_MIN, SUBPIX_MAX = 3, 12


@dataclass(frozen=True)
class Board:
    """A planar calibration target (see the module docstring for the spec and the frame)."""

    kind: str
    cols: int
    rows: int
    pitch_mm: float
    marker_mm: float | None = None
    dictionary: str | None = None

    @property
    def symmetric(self) -> bool:
        """Whether the board looks the same turned by 180 degrees (a chessboard with
        ``cols + rows`` even, e.g. 9x7 inner corners, or a symmetric circle grid): corner 0 is
        then only consistent while the board is not rolled by more than about 90 degrees."""
        return (self.kind == "chessboard" and (self.cols + self.rows) % 2 == 0) or (
            self.kind == "circles")

    def symmetry_warning(self) -> str | None:
        """The warning for a board whose corner order is ambiguous (None when it is not)."""
        if not self.symmetric:
            return None
        fix = ("one even and one odd number of inner corners, e.g. "
               f"{self.cols}x{self.rows + 1}" if self.kind == "chessboard" else
               "an asymmetric circle grid (acircles)")
        return (f"board {self.spec}: symmetric (it looks the same turned by 180 deg), so "
                f"corner 0 is only consistent while the board is not rolled by more than about "
                f"90 deg between views: a flipped corner order spoils a stereo or hand-eye "
                f"calibration; prefer {fix} or ChArUco (docs/calibration-intrinsics.md)")

    @classmethod
    def parse(cls, spec: str) -> Board:
        """Board from ``KIND:COLSxROWS:PITCH_MM[:MARKER_MM[:DICT]]``; CalibrationError names
        the bad part."""
        parts = spec.strip().split(":")
        kind = parts[0].lower()
        if kind not in KINDS:
            raise CalibrationError(
                f"board {spec!r}: unknown kind {parts[0]!r} (one of {', '.join(KINDS)})")
        n_parts = (4, 5) if kind == "charuco" else (3,)
        if len(parts) not in n_parts:
            form = ("charuco:COLSxROWS:SQUARE_MM:MARKER_MM[:DICT]" if kind == "charuco"
                    else f"{kind}:COLSxROWS:PITCH_MM")
            raise CalibrationError(f"board {spec!r}: expected {form}")
        dims = parts[1].lower().split("x")
        try:
            cols, rows = (int(d) for d in dims)
        except ValueError:
            raise CalibrationError(
                f"board {spec!r}: size {parts[1]!r} is not COLSxROWS (e.g. 13x12)") from None
        least = 3
        if cols < least or rows < least:
            raise CalibrationError(f"board {spec!r}: size {parts[1]!r} must be at least "
                                   f"{least}x{least}")
        pitch = _positive_mm(parts[2], spec, "pitch")
        if kind != "charuco":
            return cls(kind, cols, rows, pitch)
        marker = _positive_mm(parts[3], spec, "marker size")
        if marker >= pitch:
            raise CalibrationError(
                f"board {spec!r}: marker size {marker:g} mm must be smaller than the square "
                f"{pitch:g} mm")
        dictionary = parts[4].upper() if len(parts) == 5 else DEFAULT_DICTIONARY
        if not dictionary.startswith("DICT_") or not hasattr(cv2.aruco, dictionary):
            raise CalibrationError(
                f"board {spec!r}: unknown ArUco dictionary {dictionary!r} (e.g. DICT_4X4_50)")
        board = cls(kind, cols, rows, pitch, marker, dictionary)
        n_markers = cols * rows // 2
        available = len(_aruco_dictionary(dictionary).bytesList)
        if n_markers > available:
            raise CalibrationError(
                f"board {spec!r}: needs {n_markers} markers, {dictionary} has {available}")
        return board

    @property
    def spec(self) -> str:
        """The spec string this board parses from."""
        text = f"{self.kind}:{self.cols}x{self.rows}:{self.pitch_mm:g}"
        if self.kind == "charuco":
            text += f":{self.marker_mm:g}:{self.dictionary}"
        return text

    @property
    def n_points(self) -> int:
        """Number of points of a complete detection."""
        if self.kind == "charuco":
            return (self.cols - 1) * (self.rows - 1)
        return self.cols * self.rows

    @property
    def grid_cols(self) -> int:
        """Points per row (for ChArUco the inner corners per row)."""
        return self.cols - 1 if self.kind == "charuco" else self.cols

    def object_points(self) -> NDArray[np.float64]:
        """Board points in the board frame, shape (N, 3), mm, z = 0; row-major (see module)."""
        n_cols = self.grid_cols
        r, c = np.divmod(np.arange(self.n_points), n_cols)
        x = c * self.pitch_mm
        if self.kind == "acircles":
            x = (2 * c + r % 2) * self.pitch_mm
        pts = np.zeros((self.n_points, 3))
        pts[:, 0] = x
        pts[:, 1] = r * self.pitch_mm
        return pts


@dataclass
class Detection:
    """The board found in one image.

    ``size`` is (width, height) px; ``ids`` (N,) index ``Board.object_points()``; ``px`` (N, 2)
    float64 image points in OpenCV's convention (centre of the top-left pixel = (0, 0)).
    """

    image: str
    size: tuple[int, int]
    ids: NDArray[np.int64]
    px: NDArray[np.float64]


def detect(board: Board, gray: NDArray[Any], image: str,
           subpix_window: int | None = None) -> Detection:
    """Find ``board`` in one 8-bit image (grey or BGR); points in canonical order.

    ``subpix_window`` is the cornerSubPix half-window in px (chessboards; None = from the corner
    spacing, see the module docstring). Raises CalibrationError ``"<image>: board not found:
    <why>"``.
    """
    gray = _as_gray(gray, image)
    size = (int(gray.shape[1]), int(gray.shape[0]))
    if board.kind == "charuco":
        ids, px = _find_charuco(board, gray, image)
        return Detection(image, size, ids, px)
    if board.kind == "chessboard":
        grid = _find_chessboard(board, gray, image, subpix_window)
    else:
        grid = _find_circles(board, gray, image)
    if board.kind != "acircles":
        grid = _canonical(grid, gray if board.kind == "chessboard" else None)
    return Detection(image, size, np.arange(board.n_points, dtype=np.int64),
                     grid.reshape(-1, 2).astype(np.float64))


def detect_files(board: Board, paths: Iterable[str | Path], subpix_window: int | None = None,
                 ) -> tuple[list[Detection], list[tuple[str, str]]]:
    """Detect the board in image files.

    Returns the detections (in the order of ``paths``) and ``(file, reason)`` for every image
    left out: unreadable, a size different from most of the images, or no board.
    """
    images: list[tuple[str, NDArray[Any] | None]] = [
        (str(p), cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)) for p in paths]
    sizes = Counter((g.shape[1], g.shape[0]) for _, g in images if g is not None)
    common = sizes.most_common(1)[0][0] if sizes else (0, 0)
    found: list[Detection] = []
    failed: list[tuple[str, str]] = []
    for name, gray in images:
        if gray is None:
            failed.append((name, "image unreadable (missing, not an image, or unsupported)"))
            continue
        size = (gray.shape[1], gray.shape[0])
        if size != common:
            failed.append((name, f"image size {size[0]}x{size[1]} differs from the "
                                 f"{common[0]}x{common[1]} of the other images"))
            continue
        try:
            found.append(detect(board, gray, name, subpix_window))
        except CalibrationError as err:
            failed.append((name, str(err).removeprefix(f"{name}: ")))
    return found, failed


def _positive_mm(text: str, spec: str, what: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise CalibrationError(f"board {spec!r}: {what} {text!r} is not a positive number of mm")
    return value


def _as_gray(img: NDArray[Any], image: str) -> NDArray[np.uint8]:
    a = np.asarray(img)
    if a.ndim == 3 and a.shape[2] == 3:
        a = cv2.cvtColor(a, cv2.COLOR_BGR2GRAY)
    if a.ndim != 2 or a.dtype != np.uint8 or min(a.shape) < 8:
        raise CalibrationError(
            f"{image}: board not found: image unreadable (need 8-bit grey or BGR, got "
            f"{a.dtype} {a.shape})")
    return a


def _not_found(image: str, why: str) -> CalibrationError:
    return CalibrationError(f"{image}: board not found: {why}")


def _find_chessboard(board: Board, gray: NDArray[np.uint8], image: str,
                     subpix_window: int | None) -> NDArray[np.float32]:
    pattern = (board.cols, board.rows)
    ok, corners = cv2.findChessboardCornersSB(gray, pattern, flags=cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not ok:
        # the exhaustive search finds strongly foreshortened boards (Bouguet's Image18) with
        # accurate corners; it costs a few times the plain search, so only on a miss
        flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
        ok, corners = cv2.findChessboardCornersSB(gray, pattern, flags=flags)
    if not ok:
        # the classic detector copes with some boards the sector-based one misses (heavy blur,
        # uneven light); its corners can be pixels off, which the per-image RMS then shows
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        ok, corners = cv2.findChessboardCorners(gray, pattern, flags=flags)
    if not ok:
        n = 0 if corners is None else len(corners)
        why = (f"only {n} of {board.n_points} corners found" if n else
               f"no {board.cols}x{board.rows} corner grid found")
        raise _not_found(image, why)
    grid = corners.reshape(board.rows, board.cols, 2).astype(np.float32)
    w = subpix_window if subpix_window is not None else default_subpix_window(grid)
    if w < 1:
        raise CalibrationError(f"subpix window {w}: must be at least 1 px")
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    refined = cv2.cornerSubPix(gray, grid.reshape(-1, 1, 2).copy(), (w, w), (-1, -1), criteria)
    return np.asarray(refined, dtype=np.float32).reshape(board.rows, board.cols, 2)


def default_subpix_window(grid: NDArray[Any]) -> int:
    """cornerSubPix half-window (px) for a (rows, cols, 2) corner grid: 35 % of the shortest
    adjacent-corner distance, clamped to 3..12."""
    g = np.asarray(grid, dtype=float)
    along = np.linalg.norm(np.diff(g, axis=1), axis=2).min()
    across = np.linalg.norm(np.diff(g, axis=0), axis=2).min()
    w = int(SUBPIX_FRACTION * min(along, across))
    return int(np.clip(w, SUBPIX_MIN, SUBPIX_MAX))


def _find_circles(board: Board, gray: NDArray[np.uint8], image: str) -> NDArray[np.float32]:
    flags = cv2.CALIB_CB_SYMMETRIC_GRID if board.kind == "circles" else cv2.CALIB_CB_ASYMMETRIC_GRID
    ok, centres = cv2.findCirclesGrid(gray, (board.cols, board.rows), flags=flags)
    if not ok:
        # circle grids are often dark on light; try the inverted image for light on dark
        ok, centres = cv2.findCirclesGrid(255 - gray, (board.cols, board.rows), flags=flags)
    if not ok:
        raise _not_found(image, f"no {board.cols}x{board.rows} circle grid found")
    return np.asarray(centres, dtype=np.float32).reshape(board.rows, board.cols, 2)


def _aruco_dictionary(name: str) -> Any:
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


def _find_charuco(board: Board, gray: NDArray[np.uint8], image: str,
                  ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    assert board.marker_mm is not None
    assert board.dictionary is not None
    cb = cv2.aruco.CharucoBoard((board.cols, board.rows), board.pitch_mm, board.marker_mm,
                                _aruco_dictionary(board.dictionary))
    corners, ids, _marker_corners, marker_ids = cv2.aruco.CharucoDetector(cb).detectBoard(gray)
    n = 0 if ids is None else len(ids)
    if n < MIN_CHARUCO_CORNERS:
        markers = 0 if marker_ids is None else len(marker_ids)
        why = (f"no {board.dictionary} markers found" if markers == 0 else
               f"only {n} of {board.n_points} ChArUco corners found ({markers} markers; "
               f"need at least {MIN_CHARUCO_CORNERS} corners)")
        raise _not_found(image, why)
    return (np.asarray(ids, dtype=np.int64).ravel(),
            np.asarray(corners, dtype=np.float64).reshape(-1, 2))


def _canonical(grid: NDArray[np.float32], gray: NDArray[np.uint8] | None) -> NDArray[np.float32]:
    """Put a (rows, cols, 2) grid in the canonical order of the module docstring; ``gray`` is
    given for chessboards (colour of the first square)."""
    if _signed_area(grid) < 0:  # board z axis towards the camera: mirror the rows
        grid = grid[:, ::-1]
    turns = (0, 1, 2, 3) if grid.shape[0] == grid.shape[1] else (0, 2)
    candidates = [np.ascontiguousarray(np.rot90(grid, k, axes=(0, 1))) for k in turns]
    if gray is not None:
        dark = [_first_square_dark(c, gray) for c in candidates]
        if any(dark) and not all(dark):
            candidates = [c for c, d in zip(candidates, dark, strict=True) if d]
    return min(candidates, key=lambda c: float(np.hypot(*c[0, 0])))


def _signed_area(grid: NDArray[Any]) -> float:
    """z of (row direction x column direction) in image coordinates (x right, y down): > 0 when
    the board's z axis points away from the camera."""
    along = (grid[:, -1] - grid[:, 0]).sum(axis=0)
    across = (grid[-1, :] - grid[0, :]).sum(axis=0)
    return float(along[0] * across[1] - along[1] * across[0])


def _first_square_dark(grid: NDArray[Any], gray: NDArray[np.uint8]) -> bool:
    """Is the square between corners (0,0), (0,1), (1,0), (1,1) darker than the square beside
    it, between (0,1) and (1,2)? Squares sharing an edge differ in colour."""
    first = _mean_at(gray, grid[:2, :2].reshape(-1, 2).mean(axis=0))
    beside = _mean_at(gray, grid[:2, 1:3].reshape(-1, 2).mean(axis=0))
    return first < beside


def _mean_at(gray: NDArray[np.uint8], xy: Sequence[float]) -> float:
    x, y = (int(round(float(v))) for v in xy)
    h, w = gray.shape
    patch = gray[max(y - 1, 0):min(y + 2, h), max(x - 1, 0):min(x + 2, w)]
    return float(patch.mean()) if patch.size else 0.0
