"""Single-camera calibration against a known camera.

Two kinds of synthetic data: board images rendered through the camera (detection + fit, the
CLI end to end), and exact projections (cv2.projectPoints) with controlled noise and
corruption, for the fit's bookkeeping (outliers, too few points, warnings) and the choice of
the distortion model (k3, p1 p2) from the data.
"""

from __future__ import annotations

import contextlib
import io
import json
import re
import tomllib

import cv2
import numpy as np
import pytest
from test_calib_boards import render

from vgripd.__main__ import main
from vgripd.calib.boards import Board, Detection, detect_files
from vgripd.calib.intrinsics import calibrate_intrinsics, empty_regions
from vgripd.errors import CalibrationError

BOARD = Board.parse("chessboard:9x6:30")
SIZE = (640, 480)
K_TRUE = np.array([[610.0, 0, 318.0], [0, 606.0, 244.0], [0, 0, 1]])
DIST_TRUE = np.array([-0.21, 0.09, 0.0012, -0.0007, 0.0])


def poses(n: int, seed: int = 1, spread: float = 1.0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Board poses (rvec, tvec) looking at the board from varied tilts, rolls and offsets;
    ``spread`` < 1 keeps the board near the image centre."""
    rng = np.random.default_rng(seed)
    centre = BOARD.object_points().mean(axis=0)
    out = []
    for _ in range(n):
        tilt = rng.uniform(-0.45, 0.45, 2)
        roll = rng.uniform(-0.5, 0.5)
        R = cv2.Rodrigues(np.array([tilt[0], tilt[1], 0.0]))[0] @ cv2.Rodrigues(np.array([0, 0, roll]))[0]
        aim = np.array([*(spread * rng.uniform(-110, 110, 2) * np.array([1.0, 0.8])), rng.uniform(430, 560)])
        out.append((cv2.Rodrigues(R)[0].ravel(), aim - R @ centre))
    return out


def projected(views, noise_px=0.05, seed=2, dist=DIST_TRUE) -> list[Detection]:
    rng = np.random.default_rng(seed)
    dets = []
    for i, (rvec, tvec) in enumerate(views):
        px, _ = cv2.projectPoints(BOARD.object_points(), rvec, tvec, K_TRUE, dist)
        px = px.reshape(-1, 2) + rng.normal(0, noise_px, (BOARD.n_points, 2))
        assert np.all((px > 0) & (px < SIZE)), "pose puts the board outside the image"
        dets.append(Detection(f"view{i}", SIZE, np.arange(BOARD.n_points), px))
    return dets


# ---------------------------------------------------------------- rendered images


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """12 rendered board images in a folder, with their true poses."""
    folder = tmp_path_factory.mktemp("rendered")
    views = poses(12)
    for i, (rvec, tvec) in enumerate(views):
        cv2.imwrite(str(folder / f"img{i:02d}.png"),
                    render(BOARD, rvec, tvec, K=K_TRUE, dist=DIST_TRUE, seed=i))
    return folder, views


def test_recovers_the_rendering_camera(rendered):
    folder, views = rendered
    found, failed = detect_files(BOARD, sorted(folder.glob("*.png")))
    assert failed == []
    r = calibrate_intrinsics(BOARD, found, SIZE)
    cam, std = r.camera, r.std
    truth = {"fx": K_TRUE[0, 0], "fy": K_TRUE[1, 1], "cx": K_TRUE[0, 2], "cy": K_TRUE[1, 2]}
    for key, value in truth.items():
        assert abs(cam[key] - value) < max(4 * std[key], 0.3), (key, cam[key], std[key])
        assert 0 < std[key] < 1.0
    assert np.all(np.abs(np.subtract(cam["dist"][:4], DIST_TRUE[:4])) < [0.004, 0.02, 3e-4, 3e-4])
    assert cam["dist"][4] == 0.0
    assert std["dist"][4] == 0.0
    assert r.rms_px < 0.1
    assert r.rejected == []
    # the board poses are the rendering poses
    for T, (rvec, tvec) in zip(r.T_cam_board, views, strict=True):
        np.testing.assert_allclose(T[:3, 3], tvec, atol=1.5)
        np.testing.assert_allclose(T[:3, :3], cv2.Rodrigues(rvec)[0], atol=3e-3)
    # residuals are observed - projected with the result
    proj, _ = cv2.projectPoints(BOARD.object_points(), r.rvecs[0], r.tvecs[0], r.camera_matrix, r.dist_coeffs)
    np.testing.assert_allclose(r.residuals_px[0], found[0].px - proj.reshape(-1, 2), atol=1e-9)


def run_cli(*argv: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(["calibrate", "intrinsics", *argv])
    return rc, out.getvalue(), err.getvalue()


def test_cli_human_output_report_and_right_camera(rendered, tmp_path, monkeypatch):
    folder, _ = rendered
    (folder / "blank.png").unlink(missing_ok=True)
    cv2.imwrite(str(folder / "blank.png"), np.full((480, 640), 90, np.uint8))
    monkeypatch.chdir(folder)  # the glob is relative to the current directory
    try:
        rc, out, err = run_cli("--images", "*.png", "--board", BOARD.spec, "--camera", "right",
                               "-o", str(tmp_path / "cam.toml"), "--report", str(tmp_path / "r.png"))
    finally:
        (folder / "blank.png").unlink()
    assert rc == 0
    assert "img00.png" in out
    assert "fx " in out
    assert "+-" in out
    assert "blank.png: board not found: no 9x6 corner grid found" in out
    data = tomllib.loads((tmp_path / "cam.toml").read_text())
    assert set(data["calibration"]) == {"right"}
    assert data["about"]["rejected"] == [{"image": "blank.png", "reason": "board not found: no 9x6 corner grid found"}]
    assert data["about"]["board"] == "chessboard:9x6:30"
    assert abs(data["calibration"]["right"]["fx"] - 610.0) < 1.0
    report = cv2.imread(str(tmp_path / "r.png"))
    assert report is not None
    assert report.shape[1] > 640


def test_cli_errors_name_the_glob_and_the_failures(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rc, _, err = run_cli("--images", "nothing/*.png", "--board", "chessboard:9x6:30")
    assert rc == 1
    assert "--images 'nothing/*.png': no file matches" in err
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"b{i}.png"), np.full((480, 640), 100, np.uint8))
    rc, _, err = run_cli("--images", "b*.png", "--board", "chessboard:9x6:30")
    assert rc == 1
    assert "found in 0 of 3 images (need at least 3): b0.png: board not found" in err
    rc, _, err = run_cli("--images", "b*.png", "--board", "chessboard:9x6")
    assert rc == 1
    assert "expected chessboard:COLSxROWS:PITCH_MM" in err
    assert not (tmp_path / "camera.toml").exists()


# ---------------------------------------------------------------- exact projections


def test_an_image_with_bad_corners_is_rejected_and_the_rest_refit():
    dets = projected(poses(12))
    truth_fit = calibrate_intrinsics(BOARD, dets, SIZE)
    rng = np.random.default_rng(5)
    dets[4].px = dets[4].px + rng.normal(0, 1.5, dets[4].px.shape)  # a blurred, misdetected view
    r = calibrate_intrinsics(BOARD, dets, SIZE)
    assert [x["image"] for x in r.rejected] == ["view4"]
    m = re.fullmatch(r"per-image RMS (\d+\.\d+) px vs median (\d+\.\d+) px \(outlier: > 3x median\)",
                     r.rejected[0]["reason"])
    assert m, r.rejected[0]["reason"]
    assert float(m[1]) > 1.0 > 0.1 > float(m[2])
    assert "view4" not in [p["image"] for p in r.per_image]
    assert len(r.detections) == 11
    for key in ("fx", "fy", "cx", "cy"):
        assert abs(r.camera[key] - truth_fit.camera[key]) < 3 * truth_fit.std[key] + 0.05


def test_too_few_points_and_too_few_images():
    dets = projected(poses(4))
    few = Detection("partial", SIZE, dets[0].ids[:5], dets[0].px[:5])
    r = calibrate_intrinsics(BOARD, [few, *dets[1:]], SIZE)
    assert r.rejected == [{"image": "partial", "reason": "only 5 board points (need at least 8)"}]
    with pytest.raises(CalibrationError, match=r"need at least 3 images with the board chessboard:9x6:30, have 2 \(1 rejected\)"):
        calibrate_intrinsics(BOARD, [few, *dets[1:3]], SIZE)
    with pytest.raises(CalibrationError, match="view0: image size 640x480 is not the calibrated 800x600"):
        calibrate_intrinsics(BOARD, dets, (800, 600))


def test_free_k3_is_estimated_and_fixed_k3_stays_zero():
    dist = np.array([-0.25, 0.12, 0.0, 0.0, -0.05])
    dets = projected(poses(15), noise_px=0.02, dist=dist)
    free = calibrate_intrinsics(BOARD, dets, SIZE, fix_k3=False)
    assert abs(free.camera["dist"][4] - dist[4]) < max(4 * free.std["dist"][4], 0.01)
    assert free.std["dist"][4] > 0
    fixed = calibrate_intrinsics(BOARD, dets, SIZE, fix_k3=True)
    assert fixed.camera["dist"][4] == 0.0
    assert fixed.rms_px > free.rms_px


def test_warnings_for_few_images_and_poor_coverage():
    far = [(rvec, tvec * 1.8) for rvec, tvec in poses(5, spread=0.0)]  # small, in the centre
    central = projected(far, noise_px=0.05)
    r = calibrate_intrinsics(BOARD, central, SIZE)
    text = "\n".join(r.warnings)
    assert "only 5 images used" in text
    assert re.search(r"no board point in the image's [a-z, -]*bottom-right \(3x3 grid\)", text)
    wide = calibrate_intrinsics(BOARD, projected(poses(12)), SIZE)
    assert wide.warnings == []


def test_empty_regions():
    pts = np.array([[10.0, 10.0], [630.0, 470.0], [320.0, 240.0]])
    det = Detection("x", SIZE, np.arange(3), pts)
    assert empty_regions([det], SIZE) == ["top", "top-right", "left", "right", "bottom-left", "bottom"]


def test_json_summary_keys(rendered, tmp_path):
    folder, _ = rendered
    rc, out, _ = run_cli("--images", str(folder / "img0*.png"), "--board", BOARD.spec,
                         "-o", str(tmp_path / "c.toml"), "--json", "--free-k3")
    assert rc == 0
    summary = json.loads(out)
    assert set(summary) == {"camera", "std", "std_model", "rms_px", "model", "per_image", "rejected", "warnings",
                            "output"}
    assert summary["model"]["chosen_by"] == "BIC"  # k3 given, p1 p2 chosen
    assert [c["model"] for c in summary["model"]["candidates"]] == ["k1 k2 k3", "k1 k2 p1 p2 k3"]
    assert set(summary["camera"]) == {"fx", "fy", "cx", "cy", "skew", "dist", "width", "height"}
    assert set(summary["std"]) == {"fx", "fy", "cx", "cy", "skew", "dist"}
    assert summary["std"]["dist"][4] > 0  # k3 was free
    assert [p["image"] for p in summary["per_image"]] == [str(folder / f"img{i:02d}.png") for i in range(10)]


# ---------------------------------------------------------------- distortion model choice

# A wide lens (about 75 degrees across 640 px): the board reaches radii where k3 = -0.01 moves
# corners by pixels, so 15 views with 0.1 px noise resolve it.
K_WIDE = np.array([[420.0, 0, 322.0], [0, 418.7, 236.0], [0, 0, 1]])
LENSES = {  # name: (dist, the model that describes it)
    "k3": ([-0.30, 0.10, 0.0, 0.0, -0.01], "k1 k2 k3"),
    "plain": ([-0.30, 0.10, 0.0, 0.0, 0.0], "k1 k2"),
    "tangential": ([-0.30, 0.10, 0.004, -0.003, 0.0], "k1 k2 p1 p2"),
}


def wide_views(dist, n: int = 15, noise_px: float = 0.1, seed: int = 0) -> list[Detection]:
    """n views of the board through K_WIDE and ``dist`` (cv2.projectPoints), spread over the
    whole image (corners included), tilted up to ~35 degrees, with Gaussian pixel noise."""
    rng = np.random.default_rng(seed)
    obj = BOARD.object_points()
    centre = obj.mean(axis=0)
    dets: list[Detection] = []
    while len(dets) < n:
        R = (cv2.Rodrigues(np.r_[rng.uniform(-0.6, 0.6, 2), 0.0])[0]
             @ cv2.Rodrigues(np.r_[0.0, 0.0, rng.uniform(-0.6, 0.6)])[0])
        z = rng.uniform(260.0, 360.0)
        aim = np.r_[rng.uniform(-1, 1) * z * 300 / 420, rng.uniform(-1, 1) * z * 220 / 420, z]
        px = cv2.projectPoints(obj, cv2.Rodrigues(R)[0], aim - R @ centre, K_WIDE,
                               np.asarray(dist))[0].reshape(-1, 2)
        if np.all((px > 2) & (px < np.array(SIZE) - 2)):
            dets.append(Detection(f"view{len(dets)}", SIZE, np.arange(len(obj)),
                                  px + rng.normal(0.0, noise_px, px.shape)))
    return dets


@pytest.mark.parametrize("lens", list(LENSES))
def test_the_distortion_model_is_chosen_from_the_data(lens):
    """The chosen model is the lens's own, k2 is within 2 sigma of the truth, the held terms
    are exactly 0, and every candidate is reported. For the k3 lens, the old default (k3
    fixed at 0) puts k2 many of its sigmas off (the issue: 3.8 sigma)."""
    dist, expected = LENSES[lens]
    r = calibrate_intrinsics(BOARD, wide_views(dist), SIZE)
    assert r.model.model.name == expected, r.model.reason
    assert r.model.chosen_by == "BIC"
    cam, std = r.camera, r.std
    assert abs(cam["dist"][1] - dist[1]) < 2 * std["dist"][1], (cam["dist"][1], std["dist"][1])
    held = [i for i, name in enumerate(("k1", "k2", "p1", "p2", "k3")) if name not in expected.split()]
    assert all(cam["dist"][i] == 0.0 and std["dist"][i] == 0.0 for i in held)
    rows = {c["model"]: c for c in r.model.candidates}
    assert list(rows) == ["k1 k2", "k1 k2 k3", "k1 k2 p1 p2", "k1 k2 p1 p2 k3"]
    assert rows[expected]["delta_bic"] == 0.0
    assert all(c["delta_bic"] > 2.0 for name, c in rows.items() if name != expected)
    if lens == "k3":
        fixed = rows["k1 k2"]  # what --fix-k3 gives on this lens
        assert abs(fixed["dist"][1] - dist[1]) > 5 * fixed["dist_std"][1]
        assert abs(cam["dist"][4] - dist[4]) < 2 * std["dist"][4]
        assert "lowest BIC" in r.model.reason
        assert r.model.notes == []
    else:
        assert r.model.notes[0].startswith("k3 left out by the choice: k2 = ")


def test_options_override_the_choice():
    k3_lens = wide_views(LENSES["k3"][0])
    r = calibrate_intrinsics(BOARD, k3_lens, SIZE, fix_k3=True)
    assert r.model.model.name == "k1 k2"  # p1 p2 still chosen: the lens has none
    assert r.camera["dist"][4] == 0.0
    assert [c["model"] for c in r.model.candidates] == ["k1 k2", "k1 k2 p1 p2"]
    r = calibrate_intrinsics(BOARD, wide_views(LENSES["plain"][0]), SIZE, fix_k3=False,
                             fix_tangential=False)
    assert r.model.model.name == "k1 k2 p1 p2 k3"
    assert r.model.chosen_by == "options"
    assert len(r.model.candidates) == 1
    assert all(s > 0 for s in r.std["dist"])


def test_an_outlier_view_is_found_with_the_richest_model_and_not_a_lens_term():
    """Outliers are judged with every term free: under k3 = 0 the views that reach the corners of
    the k3 lens fit worse, and must not be the ones dropped."""
    dets = wide_views(LENSES["k3"][0])
    dets[6].px = dets[6].px + np.random.default_rng(1).normal(0.0, 1.5, dets[6].px.shape)
    r = calibrate_intrinsics(BOARD, dets, SIZE)
    assert [x["image"] for x in r.rejected] == ["view6"]
    assert r.model.model.name == "k1 k2 k3"


def test_cli_reports_the_model_choice(rendered, tmp_path):
    """Human lines, --json and the result file's [about] say which model, why, and the
    candidates; the command line in [about] has only the model options that were given."""
    folder, _ = rendered
    images = str(folder / "img*.png")
    rc, out, _ = run_cli("--images", images, "--board", BOARD.spec, "-o", str(tmp_path / "a.toml"))
    assert rc == 0
    assert re.search(r"^distortion model: k1 k2 p1 p2 \(chosen by BIC: ", out, re.MULTILINE)
    assert re.search(r"^\* k1 k2 p1 p2 +\d\.\d{4} +0\.0 ", out, re.MULTILINE)
    assert "note: k3 left out by the choice" in out
    # k2 is printed with two sigmas: each says which it is
    assert "+- = 1 sigma, covering the distortion terms the model leaves out:" in out
    assert "k2 and k3 +- each model's own 1 sigma (valid only if the terms it leaves out" in out
    about = tomllib.loads((tmp_path / "a.toml").read_text())["about"]
    assert about["model"] == "pinhole fx fy cx cy, skew 0, dist k1 k2 p1 p2 (others 0)"
    assert about["model_choice"]["model"] == "k1 k2 p1 p2"
    assert len(about["model_choice"]["candidates"]) == 4
    assert "-k3" not in about["command"]
    rc, out, _ = run_cli("--images", images, "--board", BOARD.spec, "-o", str(tmp_path / "b.toml"),
                         "--json", "--fix-k3", "--fix-tangential")
    assert rc == 0
    model = json.loads(out)["model"]
    assert (model["model"], model["chosen_by"]) == ("k1 k2", "options")
    about = tomllib.loads((tmp_path / "b.toml").read_text())["about"]
    assert about["command"].endswith("--fix-k3 --fix-tangential -o " + str(tmp_path / "b.toml"))
