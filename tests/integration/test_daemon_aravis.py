"""The daemon (camera and pipeline in its worker process, as deployed) on the aravis driver with
two of Aravis' fake GigE cameras, driven over Modbus/TCP: the right camera killed between two jobs makes the
next job CAMERA_ERROR naming it, the daemon keeps running without declaring the camera faulty,
and once the camera is started again a job takes a new image again."""

from __future__ import annotations

import asyncio
import tomllib
from collections.abc import Iterator
from typing import Any

import pytest

from tests.conftest import REPO
from tests.drivers.cameras.test_cameras_aravis import FakeCamera, two_fake_cameras
from tests.integration.test_daemon import WAIT_S, Plc, running
from vgripd.config import config_from_dict
from vgripd.peer.registers import Reg
from vgripd.types import Status


@pytest.fixture
def fakes() -> Iterator[tuple[FakeCamera, FakeCamera]]:
    with two_fake_cameras() as cameras:
        yield cameras


def cell() -> Any:
    """config/example.toml's demo cell seen by two fake GigE cameras."""
    data = tomllib.loads((REPO / "config" / "example.toml").read_text())
    data["camera"] = {"type": "aravis", "cameras": [{"serial": "GV01"}, {"ip": "127.0.0.2"}],
                      "roi": {"width": 1280, "height": 1024}, "frame_timeout_s": 2.0,
                      "reopen_backoff_s": 0.2, "reopen_backoff_max_s": 0.4}
    data["links"] = [{"type": "modbus_server", "host": "127.0.0.1", "port": 0}]
    data["status"] = {"enabled": False}
    data["daemon"]["job_timeout_s"] = 15.0
    return config_from_dict(data)


async def test_a_camera_unplugged_between_jobs_is_camera_error_then_reopened(
        fakes: tuple[FakeCamera, FakeCamera]) -> None:
    _, fake = fakes
    async with running(cell()) as run, Plc(run.port()) as plc:
        await plc.trigger(1)
        words = await plc.result(1)
        _, first = await run.job_done(1)
        # the fake's ramp holds no plate: a vision status, but an image was taken
        assert words[Reg.STATUS] not in (Status.CAMERA_ERROR, Status.NOT_CALIBRATED), first
        fake.kill()
        await plc.trigger(2)
        words = await plc.result(2)
        _, gone = await run.job_done(2)
        assert words[Reg.STATUS] == Status.CAMERA_ERROR
        assert "camera right (Aravis Fake, serial GV02, 127.0.0.2)" in gone.result.message
        fake.start()
        seq = 2
        statuses = []
        async with asyncio.timeout(WAIT_S):
            while True:  # the PLC triggers again until the camera is back
                seq += 1
                await plc.trigger(seq)
                words = await plc.result(seq)
                _, rec = await run.job_done(seq)
                statuses.append((words[Reg.STATUS], rec.result.message))
                if words[Reg.STATUS] != Status.CAMERA_ERROR:
                    break
        assert words[Reg.STATUS] == first.result.status, statuses
        assert all("stopped answering" in m for s, m in statuses[:-1]), statuses
        assert run.daemon.rooms.cameras.fault == ""
