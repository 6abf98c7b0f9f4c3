"""Stereo rig calibration on Bouguet's stereo example, against his published global stereo
optimisation (../shared/datasets/bouguet_stereo_example/PROVENANCE.md, PDF page 2).

Two routes:

1. the rig solver (``vgripd.calib.rig``) on his stored corners (``x_i``/``X_i`` of
   ``Calib_Results_left.mat``/``_right.mat``): same points, same model, so it must land on his
   optimum (to the rounding of his printed decimals) and its one-sigma standard deviations
   times 3 must match his printed ``+-`` (the toolbox's ~3 sigma);
2. the CLI on the 14 JPEG pairs with our own corner detection: within his ``+-``
   (``|ours - published| <= published+-``), and the written rig.toml, loaded through a config
   ``include``, triangulates his stored corners into a 30 mm grid.

Model as his: fx, fy, cx, cy, k1, k2, p1, p2, k3 = 0, skew 0; ``X_R = R(om) X_L + T``, mm. That
is also the model the joint fit chooses from the data here (BIC; k3 free is 7 higher on the
JPEGs), so no model option is passed.

Pairs that are not pairs: the same JPEGs with the right images shifted by one, or two right
images swapped, are refused before the joint fit, naming the pairs (and the shift).
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import scipy.io

from vgripd.__main__ import main
from vgripd.calib.rig import RigResult, calibrate_rig
from vgripd.config import load_config
from vgripd.geometry.stereo import StereoRig
from vgripd.vision.scene import stereo_rig

# Bouguet, "Fifth calibration example", PDF page 2: value, +- (about 3 sigma)
PUBLISHED = {
    "om": ([0.00669, 0.00452, -0.00350], [0.00270, 0.00308, 0.00029]),
    "T": ([-99.80198, 1.12443, 0.05041], [0.14200, 0.11352, 0.49773]),
    "left.fc": ([533.52331, 533.52699], [0.83147, 0.84055]),
    "left.cc": ([341.60376, 235.19287], [1.23937, 1.20470]),
    "left.kc": ([-0.28838, 0.09714, 0.00109, -0.00030], [0.00621, 0.02155, 0.00028, 0.00034]),
    "right.fc": ([536.81377, 536.47649], [0.87631, 0.86541]),
    "right.cc": ([326.28657, 250.10121], [1.31444, 1.16609]),
    "right.kc": ([-0.28943, 0.10690, -0.00059, 0.00014], [0.00486, 0.00883, 0.00022, 0.00055]),
}
ROUNDING = 1e-5  # his numbers are printed with 5 decimals
GRID_PITCH_MM = 30.0


def values(left: dict, right: dict, left_std: dict, right_std: dict, om, T, om_std,
           T_std) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Our result in the keys of PUBLISHED: (value, one-sigma std)."""
    out = {"om": (om, om_std), "T": (T, T_std)}
    for side, cam, std in (("left", left, left_std), ("right", right, right_std)):
        out[f"{side}.fc"] = ([cam["fx"], cam["fy"]], [std["fx"], std["fy"]])
        out[f"{side}.cc"] = ([cam["cx"], cam["cy"]], [std["cx"], std["cy"]])
        out[f"{side}.kc"] = (cam["dist"][:4], std["dist"][:4])
        assert cam["dist"][4] == 0.0
        assert cam["skew"] == 0.0
    return {k: (np.asarray(v, float), np.asarray(s, float)) for k, (v, s) in out.items()}


# Like for like: the toolbox's +- are the model's own sigmas; our *_std also hold the bias of
# the terms the model choice left out (intrinsics.with_model_bias), std_model does not.
def from_result(r: RigResult) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    m = r.std_model
    return values(r.left, r.right, m["left"], m["right"], r.rotvec_rad, r.translation_mm,
                  m["rotvec_rad"], m["translation_mm"])


def from_summary(s: dict) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    m = s["std_model"]
    return values(s["left"], s["right"], m["left"], m["right"], s["rotvec_rad"],
                  s["translation_mm"], m["rotvec_rad"], m["translation_mm"])


def stored_corners(datasets: Path) -> tuple[list, list, list]:
    folder = datasets / "bouguet_stereo_example"
    mats = [scipy.io.loadmat(folder / f"Calib_Results_{s}.mat") for s in ("left", "right")]
    obj = [mats[0][f"X_{i}"].T.astype(float) for i in range(1, 15)]  # stored as uint8
    assert all(np.array_equal(mats[1][f"X_{i}"].T, o) for i, o in enumerate(obj, 1))
    return obj, [mats[0][f"x_{i}"].T for i in range(1, 15)], [
        mats[1][f"x_{i}"].T for i in range(1, 15)]


