"""CameraModel against OpenCV (projectPoints, undistortPoints) and Bouguet's own calibration.

Max abs errors are printed with an ORACLE prefix (see them with ``pytest -s``).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import scipy.io

from vgripd.errors import ConvergenceError, DegenerateInputError
from vgripd.geometry.camera_model import CameraModel

# Strong barrel distortion with all five terms, like a 4-6 mm lens on a 2/3" sensor (k3 > 0
# keeps r_d(r) monotonic out to the image corners, i.e. the model is invertible there).
STRONG = CameraModel(fx=820.0, fy=815.0, cx=645.3, cy=478.9, dist=(-0.32, 0.14, 1.2e-3, -8e-4, 0.02),
                     width=1280, height=960)


def _scene(rng: np.random.Generator, n: int = 500) -> np.ndarray:
    """Points in front of the camera filling roughly the field of view of STRONG (normalized |x| < 0.8)."""
    z = rng.uniform(300.0, 2000.0, n)
    xy = rng.uniform(-0.75, 0.75, (n, 2)) * z[:, None]
    return np.column_stack((xy, z))


def _cv_project(cam: CameraModel, P: np.ndarray) -> np.ndarray:
    K, d = cam.to_opencv()
    out, _ = cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, d)
    return out.reshape(-1, 2)


def test_project_matches_opencv_strong_distortion() -> None:
    P = _scene(np.random.default_rng(1))
    err = np.abs(STRONG.project(P) - _cv_project(STRONG, P)).max()
    print(f"ORACLE project vs cv2.projectPoints (strong distortion, 500 pts): max abs {err:.3g} px")
    assert err < 1e-9


def test_opencv_projectpoints_ignores_skew_so_skew_is_checked_by_bouguets_formula() -> None:
    cam = CameraModel(fx=533.0, fy=533.2, cx=341.6, cy=234.3, skew=4.0, dist=(-0.29, 0.10, 1e-3, -3e-4, 0.0))
    P = _scene(np.random.default_rng(2), 50)
    no_skew = CameraModel(cam.fx, cam.fy, cam.cx, cam.cy, 0.0, cam.dist)
    # OpenCV's projectPoints reads only fx, fy, cx, cy from K: K[0, 1] changes nothing.
    assert np.array_equal(_cv_project(cam, P), _cv_project(no_skew, P))
    # Bouguet: x_px = fc1 (xd1 + alpha_c xd2) + cc1 with alpha_c = skew / fc1, and yd from v.
    ref = _cv_project(no_skew, P)
    yd = (ref[:, 1] - cam.cy) / cam.fy
    ref[:, 0] += cam.fx * (cam.skew / cam.fx) * yd
    err = np.abs(cam.project(P) - ref).max()
    print(f"ORACLE project with skew vs Bouguet's skew formula on cv2 output: max abs {err:.3g} px")
    assert err < 1e-9
    # ... and undistort removes the skew again, which cv2.undistortPoints would not (it ignores K[0, 1]).
    px = cam.project(P)
    xn = cam.undistort(px)
    assert np.abs(xn - P[:, :2] / P[:, 2:]).max() < 1e-12
    cv_skew = cv2.undistortPoints(px.reshape(-1, 1, 2), cam.K, cam.dist_array)
    assert np.array_equal(cv_skew, cv2.undistortPoints(px.reshape(-1, 1, 2), no_skew.K, cam.dist_array))


def test_undistort_matches_opencv_iterated_to_convergence() -> None:
    P = _scene(np.random.default_rng(3))
    px = STRONG.project(P)
    K, d = STRONG.to_opencv()
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 1000, 1e-15)
    ref = cv2.undistortPoints(px.reshape(-1, 1, 2), K, d, criteria=criteria).reshape(-1, 2)
    ours = STRONG.undistort(px)
    err = np.abs(ours - ref).max()
    truth_err = np.abs(ours - P[:, :2] / P[:, 2:]).max()
    print(f"ORACLE undistort vs cv2.undistortPoints(1000 it): max abs {err:.3g} (normalized), "
          f"{err * STRONG.fx:.3g} px; vs truth {truth_err:.3g}")
    assert err < 1e-11
    assert truth_err < 1e-12


def test_round_trip_pixels_undistort_project_over_whole_image() -> None:
    u, v = np.meshgrid(np.linspace(0, STRONG.width - 1, 41), np.linspace(0, STRONG.height - 1, 31))
    px = np.column_stack((u.ravel(), v.ravel()))
    xn = STRONG.undistort(px)
    back = STRONG.project(np.column_stack((xn, np.ones(len(xn)))))
    err = np.abs(back - px).max()
    print(f"ORACLE round trip px -> undistort -> project (1271 px incl. corners): max abs {err:.3g} px")
    assert err < 1e-8


def test_newton_repairs_points_where_the_fixed_point_iteration_is_slow() -> None:
    # k1 = -0.5 near the fold: OpenCV's fixed-point iteration contracts only by ~0.7 per step
    # there, so 20 steps (our starting point) leave ~1e-4; Newton must finish the job.
    cam = CameraModel(fx=600.0, fy=600.0, cx=320.0, cy=240.0, dist=(-0.5, 0.0, 0.0, 0.0, 0.0))
    xn = np.array([[0.7, 0.2], [-0.5, -0.5], [0.1, 0.05]])
    px = cam.project(np.column_stack((xn, np.ones(3))))
    fixed_point = cv2.undistortPoints(px.reshape(-1, 1, 2), cam.K, cam.dist_array,
                                      criteria=(cv2.TERM_CRITERIA_COUNT, 20, 0.0)).reshape(-1, 2)
    assert np.abs(fixed_point - xn).max() > 1e-6
    err = np.abs(cam.undistort(px) - xn).max()
    print(f"ORACLE undistort near the fold (k1=-0.5) vs truth: max abs {err:.3g} "
          f"(cv2 20 it: {np.abs(fixed_point - xn).max():.3g})")
    assert err < 1e-12


def test_point_beyond_the_fold_raises_convergence_error_naming_it() -> None:
    # r_d = r (1 - r^2) never exceeds 2 / (3 sqrt 3) = 0.385: x_d = 0.6 has no valid inverse.
    cam = CameraModel(fx=500.0, fy=500.0, cx=320.0, cy=240.0, dist=(-1.0, 0.0, 0.0, 0.0, 0.0))
    px = np.array([[320.0, 240.0], [320.0 + 0.1 * 500, 240.0], [320.0 + 0.6 * 500, 240.0]])
    with pytest.raises(ConvergenceError, match=r"point 2 .*fold.*px"):
        cam.undistort(px)
    assert cam.undistort(px[:2]).shape == (2, 2)


def test_too_few_iterations_raise_convergence_error() -> None:
    cam = CameraModel(fx=600.0, fy=600.0, cx=320.0, cy=240.0, dist=(-0.5, 0.0, 0.0, 0.0, 0.0))
    px = cam.project(np.array([[0.7, 0.2, 1.0]]))
    with pytest.raises(ConvergenceError, match="point 0 did not converge"):
        cam.undistort(px, max_iter=0)


def test_project_rejects_points_behind_and_nan_naming_the_index() -> None:
    with pytest.raises(DegenerateInputError, match="point 1 .*Z = 0"):
        STRONG.project([[0, 0, 100.0], [1, 1, 0.0]])
    with pytest.raises(DegenerateInputError, match="point 2 is not finite"):
        STRONG.project([[0, 0, 100.0], [1, 1, 5.0], [np.nan, 0, 1.0]])
    with pytest.raises(DegenerateInputError, match=r"shape \(n, 3\)"):
        STRONG.project(np.zeros((4, 2)))
    with pytest.raises(DegenerateInputError, match="point 0 is not finite"):
        STRONG.undistort([[np.inf, 3.0]])


def test_rays_are_unit_and_point_at_the_scene_points() -> None:
    P = _scene(np.random.default_rng(4), 100)
    r = STRONG.rays(STRONG.project(P))
    assert np.allclose(np.linalg.norm(r, axis=1), 1.0, atol=1e-15)
    cosines = np.sum(r * P / np.linalg.norm(P, axis=1, keepdims=True), axis=1)
    assert np.abs(1.0 - cosines).max() < 1e-13


def test_empty_and_single_point_inputs() -> None:
    assert STRONG.project(np.zeros((0, 3))).shape == (0, 2)
    assert STRONG.undistort(np.zeros((0, 2))).shape == (0, 2)
    assert STRONG.rays(np.zeros((0, 2))).shape == (0, 3)
    assert STRONG.undistort([645.3, 478.9]).shape == (1, 2)
    assert np.abs(STRONG.undistort([645.3, 478.9])).max() < 1e-15


def test_opencv_round_trip_and_invalid_parameters() -> None:
    K, d = STRONG.to_opencv()
    assert CameraModel.from_opencv(K, d, (1280, 960)) == STRONG
    assert CameraModel.from_opencv(K, d[:4]).dist[4] == 0.0
    eight = np.r_[d, 0.0, 0.0, 0.0]
    assert CameraModel.from_opencv(K, eight).dist == STRONG.dist
    with pytest.raises(DegenerateInputError, match="rational"):
        CameraModel.from_opencv(K, np.r_[d, 0.1, 0.0, 0.0])
    with pytest.raises(DegenerateInputError, match="focal"):
        CameraModel(fx=0.0, fy=1.0, cx=0.0, cy=0.0)
    with pytest.raises(DegenerateInputError, match="cx is not finite"):
        CameraModel(fx=1.0, fy=1.0, cx=np.nan, cy=0.0)
    with pytest.raises(DegenerateInputError, match="5 finite"):
        CameraModel(fx=1.0, fy=1.0, cx=0.0, cy=0.0, dist=(0.1, 0.2))  # type: ignore[arg-type]


@pytest.mark.parametrize("side", ["left", "right"])
def test_bouguet_toolbox_reprojection_reproduces_its_corners(datasets, side: str) -> None:
    """Bouguet's own result: fc, cc, kc, alpha_c and per image omc_i, Tc_i, X_i, x_i.

    Reprojecting X_i with our model must give residuals against his x_i with zero mean and the
    standard deviation he stored (err_std); this checks our kc order against the toolbox itself.
    """
    m = scipy.io.loadmat(datasets / "bouguet_stereo_example" / f"Calib_Results_{side}.mat")
    fc, cc, kc = m["fc"].ravel(), m["cc"].ravel(), m["kc"].ravel()
    cam = CameraModel(fx=fc[0], fy=fc[1], cx=cc[0], cy=cc[1], skew=fc[0] * float(m["alpha_c"][0, 0]),
                      dist=tuple(kc), width=int(m["nx"][0, 0]), height=int(m["ny"][0, 0]))
    residuals, cv_err = [], 0.0
    for i in range(1, int(m["n_ima"][0, 0]) + 1):
        R, _ = cv2.Rodrigues(m[f"omc_{i}"].ravel())
        Xc = m[f"X_{i}"].T @ R.T + m[f"Tc_{i}"].ravel()
        ours = cam.project(Xc)
        residuals.append(m[f"x_{i}"].T - ours)
        cv_err = max(cv_err, float(np.abs(ours - _cv_project(cam, Xc)).max()))
    res = np.vstack(residuals)
    std = res.std(axis=0, ddof=1)
    err_std = m["err_std"].ravel()
    print(f"ORACLE Bouguet {side}: residual std {std} px vs err_std {err_std}; mean {res.mean(axis=0)}; "
          f"project vs cv2 on the same points max abs {cv_err:.3g} px")
    assert np.abs(std - err_std).max() < 1e-6
    assert np.abs(res.mean(axis=0)).max() < 0.02
    assert cv_err < 1e-9


def test_safe_radius_lies_inside_the_fold() -> None:
    # undistort skips the exact slope test for points with r2 below _safe_r2: it must be a true
    # bound. Oracle: the smallest positive root of the slope polynomial (numpy's roots), and
    # the slope itself on a fine grid below the bound.
    for k1, k2, k3 in [(-0.25, 0.08, 0.01), (-0.32, 0.14, 0.02), (-0.5, 0.0, 0.0), (-1.0, 0.0, 0.0),
                       (0.1, -0.3, 0.05), (-0.2, -0.1, -0.05), (0.2, 0.1, 0.0)]:
        cam = CameraModel(600.0, 600.0, 320.0, 240.0, dist=(k1, k2, 0.0, 0.0, k3))
        safe = cam._inverse.r2_safe
        roots = np.roots([7 * k3, 5 * k2, 3 * k1, 1.0])
        real = roots[(np.abs(roots.imag) < 1e-12) & (roots.real > 0)].real
        if real.size:
            assert safe < real.min()
        s = np.linspace(0.0, safe if np.isfinite(safe) else 10.0, 10001)
        assert (1 + s * (3 * k1 + s * (5 * k2 + s * 7 * k3))).min() > 0
    assert np.isinf(CameraModel(600.0, 600.0, 320.0, 240.0, dist=(0.2, 0.1, 0.0, 0.0, 0.0))._inverse.r2_safe)


def test_undistort_names_a_nan_found_after_the_fact() -> None:
    # Finiteness is checked only when Newton fails (NaN propagates there): the error is the same.
    px = np.array([[100.0, 100.0], [200.0, 300.0], [np.nan, 5.0], [400.0, 50.0]])
    with pytest.raises(DegenerateInputError, match="undistort: point 2 is not finite"):
        STRONG.undistort(px)
    with pytest.raises(DegenerateInputError, match=r"undistort: expected shape \(n, 2\)"):
        STRONG.undistort(np.zeros((3, 3)))
