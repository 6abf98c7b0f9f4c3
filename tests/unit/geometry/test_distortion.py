"""The one Brown-Conrady implementation (vgripd.geometry.distortion) against OpenCV.

Oracles: ``cv2.projectPoints`` with an identity camera matrix and the points on the plane Z = 1
(it then returns the distorted normalized coordinates, and its Jacobian's tvec and distortion
columns are the derivatives with respect to (x, y) and to the coefficients), and
``cv2.undistortPoints`` iterated to convergence. Degenerate inputs: points at the principal
point, large radii, all coefficients zero, one coefficient set per point.
"""

from __future__ import annotations

import re

import cv2
import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st

from tests.conftest import REPO
from vgripd.geometry.camera_model import CameraModel, project_with_jacobian
from vgripd.geometry.distortion import (
    Brown,
    coefficient_jacobian,
    distort,
    distort_with_jacobian,
    opencv_start,
    radial_slope,
    safe_r2,
    undistort,
)

ZERO = (0.0, 0.0, 0.0, 0.0, 0.0)
# Coefficients of real lenses and then some: (k1, k2, p1, p2, k3).
COEFFS = st.tuples(st.floats(-0.6, 0.6), st.floats(-0.5, 0.5), st.floats(-0.02, 0.02),
                   st.floats(-0.02, 0.02), st.floats(-0.3, 0.3))
# Normalized radii up to 2.5 (a 136 deg field of view), the principal point included.
POINTS = st.lists(st.tuples(st.floats(-2.5, 2.5), st.floats(-2.5, 2.5)), min_size=1,
                  max_size=30)
CV_CONVERGED = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 2000, 1e-16)