def adjacent_distances_mm(rig: StereoRig, obj: list, left: list, right: list) -> np.ndarray:
    """Triangulated distances between grid neighbours (board points 30 mm apart in X_i)."""
    out = []
    for o, pl, pr in zip(obj, left, right, strict=True):
        a, b = np.nonzero(np.triu(np.isclose(
            np.linalg.norm(o[:, None] - o[None], axis=2), GRID_PITCH_MM)))
        P = rig.triangulate(pl, pr).points_mm
        out.append(np.linalg.norm(P[a] - P[b], axis=1))
    return np.concatenate(out)


@pytest.fixture(scope="module")
def stored_fit(datasets) -> RigResult:
    obj, left, right = stored_corners(datasets)
    return calibrate_rig(obj, left, right, (640, 480))


def test_stored_corners_reproduce_the_published_optimum(stored_fit):
    """Same corners, same model: |ours - his| within a hundredth of his +- or the rounding of
    his 5 printed decimals, for om, T and both cameras' fc, cc, kc."""
    assert stored_fit.rejected == []
    assert stored_fit.model.model.name == "k1 k2 p1 p2"
    ours = from_result(stored_fit)
    for key, (value, pm) in PUBLISHED.items():
        diff = np.abs(ours[key][0] - np.asarray(value))
        limit = np.maximum(0.01 * np.asarray(pm), ROUNDING)
        assert np.all(diff <= limit), f"{key}: ours {ours[key][0]} vs {value}"


def test_std_devs_match_the_published_uncertainties(stored_fit):
    """Our sigma from the full Jacobian (both cameras, om, T, 14 board poses) times 3 is his
    +- times sqrt(m / (m - p)) (m = 3024 residuals, p = 106 parameters: we divide the SSR by
    the degrees of freedom, the toolbox by m), to 2 % for every parameter."""
    ours = from_result(stored_fit)
    m = 2 * 2 * sum(p["points"] for p in stored_fit.per_pair)
    dof_factor = np.sqrt(m / (m - len(stored_fit.parameter_names)))
    assert dof_factor == pytest.approx(1.018, abs=1e-3)
    for key, (_value, pm) in PUBLISHED.items():
        ratio = 3 * ours[key][1] / np.asarray(pm) / dof_factor
        assert np.all((ratio > 0.98) & (ratio < 1.02)), f"{key}: 3 sigma / his +- = {ratio}"


def test_stored_corners_rms_and_epipolar_residuals(stored_fit):
    """The stereo fit's RMS equals OpenCV's (0.2039 px, length of the 2D error); the epipolar
    residuals of his corners under our rig are a fraction of a pixel."""
    assert [p["points"] for p in stored_fit.per_pair] == [54] * 14
    assert stored_fit.rms_px == pytest.approx(0.2039, abs=5e-4)
    e = stored_fit.epipolar_px
    assert e["median"] < 0.15
    assert e["p95"] < 0.5
    assert e["max"] < 1.0
    assert stored_fit.warnings == []


def test_stored_corners_triangulate_to_the_30mm_grid(datasets, stored_fit):
    """PROVENANCE: adjacent-corner distances 30.007 +- 0.196 mm with his parameters."""
    d = adjacent_distances_mm(stored_fit.rig, *stored_corners(datasets))
    assert len(d) == 14 * (6 * 8 + 5 * 9)
    assert abs(d.mean() - 30.007) < 0.01
    assert d.std() < 0.21


@pytest.fixture(scope="module")
def cli_run(datasets, tmp_path_factory) -> tuple[dict, Path, Path]:
    folder = datasets / "bouguet_stereo_example"
    out = tmp_path_factory.mktemp("stereo") / "rig.toml"
    report = out.with_name("rig.png")
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        rc = main(["calibrate", "stereo", "--left", str(folder / "left*.jpg"),
                   "--right", str(folder / "right*.jpg"), "--board", "chessboard:9x6:30",
                   "-o", str(out), "--report", str(report), "--json"])
    assert rc == 0
    return json.loads(stdout.getvalue()), out, report


