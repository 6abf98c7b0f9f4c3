"""N-camera calibration (``vgripd.calib.camera_poses``) on board corners projected through known
cameras.

Oracles: ``cv2.projectPoints`` for the projection model and for the truth (every corner is
projected by OpenCV through the true cameras and board poses, then noised); scipy's
``approx_derivative`` for the analytic Jacobian and its MINPACK ``least_squares`` for the
solver; ``cv2.stereoCalibrate`` for a pair (same observations, same model: it must land on the
same optimum).

The cell: four cameras 200 mm apart in a row, 900 mm above a table, looking down, each turned a
little differently; boards at random poses 550-750 mm below them. Camera a and camera d are
600 mm apart and never see the board at the same instant, so d is reached by chaining
(a - b - c - d).
"""

from __future__ import annotations

from collections import Counter

import cv2
import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy.optimize import least_squares
from scipy.optimize._numdiff import approx_derivative

from vgripd.calib.camera_poses import (
    INTRINSIC_KEYS,
    Observation,
    _Problem,
    base_from_board,
    base_from_camera,
    calibrate_cameras,
    intrinsic_vector,
    levenberg_marquardt,
    place,
    project,
)
from vgripd.errors import CalibrationError
from vgripd.geometry.transforms import pose_error

NAMES = ["a", "b", "c", "d"]
BOARD = np.array([[c * 25.0, r * 25.0, 0.0] for r in range(5) for c in range(7)])  # 7x5, 25 mm
SIZE = (640, 480)


def camera(i: int) -> dict:
    return {"fx": 800.0 + 7 * i, "fy": 803.0 + 5 * i, "cx": 321.0 - i, "cy": 238.0 + 2 * i,
            "skew": 0.0, "dist": [-0.21 + 0.01 * i, 0.11, 0.0008, -0.0004, 0.0],
            "width": SIZE[0], "height": SIZE[1]}


CAMERAS = [camera(i) for i in range(4)]


def transform(rvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, float))[0]
    T[:3, 3] = t
    return T


# cameras in the base frame: looking down (pi about x), each tilted and rolled a little
T_BASE_CAMERA = [transform([np.pi + 0.02 * i, 0.03 * i - 0.04, 0.05 * i], [200.0 * i, 10 * i, 900])
                 for i in range(4)]


def opencv(cam: dict) -> tuple[np.ndarray, np.ndarray]:
    K = np.array([[cam["fx"], cam["skew"], cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]])
    return K, np.asarray(cam["dist"], float)


def opencv_px(T_cam_board: np.ndarray, cam: dict) -> np.ndarray:
    """OpenCV's projection of the board's corners, (35, 2) px, at pose ``T_cam_board``.

    The corners are moved into the camera frame here and projected with a zero rotation:
    handing projectPoints the pose as a rotation vector would go through cv2.Rodrigues(R),
    which near a half turn (3.141586 rad, a board seen from behind) returns a vector up to
    1e-5 rad off; the "exact" pixels would then belong to another pose (0.0006 px)."""
    K, d = opencv(cam)
    pts = BOARD @ T_cam_board[:3, :3].T + T_cam_board[:3, 3]
    return cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, d)[0].reshape(-1, 2)


def truth_px(c: int, T_base_board: np.ndarray) -> np.ndarray | None:
    """OpenCV's projection of the board into camera c, None unless wholly inside."""
    T = np.linalg.inv(T_BASE_CAMERA[c]) @ T_base_board
    if T[2, 3] <= 0:
        return None
    px = opencv_px(T, CAMERAS[c])
    inside = np.all((px > 5) & (px < np.array(SIZE) - 5))
    return px if inside else None


