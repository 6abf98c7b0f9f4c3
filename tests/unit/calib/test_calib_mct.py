"""Camera Calibration Toolbox (Bouguet) result scripts: import, export, conventions.

Oracles: Bouguet's own stereo example (``bouguet_stereo_example``): his results and stored
corners in ``Calib_Results_left/right.mat`` (read with scipy, tests only) and the published
stereo result of PROVENANCE.md. The tests write those numbers into a script in the toolbox's
``Calib_Results.m`` layout (tmp_path), import it with our CLI and check

- the values and std = error / 3 (the toolbox's "±" is about 3 sigma);
- kc order and pixel origin: projecting the stored board points X_i with the stored poses
  omc_i, Tc_i through our camera model with the *imported* intrinsics reproduces the stored
  corners x_i with zero mean and the stored err_std; and OpenCV's cornerSubPix on left01.jpg
  finds the stored x_1 (same pixel origin as OpenCV, no 0.5 / 1 px shift);
- om/T direction: triangulating the stored left/right corners with the imported rig gives
  30 mm between adjacent corners (the inverted transform does not).
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import cv2
import numpy as np
import pytest
import scipy.io

from vgripd.__main__ import main
from vgripd.calib.mct import parse_mct, read_mct
from vgripd.errors import CalibrationError, DegenerateInputError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.stereo import StereoRig
from vgripd.geometry.transforms import invert_transform, make_transform, matrix_from_rotvec
from vgripd.serialize import toml_from_dict

SQUARE_MM = 30.0

# PROVENANCE.md, published result after the global stereo optimisation (PDF page 2)
PUBLISHED_STEREO = {
    "fc_left": [533.52331, 533.52699], "fc_left_error": [0.83147, 0.84055],
    "cc_left": [341.60376, 235.19287], "cc_left_error": [1.23937, 1.20470],
    "kc_left": [-0.28838, 0.09714, 0.00109, -0.00030, 0],
    "kc_left_error": [0.00621, 0.02155, 0.00028, 0.00034, 0],
    "alpha_c_left": [0.0], "alpha_c_left_error": [0.0],
    "fc_right": [536.81377, 536.47649], "fc_right_error": [0.87631, 0.86541],
    "cc_right": [326.28657, 250.10121], "cc_right_error": [1.31444, 1.16609],
    "kc_right": [-0.28943, 0.10690, -0.00059, 0.00014, 0],
    "kc_right_error": [0.00486, 0.00883, 0.00022, 0.00055, 0],
    "alpha_c_right": [0.0], "alpha_c_right_error": [0.0],
    "om": [0.00669, 0.00452, -0.00350], "om_error": [0.00270, 0.00308, 0.00029],
    "T": [-99.80198, 1.12443, 0.05041], "T_error": [0.14200, 0.11352, 0.49773],
    "nx": [640], "ny": [480],
}


def matlab(name: str, values) -> str:
    v = np.asarray(values, dtype=float).ravel()
    if v.size == 1 and name in ("nx", "ny", "n_ima"):
        return f"{name} = {int(v[0])};"
    if v.size == 1:
        return f"{name} = {v[0]:.15f};"
    return f"{name} = [ " + " ; ".join(f"{x:.15f}" for x in v) + " ];"


def calib_results_m(mat: dict) -> str:
    """A Calib_Results.m as the toolbox writes it (its layout and %5.15f / %d formats)."""
    lines = ["% Intrinsic and Extrinsic Camera Parameters", "%", ""]
    for name in ("fc", "cc", "alpha_c", "kc", "fc_error", "cc_error", "alpha_c_error",
                 "kc_error", "nx", "ny"):
        lines += [f"%-- {name}:", matlab(name, mat[name]), ""]
    n = int(mat["n_ima"].ravel()[0])
    lines += [matlab("n_ima", [n]) + "\t\t\t\t\t\t% Number of calibration images",
              "est_fc = [ 1 ; 1 ];\t\t\t\t\t% Estimation indicator", ""]
    for i in range(1, n + 1):
        lines.append(f"%-- Image #{i}:")
        for name in (f"omc_{i}", f"Tc_{i}"):
            lines.append(f"{name} = [ " + " ; ".join(f"{x:e}" for x in mat[name].ravel())
                         + " ];")
    return "\n".join(lines) + "\n"


@pytest.fixture(scope="module")
def stereo_mats(datasets: Path) -> dict[str, dict]:
    root = datasets / "bouguet_stereo_example"
    return {side: scipy.io.loadmat(root / f"Calib_Results_{side}.mat") for side in ("left", "right")}


def run_cli(argv: list[str], capsys) -> tuple[int, str, str]:
    rc = main(argv)
    out, err = capsys.readouterr()
    return rc, out, err


def import_file(tmp_path: Path, text: str, capsys, *extra: str, name="Calib_Results.m"):
    src = tmp_path / name
    src.write_text(text)
    out = tmp_path / ("rig.toml" if "stereo" in name else "camera.toml")
    rc, stdout, err = run_cli(["calibrate", "import-mct", str(src), "-o", str(out), "--json",
                               *extra], capsys)
    assert rc == 0, err
    return tomllib.loads(out.read_text()), json.loads(stdout)


def camera_model(table: dict) -> CameraModel:
    return CameraModel(fx=table["fx"], fy=table["fy"], cx=table["cx"], cy=table["cy"],
                       skew=table["skew"], dist=tuple(table["dist"]), width=table["width"],
                       height=table["height"])


def test_import_gives_the_toolbox_values_and_std_is_error_over_3(tmp_path, capsys, stereo_mats):
    mat = stereo_mats["left"]
    data, summary = import_file(tmp_path, calib_results_m(mat), capsys)
    cam = data["calibration"]["left"]
    fc, cc, kc = (mat[k].ravel() for k in ("fc", "cc", "kc"))
    assert cam["fx"] == pytest.approx(fc[0], abs=1e-12)
    assert cam["fy"] == pytest.approx(fc[1], abs=1e-12)
    assert (cam["cx"], cam["cy"]) == pytest.approx(tuple(cc), abs=1e-12)
    assert cam["dist"] == pytest.approx(list(kc), abs=1e-15)
    assert (cam["width"], cam["height"], cam["skew"]) == (640, 480, 0.0)
    # PROVENANCE.md page 1: fc = [533.00371, 533.15260], cc = [341.58612, 234.25940]
    assert cam["fx"] == pytest.approx(533.00371, abs=5e-6)
    assert cam["cy"] == pytest.approx(234.25940, abs=5e-6)
    std = data["about"]["std"]
    assert std["fx"] == pytest.approx(mat["fc_error"].ravel()[0] / 3, rel=1e-12)
    assert std["cy"] == pytest.approx(mat["cc_error"].ravel()[1] / 3, rel=1e-12)
    assert std["dist"] == pytest.approx(list(mat["kc_error"].ravel() / 3), rel=1e-12)
    assert summary["camera"] == cam
    assert summary["std"] == std


@pytest.mark.parametrize("side", ["left", "right"])
def test_imported_camera_reprojects_the_stored_corners(tmp_path, capsys, stereo_mats, side):
    """Pixel origin and kc order: X_i through (omc_i, Tc_i) and our model with the imported
    intrinsics land on the stored x_i with zero mean and the toolbox's own err_std."""
    mat = stereo_mats[side]
    data, _ = import_file(tmp_path, calib_results_m(mat), capsys, "--camera", side)
    cam = camera_model(data["calibration"][side])
    residuals = []
    for i in range(1, 15):
        X = mat[f"X_{i}"].astype(float).T
        T = make_transform(matrix_from_rotvec(mat[f"omc_{i}"].ravel()), mat[f"Tc_{i}"].ravel())
        X_cam = X @ T[:3, :3].T + T[:3, 3]
        residuals.append(mat[f"x_{i}"].T - cam.project(X_cam))
    r = np.vstack(residuals)
    assert np.abs(r.mean(axis=0)).max() < 1e-6  # measured ~1e-12; a 0.5 px shift shows as 0.5
    np.testing.assert_allclose(r.std(axis=0, ddof=1), mat["err_std"].ravel(), rtol=1e-6)
    # the same check with k2 and p1 swapped (a wrong kc order) fails by far
    wrong = CameraModel(cam.fx, cam.fy, cam.cx, cam.cy, dist=(cam.dist[0], cam.dist[2],
                                                                cam.dist[1], *cam.dist[3:]))
    r_wrong = mat["x_1"].T - wrong.project(
        mat["X_1"].astype(float).T @ matrix_from_rotvec(mat["omc_1"].ravel()).T
        + mat["Tc_1"].ravel())
    assert np.abs(r_wrong).max() > 1.0