def test_cli_on_the_jpegs_agrees_with_published(cli_run):
    """Our corners (default sub-pixel window), all 14 pairs: within his +- everywhere, and our
    3 sigma within a factor 1.5 of his +-."""
    summary, _, _ = cli_run
    assert len(summary["per_pair"]) == 14
    assert summary["rejected"] == []
    assert [Path(p["left"]).name for p in summary["per_pair"]] == [
        f"left{i:02d}.jpg" for i in range(1, 15)]
    assert [Path(p["right"]).name for p in summary["per_pair"]] == [
        f"right{i:02d}.jpg" for i in range(1, 15)]
    ours = from_summary(summary)
    for key, (value, pm) in PUBLISHED.items():
        diff = np.abs(ours[key][0] - np.asarray(value))
        assert np.all(diff <= np.asarray(pm)), f"{key}: ours {ours[key][0]} vs {value} +- {pm}"
        ratio = 3 * ours[key][1] / np.asarray(pm)
        assert np.all((ratio > 1 / 1.5) & (ratio < 1.5)), f"{key}: 3 sigma / his +- = {ratio}"
    assert summary["rms_px"] < 0.25
    assert (summary["model"]["model"], summary["model"]["chosen_by"]) == ("k1 k2 p1 p2", "BIC")
    rows = {c["model"]: c for c in summary["model"]["candidates"]}
    assert rows["k1 k2 p1 p2 k3"]["delta_bic"] > 2.0
    assert summary["epipolar_px"]["median"] < 0.15
    assert summary["epipolar_px"]["p95"] < 0.5
    assert summary["warnings"] == []


def test_rig_file_loads_through_include_and_triangulates_the_grid(datasets, cli_run):
    """The written rig.toml is what the daemon reads: through a config include and
    ``scene.stereo_rig`` it triangulates his stored corners into the 30 mm grid."""
    summary, out, _ = cli_run
    cfg_path = out.parent / "cell.toml"
    cfg_path.write_text(
        f'include = ["{out.name}"]\n[camera]\ntype = "synthetic"\n'
        '[calibration.hand_eye]\nmounting = "fixed"\n'
        "T_base_camera = { translation_mm = [0.0, 0.0, 1000.0], rotvec_rad = [0.0, 0.0, 0.0] }\n")
    cfg = load_config(cfg_path)
    rig = stereo_rig(cfg)
    assert rig is not None
    np.testing.assert_allclose(rig.T_right_left[:3, 3], summary["translation_mm"], rtol=1e-12)
    np.testing.assert_allclose(cv2.Rodrigues(rig.T_right_left[:3, :3])[0].ravel(),
                               summary["rotvec_rad"], atol=1e-12)
    assert cfg.calibration is not None
    assert cfg.calibration.right is not None
    assert cfg.calibration.right.fx == summary["right"]["fx"]
    d = adjacent_distances_mm(rig, *stored_corners(datasets))
    assert abs(d.mean() - 30.007) < 0.02
    assert d.std() < 0.21


def test_cli_report_and_about(cli_run):
    summary, out, report = cli_run
    img = cv2.imread(str(report))
    assert img is not None
    assert img.shape[0] > 400
    assert summary["report"] == str(report)
    text = out.read_text()
    for section in ("[calibration.left]", "[calibration.right]",
                    "[calibration.stereo.T_right_left]", "[about]", "[about.epipolar_px]",
                    "[about.model_choice]"):
        assert section in text


def link_pairs(datasets: Path, folder: Path, numbers: list[int],
               right_of: dict[int, int] | None = None) -> None:
    """left{n}.jpg / right{n}.jpg in ``folder`` -> his pairs 1, 2, ... (symlinks, no copies);
    ``right_of`` {k: j}: the k-th right file is his right image j instead."""
    source = datasets / "bouguet_stereo_example"
    for k, n in enumerate(numbers, 1):
        j = (right_of or {}).get(k, k)
        (folder / f"left{n}.jpg").symlink_to(source / f"left{k:02d}.jpg")
        (folder / f"right{n}.jpg").symlink_to(source / f"right{j:02d}.jpg")


def run_cli(*argv: str) -> tuple[int, str]:
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        rc = main(["calibrate", "stereo", *argv])
    return rc, stdout.getvalue()


