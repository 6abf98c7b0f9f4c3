"""``vgripd calibrate cameras`` on rendered board images of a 4-camera cell.

Images are rendered with the board tests' renderer (``tests/unit/calib/test_calib_boards.py``:
every pixel mapped back through OpenCV's distortion onto the board plane), so the truth -- the
cameras' poses in the base frame and the board poses -- is the renderer's, never ours. The cell:
four cameras 200 mm apart in a row 900 mm above the table, looking down; camera a and camera d
never see the board at the same instant (chaining through b and c). The board is colour
asymmetric (8x5 inner corners), so corner 0 is the same physical corner in every camera.
"""

from __future__ import annotations

import contextlib
import io
import json
import tomllib
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.unit.calib.test_calib_boards import render
from vgripd.__main__ import main
from vgripd.calib.boards import Board
from vgripd.cli.calibrate_cameras import _board_pose
from vgripd.config import CalibrationConfig, IntrinsicsConfig, PoseConfig, load_config
from vgripd.geometry.transforms import pose_error
from vgripd.geometry.vendors import vendor_from_transform
from vgripd.serialize import toml_from_dict

NAMES = ["a", "b", "c", "d"]
SPEC = "chessboard:8x5:20"
BOARD = Board.parse(SPEC)
SIZE = (640, 480)


def camera(i: int) -> dict:
    return {"fx": 800.0 + 7 * i, "fy": 803.0 + 5 * i, "cx": 321.0 - i, "cy": 238.0 + 2 * i,
            "skew": 0.0, "dist": [-0.21 + 0.01 * i, 0.11, 0.0008, -0.0004, 0.0],
            "width": SIZE[0], "height": SIZE[1]}


def transform(rvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, float))[0]
    T[:3, 3] = t
    return T


CAMERAS = [camera(i) for i in range(4)]
T_BASE_CAMERA = [transform([np.pi + 0.02 * i, 0.03 * i - 0.04, 0.05 * i], [200.0 * i, 10 * i, 900])
                 for i in range(4)]


def opencv(cam: dict) -> tuple[np.ndarray, np.ndarray]:
    K = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]])
    return K, np.asarray(cam["dist"], float)


def board_in_camera(c: int, T_base_board: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, bool]:
    """rvec, tvec of the board in camera c; the smallest distance of a corner from the image
    edge (px, < 0: outside); partly inside."""
    T = np.linalg.inv(T_BASE_CAMERA[c]) @ T_base_board
    rvec, tvec = cv2.Rodrigues(T[:3, :3])[0].ravel(), T[:3, 3]
    K, d = opencv(CAMERAS[c])
    px = cv2.projectPoints(BOARD.object_points(), rvec, tvec, K, d)[0].reshape(-1, 2)
    margin = np.minimum(px, np.array(SIZE) - 1 - px).min(axis=1)
    if T[2, 3] <= 0:
        margin[:] = -1.0
    return rvec, tvec, float(margin.min()), bool((margin > 5).any())


