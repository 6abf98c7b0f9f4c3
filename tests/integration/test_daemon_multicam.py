"""A two-rig cell through the daemon: config/samples/two_rigs_frame.toml (a 1.5 m frame, marks
on both faces, two stereo rigs on opposite sides) with the synthetic cameras rendering all four
views in the worker process, the Modbus/TCP server link and a real pymodbus client as the PLC.

Done-when of docs/multicamera.md: the frame, which neither rig sees whole, is located within
0.1 mm / 0.02 deg of the renderer's truth with each rig's residuals shown; a camera moved since
calibration (its pose perturbed in the config) names its rig and publishes nothing.
"""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from tests.conftest import REPO
from tests.integration.test_daemon import Plc, running
from vgripd.config import config_from_dict, read_config_data
from vgripd.geometry.transforms import pose_error
from vgripd.peer.registers import Reg
from vgripd.registry import CAMERAS, load_class, validate_options
from vgripd.types import Status

SAMPLE = REPO / "config" / "samples" / "two_rigs_frame.toml"


def cell(tmp_path: Path, moved: tuple[int, list[float], list[float]] | None = None,
         record: bool = False, camera: dict[str, Any] | None = None) -> Any:
    data = copy.deepcopy(read_config_data(SAMPLE))
    if camera is not None:
        data["camera"] = camera
    data["links"] = [{"type": "modbus_server", "host": "127.0.0.1", "port": 0}]
    data["status"] = {"port": 0}
    if record:
        data["record"] = {"enabled": True, "folder": str(tmp_path / "record")}
    if moved is not None:
        index, dt_mm, drot_rad = moved
        pose = data["calibration"]["cameras"][index]["T_base_camera"]
        pose["translation_mm"] = list(np.add(pose["translation_mm"], dt_mm))
        pose["rotvec_rad"] = list(np.add(pose["rotvec_rad"], drot_rad))
    return config_from_dict(data, str(SAMPLE))


async def test_two_rigs_locate_a_frame_neither_sees_whole(tmp_path: Path) -> None:
    async with running(cell(tmp_path, record=True)) as run, Plc(run.port()) as plc:
        for seq in (1, 2, 3):
            await plc.trigger(seq)
            words = await plc.result(seq)
            pair, rec = await run.job_done(seq)
            result = rec.result
            assert words[Reg.STATUS] == Status.OK, result.message
            assert words[Reg.N_VALUES] == 6
            assert pair is not None
            assert len(pair.views) == 4
            # Each rig sees the eight marks of its own face and none of the other's.
            seen = ~np.isnan(pair.truth["pixels_views"][..., 0])
            assert seen[:8].tolist() == [[True, True, False, False]] * 8
            assert seen[8:].tolist() == [[False, False, True, True]] * 8
            assert result.T_base_obj is not None
            mm, deg = pose_error(result.T_base_obj, pair.truth["T_base_obj"])
            assert mm < 0.1
            assert deg < 0.02
            assert len(result.features_used) == 16
            r = result.residuals
            for rig in ("north", "south"):
                assert r[f"rig.{rig}.marks"] == 16  # 8 marks x 2 cameras
                assert r[f"rig.{rig}.reprojection_px"] < 0.2
                assert r[f"rig.{rig}.fit_rms_mm"] < 0.5
            assert r["reprojection_px"] < 0.2
        assert run.daemon.rooms.jobs.counters == {"OK": 3}
    # The recorder got all four images of every job, in camera order.
    jobs = sorted((tmp_path / "record").iterdir())
    assert len(jobs) == 3
    assert sorted(p.name for p in jobs[0].glob("*.png")) == [f"view{j}.png" for j in range(4)]
    truth = json.loads((jobs[0] / "pair.json").read_text())["truth"]
    assert truth["camera_names"] == ["north_left", "north_right", "south_left", "south_right"]


async def render(folder: Path, frames: int) -> list[str]:
    """Frames of the sample cell as the synthetic cameras see it, as PNG files per camera
    (``<camera>_<frame>.png``); the replay globs that read them back."""
    config = cell(folder)
    cls = load_class(CAMERAS, "camera", config.camera.type)
    camera = cls(validate_options(cls, config.camera, "camera"), config)
    names = [c.name for c in config.calibration.cameras]
    await camera.open()
    try:
        for k in range(frames):
            pair = await camera.grab(30.0)
            for name, image in zip(names, pair.views, strict=True):
                assert cv2.imwrite(str(folder / f"{name}_{k:02d}.png"), image)
    finally:
        await camera.close()
    return [f"{name}_*.png" for name in names]


@pytest.mark.parametrize(("moved", "rig"), [
    ((0, [3.0, 0.0, 0.0], [0.0, 0.0, 0.0]), "north"),    # 3 mm along the rig's baseline
    ((3, [0.0, 0.0, 0.0], [0.0, 0.0035, 0.0]), "south"),  # turned 0.2 deg
])
async def test_a_moved_camera_names_its_rig_and_publishes_nothing(
        tmp_path: Path, moved: tuple[int, list[float], list[float]], rig: str) -> None:
    # The images come from the true cell; the config the daemon runs with has one camera's
    # pose off, as after a knock (read back through the replay camera, one glob per camera).
    globs = await render(tmp_path, 1)
    replay = {"type": "replay", "folder": str(tmp_path), "globs": globs}
    async with running(cell(tmp_path, moved, camera=replay)) as run, Plc(run.port()) as plc:
        await plc.trigger(1)
        words = await plc.result(1)
        _, rec = await run.job_done(1)
        assert words[Reg.STATUS] == Status.RESIDUAL_TOO_HIGH
        assert words[Reg.N_VALUES] == 0
        assert rec.result.target is None
        assert f"rig {rig} disagrees with the other rigs" in rec.result.message
        other = "south" if rig == "north" else "north"
        assert f"rig {other} disagrees" not in rec.result.message
    # The same images with the true calibration: published.
    async with running(cell(tmp_path, camera=replay)) as run, Plc(run.port()) as plc:
        await plc.trigger(1)
        assert (await plc.result(1))[Reg.STATUS] == Status.OK


async def test_one_camera_of_the_multi_driver_failing_names_it(tmp_path: Path) -> None:
    """Four replay drivers in a ``multi`` camera, south_left's folder one frame short: its
    second job ends CAMERA_ERROR naming south_left, nothing is published, and the daemon
    keeps serving (the third trigger is answered too)."""
    globs = await render(tmp_path, 2)
    names = ["north_left", "north_right", "south_left", "south_right"]
    (tmp_path / "south_left_01.png").unlink()
    multi = {"type": "multi", "cameras": [
        {"type": "replay", "folder": str(tmp_path), "glob": glob, "loop": False}
        for glob in globs]}
    assert [g.split("_*")[0] for g in globs] == names
    async with running(cell(tmp_path, camera=multi)) as run, Plc(run.port()) as plc:
        await plc.trigger(1)
        assert (await plc.result(1))[Reg.STATUS] == Status.OK
        await plc.trigger(2)
        words = await plc.result(2)
        _, rec = await run.job_done(2)
        assert words[Reg.STATUS] == Status.CAMERA_ERROR
        assert words[Reg.N_VALUES] == 0
        assert "camera.cameras.2 (replay, camera south_left)" in rec.result.message
        await plc.trigger(3)
        assert (await plc.result(3))[Reg.STATUS] == Status.CAMERA_ERROR
