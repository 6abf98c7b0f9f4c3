"""The acceptance test of the browser setup (docs/setup.md): from the learning cell with empty
includes (``vgripd demo --setup``) to the first OK job received by a pymodbus PLC client, every
step done by clicking the page in headless Chromium, no file edited by hand. Then what the page
wrote: each include through the config transaction (its numbered backup beside it), the object
a reference object of the plate's six marks, the reference taught."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from tests.conftest import need_tool
from tests.integration.setup_browser import SETS, demo_setup, drive
from vgripd.peer.registers import Reg
from vgripd.types import Status

pytestmark = pytest.mark.slow(minutes=6)


@pytest.mark.timeout(2400)
async def test_the_whole_setup_in_chromium_ends_in_a_plc_job(tmp_path: Path) -> None:
    need_tool("chromium")
    folder = tmp_path / "cell"
    async with demo_setup(folder) as cell:
        before = {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file()}
        flow = await drive(cell, tmp_path)
    assert flow.plc_status == Status.OK, flow.plc_values
    assert flow.plc_values[Reg.N_VALUES] == 6  # x y z a b c for the robot
    # the main file and the token as demo --setup wrote them; the includes by the page alone
    assert (folder / "vgripd.toml").read_bytes() == before["vgripd.toml"]
    assert (folder / "access.toml").read_bytes() == before["access.toml"]
    for name in ("rig.toml", "handeye.toml", "cell.toml", "reference.toml"):
        assert (folder / f"{name}.1").read_bytes() == before[name], name  # the first backup
    rig = tomllib.loads((folder / "rig.toml").read_text())["calibration"]
    assert abs(rig["left"]["fx"] - 1805.2) < 15.0  # the learning cell's truth camera
    cell_data = tomllib.loads((folder / "cell.toml").read_text())
    assert cell_data["object"]["definition"] == "reference"
    assert len(cell_data["object"]["features"]) == 6
    reference = tomllib.loads((folder / "reference.toml").read_text())
    assert set(reference["reference"]["points_mm"]) == {
        f["name"] for f in cell_data["object"]["features"]}
    progress = (folder / "setup" / "progress.json").read_text()
    for step in ("cameras", "calibration", "handeye", "object", "link"):
        assert f'"{step}"' in progress
    assert len(list((folder / "setup" / "calib").glob("left_*.png"))) >= SETS
    assert flow.actions >= 15
