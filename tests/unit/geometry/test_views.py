"""N-camera triangulation and the multi-rig pose fit against OpenCV, scipy and the truth.

Oracles: ``cv2.triangulatePoints`` (two views), ``cv2.projectPoints`` (the projection and its
Jacobian), scipy's ``least_squares`` with numeric derivatives on a plain parametrisation (the
refinements), and the known scene (noise-free recovery). Degenerate inputs: parallel rays, one
ray, a point behind a camera, too few marks.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from vgripd.errors import DegenerateInputError
from vgripd.geometry.camera_model import CameraModel, project_with_jacobian
from vgripd.geometry.points_from_views import MultiView
from vgripd.geometry.pose_from_views import fit_pose, rig_consistency
from vgripd.geometry.stereo import StereoRig
from vgripd.geometry.transforms import invert_transform, make_transform, pose_error

CAM = CameraModel(1800.0, 1795.0, 640.0, 512.0, dist=(-0.08, 0.11, 0.0004, -0.0003, 0.01),
                  width=1280, height=1024)
CV_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)


def look_at(eye: object, target: object = (0.0, 0.0, 0.0)) -> np.ndarray:
    """Pose of a camera at ``eye`` (base frame) whose optical axis points at ``target``."""
    e = np.asarray(eye, dtype=float)
    z = np.asarray(target, dtype=float) - e
    z /= np.linalg.norm(z)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    return make_transform(np.c_[x, np.cross(z, x), z], e)


def ring(n: int, radius: float = 1500.0, height: float = 600.0) -> list[np.ndarray]:
    """n cameras on a circle around the origin, all looking at it."""
    angles = np.linspace(0.0, 2 * np.pi, n, endpoint=False) + 0.3
    return [look_at((radius * np.cos(a), radius * np.sin(a), height)) for a in angles]


def project_all(Ts: list[np.ndarray], X: np.ndarray, cams: list[CameraModel] | None = None
                ) -> np.ndarray:
    cams = cams or [CAM] * len(Ts)
    out = np.empty((len(X), len(Ts), 2))
    for j, (T, cam) in enumerate(zip(Ts, cams, strict=True)):
        Ti = invert_transform(T)
        out[:, j] = cam.project(X @ Ti[:3, :3].T + Ti[:3, 3])
    return out


# ---------------------------------------------------------------------- projection Jacobian
@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), skew=st.floats(-2.0, 2.0))
def test_projection_and_its_jacobian_match_opencv(seed: int, skew: float) -> None:
    rng = np.random.default_rng(seed)
    cam = CameraModel(1500.0, 1480.0, 600.0, 500.0, skew=skew,
                      dist=tuple(rng.uniform(-0.1, 0.1, 5) * [1, 1, 0.01, 0.01, 1]))
    P = np.c_[rng.uniform(-200, 200, (20, 2)), rng.uniform(400, 1500, 20)]
    px, J = project_with_jacobian(cam, P)
    np.testing.assert_allclose(px, cam.project(P), atol=1e-9)
    # cv2.projectPoints' Jacobian is against rvec/tvec; with rvec = 0 its d/dtvec is d/dP.
    K, dist = cam.to_opencv()
    for i in range(0, 20, 5):
        ref, jac = cv2.projectPoints(P[i:i + 1], np.zeros(3), np.zeros(3), K, dist)
        if skew == 0.0:  # OpenCV's projectPoints ignores K[0, 1]
            np.testing.assert_allclose(px[i], ref.reshape(2), atol=1e-9)
            np.testing.assert_allclose(J[i], jac[:, 3:6], rtol=1e-7, atol=1e-9)
    # Independent of OpenCV (skew included): central differences of our own projection.
    h = 1e-4
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        num = (cam.project(P + e) - cam.project(P - e)) / (2 * h)
        np.testing.assert_allclose(J[:, :, k], num, rtol=1e-6, atol=1e-7)


# ---------------------------------------------------------------------- triangulation
@settings(max_examples=30, deadline=None)
@given(n_cams=st.integers(2, 8), seed=st.integers(0, 2**32 - 1))
def test_noise_free_points_are_recovered_from_any_subset_of_cameras(n_cams: int,
                                                                    seed: int) -> None:
    rng = np.random.default_rng(seed)
    Ts = ring(n_cams)
    mv = MultiView([CAM] * n_cams, Ts)
    X = rng.uniform(-200, 200, (15, 3))
    px = project_all(Ts, X)
    seen = rng.random((15, n_cams)) < 0.6
    seen[seen.sum(axis=1) < 2, :2] = True  # every point in at least two cameras
    px[~seen] = np.nan
    tri = mv.triangulate(px)
    np.testing.assert_array_equal(tri.views, seen.sum(axis=1))
    np.testing.assert_allclose(tri.points_mm, X, atol=1e-7)
    assert np.nanmax(tri.ray_distance_mm) < 1e-7
    assert np.isnan(tri.ray_distance_mm[~seen]).all()


def test_two_views_are_eq14_and_opencv_triangulate_points() -> None:
    """Two cameras: the nearest point to both rays is StereoRig's eq. (14) midpoint, and
    noise-free it is cv2.triangulatePoints' (DLT) point."""
    Ts = [look_at((-200.0, -1200.0, 500.0)), look_at((250.0, -1100.0, 650.0))]
    cams = [CAM, CameraModel(1750.0, 1752.0, 630.0, 520.0, dist=(-0.05, 0.02, 0, 0, 0))]
    mv = MultiView(cams, Ts)
    rng = np.random.default_rng(3)
    X = rng.uniform(-150, 150, (30, 3))
    px = project_all(Ts, X, cams)
    T_right_left = invert_transform(Ts[1]) @ Ts[0]
    Xh = cv2.triangulatePoints(
        np.eye(4)[:3], T_right_left[:3],
        cv2.undistortPoints(px[:, 0].reshape(-1, 1, 2), cams[0].K, cams[0].dist_array,
                            criteria=CV_CRITERIA).reshape(-1, 2).T.copy(),
        cv2.undistortPoints(px[:, 1].reshape(-1, 1, 2), cams[1].K, cams[1].dist_array,
                            criteria=CV_CRITERIA).reshape(-1, 2).T.copy())
    cv_base = (Xh[:3] / Xh[3]).T @ Ts[0][:3, :3].T + Ts[0][:3, 3]
    np.testing.assert_allclose(mv.triangulate(px).points_mm, cv_base, atol=1e-6)
    # With noise: identical to StereoRig's eq. (14) midpoint (same criterion, other algebra).
    noisy = px + rng.normal(0, 0.5, px.shape)
    rig = StereoRig(cams[0], cams[1], T_right_left)
    mid = rig.triangulate(noisy[:, 0], noisy[:, 1])
    ours = mv.triangulate(noisy)
    np.testing.assert_allclose(ours.points_mm, mid.points_mm @ Ts[0][:3, :3].T + Ts[0][:3, 3],
                               atol=1e-8)
    # Both ray distances are half the gap between the two rays.
    np.testing.assert_allclose(ours.ray_distance_mm, np.c_[mid.gap_mm, mid.gap_mm] / 2,
                               atol=1e-8)


