"""Calibration files that belong together: the camera-model fingerprint each result file records
(``vgripd.geometry.fingerprint``), checked by the config loader (so by ``vgripd check`` and at the
daemon's start): a hand-eye or a taught reference made with another camera model (or the
reference with another hand-eye) is refused naming both files; a file without a fingerprint
loads with a warning. And the symmetric-board warning (9x7 inner corners)."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from vgripd.__main__ import main
from vgripd.calib.boards import Board
from vgripd.calib.files import pose_table, write_result
from vgripd.calib.handeye import save_samples, synthetic_samples
from vgripd.config import DEMO_CALIBRATION, load_config
from vgripd.errors import ConfigError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.fingerprint import camera_fingerprint, hand_eye_fingerprint
from vgripd.geometry.transforms import make_transform, matrix_from_rotvec
from vgripd.serialize import toml_from_dict

LEFT = {"fx": 1200.0, "fy": 1199.5, "cx": 640.2, "cy": 511.7, "skew": 0.0,
        "dist": [-0.08, 0.11, 0.0002, -0.0001, -0.01], "width": 1280, "height": 1024}
X_TRUE = make_transform(matrix_from_rotvec([0.02, -0.05, 1.57]), [60.0, -30.0, -40.0])
# where the synthetic camera puts the demo plate (as tests/integration/test_teach_cli.py)
POSE = "pose = {translation_mm = [604.0, 97.0, 12.0], rotvec_rad = [0.01, -0.02, 0.08]}\n"
BOARD_IN_BASE = make_transform(matrix_from_rotvec([3.1, 0.1, 0.0]), [600.0, 50.0, -100.0])


def camera(left: dict[str, Any]) -> CameraModel:
    return CameraModel(left["fx"], left["fy"], left["cx"], left["cy"], left["skew"],
                       tuple(left["dist"]), left["width"], left["height"])


def write_camera(path: Path, left: dict[str, Any]) -> Path:
    return write_result(path, {"calibration": {"left": left}}, {"command": "test"})


def hand_eye(tmp_path: Path, board: str, capsys: pytest.CaptureFixture[str]) -> tuple[Path, str]:
    """A hand-eye computed by the command from synthetic samples with ``intrinsics.toml``."""
    intrinsics = write_camera(tmp_path / "intrinsics.toml", LEFT)
    obj = Board.parse(board).object_points()
    samples = synthetic_samples("eye-in-hand", X_TRUE, BOARD_IN_BASE, camera(LEFT), obj, 10,
                                rng=np.random.default_rng(4), noise_px=0.05)
    save_samples(tmp_path / "he.samples.json", samples, "eye-in-hand", board, camera(LEFT))
    out = tmp_path / "handeye.toml"
    assert main(["calibrate", "handeye", "--samples", str(tmp_path / "he.samples.json"),
                 "--intrinsics", str(intrinsics), "-o", str(out), "--json"]) == 0
    return out, capsys.readouterr().err


def cell(tmp_path: Path, *includes: str) -> Path:
    path = tmp_path / "cell.toml"
    path.write_text(f"include = {json.dumps(list(includes))}\n[camera]\ntype = \"synthetic\"\n",
                    encoding="utf-8")
    return path


def test_fingerprint_survives_the_file_and_sees_a_tenth_of_a_pixel(tmp_path: Path) -> None:
    path = write_camera(tmp_path / "cam.toml", LEFT)
    data = tomllib.loads(path.read_text(encoding="utf-8"))
    assert data["about"]["camera_model"] == camera_fingerprint({"left": LEFT})
    assert data["about"]["camera_model_parts"] == ["left"]
    assert camera_fingerprint(data["calibration"]) == camera_fingerprint({"left": LEFT})
    for key in ("fx", "cx", "cy"):
        moved = {**LEFT, key: LEFT[key] + 0.1}
        assert camera_fingerprint({"left": moved}) != camera_fingerprint({"left": LEFT})
    # the same pose in its two forms has one fingerprint
    T = make_transform(matrix_from_rotvec([0.1, 0.2, -0.3]), [100.0, 2.0, 3.0])
    as_rotvec = {"hand_eye": {"mounting": "fixed", "T_base_camera": pose_table(T)}}
    as_matrix = {"hand_eye": {"mounting": "fixed", "T_base_camera": {"matrix": T.tolist()}}}
    assert hand_eye_fingerprint(as_rotvec) == hand_eye_fingerprint(as_matrix)


def test_hand_eye_with_another_camera_model_is_refused_naming_both_files(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    he, _ = hand_eye(tmp_path, "chessboard:9x6:30", capsys)
    about = tomllib.loads(he.read_text(encoding="utf-8"))["about"]
    assert about["camera_model"] == camera_fingerprint({"left": LEFT})
    config = load_config(cell(tmp_path, "intrinsics.toml", "handeye.toml"))
    assert config.load_warnings == []
    # the camera recalibrated: 0.1 px of principal point (about 0.06 mm at 820 mm)
    write_camera(tmp_path / "recalibrated.toml", {**LEFT, "cx": LEFT["cx"] + 0.1})
    path = cell(tmp_path, "recalibrated.toml", "handeye.toml")
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert str(he) in str(err.value)
    assert str(tmp_path / "recalibrated.toml") in str(err.value)
    assert "rig -> hand-eye -> teach" in str(err.value)
    assert main(["check", "-c", str(path), "--no-links-ok"]) == 78
    assert str(he) in capsys.readouterr().err


def test_a_file_without_fingerprint_loads_with_a_warning(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_camera(tmp_path / "intrinsics.toml", LEFT)
    old = tmp_path / "old-handeye.toml"
    old.write_text(toml_from_dict({"calibration": {"hand_eye": {
        "mounting": "robot", "T_flange_camera": pose_table(X_TRUE)}},
        "about": {"command": "vgripd calibrate handeye (before fingerprints)"}}),
        encoding="utf-8")
    config = load_config(cell(tmp_path, "intrinsics.toml", "old-handeye.toml"))
    assert len(config.load_warnings) == 1
    assert str(old) in config.load_warnings[0]
    assert "no camera model fingerprint" in config.load_warnings[0]


def test_taught_reference_needs_the_camera_model_and_hand_eye_it_was_taught_with(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    calibration = DEMO_CALIBRATION.model_dump(mode="json", exclude_none=True)
    write_result(tmp_path / "rig.toml", {"calibration": {
        k: v for k, v in calibration.items() if k in ("left", "right", "stereo")}}, {})
    write_result(tmp_path / "handeye.toml", {"calibration": {"hand_eye": calibration[
        "hand_eye"]}}, {"camera_model": camera_fingerprint(calibration),
                        "camera_model_parts": ["left", "right", "stereo"]})
    path = tmp_path / "cell.toml"
    path.write_text('include = ["rig.toml", "handeye.toml"]\n[camera]\ntype = "synthetic"\n'
                    'seed = 3\n' + POSE, encoding="utf-8")
    assert main(["teach", "-c", str(path), "--shots", "2", "-o", str(tmp_path / "ref.toml")]) == 0
    about = tomllib.loads((tmp_path / "ref.toml").read_text(encoding="utf-8"))["about"]
    assert about["camera_model"] == camera_fingerprint(calibration)
    assert about["hand_eye"] == hand_eye_fingerprint(calibration)
    path.write_text('include = ["rig.toml", "handeye.toml", "ref.toml"]\n[camera]\n'
                    'type = "synthetic"\nseed = 3\n' + POSE, encoding="utf-8")
    assert load_config(path).load_warnings == []
    # a new hand-eye (made with the same rig): the reference must be taught again
    moved = dict(calibration["hand_eye"])
    pose = moved["T_base_camera"]
    moved["T_base_camera"] = {**pose, "translation_mm": [pose["translation_mm"][0] + 0.2,
                                                         *pose["translation_mm"][1:]]}
    write_result(tmp_path / "handeye.toml", {"calibration": {"hand_eye": moved}},
                 {"camera_model": camera_fingerprint(calibration),
                  "camera_model_parts": ["left", "right", "stereo"]})
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert str(tmp_path / "ref.toml") in str(err.value)
    assert str(tmp_path / "handeye.toml") in str(err.value)
    assert "teach it again" in str(err.value)


def test_symmetric_board_is_warned_about(tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    assert Board.parse("chessboard:9x7:30").symmetric
    assert Board.parse("circles:4x11:20").symmetric
    assert not Board.parse("chessboard:9x6:30").symmetric
    assert not Board.parse("acircles:4x11:20").symmetric
    _, err = hand_eye(tmp_path, "chessboard:9x7:30", capsys)
    assert "chessboard:9x7:30: symmetric" in err
    _, err = hand_eye(tmp_path, "chessboard:9x6:30", capsys)
    assert "symmetric" not in err
