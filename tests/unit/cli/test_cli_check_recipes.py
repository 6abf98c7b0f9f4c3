"""`vgripd check` and `vgripd run` on recipes spread over include files, and on a recipe whose
template file is missing: the error names the config file, ``recipes.N...`` and the file tried
(a relative path is taken from the working directory, so the absolute one is shown)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from tests.conftest import REPO
from vgripd.__main__ import EXIT_CONFIG, main

SAMPLE = REPO / "config" / "samples" / "recipes.toml"

PLATE_C = """
[recipes.65535]
name = "plate-c"
[recipes.65535.object]
name = "plate_c"
features = [
  { name = "c1", kind = "circle", diameter_mm = 10.0, xyz_mm = [-60.0, -30.0, 0.0] },
  { name = "c2", kind = "circle", diameter_mm = 10.0, xyz_mm = [55.0, -25.0, 0.0] },
  { name = "c3", kind = "circle", diameter_mm = 10.0, xyz_mm = [40.0, 35.0, 0.0] },
  { name = "c4", kind = "circle", diameter_mm = 10.0, xyz_mm = [-45.0, 30.0, 8.0] },
]
"""

REFERENCE_C = """
[recipes.65535.reference.T_base_obj]
translation_mm = [600.0, 100.0, 10.0]
rotvec_rad = [0.0, 0.0, 0.02]
"""

TEMPLATE_RECIPE = """
[recipes.3]
name = "tagged"
[recipes.3.object]
features = [
  { name = "t1", kind = "template", template = "missing.png", size_px = 24, xyz_mm = [0.0, 0.0, 0.0] },
  { name = "d1", kind = "circle", diameter_mm = 8.0, xyz_mm = [40.0, 0.0, 0.0] },
  { name = "d2", kind = "circle", diameter_mm = 8.0, xyz_mm = [0.0, 40.0, 0.0] },
  { name = "d3", kind = "circle", diameter_mm = 8.0, xyz_mm = [40.0, 40.0, 0.0] },
]
[recipes.3.reference.T_base_obj]
translation_mm = [600.0, 100.0, 10.0]
rotvec_rad = [0.0, 0.0, 0.0]
"""


def cell(tmp_path: Path, includes: dict[str, str]) -> Path:
    """The two-plate sample with its port free for the check, plus ``includes`` files."""
    text = SAMPLE.read_text().replace("port = 1502", "port = 0")
    for name, body in includes.items():
        (tmp_path / name).write_text(body)
    listed = ", ".join(f'"{name}"' for name in includes)
    path = tmp_path / "cell.toml"
    path.write_text(f"include = [{listed}]\n{text}")
    return path


def run_cli(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    rc = main(args)
    out = capsys.readouterr()
    return rc, out.out + out.err


def test_a_recipe_from_include_files_is_checked_and_listed(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = cell(tmp_path, {"plate-c.toml": PLATE_C, "reference-recipe-65535.toml": REFERENCE_C})
    rc, text = run_cli(["check", "-c", str(path)], capsys)
    assert rc == 0, text
    assert "recipe 1 (plate-a), recipe 2 (plate-b), recipe 65535 (plate-c)" in text


def test_an_include_without_the_taught_reference_names_the_recipe(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = cell(tmp_path, {"plate-c.toml": PLATE_C})
    rc, text = run_cli(["check", "-c", str(path)], capsys)
    assert rc == EXIT_CONFIG
    assert f"{path}: recipe 65535 (plate-c): not calibrated: " in text


def test_untaught_ok_makes_a_missing_reference_a_warning_and_nothing_else(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """What the reload after a hand-eye accept that set the references aside runs: the
    untaught recipe is a warning (its jobs end NOT_CALIBRATED); any other problem stays one."""
    path = cell(tmp_path, {"plate-c.toml": PLATE_C})
    rc, text = run_cli(["check", "--untaught-ok", "-c", str(path)], capsys)
    assert rc == 0, text
    assert (f"warning: {path}: recipe 65535 (plate-c): not taught, its jobs end NOT_CALIBRATED"
            in text)
    broken = cell(tmp_path, {"plate-c.toml": PLATE_C, "tagged.toml": TEMPLATE_RECIPE})
    rc, text = run_cli(["check", "--untaught-ok", "-c", str(broken)], capsys)
    assert rc == EXIT_CONFIG
    assert "missing.png" in text


@pytest.mark.parametrize("command", ["check", "run"])
def test_a_missing_template_file_names_recipe_field_and_file(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str) -> None:
    path = cell(tmp_path, {"recipe-3.toml": TEMPLATE_RECIPE})
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        rc, text = run_cli([command, "-c", str(path)], capsys)
    finally:
        os.chdir(cwd)
    assert rc == EXIT_CONFIG, text
    assert (f"{path}: recipes.3.object.features[0].template: cannot read image file "
            f"'missing.png' (no such file, tried {tmp_path / 'missing.png'})") in text
    assert "Traceback" not in text


def test_uncalibrated_ok_makes_a_cell_not_calibrated_yet_a_warning(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """What the setup page's camera and link choices run on a cell it has not calibrated yet:
    no calibration is a warning (its jobs end NOT_CALIBRATED); a bad link stays an error."""
    path = tmp_path / "board.toml"
    link = '[[links]]\ntype = "modbus_server"\nhost = "127.0.0.1"\nport = {port}\n'
    path.write_text('[camera]\ntype = "board"\n' + link.format(port=1502))
    rc, text = run_cli(["check", "--running", "-c", str(path)], capsys)
    assert rc == EXIT_CONFIG
    assert "not calibrated" in text
    rc, text = run_cli(["check", "--running", "--uncalibrated-ok", "-c", str(path)], capsys)
    assert rc == 0, text
    assert f"warning: {path}: not calibrated, its jobs end NOT_CALIBRATED" in text
    path.write_text('[camera]\ntype = "board"\n' + link.format(port=70000))
    rc, text = run_cli(["check", "--running", "--uncalibrated-ok", "-c", str(path)], capsys)
    assert rc == EXIT_CONFIG
    assert "port" in text