def test_refined_points_minimise_reprojection_like_scipy() -> None:
    Ts = ring(5)
    mv = MultiView([CAM] * 5, Ts)
    rng = np.random.default_rng(11)
    X = rng.uniform(-200, 200, (12, 3))
    px = project_all(Ts, X) + rng.normal(0, 0.4, (12, 5, 2))
    px[rng.random((12, 5)) < 0.3] = np.nan
    px[:, :2][np.isnan(px[:, :2])] = project_all(Ts[:2], X)[np.isnan(px[:, :2])]
    start = mv.triangulate(px).points_mm
    refined, errors = mv.refine_points(start, px)
    for i in range(12):
        seen = ~np.isnan(px[i, :, 0])

        def res(p: np.ndarray, i: int = i, seen: np.ndarray = seen) -> np.ndarray:
            return (project_all([T for T, s in zip(Ts, seen, strict=True) if s], p[None])[0]
                    - px[i, seen]).ravel()

        oracle = least_squares(res, start[i], method="lm", xtol=1e-14, ftol=1e-14).x
        np.testing.assert_allclose(refined[i], oracle, atol=1e-6)
        assert (errors[i, seen] ** 2).sum() <= (mv.reprojection_errors(start, px)[i, seen]
                                                ** 2).sum() + 1e-12
    assert np.isnan(errors[np.isnan(px[..., 0])]).all()


