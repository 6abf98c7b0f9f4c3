"""The setup page's calibration in a child (``setupsteps.calibration_command``/``read_result``):
one camera runs ``calibrate intrinsics``, the left/right pair ``calibrate stereo``, more cameras
``calibrate cameras``; each command is parsed by the real ``vgripd`` argument parser, and each
kind of result file is read back for the page (a ``cameras`` result placed in no base frame is
shown but cannot be accepted)."""

from __future__ import annotations

from pathlib import Path

import pytest

from vgripd.__main__ import build_parser
from vgripd.serialize import toml_from_dict
from vgripd.service.web.setupsteps import calibration_command, read_result

BOARD = "chessboard:9x6:30"
CAM = {"fx": 1800.0, "fy": 1800.0, "cx": 640.0, "cy": 512.0, "dist": [-0.08, 0.1, 0, 0, 0],
       "width": 1280, "height": 1024}


def _parsed(args: list[str]):  # noqa: ANN202
    return build_parser(args[0], every=False).parse_args(args)


def test_one_camera_runs_intrinsics_on_its_images(tmp_path: Path) -> None:
    args = calibration_command(["cam0"], tmp_path, BOARD, tmp_path / "r.toml")
    ns = _parsed(args)
    assert args[:2] == ["calibrate", "intrinsics"]
    assert ns.images == str(tmp_path / "cam0_*.png")
    assert ns.board == BOARD
    assert ns.output == str(tmp_path / "r.toml")


def test_the_pair_runs_stereo(tmp_path: Path) -> None:
    ns = _parsed(calibration_command(["left", "right"], tmp_path, BOARD, tmp_path / "r.toml"))
    assert ns.left == str(tmp_path / "left_*.png")
    assert ns.right == str(tmp_path / "right_*.png")


def test_more_cameras_run_cameras_with_one_glob_each(tmp_path: Path) -> None:
    names = ["top", "side", "back"]
    args = calibration_command(names, tmp_path, BOARD, tmp_path / "r.toml")
    ns = _parsed(args)
    assert args[:2] == ["calibrate", "cameras"]
    assert ns.camera == [f"{n}={tmp_path / (n + '_*.png')}" for n in names]
    assert ns.board == BOARD
    with pytest.raises(ValueError, match="no camera"):
        calibration_command([], tmp_path, BOARD, tmp_path / "r.toml")


def test_an_intrinsics_result_is_read_with_its_images() -> None:
    text = toml_from_dict({"about": {
        "rms_px": 0.12, "std": {"fx": 0.8}, "images_used": 14, "model_choice": "k1 k2",
        "per_image": [{"image": "/x/cam0_003.png", "rms_px": 0.1, "points": 54}],
        "rejected": [], "warnings": []}, "calibration": {"left": CAM}})
    res = read_result(text)
    assert res["kind"] == "intrinsics"
    assert res["usable"] is True
    assert res["left"]["fx"] == 1800.0
    assert res["images_used"] == 14
    assert res["per_pair"][0]["image"] == "/x/cam0_003.png"


def test_a_stereo_result_is_read_with_its_pairs() -> None:
    text = toml_from_dict({"about": {"rms_px": 0.1, "pairs_used": 12, "per_pair": [
        {"left": "left_001.png", "rms_px": 0.09}]}, "calibration": {
        "left": CAM, "right": CAM, "stereo": {"T_right_left": {"translation_mm": [-120, 0, 0],
                                                               "rotvec_rad": [0, 0, 0]}}}})
    res = read_result(text)
    assert res["kind"] == "stereo"
    assert res["usable"] is True
    assert res["T_right_left"]["translation_mm"] == [-120, 0, 0]
    assert res["pairs_used"] == 12


def test_a_cameras_result_without_a_base_frame_is_shown_but_not_usable() -> None:
    about = {"rms_px": 0.2, "reference": "top", "base_frame": "none",
             "cameras": [{"name": "top", "rms_px": 0.2}, {"name": "side", "rms_px": 0.3}],
             "warnings": ["no --board-in-base or --hand-eye: ..."]}
    res = read_result(toml_from_dict({"about": about}))
    assert res["kind"] == "cameras"
    assert res["usable"] is False
    assert [c["name"] for c in res["cameras"]] == ["top", "side"]
    placed = read_result(toml_from_dict({"about": about, "calibration": {"cameras": [
        {"name": "top", "intrinsics": CAM, "mounting": "fixed",
         "T_base_camera": {"translation_mm": [0, 0, 900], "rotvec_rad": [3.14, 0, 0]}}]}}))
    assert placed["usable"] is True
