"""`vgripd calibrate handeye` refuses a fit that noise cannot explain, and says why.

A synthetic eye-in-hand set made through the real command: chessboard images rendered through
a known camera (``test_calib_boards.render``) and robot poses with a realistic error (0.05 deg,
0.3 mm per axis) written in a vendor's format. With the right input the command writes the
result; with the input read wrong (pose format, units, pose order, mounting) it exits 1,
writes nothing, gives the residual against what noise explains and names the cause, the
reading that fits when there is one. ``--force`` writes the result anyway, warning loudly.
A robot noise estimate at an edge of its search grid is reported as a bound.
"""

from __future__ import annotations

import json
import tomllib
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
from test_calib_boards import SIZE, K, render

from vgripd.__main__ import main
from vgripd.calib.boards import Board
from vgripd.calib.handeye import (
    REFUSE_RATIO,
    ROBOT_SIGMA_DEG,
    ROBOT_SIGMA_MM,
    save_samples,
    synthetic_samples,
)
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.transforms import (
    invert_transform,
    make_transform,
    matrix_from_rotvec,
    pose_error,
    transforms_from_vectors,
)
from vgripd.geometry.vendors import vendor_from_transform

BOARD = "chessboard:9x6:30"
X_TRUE = make_transform(matrix_from_rotvec([0.02, -0.05, 1.57]), [60.0, -30.0, -40.0])
BOARD_IN_BASE = make_transform(matrix_from_rotvec([3.1, 0.1, 0.0]), [600.0, 50.0, -100.0])
N = 10
# views: (roll deg, tilt about x rad, tilt about y rad, distance mm)
VIEWS = [(15 + 37 * i, 0.35 * np.cos(1.3 * i), 0.35 * np.sin(1.7 * i + 0.4), 420 + 15 * (i % 4))
         for i in range(N)]


@dataclass
class Rig:
    folder: Path
    poses: list[np.ndarray]  # T_base_flange as the controller reports them (with its error)
    camera: Path

    def images(self) -> str:
        return str(self.folder / "img*.png")

    def write_poses(self, name: str, fmt: str, poses: list[np.ndarray] | None = None,
                    scale: float = 1.0) -> Path:
        """The poses in ``fmt``'s numbers, positions multiplied by ``scale``."""
        lines = []
        for T in self.poses if poses is None else poses:
            v = list(vendor_from_transform(fmt, T))
            v[:3] = [x * scale for x in v[:3]]
            lines.append(" ".join(f"{x:.9g}" for x in v))
        path = self.folder / name
        path.write_text("\n".join(lines) + "\n")
        return path


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Rig:
    folder = tmp_path_factory.mktemp("handeye_rig")
    board = Board.parse(BOARD)
    centre = board.object_points().mean(axis=0)
    rng = np.random.default_rng(4)
    poses = []
    for i, (roll, tx, ty, distance) in enumerate(VIEWS):
        R = (cv2.Rodrigues(np.array([tx, ty, 0.0]))[0]
             @ cv2.Rodrigues(np.array([0.0, 0.0, np.radians(roll)]))[0])
        t = np.array([0.0, 0.0, distance]) - R @ centre
        cv2.imwrite(str(folder / f"img{i:02d}.png"),
                    render(board, cv2.Rodrigues(R)[0].ravel(), t, seed=i))
        B = make_transform(R, t)  # T_cam_board
        P = BOARD_IN_BASE @ invert_transform(B) @ invert_transform(X_TRUE)
        error = np.concatenate([np.radians(rng.normal(scale=0.05, size=3)),
                                rng.normal(scale=0.3, size=3)])
        poses.append(P @ transforms_from_vectors(error))
    camera = folder / "camera.toml"
    camera.write_text(f"[calibration.left]\nfx = {K[0, 0]}\nfy = {K[1, 1]}\ncx = {K[0, 2]}\n"
                      f"cy = {K[1, 2]}\nwidth = {SIZE[0]}\nheight = {SIZE[1]}\n")
    return Rig(folder, poses, camera)


def _run(rig: Rig, tmp_path: Path, capsys: pytest.CaptureFixture[str], poses: Path, fmt: str,
         *extra: str, mode: str = "eye-in-hand") -> tuple[int, str, str, Path]:
    out = tmp_path / "handeye.toml"
    rc = main(["calibrate", "handeye", "--mode", mode, "--poses", str(poses), "--pose-format",
               fmt, "--images", rig.images(), "--board", BOARD, "--intrinsics", str(rig.camera),
               "-o", str(out), *extra])
    captured = capsys.readouterr()
    return rc, captured.out, captured.err, out