def test_stored_corners_use_opencv_pixel_origin(datasets, stereo_mats):
    """OpenCV's cornerSubPix (centre of the top-left pixel = (0, 0)) on left01.jpg, with the
    toolbox's window (wintx = 7), finds the stored x_1: no 0.5 px or 1 px (MATLAB) offset."""
    gray = cv2.imread(str(datasets / "bouguet_stereo_example" / "left01.jpg"),
                      cv2.IMREAD_GRAYSCALE)
    ok, corners = cv2.findChessboardCorners(gray, (9, 6))
    assert ok
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-6)
    ours = cv2.cornerSubPix(gray, corners, (7, 7), (-1, -1), criteria).reshape(-1, 2)
    stored = stereo_mats["left"]["x_1"].T
    nearest = np.linalg.norm(stored[:, None] - ours[None], axis=2).argmin(axis=1)
    diff = stored - ours[nearest]
    assert len(set(nearest.tolist())) == 54
    assert np.abs(diff).max() < 0.01


def published_stereo_m() -> str:
    return "% Stereo calibration\n" + "\n".join(
        matlab(k, v) for k, v in PUBLISHED_STEREO.items()) + "\n"


def test_stereo_import_direction_triangulates_30mm_squares(tmp_path, capsys, stereo_mats):
    data, summary = import_file(tmp_path, published_stereo_m(), capsys,
                                name="Calib_Results_stereo.m")
    calib = data["calibration"]
    pose = calib["stereo"]["T_right_left"]
    assert pose["translation_mm"] == pytest.approx(PUBLISHED_STEREO["T"], abs=1e-12)
    assert pose["rotvec_rad"] == pytest.approx(PUBLISHED_STEREO["om"], abs=1e-12)
    about = data["about"]
    assert about["rotvec_std"] == pytest.approx(np.array(PUBLISHED_STEREO["om_error"]) / 3)
    assert about["translation_std"] == pytest.approx(np.array(PUBLISHED_STEREO["T_error"]) / 3)
    assert about["right_std"]["fx"] == pytest.approx(0.87631 / 3)
    assert summary["translation_mm"] == pose["translation_mm"]
    assert summary["left"]["fx"] == 533.52331

    T = make_transform(matrix_from_rotvec(pose["rotvec_rad"]), pose["translation_mm"])
    left, right = camera_model(calib["left"]), camera_model(calib["right"])

    def adjacent_distances(T_right_left):
        rig = StereoRig(left, right, T_right_left)
        dists = []
        for i in range(1, 15):
            pts = rig.triangulate(stereo_mats["left"][f"x_{i}"].T,
                                  stereo_mats["right"][f"x_{i}"].T).points_mm
            X = stereo_mats["left"][f"X_{i}"].astype(float).T
            a, b = np.nonzero(np.isclose(np.linalg.norm(X[:, None] - X[None], axis=2),
                                         SQUARE_MM))
            dists.append(np.linalg.norm(pts[a] - pts[b], axis=1)[a < b])
        return np.concatenate(dists)

    d = adjacent_distances(T)
    assert len(d) == 14 * 93  # 9x6 grid: 8*6 + 9*5 adjacent pairs per image
    assert d.mean() == pytest.approx(30.0, abs=0.02)  # PROVENANCE: 30.007 +- 0.196
    assert d.std() < 0.25
    # the opposite reading of om/T (X_L = R X_R + T) puts the board behind the cameras
    with pytest.raises(DegenerateInputError, match="behind a camera"):
        adjacent_distances(invert_transform(T))


