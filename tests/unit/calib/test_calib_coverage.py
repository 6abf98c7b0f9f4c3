"""The reported standard deviations of an intrinsic calibration cover its error also when the
automatic model choice leaves out a real term (``intrinsics.with_model_bias``): the issue's 2.2 m
profile (p1 = p2 = 0.0002, dropped by the BIC in most sets) and its wide profile (k3 = -0.01).
bench/bench_calib_coverage.py measures the same over more sets."""

from __future__ import annotations

import numpy as np
import pytest

from bench.bench_calib_coverage import PROFILES, rig_z, views, z_scores
from vgripd.calib.boards import Board
from vgripd.calib.intrinsics import calibrate_intrinsics


@pytest.mark.parametrize("profile", ["far", "wide"])
def test_reported_sigmas_cover_the_error_of_the_chosen_model(profile: str) -> None:
    p = PROFILES[profile]
    board = Board.parse(str(p["board"]))
    camera = p["camera"]
    zs = []
    dropped = 0
    for trial in range(8):
        dets = views(camera, board, float(p["distance"]), np.random.default_rng(trial))
        r = calibrate_intrinsics(board, dets, (camera.width, camera.height))
        dropped += r.model.model.name != "k1 k2 p1 p2 k3"
        zs.append(z_scores(r, camera))
    assert dropped >= 4  # the choice does leave terms out here
    flat = [abs(v) for z in zs for v in z.values()]
    assert sum(v <= 2 for v in flat) / len(flat) >= 0.9
    assert max(flat) < 3.5  # was 4.7 sigma (far: cx) and 21 sigma (wide: k2)


def test_rig_extrinsic_sigmas_include_the_model_bias() -> None:
    """The far profile as a stereo rig (300 mm baseline, p1 = p2 = 0.0002 dropped by the
    choice): the rig rotation and translation errors in units of the reported sigma. With the
    model's own sigmas the worst was 3.6 sigma and 92 % were within 2 (seeded, deterministic)."""
    z = np.abs(np.array(rig_z(10)))
    assert (z <= 2).mean() >= 0.94
    assert z.max() < 3.4


# ------------------------------------------------ issue 24: the richest model's sigma, cameras


def test_intrinsic_sigma_is_no_smaller_than_the_richest_models() -> None:
    """The far profile's sets 8 and 30: the choice dropped p1 p2, and the shift between the
    chosen and the richest model happened to be small, so the chosen model's own sigma plus
    that shift (the rule before) left cx/cy 3.1 and 3.5 sigma off. With the richest model's
    sigma (the chosen value's error is the shift plus the richest model's error) they are
    within 2.3."""
    p = PROFILES["far"]
    board = Board.parse(str(p["board"]))
    camera = p["camera"]
    for seed in (8, 30):
        dets = views(camera, board, float(p["distance"]), np.random.default_rng(seed))
        r = calibrate_intrinsics(board, dets, (camera.width, camera.height))
        assert r.model.model.name == "k1 k2"  # p1 p2 left out
        z = z_scores(r, camera)
        assert max(abs(v) for v in z.values()) < 2.5, (seed, z)
        # the richest model's estimate and covariance are kept for calibrate cameras
        assert r.richest is not None
        cov = np.asarray(r.richest["covariance"])
        assert cov.shape == (9, 9)
        assert r.std["cx"] >= np.sqrt(cov[2, 2]) * 0.999


RIG_SEEDS = (21, 23, 28)


def test_rig_intrinsic_sigmas_cover_over_sets() -> None:
    """The stereo path on the far profile (p1 = p2 = 0.0002 dropped in most sets): both
    cameras' intrinsics in units of the reported sigma in three seeded sets where the rule
    before (the chosen model's own sigma with the shift) left the worst 2.65-2.76 sigma off
    (cx, cy); with the sigmas reported now the worst is at most 2.2."""
    from bench.bench_calib_coverage import stereo_views
    from vgripd.calib.rig import calibrate_rig
    from vgripd.geometry.transforms import make_transform, matrix_from_rotvec

    p = PROFILES["far"]
    camera = p["camera"]
    board = Board.parse(str(p["board"]))
    T = make_transform(matrix_from_rotvec([0.01, -0.12, 0.02]), [-300.0, 4.0, 20.0])
    truth = np.array([camera.fx, camera.fy, camera.cx, camera.cy, *camera.dist])
    zs = []
    for seed in RIG_SEEDS:
        objs, left, right = stereo_views(camera, board, float(p["distance"]), T,
                                         np.random.default_rng(100 + seed))
        r = calibrate_rig(objs, left, right, (camera.width, camera.height))
        for cam, std in ((r.left, r.left_std), (r.right, r.right_std)):
            est = np.array([cam["fx"], cam["fy"], cam["cx"], cam["cy"], *cam["dist"]])
            sig = np.array([std["fx"], std["fy"], std["cx"], std["cy"], *std["dist"]])
            zs += list(np.abs(est - truth)[sig > 0] / sig[sig > 0])
    assert max(zs) < 2.3, max(zs)


