"""The daemon's RECALIBRATE warning: a window of stereo jobs whose epipolar residuals exceed
``vision.epipolar_warn_px`` too often raises it (status endpoint, ``vgripd status``, log);
good jobs clear it.

Images: the synthetic demo cell rendered once with the calibrated rig and once with the right
camera turned by 1.2 mrad about the left camera's x axis (a rig knocked after calibration:
right image rows move by ~2.2 px, inside the matching tolerance, above the 1 px warning level).
The daemon replays them in a chosen order with the *calibrated* rig, driven by a real Modbus
client over TCP; the status is read over a real HTTP socket. The PLC also reads the WARNINGS
register (map version 2) of the link it triggers, in the same read as each ACK_SEQ, and of a
second link that never triggers.
"""

from __future__ import annotations

import asyncio
import json
import logging
import urllib.request
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from tests.integration.test_daemon import Plc, running
from vgripd.cli.status import format_status
from vgripd.config import config_from_dict
from vgripd.peer.registers import Reg, Warnings
from vgripd.registry import CAMERAS, load_class, validate_options
from vgripd.service.jobs.jobrecord import EpipolarMonitor
from vgripd.sim.robot_modbus import UR_FIRST_REGISTER as BASE
from vgripd.sim.robot_modbus import MockRobotModbus, RegisterWrite
from vgripd.types import ImagePair, Status

# good x4, knocked x4, good x4: with a window of 4, warning above a share of 0.5
SEQUENCE = "GGGGBBBBGGGG"


async def _render(data: dict[str, Any]) -> ImagePair:
    config = config_from_dict(data)
    cls = load_class(CAMERAS, "camera", "synthetic")
    camera = cls(validate_options(cls, config.camera, "camera"), config)
    await camera.open()
    try:
        return await camera.grab(30.0)
    finally:
        await camera.close()


async def _write_sequence(folder: Path) -> None:
    camera = {"type": "synthetic", "seed": 4,
              "pose": {"translation_mm": [602.0, 98.0, 11.0], "rotvec_rad": [0.0, 0.01, 0.06]}}
    good = await _render({"camera": camera})
    knocked_cal = config_from_dict({"camera": camera}).model_dump()
    T_rl = knocked_cal["calibration"]["stereo"]["T_right_left"]
    T_rl["rotvec_rad"] = (np.array(T_rl["rotvec_rad"]) + (0.0012, 0.0, 0.0)).tolist()
    knocked = await _render({"camera": camera, "calibration": knocked_cal["calibration"]})
    for i, kind in enumerate(SEQUENCE):
        pair = good if kind == "G" else knocked
        assert pair.right is not None
        cv2.imwrite(str(folder / f"left_{i}.png"), pair.left)
        cv2.imwrite(str(folder / f"right_{i}.png"), pair.right)


def _get_status(url: str) -> dict[str, Any]:
    # The daemon answers on the test's own event loop, which a busy machine (a second suite
    # beside this one) can hold for seconds: 5 s timed out once.
    with urllib.request.urlopen(url, timeout=30) as resp:
        data: dict[str, Any] = json.loads(resp.read())
    return data


def _config(folder: Path, links: list[dict[str, Any]]) -> Any:
    return config_from_dict({
        "camera": {"type": "replay", "folder": str(folder), "left_glob": "left_*.png",
                   "right_glob": "right_*.png"},
        "calibration": config_from_dict({}).model_dump()["calibration"],
        "links": links,
        "status": {"port": 0},
        "daemon": {"recalibrate_window": 4, "recalibrate_share": 0.5,
                   "recalibrate_min_jobs": 4},
    })


