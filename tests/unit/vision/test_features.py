"""Feature finders and correspondence against rendered ground truth.

Marks are rendered by supersampling (area coverage of a disc per pixel, 8x8 samples), then
blurred (Gaussian, sigma 1.2 px), lit unevenly (a 0.6..1.0 ramp across the image) and given
Gaussian noise (sigma 3 grey levels), so the true centre is known to about 0.01 px.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vgripd.vision import features as ft

SS = 8  # supersampling factor of the renderer


def render_discs(shape, discs, polarity="dark", noise=3.0, blur=1.2, seed=0):
    """Grey image with discs (cx, cy, r) in px; returns uint8 image."""
    h, w = shape
    rng = np.random.default_rng(seed)
    fg, bg = (50.0, 200.0) if polarity == "dark" else (230.0, 80.0)
    img = np.full((h, w), bg)
    for cx, cy, r in discs:
        x0, y0 = int(cx - r - 2), int(cy - r - 2)
        x1, y1 = int(cx + r + 3), int(cy + r + 3)
        sy, sx = np.mgrid[y0 * SS : y1 * SS, x0 * SS : x1 * SS]
        inside = ((sx + 0.5) / SS - 0.5 - cx) ** 2 + ((sy + 0.5) / SS - 0.5 - cy) ** 2 <= r * r
        cover = inside.reshape(y1 - y0, SS, x1 - x0, SS).mean(axis=(1, 3))
        img[y0:y1, x0:x1] = img[y0:y1, x0:x1] * (1 - cover) + fg * cover
    img *= np.linspace(0.6, 1.0, w)[None, :]
    img = cv2.GaussianBlur(img, (0, 0), blur) + rng.normal(0.0, noise, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def random_discs(rng, n, shape, r_range=(6.0, 16.0)):
    h, w = shape
    discs: list[tuple[float, float, float]] = []
    while len(discs) < n:
        c = (rng.uniform(60, w - 60), rng.uniform(60, h - 60), rng.uniform(*r_range))
        if all(np.hypot(c[0] - d[0], c[1] - d[1]) > 4 * max(c[2], d[2]) for d in discs):
            discs.append(c)
    return discs


def nearest_errors(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    d = np.linalg.norm(found[:, None, :] - truth[None, :, :2], axis=2)
    return d.min(axis=0)


@pytest.mark.parametrize("polarity", ["dark", "bright"])
@pytest.mark.parametrize("downscale", [1, 2, 4])
def test_circle_centres_subpixel(polarity, downscale):
    rng = np.random.default_rng(7)
    shape = (600, 800)
    discs = random_discs(rng, 10, shape)
    img = render_discs(shape, discs, polarity=polarity, seed=downscale)
    spec = ft.CircleSpec(polarity=polarity, min_diameter_px=10, max_diameter_px=36,
                         downscale=downscale)
    blobs = ft.find_circles(img, spec)
    truth = np.array(discs)
    assert len(blobs) == len(discs)
    # Centroid noise: sigma_I / contrast * sqrt(sum r^2 over the window) / area, about 0.02 px
    # here; the bound is 5x that.
    assert nearest_errors(blobs.xy, truth).max() < 0.1
    # Equivalent diameter from the mark fraction: within a pixel of the truth.
    d_err = np.abs(np.sort(blobs.diameter_px) - np.sort(2 * truth[:, 2]))
    assert d_err.max() < 1.0


def test_circle_filters_size_shape_border_and_polarity():
    shape = (400, 600)
    img = render_discs(shape, [(100.5, 100.25, 10.0), (300.0, 200.0, 3.0), (500.0, 200.0, 40.0)])
    cv2.rectangle(img, (200, 300), (320, 312), 50, -1)  # a bar: not circular
    cv2.circle(img, (3, 200), 10, 50, -1)  # cut by the left border
    spec = ft.CircleSpec(min_diameter_px=12, max_diameter_px=40, downscale=2)
    blobs = ft.find_circles(img, spec)
    assert blobs.xy.shape == (1, 2)
    np.testing.assert_allclose(blobs.xy[0], (100.5, 100.25), atol=0.1)
    bright = ft.find_circles(img, ft.CircleSpec(polarity="bright", min_diameter_px=12,
                                                max_diameter_px=40))
    assert len(bright) == 0


def test_gray_from_image_rejects_bad_arrays():
    assert ft.gray_from_image(np.zeros((4, 5, 3), np.uint8)).shape == (4, 5)
    with pytest.raises(ValueError, match="dtype"):
        ft.gray_from_image(np.zeros((4, 5), np.uint16))
    with pytest.raises(ValueError, match="shape"):
        ft.gray_from_image(np.zeros((4, 5, 4), np.uint8))


def test_aruco_centre_is_projected_square_centre():
    # A marker warped by a perspective homography: its centre must be H applied to the centre
    # of the square, which differs from the mean of the corners.
    side = 200
    marker = cv2.aruco.generateImageMarker(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), 7, side)
    canvas = np.full((side + 80, side + 80), 255, np.uint8)
    canvas[40:40 + side, 40:40 + side] = marker
    src = np.array([[40, 40], [40 + side, 40], [40 + side, 40 + side], [40, 40 + side]],
                   np.float32) - 0.5
    dst = np.array([[210, 150], [420, 170], [440, 390], [190, 350]], np.float32)
    H = cv2.getPerspectiveTransform(src, dst)
    img = cv2.warpPerspective(canvas, H, (640, 480), flags=cv2.INTER_LINEAR,
                              borderValue=255)
    found = ft.find_aruco(img, "DICT_4X4_50")
    assert set(found) == {7}
    centre = cv2.perspectiveTransform(np.array([[[40 + side / 2 - 0.5] * 2]], np.float32), H)
    np.testing.assert_allclose(found[7].centre, centre.reshape(2), atol=0.5)
    assert np.linalg.norm(found[7].corners.mean(axis=0) - centre.reshape(2)) > 1.0
    with pytest.raises(ValueError, match="unknown ArUco"):
        ft.aruco_dictionary("DICT_NOPE")


def test_template_subpixel_peak():
    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (300, 400)), (0, 0), 2.0)
    base = cv2.normalize(texture, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    patch = base[100:141, 150:191].copy()  # centre (170, 120)
    for dx, dy in [(0.0, 0.0), (0.3, -0.4), (-0.45, 0.2)]:
        M = np.float32([[1, 0, dx], [0, 1, dy]])
        shifted = cv2.warpAffine(base, M, (400, 300), flags=cv2.INTER_CUBIC)
        hit = ft.find_template(shifted, patch, 0.7)
        assert hit is not None
        np.testing.assert_allclose(hit[0], (170 + dx, 120 + dy), atol=0.15)
    assert ft.find_template(np.full((300, 400), 128, np.uint8), patch, 0.7) is None


def test_match_epipolar_keeps_all_partners_within_tolerance():
    d = np.array([[0.5, 9.0, 2.0], [7.0, 0.1, 8.0]])
    pairs = ft.match_epipolar(d, 2.5)
    assert pairs.tolist() == [[0, 0], [0, 2], [1, 1]]
    plausible = np.array([[False, True, True], [True, True, True]])
    assert ft.match_epipolar(d, 2.5, plausible).tolist() == [[0, 2], [1, 1]]


def _scene(rng, n_model=8, n_spurious=20, noise=0.1, drop=()):
    model = rng.uniform(-80, 80, (n_model, 3)) * (1, 1, 0.2)
    R = Rotation.random(random_state=rng)
    t = np.array([20.0, -10.0, 700.0])
    measured = R.apply(model) + t + rng.normal(0, noise, (n_model, 3))
    keep = [i for i in range(n_model) if i not in drop]
    spurious = t + rng.uniform(-120, 120, (n_spurious, 3))
    points = np.vstack([measured[keep], spurious])
    perm = rng.permutation(len(points))
    points = points[perm]
    where = {int(np.flatnonzero(perm == k)[0]): keep[k] for k in range(len(keep))}
    return model, points, where, R, t


@pytest.mark.parametrize("seed", range(5))
def test_match_model_with_spurious_and_missing_points(seed):
    rng = np.random.default_rng(seed)
    model, points, where, R, t = _scene(rng, drop=(seed % 8,))
    match = ft.match_model(model, points, tolerance_mm=1.0)
    assert match is not None
    assert not match.ambiguous
    expected = np.full(len(model), -1)
    for p, m in where.items():
        expected[m] = p
    np.testing.assert_array_equal(match.assignment, expected)
    # The seed's rigid motion is the true one within the noise (oracle: scipy Rotation).
    err = Rotation.from_matrix(match.T_points_model[:3, :3]) * R.inv()
    assert np.degrees(err.magnitude()) < 1.0


def test_match_model_exclusive_keys_and_no_match():
    rng = np.random.default_rng(11)
    model, points, _, _, _ = _scene(rng, n_spurious=0, noise=0.0)
    # Two alternatives for one blob (same key): only one may be used.
    dup = np.vstack([points, points[:1] + 0.3])
    keys = [(i,) for i in range(len(points))] + [(0,)]
    match = ft.match_model(model, dup, 1.0, keys)
    assert match is not None
    used = match.assignment[match.assignment >= 0]
    assert not ({0, len(points)} <= set(used.tolist()))
    far = rng.uniform(-1000, 1000, (2, 3))
    assert ft.match_model(model, far, 1.0) is None


def test_match_model_reports_symmetric_model_as_ambiguous():
    # A square: rotating it by 90 deg maps the model onto itself with a different assignment.
    model = np.array([[0, 0, 0], [100, 0, 0], [100, 100, 0], [0, 100, 0]], float)
    points = model + (5.0, 5.0, 600.0)
    match = ft.match_model(model, points, 1.0)
    assert match is not None
    assert match.ambiguous


def _layout(rng, n):
    """n marks on a 200 x 150 mm plate, some on bosses, at least 25 mm apart."""
    marks: list[np.ndarray] = []
    while len(marks) < n:
        p = np.r_[rng.uniform([-100, -75], [100, 75]), rng.choice([0.0, 0.0, 12.0, 20.0])]
        if all(np.linalg.norm(p[:2] - q[:2]) > 25 for q in marks):
            marks.append(p)
    return np.array(marks)


def test_match_model_finds_every_subset_of_visible_marks():
    # Every subset of >= 3 of 8 marks, among 12 spurious points on the plate's plane and above
    # it, noise 0.05 mm. >= 4 visible: exactly the true assignment, not ambiguous; 3 visible:
    # the true assignment (possibly flagged ambiguous by a clutter triangle), never a wrong
    # assignment that is not flagged.
    rng = np.random.default_rng(3)
    model = _layout(rng, 8)
    R = Rotation.from_rotvec([0.1, -0.2, 2.0])
    t = np.array([15.0, -20.0, 690.0])
    measured = R.apply(model) + t + rng.normal(0, 0.05, model.shape)
    spurious = R.apply(np.c_[rng.uniform(-120, 120, (12, 2)), rng.uniform(-5, 25, 12)]) + t
    from itertools import combinations

    tried = 0
    for k in range(3, 9):
        for shown in combinations(range(8), k):
            points = np.vstack([measured[list(shown)], spurious])
            match = ft.match_model(model, points, 3.0, max_rms_mm=1.0)
            assert match is not None
            expected = np.full(8, -1)
            expected[list(shown)] = np.arange(k)
            right = np.array_equal(match.assignment, expected)
            if k >= 4:
                assert right, shown
                assert not match.ambiguous, shown
                assert match.complete, shown
            else:
                assert right or match.ambiguous, shown
            tried += 1
    assert tried == 219


def test_match_model_work_stops_early_when_all_marks_are_seen():
    rng = np.random.default_rng(5)
    for n in (6, 12, 20):
        model = _layout(rng, n)
        points = np.vstack([model + (3.0, 4.0, 700.0), rng.uniform(-100, 100, (20, 3)) + 700])
        match = ft.match_model(model, points, 3.0, max_rms_mm=1.0)
        assert match is not None
        assert match.count == n
        # One seed triangle explains everything: nothing unseen could rival it.
        assert match.hypotheses <= 3, (n, match.hypotheses)


def test_match_model_work_bound_makes_an_unfinished_search_ambiguous():
    # Four of eight marks among spurious points: the full search must try the triples of six
    # marks. Cut short by max_seeds, a search that could still have missed a rival says so.
    rng = np.random.default_rng(9)
    model = _layout(rng, 8)
    shown = [1, 3, 4, 6]
    points = np.vstack([model[shown], rng.uniform(-120, 120, (12, 3)) * (1, 1, 0.1)]) + 700.0
    expected = np.full(8, -1)
    expected[shown] = np.arange(4)
    full = ft.match_model(model, points, 3.0, max_rms_mm=1.0)
    assert full is not None
    assert full.complete
    assert not full.ambiguous
    np.testing.assert_array_equal(full.assignment, expected)
    cut = 0
    for budget in (1, 3, 10, 30, 100, 300, 1000):
        match = ft.match_model(model, points, 3.0, max_rms_mm=1.0, max_seeds=budget)
        if match is None:
            continue
        cut += not match.complete
        assert match.complete or match.ambiguous
        if not match.ambiguous:
            np.testing.assert_array_equal(match.assignment, expected)
    assert cut >= 2
    # A regular grid: the model fits in many places, found and flagged.
    g = np.arange(6) * 20.0
    grid = np.array([(x, y, 0.0) for x in g for y in g])
    match = ft.match_model(grid[[0, 7, 14, 21, 2, 30, 33, 11]], grid + 700.0, 1.0)
    assert match is not None
    assert match.count == 8
    assert match.ambiguous


def test_match_model_drops_one_gross_outlier_but_not_a_uniform_misfit():
    rng = np.random.default_rng(8)
    model = _layout(rng, 6)
    points = model[:5] + (0.0, 0.0, 700.0)
    # A blob 2.5 mm from where the hidden sixth mark would be: inside the 3 mm tolerance, but
    # it lifts the RMS of the six over a 0.5 mm gate. It is dropped; the five marks stay.
    blob = model[5] + (0.0, 0.0, 700.0) + (2.5, 0.0, 0.0)
    points = np.vstack([points, blob])
    with_blob = ft.match_model(model, points, 3.0)
    assert with_blob is not None
    assert with_blob.count == 6
    assert with_blob.rms_mm > 0.5
    match = ft.match_model(model, points, 3.0, max_rms_mm=0.5)
    assert match is not None
    assert match.assignment.tolist() == [0, 1, 2, 3, 4, -1]
    assert match.rms_mm < 0.01
    # Every point off in proportion to its distance from the centre (a scale error, like a
    # drifted calibration): no point stands out, nothing is dropped, and the residual gate of
    # the pipeline judges the whole fit.
    scaled = (model - model.mean(axis=0)) * 1.015 + (0.0, 0.0, 700.0)
    match = ft.match_model(model, scaled, 3.0, max_rms_mm=0.5)
    assert match is not None
    assert match.count == 6
    assert match.rms_mm > 0.5


def test_match_model_in_dense_clutter_never_trusts_a_coincidence():
    # Twenty marks (a 260 x 200 mm plate) among holes on its plane, 40 candidates in all:
    # four clutter points can fall within the tolerance of four marks' places and fit within
    # the RMS gate. Such a pose must come out ambiguous (a rival, or an expected number of
    # chance matches >= 1), never as an unflagged wrong pose.
    rng = np.random.default_rng(20)
    model = _layout(rng, 20) * (1.3, 1.3, 1.0)
    R = Rotation.from_rotvec([0.1, -0.2, 2.0])
    t = np.array([15.0, -20.0, 690.0])
    measured = R.apply(model) + t + rng.normal(0, 0.05, model.shape)
    wrong_flagged = 0
    for k in (3, 4, 5, 10):
        for _ in range(4):
            shown = np.sort(rng.choice(20, k, replace=False))
            holes = np.c_[rng.uniform(-150, 150, (40 - k, 2)), np.zeros(40 - k)]
            points = np.vstack([measured[shown], R.apply(holes) + t])
            match = ft.match_model(model, points, 3.0, max_rms_mm=1.0)
            assert match is not None
            expected = np.full(20, -1)
            expected[shown] = np.arange(k)
            # Right pose: every visible mark assigned as itself (a hole may sit on a hidden
            # mark's place and be taken for it, the pose is still right).
            right = (match.assignment[shown] == expected[shown]).all()
            if k >= 10:
                assert right, shown
                assert not match.ambiguous, shown
            elif not right:
                assert match.ambiguous, (shown, match)
                wrong_flagged += 1
    assert wrong_flagged >= 1  # the scene does produce coincidences


@pytest.mark.parametrize("gap_px", [4.0, 8.0, 14.0])
def test_circle_centres_of_marks_closer_than_their_windows(gap_px):
    """Marks of touching plates (pick lists): a neighbour inside the refinement window pulls a
    centre towards it (2 px at a 4 px gap); with ``separate_neighbours`` each mark keeps the
    pixels nearer to its own coarse centre. An isolated mark keeps exactly the centre it had
    (no neighbours: nothing changes), and without the option the finder is as before."""
    r = 13.0
    discs = [(200.3, 300.6, r), (200.3 + 2 * r + gap_px, 300.6 - 3.1, r), (600.4, 250.2, r)]
    img = render_discs((500, 800), discs, seed=int(gap_px))
    spec = ft.CircleSpec(polarity="dark", min_diameter_px=10, max_diameter_px=36,
                         min_contrast=20, min_circularity=0.6, downscale=2,
                         separate_neighbours=True)
    blobs = ft.find_circles(img, spec)
    assert len(blobs) == 3
    err = nearest_errors(blobs.xy, np.array(discs))
    assert err.max() < 0.1, err
    # Off (one object): the finder as before, the isolated mark's centre unchanged.
    before = ft.find_circles(img, dataclasses.replace(spec, separate_neighbours=False))
    if gap_px <= 4.0:
        assert nearest_errors(before.xy, np.array(discs))[:2].max() > 0.5
    k0 = int(np.argmin(np.linalg.norm(before.xy - discs[2][:2], axis=1)))
    k1 = int(np.argmin(np.linalg.norm(blobs.xy - discs[2][:2], axis=1)))
    assert tuple(before.xy[k0]) == tuple(blobs.xy[k1])
    # The isolated mark: the same centre as a refinement that knows of no neighbour.
    k = int(np.argmin(np.linalg.norm(blobs.xy - discs[2][:2], axis=1)))
    alone = ft._refine_centre(img, *blobs.xy[k], 2 * r, "dark")
    assert alone is not None
    again = ft._refine_centre(img, *blobs.xy[k], 2 * r, "dark", np.zeros((0, 2)))
    assert again == alone


@pytest.mark.parametrize("s", [2, 3, 4, 8])
def test_shrink_is_the_block_mean_of_inter_area(s: int) -> None:
    rng = np.random.default_rng(s)
    for h, w in ((2048, 2448), (1001, 777)):  # the second does not divide: INTER_AREA itself
        gray = rng.integers(0, 256, (h, w), dtype=np.uint8)
        got = ft.shrink(gray, s)
        want = cv2.resize(gray, (w // s, h // s), interpolation=cv2.INTER_AREA)
        assert got.shape == want.shape
        assert got.dtype == np.uint8
        assert np.abs(got.astype(int) - want).max() <= 1
