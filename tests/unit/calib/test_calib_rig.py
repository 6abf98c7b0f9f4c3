"""Stereo rig calibration on a synthetic rig with known truth.

Views are projected with ``cv2.projectPoints`` (the oracle for the camera model) through a
known left camera, right camera and left->right transform; Gaussian pixel noise is added.
Checks: exact recovery without noise, recovery within the predicted standard deviations with
noise, predicted std against the empirical spread over noise draws, outlier pairs, input
errors and warnings.
"""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest

from vgripd.calib.rig import EPIPOLAR_WARN_MEDIAN_PX, calibrate_rig
from vgripd.errors import CalibrationError
from vgripd.geometry.camera_model import CameraModel

SIZE = (640, 480)
K_LEFT = np.array([[800.0, 0.0, 322.0], [0.0, 805.0, 236.0], [0.0, 0.0, 1.0]])
D_LEFT = np.array([-0.25, 0.12, 0.0008, -0.0005, 0.0])
K_RIGHT = np.array([[790.0, 0.0, 318.0], [0.0, 792.0, 244.0], [0.0, 0.0, 1.0]])
D_RIGHT = np.array([-0.22, 0.09, -0.0006, 0.0004, 0.0])
OM = np.array([0.012, -0.035, 0.004])  # rad, X_R = R(OM) X_L + T
T = np.array([-120.0, 1.5, 3.0])  # mm
BOARD = np.array([[c * 30.0, r * 30.0, 0.0] for r in range(6) for c in range(9)])
# The lenses' own model (k1 k2 p1 p2, k3 = 0), for the tests of the fit's statistics: at 0.3 px
# noise the data would drop these small p1 p2 (tests of the choice itself are further down).
TRUE_MODEL = {"fix_k3": True, "fix_tangential": False}


def truth_vector() -> np.ndarray:
    """fx fy cx cy k1 k2 p1 p2 of both cameras, om, T: the parameters compared below."""
    cams = [np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2], D[:4]]
            for K, D in ((K_LEFT, D_LEFT), (K_RIGHT, D_RIGHT))]
    return np.concatenate([*cams, OM, T])


def result_vectors(r) -> tuple[np.ndarray, np.ndarray]:
    """(values, one-sigma std) in the order of ``truth_vector``."""
    vals, stds = [], []
    for cam, std in ((r.left, r.left_std), (r.right, r.right_std)):
        vals.append([cam["fx"], cam["fy"], cam["cx"], cam["cy"], *cam["dist"][:4]])
        stds.append([std["fx"], std["fy"], std["cx"], std["cy"], *std["dist"][:4]])
    return (np.concatenate([*vals, r.rotvec_rad, r.translation_mm]),
            np.concatenate([*stds, r.rotvec_std, r.translation_std]))


def make_views(n: int, seed: int = 1, jitter_mm: float = 0.0) -> tuple[list, list, list]:
    """n board poses at 450-650 mm with tilts up to ~30 degrees, fully seen by both cameras;
    ``jitter_mm``: the board moves by about that much between the left and the right shot."""
    rng = np.random.default_rng(seed)
    obj, left, right = [], [], []
    centre = BOARD.mean(axis=0)
    while len(obj) < n:
        rvec = rng.uniform([-0.5, -0.5, -0.3], [0.5, 0.5, 0.3])
        R = cv2.Rodrigues(rvec)[0]
        tvec = np.r_[rng.uniform(-60, 40), rng.uniform(-50, 50), rng.uniform(450, 650)]
        tvec = tvec - R @ centre
        pl = cv2.projectPoints(BOARD, rvec, tvec, K_LEFT, D_LEFT)[0].reshape(-1, 2)
        moved = tvec + rng.normal(0.0, jitter_mm / np.sqrt(3), 3)
        rv_r, tv_r = cv2.composeRT(rvec, moved, OM, T)[:2]
        pr = cv2.projectPoints(BOARD, rv_r, tv_r, K_RIGHT, D_RIGHT)[0].reshape(-1, 2)
        inside = all(np.all((p > 10) & (p < np.array(SIZE) - 10)) for p in (pl, pr))
        if inside:
            obj.append(BOARD.copy())
            left.append(pl)
            right.append(pr)
    return obj, left, right