def test_parallel_rays_are_refused_naming_the_point() -> None:
    # Two cameras side by side looking the same way: the pixel at the principal point of both
    # is one direction from two centres (a point at infinity).
    Ts = [look_at((0.0, 0.0, 1000.0), (0.0, 0.0, 0.0)), look_at((100.0, 0.0, 1000.0),
                                                                (100.0, 0.0, 0.0))]
    mv = MultiView([CameraModel(1000.0, 1000.0, 500.0, 400.0)] * 2, Ts)
    good = project_all(Ts, np.array([[20.0, 10.0, 0.0]]), list(mv.cameras))[0]
    px = np.array([good, [[500.0, 400.0], [500.0, 400.0]]])
    with pytest.raises(DegenerateInputError, match=r"point 1: its 2 rays are \(nearly\) parallel"):
        mv.triangulate(px)
    soft = mv.triangulate(px, strict=False)
    assert np.isfinite(soft.points_mm[0]).all()
    assert np.isnan(soft.points_mm[1]).all()
    assert soft.problems == ("point 1: its 2 rays are (nearly) parallel",)


def test_one_ray_gives_no_point_and_half_nan_pixel_is_an_error() -> None:
    Ts = ring(3)
    mv = MultiView([CAM] * 3, Ts, names=["a", "b", "c"])
    px = project_all(Ts, np.zeros((2, 3)))
    px[0, 1:] = np.nan
    tri = mv.triangulate(px)
    assert tri.views.tolist() == [1, 3]
    assert np.isnan(tri.points_mm[0]).all()
    assert np.isfinite(tri.points_mm[1]).all()
    px[1, 2, 0] = np.nan
    with pytest.raises(DegenerateInputError, match="point 1 in camera 2 is not a finite pixel"):
        mv.triangulate(px)
    with pytest.raises(DegenerateInputError, match=r"expected shape \(m, 3, 2\)"):
        mv.triangulate(np.zeros((2, 2, 2)))


def test_point_behind_a_camera_is_refused_naming_the_camera() -> None:
    # Camera "b" looks away from camera "a"'s scene; a pixel pair whose least-squares point
    # lies behind b (a wrong correspondence) must not come back as a point.
    Ta = look_at((0.0, -1000.0, 0.0))
    Tb = look_at((300.0, -1000.0, 0.0), (300.0, -2000.0, 0.0))  # looks the other way
    mv = MultiView([CAM, CAM], [Ta, Tb], names=["a", "b"])
    X_front_of_b = np.array([[300.0, -1500.0, 10.0]])
    X_front_of_a = np.array([[0.0, 0.0, 10.0]])
    px = np.array([[project_all([Ta], X_front_of_a)[0, 0], project_all([Tb], X_front_of_b)[0, 0]]])
    with pytest.raises(DegenerateInputError, match="point 0: lies behind camera"):
        mv.triangulate(px)


# ---------------------------------------------------------------------- the object pose
def _two_rig_scene(seed: int = 0, noise_px: float = 0.0):  # type: ignore[no-untyped-def]
    """A 1.5 m frame with 10 marks on each side, two stereo rigs on opposite sides: each rig
    sees only the marks of its own side (neither sees the frame whole)."""
    rng = np.random.default_rng(seed)
    model = np.c_[rng.uniform(-700, 700, 20), np.repeat([-60.0, 60.0], 10),
                  rng.uniform(-200, 200, 20)]
    Ts = [look_at(e) for e in [(-200, -1600, 500), (200, -1600, 500),
                               (-200, 1600, 500), (200, 1600, 500)]]
    T_true = make_transform(Rotation.from_rotvec([0.03, -0.02, 0.15]).as_matrix(), [12, -8, 20])
    X = model @ T_true[:3, :3].T + T_true[:3, 3]
    px = project_all(Ts, X) + rng.normal(0, noise_px, (20, 4, 2))
    px[10:, :2] = np.nan  # the north rig sees the y < 0 side only
    px[:10, 2:] = np.nan
    mv = MultiView([CAM] * 4, Ts, names=["nl", "nr", "sl", "sr"],
                   groups=[("north", (0, 1)), ("south", (2, 3))])
    return mv, model, px, T_true, Ts


def test_two_rigs_that_each_see_half_give_the_exact_pose() -> None:
    mv, model, px, T_true, _ = _two_rig_scene()
    fit = fit_pose(mv, model, px)
    mm, deg = pose_error(fit.T_base_obj, T_true)
    assert mm < 1e-6
    assert deg < 1e-7
    assert fit.rms_px < 1e-6
    assert fit.triangulated == 20
    assert fit.converged
    assert [(g.name, g.observations) for g in fit.groups] == [("north", 20), ("south", 20)]
    # Neither rig alone covers the frame: each sees 10 of its 20 marks.
    assert np.isnan(fit.errors_px[10:, :2]).all()
    assert np.isnan(fit.errors_px[:10, 2:]).all()