def opencv_distort(xy: np.ndarray, dist: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's distorted normalized points (n, 2) of ``xy`` (n, 2) and its Jacobian (2n, 15)
    (rvec 3, tvec 3, fx fy cx cy, k1 k2 p1 p2 k3)."""
    pts = np.column_stack([xy, np.ones(len(xy))])
    out, jac = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), np.eye(3),
                                 np.asarray(dist, dtype=np.float64))
    return out.reshape(-1, 2), jac


def close(ours: np.ndarray, ref: np.ndarray, rel: float = 1e-12) -> None:
    scale = 1.0 + np.abs(ref)
    err = np.abs(ours - ref) / scale
    assert err.max(initial=0.0) <= rel, f"max relative difference {err.max():.3g}"


@settings(max_examples=200, deadline=None)
@given(dist=COEFFS, pts=POINTS)
@example(dist=ZERO, pts=[(0.0, 0.0), (2.5, -2.5)])
@example(dist=(0.3, -0.2, 0.01, -0.01, 0.1), pts=[(0.0, 0.0)])
@example(dist=(-0.6, 0.5, 0.02, 0.02, -0.3), pts=[(2.5, 2.5), (-2.5, 0.0), (0.0, -2.5)])
def test_forward_and_jacobians_equal_opencv(dist, pts):
    xy = np.asarray(pts, dtype=np.float64)
    ref, jac = opencv_distort(xy, dist)
    c = Brown.of(dist)
    close(distort(xy.T, c).T, ref)
    D, J, Jxy = distort_with_jacobian(xy.T, c)
    close(D.T, ref)
    # With Z = 1 and K = I, d(xd, yd)/d(x, y) is OpenCV's column for tvec x and tvec y.
    d_dxy = jac[:, 3:5].reshape(-1, 2, 2)  # per point [[dxd/dx, dxd/dy], [dyd/dx, dyd/dy]]
    ours = np.stack([np.stack([J[0], Jxy], axis=1), np.stack([Jxy, J[1]], axis=1)], axis=1)
    close(ours, d_dxy, 1e-10)
    # d(xd, yd)/d(k1, k2, p1, p2, k3): OpenCV's last five columns (fx = fy = 1).
    G = coefficient_jacobian(xy.T)  # (2, 5, n)
    close(np.moveaxis(G, 2, 0), jac[:, 10:15].reshape(-1, 2, 5), 1e-10)


@settings(max_examples=200, deadline=None)
@given(dist=COEFFS, pts=POINTS)
@example(dist=ZERO, pts=[(0.0, 0.0), (1.0, 1.0)])
@example(dist=(-0.4, 0.2, 0.01, -0.01, -0.05), pts=[(0.0, 0.0)])
@example(dist=(0.6, 0.5, 0.0, 0.0, 0.3), pts=[(0.8, 0.8), (2.5, 2.5)])
@example(dist=(-0.5, 0.0, 0.0, 0.0, 0.0), pts=[(0.8, 0.0), (0.0, -0.81)])
def test_undistort_inverts_distort_and_equals_opencv(dist, pts):
    """Newton from OpenCV's start recovers every point inside the radius where the model is
    surely invertible (``safe_r2``) whose image lies within a 136 deg field; where OpenCV's own
    iteration converges, both agree."""
    k1, k2, _, _, k3 = dist
    xy = np.asarray(pts, dtype=np.float64)
    c = Brown.of(dist)
    safe = safe_r2(k1, k2, k3)
    xy = xy[(xy * xy).sum(axis=1) < safe]
    target = distort(xy.T, c).T
    keep = (target * target).sum(axis=1) <= 2.5**2 * 2
    xy, target = xy[keep], target[keep]
    if not len(xy):
        return
    P, r2, F, converged = undistort(target.T, opencv_start(target, np.asarray(dist)), c, 20,
                                    1e-12)
    assert converged, f"residual {np.abs(F).max():.3g}"
    np.testing.assert_allclose(r2, (P * P).sum(axis=0))
    # The inverse is unique on this side of the fold (CameraModel refuses answers beyond it).
    inside = r2 < safe
    np.testing.assert_allclose(P.T[inside], xy[inside], rtol=0, atol=1e-9)
    cv = cv2.undistortPoints(target.reshape(-1, 1, 2), np.eye(3), np.asarray(dist),
                             criteria=CV_CONVERGED).reshape(-1, 2)
    back, _ = opencv_distort(cv, dist)
    cv_done = np.abs(back - target).max(axis=1) < 1e-13  # OpenCV converged on these
    np.testing.assert_allclose(P.T[cv_done & inside], cv[cv_done & inside], rtol=0, atol=1e-9)


def test_degenerate_inputs() -> None:
    """The principal point stays put with any coefficients and has the identity as derivative
    (tangential terms aside); zero coefficients are the identity everywhere."""
    c = Brown.of((-0.3, 0.2, 0.01, -0.02, 0.05))
    origin = np.zeros((2, 1))
    D, J, Jxy = distort_with_jacobian(origin, c)
    assert np.array_equal(D, origin)
    np.testing.assert_allclose([J[0, 0], J[1, 0], Jxy[0]], [1.0, 1.0, 0.0])
    P, _, _, converged = undistort(origin, origin.copy(), c, 20, 1e-12)
    assert converged
    assert np.array_equal(P, origin)
    assert np.array_equal(coefficient_jacobian(origin), np.zeros((2, 5, 1)))
    far = np.array([[0.0, 40.0, -1e3], [0.0, -25.0, 7.0]])
    none = Brown.of(ZERO)
    assert np.array_equal(distort(far, none), far)
    assert safe_r2(0.0, 0.0, 0.0) == np.inf
    assert safe_r2(0.2, 0.1, 0.01) == np.inf  # only positive terms: invertible everywhere
    s = safe_r2(-0.5, 0.0, 0.0)  # slope 1 - 1.5 r2 vanishes at r2 = 2/3
    assert 0.0 < s < 2.0 / 3.0
    assert radial_slope(-0.5, 0.0, 0.0, np.array(s)) > 0
    # Large radii: OpenCV and this model agree in relative terms where values reach 1e7.
    big = np.array([[30.0, -40.0], [-50.0, 0.0]])
    ref, _ = opencv_distort(big, (0.1, 0.01, 0.001, 0.002, 0.001))
    close(distort(big.T, Brown.of((0.1, 0.01, 0.001, 0.002, 0.001))).T, ref)


@settings(max_examples=50, deadline=None)
@given(a=COEFFS, b=COEFFS, pts=POINTS)
def test_per_point_and_stacked_coefficients_equal_one_set_each(a, b, pts):
    """One coefficient set per point (calibrations) or two cameras stacked (a stereo pair)
    give exactly what each camera's own set gives."""
    xy = np.asarray(pts, dtype=np.float64).T
    n = xy.shape[1]
    both = np.concatenate([xy, xy], axis=1)
    want = np.concatenate([distort(xy, Brown.of(a)), distort(xy, Brown.of(b))], axis=1)
    per = np.array([a] * n + [b] * n).T  # (5, 2n): k1 k2 p1 p2 k3 rows
    np.testing.assert_allclose(distort(both, Brown.per_point(*per)), want, rtol=1e-15, atol=0)
    np.testing.assert_allclose(distort(both, Brown.stacked(Brown.of(a), Brown.of(b), n)), want,
                               rtol=1e-15, atol=0)


@settings(max_examples=60, deadline=None)
@given(dist=COEFFS, skew=st.floats(-2.0, 2.0), seed=st.integers(0, 2**16))
def test_camera_projection_and_its_derivative_equal_opencv(dist, skew, seed):
    """CameraModel.project and project_with_jacobian (pinhole + this distortion) against
    cv2.projectPoints; OpenCV ignores K's skew, so skew * yd is added to its u here."""
    cam = CameraModel(1500.0, 1490.0, 640.0, 480.0, skew=skew, dist=dist)
    pts = np.random.default_rng(seed).uniform([-400, -400, 300], [400, 400, 1500], (25, 3))
    K = cam.K.copy()
    K[0, 1] = 0.0
    cv, jac = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, cam.dist_array)
    cv = cv.reshape(-1, 2)
    cv[:, 0] += skew * (cv[:, 1] - cam.cy) / cam.fy
    np.testing.assert_allclose(cam.project(pts), cv, rtol=1e-12, atol=1e-8)
    px, J = project_with_jacobian(cam, pts)
    np.testing.assert_allclose(px, cam.project(pts), rtol=0, atol=1e-9)
    # d px / d P = d px / d tvec (rvec = 0): OpenCV's tvec columns, skew added to row u.
    d_tvec = jac[:, 3:6].reshape(-1, 2, 3)
    d_tvec[:, 0] += skew / cam.fy * d_tvec[:, 1]
    np.testing.assert_allclose(J, d_tvec, rtol=1e-9, atol=1e-9)