def _refused(rc: int, err: str, out: Path) -> str:
    assert rc == 1, err
    assert not out.exists()
    assert "refused: the fit does not explain the data" in err
    assert "--force writes the result anyway" in err
    # every likely cause is listed with the flag to check
    for flag in ("--pose-format", "units", "pose order", "--exclude", "--mode"):
        assert flag in err, flag
    return " ".join(err.split())  # one line: the message wraps


def test_right_input_is_written_and_passes_the_check(rig: Rig, tmp_path: Path, capsys) -> None:
    rc, stdout, err, out = _run(rig, tmp_path, capsys, rig.write_poses("kuka.txt", "kuka"),
                                "kuka", "--json")
    assert rc == 0, err
    summary = json.loads(stdout)
    check = summary["fit_check"]
    assert check["ok"] is True
    assert check["ratio"] < REFUSE_RATIO / 3  # clear of the limit
    assert check["better_readings"] == []
    assert check["forced"] is False
    mm, deg = pose_error(np.array(summary["matrix_mm"]), X_TRUE)
    assert deg < 0.2
    assert mm < 2.0
    assert not any("does not explain" in w or "FORCED" in w for w in summary["warnings"])
    about = tomllib.loads(out.read_text())["about"]
    assert about["fit_check"]["ok"] is True


def test_kuka_poses_read_as_fanuc_are_refused_naming_kuka(rig: Rig, tmp_path: Path,
                                                         capsys) -> None:
    """The issue's case: KUKA's A B C read as FANUC's W P R."""
    rc, _, err, out = _run(rig, tmp_path, capsys, rig.write_poses("kuka.txt", "kuka"), "fanuc")
    text = _refused(rc, err, out)
    assert "reprojection RMS" in text
    assert "the corners' own noise is" in text
    assert "Most likely the pose format: the data fit with --pose-format kuka" in text
    # the robot noise is not called noise when the fit is refused
    assert "most likely noise" not in text
    assert "robot noise of that size explains" not in text


def test_fanuc_poses_read_as_kuka_are_refused_naming_fanuc(rig: Rig, tmp_path: Path,
                                                          capsys) -> None:
    rc, _, err, out = _run(rig, tmp_path, capsys, rig.write_poses("fanuc.txt", "fanuc"), "kuka")
    text = _refused(rc, err, out)
    assert "Most likely the pose format: the data fit with --pose-format fanuc" in text


def test_metres_given_as_millimetres_are_refused_naming_the_units(rig: Rig, tmp_path: Path,
                                                                  capsys) -> None:
    poses = rig.write_poses("kuka_m.txt", "kuka", scale=0.001)
    rc, _, err, out = _run(rig, tmp_path, capsys, poses, "kuka")
    text = _refused(rc, err, out)
    assert ("Most likely the units: the data fit with the robot positions x1000 (the poses "
            "file holds m where --pose-format kuka expects mm)") in text


def test_millimetres_given_as_metres_are_refused_naming_the_units(rig: Rig, tmp_path: Path,
                                                                  capsys) -> None:
    poses = rig.write_poses("ur_mm.txt", "ur", scale=1000.0)
    rc, _, err, out = _run(rig, tmp_path, capsys, poses, "ur")
    text = _refused(rc, err, out)
    assert ("Most likely the units: the data fit with the robot positions x0.001 (the poses "
            "file holds mm where --pose-format ur expects m)") in text


def test_poses_shifted_by_one_are_refused_naming_the_order(rig: Rig, tmp_path: Path,
                                                           capsys) -> None:
    """The pose of image k+1 on line k (the first pose missing, one extra at the end)."""
    shifted = rig.poses[1:] + rig.poses[:1]
    rc, _, err, out = _run(rig, tmp_path, capsys, rig.write_poses("shift.txt", "kuka", shifted),
                           "kuka")
    text = _refused(rc, err, out)
    assert ("Most likely the pose order: the data fit with each image with the pose one line "
            "earlier in the poses file") in text


