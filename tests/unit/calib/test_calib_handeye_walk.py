"""The walked hand-eye calibration through the real commands: ``calibrate handeye plan`` makes
the targets from a config with a rough hand-eye, a simulated arm (reach limit, settle cycles,
noise on the pose it reports) visits them as a robot program would, each image is rendered from
the pose reached (``test_calib_boards.render``) and recorded by :class:`Walk`, and
``calibrate handeye --samples`` solves the record: within 0.05 mm / 0.01 deg of the truth for
eye-in-hand and eye-to-hand; the unreachable target is skipped and listed; an interrupted walk
resumes where it stopped. The plan command refuses small and parallel rotations with the reason.
"""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path

import cv2
import numpy as np
import pytest
import test_calib_boards
from test_calib_boards import render

from vgripd.__main__ import main
from vgripd.calib.boards import Board
from vgripd.calib.files import pose_table
from vgripd.calib.handeye.plan import load_plan, plan_condition
from vgripd.calib.handeye.walk import NOT_SEEN, SEEN, UNREACHABLE, Walk
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.transforms import (
    invert_transform,
    make_transform,
    matrix_from_rotvec,
    pose_error,
    transforms_from_vectors,
)
from vgripd.geometry.vendors import vendor_from_transform
from vgripd.serialize import toml_from_dict
from vgripd.sim.arm import ArmState, SimulatedArm, Unreachable

BOARD = Board.parse("chessboard:9x6:25")
# a 1.2 MP camera (what a cell uses; the 640x480 of test_calib_boards leaves 0.2 mm)
SIZE_HE = (1280, 960)
K_HE = np.array([[1500.0, 0.0, 641.0], [0.0, 1500.0, 479.0], [0.0, 0.0, 1.0]])
CAMERA = CameraModel(K_HE[0, 0], K_HE[1, 1], K_HE[0, 2], K_HE[1, 2], 0.0, (0.0,) * 5, *SIZE_HE)
DISTANCE = 420.0
X_EYE_IN_HAND = make_transform(matrix_from_rotvec([0.02, -0.03, 1.55]), [55.0, -32.0, 80.0])
T_BASE_BOARD = make_transform(matrix_from_rotvec([math.pi, 0.0, 0.2]), [650.0, 40.0, 20.0])
T_BASE_CAMERA = make_transform(matrix_from_rotvec([0.0, math.pi * 0.95, 0.1]),
                               [600.0, -30.0, -250.0])
CENTRE = BOARD.object_points().mean(axis=0)
FLIP = make_transform(matrix_from_rotvec([math.pi, 0.0, 0.0]), np.zeros(3))
T_FLANGE_BOARD = (make_transform(np.eye(3), [0.0, 0.0, 30.0]) @ FLIP
                  @ make_transform(np.eye(3), -CENTRE))
B0 = make_transform(np.eye(3), np.array([0.0, 0.0, DISTANCE]) - CENTRE)
ROUGH = transforms_from_vectors(np.array([0.02, -0.015, 0.03, 4.0, -3.0, 5.0]))  # ~2 deg, 7 mm


@pytest.fixture(autouse=True)
def sharp_texture(monkeypatch: pytest.MonkeyPatch) -> None:
    """The printed texture at about the imaged scale (1500 px / 420 mm = 3.6 px/mm)."""
    monkeypatch.setattr(test_calib_boards, "PPM", 4.0)


def truth(mode: str) -> tuple[np.ndarray, np.ndarray]:
    """(true X, start flange pose where the camera sees the board centre at DISTANCE)."""
    if mode == "eye-in-hand":
        X = X_EYE_IN_HAND
        return X, T_BASE_BOARD @ invert_transform(B0) @ invert_transform(X)
    return T_BASE_CAMERA, T_BASE_CAMERA @ B0 @ invert_transform(T_FLANGE_BOARD)