# The distortion polynomial, as it reads when written out by hand: k1 + r2 (k2 + r2 k3) in any
# spelling, or a tangential term p1 (r2 + 2 y^2) / 2 p1 x y.
HAND_WRITTEN = re.compile(r"k1\s*\+\s*r2\s*\*|r2\s*\*\s*\(\s*k1|\bp[12]\s*\*\s*\(\s*r2|"
                          r"2(?:\.0)?\s*\*\s*p[12]\s*\*")


def test_the_model_is_written_once() -> None:
    """Only vgripd/geometry/distortion.py spells out the Brown polynomial; every other module
    (camera model, several-view geometry, calibrations, drivers) calls it."""
    here = REPO / "vgripd" / "geometry" / "distortion.py"
    found = [f"{path.relative_to(REPO)}:{i}: {line.strip()}"
             for path in sorted([*(REPO / "vgripd").rglob("*.py"), *(REPO / "drivers").rglob("*.py")])
             if path != here
             for i, line in enumerate(path.read_text().splitlines(), 1)
             if HAND_WRITTEN.search(line.split("#")[0])]
    assert not found, "Brown distortion written outside geometry/distortion.py:\n" + \
        "\n".join(found)
    assert HAND_WRITTEN.search(here.read_text()), "the pattern no longer matches the model"