def test_shuffled_poses_are_refused_with_the_causes_to_check(rig: Rig, tmp_path: Path,
                                                             capsys) -> None:
    order = [3, 7, 0, 9, 1, 8, 2, 5, 4, 6]  # no pose in its place
    shuffled = [rig.poses[k] for k in order]
    rc, _, err, out = _run(rig, tmp_path, capsys,
                           rig.write_poses("shuffled.txt", "kuka", shuffled), "kuka")
    text = _refused(rc, err, out)
    assert "No other pose format, units, shift by one, mounting" in text
    assert "the pose order (one pose per image, in image order" in text


def test_two_swapped_lines_are_refused_naming_the_samples(rig: Rig, tmp_path: Path,
                                                          capsys) -> None:
    swapped = list(rig.poses)
    swapped[2], swapped[6] = swapped[6], swapped[2]
    rc, _, err, out = _run(rig, tmp_path, capsys,
                           rig.write_poses("swapped.txt", "kuka", swapped), "kuka")
    text = _refused(rc, err, out)
    assert "Most likely bad samples" in text
    assert "the data fit with --exclude 2,6" in text


def test_wrong_mounting_is_refused_naming_the_mode(rig: Rig, tmp_path: Path, capsys) -> None:
    rc, _, err, out = _run(rig, tmp_path, capsys, rig.write_poses("kuka.txt", "kuka"), "kuka",
                           mode="eye-to-hand")
    text = _refused(rc, err, out)
    assert "Most likely the mounting: the data fit with --mode eye-in-hand" in text


def test_force_writes_the_refused_result_with_a_loud_warning(rig: Rig, tmp_path: Path,
                                                             capsys) -> None:
    poses = rig.write_poses("kuka.txt", "kuka")
    rc, stdout, err, out = _run(rig, tmp_path, capsys, poses, "fanuc", "--force")
    assert rc == 0, err
    assert stdout.startswith("!!! NOT A VALID CALIBRATION")
    assert "fit check:" in stdout
    assert "FAILED, written only because of --force" in stdout
    assert "warning: FORCED (--force): this result is most likely WRONG" in err
    assert "--pose-format kuka" in err
    data = tomllib.loads(out.read_text())
    assert "T_flange_camera" in data["calibration"]["hand_eye"]
    about = data["about"]
    assert about["fit_check"]["ok"] is False
    assert about["fit_check"]["forced"] is True
    assert about["fit_check"]["ratio"] > REFUSE_RATIO
    assert "--force" in about["command"]
    assert about["fit_check"]["better_readings"][0]["change"].startswith("--pose-format kuka")
    assert any(w.startswith("FORCED") for w in about["warnings"])
    # the misread robot poses need a robot noise beyond the top of the grid: a bound
    assert about["noise"]["robot_at_edge"] is True
    assert about["noise"]["robot_deg_at_least"] == ROBOT_SIGMA_DEG[-1]
    assert "robot_deg" not in about["noise"]



def test_force_json_reports_the_failed_check(rig: Rig, tmp_path: Path, capsys) -> None:
    poses = rig.write_poses("kuka_m.txt", "kuka", scale=0.001)
    rc, stdout, err, out = _run(rig, tmp_path, capsys, poses, "kuka", "--force", "--json")
    assert rc == 0, err
    summary = json.loads(stdout)
    check = summary["fit_check"]
    assert check["ok"] is False
    assert check["forced"] is True
    assert check["better_readings"][0]["cause"] == "the units"
    assert check["better_readings"][0]["change"].startswith("the robot positions x1000")
    assert check["ratio"] > 3.0 * check["better_readings"][0]["ratio"]
    assert summary["warnings"][0].startswith("FORCED (--force)")
    assert out.exists()


# ---------------------------------------------------------------------- the robot noise grid
CAMERA = CameraModel(800.0, 805.0, 322.0, 241.0, dist=(-0.12, 0.08, 0.0005, -0.0003, 0.0),
                     width=640, height=480)
POINTS = np.zeros((54, 3))
POINTS[:, 1], POINTS[:, 0] = np.divmod(np.arange(54), 9)
POINTS *= 25.0