def noisy(px: list, sigma: float, rng: np.random.Generator) -> list:
    return [p + rng.normal(0.0, sigma, p.shape) for p in px]


@pytest.fixture(scope="module")
def views() -> tuple[list, list, list]:
    return make_views(12)


def test_noise_free_views_recover_the_truth(views):
    """Up to OpenCV's float32 points (~1e-5 px at 300 px)."""
    obj, left, right = views
    r = calibrate_rig(obj, left, right, SIZE)
    values, _ = result_vectors(r)
    np.testing.assert_allclose(values, truth_vector(), rtol=1e-4, atol=1e-5)
    assert r.rms_px < 1e-4
    assert r.epipolar_px["max"] < 1e-4
    np.testing.assert_allclose(r.T_right_left[:3, :3], cv2.Rodrigues(OM)[0], atol=1e-6)
    assert r.rejected == []


def test_noisy_views_recover_the_truth_within_predicted_std(views):
    """0.3 px noise: every parameter within 4 predicted sigma of the truth; the residual RMS
    estimates the noise (length of a 2D error: sqrt(2) * sigma)."""
    obj, left, right = views
    rng = np.random.default_rng(7)
    r = calibrate_rig(obj, noisy(left, 0.3, rng), noisy(right, 0.3, rng), SIZE, **TRUE_MODEL)
    values, std = result_vectors(r)
    z = (values - truth_vector()) / std
    assert np.all(np.abs(z) < 4), z
    assert r.rms_px == pytest.approx(0.3 * np.sqrt(2), rel=0.1)
    assert 0.05 < r.epipolar_px["median"] < 0.4
    assert r.warnings == []
    assert len(r.parameter_names) == r.covariance.shape[0] == 16 + 6 + 6 * 12


def test_predicted_std_matches_the_empirical_spread(views):
    """Over 12 noise draws the errors normalised by the predicted sigma have RMS ~1 (pooled
    over all 22 parameters), and no parameter's spread is off by more than a factor 2.5."""
    obj, left, right = views
    rng = np.random.default_rng(11)
    errors, stds = [], []
    for _ in range(12):
        r = calibrate_rig(obj, noisy(left, 0.3, rng), noisy(right, 0.3, rng), SIZE, **TRUE_MODEL)
        values, std = result_vectors(r)
        errors.append(values - truth_vector())
        stds.append(std)
    z = np.array(errors) / np.mean(stds, axis=0)
    assert 0.8 < np.sqrt(np.mean(z**2)) < 1.25
    per_parameter = np.sqrt(np.mean(z**2, axis=0))
    assert np.all((per_parameter > 1 / 2.5) & (per_parameter < 2.5)), per_parameter


def test_given_initial_intrinsics_reach_the_same_optimum(views):
    obj, left, right = views
    rng = np.random.default_rng(3)
    left_n, right_n = noisy(left, 0.2, rng), noisy(right, 0.2, rng)
    free = calibrate_rig(obj, left_n, right_n, SIZE, **TRUE_MODEL)
    start = (CameraModel.from_opencv(K_LEFT * [[1.01], [1.01], [1]], np.zeros(5), SIZE),
             CameraModel.from_opencv(K_RIGHT * [[0.99], [0.99], [1]], np.zeros(5), SIZE))
    guided = calibrate_rig(obj, left_n, right_n, SIZE, initial=start, **TRUE_MODEL)
    values, std = result_vectors(free)
    assert np.all(np.abs(result_vectors(guided)[0] - values) < 0.01 * std)


