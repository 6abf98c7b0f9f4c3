"""The daemon with the robot links, end to end with real jobs.

- A UR robot triggers over RTDE (the real ur_rtde client in the link's child process, against the
  mock controller in its own process); the daemon runs a real synthetic job and the simulated
  robot program reads the very offset the pipeline computed.
- Two links at once, one of them to a controller that never answers: the other link keeps
  serving and the status names what is wrong with the bad one.
"""

from __future__ import annotations

import asyncio
from typing import Any

import numpy as np
import pytest

from tests.conftest import lo
from tests.integration.test_daemon import Plc, running, values
from vgripd.config import Config, config_from_dict
from vgripd.peer.registers import Reg
from vgripd.service.links.protocol import LinkState
from vgripd.sim.ur_controller import URController
from vgripd.types import Status

pytestmark = pytest.mark.timeout(90)

TAUGHT = (0.30, 0.10, 0.20, 0.0, 3.1, 0.05)  # UR pose, m and rad


def make_config(links: list[dict[str, Any]], vendor: str = "kuka") -> Config:
    return config_from_dict({
        "camera": {"type": "synthetic", "seed": 11, "max_tilt_deg": 2.0},
        "output": {"vendor": vendor},
        "links": links,
        "status": {"port": 0},
    })


def link_state(snapshot: dict[str, Any], name: str) -> dict[str, Any]:
    for entry in snapshot["links"]:
        if entry["name"] == name:
            return dict(entry)
    raise AssertionError(f"no link {name!r} in {snapshot['links']}")


async def test_ur_robot_triggers_a_job_and_reads_the_computed_offset() -> None:
    with URController(lo("127.0.7.1")) as robot:
        config = make_config([{"type": "ur_rtde", "host": robot.host}], vendor="ur")
        async with running(config) as run:
            await run.daemon.wait_for(
                lambda: all(link.health().state is LinkState.UP
                            for link in run.daemon.rooms.links.links.values()), 30)
            seq = robot.start_program(1, taught_pose=TAUGHT)
            result = await asyncio.to_thread(robot.program_result, seq)
            _, record = await run.job_done(1)

    assert result["error"] is None, result["error"]
    assert record.result.status is Status.OK
    assert (result["status"], result["job_id"], result["captured"]) == (1, record.job_id, seq)
    assert record.result.target is not None
    assert record.result.target.vendor == "ur"
    # The robot read exactly what the pipeline computed (float64 registers: bit-exact).
    assert tuple(result["offset"]) == record.result.target.values
    # ... and that is the base-frame offset in metres / rotation vector.
    offset = record.result.offset
    assert offset is not None
    np.testing.assert_allclose(np.array(result["offset"][:3]) * 1000.0, offset[:3, 3], atol=1e-9)


async def test_a_silent_ur_controller_does_not_stop_the_plc_link() -> None:
    with URController(lo("127.0.7.2")) as robot:
        robot.set_silent(True)
        config = make_config([
            {"type": "modbus_server", "host": "127.0.0.1", "port": 0},
            {"type": "ur_rtde", "host": robot.host, "connect_timeout_s": 1.0}], vendor="ur")
        async with running(config) as run:
            plc_name, ur_name = run.daemon.rooms.links.links  # in config order
            await run.daemon.wait_for(
                lambda: link_state(run.daemon.snapshot(), ur_name)["state"] == "down", 30)
            async with Plc(run.port(0)) as plc:
                await plc.trigger(1)
                words = await plc.result(1)
            snapshot = run.daemon.snapshot()

    assert words[Reg.STATUS] == Status.OK
    assert len(values(words)) == 6
    ur = link_state(snapshot, ur_name)
    assert ur["state"] == "down"
    assert lo("127.0.7.2") in ur["last_error"] or lo("127.0.7.2") in ur["peer"]
    assert "RTDE setup" in ur["last_error"]
    assert link_state(snapshot, plc_name)["state"] == "up"