async def test_recalibrate_warning_rises_and_clears(tmp_path: Path,
                                                   caplog: pytest.LogCaptureFixture) -> None:
    await _write_sequence(tmp_path)
    config = _config(tmp_path, [{"type": "modbus_server", "host": "127.0.0.1", "port": 0}] * 2)
    caplog.set_level(logging.INFO, logger="vgripd")
    warning_after: list[bool] = []
    warnings_at_ack: list[int] = []  # WARNINGS in the read that shows ACK_SEQ == seq
    warnings_other: list[int] = []  # WARNINGS of the second link, read after each job
    async with running(config) as run, Plc(run.port()) as plc, Plc(run.port(1)) as hmi:
        run.daemon.rooms.jobs.listeners.append(
            lambda pair, rec: warning_after.append(run.daemon.rooms.jobs.epipolar.warning))
        assert run.daemon.status_server is not None
        url = f"http://127.0.0.1:{run.daemon.status_server.port}/status"
        loop = asyncio.get_running_loop()
        with ThreadPoolExecutor(1) as pool:
            for seq, kind in enumerate(SEQUENCE, start=1):
                await plc.trigger(seq)
                words = await plc.result(seq)
                assert words[Reg.MAP_VERSION] == 3
                warnings_at_ack.append(words[Reg.WARNINGS])
                _, rec = await run.job_done(seq)
                warnings_other.append((await hmi.read())[Reg.WARNINGS])
                epi = rec.result.residuals["epipolar_px"]
                if kind == "G":
                    assert rec.result.status is Status.OK, rec.result.message
                    assert epi < 0.5
                else:
                    assert rec.result.status is Status.OK_RECALIBRATE, rec.result.message
                    assert epi > 1.5
                if seq == 8:  # four knocked jobs in the window: warning up, over HTTP
                    status = await loop.run_in_executor(pool, _get_status, url)
                    rc = status["recalibrate"]
                    assert rc["warning"] is True
                    assert (rc["jobs"], rc["above"], rc["share"]) == (4, 4, 1.0)
                    text = format_status(status)
                    assert "RECALIBRATE: 4 of the last 4 stereo jobs above 1.0 px" in text
                    assert run.daemon.status_line().endswith("; RECALIBRATE")  # systemd STATUS
            status = await loop.run_in_executor(pool, _get_status, url)
        assert status["recalibrate"]["warning"] is False
        assert status["recalibrate"]["above"] == 0
        assert not run.daemon.status_line().endswith("; RECALIBRATE")
    # 3 of 4 above (> 0.5) at job 7; 2 of 4 (not > 0.5) again at job 10.
    assert warning_after == [False] * 6 + [True] * 3 + [False] * 3
    # the PLC sees the bit with the ack of the job that raised it, and of the one that cleared it
    assert warnings_at_ack == [0] * 6 + [Warnings.RECALIBRATE] * 3 + [0] * 3
    assert warnings_other == warnings_at_ack
    risen = [r for r in caplog.records if r.getMessage().startswith("RECALIBRATE:")]
    cleared = [r for r in caplog.records if r.getMessage().startswith("RECALIBRATE cleared")]
    assert len(risen) == 1
    assert risen[0].levelno == logging.WARNING
    assert len(cleared) == 1


async def test_warnings_word_is_written_to_a_robot_before_the_ack(tmp_path: Path) -> None:
    """modbus_client link: the robot's register server gets the WARNINGS write of the job that
    raises (and clears) the warning before that job's ACK_SEQ write."""
    await _write_sequence(tmp_path)
    robot = MockRobotModbus()
    await robot.start()
    config = _config(tmp_path, [{"type": "modbus_client", "host": robot.host,
                                 "port": robot.port, "poll_interval_s": 0.005}])
    warnings_at_ack: list[int] = []
    try:
        async with running(config):
            for seq in range(1, len(SEQUENCE) + 1):
                seen = await robot.run_job(seq, 30.0)
                warnings_at_ack.append(seen.words[Reg.WARNINGS])
                ack = seen.writes.index(RegisterWrite(BASE + Reg.ACK_SEQ, (seq,)))
                if seq in (7, 10):  # the jobs that raise and clear it
                    bits = Warnings.RECALIBRATE if seq == 7 else 0
                    assert seen.writes.index(RegisterWrite(BASE + Reg.WARNINGS, (bits,))) < ack
                else:
                    assert all(w.address != BASE + Reg.WARNINGS for w in seen.writes)
    finally:
        await robot.stop()
    assert warnings_at_ack == [0] * 6 + [Warnings.RECALIBRATE] * 3 + [0] * 3


def test_monitor_waits_for_min_jobs_and_judges_the_share() -> None:
    monitor = EpipolarMonitor(window=10, share=0.2, min_jobs=5, threshold_px=1.0)
    changes = [monitor.add(px, 0) for px in (2.0, 2.0, 2.0, 2.0)]
    assert changes == [False] * 4
    assert not monitor.warning
    assert monitor.add(0.1, 0)
    assert monitor.warning
    for _ in range(10):
        monitor.add(0.1, 0)
    assert not monitor.warning
    assert monitor.share() == 0.0
    assert monitor.add(1.0 + 1e-9, 0) is False  # 1 of 10 = 0.1, not above 0.2
