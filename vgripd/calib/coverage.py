"""How well a set of board images covers a camera for calibration: image regions and tilts.

A good calibration set shows the board in every part of the image (the distortion is only
known where corners were seen: the corners of the image matter most) and tilted in each
direction (without tilt the focal length and the distance cannot be told apart). This module
keeps that account for one camera from the board detections, without intrinsics (before the
calibration there are none), and says what is still missing.

Regions: the image cut into ``grid x grid`` cells; a cell counts as covered when a detected
board point lies in it.

Tilt: from the plane-to-image homography ``H`` of the detection (board mm -> px), as in
Zhang's calibration: with the principal point taken at the image centre and square pixels, the
two constraints a homography puts on the camera (``h1' w h2 = 0``, ``h1' w h1 = h2' w h2``,
``w = K^-T K^-1``) give the focal length in a least-squares sense (the image width when they
cannot: a board facing the camera squarely), then ``K^-1 H = [r1 r2 t]`` gives the board's
normal ``n = r1 x r2`` in the camera frame. The tilt is the angle between ``n`` and the optical
axis; above ``TILT_MIN_DEG`` the board counts as tilted, and the side nearer the camera is the
one the depth falls towards (``dz/dx = -n_x / n_z``, ``dz/dy = -n_y / n_z``), whatever the
board's roll. A guide for the operator (the focal length is estimated), not a measured angle.

Pure functions and values: no I/O, no camera; ``vgripd capture`` and the setup pages use it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from vgripd.calib.boards import Board, Detection

#: Tilt (deg, board normal vs optical axis) from which a board counts as tilted.
TILT_MIN_DEG = 15.0
#: The tilt classes a complete set shows (each side nearer the camera once, and flat).
TILTS = ("flat", "left nearer", "right nearer", "top nearer", "bottom nearer")


def board_normal(board: Board, det: Detection) -> NDArray[np.float64] | None:
    """The board's unit normal in the camera frame (z towards the scene), from the detection
    alone (module docstring); None when the points give no homography."""
    obj = board.object_points()[det.ids][:, :2]
    px = np.asarray(det.px, np.float64)
    if len(px) < 4:
        return None
    w, h = det.size
    c = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    H, _ = cv2.findHomography(obj, px - c, 0)
    if H is None or not np.all(np.isfinite(H)):
        return None
    h1, h2 = H[:, 0], H[:, 1]
    # a * A_i + B_i = 0 with a = 1 / f^2, i = orthogonality, equal norms
    A = np.array([h1[0] * h2[0] + h1[1] * h2[1],
                  h1[0] ** 2 + h1[1] ** 2 - h2[0] ** 2 - h2[1] ** 2])
    B = np.array([h1[2] * h2[2], h1[2] ** 2 - h2[2] ** 2])
    a = -float(A @ B) / float(A @ A) if float(A @ A) > 0 else 0.0
    f = 1.0 / np.sqrt(a) if a > 0 else float(max(w, h))
    if not np.isfinite(f) or not 0.1 * max(w, h) < f < 20.0 * max(w, h):
        f = float(max(w, h))
    M = np.diag([1.0 / f, 1.0 / f, 1.0]) @ H
    r1, r2 = M[:, 0], M[:, 1]
    scale = 2.0 / (np.linalg.norm(r1) + np.linalg.norm(r2))
    if M[2, 2] * scale < 0:  # the board in front of the camera
        scale = -scale
    n = np.cross(r1 * scale, r2 * scale)
    norm = np.linalg.norm(n)
    return None if norm == 0 else n / norm


def tilt_of(board: Board, det: Detection) -> str:
    """The board's apparent tilt in one detection: one of ``TILTS`` (the stronger side)."""
    n = board_normal(board, det)
    if n is None or np.degrees(np.arccos(min(1.0, abs(n[2])))) < TILT_MIN_DEG:
        return "flat"
    if abs(n[0]) >= abs(n[1]):
        return "left nearer" if -n[0] / n[2] > 0 else "right nearer"
    return "top nearer" if -n[1] / n[2] > 0 else "bottom nearer"


@dataclass
class Coverage:
    """What one camera's kept detections cover: image cells and tilt classes.

    ``size``: (width, height) px; ``grid``: cells per side."""

    size: tuple[int, int]
    grid: int = 4
    cells: set[tuple[int, int]] = field(default_factory=set)
    tilts: set[str] = field(default_factory=set)
    images: int = 0

    def cells_of(self, det: Detection) -> set[tuple[int, int]]:
        """The cells (column, row) holding a point of ``det``."""
        w, h = self.size
        px = np.asarray(det.px, np.float64)
        col = np.clip((px[:, 0] / w * self.grid).astype(int), 0, self.grid - 1)
        row = np.clip((px[:, 1] / h * self.grid).astype(int), 0, self.grid - 1)
        return {(int(c), int(r)) for c, r in zip(col, row, strict=True)}

    def news(self, board: Board, det: Detection) -> list[str]:
        """What ``det`` would add: new cells and a new tilt, in words (empty: nothing)."""
        out = []
        new_cells = self.cells_of(det) - self.cells
        if new_cells:
            out.append(f"{len(new_cells)} new image region(s)")
        tilt = tilt_of(board, det)
        if tilt not in self.tilts:
            out.append(f"tilt {tilt}")
        return out

    def add(self, board: Board, det: Detection) -> None:
        self.cells |= self.cells_of(det)
        self.tilts.add(tilt_of(board, det))
        self.images += 1

    @property
    def share(self) -> float:
        """Covered cells / all cells."""
        return len(self.cells) / self.grid ** 2

    def missing(self) -> list[str]:
        """What a good set still lacks, in words an operator can act on."""
        out = []
        names = {(0, 0): "top-left", (self.grid - 1, 0): "top-right",
                 (0, self.grid - 1): "bottom-left", (self.grid - 1, self.grid - 1): "bottom-right"}
        corners = [n for c, n in names.items() if c not in self.cells]
        if corners:
            out.append("the board in the image's " + ", ".join(corners) + " corner(s)")
        others = self.grid ** 2 - len(self.cells) - len(corners)
        if others > 0:
            out.append(f"{others} more image region(s) (of {self.grid}x{self.grid})")
        tilts = [t for t in TILTS if t not in self.tilts]
        if tilts:
            out.append("the board tilted: " + ", ".join(tilts))
        return out

    def summary(self) -> str:
        return (f"{len(self.cells)}/{self.grid ** 2} regions, tilts "
                f"{', '.join(t for t in TILTS if t in self.tilts) or 'none'}")


def moved_px(a: Detection, b: Detection) -> float:
    """The largest displacement (px) of the board points two detections share; inf when they
    share none."""
    common, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
    if len(common) == 0:
        return float("inf")
    return float(np.max(np.linalg.norm(a.px[ia] - b.px[ib], axis=1)))


def mean_moved_px(a: Detection, b: Detection) -> float:
    """The mean displacement (px) of the shared board points; inf when none are shared."""
    common, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
    if len(common) == 0:
        return float("inf")
    return float(np.mean(np.linalg.norm(a.px[ia] - b.px[ib], axis=1)))