def test_free_k3_estimates_it_with_a_std(views):
    obj, left, right = views
    rng = np.random.default_rng(9)
    r = calibrate_rig(obj, noisy(left, 0.2, rng), noisy(right, 0.2, rng), SIZE, fix_k3=False,
                      fix_tangential=False)
    for cam, std in ((r.left, r.left_std), (r.right, r.right_std)):
        assert std["dist"][4] > 0
        assert abs(cam["dist"][4]) < 4 * std["dist"][4]
    assert len(r.parameter_names) == 18 + 6 + 6 * 12


def test_an_outlier_pair_is_rejected_with_the_reason(views):
    """A pair whose right corners were shifted by several pixels (a wrong image, a moved
    board) is dropped by name, and the rig is recovered from the others."""
    obj, left, right = views
    rng = np.random.default_rng(5)
    left_n, right_n = noisy(left, 0.2, rng), noisy(right, 0.2, rng)
    right_n[4] = right_n[4] + rng.normal(0.0, 4.0, right_n[4].shape)
    names = [(f"L{i}.png", f"R{i}.png") for i in range(len(obj))]
    r = calibrate_rig(obj, left_n, right_n, SIZE, names=names, **TRUE_MODEL)
    assert [(x["left"], x["right"]) for x in r.rejected] == [("L4.png", "R4.png")]
    assert "outlier" in r.rejected[0]["reason"]
    assert ("L4.png", "R4.png") not in r.names
    values, std = result_vectors(r)
    assert np.all(np.abs(values - truth_vector()) < 4 * std)


def test_few_pairs_and_baseline_hint_warn(views):
    obj, left, right = views
    r = calibrate_rig(obj[:5], left[:5], right[:5], SIZE, baseline_hint_mm=200.0)
    text = " | ".join(r.warnings)
    assert "only 5 pairs" in text
    assert "baseline 120.05 mm differs from the expected 200 mm" in text
    ok = calibrate_rig(obj[:5], left[:5], right[:5], SIZE, baseline_hint_mm=121.0)
    assert not any("baseline" in w for w in ok.warnings)


def test_unsynchronised_pairs_give_large_epipolar_residuals_and_a_warning():
    """The board moved by ~2 mm between the left and the right shot of every pair: no rig
    explains that, the epipolar residuals of the calibration images say so."""
    obj, left, right = make_views(12, jitter_mm=2.0)
    r = calibrate_rig(obj, left, right, SIZE)
    assert r.epipolar_px["median"] > EPIPOLAR_WARN_MEDIAN_PX
    assert any("large epipolar residuals" in w for w in r.warnings)


def test_few_noisy_pairs_warn_that_the_baseline_is_uncertain():
    obj, left, right = make_views(4, seed=2)
    rng = np.random.default_rng(4)
    r = calibrate_rig(obj, noisy(left, 1.0, rng), noisy(right, 1.0, rng), SIZE)
    assert any("the baseline is uncertain" in w for w in r.warnings), r.warnings


@pytest.mark.parametrize(("mutate", "message"), [
    (lambda o, pl, pr: (o, pl, pr[:-1]), "object_points has 12 views but px_left 12 and "
                                         "px_right 11"),
    (lambda o, pl, pr: (o, pl, [*pr[:2], pr[2][:-1], *pr[3:]]),
     r"pair 3 left / pair 3 right: right pixels must be \(54, 2\)"),
    (lambda o, pl, pr: (o, [*pl[:1], np.where(np.arange(54)[:, None] == 7, np.nan, pl[1]),
                            *pl[2:]], pr), "pair 2 left / pair 2 right: left pixel 7 is not "
                                           "finite"),
    (lambda o, pl, pr: (o[:2], pl[:2], pr[:2]), "need at least 3 pairs"),
    (lambda o, pl, pr: ([x[:5] for x in o], [x[:5] for x in pl], [x[:5] for x in pr]),
     "only 5 points"),
])
def test_bad_input_is_a_calibration_error_naming_the_view(views, mutate, message):
    obj, left, right = mutate(*views)
    with pytest.raises(CalibrationError, match=message):
        calibrate_rig(obj, left, right, SIZE)


