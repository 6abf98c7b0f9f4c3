"""Health tells the truth while no job can get a frame: two grabs in a row that fail make the
daemon unhealthy at once, naming the camera, the time and the last failure; the systemd
watchdog keeps pinging until that has lasted ``daemon.camera_down_restart_s``, then stops; the
next job that gets an image makes it healthy again. The daemon (replay driver in its worker)
is driven over Modbus/TCP by a pymodbus client as a PLC."""

from __future__ import annotations

import re
from pathlib import Path

import cv2

from tests.integration.test_daemon import Plc, _synthetic_pair, make_config, running
from vgripd.config import Config
from vgripd.peer.registers import Reg
from vgripd.types import Status


async def test_grabs_failing_in_a_row_are_unhealthy_and_stop_the_watchdog_after_the_limit(
        tmp_path: Path) -> None:
    pair = await _synthetic_pair(5)
    for i in (1, 2):  # two pairs that cannot be read, then a good one
        for side in ("left", "right"):
            (tmp_path / f"{side}_{i}.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 50)
    cv2.imwrite(str(tmp_path / "left_3.png"), pair.left)
    cv2.imwrite(str(tmp_path / "right_3.png"), pair.right)
    camera = {"type": "replay", "folder": str(tmp_path), "left_glob": "left_*.png",
              "right_glob": "right_*.png"}
    demo = Config().calibration
    assert demo is not None
    config = make_config(camera, calibration=demo.model_dump(mode="json", exclude_none=True),
                         daemon={"camera_down_restart_s": 30.0})
    async with running(config) as run, Plc(run.port()) as plc:
        daemon = run.daemon
        await plc.trigger(1)
        assert (await plc.result(1))[Reg.STATUS] == Status.CAMERA_ERROR
        assert daemon.healthy()  # one failed grab may be one bad frame
        await plc.trigger(2)
        assert (await plc.result(2))[Reg.STATUS] == Status.CAMERA_ERROR
        snap = daemon.snapshot()
        assert not snap["healthy"]
        problem = snap["health_problem"]
        assert re.match(r"camera replay: no frame for \d+\.\d s: 2 grabs in a row failed, the "
                        r"last: .*left_2\.png", problem), problem
        assert snap["camera"]["down"].startswith("2 grabs in a row failed")
        assert "CAMERA DOWN" in daemon.status_line()
        assert daemon.watchdog_problem() == ""  # the camera may come back on its own first

        daemon.rooms.cameras.down_since -= 31.0  # the same, 31 s later
        assert daemon.watchdog_problem().endswith(
            "(longer than daemon.camera_down_restart_s = 30 s)")
        assert daemon.watchdog_problem().startswith("camera replay: no frame for 31.")

        await plc.trigger(3)
        assert (await plc.result(3))[Reg.STATUS] == Status.OK
        assert daemon.healthy()
        assert daemon.watchdog_problem() == ""
        assert daemon.snapshot()["camera"]["down"] is None