def test_round_trip_camera_export_import(tmp_path, capsys, stereo_mats):
    data, _ = import_file(tmp_path, calib_results_m(stereo_mats["right"]), capsys)
    script = tmp_path / "back.m"
    rc, _, err = run_cli(["calibrate", "export-mct", str(tmp_path / "camera.toml"),
                          "-o", str(script)], capsys)
    assert rc == 0, err
    again = read_mct(script)
    cam, std = data["calibration"]["left"], data["about"]["std"]
    for k in ("fx", "fy", "cx", "cy", "skew", "width", "height"):
        assert again.camera[k] == pytest.approx(cam[k], abs=1e-12), k
    for k in ("fx", "fy", "cx", "cy", "skew"):
        assert again.std[k] == pytest.approx(std[k], abs=1e-15), k
    assert again.camera["dist"] == pytest.approx(cam["dist"], abs=1e-15)
    assert again.std["dist"] == pytest.approx(std["dist"], abs=1e-15)
    text = script.read_text()
    assert "fc_error = [ 1.197859" in text  # the toolbox's own error (3 sigma) comes back
    assert "alpha_c = 0.000000000000000;" in text


def test_round_trip_stereo_export_import_and_from_a_config(tmp_path, capsys):
    import_file(tmp_path, published_stereo_m(), capsys, name="Calib_Results_stereo.m")
    script = tmp_path / "out_stereo.m"
    rc, _, err = run_cli(["calibrate", "export-mct", str(tmp_path / "rig.toml"),
                          "-o", str(script)], capsys)
    assert rc == 0, err
    back = read_mct(script)
    assert back.translation_mm == pytest.approx(PUBLISHED_STEREO["T"], abs=1e-12)
    assert back.rotvec_rad == pytest.approx(PUBLISHED_STEREO["om"], abs=1e-12)
    assert back.translation_std == pytest.approx(np.array(PUBLISHED_STEREO["T_error"]) / 3)
    assert back.right.camera["cx"] == pytest.approx(326.28657, abs=1e-12)
    assert back.left.std["dist"][0] == pytest.approx(0.00621 / 3, abs=1e-15)
    # a config pulling the rig in with include: exported without *_error, with a warning
    config = tmp_path / "config.toml"
    config.write_text('include = ["rig.toml"]\n')
    rc, _, err = run_cli(["calibrate", "export-mct", str(config), "-o",
                          str(tmp_path / "c.m")], capsys)
    assert rc == 0
    assert "*_error not written" in err
    text = (tmp_path / "c.m").read_text()
    assert f"fc_left = [ {533.52331:.15f} ; {533.52699:.15f} ];" in text
    assert "_error" not in text.split("%", 1)[0]
    assert "fc_left_error" not in text
    # one camera of the rig
    rc, _, _ = run_cli(["calibrate", "export-mct", str(tmp_path / "rig.toml"), "--camera",
                        "right", "-o", str(tmp_path / "r.m")], capsys)
    assert read_mct(tmp_path / "r.m").camera["fx"] == 536.81377


