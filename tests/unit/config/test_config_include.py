"""Config ``include``: calibration result files merged into a config, errors naming the file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vgripd.calib.files import pose_table, write_result
from vgripd.config import load_config
from vgripd.errors import CalibrationError, ConfigError

INTRINSICS = {"fx": 900.0, "fy": 901.0, "cx": 320.0, "cy": 240.0, "width": 640, "height": 480,
              "dist": [-0.1, 0.01, 0.0, 0.0, 0.0]}


def _main(tmp_path: Path, body: str) -> Path:
    p = tmp_path / "cell" / "config.toml"
    p.parent.mkdir(exist_ok=True)
    p.write_text(body)
    return p


def test_included_results_fill_the_calibration(tmp_path: Path) -> None:
    cell = tmp_path / "cell"
    write_result(cell / "camera.toml", {"calibration": {"left": INTRINSICS}},
                 {"command": "test", "rms_px": 0.12})
    T = np.eye(4)
    T[:3, 3] = (500.0, 0.0, 800.0)
    write_result(cell / "handeye.toml",
                 {"calibration": {"hand_eye": {"mounting": "fixed",
                                               "T_base_camera": pose_table(T)}}}, {})
    cfg = load_config(_main(tmp_path, 'include = ["camera.toml", "handeye.toml"]\n'
                                      '[camera]\ntype = "synthetic"\n'))
    assert cfg.calibration is not None
    assert cfg.calibration.left.fx == 900.0
    assert cfg.calibration.right is None
    assert cfg.calibration.hand_eye.T_base_camera is not None
    assert cfg.calibration.hand_eye.T_base_camera.translation_mm == (500.0, 0.0, 800.0)


def test_a_value_set_twice_names_both_files(tmp_path: Path) -> None:
    write_result(tmp_path / "cell" / "camera.toml", {"calibration": {"left": INTRINSICS}}, {})
    main = _main(tmp_path, 'include = ["camera.toml"]\n[calibration.left]\nfx = 1.0\n')
    with pytest.raises(ConfigError, match=r"camera.toml: calibration.left.fx is already set in "
                                          r".*config.toml"):
        load_config(main)


def test_a_bad_value_in_an_included_file_is_blamed_on_that_file(tmp_path: Path) -> None:
    bad = dict(INTRINSICS, fx=-3.0)
    write_result(tmp_path / "cell" / "camera.toml", {"calibration": {"left": bad}}, {})
    write_result(tmp_path / "cell" / "handeye.toml", {"calibration": {"hand_eye": {
        "T_base_camera": {"translation_mm": [0.0, 0.0, 0.0]}}}}, {})
    main = _main(tmp_path, 'include = ["camera.toml", "handeye.toml"]\n'
                           '[camera]\ntype = "synthetic"\n')
    with pytest.raises(ConfigError, match=r"camera.toml: calibration.left.fx: Input should be "
                                          r"greater than 0"):
        load_config(main)


def test_missing_include_and_nested_include_are_config_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"nope.toml: cannot read included file"):
        load_config(_main(tmp_path, 'include = ["nope.toml"]\n'))
    (tmp_path / "cell" / "a.toml").write_text('include = ["b.toml"]\n')
    with pytest.raises(ConfigError, match=r"a.toml: include: included files may not include"):
        load_config(_main(tmp_path, 'include = ["a.toml"]\n'))
    with pytest.raises(ConfigError, match=r"include: must be a list"):
        load_config(_main(tmp_path, 'include = "a.toml"\n'))


def test_result_files_refuse_non_finite_values(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match=r"calibration.left.fx: refusing to write"):
        write_result(tmp_path / "x.toml", {"calibration": {"left": {"fx": float("nan")}}}, {})
    assert not (tmp_path / "x.toml").exists()
