"""Stereo triangulation and epipolar geometry against OpenCV, geometry and Bouguet's stereo data."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import scipy.io

from vgripd.errors import ConvergenceError, DegenerateInputError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.stereo import StereoRig
from vgripd.geometry.transforms import make_transform, matrix_from_rotvec

LEFT = CameraModel(810.0, 805.0, 330.0, 245.0, skew=0.4, dist=(-0.25, 0.08, 0.001, -0.0005, 0.01))
RIGHT = CameraModel(790.0, 792.0, 318.0, 236.0, dist=(-0.22, 0.06, -0.0007, 0.0004, 0.0))
# Right camera 120 mm to the right of the left one, verged inwards by 4 degrees.
T_RIGHT_LEFT = make_transform(matrix_from_rotvec([0.01, np.radians(-4.0), 0.005]), [-120.0, 1.5, 3.0])
CV_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)


def _scene(n: int = 40, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, StereoRig]:
    rng = np.random.default_rng(seed)
    X = np.c_[rng.uniform(-120, 120, n), rng.uniform(-90, 90, n), rng.uniform(350, 900, n)]
    rig = StereoRig(LEFT, RIGHT, T_RIGHT_LEFT)
    px_l = LEFT.project(X)
    px_r = RIGHT.project(X @ T_RIGHT_LEFT[:3, :3].T + T_RIGHT_LEFT[:3, 3])
    return X, px_l, px_r, rig


def _cv_triangulate(rig: StereoRig, px_l: np.ndarray, px_r: np.ndarray) -> np.ndarray:
    """OpenCV's DLT on OpenCV-undistorted normalised points, P1 = [I|0], P2 = [R|t].

    undistortPoints stops after 5 iterations by default, which leaves up to ~0.1 mm of error
    at the image corners under Bouguet's k1 = -0.29; iterate to convergence instead.
    """
    nl = cv2.undistortPoints(px_l.reshape(-1, 1, 2), rig.left.K, rig.left.dist_array, criteria=CV_CRITERIA).reshape(-1, 2)
    nr = cv2.undistortPoints(px_r.reshape(-1, 1, 2), rig.right.K, rig.right.dist_array, criteria=CV_CRITERIA).reshape(-1, 2)
    P1 = np.hstack([np.eye(3), np.zeros((3, 1))])
    P2 = rig.T_right_left[:3]
    Xh = cv2.triangulatePoints(P1, P2, nl.T.copy(), nr.T.copy())
    return (Xh[:3] / Xh[3]).T


def test_noise_free_recovery_is_exact() -> None:
    X, px_l, px_r, rig = _scene()
    tri = rig.triangulate(px_l, px_r)
    err = np.abs(tri.points_mm - X).max()
    print(f"noise-free triangulation max abs error {err:.2e} mm, max gap {tri.gap_mm.max():.2e} mm")
    assert err < 1e-9
    assert tri.gap_mm.max() < 1e-9


def test_matches_opencv_triangulate_points() -> None:
    # Skew-free cameras: cv2.undistortPoints ignores K[0, 1].
    left = CameraModel(810.0, 805.0, 330.0, 245.0, dist=(-0.25, 0.08, 0.001, -0.0005, 0.01))
    rig = StereoRig(left, RIGHT, T_RIGHT_LEFT)
    X, _, px_r, _ = _scene()
    px_l = left.project(X)
    ours = rig.triangulate(px_l, px_r).points_mm
    theirs = _cv_triangulate(rig, px_l, px_r)
    err = np.abs(ours - theirs).max()
    print(f"vs cv2.triangulatePoints, noise-free: max abs difference {err:.2e} mm")
    assert err < 1e-9
    # With 0.3 px noise the midpoint (ours) and DLT (OpenCV) estimators differ, by much less
    # than either's error, and they are equally accurate.
    rng = np.random.default_rng(5)
    noisy_l = px_l + rng.normal(0, 0.3, px_l.shape)
    noisy_r = px_r + rng.normal(0, 0.3, px_r.shape)
    ours = rig.triangulate(noisy_l, noisy_r).points_mm
    theirs = _cv_triangulate(rig, noisy_l, noisy_r)
    diff = np.abs(ours - theirs).max()
    rms_ours = np.sqrt(((ours - X) ** 2).sum(axis=1).mean())
    rms_cv = np.sqrt(((theirs - X) ** 2).sum(axis=1).mean())
    print(f"vs cv2.triangulatePoints, 0.3 px noise: max abs difference {diff:.3f} mm; RMS error vs truth ours {rms_ours:.3f}, OpenCV {rms_cv:.3f} mm")
    assert diff < 0.05 * np.abs(ours - X).max()
    assert abs(rms_ours - rms_cv) < 0.02 * rms_cv


def test_gap_equals_the_distance_between_skew_rays() -> None:
    X, px_l, _, rig = _scene(n=10, seed=3)
    R, t = T_RIGHT_LEFT[:3, :3], T_RIGHT_LEFT[:3, 3]
    c_right = -R.T @ t
    offset_mm = 0.8
    # Move the right ray's target across the epipolar plane (normal = left ray x right ray).
    normal = np.cross(X, X - c_right)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    Y = X + offset_mm * normal
    px_r = RIGHT.project(Y @ R.T + t)
    tri = rig.triangulate(px_l, px_r)
    # Independent oracle: distance between two skew lines, |(p2 - p1) . (d1 x d2)| / |d1 x d2|.
    cross = np.cross(X, Y - c_right)
    expected = np.abs(cross @ c_right) / np.linalg.norm(cross, axis=1)
    err = np.abs(tri.gap_mm - expected).max()
    print(f"gap vs skew-line distance: max abs error {err:.2e} mm (offset {offset_mm} mm)")
    assert err < 1e-9
    np.testing.assert_allclose(tri.gap_mm, offset_mm, rtol=1e-3)


def test_epipolar_residuals_and_lines() -> None:
    X, px_l, px_r, rig = _scene()
    assert np.abs(rig.epipolar_residuals_px(px_l, px_r)).max() < 1e-8
    # Oracle: OpenCV's 8-point fundamental matrix from the same ideal pixels, and its epilines.
    ideal_l = rig.ideal_pixels(rig.left, px_l)
    ideal_r = rig.ideal_pixels(rig.right, px_r)
    F_cv, _ = cv2.findFundamentalMat(ideal_l, ideal_r, cv2.FM_8POINT)
    lines_cv = cv2.computeCorrespondEpilines(ideal_l.reshape(-1, 1, 2), 1, F_cv).reshape(-1, 3)
    lines = rig.epipolar_lines_right(px_l)
    # Compare where the lines run: distance (px) of points on OpenCV's lines from ours, u in 0..640.
    u = np.array([0.0, 320.0, 640.0])
    v = -(lines_cv[:, [0]] * u + lines_cv[:, [2]]) / lines_cv[:, [1]]
    err = np.abs(lines[:, [0]] * u + lines[:, [1]] * v + lines[:, [2]]).max()
    print(f"epipolar lines vs cv2.computeCorrespondEpilines: max distance {err:.2e} px")
    assert err < 1e-4
    # Shift the right points perpendicular to their epipolar line by a known amount.
    shift_px = 1.7
    moved = ideal_r + shift_px * lines[:, :2]
    moved_raw = RIGHT.project(np.c_[np.linalg.solve(RIGHT.K, np.c_[moved, np.ones(len(moved))].T).T])
    res = rig.epipolar_residuals_px(px_l, moved_raw)
    np.testing.assert_allclose(res[:, 1], shift_px, atol=1e-8)
    assert (res[:, 0] > 0.5).all()


def test_degenerate_inputs_raise() -> None:
    _, px_l, px_r, rig = _scene(n=6)
    bad = px_l.copy()
    bad[4, 1] = np.nan
    with pytest.raises(DegenerateInputError, match="point 4"):
        rig.triangulate(bad, px_r)
    with pytest.raises(DegenerateInputError, match="px_right has 5"):
        rig.triangulate(px_l, px_r[:5])
    with pytest.raises(DegenerateInputError, match="shape"):
        rig.triangulate(px_l[:, :1], px_r[:, :1])
    # A point at 1e12 mm: both rays are parallel.
    far = np.array([[1e10, 2e10, 1e12]])
    far_l = LEFT.project(far)
    far_r = RIGHT.project(far @ T_RIGHT_LEFT[:3, :3].T + T_RIGHT_LEFT[:3, 3])
    with pytest.raises(DegenerateInputError, match="point 2: .*parallel"):
        rig.triangulate(np.r_[px_l[:2], far_l], np.r_[px_r[:2], far_r])
    # Negative disparity: the rays diverge and only meet behind the cameras.
    swapped_r = px_r.copy()
    swapped_r[3] = RIGHT.project(np.array([[200.0, 0.0, 500.0]]))[0]
    swapped_l = px_l.copy()
    swapped_l[3] = LEFT.project(np.array([[-200.0, 0.0, 500.0]]))[0]
    with pytest.raises(DegenerateInputError, match="point 3: rays meet behind"):
        rig.triangulate(swapped_l, swapped_r)
    with pytest.raises(DegenerateInputError, match="T_right_left"):
        StereoRig(LEFT, RIGHT, np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(DegenerateInputError, match="zero baseline"):
        StereoRig(LEFT, RIGHT, np.eye(4))


# ----------------------------------------------------------------------------- Bouguet data
def _bouguet_rig() -> StereoRig:
    """Published optimised stereo parameters (PROVENANCE.md, PDF page 2)."""
    left = CameraModel(533.52331, 533.52699, 341.60376, 235.19287, dist=(-0.28838, 0.09714, 0.00109, -0.00030, 0.0))
    right = CameraModel(536.81377, 536.47649, 326.28657, 250.10121, dist=(-0.28943, 0.10690, -0.00059, 0.00014, 0.0))
    T = make_transform(matrix_from_rotvec([0.00669, 0.00452, -0.00350]), [-99.80198, 1.12443, 0.05041])
    return StereoRig(left, right, T)


def _load(path: Path) -> dict[str, np.ndarray]:
    return scipy.io.loadmat(str(path))


def test_bouguet_stereo_grid_spacing(datasets: Path) -> None:
    root = datasets / "bouguet_stereo_example"
    mat_l = _load(root / "Calib_Results_left.mat")
    mat_r = _load(root / "Calib_Results_right.mat")
    rig = _bouguet_rig()
    spacing, epi, cv_diff = [], [], []
    for i in range(1, 15):
        px_l = mat_l[f"x_{i}"].T.astype(float)
        px_r = mat_r[f"x_{i}"].T.astype(float)
        grid = mat_l[f"X_{i}"].T.astype(float)  # stored as integers: convert before subtracting
        tri = rig.triangulate(px_l, px_r)
        d_grid = np.linalg.norm(grid[:, None] - grid[None], axis=2)
        ii, jj = np.nonzero(np.triu(np.isclose(d_grid, 30.0)))
        spacing.append(np.linalg.norm(tri.points_mm[ii] - tri.points_mm[jj], axis=1))
        epi.append(rig.epipolar_residuals_px(px_l, px_r))
        cv_diff.append(np.abs(tri.points_mm - _cv_triangulate(rig, px_l, px_r)).max())
        if i == 1:
            z = tri.points_mm[:, 2]
            # PROVENANCE: pair 1 lies at Z = 414-502 mm
            assert z.min() > 410
            assert z.max() < 505
    d = np.concatenate(spacing)
    e = np.concatenate(epi)
    print(
        f"Bouguet: {d.size} adjacent-corner distances {d.mean():.4f} +- {d.std():.4f} mm "
        f"(reference 30.007 +- 0.196); epipolar residual median {np.median(e):.3f} px, "
        f"max {e.max():.3f} px; max |ours - cv2.triangulatePoints| {max(cv_diff):.2e} mm"
    )
    assert d.size == 14 * (8 * 6 + 9 * 5)
    assert abs(d.mean() - 30.0) < 0.05
    assert abs(d.mean() - 30.007) < 0.002
    assert d.std() < 0.3
    assert np.median(e) < 0.3
    assert e.max() < 1.5
    assert max(cv_diff) < 0.2  # midpoint vs DLT on real corners (~0.1 px noise, Z ~ 450 mm)


# ----------------------------------------------------------------------------- pair fast path
def test_triangulate_matches_per_point_least_squares() -> None:
    # triangulate solves both images in one Newton run and eq. (14) through tabulated maps;
    # oracle: each camera's own undistort, then numpy's lstsq per point on z1 d - z2 e = c.
    X, px_l, px_r, rig = _scene(30, seed=5)
    rng = np.random.default_rng(6)
    px_l = px_l + rng.normal(0, 0.5, px_l.shape)
    px_r = px_r + rng.normal(0, 0.5, px_r.shape)
    tri = rig.triangulate(px_l, px_r)
    R, t = T_RIGHT_LEFT[:3, :3], T_RIGHT_LEFT[:3, 3]
    c = -R.T @ t
    nl, nr = LEFT.undistort(px_l), RIGHT.undistort(px_r)
    for i in range(len(X)):
        d = np.r_[nl[i], 1.0]
        e = R.T @ np.r_[nr[i], 1.0]
        (z1, z2), *_ = np.linalg.lstsq(np.c_[d, -e], c, rcond=None)
        p_left, p_right = z1 * d, z2 * e + c
        np.testing.assert_allclose(tri.points_mm[i], 0.5 * (p_left + p_right), rtol=0, atol=1e-9)
        assert tri.gap_mm[i] == pytest.approx(np.linalg.norm(p_left - p_right), abs=1e-9)
    assert tri.gap_mm.max() > 0.05  # the noise opens real gaps: the gap formula is exercised
    assert tri.points_mm.flags.c_contiguous
    assert tri.points_mm.shape == (30, 3)
    # A single point as a (2,) pixel takes the general path and agrees.
    one = rig.triangulate(px_l[4], px_r[4])
    np.testing.assert_allclose(one.points_mm[0], tri.points_mm[4], rtol=0, atol=1e-9)


def test_pair_path_errors_name_the_image_and_point() -> None:
    _, px_l, px_r, rig = _scene(n=6)
    bad = px_r.copy()
    bad[3, 0] = np.nan
    with pytest.raises(DegenerateInputError, match="px_right: undistort: point 3 is not finite"):
        rig.triangulate(px_l, bad)
    # A right camera whose model folds at x_d = 0.385: a pixel beyond has no inverse.
    folding = CameraModel(500.0, 500.0, 320.0, 240.0, dist=(-1.0, 0.0, 0.0, 0.0, 0.0))
    rig2 = StereoRig(LEFT, folding, T_RIGHT_LEFT)
    px = np.array([[300.0, 240.0], [320.0, 250.0], [320.0 + 0.6 * 500, 240.0]])
    with pytest.raises(ConvergenceError, match=r"point 2 .*fold"):
        rig2.triangulate(px, px)


def test_empty_input_gives_empty_triangulation() -> None:
    _, _, _, rig = _scene(n=3)
    tri = rig.triangulate(np.zeros((0, 2)), np.zeros((0, 2)))
    assert tri.points_mm.shape == (0, 3)
    assert tri.gap_mm.shape == (0,)
