"""Pinhole camera with skew and Brown ("Plumb Bob") lens distortion.

The model is the one of the Caltech (Bouguet) toolbox and of OpenCV; see ``docs/geometry.md`` for
how it relates to the chapter's equations (3), (4), (7), (8) and to the toolbox's ``kc``.

For a point ``(X, Y, Z)`` in the camera frame (mm, Z along the optical axis, Z > 0)::

    x, y   = X / Z, Y / Z                        normalized (undistorted) coordinates
    r2     = x**2 + y**2
    radial = 1 + k1 r2 + k2 r2**2 + k3 r2**3
    xd     = radial x + 2 p1 x y + p2 (r2 + 2 x**2)
    yd     = radial y + p1 (r2 + 2 y**2) + 2 p2 x y
    u      = fx xd + skew yd + cx                pixels; origin at the centre of the
    v      = fy yd + cy                          top-left pixel (OpenCV and Bouguet)

``dist`` is stored in OpenCV's order ``(k1, k2, p1, p2, k3)``, which equals Bouguet's ``kc``;
``skew`` is in pixels (``K[0, 1]``), i.e. ``fx * alpha_c`` in Bouguet's notation.
No I/O here: loading and saving calibrations lives in ``vgripd.calibrate``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NoReturn

import cv2
import numpy as np
import numpy.typing as npt

from vgripd.errors import ConvergenceError, DegenerateInputError

FloatArray = npt.NDArray[np.float64]

_EYE3 = np.eye(3)
# A fixed number of OpenCV fixed-point iterations for the starting point: 20 reach ~1e-13 at
# |k1| ~ 0.3 and cost ~2x the default 5; an EPS criterion would make OpenCV reproject every
# iteration, several times slower than Newton's own check.
_GUESS_CRITERIA = (cv2.TERM_CRITERIA_COUNT, 20, 0.0)


def _points(a: Any, dims: int, what: str) -> FloatArray:
    """``a`` as a float64 (n, dims) array; a single point of shape (dims,) is accepted as n = 1."""
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim == 1 and arr.shape[0] == dims:
        arr = arr.reshape(1, dims)
    if arr.ndim != 2 or arr.shape[1] != dims:
        raise DegenerateInputError(f"{what}: expected shape (n, {dims}), got {arr.shape}")
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        raise DegenerateInputError(f"{what}: point {int(np.argmax(bad))} is not finite")
    return arr


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics of one camera (pixels) and its distortion (dimensionless).

    Parameters
    ----------
    fx, fy : focal lengths in pixels (Bouguet ``fc``), > 0.
    cx, cy : principal point in pixels (Bouguet ``cc``).
    skew : ``K[0, 1]`` in pixels (Bouguet ``fc[0] * alpha_c``); 0 for all ordinary cameras.
    dist : ``(k1, k2, p1, p2, k3)``, OpenCV order, equal to Bouguet ``kc``.
    width, height : image size in pixels; 0 when unknown.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    skew: float = 0.0
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    width: int = 0
    height: int = 0

    def __post_init__(self) -> None:
        scalars = {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "skew": self.skew}
        for name, value in scalars.items():
            if not math.isfinite(value):
                raise DegenerateInputError(f"camera model: {name} is not finite ({value})")
            object.__setattr__(self, name, float(value))
        if self.fx <= 0 or self.fy <= 0:
            raise DegenerateInputError(
                f"camera model: focal lengths must be > 0 px, got fx={self.fx}, fy={self.fy}")
        dist = tuple(float(k) for k in self.dist)
        if len(dist) != 5 or not all(math.isfinite(k) for k in dist):
            raise DegenerateInputError(
                f"camera model: dist must be 5 finite numbers (k1, k2, p1, p2, k3), got {dist}")
        object.__setattr__(self, "dist", dist)
        if self.width < 0 or self.height < 0:
            raise DegenerateInputError(
                f"camera model: negative image size {self.width}x{self.height}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    # ------------------------------------------------------------------ conversions
    @property
    def K(self) -> FloatArray:
        """The (3, 3) camera matrix ``[[fx, skew, cx], [0, fy, cy], [0, 0, 1]]`` (chapter eq. 7)."""
        return np.array([[self.fx, self.skew, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_array(self) -> FloatArray:
        """Distortion ``(k1, k2, p1, p2, k3)`` as a (5,) array, ready for OpenCV."""
        return np.array(self.dist, dtype=np.float64)

    @classmethod
    def from_opencv(cls, K: Any, dist: Any, size: tuple[int, int] = (0, 0)) -> CameraModel:
        """Build from an OpenCV camera matrix, distortion vector and image size ``(w, h)``.

        ``dist`` may have 4 or 5 entries, or more when the extra (rational, thin-prism, tilt)
        terms are all zero: this model cannot represent them, so non-zero ones are an error.
        """
        Km = np.asarray(K, dtype=np.float64)
        if Km.shape != (3, 3):
            raise DegenerateInputError(f"camera matrix: expected shape (3, 3), got {Km.shape}")
        if Km[1, 0] != 0 or Km[2, 0] != 0 or Km[2, 1] != 0 or Km[2, 2] != 1:
            raise DegenerateInputError(f"camera matrix is not upper triangular with K[2,2]=1: {Km}")
        d = np.asarray(dist, dtype=np.float64).ravel()
        if d.size < 4:
            raise DegenerateInputError(f"distortion: need at least 4 coefficients, got {d.size}")
        if d.size > 5 and np.any(d[5:] != 0):
            raise DegenerateInputError(
                "distortion: coefficients beyond k3 (rational/thin-prism/tilt) are not supported, "
                f"got {d.tolist()}")
        d5 = np.zeros(5)
        d5[: min(5, d.size)] = d[:5]
        return cls(fx=Km[0, 0], fy=Km[1, 1], cx=Km[0, 2], cy=Km[1, 2], skew=Km[0, 1],
                   dist=(d5[0], d5[1], d5[2], d5[3], d5[4]), width=size[0], height=size[1])

    def to_opencv(self) -> tuple[FloatArray, FloatArray]:
        """``(K, dist)`` with ``K`` (3, 3) and ``dist`` (5,) for OpenCV calls."""
        return self.K, self.dist_array

    # ------------------------------------------------------------------ forward model
    def distort(self, xn: Any) -> FloatArray:
        """Apply the Brown distortion to normalized coordinates.

        Parameters
        ----------
        xn : (n, 2) normalized undistorted coordinates ``(X/Z, Y/Z)``.

        Returns
        -------
        (n, 2) normalized distorted coordinates ``(xd, yd)``.
        """
        p = _points(xn, 2, "distort")
        return np.stack(self._distort_xy(p[:, 0], p[:, 1]), axis=1)

    def _distort_xy(self, x: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
        k1, k2, p1, p2, k3 = self.dist
        xy = x * y
        x2 = x * x
        y2 = y * y
        r2 = x2 + y2
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = radial * x + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x2)
        yd = radial * y + p1 * (r2 + 2.0 * y2) + 2.0 * p2 * xy
        return xd, yd

    def project(self, points_cam: Any) -> FloatArray:
        """Project points given in the camera frame to pixels (chapter eqs. 3, 4, 8).

        Parameters
        ----------
        points_cam : (n, 3) points in the camera frame, mm.

        Returns
        -------
        (n, 2) pixel coordinates ``(u, v)``.

        Raises
        ------
        DegenerateInputError
            naming the first point index that is not finite or not in front of the camera (Z <= 0).
        """
        P = _points(points_cam, 3, "project")
        behind = P[:, 2] <= 0
        if behind.any():
            i = int(np.argmax(behind))
            raise DegenerateInputError(
                f"project: point {i} is not in front of the camera (Z = {P[i, 2]} mm)")
        x = P[:, 0] / P[:, 2]
        y = P[:, 1] / P[:, 2]
        xd, yd = self._distort_xy(x, y)
        out = np.empty((P.shape[0], 2))
        out[:, 0] = self.fx * xd + self.skew * yd + self.cx
        out[:, 1] = self.fy * yd + self.cy
        return out

    # ------------------------------------------------------------------ inverse model
    def undistort(self, px: Any, *, max_iter: int = 20, tol: float = 1e-12) -> FloatArray:
        """Pixels -> normalized undistorted coordinates ``(X/Z, Y/Z)``.

        The distortion has no closed-form inverse (the chapter notes that (3) and (4) "are not
        linear"), so it is inverted iteratively. OpenCV's fixed-point iteration (compiled, fast,
        given the distorted normalized coordinates and an identity camera matrix, so skew and
        the principal point are handled here) provides the starting point; Newton's method on
        both coordinates, vectorised over the points, then runs until every point's residual
        ``|distort(x) - xd|`` is below ``tol``. The first Newton evaluation is the check that
        the starting point is right; where the fixed-point iteration has stalled or diverged
        (strong distortion near the image corners), Newton repairs it in a few quadratic steps.

        Parameters
        ----------
        px : (n, 2) pixel coordinates.
        max_iter : Newton steps allowed after the starting point.
        tol : tolerance on the residual in normalized coordinates (dimensionless; multiply by
            ``fx`` for pixels). 1e-12 is about 1e-9 px for usual focal lengths.

        Returns
        -------
        (n, 2) normalized undistorted coordinates.

        Raises
        ------
        ConvergenceError
            if some point does not converge, or converges beyond the fold of the distortion
            polynomial (where distance from the centre stops growing with the true radius, so
            the model is not invertible); names the worst point's index and residual in pixels.
        """
        p = _points(px, 2, "undistort")
        target = np.empty((2, p.shape[0]))  # distorted normalized coordinates, one row per axis
        target[1] = (p[:, 1] - self.cy) / self.fy
        target[0] = (p[:, 0] - self.cx - self.skew * target[1]) / self.fx
        if not any(self.dist) or p.shape[0] == 0:
            return target.T.copy()
        k1, k2, p1, p2, k3 = self.dist
        guess = cv2.undistortPoints(target.T.reshape(-1, 1, 2), _EYE3, self.dist_array,
                                    criteria=_GUESS_CRITERIA)
        P: FloatArray = np.array(guess.reshape(-1, 2).T, dtype=np.float64)
        # With c = p2 x + p1 y the tangential terms are 2 c (x, y) + (p2, p1) r2, which lets
        # both coordinates share one array expression.
        tang = np.array([p2, p1])
        for step in range(max_iter + 1):
            P2 = P * P
            r2 = P2[0] + P2[1]
            scale = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3)) + 2.0 * (tang @ P)
            F = scale * P + tang[:, None] * r2 - target
            converged = bool(np.vdot(F, F) < tol * tol)  # every point's residual < tol
            if converged or step == max_iter:
                break
            dradial = 2.0 * (k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2))  # 2 d(radial)/d(r2)
            # The Jacobian of (xd, yd) w.r.t. (x, y) is symmetric: [[J0, Jxy], [Jxy, J1]].
            J = scale + dradial * P2 + np.array([[4.0 * p2], [4.0 * p1]]) * P
            Jxy = dradial * (P[0] * P[1]) + np.array([2.0 * p1, 2.0 * p2]) @ P
            P -= (J[::-1] * F - Jxy * F[::-1]) / (J[0] * J[1] - Jxy * Jxy)
        # d(r_d)/dr along the ray (r_d = r radial(r^2)); > 0 on the invertible side of the fold.
        slope = 1.0 + r2 * (3.0 * k1 + r2 * (5.0 * k2 + r2 * 7.0 * k3))
        if not converged or not slope.min() > 0:
            self._raise_not_converged(F, slope, tol)
        return P.T.copy()

    def _raise_not_converged(self, F: FloatArray, slope: FloatArray, tol: float) -> NoReturn:
        with np.errstate(invalid="ignore"):
            res = np.hypot(F[0], F[1])
        res = np.where(np.isfinite(res), res, np.inf)
        bad = (res > tol) | ~(slope > 0)
        i = int(np.argmax(np.where(bad, res, -1.0)))
        why = "did not converge" if res[i] > tol else "converged beyond the distortion's fold"
        raise ConvergenceError(
            f"undistort: point {i} {why} (residual {res[i] * max(self.fx, self.fy):.3g} px; "
            f"{int(bad.sum())} of {res.size} points bad)")

    def rays(self, px: Any) -> FloatArray:
        """Unit viewing directions in the camera frame for pixels.

        Parameters
        ----------
        px : (n, 2) pixel coordinates.

        Returns
        -------
        (n, 3) unit vectors, Z > 0.
        """
        xn = self.undistort(px)
        v = np.empty((xn.shape[0], 3))
        v[:, :2] = xn
        v[:, 2] = 1.0
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        return v
