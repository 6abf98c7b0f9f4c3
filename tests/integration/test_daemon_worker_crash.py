"""A worker process SIGKILLed while it holds the camera never leaves the cell blind: the daemon
(camera and pipeline in its worker, as deployed) on Aravis' fake GigE cameras and on pylon's
camera emulation, driven over Modbus/TCP by a pymodbus client as a PLC.

The worker is killed between jobs, during a grab and during processing, each time with a
trigger right after. Meanwhile the status says the camera is down and why (``healthy`` false,
the time waited in ``health_problem``); the job in flight gets what docs/daemon.md says (a
grab is taken again on the new worker; processing ends INTERNAL); the next job takes an image
again (the status a working camera gives), and the status is healthy again after it. Every wait
is on a register value or a daemon state, with a deadline that holds on a busy machine."""

from __future__ import annotations

import importlib.util
import os
import re
import signal
import tomllib
from collections.abc import Iterator
from typing import Any

import pytest

from tests.conftest import REPO, need
from tests.drivers.cameras.test_cameras_aravis import two_fake_cameras
from tests.integration.test_daemon import Plc, Run, running
from vgripd.config import config_from_dict
from vgripd.peer.registers import Reg
from vgripd.service.daemon import Daemon
from vgripd.service.jobs.runner import JobState
from vgripd.types import Status

# pylon's waits end early under pytest-timeout's SIGALRM method (tests/drivers/cameras/test_cameras_pylon.py)
pytestmark = pytest.mark.timeout(600, method="thread")
os.environ["PYLON_CAMEMU"] = "3"  # read when pylon's transport layers load (in the worker too)

#: Generous: a new worker (spawn, imports, warm-up) and a GigE camera's control channel
#: (the fake's heartbeat timeout, 3 s) on a machine shared with other jobs.
WAIT_S = 120.0
SAMPLES = REPO / "config" / "samples"
KILLED = "worker process exited with signal 9 (SIGKILL)"


def cell(camera: dict[str, Any]) -> Any:
    """config/example.toml's demo cell with ``camera``, a Modbus server, no web view, and a
    job time long enough for a new worker to start within it on a busy machine."""
    data = tomllib.loads((REPO / "config" / "example.toml").read_text())
    data["camera"] = camera
    data["links"] = [{"type": "modbus_server", "host": "127.0.0.1", "port": 0}]
    data["status"] = {"enabled": False}
    data["daemon"]["job_timeout_s"] = WAIT_S / 2
    return config_from_dict(data)


@pytest.fixture
def fakes() -> Iterator[None]:
    with two_fake_cameras():
        yield


def aravis_cell() -> Any:
    return cell({"type": "aravis", "cameras": [{"serial": "GV01"}, {"ip": "127.0.0.2"}],
                 "roi": {"width": 1280, "height": 1024}, "frame_timeout_s": 2.0,
                 "reopen_backoff_s": 0.2, "reopen_backoff_max_s": 0.4})


def pylon_cell() -> Any:
    def feed(side: str) -> dict[str, Any]:
        return {"TestImageSelector": "Off", "ImageFileMode": "On",
                "ImageFilename": str(SAMPLES / f"{side}_00.png")}
    return cell({"type": "pylon", "roi": {"width": 1280, "height": 1024},
                 "pixel_format": "Mono8", "exposure_us": 5000,
                 "cameras": [{"serial": "0815-0000", "features": feed("left")},
                             {"serial": "0815-0001", "features": feed("right")}]})


class Cell:
    """The daemon, its PLC and the jobs' statuses."""

    def __init__(self, run: Run, plc: Plc) -> None:
        self.run, self.plc, self.seq = run, plc, 0
        self.downs: list[str] = []  # what the status said while the camera was down

    @property
    def daemon(self) -> Daemon:
        return self.run.daemon

    async def trigger(self) -> int:
        self.seq += 1
        await self.plc.trigger(self.seq)
        return self.seq

    async def answer(self, seq: int) -> tuple[Status, str]:
        words = await self.plc.until(lambda w: w[Reg.ACK_SEQ] == seq)
        _, rec = await self.run.job_done(seq)
        assert words[Reg.STATUS] == rec.result.status
        return rec.result.status, rec.result.message

    async def job(self) -> tuple[Status, str]:
        return await self.answer(await self.trigger())

    def kill_worker(self) -> None:
        pid = self.daemon.snapshot()["worker"]["pid"]
        assert pid not in (None, os.getpid())
        os.kill(pid, signal.SIGKILL)

    async def down_then_up(self, good: Status) -> None:
        """The status said the camera was down, naming the death and the time waited; a job
        now takes an image again (``good``) and the status is healthy after it."""
        assert self.downs, "the status never said the camera was down"
        assert any(KILLED in d for d in self.downs), self.downs
        assert all(re.search(r"no frame for \d+\.\d s", d) for d in self.downs), self.downs
        status, message = await self.job()
        assert status == good, message
        snap = self.daemon.snapshot()
        assert snap["healthy"], snap["health_problem"]
        assert snap["health_problem"] is None
        assert snap["camera"]["open"]
        assert snap["camera"]["down"] is None

    async def watch_health(self) -> None:
        """Wait until the status says unhealthy, recording what it says."""
        await self.daemon.wait_for(lambda: not self.daemon.healthy(), WAIT_S)
        self.downs.append(self.daemon.health_problem())
        snap = self.daemon.snapshot()
        assert not snap["healthy"]
        assert snap["camera"]["down"], snap["camera"]


async def kills_at_every_point(run: Run) -> None:
    async with Plc(run.port()) as plc:
        cell = Cell(run, plc)
        good, message = await cell.job()
        assert good not in (Status.CAMERA_ERROR, Status.INTERNAL), message

        # between jobs, a trigger right after: it waits for the camera in the new worker
        cell.downs = []
        cell.kill_worker()
        seq = await cell.trigger()
        await cell.watch_health()
        status, message = await cell.answer(seq)
        assert status == good, message
        await cell.down_then_up(good)

        # during the grab: the job is grabbed again on the new worker, within its time
        cell.downs = []
        seq = await cell.trigger()
        await cell.daemon.wait_for(lambda: cell.daemon.rooms.jobs.state is JobState.ACQUIRING, WAIT_S)
        cell.kill_worker()
        await cell.watch_health()
        status, message = await cell.answer(seq)
        assert status == good, message
        await cell.down_then_up(good)

        # during processing: that job ends INTERNAL naming the signal; the next is good
        cell.downs = []
        seq = await cell.trigger()
        await cell.daemon.wait_for(lambda: cell.daemon.rooms.jobs.state is JobState.PROCESSING, WAIT_S)
        cell.kill_worker()
        status, message = await cell.answer(seq)
        assert (status, message) == (Status.INTERNAL, KILLED)
        await cell.watch_health()
        await cell.down_then_up(good)
        assert cell.daemon.snapshot()["worker"]["restarts"] == 3


@pytest.mark.usefixtures("fakes")
async def test_aravis_worker_killed_between_jobs_in_a_grab_and_in_processing() -> None:
    async with running(aravis_cell()) as run:
        await kills_at_every_point(run)


async def test_pylon_worker_killed_between_jobs_in_a_grab_and_in_processing() -> None:
    need(importlib.util.find_spec("pypylon") is not None,
         "needs pypylon: pip install vgripd[pylon]")
    async with running(pylon_cell()) as run:
        await kills_at_every_point(run)
