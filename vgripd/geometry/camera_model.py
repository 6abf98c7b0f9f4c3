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
The distortion itself (forward, derivative, inverse) is :mod:`vgripd.geometry.distortion`, the
one implementation of it. No I/O here: loading and saving calibrations lives in
``vgripd.calib``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Any, NamedTuple, NoReturn

import numpy as np

from vgripd.errors import ConvergenceError, DegenerateInputError
from vgripd.geometry.distortion import (
    Brown,
    distort,
    distort_with_jacobian,
    opencv_start,
    radial_slope,
    safe_r2,
    undistort,
)
from vgripd.types import FloatArray


class _Inverse(NamedTuple):
    """What :meth:`CameraModel.undistort` needs on every call, prepared once."""

    c: FloatArray  # (cx, cy), px
    f: FloatArray  # (fx, fy), px
    dist: FloatArray  # (5,), OpenCV order
    distorted: bool  # any coefficient non-zero
    coef: Brown  # for distortion.undistort
    r2_safe: float  # distortion.safe_r2


class PairInverse(NamedTuple):
    """:class:`_Inverse` of two cameras, for n points of each stacked (left block first)."""

    cameras: tuple[CameraModel, CameraModel]
    c: FloatArray  # (2n, 2)
    f: FloatArray  # (2n, 2)
    skew: FloatArray | None  # (2n,), None when both cameras have none
    coef: Brown  # k1, k2, k3 (2n,); tang2 (2, 2n)
    r2_safe: float  # the smaller of both


def undistort_pair(pc: PairInverse, px_a: FloatArray, px_b: FloatArray,
                   ) -> tuple[FloatArray, FloatArray] | None:
    """Both cameras' pixels (n, 2) each -> normalized coordinates, one Newton run for both.

    The fast path of a stereo pair: what :meth:`CameraModel.undistort` does, with both cameras'
    points in one set of arrays (half the numpy calls). Returns P (2, 2n), one row per axis,
    the first camera's points first, and r2 = x^2 + y^2 (2n,) of P; or None when anything is
    wrong or unusual (not finite, not converged, near the fold): then the caller undistorts each
    camera on its own, which names the error.
    """
    n = px_a.shape[0]
    d = np.concatenate((px_a, px_b)) - pc.c
    if pc.skew is not None:
        d[:, 0] -= pc.skew * (d[:, 1] / pc.f[:, 1])
    target = d / pc.f
    a, b = pc.cameras
    start = np.concatenate([opencv_start(target[:n], a._inverse.dist),
                            opencv_start(target[n:], b._inverse.dist)], axis=1)
    P, r2, _, converged = undistort(target.T, start, pc.coef, 20, 1e-12)
    if converged and np.maximum.reduce(r2) < pc.r2_safe:
        return P, r2
    return None


def project_with_jacobian(camera: CameraModel, P: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Pixels (n, 2) of camera-frame points P (n, 3) and their derivative (n, 2, 3) d px / d P.

    The analytic derivative of :meth:`CameraModel.project` (pinhole, Brown distortion, skew),
    so a pose refinement needs no finite differences. Depths are not checked here (the
    callers keep them positive).
    """
    inv_z = 1.0 / P[:, 2]
    xn = P[:, :2].T * inv_z
    (xd, yd), (a, d), b = distort_with_jacobian(xn, camera._inverse.coef)
    px = np.empty((P.shape[0], 2))
    px[:, 0] = camera.fx * xd + camera.skew * yd + camera.cx
    px[:, 1] = camera.fy * yd + camera.cy
    # d(u, v) / d(x, y): K's upper-left 2x2 times the distortion's derivative [[a, b], [b, d]]
    du = np.stack([camera.fx * a + camera.skew * b, camera.fx * b + camera.skew * d], axis=1)
    dv = np.stack([camera.fy * b, camera.fy * d], axis=1)
    x, y = xn
    J = np.empty((P.shape[0], 2, 3))
    for row, g in ((0, du), (1, dv)):
        J[:, row, 0] = g[:, 0] * inv_z
        J[:, row, 1] = g[:, 1] * inv_z
        J[:, row, 2] = -(g[:, 0] * x + g[:, 1] * y) * inv_z
    return px, J


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

    @cached_property
    def _inverse(self) -> _Inverse:
        """Constants of the undistortion hot path, computed once per camera."""
        k1, k2, _, _, k3 = self.dist
        return _Inverse(c=np.array([self.cx, self.cy]), f=np.array([self.fx, self.fy]),
                        dist=self.dist_array, distorted=any(self.dist),
                        coef=Brown.of(self.dist), r2_safe=safe_r2(k1, k2, k3))

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
        return distort(p.T, self._inverse.coef).T.copy()

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
        xd, yd = distort(P[:, :2].T / P[:, 2], self._inverse.coef)
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
        DegenerateInputError
            naming the first point that is not finite, or for a wrong shape.
        ConvergenceError
            if some point does not converge, or converges beyond the fold of the distortion
            polynomial (where distance from the centre stops growing with the true radius, so
            the model is not invertible); names the worst point's index and residual in pixels.
        """
        inv = self._inverse
        p = np.asarray(px, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 2 or not p.shape[0] or not inv.distorted:
            p = _points(p, 2, "undistort")  # the general path: shape and NaN checked up front
            if not inv.distorted or not p.shape[0]:
                return self._normalized(p)
        # Not finite pixels are found (and named) only if Newton fails: NaN propagates there.
        target = self._normalized(p)
        start = opencv_start(target, inv.dist)
        P, r2, F, converged = undistort(target.T, start, inv.coef, max_iter, tol)
        if not (converged and np.maximum.reduce(r2) < inv.r2_safe):
            self._check_inverse(p, r2, F, converged, tol)
        return P.T.copy()

    def _pair_constants(self, other: CameraModel, n: int) -> PairInverse:
        """Constants for :func:`undistort_pair` of n points of this camera and of ``other``."""
        cams = (self._inverse, other._inverse)
        return PairInverse(
            cameras=(self, other),
            c=np.repeat([c.c for c in cams], n, axis=0),
            f=np.repeat([c.f for c in cams], n, axis=0),
            skew=np.repeat([self.skew, other.skew], n) if self.skew or other.skew else None,
            coef=Brown.stacked(cams[0].coef, cams[1].coef, n),
            r2_safe=min(c.r2_safe for c in cams),
        )

    def _normalized(self, p: FloatArray) -> FloatArray:
        """(n, 2) pixels -> (n, 2) distorted normalized coordinates (K^-1, skew included)."""
        inv = self._inverse
        d = p - inv.c
        if self.skew:
            d[:, 0] -= self.skew * (d[:, 1] / self.fy)
        return d / inv.f

    def _check_inverse(self, p: FloatArray, r2: FloatArray, F: FloatArray, converged: bool,
                       tol: float) -> None:
        """Raise unless Newton's result for pixels ``p`` (its r2 and residual F) is valid.

        Called off the fast path only: when Newton did not converge (first: is a point not
        finite?) or when some point lies beyond the radius below which the slope is known to be
        positive (then the slope is evaluated exactly).
        """
        if not converged:
            _points(p, 2, "undistort")
        k1, k2, _, _, k3 = self.dist
        slope = radial_slope(k1, k2, k3, r2)  # > 0 on the invertible side of the fold
        if not converged or not slope.min() > 0:
            self._raise_not_converged(F, slope, tol)

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
