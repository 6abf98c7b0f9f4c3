"""Chessboard images through a known OpenCV camera, with nothing from ``vgripd``.

For the coverage benchmark (``bench_calib_coverage.py --rendered``): the calibration under
test must not supply its own ground truth, so the images are made here from plain numbers with
OpenCV and numpy only, and the truth of every corner is ``cv2.projectPoints`` of its board
coordinates.

How a pixel gets its grey level: its centre is undistorted once per camera
(``cv2.undistortPoints``, iterated to 1e-12; checked by projecting back, :meth:`Camera.check`)
into a normalised ray, the ray is cut with the board plane of the view (a homography), and the
board point (x, y) mm is shaded by an anti-aliased chessboard function: per axis a square wave
of the pitch whose steps are linear ramps one pixel footprint wide, the two multiplied. Each
edge is where its ramp crosses zero, so every inner corner sits exactly at its board
coordinates (no texture grid, no resampling); then a Gaussian blur (the optics) and Gaussian
sensor noise. Board layout as the project's chessboard convention (``Board.object_points``:
inner corner (i, j) at (i p, j p)); the square whose lower corner is (-p, -p) is black; a white
margin of one square surrounds the squares, the rest of the scene is mid grey.
"""

from __future__ import annotations

import cv2
import numpy as np

WHITE, BLACK, BACKGROUND = 225.0, 30.0, 120.0


class Camera:
    """A pinhole + Brown (k1 k2 p1 p2 k3) camera, OpenCV's conventions, with its per-pixel
    rays precomputed."""

    def __init__(self, fx: float, fy: float, cx: float, cy: float, dist: tuple[float, ...],
                 width: int, height: int) -> None:
        self.K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        self.dist = np.asarray(dist, dtype=np.float64)
        self.size = (width, height)
        xs, ys = np.meshgrid(np.arange(width, dtype=np.float64),
                             np.arange(height, dtype=np.float64))
        pix = np.stack([xs.ravel(), ys.ravel()], axis=1).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
        rays = cv2.undistortPoints(pix, self.K, self.dist, None, None, None, crit).reshape(-1, 2)
        self.rays = rays  # (H*W, 2) normalised x/z, y/z of each pixel centre
        self.ray_grid = rays.reshape(height, width, 2)

    def check(self, samples: int = 20000, seed: int = 0) -> float:
        """Largest px distance between sampled pixel centres and their rays projected back."""
        idx = np.random.default_rng(seed).choice(len(self.rays), samples, replace=False)
        pts = np.column_stack([self.rays[idx], np.ones(samples)])
        back, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), self.K, self.dist)
        w = self.size[0]
        centre = np.column_stack([idx % w, idx // w]).astype(np.float64)
        return float(np.abs(back.reshape(-1, 2) - centre).max())

    def project(self, points_mm: np.ndarray, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
        """(N, 2) px of board points (N, 3) mm at pose (rvec, tvec) board -> camera."""
        px, _ = cv2.projectPoints(np.asarray(points_mm, np.float64), rvec, tvec, self.K,
                                  self.dist)
        return px.reshape(-1, 2)

    def render(self, cols: int, rows: int, pitch_mm: float, rvec: np.ndarray, tvec: np.ndarray,
               rng: np.random.Generator, blur_px: float = 0.8,
               noise: float = 2.0) -> np.ndarray:
        """8-bit image of a chessboard with ``cols`` x ``rows`` inner corners at the pose."""
        w, h = self.size
        R = cv2.Rodrigues(np.asarray(rvec, np.float64))[0]
        t = np.asarray(tvec, np.float64).ravel()
        # only the pixels near the board's paper are shaded (the rest is background)
        edge = np.linspace(-2 * pitch_mm, (max(cols, rows) + 1) * pitch_mm, 64)
        x0, x1, y0, y1 = -2 * pitch_mm, (cols + 1) * pitch_mm, -2 * pitch_mm, (rows + 1) * pitch_mm
        rim = np.concatenate([
            np.column_stack([np.clip(edge, x0, x1), np.full(64, y0)]),
            np.column_stack([np.clip(edge, x0, x1), np.full(64, y1)]),
            np.column_stack([np.full(64, x0), np.clip(edge, y0, y1)]),
            np.column_stack([np.full(64, x1), np.clip(edge, y0, y1)])])
        box = self.project(np.column_stack([rim, np.zeros(len(rim))]), rvec, tvec)
        u0, v0 = (max(0, int(np.floor(box[:, i].min())) - 8) for i in (0, 1))
        u1 = min(w, int(np.ceil(box[:, 0].max())) + 9)
        v1 = min(h, int(np.ceil(box[:, 1].max())) + 9)
        rays = self.ray_grid[v0:v1, u0:u1].reshape(-1, 2)
        # ray (x, y, 1) meets the plane z_board = 0: board (X, Y, 1) ~ H^-1 (x, y, 1)
        Hn = np.column_stack([R[:, 0], R[:, 1], t])
        Hinv = np.linalg.inv(Hn)
        q = rays @ Hinv[:, :2].T + Hinv[:, 2]
        in_front = q[:, 2] > 0
        bx = q[:, 0] / q[:, 2]  # board mm
        by = q[:, 1] / q[:, 2]
        footprint = float(t[2]) / self.K[0, 0]  # mm per px at the board's distance

        def wave(u: np.ndarray) -> np.ndarray:
            s = u / pitch_mm
            sign = np.where(np.floor(s) % 2 == 0, 1.0, -1.0)
            edge = np.abs(s - np.round(s)) * pitch_mm / footprint  # px to the nearest edge
            return sign * np.clip(edge, 0.0, 0.5) * 2.0

        a, b = wave(bx), wave(by)
        dark = (1.0 + a * b) / 2.0  # 1 on black squares, 0 on white, ramps at the edges
        grey = WHITE - (WHITE - BLACK) * dark
        inside = (bx > -pitch_mm) & (bx < cols * pitch_mm) & (by > -pitch_mm) & (
            by < rows * pitch_mm)
        paper = (bx > -2 * pitch_mm) & (bx < (cols + 1) * pitch_mm) & (
            by > -2 * pitch_mm) & (by < (rows + 1) * pitch_mm)
        shaded = np.where(inside, grey, np.where(paper, WHITE, BACKGROUND))
        img = np.full((h, w), BACKGROUND, np.float32)
        img[v0:v1, u0:u1] = np.where(in_front, shaded, BACKGROUND).reshape(v1 - v0, u1 - u0)
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
        img += rng.normal(0.0, noise, img.shape).astype(np.float32)
        return np.clip(np.round(img), 0, 255).astype(np.uint8)