@pytest.fixture(scope="module")
def cell(tmp_path_factory) -> dict:
    """Rendered images (a camera writes a file when it sees the whole board, and for the first
    two boards it sees only in part: those are 'not found'; a failed search costs the detector
    seconds), the true intrinsics as camera.toml files, the truth."""
    root = tmp_path_factory.mktemp("cell")
    rng = np.random.default_rng(7)
    boards: dict[str, np.ndarray] = {}
    seen: dict[str, list[str]] = {}  # cameras with the whole board in view (5 px margin)
    clear: dict[str, list[str]] = {}  # ... and 25 px from the edges: the detector must find it
    partial_images = 0
    centre_board = BOARD.object_points().mean(axis=0)
    while len(boards) < 32:
        # the board faces up, its z axis down (away from the cameras, as a detector labels it)
        R = cv2.Rodrigues(rng.uniform(-0.35, 0.35, 3))[0] @ cv2.Rodrigues(
            np.array([np.pi, 0.0, 0.0]))[0]
        x = (rng.choice([0.0, 100.0, 300.0, 500.0, 600.0]) + rng.uniform(-40, 40) if rng.random() < 0.8
             else rng.uniform(-100, 700))
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = np.array([x, rng.uniform(-80, 110), rng.uniform(200, 330)]) - R @ centre_board
        views = [(c, *board_in_camera(c, T)) for c in range(4)]
        if not any(margin > 5 for _c, _r, _t, margin, _p in views):
            continue
        key = f"{len(boards) + 1:03d}"
        boards[str(int(key))] = T
        seen[str(int(key))] = [NAMES[c] for c, _r, _t, margin, _p in views if margin > 5]
        clear[str(int(key))] = [NAMES[c] for c, _r, _t, margin, _p in views if margin > 25]
        for c, rvec, tvec, margin, part in views:
            whole = margin > 5
            if whole or (part and partial_images < 2):
                partial_images += not whole
                K, d = opencv(CAMERAS[c])
                img = render(BOARD, rvec, tvec, K=K, dist=d, size=SIZE, noise=1.0,
                             seed=int(key) * 10 + c)
                folder = root / NAMES[c]
                folder.mkdir(exist_ok=True)
                cv2.imwrite(str(folder / f"{NAMES[c]}_{key}.png"), img)
    for c, name in enumerate(NAMES):
        (root / f"{name}.toml").write_text(toml_from_dict({"calibration": {"left": CAMERAS[c]}}))
    return {"root": root, "boards": boards, "seen": seen, "clear": clear}