def scene(n_sets: int = 40, noise_px: float = 0.1, seed: int = 0,
          ) -> tuple[list[Observation], dict[str, np.ndarray]]:
    rng = np.random.default_rng(seed)
    obs, boards = [], {}
    while len(boards) < n_sets:
        R = cv2.Rodrigues(rng.uniform(-0.4, 0.4, 3))[0]
        # mostly where two neighbours overlap (x = 100, 300, 500), else anywhere
        x = (rng.choice([100.0, 300.0, 500.0]) + rng.uniform(-40, 40) if rng.random() < 0.7
             else rng.uniform(-150, 750))
        centre = [x, rng.uniform(-100, 130), rng.uniform(150, 350)]
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = centre - R @ BOARD.mean(axis=0)
        key = str(len(boards) + 1)
        seen = [(c, truth_px(c, T)) for c in range(4)]
        seen = [(c, px) for c, px in seen if px is not None]
        if not seen:
            continue
        boards[key] = T
        obs += [Observation(c, key, BOARD, px + rng.normal(0, noise_px, px.shape),
                            f"{NAMES[c]}_{key}.png") for c, px in seen]
    return obs, boards


def truth_ref_camera(c: int, ref: int = 0) -> np.ndarray:
    return np.linalg.inv(T_BASE_CAMERA[ref]) @ T_BASE_CAMERA[c]


def assert_pose(T, T_truth, mm: float, deg: float, what: str = "") -> None:
    err_mm, err_deg = pose_error(T, T_truth)
    assert err_mm < mm, (what, err_mm)
    assert err_deg < deg, (what, err_deg)


@pytest.fixture(scope="module")
def cell():
    obs, boards = scene()
    return obs, boards, calibrate_cameras(NAMES, CAMERAS, obs)


# ----------------------------------------------------------------- the model


@settings(max_examples=60, deadline=None)
@given(k=st.tuples(st.floats(300, 3000), st.floats(300, 3000), st.floats(100, 900),
                   st.floats(100, 700), st.floats(-0.5, 0.5), st.floats(-0.5, 0.5),
                   st.floats(-0.01, 0.01), st.floats(-0.01, 0.01), st.floats(-0.2, 0.2)),
       skew=st.floats(-2, 2), seed=st.integers(0, 2**16))
def test_projection_equals_opencv(k, skew, seed):
    """OpenCV's model; projectPoints ignores K's skew entry, so skew (u += skew * yd, yd the
    distorted normalised y = (v - cy) / fy) is added to OpenCV's u here."""
    pts = np.random.default_rng(seed).uniform([-300, -300, 200], [300, 300, 1500], (20, 3))
    K = np.array([[k[0], 0.0, k[2]], [0, k[1], k[3]], [0, 0, 1]])
    ours = project(pts, np.tile(np.asarray(k), (len(pts), 1)), skew)
    cv = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, np.asarray(k[4:9]))[0].reshape(-1, 2)
    cv[:, 0] += skew * (cv[:, 1] - k[3]) / k[1]
    np.testing.assert_allclose(ours, cv, rtol=1e-9, atol=1e-7)


def test_analytic_jacobian_equals_finite_differences():
    """Every column (camera poses, board poses, all nine intrinsics with skew) against scipy's
    central differences, at a point off the optimum."""
    obs, boards = scene(n_sets=20, seed=3)
    cams = [dict(c, dist=[-0.2, 0.1, 0.001, -0.0005, 0.02], skew=0.4) for c in CAMERAS]
    keys = sorted({o.set_key for o in obs}, key=int)
    used = sorted({o.camera for o in obs})
    assert len(used) == 4
    problem = _Problem(obs, 4, keys, [INTRINSIC_KEYS] * 4, ref=1)
    intr0 = np.array([intrinsic_vector(c) for c in cams])
    skews = np.full(4, 0.4)
    T_cam_ref = [np.linalg.inv(truth_ref_camera(c, 1)) for c in range(4)]
    x = problem.pack(T_cam_ref, [np.linalg.inv(T_BASE_CAMERA[1]) @ boards[k] for k in keys], intr0)
    x = x + np.random.default_rng(1).normal(0, 1e-3, x.shape)
    analytic = problem.jacobian(x, intr0, skews).toarray()
    numeric = approx_derivative(lambda v: problem.residuals(v, intr0, skews), x,
                                method="3-point")
    scale = np.maximum(np.abs(numeric).max(axis=0), 1e-9)
    assert np.max(np.abs(analytic - numeric) / scale) < 1e-5