def test_initial_skew_is_refused(views):
    skewed = CameraModel(800.0, 805.0, 322.0, 236.0, skew=1.5)
    with pytest.raises(CalibrationError, match="initial left intrinsics: skew 1.5"):
        calibrate_rig(*views, SIZE, initial=(skewed, skewed))


# ---------------------------------------------------------------- distortion model choice

K_WIDE_LEFT = np.array([[420.0, 0.0, 322.0], [0.0, 418.7, 236.0], [0.0, 0.0, 1.0]])
K_WIDE_RIGHT = np.array([[415.0, 0.0, 318.0], [0.0, 414.0, 244.0], [0.0, 0.0, 1.0]])
D_WIDE_LEFT = np.array([-0.30, 0.10, 0.0, 0.0, -0.01])  # k3 = -0.01, no tangential terms
D_WIDE_RIGHT = np.array([-0.28, 0.09, 0.0, 0.0, -0.01])


def make_wide_views(n: int, seed: int = 0, noise_px: float = 0.1) -> tuple[list, list, list]:
    """n views of the board by a rig of two wide lenses (~75 degrees across), the board at
    250-380 mm and anywhere in the left image, fully seen by both cameras; Gaussian noise."""
    rng = np.random.default_rng(seed)
    obj, left, right = [], [], []
    centre = BOARD.mean(axis=0)
    while len(obj) < n:
        R = (cv2.Rodrigues(np.r_[rng.uniform(-0.6, 0.6, 2), 0.0])[0]
             @ cv2.Rodrigues(np.r_[0.0, 0.0, rng.uniform(-0.5, 0.5)])[0])
        z = rng.uniform(250.0, 380.0)
        aim = np.r_[rng.uniform(-1, 1) * z * 300 / 420, rng.uniform(-1, 1) * z * 220 / 420, z]
        rvec, tvec = cv2.Rodrigues(R)[0].ravel(), aim - R @ centre
        pl = cv2.projectPoints(BOARD, rvec, tvec, K_WIDE_LEFT, D_WIDE_LEFT)[0].reshape(-1, 2)
        rv_r, tv_r = cv2.composeRT(rvec, tvec, OM, T)[:2]
        pr = cv2.projectPoints(BOARD, rv_r, tv_r, K_WIDE_RIGHT, D_WIDE_RIGHT)[0].reshape(-1, 2)
        if all(np.all((p > 2) & (p < np.array(SIZE) - 2)) for p in (pl, pr)):
            obj.append(BOARD.copy())
            left.append(pl + rng.normal(0.0, noise_px, pl.shape))
            right.append(pr + rng.normal(0.0, noise_px, pr.shape))
    return obj, left, right


def test_the_rig_chooses_k3_for_wide_lenses_that_have_it():
    """Both lenses have k3 = -0.01 and no tangential terms: the joint fit chooses k1 k2 k3 for
    both, and k2 lands within 2 sigma of the truth in both cameras; with k3 held at 0 (the old
    default) k2 is many sigmas off."""
    obj, left, right = make_wide_views(15)
    r = calibrate_rig(obj, left, right, SIZE)
    assert r.model.model.name == "k1 k2 k3", r.model.reason
    rows = {c["model"]: c for c in r.model.candidates}
    assert all(c["delta_bic"] > 2.0 for name, c in rows.items() if name != "k1 k2 k3")
    for cam, std, truth in ((r.left, r.left_std, D_WIDE_LEFT), (r.right, r.right_std,
                                                               D_WIDE_RIGHT)):
        assert abs(cam["dist"][1] - truth[1]) < 2 * std["dist"][1]
        assert abs(cam["dist"][4] - truth[4]) < 2 * std["dist"][4]
        assert cam["dist"][2] == cam["dist"][3] == 0.0
    assert "left.k3" in r.parameter_names
    assert "left.p1" not in r.parameter_names
    fixed = rows["k1 k2"]  # what the old default k3 = 0 gives
    for key, truth in (("dist", D_WIDE_LEFT), ("right_dist", D_WIDE_RIGHT)):
        assert abs(fixed[key][1] - truth[1]) > 5 * fixed[key + "_std"][1]
    held = calibrate_rig(obj, left, right, SIZE, fix_k3=True, fix_tangential=True)
    assert (held.model.model.name, held.model.chosen_by) == ("k1 k2", "options")
    assert held.left["dist"][4] == 0.0