def test_joint_refinement_is_the_reprojection_optimum_scipy_finds() -> None:
    mv, model, px, T_true, Ts = _two_rig_scene(seed=4, noise_px=0.3)
    fit = fit_pose(mv, model, px)
    seen = ~np.isnan(px[..., 0])

    def res(v: np.ndarray) -> np.ndarray:  # a plain rotation-vector parametrisation
        T = make_transform(Rotation.from_rotvec(v[:3]).as_matrix(), v[3:])
        X = model @ T[:3, :3].T + T[:3, 3]
        return (project_all(Ts, X) - px)[seen].ravel()

    v0 = np.r_[Rotation.from_matrix(fit.T_base_obj_horn[:3, :3]).as_rotvec(),
               fit.T_base_obj_horn[:3, 3]]
    oracle = least_squares(res, v0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15).x
    T_oracle = make_transform(Rotation.from_rotvec(oracle[:3]).as_matrix(), oracle[3:])
    mm, deg = pose_error(fit.T_base_obj, T_oracle)
    assert mm < 1e-5
    assert deg < 1e-6
    # The refinement improves on Horn's closed form against the truth.
    assert pose_error(fit.T_base_obj, T_true)[0] <= pose_error(fit.T_base_obj_horn, T_true)[0]
    assert fit.rms_px == pytest.approx(np.sqrt((res(oracle) ** 2).sum() / seen.sum()), rel=1e-6)


def test_marks_seen_by_one_camera_each_start_from_pnp() -> None:
    mv, model, px, T_true, _ = _two_rig_scene()
    px[:, 1] = np.nan  # only one camera per rig left: nothing is triangulated
    px[:, 3] = np.nan
    fit = fit_pose(mv, model, px)
    assert fit.triangulated == 0
    assert np.isnan(fit.horn_rms_mm)
    assert pose_error(fit.T_base_obj, T_true)[0] < 1e-6


def test_too_few_marks_are_refused() -> None:
    mv, model, px, _, _ = _two_rig_scene()
    px[2:] = np.nan
    with pytest.raises(DegenerateInputError, match="too few marks for a pose: 2 marks seen"):
        fit_pose(mv, model, px)


def test_a_pose_behind_an_observing_camera_is_refused() -> None:
    mv, model, px, T_true, _ = _two_rig_scene()
    flipped = T_true.copy()
    flipped[:3, 3] += [0.0, -5000.0, 0.0]  # behind the north rig, far beyond it
    with pytest.raises(DegenerateInputError, match="lies behind camera"):
        fit_pose(mv, model, px, flipped)


# ---------------------------------------------------------------------- consistency
def test_consistent_cell_names_no_rig() -> None:
    mv, model, px, _, _ = _two_rig_scene(seed=2, noise_px=0.2)
    fit = fit_pose(mv, model, px)
    checks = rig_consistency(mv, model, px, fit.T_base_obj, limit_px=1.5,
                             max_deviation_mm=3.0, max_deviation_deg=0.5)
    assert [c.name for c in checks] == ["north", "south"]
    assert not any(c.odd for c in checks)
    assert all(c.alone_rms_px < 0.5 for c in checks)


@pytest.mark.parametrize("moved", [0, 1, 2, 3])
def test_a_moved_camera_names_its_rig(moved: int) -> None:
    mv, model, px, _, Ts = _two_rig_scene(seed=6, noise_px=0.2)
    knocked = list(Ts)
    # The camera moved 3 mm and turned 0.2 deg after calibration: the config is now wrong.
    knocked[moved] = Ts[moved] @ make_transform(
        Rotation.from_rotvec([0.0, np.radians(0.2), 0.0]).as_matrix(), [3.0, 0.0, 0.0])
    bad = MultiView(list(mv.cameras), knocked, names=mv.names, groups=mv.groups)
    fit = fit_pose(bad, model, px)
    checks = rig_consistency(bad, model, px, fit.T_base_obj, limit_px=1.5,
                             max_deviation_mm=3.0, max_deviation_deg=0.5)
    rig = "north" if moved < 2 else "south"
    assert [c.name for c in checks if c.odd] == [rig]