# ----------------------------------------------------------------- the 4-camera cell


def test_scene_needs_chaining(cell):
    """The scene as described: a and d never share a set; every camera sees >= 5 sets."""
    obs, _, _ = cell
    sets: dict[str, set[int]] = {}
    for o in obs:
        sets.setdefault(o.set_key, set()).add(o.camera)
    assert not any({0, 3} <= s for s in sets.values())
    assert min(Counter(o.camera for o in obs).values()) >= 5


def test_four_cameras_recovered_by_chaining(cell):
    """Poses relative to camera a within 1 mm and 0.1 deg of the truth at 0.1 px noise (the
    chain's far end, c and d, is worst: about 0.45 mm and 0.035 deg with 7 shared sets per
    link; without noise all are exact to 1e-9); RMS at the noise level; the tree chains
    a-b-c-d."""
    _, _, r = cell
    for c in range(4):
        mm, deg = pose_error(r.T_ref_camera[c], truth_ref_camera(c))
        assert mm < 1.0, (NAMES[c], mm)
        assert deg < 0.1, (NAMES[c], deg)
    assert r.rms_px == pytest.approx(0.1 * np.sqrt(2), rel=0.1)
    assert [cam["rms_px"] for cam in r.cameras] == pytest.approx([0.14] * 4, rel=0.15)
    assert r.graph["tree"] == [("a", "b"), ("b", "c"), ("c", "d")]
    assert {(a, b) for a, b, _ in r.graph["edges"]} == {("a", "b"), ("b", "c"), ("c", "d")}
    assert r.rejected == []
    assert r.warnings == []


def test_pair_residuals_are_the_spread_of_the_per_set_estimates(cell):
    """Each pair's per-set estimates scatter around the joint solution by about the
    single-view PnP precision of this small board (150 mm at 650 mm): tenths of a degree, a
    few millimetres, under the warning limits."""
    _, _, r = cell
    assert len(r.pairs) == 3
    for p in r.pairs:
        assert p["shared_sets"] >= 3
        assert 0.0 < p["rotation_deg"]["rms"] < 0.3
        assert 0.0 < p["translation_mm"]["rms"] < 0.01 * p["board_distance_mm"]
        assert 550 < p["board_distance_mm"] < 750
        assert p["rotation_deg"]["max"] >= p["rotation_deg"]["rms"]


def test_noise_free_cell_is_exact():
    obs, _ = scene(noise_px=0.0)
    r = calibrate_cameras(NAMES, CAMERAS, obs)
    for c in range(4):
        assert_pose(r.T_ref_camera[c], truth_ref_camera(c), 1e-6, 1e-7, NAMES[c])
    assert r.rms_px < 1e-6


def test_base_frame_from_the_board(cell):
    """T_base_camera of every camera from one set's board pose in the base frame (a set at the
    far end, seen by c and d: camera a then carries the whole chain's error)."""
    _, boards, r = cell
    key = next(s["set"] for s in r.sets if s["cameras"] == ["c", "d"])
    placed = place(r, base_from_board(r, key, boards[key]))
    for c in range(4):
        assert_pose(placed[c], T_BASE_CAMERA[c], 1.5, 0.1, NAMES[c])
    with pytest.raises(CalibrationError, match="image set '999' is not in the fit"):
        base_from_board(r, "999", np.eye(4))


def test_base_frame_from_one_cameras_hand_eye(cell):
    _, _, r = cell
    placed = place(r, base_from_camera(r, "c", T_BASE_CAMERA[2]))
    np.testing.assert_allclose(placed[2], T_BASE_CAMERA[2], atol=1e-9)
    for c in range(4):
        assert_pose(placed[c], T_BASE_CAMERA[c], 1.0, 0.1, NAMES[c])
    with pytest.raises(CalibrationError, match="camera 'x' is not one of"):
        base_from_camera(r, "x", np.eye(4))


