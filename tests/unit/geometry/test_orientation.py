"""Horn's absolute orientation and PnP against SVD/Kabsch, scipy, OpenCV and Bouguet's poses."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import scipy.io
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from vgripd.errors import DegenerateInputError, GeometryError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.orientation import horn, horn_robust, pnp
from vgripd.geometry.transforms import make_transform, matrix_from_rotvec, rotvec_from_matrix

RNG_SEED = 11


def _kabsch(a: np.ndarray, b: np.ndarray, w: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Independent oracle: weighted SVD (Kabsch/Umeyama without scale), b ~ R a + t."""
    w = np.ones(len(a)) if w is None else w
    w = w / w.sum()
    ca, cb = w @ a, w @ b
    H = ((a - ca) * w[:, None]).T @ (b - cb)
    U, _, Vt = np.linalg.svd(H)
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ S @ U.T
    return R, cb - R @ ca


def _random_pose(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    return Rotation.random(random_state=rng).as_matrix(), rng.uniform(-500, 500, 3)


def test_horn_matches_kabsch_and_scipy_on_noisy_points() -> None:
    rng = np.random.default_rng(RNG_SEED)
    worst = 0.0
    for _ in range(20):
        R, t = _random_pose(rng)
        a = rng.uniform(-100, 100, (12, 3))
        b = a @ R.T + t + rng.normal(0, 0.5, a.shape)
        w = rng.uniform(0.1, 2.0, 12)
        for weights in (None, w):
            res = horn(a, b, weights)
            R_k, t_k = _kabsch(a, b, weights)
            worst = max(worst, np.abs(res.T_to_from[:3, :3] - R_k).max(), np.abs(res.T_to_from[:3, 3] - t_k).max())
            ww = np.ones(12) if weights is None else weights
            ca, cb = (ww @ a) / ww.sum(), (ww @ b) / ww.sum()
            rot, _ = Rotation.align_vectors(b - cb, a - ca, weights=ww)
            worst = max(worst, np.abs(res.T_to_from[:3, :3] - rot.as_matrix()).max())
            np.testing.assert_allclose(res.residuals_mm, np.linalg.norm(a @ R_k.T + t_k - b, axis=1), atol=1e-9)
    print(f"Horn vs Kabsch/scipy (0.5 mm noise, with and without weights): max abs difference {worst:.2e}")
    assert worst < 1e-9


finite = st.floats(-300.0, 300.0, allow_nan=False, allow_infinity=False)


@settings(max_examples=200, deadline=None)
@given(
    pts=st.integers(3, 15).flatmap(lambda n: arrays(np.float64, (n, 3), elements=finite)),
    quat=arrays(np.float64, 4, elements=st.floats(-1, 1)),
    t=arrays(np.float64, 3, elements=st.floats(-2000, 2000)),
)
def test_horn_round_trip(pts: np.ndarray, quat: np.ndarray, t: np.ndarray) -> None:
    assume(np.linalg.norm(quat) > 0.1)
    s = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
    assume(s[1] > 0.05 * s[0])
    assume(s[0] > 1.0)
    R = Rotation.from_quat(quat).as_matrix()
    res = horn(pts, pts @ R.T + t)
    np.testing.assert_allclose(res.T_to_from[:3, :3], R, atol=1e-9)
    np.testing.assert_allclose(res.T_to_from[:3, 3], t, atol=1e-9)
    assert res.rms_mm < 1e-9


def test_horn_weights() -> None:
    rng = np.random.default_rng(RNG_SEED + 1)
    R, t = _random_pose(rng)
    a = rng.uniform(-100, 100, (8, 3))
    b = a @ R.T + t
    b[5, 0] += 40.0  # a wrong point: zero weight must ignore it exactly
    w = np.ones(8)
    w[5] = 0.0
    res = horn(a, b, w)
    np.testing.assert_allclose(res.T_to_from, make_transform(R, t), atol=1e-9)
    assert res.residuals_mm[5] == pytest.approx(40.0)
    # Scaling all weights changes nothing.
    np.testing.assert_allclose(horn(a, b, 7.0 * w).T_to_from, res.T_to_from, atol=1e-12)
    robust = horn_robust(a, b, w, threshold_mm=0.5)
    assert robust.dropped == ()  # weight 0 means "not used", not "wrong"
    assert not robust.inliers[5]


def _spread_points(rng: np.random.Generator, n: int) -> np.ndarray:
    """n points in a 200 mm cube whose every (n - 1)-subset is far from collinear."""
    while True:
        a = rng.uniform(-100, 100, (n, 3))
        if all(
            (lambda s: s[1] > 0.3 * s[0])(np.linalg.svd(np.delete(a, k, 0) - np.delete(a, k, 0).mean(0), compute_uv=False))
            for k in range(n)
        ):
            return a


@pytest.mark.parametrize("n", [4, 5, 8, 12])
def test_horn_robust_finds_one_wrong_correspondence(n: int) -> None:
    rng = np.random.default_rng(RNG_SEED + n)
    for trial in range(10):
        R, t = _random_pose(rng)
        a = _spread_points(rng, n)
        b = a @ R.T + t + rng.normal(0, 0.05, a.shape)
        bad = trial % n
        b[bad] += rng.normal(0, 1, 3) / np.sqrt(3) * 15.0 + 5.0  # a wrong feature, >= ~5 mm off
        res = horn_robust(a, b, threshold_mm=0.5)
        assert res.dropped == (bad,)
        assert res.inliers.sum() == n - 1
        assert not res.inliers[bad]
        assert res.residuals_mm[bad] > 1.0
        assert res.rms_mm < 0.2
        R_err = np.degrees(np.linalg.norm(rotvec_from_matrix(res.T_to_from[:3, :3] @ R.T)))
        assert R_err < 1.0


def test_horn_robust_finds_a_swapped_pair() -> None:
    rng = np.random.default_rng(RNG_SEED + 99)
    for _ in range(10):
        R, t = _random_pose(rng)
        a = rng.uniform(-100, 100, (6, 3))
        b = a @ R.T + t + rng.normal(0, 0.05, a.shape)
        i, j = rng.choice(6, 2, replace=False)
        b[[i, j]] = b[[j, i]]
        res = horn_robust(a, b, threshold_mm=0.5)
        assert res.dropped == tuple(sorted((int(i), int(j))))
        assert res.rms_mm < 0.2


def test_horn_robust_refuses_when_too_few_agree() -> None:
    rng = np.random.default_rng(RNG_SEED + 7)
    R, t = _random_pose(rng)
    a = rng.uniform(-100, 100, (4, 3))
    b = a @ R.T + t
    b[1] += 20.0
    b[2] -= 30.0
    with pytest.raises(GeometryError, match="fewer than 3 correspondences agree"):
        horn_robust(a, b, threshold_mm=0.5)
    assert horn_robust(a[[0, 3, 1]], b[[0, 3, 1]], threshold_mm=1e3).dropped == ()


def test_horn_degenerate_inputs_raise() -> None:
    a = np.array([[0.0, 0, 0], [100, 0, 0], [0, 80, 0], [30, 20, 50]])
    with pytest.raises(DegenerateInputError, match="at least 3"):
        horn(a[:2], a[:2])
    with pytest.raises(DegenerateInputError, match="points_to has 3"):
        horn(a, a[:3])
    with pytest.raises(DegenerateInputError, match=r"shape \(n, 3\)"):
        horn(a[:, :2], a[:, :2])
    nan = a.copy()
    nan[2, 1] = np.nan
    with pytest.raises(DegenerateInputError, match="points_to: point 2 is not finite"):
        horn(a, nan)
    line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    with pytest.raises(DegenerateInputError, match="points_from: .*collinear"):
        horn(line, line)
    nearly = line + np.array([[0, 0, 0], [0, 0, 0], [0, 1e-4, 0], [0, 0, 0], [0, 0, 0]])
    with pytest.raises(DegenerateInputError, match="collinear"):
        horn(nearly, nearly)
    with pytest.raises(DegenerateInputError, match="coincide"):
        horn(np.ones((4, 3)), a)
    with pytest.raises(DegenerateInputError, match="points_to: .*collinear"):
        horn(a, line[:4])
    with pytest.raises(DegenerateInputError, match="weight 1 is negative"):
        horn(a, a, [1.0, -1.0, 1.0, 1.0])
    with pytest.raises(DegenerateInputError, match="fewer than 3 points have a positive weight"):
        horn(a, a, [1.0, 0.0, 0.0, 1.0])


# ----------------------------------------------------------------------------------- PnP
CAMERA = CameraModel(820.0, 815.0, 322.0, 241.0, dist=(-0.21, 0.07, 0.0008, -0.0004, 0.005))


def _object_points(rng: np.random.Generator, n: int) -> np.ndarray:
    return rng.uniform(-80, 80, (n, 3))


def test_pnp_matches_opencv_iterative_on_non_planar_points() -> None:
    rng = np.random.default_rng(RNG_SEED + 3)
    worst_truth, worst_cv = 0.0, 0.0
    K, dist = CAMERA.to_opencv()
    for _ in range(10):
        obj = _object_points(rng, 10)
        R = Rotation.random(random_state=rng).as_matrix()
        t = np.r_[rng.uniform(-50, 50, 2), rng.uniform(450, 800)]
        px = CAMERA.project(obj @ R.T + t)
        res = pnp(obj, px, CAMERA)
        assert not res.ambiguous
        worst_truth = max(worst_truth, np.abs(res.T_cam_obj - make_transform(R, t)).max())
        noisy = px + rng.normal(0, 0.3, px.shape)
        res = pnp(obj, noisy, CAMERA)
        ok, rvec, tvec = cv2.solvePnP(obj, noisy, K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
        assert ok
        T_cv = make_transform(matrix_from_rotvec(rvec.ravel()), tvec.ravel())
        worst_cv = max(worst_cv, np.abs(res.T_cam_obj - T_cv).max())
        errors = np.linalg.norm(CAMERA.project(obj @ res.T_cam_obj[:3, :3].T + res.T_cam_obj[:3, 3]) - noisy, axis=1)
        np.testing.assert_allclose(res.errors_px, errors, atol=1e-9)
        assert res.rms_px == pytest.approx(np.sqrt(np.mean(errors**2)))
    print(f"PnP noise-free vs truth: max abs error {worst_truth:.2e}; 0.3 px noise vs cv2 ITERATIVE: max abs difference {worst_cv:.2e} (T entries, mm)")
    assert worst_truth < 1e-8
    assert worst_cv < 1e-4


def test_pnp_reproduces_bouguet_extrinsics(datasets: Path) -> None:
    mat = scipy.io.loadmat(str(datasets / "bouguet_stereo_example" / "Calib_Results_left.mat"))
    fc, cc, kc = mat["fc"].ravel(), mat["cc"].ravel(), mat["kc"].ravel()
    camera = CameraModel(fc[0], fc[1], cc[0], cc[1], skew=fc[0] * float(mat["alpha_c"].ravel()[0]), dist=tuple(kc))
    worst_mm, worst_deg, worst_rms = 0.0, 0.0, 0.0
    for i in range(1, 15):
        res = pnp(mat[f"X_{i}"].T, mat[f"x_{i}"].T, camera)
        R_ref = matrix_from_rotvec(mat[f"omc_{i}"].ravel())
        t_ref = mat[f"Tc_{i}"].ravel()
        worst_mm = max(worst_mm, np.abs(res.T_cam_obj[:3, 3] - t_ref).max())
        worst_deg = max(worst_deg, np.degrees(np.linalg.norm(rotvec_from_matrix(res.T_cam_obj[:3, :3] @ R_ref.T))))
        worst_rms = max(worst_rms, res.rms_px)
        assert not res.ambiguous
    print(f"PnP vs Bouguet omc_i/Tc_i (14 views): max {worst_mm:.2e} mm, {worst_deg:.2e} deg; worst RMS {worst_rms:.3f} px")
    assert worst_mm < 1e-3
    assert worst_deg < 1e-4
    assert worst_rms < 0.3


def _planar_view(rng: np.random.Generator, nx: int, ny: int, pitch_mm: float, z_mm: float, tilt_deg: float, noise_px: float):
    g = np.stack(np.meshgrid(np.arange(nx), np.arange(ny)), -1).reshape(-1, 2) * pitch_mm
    obj = np.c_[g - g.mean(axis=0), np.zeros(len(g))]
    axis = np.array([1.0, 0.5, 0.0]) / np.linalg.norm([1.0, 0.5, 0.0])
    T = make_transform(matrix_from_rotvec(np.radians(tilt_deg) * axis), [10.0, 5.0, z_mm])
    px = CAMERA.project(obj @ T[:3, :3].T + T[:3, 3]) + rng.normal(0, noise_px, (len(obj), 2))
    return obj, px, T


def test_pnp_flags_planar_ambiguity() -> None:
    rng = np.random.default_rng(RNG_SEED + 4)
    for _ in range(5):
        # 30 mm square target at 1 m, nearly fronto-parallel, 0.5 px noise: ~25 px wide.
        obj, px, _ = _planar_view(rng, 4, 4, 10.0, 1000.0, 3.0, 0.5)
        res = pnp(obj, px, CAMERA)
        assert res.ambiguous
        assert res.T_cam_obj_alt is not None
        assert res.rms_px_alt is not None
        assert res.rms_px_alt < 2.0 * max(res.rms_px, 0.1)
        # The two poses differ mainly by the tilt's mirror image about the line of sight.
        angle = np.linalg.norm(rotvec_from_matrix(res.T_cam_obj[:3, :3] @ res.T_cam_obj_alt[:3, :3].T))
        assert angle > np.radians(0.5)
    for _ in range(5):
        # 9x6 board of 30 mm squares at 500 mm, tilted 30 degrees, 0.2 px noise.
        obj, px, T = _planar_view(rng, 9, 6, 30.0, 500.0, 30.0, 0.2)
        res = pnp(obj, px, CAMERA)
        assert not res.ambiguous
        assert np.abs(res.T_cam_obj[:3, 3] - T[:3, 3]).max() < 1.0


def test_pnp_degenerate_inputs_raise() -> None:
    rng = np.random.default_rng(RNG_SEED + 5)
    obj = _object_points(rng, 6)
    T = make_transform(np.eye(3), [0.0, 0.0, 600.0])
    px = CAMERA.project(obj + T[:3, 3])
    with pytest.raises(DegenerateInputError, match="at least 4 points, got 3"):
        pnp(obj[:3], px[:3], CAMERA)
    with pytest.raises(DegenerateInputError, match="pixels has 5"):
        pnp(obj, px[:5], CAMERA)
    bad = px.copy()
    bad[3, 0] = np.inf
    with pytest.raises(DegenerateInputError, match="pixels: point 3 is not finite"):
        pnp(obj, bad, CAMERA)
    line = np.outer(np.arange(5.0), [10.0, 5.0, 1.0])
    with pytest.raises(DegenerateInputError, match="model_points: .*collinear"):
        pnp(line, CAMERA.project(line + [0, 0, 500]), CAMERA)
    # A planar target seen exactly edge-on: its image is a line.
    edge = np.array([[0.0, 0, 0], [50, 0, 0], [0, 0, 40], [50, 0, 40], [25, 0, 20]])
    with pytest.raises(DegenerateInputError, match="pixels .*collinear"):
        pnp(edge, CAMERA.project(edge + [0, 0, 500]), CAMERA)
    # Pixels of a configuration whose only exact fit puts point 2 behind the camera (pinhole
    # x/z, y/z of a point at negative z).
    obj[2, 2] = -900.0
    cam_pts = obj + T[:3, 3]
    ideal = cam_pts[:, :2] / cam_pts[:, 2:]
    behind_px = ideal * [CAMERA.fx, CAMERA.fy] + [CAMERA.cx, CAMERA.cy]
    no_dist = CameraModel(CAMERA.fx, CAMERA.fy, CAMERA.cx, CAMERA.cy)
    with pytest.raises(DegenerateInputError, match="behind the camera"):
        pnp(obj, behind_px, no_dist)