def test_linearised_leave_one_out_agrees_with_a_real_refit() -> None:
    mv, model, px, _, Ts = _two_rig_scene(seed=8, noise_px=0.2)
    knocked = list(Ts)
    knocked[3] = Ts[3] @ make_transform(np.eye(3), [0.0, 4.0, 0.0])
    bad = MultiView(list(mv.cameras), knocked, names=mv.names, groups=mv.groups)
    fit = fit_pose(bad, model, px)
    north, south = rig_consistency(bad, model, px, fit.T_base_obj, limit_px=1.5,
                                   max_deviation_mm=3.0, max_deviation_deg=0.5)
    # The real fit of the north rig alone (the "rest" of south) and south's RMS under it.
    only_north = px.copy()
    only_north[:, 2:] = np.nan
    refit = fit_pose(bad, model, only_north)
    assert south.rest_rms_px == pytest.approx(refit.rms_px, rel=0.05)
    full = bad.reprojection_errors(model @ refit.T_base_obj[:3, :3].T + refit.T_base_obj[:3, 3],
                                   px)
    pred = np.sqrt(np.nanmean(full[:, 2:] ** 2))
    assert south.predicted_rms_px == pytest.approx(pred, rel=0.05)
    assert south.odd
    assert not north.odd


def test_one_camera_at_several_robot_poses_is_several_views() -> None:
    """A robot-mounted camera taking images from several flange poses: each image is a view
    whose pose is T_base_flange @ T_flange_camera, and the object pose is fitted over all."""
    T_flange_camera = make_transform(Rotation.from_rotvec([0.0, 0.0, 0.1]).as_matrix(),
                                     [0.0, 60.0, 120.0])
    flanges = [look_at(e) @ invert_transform(T_flange_camera)
               for e in [(-300, -1200, 500), (300, -1200, 500), (0, -1100, 900)]]
    Ts = [F @ T_flange_camera for F in flanges]
    mv = MultiView([CAM] * 3, Ts, names=["shot0", "shot1", "shot2"])
    rng = np.random.default_rng(9)
    model = rng.uniform(-150, 150, (10, 3))
    T_true = make_transform(Rotation.from_rotvec([0.1, 0.0, -0.05]).as_matrix(), [5, 3, -2])
    px = project_all(Ts, model @ T_true[:3, :3].T + T_true[:3, 3]) + rng.normal(0, 0.1,
                                                                               (10, 3, 2))
    fit = fit_pose(mv, model, px)
    assert pose_error(fit.T_base_obj, T_true)[0] < 0.1
    assert fit.rms_px < 0.2
    assert [g.observations for g in fit.groups] == [10, 10, 10]


def test_with_three_rigs_a_rig_moved_as_a_whole_is_named() -> None:
    """Two rigs cannot tell which of them moved as a whole (each is consistent in itself);
    three can: the other two agree, and the moved one disagrees with them."""
    rng = np.random.default_rng(12)
    model = rng.uniform(-300, 300, (24, 3))
    eyes = [(-150, -1500, 500), (150, -1500, 500), (1300, 700, 600), (1450, 450, 600),
            (-1300, 700, 600), (-1450, 450, 600)]
    Ts = [look_at(e) for e in eyes]
    px = project_all(Ts, model) + rng.normal(0, 0.1, (24, 6, 2))
    groups = [("a", (0, 1)), ("b", (2, 3)), ("c", (4, 5))]
    knock = make_transform(Rotation.from_rotvec([0.0, 0.0, np.radians(0.3)]).as_matrix(),
                           [2.0, 1.0, 0.0])
    for moved in range(3):
        Ts_config = [knock @ T if j // 2 == moved else T for j, T in enumerate(Ts)]
        mv = MultiView([CAM] * 6, Ts_config, groups=groups)
        fit = fit_pose(mv, model, px)
        checks = rig_consistency(mv, model, px, fit.T_base_obj, limit_px=1.5,
                                 max_deviation_mm=3.0, max_deviation_deg=0.5)
        assert [c.name for c in checks if c.odd] == ["abc"[moved]]
    # With only two of the rigs, the same knock makes both disagree: no single one to blame.
    two = MultiView([CAM] * 4, [knock @ Ts[0], knock @ Ts[1], Ts[2], Ts[3]],
                    groups=groups[:2])
    fit = fit_pose(two, model, px[:, :4])
    checks = rig_consistency(two, model, px[:, :4], fit.T_base_obj, limit_px=1.5,
                             max_deviation_mm=3.0, max_deviation_deg=0.5)
    assert [c.odd for c in checks] == [True, True]