def write_cell(folder: Path, mode: str) -> Path:
    X, _ = truth(mode)
    rough = pose_table(X @ ROUGH)
    hand_eye = ({"mounting": "robot", "T_flange_camera": rough} if mode == "eye-in-hand"
                else {"mounting": "fixed", "T_base_camera": rough})
    left = {"fx": CAMERA.fx, "fy": CAMERA.fy, "cx": CAMERA.cx, "cy": CAMERA.cy,
            "width": CAMERA.width, "height": CAMERA.height}
    path = folder / "cell.toml"
    path.write_text(toml_from_dict({"camera": {"type": "synthetic"},
                                    "output": {"vendor": "ur"},
                                    "calibration": {"left": left, "hand_eye": hand_eye}}),
                    encoding="utf-8")
    return path


def make_plan(folder: Path, mode: str, box: str = "250 30", count: int = 16) -> int:
    _, T0 = truth(mode)
    around = " ".join(f"{v:.9f}" for v in vendor_from_transform("ur", T0))
    return main(["calibrate", "handeye", "plan", "--mode", mode, "-c",
                 str(write_cell(folder, mode)), "--board", BOARD.spec, "--around", around,
                 "--box", box, "--distance", str(DISTANCE), "--count", str(count),
                 "--board-offset", "0 0 30", "-o", str(folder / "plan.toml")])


def image_at(mode: str, T_true: np.ndarray, seed: int) -> np.ndarray:
    X, _ = truth(mode)
    if mode == "eye-in-hand":
        B = invert_transform(X) @ invert_transform(T_true) @ T_BASE_BOARD
    else:
        B = invert_transform(X) @ T_true @ T_FLANGE_BOARD
    rvec, _ = cv2.Rodrigues(B[:3, :3])
    return render(BOARD, rvec.ravel(), B[:3, 3], K=K_HE, size=SIZE_HE, noise=1.0, seed=seed)


def walk(walk_file: Path, plan_file: Path, arm: SimulatedArm, mode: str,
         stop_after: int | None = None) -> Walk:
    """The robot program's loop: next target, move (or report it unreachable), wait until
    settled, image with the pose reached."""
    w = Walk(walk_file, load_plan(str(plan_file)), BOARD, CAMERA)
    done = 0
    while (k := w.next_index()) is not None:
        if stop_after is not None and done == stop_after:
            break  # the robot stopped: the walk object is dropped here
        try:
            arm.move(w.target(k))
        except Unreachable as err:
            w.unreachable(k, str(err))
            done += 1
            continue
        while arm.step() is not ArmState.SETTLED:
            pass
        w.capture(k, arm.reported_pose(), image_at(mode, arm.T_true, seed=k))
        done += 1
    return w