def test_reference_camera_choice():
    obs, _ = scene(n_sets=40, seed=5)
    r = calibrate_cameras(NAMES, CAMERAS, obs, reference="c")
    assert r.reference == "c"
    np.testing.assert_allclose(r.T_ref_camera[2], np.eye(4), atol=1e-12)
    for c in range(4):
        assert_pose(r.T_ref_camera[c], truth_ref_camera(c, 2), 1.0, 0.1, NAMES[c])


def test_unconnected_cameras_are_refused_by_name():
    """Without the sets b and c share, {a, b} and {c, d} are two islands."""
    obs, _ = scene(n_sets=60, seed=0)
    by_set: dict[str, set[int]] = {}
    for o in obs:
        by_set.setdefault(o.set_key, set()).add(o.camera)
    bridge = {k for k, s in by_set.items() if {1, 2} <= s}
    assert bridge
    cut = [o for o in obs if not (o.set_key in bridge and o.camera == 2)]
    with pytest.raises(CalibrationError) as err:
        calibrate_cameras(NAMES, CAMERAS, cut)
    msg = str(err.value)
    assert "cannot connect camera(s) c, d to the reference a" in msg
    assert "{c, d}" in msg


def test_an_image_from_another_instant_is_rejected_by_name():
    """Camera b's image of a set it shares with a shows the board 15 mm off (taken late): one
    image of that set is left out, named (with two cameras in a set the data cannot say which
    one is late), and the poses stay as good as without it."""
    obs, boards = scene(n_sets=60, seed=0)
    i = next(i for i, o in enumerate(obs) if o.camera == 1 and any(
        p.camera == 0 and p.set_key == o.set_key for p in obs))
    moved = boards[obs[i].set_key].copy()
    moved[:3, 3] += [15.0, 0.0, 0.0]
    obs[i].px = truth_px(1, moved)
    assert obs[i].px is not None
    r = calibrate_cameras(NAMES, CAMERAS, obs)
    key = obs[i].set_key
    assert [x["image"] for x in r.rejected] in ([f"a_{key}.png"], [f"b_{key}.png"])
    assert r.rejected[0]["set"] == key
    assert "outlier" in r.rejected[0]["reason"]
    for c in range(4):
        assert_pose(r.T_ref_camera[c], truth_ref_camera(c), 1.0, 0.1, NAMES[c])


@pytest.mark.parametrize(("names", "cams", "match"), [
    (["a"], CAMERAS[:1], "1 cameras: need 2 to 8"),
    ([f"c{i}" for i in range(9)], [CAMERAS[0]] * 9, "9 cameras: need 2 to 8"),
    (["a", "a"], CAMERAS[:2], "not unique"),
    (["a", "b"], CAMERAS[:1], "1 intrinsics for 2 cameras"),
])
def test_bad_camera_lists(names, cams, match):
    obs, _ = scene(n_sets=10)
    with pytest.raises(CalibrationError, match=match):
        calibrate_cameras(names, cams, [o for o in obs if o.camera < len(names)])


def test_bad_observations():
    obs, _ = scene(n_sets=10)
    few = Observation(0, "1", BOARD[:5], obs[0].px[:5], "short.png")
    with pytest.raises(CalibrationError, match="short.png: only 5 board points"):
        calibrate_cameras(NAMES, CAMERAS, [*obs, few])
    with pytest.raises(CalibrationError, match="camera\\(s\\) d: the board was not found"):
        calibrate_cameras(NAMES, CAMERAS, [o for o in obs if o.camera != 3])
    with pytest.raises(CalibrationError, match="reference camera 'z'"):
        calibrate_cameras(NAMES, CAMERAS, obs, reference="z")
    with pytest.raises(CalibrationError, match="unknown intrinsic"):
        calibrate_cameras(NAMES, CAMERAS, obs, free=[("fx", "focal")] * 4)


# ----------------------------------------------------------------- a pair against OpenCV


