"""Brown-Conrady lens distortion ("Plumb Bob"): the one implementation every module uses.

The model of OpenCV and of the Caltech (Bouguet) toolbox, coefficients in OpenCV's order
``(k1, k2, p1, p2, k3)`` (= Bouguet's ``kc``). For undistorted normalized coordinates
``(x, y) = (X/Z, Y/Z)``::

    r2     = x**2 + y**2
    radial = 1 + k1 r2 + k2 r2**2 + k3 r2**3
    xd     = radial x + 2 p1 x y + p2 (r2 + 2 x**2)
    yd     = radial y + p1 (r2 + 2 y**2) + 2 p2 x y

Written here as ``(xd, yd) = s (x, y) + (p2, p1) r2`` with ``s = radial + 2 (p2 x + p1 y)``,
which lets both coordinates share one array expression. Points are columns of a (2, n) array
(row 0 = x, row 1 = y); the coefficients are one set for all points or one per point
(:class:`Brown`), so a stereo pair or a whole calibration (every camera's points) runs in one
call.

* :func:`distort`: the forward model.
* :func:`distort_with_jacobian`: and its derivative with respect to ``(x, y)``, which is
  symmetric: ``[[J0, Jxy], [Jxy, J1]]``.
* :func:`coefficient_jacobian`: the derivative with respect to ``(k1, k2, p1, p2, k3)`` (the
  model is linear in them), for calibrations that refine the distortion.
* :func:`undistort`: the inverse, Newton's method from OpenCV's fixed-point iteration
  (:func:`opencv_start`); :func:`safe_r2` and :func:`radial_slope` say where the model is
  invertible (the slope of the distorted radius along a ray stays positive).

No pixels here: the camera matrix (focal lengths, principal point, skew) is
:class:`vgripd.geometry.camera_model.CameraModel`'s.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple, cast

import cv2
import numpy as np

from vgripd.types import FloatArray

__all__ = ["Brown", "coefficient_jacobian", "distort", "distort_with_jacobian", "opencv_start",
           "radial_slope", "safe_r2", "undistort"]

_EYE3 = np.eye(3)
# A fixed number of OpenCV fixed-point iterations for the starting point: 20 reach ~1e-13 at
# |k1| ~ 0.3 and cost ~2x the default 5; an EPS criterion would make OpenCV reproject every
# iteration, several times slower than Newton's own check.
_START_CRITERIA = (cv2.TERM_CRITERIA_COUNT, 20, 0.0)


class Brown(NamedTuple):
    """Distortion coefficients laid out for the (2, n) point arrays of this module.

    k1, k2, k3 are floats (one set for all points) or (n,) arrays (one per point);
    tang = (p2, p1) and tang2 = 2 tang are (2, 1) or (2, n).
    """

    k1: Any
    k2: Any
    k3: Any
    tang: FloatArray
    tang2: FloatArray

    @classmethod
    def of(cls, dist: tuple[float, float, float, float, float]) -> Brown:
        """One set ``(k1, k2, p1, p2, k3)`` (OpenCV order) for all points."""
        k1, k2, p1, p2, k3 = dist
        return cls(k1, k2, k3, np.array([[p2], [p1]]), np.array([[2.0 * p2], [2.0 * p1]]))

    @classmethod
    def per_point(cls, k1: FloatArray, k2: FloatArray, p1: FloatArray, p2: FloatArray,
                  k3: FloatArray) -> Brown:
        """One set per point: each argument an (n,) array."""
        tang = np.stack([p2, p1])
        return cls(k1, k2, k3, tang, 2.0 * tang)

    @classmethod
    def stacked(cls, a: Brown, b: Brown, n: int) -> Brown:
        """n points of camera a, then n of camera b."""
        def per_point(x: Any, y: Any) -> FloatArray:
            if np.ndim(x) == 0:  # k1, k2, k3 -> (2n,)
                return np.repeat([x, y], n)
            return np.repeat(np.hstack([x, y]), n, axis=1)  # (m, 1) columns -> (m, 2n)

        return cls(*(per_point(x, y) for x, y in zip(a, b, strict=True)))


def _terms(P: FloatArray, c: Brown) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """P^2 (2, n), r2 (n,), the scale s (n,) and the distorted points (2, n)."""
    P2 = P * P
    r2 = P2[0] + P2[1]
    scale = 1.0 + r2 * (c.k1 + r2 * (c.k2 + r2 * c.k3)) + np.add.reduce(c.tang2 * P)
    return P2, r2, scale, scale * P + c.tang * r2


def _jacobian(P: FloatArray, P2: FloatArray, r2: FloatArray, scale: FloatArray, c: Brown,
              ) -> tuple[FloatArray, FloatArray]:
    """The diagonal (2, n) and the off-diagonal term (n,) of d(xd, yd) / d(x, y)."""
    dradial = 2.0 * (c.k1 + r2 * (2.0 * c.k2 + 3.0 * c.k3 * r2))  # 2 d(radial)/d(r2)
    J = scale + dradial * P2 + (c.tang2 + c.tang2) * P
    Jxy = dradial * (P[0] * P[1]) + np.add.reduce(c.tang2[::-1] * P)
    return J, Jxy


def distort(P: FloatArray, c: Brown) -> FloatArray:
    """Undistorted normalized coordinates (2, n) -> distorted ones (2, n)."""
    return _terms(P, c)[3]


def distort_with_jacobian(P: FloatArray, c: Brown,
                          ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`distort` of P (2, n), and its derivative with respect to P: the diagonal
    ``(dxd/dx, dyd/dy)`` as (2, n) and ``dxd/dy = dyd/dx`` as (n,)."""
    P2, r2, scale, D = _terms(P, c)
    J, Jxy = _jacobian(P, P2, r2, scale, c)
    return D, J, Jxy