def test_cli_pairs_by_natural_order_and_rejects_a_pair_without_board(datasets, tmp_path):
    """Pairs follow numbers by value (left10 after left5); a right image without the board
    drops its pair with the reason; few pairs are warned about."""
    link_pairs(datasets, tmp_path, [1, 2, 3, 4, 5, 10])
    (tmp_path / "right3.jpg").unlink()
    cv2.imwrite(str(tmp_path / "right3.jpg"), np.full((480, 640), 128, np.uint8))
    rc, out = run_cli("--left", str(tmp_path / "left*.jpg"), "--right",
                      str(tmp_path / "right*.jpg"), "--board", "chessboard:9x6:30",
                      "-o", str(tmp_path / "rig.toml"), "--json")
    assert rc == 0
    summary = json.loads(out)
    assert [Path(p["left"]).name for p in summary["per_pair"]] == [
        "left1.jpg", "left2.jpg", "left4.jpg", "left5.jpg", "left10.jpg"]
    assert [Path(p["right"]).name for p in summary["per_pair"]] == [
        "right1.jpg", "right2.jpg", "right4.jpg", "right5.jpg", "right10.jpg"]
    assert len(summary["rejected"]) == 1
    bad = summary["rejected"][0]
    assert Path(bad["left"]).name == "left3.jpg"
    assert bad["reason"].startswith("right image: board not found")
    assert any("only 5 pairs" in w for w in summary["warnings"])


def test_cli_mismatched_counts_and_empty_globs_are_errors(datasets, tmp_path, capsys):
    link_pairs(datasets, tmp_path, [1, 2, 3])
    (tmp_path / "right3.jpg").unlink()
    rc, _ = run_cli("--left", str(tmp_path / "left*.jpg"), "--right",
                    str(tmp_path / "right*.jpg"), "--board", "chessboard:9x6:30",
                    "-o", str(tmp_path / "rig.toml"))
    assert rc == 1
    assert "--left matches 3 files but --right matches 2" in capsys.readouterr().err
    rc, _ = run_cli("--left", str(tmp_path / "nothing*.png"), "--right",
                    str(tmp_path / "right*.jpg"), "--board", "chessboard:9x6:30")
    assert rc == 1
    assert "--left" in capsys.readouterr().err
    assert not (tmp_path / "rig.toml").exists()


def test_cli_refuses_pairs_shifted_by_one_and_names_the_shift(datasets, tmp_path, capsys):
    """left k with his right k+1 (as when right01 is missing and the rest renumbered): before,
    the joint fit ended in "undistort: point 53 ... beyond the distortion's fold"."""
    link_pairs(datasets, tmp_path, list(range(1, 14)), right_of={k: k + 1 for k in range(1, 14)})
    rc, out = run_cli("--left", str(tmp_path / "left*.jpg"), "--right",
                      str(tmp_path / "right*.jpg"), "--board", "chessboard:9x6:30",
                      "-o", str(tmp_path / "rig.toml"))
    err = capsys.readouterr().err
    assert rc == 1
    assert out == ""
    assert err.count("\n") == 1
    assert "left and right images are not consistent pairs: 13 of 13 pairs disagree" in err
    assert (f"fit the rig when left i goes with right i-1 (from {tmp_path / 'left2.jpg'} with "
            f"{tmp_path / 'right1.jpg'}): the right images are shifted by 1") in err
    assert "fold" not in err
    assert not (tmp_path / "rig.toml").exists()


def test_cli_names_two_swapped_right_images(datasets, tmp_path, capsys):
    link_pairs(datasets, tmp_path, list(range(1, 11)), right_of={4: 8, 8: 4})
    rc, _ = run_cli("--left", str(tmp_path / "left*.jpg"), "--right",
                    str(tmp_path / "right*.jpg"), "--board", "chessboard:9x6:30",
                    "-o", str(tmp_path / "rig.toml"))
    err = capsys.readouterr().err
    assert rc == 1
    assert "2 of 10 pairs disagree with the rig of the other 8" in err
    for k in (4, 8):
        assert f"{tmp_path / f'left{k}.jpg'} / {tmp_path / f'right{k}.jpg'} (" in err
    assert "Likely: pairs shifted (left i with right i+1), images not taken at the same time" in err


def test_cli_human_output_reports_the_model_choice(datasets, tmp_path):
    link_pairs(datasets, tmp_path, list(range(1, 8)))
    rc, out = run_cli("--left", str(tmp_path / "left*.jpg"), "--right",
                      str(tmp_path / "right*.jpg"), "--board", "chessboard:9x6:30",
                      "-o", str(tmp_path / "rig.toml"), "--fix-k3")
    assert rc == 0
    assert "distortion model, both cameras: k1 k2 p1 p2 (chosen by BIC: " in out
    assert "left k2" in out
    assert "right k2" in out
    assert "--fix-k3" in (tmp_path / "rig.toml").read_text()  # the command in [about]