def pair_scene(seed: int = 2) -> tuple[list, list, list, list[Observation]]:
    """Cameras a and b, 25 sets both see (stereoCalibrate needs every view in both)."""
    obs, _ = scene(n_sets=200, seed=seed)
    by_set: dict[str, dict[int, Observation]] = {}
    for o in obs:
        by_set.setdefault(o.set_key, {})[o.camera] = o
    both = [s for s in by_set.values() if 0 in s and 1 in s][:25]
    assert len(both) >= 12
    pair_obs = [s[c] for s in both for c in (0, 1)]
    return ([BOARD.astype(np.float32)] * len(both),
            [s[0].px.astype(np.float32) for s in both],
            [s[1].px.astype(np.float32) for s in both], pair_obs)


def test_pair_with_fixed_intrinsics_equals_stereo_calibrate():
    obj, left, right, obs = pair_scene()
    (Ka, da), (Kb, db) = opencv(CAMERAS[0]), opencv(CAMERAS[1])
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 500, 1e-15)
    _, *_, R, T, _E, _F = cv2.stereoCalibrate(obj, left, right, Ka, da, Kb, db, SIZE,
                                              flags=cv2.CALIB_FIX_INTRINSIC, criteria=crit)
    r = calibrate_cameras(NAMES[:2], CAMERAS[:2], [Observation(o.camera, o.set_key, o.obj, o.px,
                                                               o.image) for o in obs])
    T_b_a = np.linalg.inv(r.T_ref_camera[1])  # X_b = R X_a + T, OpenCV's R, T
    mm, deg = pose_error(T_b_a, transform(cv2.Rodrigues(R)[0].ravel(), T.ravel()))
    assert mm < 1e-3
    assert deg < 1e-4


def test_pair_with_refined_intrinsics_equals_stereo_calibrate():
    """Both fits free fx fy cx cy k1 k2 p1 p2 (k3 held): the same optimum (RMS to 1e-6,
    ours never higher), intrinsics to 5e-3 px, the rig to 5 micrometres (the optimum is flat
    along fx-distance and cx-rotation: both stop within that of each other)."""
    obj, left, right, obs = pair_scene(seed=4)
    start = [dict(c, fx=c["fx"] * 1.01, cx=c["cx"] + 3, dist=[0.0] * 5) for c in CAMERAS[:2]]
    (Ka, da), (Kb, db) = opencv(start[0]), opencv(start[1])
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 1000, 1e-15)
    rms, Ka, da, Kb, db, R, T, *_ = cv2.stereoCalibrateExtended(
        obj, left, right, Ka, da, Kb, db, SIZE, None, None,
        flags=cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K3, criteria=crit)
    free = [("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")] * 2
    r = calibrate_cameras(NAMES[:2], start, obs, free=free)
    assert r.rms_px <= rms * (1 + 1e-9)  # ours at least as low: the same minimum or deeper
    assert r.rms_px == pytest.approx(rms, rel=1e-6)
    for cam, K, d in ((r.intrinsics[0], Ka, da), (r.intrinsics[1], Kb, db)):
        np.testing.assert_allclose([cam["fx"], cam["fy"], cam["cx"], cam["cy"]],
                                   [K[0, 0], K[1, 1], K[0, 2], K[1, 2]], atol=5e-3)
        np.testing.assert_allclose(cam["dist"], np.ravel(d)[:5], atol=2e-5)
    mm, deg = pose_error(np.linalg.inv(r.T_ref_camera[1]),
                         transform(cv2.Rodrigues(R)[0].ravel(), T.ravel()))
    assert mm < 5e-3
    assert deg < 1e-3
    # and both near the truth (fx within 0.5 %: small board, 25 views)
    for c, cam in enumerate(r.intrinsics):
        assert cam["fx"] == pytest.approx(CAMERAS[c]["fx"], rel=0.005)


