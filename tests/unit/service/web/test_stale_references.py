"""Taught references against a new hand-eye (``vgripd.service.web.stale``, the accept of a
walked hand-eye): which references it makes wrong, setting them aside, and teaching again from
the page recording the fingerprints the reference now belongs to, so the files load together
(``vgripd.config.check_calibration_files``)."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

import pytest

from vgripd.config import load_config, read_config_data
from vgripd.errors import ConfigError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.fingerprint import camera_about, hand_eye_fingerprint, intrinsics_table
from vgripd.serialize import toml_from_dict
from vgripd.service.web.stale import set_aside, stale_references
from vgripd.service.web.teaching import reference_target, with_reference

LEFT = intrinsics_table(CameraModel(1500.0, 1500.0, 641.0, 479.0, 0.0, (0.0,) * 5, 1280, 960))
OLD = {"mounting": "fixed", "T_base_camera": {"translation_mm": [600.0, -30.0, 800.0],
                                              "rotvec_rad": [3.1, 0.0, 0.0]}}
NEW = {"mounting": "fixed", "T_base_camera": {"translation_mm": [600.4, -30.2, 800.1],
                                              "rotvec_rad": [3.1, 0.001, 0.0]}}
GRIP = {"translation_mm": [1.0, 2.0, 3.0], "rotvec_rad": [0.0, 0.0, 0.0]}
REFERENCE = {"T_base_obj": {"translation_mm": [650.0, 40.0, 20.0], "rotvec_rad": [0.0, 0.0, 0.2]},
             "grip": GRIP}


def write(path: Path, data: dict[str, Any]) -> Path:
    path.write_text(toml_from_dict(data), encoding="utf-8")
    return path


def cell(folder: Path, hand_eye: dict[str, Any], taught_with: dict[str, Any]) -> Path:
    """cell.toml including he.toml (``hand_eye``) and ref.toml (taught with ``taught_with``)."""
    about = camera_about({"left": LEFT})
    write(folder / "he.toml", {"calibration": {"hand_eye": hand_eye}, "about": about})
    write(folder / "ref.toml", {"reference": REFERENCE, "about": {
        **about, "hand_eye": hand_eye_fingerprint({"hand_eye": taught_with})}})
    return write(folder / "cell.toml", {"include": ["he.toml", "ref.toml"],
                                        "camera": {"type": "synthetic"},
                                        "calibration": {"left": LEFT}})


def with_new_hand_eye(path: Path) -> dict[str, Any]:
    calibration: dict[str, Any] = read_config_data(path)["calibration"]
    return {**calibration, "hand_eye": NEW}


def test_a_reference_taught_with_another_hand_eye_is_stale(tmp_path: Path) -> None:
    path = cell(tmp_path, OLD, OLD)
    assert load_config(path).reference.T_base_obj is not None
    assert stale_references(path, read_config_data(path)["calibration"]) == ([], False)
    assert stale_references(path, with_new_hand_eye(path)) == ([tmp_path / "ref.toml"], False)
    # none recorded counts as another: it cannot be shown to belong to the new one
    text = (tmp_path / "ref.toml").read_text()
    write(tmp_path / "ref.toml", {"reference": tomllib.loads(text)["reference"]})
    assert stale_references(path, read_config_data(path)["calibration"])[0] == [
        tmp_path / "ref.toml"]


def test_a_reference_in_the_main_file_is_named_apart(tmp_path: Path) -> None:
    path = cell(tmp_path, OLD, OLD)
    write(tmp_path / "ref.toml", {})
    data = tomllib.loads(path.read_text())
    write(path, {**data, "reference": REFERENCE})
    assert stale_references(path, with_new_hand_eye(path)) == ([], True)


def test_set_aside_then_taught_again_from_the_page_loads_with_the_new_hand_eye(
        tmp_path: Path) -> None:
    path = cell(tmp_path, OLD, OLD)
    write(tmp_path / "he.toml", {"calibration": {"hand_eye": NEW},
                                 "about": camera_about({"left": LEFT})})
    with pytest.raises(ConfigError, match="teach it again"):  # the old reference is refused
        load_config(path)

    ref = tmp_path / "ref.toml"
    ref.write_text(set_aside(ref.read_text()))
    aside = tomllib.loads(ref.read_text())
    assert aside["reference"] == {"grip": GRIP}  # the grip stays, the measurement goes
    assert not {"camera_model", "hand_eye"} & set(aside["about"])
    config = load_config(path)  # loads: not taught (jobs end NOT_CALIBRATED)
    assert config.reference.T_base_obj is None
    assert not [w for w in config.load_warnings if "ref.toml" in w]

    # the teaching page writes into the file set aside, with the fingerprints of today
    assert reference_target(path, 0) == ref
    assert config.calibration is not None
    taught = with_reference(ref.read_text(), 0, {"reference": {"T_base_obj": REFERENCE[
        "T_base_obj"]}}, config.calibration.model_dump(mode="json"))
    ref.write_text(taught)
    again = load_config(path)
    assert again.reference.T_base_obj is not None
    assert not [w for w in again.load_warnings if "ref.toml" in w]
    assert "set_aside" not in tomllib.loads(taught)["about"]
    assert stale_references(path, read_config_data(path)["calibration"]) == ([], False)


def test_set_aside_file_without_grip_is_still_found_by_the_teaching_page(tmp_path: Path) -> None:
    path = cell(tmp_path, OLD, OLD)
    ref = tmp_path / "ref.toml"
    write(ref, {"reference": {"T_base_obj": REFERENCE["T_base_obj"]}})
    ref.write_text(set_aside(ref.read_text()))
    assert tomllib.loads(ref.read_text()) == {"reference": {}}
    assert reference_target(path, 0) == ref
