"""Single-camera calibration against a known camera.

Two kinds of synthetic data: board images rendered through the camera (detection + fit, the
CLI end to end), and exact projections (cv2.projectPoints) with controlled noise and
corruption, for the fit's bookkeeping (outliers, too few points, warnings).
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
    fixed = calibrate_intrinsics(BOARD, dets, SIZE)
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
    assert set(summary) == {"camera", "std", "rms_px", "per_image", "rejected", "warnings", "output"}
    assert set(summary["camera"]) == {"fx", "fy", "cx", "cy", "skew", "dist", "width", "height"}
    assert set(summary["std"]) == {"fx", "fy", "cx", "cy", "skew", "dist"}
    assert summary["std"]["dist"][4] > 0  # k3 was free
    assert [p["image"] for p in summary["per_image"]] == [str(folder / f"img{i:02d}.png") for i in range(10)]