def test_levenberg_marquardt_reaches_scipys_minimum():
    """Our solver against scipy's MINPACK Levenberg-Marquardt (dense) on the same problem,
    started off the optimum: the same cost and parameters."""
    obs, boards = scene(n_sets=12, seed=9)
    keys = sorted({o.set_key for o in obs}, key=int)
    cams = sorted({o.camera for o in obs})
    problem = _Problem(obs, 4, keys, [("fx", "k1")] * 4, ref=0)
    intr0 = np.array([intrinsic_vector(c) for c in CAMERAS])
    skews = np.zeros(4)
    x0 = problem.pack([np.linalg.inv(truth_ref_camera(c)) for c in range(4)],
                      [np.linalg.inv(T_BASE_CAMERA[0]) @ boards[k] for k in keys], intr0)
    x0 = x0 + np.random.default_rng(2).normal(0, 1e-2, x0.shape)
    x, r = levenberg_marquardt(lambda v: problem.residuals(v, intr0, skews),
                               lambda v: problem.jacobian(v, intr0, skews), x0)
    ref = least_squares(lambda v: problem.residuals(v, intr0, skews), x0,
                        jac=lambda v: problem.jacobian(v, intr0, skews).toarray(), method="lm",
                        xtol=1e-15, ftol=1e-15, gtol=1e-15)
    assert len(cams) == 4
    assert r @ r <= 2 * ref.cost * (1 + 1e-9)
    assert r @ r == pytest.approx(2 * ref.cost, rel=1e-9)
    np.testing.assert_allclose(x, ref.x, atol=1e-5)


# ----------------------------------------------------------------- any relative pose


def look_at(eye: np.ndarray, target: np.ndarray, roll: float) -> np.ndarray:
    """T_0_cam of a camera at ``eye`` whose optical axis points at ``target``, rolled."""
    z = (target - eye) / np.linalg.norm(target - eye)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    R = np.column_stack([x, np.cross(z, x), z]) @ cv2.Rodrigues(np.array([0, 0, roll]))[0]
    return transform(cv2.Rodrigues(R)[0].ravel(), eye)


@settings(max_examples=25, deadline=None)
@given(polar=st.floats(0.0, np.pi), azimuth=st.floats(-np.pi, np.pi),
       roll=st.floats(-np.pi, np.pi), seed=st.integers(0, 2**16))
@example(polar=np.pi, azimuth=0.0, roll=0.0, seed=1)  # facing each other: a pi rotation
@example(polar=0.0, azimuth=0.0, roll=np.pi, seed=2)  # same axis, turned upside down
@example(polar=np.pi / 2, azimuth=0.5, roll=-3.0, seed=3)  # at right angles
# a board seen by b at 3.141586 rad: the exact pixels must not go through cv2.Rodrigues(R)
@example(polar=2.552137069255595, azimuth=1.934381343910851, roll=-1.1600727980322971, seed=125)
def test_any_relative_pose_is_recovered_exactly(polar, azimuth, roll, seed):
    """Camera b anywhere on a sphere of 600 mm around the point camera a looks at, looking at
    it too (relative rotations up to 180 deg, including exactly pi), rolled freely; boards
    around that point turned to face both. Without noise the pose is exact: no sign or
    parameterisation trouble anywhere, the rotation vector's pi included."""
    rng = np.random.default_rng(seed)
    P = np.array([0.0, 0.0, 600.0])
    d = np.array([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth),
                  np.cos(polar)])
    T_a_b = look_at(P - 600.0 * d, P, roll)
    z_a, z_b = np.array([0.0, 0.0, 1.0]), T_a_b[:3, 2]
    s = 1.0 if z_a @ z_b >= 0 else -1.0
    normal = z_a + s * z_b
    normal = normal / np.linalg.norm(normal)
    obs = []
    for k in range(8):
        n = cv2.Rodrigues(rng.uniform(-0.3, 0.3, 3))[0] @ normal
        board_frame = look_at(P - n, P, rng.uniform(-np.pi, np.pi))  # board z along n
        T_a_board = board_frame.copy()
        T_a_board[:3, 3] = P + rng.uniform(-30, 30, 3) - board_frame[:3, :3] @ BOARD.mean(0)
        for c, T_cam_a in ((0, np.eye(4)), (1, np.linalg.inv(T_a_b))):
            T = T_cam_a @ T_a_board
            assert np.all((T[:3, :3] @ BOARD.T + T[:3, 3:])[2] > 100)
            obs.append(Observation(c, str(k), BOARD, opencv_px(T, CAMERAS[c]), f"{c}_{k}"))
    r = calibrate_cameras(["a", "b"], CAMERAS[:2], obs)
    assert_pose(r.T_ref_camera[1], T_a_b, 1e-6, 1e-6)
    assert r.rms_px < 1e-6