def test_camera_right_and_four_coefficient_kc(tmp_path, capsys):
    text = ("fc = [ 600 ; 601 ];\ncc = [ 320 ; 240 ];\nalpha_c = 0.001;\n"
            "kc = [ -0.2 ; 0.1 ; 0.001 ; 0.002 ];\nnx = 640;\nny = 480;\n")
    data, summary = import_file(tmp_path, text, capsys, "--camera", "right")
    cam = data["calibration"]["right"]
    assert cam["dist"] == [-0.2, 0.1, 0.001, 0.002, 0.0]
    assert cam["skew"] == pytest.approx(0.6)  # alpha_c * fc(1)
    assert summary["std"] is None
    assert "std" not in data["about"]


def test_missing_variable_names_file_and_variable(tmp_path, capsys, stereo_mats):
    text = "\n".join(line for line in calib_results_m(stereo_mats["left"]).splitlines()
                     if not line.startswith("kc ="))
    src = tmp_path / "Calib_Results.m"
    src.write_text(text)
    with pytest.raises(CalibrationError, match=r"Calib_Results\.m: variable kc missing"):
        read_mct(src)
    rc, _, err = run_cli(["calibrate", "import-mct", str(src), "-o",
                          str(tmp_path / "c.toml")], capsys)
    assert rc == 1
    assert "variable kc missing" in err
    assert not (tmp_path / "c.toml").exists()
    stereo = "\n".join(line for line in published_stereo_m().splitlines()
                       if not line.startswith("om ="))
    with pytest.raises(CalibrationError, match="s.m: variable om missing"):
        parse_mct(stereo, "s.m")


@pytest.mark.parametrize(("text", "match"), [
    ("x = 1;\ny = [1 2];\n", "not a Camera Calibration Toolbox result"),
    ("[calibration.left]\nfx = 1\n", "not a Camera Calibration Toolbox result"),
    ("fc = [ 600 ; 601 ; 3 ];\n", r"f\.m:1: fc: expected 2 numbers, got 3"),
    ("% c\nfc = [ 600 ; 601 ];\ncc = fc / 2;\n", r"f\.m:3: cc: not a numeric literal"),
    ("fc = [ 600 ; NaN ];\n", r"f\.m:1: fc: not finite"),
    ("fc = [600 600]; cc = [700; 240]; alpha_c = 0; kc = [0;0;0;0;0];\nnx = 640;\nny = 480;",
     "principal point"),
])
def test_bad_scripts_are_refused_with_where(text, match):
    with pytest.raises(CalibrationError, match=match):
        parse_mct(text, "f.m")


def test_inconsistent_R_and_camera_option_on_stereo(tmp_path, capsys):
    bad = published_stereo_m() + "R = [ 1 0 0 ; 0 1 0 ; 0 0 1 ];\n"
    with pytest.raises(CalibrationError, match="R disagrees with rodrigues"):
        parse_mct(bad, "s.m")
    src = tmp_path / "Calib_Results_stereo.m"
    src.write_text(published_stereo_m())
    rc, _, err = run_cli(["calibrate", "import-mct", str(src), "--camera", "left",
                          "-o", str(tmp_path / "x.toml")], capsys)
    assert rc == 1
    assert "holds both cameras" in err