@pytest.mark.parametrize("mode", ["eye-in-hand", "eye-to-hand"])
def test_walked_calibration_within_tolerance_skips_unreachable_and_resumes(
        tmp_path: Path, mode: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert make_plan(tmp_path, mode) == 0
    plan = load_plan(str(tmp_path / "plan.toml"))
    assert len(plan.poses) == 16
    assert plan.condition.condition < 3
    assert plan.condition.effective_deg > 15
    # the farthest target is beyond the arm's reach
    reach = sorted(np.linalg.norm(T[:3, 3]) for T in plan.poses)
    arm = SimulatedArm(plan.poses[0], reach_mm=(reach[-1] + reach[-2]) / 2, settle_cycles=4,
                       noise_deg=0.001,
                       noise_mm=0.005, rng=np.random.default_rng(7))
    walk_file = tmp_path / "walk.json"
    first = walk(walk_file, tmp_path / "plan.toml", arm, mode, stop_after=6)
    assert len(first.records) == 6
    resumed = walk(walk_file, tmp_path / "plan.toml", arm, mode)  # a new process would do this
    assert sorted(resumed.records) == list(range(16))
    assert arm.moves == 15  # every reachable target visited once, none again after the resume
    statuses = [r.status for _, r in sorted(resumed.records.items())]
    assert statuses.count(UNREACHABLE) == 1
    assert NOT_SEEN not in statuses
    assert statuses.count(SEEN) == 15
    out = tmp_path / "handeye.toml"
    capsys.readouterr()
    assert main(["calibrate", "handeye", "--samples", str(walk_file), "--intrinsics",
                 str(tmp_path / "cell.toml"), "-o", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    X = np.asarray(summary["matrix_mm"])
    mm, deg = pose_error(X, truth(mode)[0])
    assert mm < 0.05, (mm, deg)
    assert deg < 0.01, (mm, deg)
    result = tomllib.loads(out.read_text(encoding="utf-8"))
    about = result["about"]
    assert about["plan"]["condition"]["condition"] == pytest.approx(plan.condition.condition)
    assert any("unreachable" in r["reason"] for r in about["rejected"])
    assert about["stability"]["translation_mm"] > 0  # leave-one-out spread written
    mounting = "robot" if mode == "eye-in-hand" else "fixed"
    assert result["calibration"]["hand_eye"]["mounting"] == mounting


def test_resume_refuses_the_record_of_another_plan(tmp_path: Path) -> None:
    assert make_plan(tmp_path, "eye-in-hand") == 0
    arm = SimulatedArm(load_plan(str(tmp_path / "plan.toml")).poses[0], reach_mm=1e4)
    walk(tmp_path / "walk.json", tmp_path / "plan.toml", arm, "eye-in-hand", stop_after=2)
    assert make_plan(tmp_path, "eye-in-hand", box="200 25") == 0
    with pytest.raises(Exception, match="another plan"):
        walk(tmp_path / "walk.json", tmp_path / "plan.toml", arm, "eye-in-hand")


def test_plan_dry_run_prints_the_robots_convention_and_draws(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _, T0 = truth("eye-in-hand")
    around = " ".join(f"{v:.3f}" for v in vendor_from_transform("kuka", T0))
    assert main(["calibrate", "handeye", "plan", "--mode", "eye-in-hand", "-c",
                 str(write_cell(tmp_path, "eye-in-hand")), "--board", BOARD.spec, "--around",
                 around, "--pose-format", "kuka", "--box", "250 30", "--distance",
                 str(DISTANCE), "--dry-run", "--draw", str(tmp_path / "plan.png")]) == 0
    out = capsys.readouterr().out
    assert "15 poses in kuka (X Y Z A B C)" in out
    first = out.splitlines()[1].split("#")[0].split()
    assert [float(v) for v in first[1:]] == pytest.approx([float(v) for v in around.split()],
                                                          abs=2e-3)
    assert "dry run: nothing written" in out
    assert not (tmp_path / "handeye-plan.toml").exists()
    drawing = cv2.imread(str(tmp_path / "plan.png"))
    assert drawing is not None
    assert drawing.shape[1] == 1000  # the 1280 px wide image scaled to 1000


def test_plan_refuses_small_rotations_with_the_reason(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert make_plan(tmp_path, "eye-in-hand", box="250 3") == 1
    err = capsys.readouterr().err
    assert "refused: the rotations are too small" in err
    assert not (tmp_path / "plan.toml").exists()


def test_condition_names_parallel_axes_and_small_rotations() -> None:
    T0 = np.eye(4)
    about_z = [T0 @ make_transform(matrix_from_rotvec([0, 0, math.radians(20 * k)]), [0, 0, 0])
               for k in range(12)]
    problems = plan_condition(about_z).problems()
    assert any("nearly parallel" in p for p in problems)
    rng = np.random.default_rng(1)
    small = [transforms_from_vectors(np.concatenate([np.radians(rng.uniform(-2, 2, 3)),
                                                     rng.uniform(-20, 20, 3)]))
             for _ in range(15)]
    problems = plan_condition(small).problems()
    assert any("too small" in p for p in problems)


def test_walk_over_a_link_without_flange_pose_is_refused_naming_it(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A Modbus server's requests carry no flange pose: the walk is refused before it starts
    (before, the robot's first TRIGGER got BAD_REQUEST in the middle of the walk)."""
    assert make_plan(tmp_path, "eye-in-hand") == 0
    cell = tmp_path / "cell.toml"
    cell.write_text(cell.read_text(encoding="utf-8")
                    + '\n[[links]]\ntype = "modbus_server"\nhost = "127.0.0.1"\nport = 0\n',
                    encoding="utf-8")
    code = main(["calibrate", "handeye", "walk", "-c", str(cell),
                 "--plan", str(tmp_path / "plan.toml")])
    err = capsys.readouterr().err
    assert code != 0
    assert "links.0" in err
    assert "no flange pose" in err
    assert not (tmp_path / "plan.walk.json").exists()