@pytest.fixture(scope="module")
def rendered_rig(tmp_path_factory):
    """The wide profile's two-camera rig, set 0 of bench/bench_calib_rendered.py, rendered by
    bench/render_board.py (OpenCV and numpy only; truth by cv2.projectPoints) into PNGs; and
    the right camera's true centre in the left camera's frame (mm)."""
    import cv2

    from bench.bench_calib_rendered import PROFILES as RENDERED
    from bench.bench_calib_rendered import render_set
    from bench.render_board import Camera

    folder = tmp_path_factory.mktemp("rig")
    p = RENDERED["wide"]
    fx, fy, cx, cy, dist, w, h = p["camera"]
    cam = Camera(fx, fy, cx, cy, dist, w, h)
    images: dict[str, list[np.ndarray]] = {"left": [], "right": []}
    render_set("wide", 0, {"left": cam, "right": cam}, images)
    for side, imgs in images.items():
        for i, img in enumerate(imgs):
            cv2.imwrite(str(folder / f"{side}_{i:02d}.png"), img)
    R_rl = cv2.Rodrigues(np.array(p["rig"][0]))[0]
    return folder, -R_rl.T @ np.array(p["rig"][1])


def _cameras(folder, out, *extra: str) -> dict:
    import tomllib

    from vgripd.__main__ import main

    assert main(["calibrate", "cameras", "--camera", f"left={folder}/left_*.png",
                 "--camera", f"right={folder}/right_*.png", "--board", "chessboard:9x7:30",
                 *extra, "-o", str(out)]) == 0
    return tomllib.loads(out.read_text())["about"]["cameras"][1]


def test_calibrate_cameras_pose_sigmas_carry_the_intrinsics_uncertainty(rendered_rig,
                                                                       tmp_path) -> None:
    """`vgripd calibrate cameras` on the rendered rig, each camera's intrinsics from its own
    images: the second camera's position error is within 2 of its reported sigmas. Before,
    the sigma took the intrinsics as exact and the error along the viewing direction was
    15.9 of them (that figure is kept as ``std_model``)."""
    folder, true_centre = rendered_rig
    right = _cameras(folder, tmp_path / "cameras.toml")
    err = np.asarray(right["T_reference_camera"]["translation_mm"]) - true_centre
    sigma = np.asarray(right["position_std_mm"])
    assert np.all(np.abs(err) <= 2 * sigma), (err, sigma)
    own = np.asarray(right["std_model"]["position_std_mm"])
    assert np.max(np.abs(err) / own) > 3  # the fit's own sigma alone does not cover it
    assert right["rotation_std_deg"] > right["std_model"]["rotation_std_deg"]


def test_calibrate_cameras_carries_given_intrinsics_covariance(rendered_rig, tmp_path) -> None:
    """The intrinsics given as `calibrate intrinsics` results: their [about.richest]
    covariance is carried into the pose sigmas (which then cover the error); a file without
    it (a config) has none, and the output says so per camera."""
    from vgripd.__main__ import main
    from vgripd.cli.calibrate_cameras import read_intrinsics_prior

    folder, true_centre = rendered_rig
    files = {}
    for side in ("left", "right"):
        files[side] = tmp_path / f"{side}.toml"
        assert main(["calibrate", "intrinsics", "--images", f"{folder}/{side}_*.png",
                     "--board", "chessboard:9x7:30", "--camera", side,
                     "-o", str(files[side])]) == 0
    right = _cameras(folder, tmp_path / "given.toml", "--intrinsics", f"left={files['left']}",
                     "--intrinsics", f"right={files['right']}:right")
    assert right["intrinsics_covariance"] == "the given file's [about.richest]"
    err = np.asarray(right["T_reference_camera"]["translation_mm"]) - true_centre
    assert np.all(np.abs(err) <= 2 * np.asarray(right["position_std_mm"])), err
    own = np.asarray(right["std_model"]["position_std_mm"])
    assert np.max(np.abs(err) / own) > 3
    prior = read_intrinsics_prior(str(files["left"]))
    assert prior is not None
    assert prior["covariance"].shape == (9, 9)
    plain = tmp_path / "plain.toml"
    text = files["left"].read_text()
    plain.write_text(text[:text.index("[about")])
    assert read_intrinsics_prior(str(plain)) is None