def test_predicted_uncertainty_matches_the_spread_over_noise_draws():
    """The reported one-sigma position and rotation uncertainty of each camera against the
    spread of its pose over 24 noise draws on the same boards (0.1 px): within a factor 1.5
    (24 draws estimate a standard deviation to about 15 %)."""
    clean, _ = scene(noise_px=0.0)
    centres = {c: [] for c in range(1, 4)}
    angles = {c: [] for c in range(1, 4)}
    predicted = []
    for draw in range(24):
        rng = np.random.default_rng(100 + draw)
        obs = [Observation(o.camera, o.set_key, o.obj, o.px + rng.normal(0, 0.1, o.px.shape),
                           o.image) for o in clean]
        r = calibrate_cameras(NAMES, CAMERAS, obs)
        predicted.append([(cam["position_std_mm"], cam["rotation_std_deg"])
                          for cam in r.cameras[1:]])
        for c in range(1, 4):
            truth = truth_ref_camera(c)
            centres[c].append(r.T_ref_camera[c][:3, 3] - truth[:3, 3])
            angles[c].append(cv2.Rodrigues(r.T_ref_camera[c][:3, :3] @ truth[:3, :3].T)[0]
                             .ravel())
    assert r.cameras[0]["position_std_mm"] == [0.0, 0.0, 0.0]
    for k, c in enumerate(range(1, 4)):
        pos_pred = np.mean([p[k][0] for p in predicted], axis=0)
        pos_seen = np.std(centres[c], axis=0)
        ratio = pos_seen / pos_pred
        assert np.all((ratio > 1 / 1.5) & (ratio < 1.5)), (NAMES[c], pos_seen, pos_pred)
        rot_pred = np.mean([p[k][1] for p in predicted])
        rot_seen = np.degrees(np.sqrt(np.sum(np.var(angles[c], axis=0))))
        assert 1 / 1.5 < rot_seen / rot_pred < 1.5, (NAMES[c], rot_seen, rot_pred)


def knocked_px(key: str, boards: dict, moved: np.ndarray) -> np.ndarray | None:
    """Camera b's truth_px of set ``key`` with b at ``moved``."""
    original = T_BASE_CAMERA[1]
    T_BASE_CAMERA[1] = moved
    try:
        return truth_px(1, boards[key])
    finally:
        T_BASE_CAMERA[1] = original


def test_a_camera_knocked_during_the_session_is_not_cleaned_away_silently():
    """Camera b moves by 6 mm and 0.6 deg after set 20: no single pose explains its images.
    The outlier rule drops the worst images one by one until the rest fit; that many outliers
    is itself warned about, so the result is not taken as clean."""
    obs, boards = scene(noise_px=0.1)
    moved = T_BASE_CAMERA[1] @ transform([0.0, 0.01, 0.0], [6.0, 0.0, 0.0])
    knocked = []
    for o in obs:
        if o.camera == 1 and int(o.set_key) > 20:
            px = knocked_px(o.set_key, boards, moved)
            if px is None:
                continue
            noise = np.random.default_rng(int(o.set_key)).normal(0, 0.1, px.shape)
            o = Observation(1, o.set_key, o.obj, px + noise, o.image)
        knocked.append(o)
    r = calibrate_cameras(NAMES, CAMERAS, knocked)
    outliers = [x for x in r.rejected if "outlier" in x["reason"]]
    assert len(outliers) > 2
    assert any("left out as outliers" in w and "camera that moved" in w for w in r.warnings)