def test_toolbox_mat_file_reads_like_its_script(datasets, tmp_path, capsys, stereo_mats):
    """The binary Calib_Results_left.mat (MATLAB 5, 2001) gives what its script gives."""
    mat_path = datasets / "bouguet_stereo_example" / "Calib_Results_left.mat"
    from_mat = read_mct(mat_path)
    from_script = parse_mct(calib_results_m(stereo_mats["left"]), "Calib_Results.m")
    for k in ("fx", "fy", "cx", "cy", "skew", "dist", "width", "height"):
        assert from_mat.camera[k] == pytest.approx(from_script.camera[k], abs=1e-12), k
    assert from_mat.std["dist"] == pytest.approx(from_script.std["dist"], abs=1e-15)
    rc, _, err = run_cli(["calibrate", "import-mct", str(mat_path), "-o",
                          str(tmp_path / "c.toml")], capsys)
    assert rc == 0, err


def test_compressed_stereo_mat_file_written_by_scipy(tmp_path):
    """A -v7 (zlib-compressed) Calib_Results_stereo.mat as scipy writes it, with the 3x3 R
    stored column-major: R must agree with rodrigues(om), so a transposed read would fail."""
    data = {k: np.array(v, dtype=float).reshape(-1, 1) for k, v in PUBLISHED_STEREO.items()}
    data["R"] = matrix_from_rotvec(PUBLISHED_STEREO["om"])
    data["calib_name_left"] = "left"  # a string variable is skipped
    path = tmp_path / "Calib_Results_stereo.mat"
    scipy.io.savemat(path, data, do_compression=True)
    rig = read_mct(path)
    assert rig.translation_mm == pytest.approx(PUBLISHED_STEREO["T"], abs=1e-12)
    assert rig.right.camera["fy"] == 536.47649
    assert rig.rotvec_std == pytest.approx(np.array(PUBLISHED_STEREO["om_error"]) / 3)
    path.write_bytes(path.read_bytes()[:300])
    with pytest.raises(CalibrationError, match="corrupt MAT-file"):
        read_mct(path)


def test_metre_baseline_warns(tmp_path, capsys):
    metres = published_stereo_m().replace("T = [ -99.801980000000000",
                                          "T = [ -0.099801980000000")
    _, summary = import_file(tmp_path, metres, capsys, name="Calib_Results_stereo.m")
    assert any("baseline" in w for w in summary["warnings"])


def test_export_reads_the_sigmas_calibrate_stereo_writes(tmp_path, capsys):
    """`calibrate stereo` records its sigmas as [about.std] with left, right, rotvec_rad and
    translation_mm: export-mct writes every *_error from them, without a warning."""
    cam = {"fx": 1800.0, "fy": 1801.0, "cx": 640.0, "cy": 512.0, "skew": 0.0,
           "dist": [-0.08, 0.11, 0.0, 0.0, 0.0], "width": 1280, "height": 1024}
    sig = {"fx": 0.3, "fy": 0.31, "cx": 0.5, "cy": 0.45, "skew": 0.0,
           "dist": [0.001, 0.004, 0.0001, 0.0001, 0.0]}
    rig = tmp_path / "rig.toml"
    rig.write_text(toml_from_dict({
        "about": {"std": {"left": sig, "right": sig, "rotvec_rad": [0.001, 0.002, 0.0003],
                          "translation_mm": [0.1, 0.2, 0.3]}},
        "calibration": {"left": cam, "right": cam, "stereo": {"T_right_left": {
            "translation_mm": [-150.0, 0.0, 0.0], "rotvec_rad": [0.0, 0.1, 0.0]}}}}))
    rc, _, err = run_cli(["calibrate", "export-mct", str(rig), "-o", str(tmp_path / "s.m")],
                         capsys)
    assert rc == 0
    assert "no standard deviations" not in err
    back = read_mct(tmp_path / "s.m")
    assert back.translation_std == pytest.approx([0.1, 0.2, 0.3])
    assert back.rotvec_std == pytest.approx([0.001, 0.002, 0.0003])
    assert back.left.std["fx"] == pytest.approx(0.3)
    assert back.right.std["dist"][1] == pytest.approx(0.004)
    # one camera of it
    rc, _, err = run_cli(["calibrate", "export-mct", str(rig), "--camera", "right", "-o",
                          str(tmp_path / "r.m")], capsys)
    assert rc == 0
    assert "no standard deviations" not in err
    assert read_mct(tmp_path / "r.m").std["cy"] == pytest.approx(0.45)