def coefficient_jacobian(P: FloatArray) -> FloatArray:
    """d(xd, yd) / d(k1, k2, p1, p2, k3) at P (2, n), as (2, 5, n). The model is linear in the
    coefficients, so this does not depend on them."""
    x, y = P
    xy2 = 2.0 * x * y
    r2 = x * x + y * y
    r4 = r2 * r2
    out = np.empty((2, 5, P.shape[1]))
    out[:, 0] = P * r2
    out[:, 1] = P * r4
    out[0, 2], out[1, 2] = xy2, r2 + 2.0 * y * y
    out[0, 3], out[1, 3] = r2 + 2.0 * x * x, xy2
    out[:, 4] = P * (r4 * r2)
    return out


def opencv_start(target: FloatArray, dist: FloatArray) -> FloatArray:
    """OpenCV's fixed-point undistortion of distorted normalized points (n, 2) with the
    coefficients ``dist`` (5,), a fixed 20 iterations: the starting point of :func:`undistort`,
    as (2, n)."""
    start = cv2.undistortPoints(target.reshape(-1, 1, 2), _EYE3, dist, criteria=_START_CRITERIA)
    return cast(FloatArray, start.reshape(-1, 2).T)


def undistort(target: FloatArray, P: FloatArray, c: Brown, max_iter: int, tol: float,
              ) -> tuple[FloatArray, FloatArray, FloatArray, bool]:
    """Newton's method on ``distort(P) = target``, vectorised over the points (columns).

    Parameters
    ----------
    target : (2, n) distorted normalized coordinates, one row per axis.
    P : (2, n) starting point (undistorted normalized coordinates), e.g. :func:`opencv_start`.
    c : the distortion, one set or one per point (the points may be different cameras').
    max_iter : Newton steps allowed after the starting point.
    tol : every point's residual must end below it (normalized units).

    Returns
    -------
    P (2, n), its r2 = x^2 + y^2 (n,), the residual F (2, n), and whether
    ``sum |F|^2 < tol^2`` (so every point converged); not finite stops at once. Whether the
    answer lies on the invertible side of the fold is the caller's check (:func:`safe_r2`,
    :func:`radial_slope`).
    """
    for step in range(max_iter + 1):
        P2, r2, scale, F = _terms(P, c)
        F -= target
        ss = float(np.vdot(F, F))
        converged = ss < tol * tol  # every point's residual < tol
        if converged or step == max_iter or not math.isfinite(ss):
            break
        J, Jxy = _jacobian(P, P2, r2, scale, c)
        P = P - (J[::-1] * F - Jxy * F[::-1]) / (J[0] * J[1] - Jxy * Jxy)
    return P, r2, F, converged


def radial_slope(k1: Any, k2: Any, k3: Any, r2: FloatArray) -> FloatArray:
    """``d(r_d)/dr`` along a ray (``r_d = r radial(r^2)``) at r2 = r^2: > 0 on the invertible
    side of the fold of the distortion polynomial."""
    return cast(FloatArray, 1.0 + r2 * (3.0 * k1 + r2 * (5.0 * k2 + r2 * 7.0 * k3)))


def safe_r2(k1: float, k2: float, k3: float) -> float:
    """An r2 = x^2 + y^2 below which the model is surely invertible (inf if everywhere).

    The slope ``d(r_d)/dr = 1 + 3 k1 r2 + 5 k2 r2^2 + 7 k3 r2^3`` is at least ``g(r2)``, the
    same polynomial without its positive terms, which falls monotonically from 1; found by
    bisection where ``g`` is still 1e-6, so rounding cannot flip the sign of the slope. Points
    inside need no slope evaluation; points outside get the exact one (:func:`radial_slope`).
    """
    c1, c2, c3 = min(0.0, 3.0 * k1), min(0.0, 5.0 * k2), min(0.0, 7.0 * k3)
    if not (c1 or c2 or c3):
        return math.inf

    def g(s: float) -> float:
        return 1.0 + s * (c1 + s * (c2 + s * c3))

    lo, hi = 0.0, 1.0
    while g(hi) > 1e-6:
        lo, hi = hi, 2.0 * hi
    for _ in range(64):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if g(mid) > 1e-6 else (lo, mid)
    return lo