def test_a_held_term_is_zero_even_if_the_initial_intrinsics_had_it(views):
    obj, left, right = views
    start = (CameraModel.from_opencv(K_LEFT, np.r_[D_LEFT[:4], 0.02], SIZE),
             CameraModel.from_opencv(K_RIGHT, np.r_[D_RIGHT[:4], -0.02], SIZE))
    r = calibrate_rig(obj, left, right, SIZE, initial=start, fix_k3=True)
    assert r.left["dist"][4] == r.right["dist"][4] == 0.0


# ---------------------------------------------------------------- pair consistency


def test_pairs_shifted_by_one_are_refused_with_the_shift_named(views):
    """left i with right i+1 (a right image missing at the start): each pair's left->right
    pose is a different one; the message names the pairs and the shift that fits."""
    obj, left, right = views
    names = [(f"L{i}.png", f"R{i + 1}.png") for i in range(11)]
    with pytest.raises(CalibrationError) as err:
        calibrate_rig(obj[:11], left[:11], right[1:], SIZE, names=names)
    text = str(err.value)
    assert "left and right images are not consistent pairs: 11 of 11 pairs disagree" in text
    assert re.search(r"\): L\d+\.png / R\d+\.png \(\d+\.\d deg, \d+ mm\), L", text)
    assert ("fit the rig when left i goes with right i-1 (from L1.png with R1.png): the right "
            "images are shifted by 1") in text
    assert "\n" not in text


def test_pairs_shifted_with_given_intrinsics_are_refused_too(views):
    obj, left, right = views
    start = (CameraModel.from_opencv(K_LEFT, D_LEFT, SIZE),
             CameraModel.from_opencv(K_RIGHT, D_RIGHT, SIZE))
    with pytest.raises(CalibrationError, match="right images are shifted by 1"):
        calibrate_rig(obj[1:], left[1:], right[:-1], SIZE, initial=start)


def test_a_wrong_partner_is_named_among_good_pairs(views):
    """Two right images swapped: those two pairs disagree with the rig of the other ten."""
    obj, left, right = views
    right = list(right)
    right[3], right[8] = right[8], right[3]
    names = [(f"L{i}.png", f"R{i}.png") for i in range(12)]
    with pytest.raises(CalibrationError, match=(
            r"2 of 12 pairs disagree with the rig of the other 10 .*: (L3\.png / R3\.png|L8\.png "
            r"/ R8\.png) \(\d+\.\d deg, \d+ mm\), (L3|L8)\.png .*Likely: pairs shifted")):
        calibrate_rig(obj, left, right, SIZE, names=names)


def test_noise_and_an_outlier_pair_do_not_look_like_wrong_pairs(views):
    """1 px noise on 4 pairs, or one pair with 4 px errors: the poses still agree."""
    obj, left, right = make_views(4, seed=2)
    rng = np.random.default_rng(4)
    calibrate_rig(obj, noisy(left, 1.0, rng), noisy(right, 1.0, rng), SIZE)
    obj, left, right = views
    right = noisy(right, 0.2, rng)
    right[4] = right[4] + rng.normal(0.0, 4.0, right[4].shape)
    calibrate_rig(obj, noisy(left, 0.2, rng), right, SIZE, **TRUE_MODEL)
