"""The walked hand-eye calibration's web helpers (``vgripd.service.web.walking``): which plan
files the page may name, the include the accept writes and what it writes, and the plan
command a form becomes (no option smuggled in through a field)."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from vgripd.calib.handeye.plan import plan_inside
from vgripd.errors import CalibrationError
from vgripd.service.web.commission import TuningError
from vgripd.service.web.walking import hand_eye_target, plan_command, with_hand_eye

HAND_EYE = """[calibration.hand_eye]
mounting = "fixed"

[calibration.hand_eye.T_base_camera]
translation_mm = [1.0, 2.0, 3.0]
rotvec_rad = [0.0, 0.0, 0.1]
"""
SOLVED = """# hand-eye calibration (eye-to-hand)
[calibration.hand_eye]
mounting = "fixed"

[calibration.hand_eye.T_base_camera]
translation_mm = [10.0, 20.0, 30.0]
rotvec_rad = [0.0, 0.0, 0.2]

[about]
camera_model = "abc"
"""


def test_plan_files_stay_in_the_configs_folder(tmp_path: Path) -> None:
    config = tmp_path / "vgripd.toml"
    assert plan_inside(config, "plan.toml") == (tmp_path / "plan.toml").resolve()
    assert plan_inside(config, str(tmp_path / "sub" / "p.toml")).parent.name == "sub"
    for bad in ("../plan.toml", "/etc/plan.toml", "plan.json", "sub/../../x.toml"):
        with pytest.raises(CalibrationError, match="inside"):
            plan_inside(config, bad)


def test_accept_writes_only_the_include_that_holds_the_hand_eye(tmp_path: Path) -> None:
    main = tmp_path / "vgripd.toml"
    main.write_text('[camera]\ntype = "synthetic"\n' + HAND_EYE)
    with pytest.raises(TuningError, match="main config file"):
        hand_eye_target(main)
    (tmp_path / "he.toml").write_text(HAND_EYE)
    main.write_text('include = ["he.toml"]\n[camera]\ntype = "synthetic"\n')
    assert hand_eye_target(main) == tmp_path / "he.toml"


def test_the_accepted_text_takes_the_solved_hand_eye_and_keeps_the_rest() -> None:
    assert with_hand_eye(HAND_EYE, SOLVED) == SOLVED  # a file of the hand-eye alone
    mixed = tomllib.loads(with_hand_eye(HAND_EYE + '\n[vision]\nmin_contrast = 20.0\n', SOLVED))
    assert mixed["vision"] == {"min_contrast": 20.0}
    assert mixed["calibration"]["hand_eye"]["T_base_camera"]["translation_mm"] == [10, 20, 30]
    assert "about" not in mixed


def test_a_form_becomes_the_plan_command_and_no_option(tmp_path: Path) -> None:
    form = {"mode": "eye-in-hand", "board": "chessboard:9x6:25", "around": "-0.1 0.2 0.3 0 0 0",
            "box": [250, 30], "count": 15, "distance": 420, "board_offset": "", "save": "x"}
    words = plan_command(form, tmp_path / "c.toml", tmp_path / "d.png", None)
    assert words[:3] == ["calibrate", "handeye", "plan"]
    assert "--box=250 30" in words
    assert "--around=-0.1 0.2 0.3 0 0 0" in words
    assert "--board=--draw=/etc/x" in plan_command({**form, "board": "--draw=/etc/x"},
                                                   tmp_path / "c.toml", tmp_path / "d.png", None)
    assert not any(w.startswith("--board-offset") for w in words)
    assert words[-1] == "--dry-run"
    assert plan_command(form, tmp_path / "c.toml", tmp_path / "d.png",
                        tmp_path / "p.toml")[-2:] == ["-o", str(tmp_path / "p.toml")]
    for field, value in (("count", True), ("mode", {"a": 1}),
                         ("board", "x" * 500)):
        with pytest.raises(TuningError, match=field):
            plan_command({**form, field: value}, tmp_path / "c.toml", tmp_path / "d.png", None)


def test_a_board_the_planner_cannot_use_is_refused_before_it_is_spawned() -> None:
    """A board of 500x500 squares ran the planner for minutes and ended in an internal error:
    its size in the image is judged first, from the running camera model."""
    from types import SimpleNamespace

    from vgripd.calib.handeye.plan import board_size_problem
    from vgripd.service.web.walking import planned_board_problem

    left = SimpleNamespace(width=1280, height=1024, fx=1200.0, fy=1200.0)
    config = SimpleNamespace(calibration=SimpleNamespace(left=left))
    form = {"board": "chessboard:500x500:20", "distance": 600}
    assert "250000 corners" in (planned_board_problem(form, config) or "")
    form = {"board": "chessboard:9x6:2", "distance": "600"}  # 4 px between corners
    assert "at least 8 px" in (planned_board_problem(form, config) or "")
    form = {"board": "chessboard:40x30:30", "distance": 600}  # 2340 px wide
    assert "does not fit" in (planned_board_problem(form, config) or "")
    assert planned_board_problem({"board": "chessboard:9x6:30", "distance": 600}, config) is None
    assert board_size_problem(9, 6, 30.0, 600.0, 1280, 1024, 1200.0, 1200.0) is None
    # what only the planner can judge is left to it
    assert planned_board_problem({"board": "chessboard:9x6:30", "distance": "far"}, config) is None