def run(args: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(["calibrate", "cameras", *args])
    return rc, out.getvalue(), err.getvalue()


def camera_args(root: Path, names=NAMES) -> list[str]:
    args = []
    for name in names:
        args += ["--camera", f"{name}={root / name / '*.png'}",
                 "--intrinsics", f"{name}={root / (name + '.toml')}"]
    return args


def far_end_set(cell: dict) -> str:
    return next(k for k, cams in cell["seen"].items() if cams == ["c", "d"])


def rotvec_pose(T: np.ndarray) -> str:
    v = [*T[:3, 3], *cv2.Rodrigues(T[:3, :3])[0].ravel()]
    return ",".join(repr(float(x)) for x in v)


@pytest.fixture(scope="module")
def board_run(cell) -> tuple[dict, Path]:
    root = cell["root"]
    key = far_end_set(cell)
    out = root / "cameras.toml"
    rc, stdout, _ = run([*camera_args(root), "--board", SPEC,
                         "--board-in-base", f"{key}={rotvec_pose(cell['boards'][key])}",
                         "--rig", "west=a,b", "--rig", "east=c,d", "-o", str(out), "--json"])
    assert rc == 0
    return json.loads(stdout), out


def test_scene_needs_chaining(cell):
    assert not any({"a", "d"} <= set(cams) for cams in cell["seen"].values())
    for name in NAMES:
        assert sum(name in cams for cams in cell["seen"].values()) >= 5


def test_cameras_in_the_base_frame_from_a_board_pose(board_run):
    """Every camera within 1.5 mm and 0.1 deg of the renderer's pose; the board pose was given
    for a set at the far end (c, d), so camera a carries the whole chain's error."""
    summary, _ = board_run
    assert [c["name"] for c in summary["cameras"]] == NAMES
    for c, cam in enumerate(summary["cameras"]):
        pose = cam["T_base_camera"]
        T = transform(pose["rotvec_rad"], pose["translation_mm"])
        mm, deg = pose_error(T, T_BASE_CAMERA[c])
        assert mm < 1.5, (cam["name"], mm)
        assert deg < 0.1, (cam["name"], deg)
        assert cam["rms_px"] < 0.15
        assert cam["intrinsics_source"] == "given"


def test_report_pairs_graph_rigs_and_left_out_images(board_run, cell):
    summary, _ = board_run
    assert summary["reference"] == "a"
    assert summary["view_graph"]["tree"] == [["a", "b"], ["b", "c"], ["c", "d"]]
    assert [(p["a"], p["b"]) for p in summary["pairs"]] == [("a", "b"), ("b", "c"), ("c", "d")]
    for p in summary["pairs"]:
        assert p["rotation_deg"]["rms"] < 0.5
        assert p["translation_mm"]["rms"] < 0.01 * p["board_distance_mm"]
    assert [r["name"] for r in summary["rigs"]] == ["west", "east"]
    assert all(r["rms_px"] < 0.15 for r in summary["rigs"])
    # images with the board partly in view are left out, each named with the reason
    partial = [r for r in summary["rejected"] if "board not found" in r["reason"]]
    assert partial
    assert all(Path(r["image"]).parent.name == r["camera"] for r in partial)
    kept = {s["set"]: s["cameras"] for s in summary["sets"]}
    for key, cams in cell["seen"].items():
        assert set(cell["clear"][key]) <= set(kept.get(key, [])) <= set(cams), key
    assert summary["warnings"] == []


def test_fragment_is_the_calibration_cameras_schema(board_run):
    """[[calibration.cameras]] and [[calibration.rigs]] as the config schema has them; when the
    config model knows ``cameras`` (multigeo's branch), the file also loads through include."""
    summary, out = board_run
    data = tomllib.loads(out.read_text())
    cams = data["calibration"]["cameras"]
    assert [c["name"] for c in cams] == NAMES
    for c, entry in enumerate(cams):
        assert set(entry) == {"name", "intrinsics", "mounting", "T_base_camera"}
        assert entry["mounting"] == "fixed"
        intr = IntrinsicsConfig.model_validate(entry["intrinsics"])
        assert intr.fx == CAMERAS[c]["fx"]
        pose = PoseConfig.model_validate(entry["T_base_camera"])
        assert list(pose.translation_mm) == summary["cameras"][c]["T_base_camera"][
            "translation_mm"]
    assert data["calibration"]["rigs"] == [{"name": "west", "cameras": ["a", "b"]},
                                           {"name": "east", "cameras": ["c", "d"]}]
    if "cameras" in CalibrationConfig.model_fields:
        cfg_path = out.parent / "cell.toml"
        cfg_path.write_text(f'include = ["{out.name}"]\n[camera]\ntype = "synthetic"\n')
        cfg = load_config(cfg_path)
        assert cfg.calibration.cameras is not None
        assert [c.name for c in cfg.calibration.cameras] == NAMES


def test_cameras_from_a_hand_eye_result(cell, tmp_path):
    """Camera c's hand-eye (its true T_base_camera) places all four."""
    root = cell["root"]
    he = tmp_path / "handeye.toml"
    T = T_BASE_CAMERA[2]
    he.write_text(toml_from_dict({"calibration": {"hand_eye": {
        "mounting": "fixed", "T_base_camera": {
            "translation_mm": [float(v) for v in T[:3, 3]],
            "rotvec_rad": [float(v) for v in cv2.Rodrigues(T[:3, :3])[0].ravel()]}}}}))
    out = tmp_path / "cams.toml"
    rc, stdout, _ = run([*camera_args(root), "--board", SPEC, "--hand-eye", f"c={he}",
                         "--reference", "b", "-o", str(out), "--json"])
    assert rc == 0
    summary = json.loads(stdout)
    assert summary["reference"] == "b"
    for c, cam in enumerate(summary["cameras"]):
        pose = cam["T_base_camera"]
        mm, deg = pose_error(transform(pose["rotvec_rad"], pose["translation_mm"]),
                             T_BASE_CAMERA[c])
        assert mm < 1.0, (cam["name"], mm)
        assert deg < 0.1, (cam["name"], deg)


def test_without_a_base_frame_nothing_is_placed(cell, tmp_path):
    out = tmp_path / "rel.toml"
    rc, stdout, stderr = run([*camera_args(cell["root"], NAMES[:2]), "--board", SPEC,
                              "-o", str(out)])
    assert rc == 0
    data = tomllib.loads(out.read_text())
    assert "calibration" not in data
    assert data["about"]["cameras"][1]["name"] == "b"
    assert "not placed in the robot base frame" in stderr
    assert "view graph tree: a -> b" in stdout


def test_cameras_that_share_no_set_are_refused_by_name(cell, tmp_path):
    """a and d alone never saw the board together."""
    rc, _, stderr = run([*camera_args(cell["root"], ["a", "d"]), "--board", SPEC,
                         "-o", str(tmp_path / "x.toml")])
    assert rc == 1
    assert "cannot connect camera(s) d to the reference a" in stderr
    assert not (tmp_path / "x.toml").exists()


@pytest.mark.parametrize(("extra", "message"), [
    (["--camera", "A=x*.png"], "camera name 'A' must be [a-z0-9_]+"),
    (["--camera", "a"], "expected NAME=GLOB"),
    (["--rig", "r=a,zz"], "--rig r: no --camera zz"),
    (["--rig", "a=a,b"], "--rig a: also a camera's name"),
    (["--rig", "r=a", "--rig", "s=b,a"], "--rig s: a camera is in one rig at most: a (in rig r)"),
    (["--reference", "zz"], "--reference zz: no --camera"),
    (["--board-in-base", "1=1,2,3"], "rotvec needs 6 finite numbers"),
    (["--board-in-base", "1=1,2,3,0,0,0", "--pose-format", "nope"], "--board-in-base:"),
    (["--intrinsics", "zz=x.toml"], "--intrinsics zz: no --camera zz"),
])
def test_bad_arguments_name_what_is_wrong(cell, tmp_path, extra, message):
    rc, _, stderr = run([*camera_args(cell["root"], ["a", "b"]), "--board", SPEC, *extra,
                         "-o", str(tmp_path / "x.toml")])
    assert rc == 1
    assert message in stderr


def test_files_without_a_set_number_are_refused(tmp_path):
    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        cv2.imwrite(str(tmp_path / name / "board.png"), np.zeros((4, 4), np.uint8))
    rc, _, stderr = run(["--camera", f"a={tmp_path / 'a' / '*.png'}", "--camera",
                         f"b={tmp_path / 'b' / '*.png'}", "--board", SPEC])
    assert rc == 1
    assert "board.png: no number in the file name" in stderr


def test_robot_mounted_hand_eye_puts_every_camera_on_the_flange(cell, tmp_path):
    """A hand-eye result with T_flange_camera for a: both written as mounting = "robot" with
    T_flange_camera = T_flange_a @ T_a_camera (here: the cell's base poses read as flange
    poses); intrinsics read from one file's [calibration.right]; a PNG report."""
    root = cell["root"]
    he = tmp_path / "handeye.toml"
    T = T_BASE_CAMERA[0]
    he.write_text(toml_from_dict({"calibration": {"hand_eye": {
        "mounting": "robot", "T_flange_camera": {
            "translation_mm": [float(v) for v in T[:3, 3]],
            "rotvec_rad": [float(v) for v in cv2.Rodrigues(T[:3, :3])[0].ravel()]}}}}))
    both = tmp_path / "rig.toml"
    both.write_text(toml_from_dict({"calibration": {"left": CAMERAS[1], "right": CAMERAS[0]}}))
    out, png = tmp_path / "flange.toml", tmp_path / "report.png"
    rc, stdout, _ = run(["--camera", f"a={root / 'a' / '*.png'}", "--camera",
                         f"b={root / 'b' / '*.png'}", "--intrinsics", f"a={both}:right",
                         "--intrinsics", f"b={both}", "--board", SPEC, "--hand-eye", f"a={he}",
                         "-o", str(out), "--report", str(png), "--json"])
    assert rc == 0
    summary = json.loads(stdout)
    assert summary["mounting"] == "robot"
    entries = tomllib.loads(out.read_text())["calibration"]["cameras"]
    assert [e["mounting"] for e in entries] == ["robot", "robot"]
    assert entries[0]["intrinsics"]["fx"] == CAMERAS[0]["fx"]
    assert entries[1]["intrinsics"]["fx"] == CAMERAS[1]["fx"]
    for c, entry in enumerate(entries):
        assert "T_base_camera" not in entry
        pose = entry["T_flange_camera"]
        mm, deg = pose_error(transform(pose["rotvec_rad"], pose["translation_mm"]),
                             T_BASE_CAMERA[c])
        assert mm < 1.0, (NAMES[c], mm)
        assert deg < 0.1, (NAMES[c], deg)
    image = cv2.imread(str(png))
    assert image is not None
    assert image.shape[0] > 100
    assert summary["report"] == str(png)


@pytest.mark.parametrize("vendor", ["kuka", "abb", "ur", "matrix"])
def test_board_pose_in_any_vendor_format(vendor):
    """--board-in-base in a robot's own format gives the same pose as in rotvec."""
    T = transform([0.3, -1.2, 2.9], [812.5, -40.25, 3.5])
    key, ours = _board_pose(f"0012={rotvec_pose(T)}", "rotvec")
    assert key == "12"
    np.testing.assert_allclose(ours, T, atol=1e-9)
    values = " ".join(repr(float(v)) for v in vendor_from_transform(vendor, T))
    key, theirs = _board_pose(f"12={values}", vendor)
    np.testing.assert_allclose(theirs, T, atol=1e-9)


def test_charuco_boards_seen_in_part(tmp_path):
    """ChArUco: a camera may see only part of the board; the corners it found are used (by
    their ids), so sets where the board hangs out of one image still link the pair."""
    board = Board.parse("charuco:7x5:25:18")
    rng = np.random.default_rng(3)
    centre = board.object_points().mean(axis=0)
    partial = 0
    for k in range(1, 9):
        R = cv2.Rodrigues(rng.uniform(-0.3, 0.3, 3))[0] @ cv2.Rodrigues(
            np.array([np.pi, 0.0, 0.0]))[0]
        T = np.eye(4)
        T[:3, :3] = R
        # alternately centred between a and b, and shifted so that one image cuts the board
        x = 100.0 + (0.0 if k % 2 else rng.choice([-130.0, 130.0]))
        T[:3, 3] = np.array([x, rng.uniform(-40, 40), rng.uniform(220, 300)]) - R @ centre
        for c in (0, 1):
            Tc = np.linalg.inv(T_BASE_CAMERA[c]) @ T
            K, d = opencv(CAMERAS[c])
            px = cv2.projectPoints(board.object_points(), cv2.Rodrigues(Tc[:3, :3])[0],
                                   Tc[:3, 3], K, d)[0].reshape(-1, 2)
            inside = ((px > 0) & (px < np.array(SIZE) - 1)).all(axis=1)
            partial += int(0 < inside.sum() < len(px))
            img = render(board, cv2.Rodrigues(Tc[:3, :3])[0].ravel(), Tc[:3, 3], K=K, dist=d,
                         size=SIZE, seed=k * 10 + c)
            (tmp_path / NAMES[c]).mkdir(exist_ok=True)
            cv2.imwrite(str(tmp_path / NAMES[c] / f"{k:02d}.png"), img)
    for c in (0, 1):
        (tmp_path / f"{NAMES[c]}.toml").write_text(
            toml_from_dict({"calibration": {"left": CAMERAS[c]}}))
    assert partial >= 3
    rc, stdout, _ = run([*camera_args(tmp_path, NAMES[:2]), "--board", board.spec,
                         "--hand-eye", f"a={write_hand_eye(tmp_path, T_BASE_CAMERA[0])}",
                         "-o", str(tmp_path / "c.toml"), "--json"])
    assert rc == 0
    summary = json.loads(stdout)
    assert len(summary["sets"]) == 8
    assert summary["pairs"][0]["shared_sets"] >= 6
    pose = summary["cameras"][1]["T_base_camera"]
    mm, deg = pose_error(transform(pose["rotvec_rad"], pose["translation_mm"]), T_BASE_CAMERA[1])
    assert mm < 1.0
    assert deg < 0.1
    assert summary["cameras"][0]["points"] < 8 * len(board.object_points())


def write_hand_eye(folder: Path, T: np.ndarray) -> Path:
    path = folder / "handeye.toml"
    path.write_text(toml_from_dict({"calibration": {"hand_eye": {
        "mounting": "fixed", "T_base_camera": {
            "translation_mm": [float(v) for v in T[:3, 3]],
            "rotvec_rad": [float(v) for v in cv2.Rodrigues(T[:3, :3])[0].ravel()]}}}}))
    return path