def test_exact_robot_poses_report_the_lower_edge_of_the_search_range(tmp_path: Path,
                                                                     capsys) -> None:
    """Robot poses without error: the most likely robot noise is the smallest of the grid,
    which says "at most", not a figure, in the human, --json and result file output."""
    samples = synthetic_samples("eye-in-hand", X_TRUE, BOARD_IN_BASE, CAMERA, POINTS, 12,
                                rng=np.random.default_rng(0), noise_px=0.2)
    path = save_samples(tmp_path / "s.json", samples, "eye-in-hand", None, CAMERA)
    out = tmp_path / "he.toml"
    argv = ["calibrate", "handeye", "--samples", str(path), "-o", str(out)]
    assert main([*argv, "--json"]) == 0
    noise = json.loads(capsys.readouterr().out)["noise"]
    assert noise["robot_at_edge"] is True
    assert noise["robot_deg"] is None
    assert noise["robot_mm"] is None
    assert noise["robot_deg_at_most"] == ROBOT_SIGMA_DEG[0]
    assert noise["robot_mm_at_most"] == ROBOT_SIGMA_MM[0]
    assert noise["robot_deg_at_least"] is None
    assert noise["robot_search_range"] == {"deg": [ROBOT_SIGMA_DEG[0], ROBOT_SIGMA_DEG[-1]],
                                           "mm": [ROBOT_SIGMA_MM[0], ROBOT_SIGMA_MM[-1]]}
    about = tomllib.loads(out.read_text())["about"]["noise"]
    assert "robot_deg" not in about
    assert about["robot_deg_at_most"] == ROBOT_SIGMA_DEG[0]
    assert about["robot_mm_at_most"] == ROBOT_SIGMA_MM[0]
    assert about["robot_at_edge"] is True
    assert main(argv) == 0
    human = capsys.readouterr().out
    assert ("robot poses <= 0.0001 deg and <= 0.001 mm (at the edge of the search range, "
            "0.0001-1 deg and 0.001-10 mm)") in human


def test_robot_noise_inside_the_grid_is_a_figure(tmp_path: Path, capsys) -> None:
    samples = synthetic_samples("eye-in-hand", X_TRUE, BOARD_IN_BASE, CAMERA, POINTS, 12,
                                rng=np.random.default_rng(1), noise_px=0.2,
                                robot_noise_deg=0.1, robot_noise_mm=0.3)
    path = save_samples(tmp_path / "s.json", samples, "eye-in-hand", None, CAMERA)
    assert main(["calibrate", "handeye", "--samples", str(path), "-o",
                 str(tmp_path / "he.toml"), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    noise = summary["noise"]
    assert noise["robot_at_edge"] is False
    assert ROBOT_SIGMA_DEG[0] < noise["robot_deg"] < ROBOT_SIGMA_DEG[-1]
    assert ROBOT_SIGMA_MM[0] < noise["robot_mm"] < ROBOT_SIGMA_MM[-1]
    assert noise["robot_deg_at_most"] is None
    assert noise["robot_mm_at_least"] is None
    assert summary["fit_check"]["ok"] is True


def test_robot_far_beyond_the_grid_is_refused_and_forced_reports_the_upper_edge(
        tmp_path: Path, capsys) -> None:
    """Robot poses off by 3 deg / 30 mm per axis: beyond any working robot, refused (no
    reading of the input fits better); forced, the robot noise is reported as at least the
    top of the grid."""
    samples = synthetic_samples("eye-in-hand", X_TRUE, BOARD_IN_BASE, CAMERA, POINTS, 12,
                                rng=np.random.default_rng(2), noise_px=0.2,
                                robot_noise_deg=3.0, robot_noise_mm=30.0)
    path = save_samples(tmp_path / "s.json", samples, "eye-in-hand", None, CAMERA)
    out = tmp_path / "he.toml"
    argv = ["calibrate", "handeye", "--samples", str(path), "-o", str(out)]
    assert main(argv) == 1
    err = " ".join(capsys.readouterr().err.split())
    assert "refused: the fit does not explain the data" in err
    assert not out.exists()
    assert main([*argv, "--force", "--json"]) == 0
    noise = json.loads(capsys.readouterr().out)["noise"]
    assert noise["robot_deg_at_least"] == ROBOT_SIGMA_DEG[-1]
    assert noise["robot_mm_at_least"] == ROBOT_SIGMA_MM[-1]
    assert noise["robot_deg"] is None
    assert noise["robot_mm"] is None
    assert tomllib.loads(out.read_text())["about"]["noise"]["robot_mm_at_least"] == 10.0
