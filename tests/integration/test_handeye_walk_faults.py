"""The walk when the robot side misbehaves (``vgripd.service.handeye_walk``), over the real
robot_socket link with a raw robot peer: an answer that cannot be delivered (the program gone
before it) does not end the walk, and the restarted program, asking NEXT (recipe 0) while a
target is pending, gets that same target again: nothing is skipped. Only NEXT with recipe 1
(``SKIP``) records the target unreachable."""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path

import numpy as np
import pytest

from drivers.links.robot_socket import RobotSocketLink, RobotSocketOptions
from tests.drivers.test_robot_socket import Peer, until
from vgripd.calib.handeye.plan import load_plan
from vgripd.calib.handeye.walk import UNREACHABLE, Walk
from vgripd.geometry.transforms import pose_error
from vgripd.geometry.vendors import transform_from_vendor
from vgripd.service.handeye_walk import SKIP, WalkServer
from vgripd.service.robot_socket_format import SocketCommand
from vgripd.types import Status

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "unit" / "calib"))
from test_calib_handeye_walk import BOARD, CAMERA, make_plan  # noqa: E402

pytestmark = pytest.mark.timeout(120)


async def test_a_lost_answer_and_a_restarted_program_skip_no_target(tmp_path: Path) -> None:
    assert make_plan(tmp_path, "eye-in-hand", count=12) == 0
    plan = load_plan(str(tmp_path / "plan.toml"))
    walk = Walk(tmp_path / "walk.json", plan, BOARD, CAMERA)

    async def no_image() -> np.ndarray:
        raise AssertionError("no image is asked for here")

    link = RobotSocketLink("walk0", RobotSocketOptions(host="127.0.0.1", port=0,
                                                       value_format="float32"))
    server = WalkServer(walk, link, no_image, "abb")
    await link.open(server.on_trigger)
    try:
        # The program asks for its target and is gone before the answer (a robot stop).
        gone = await Peer.dial(link.port)
        await gone.request(1, SocketCommand.NEXT)
        await gone.close()
        await until(lambda: not link.connections() and not server._queue.empty())
        task = asyncio.get_running_loop().create_task(server.serve())
        await until(lambda: server.pending is not None)
        assert server.pending == 0
        assert not task.done()  # the undelivered answer did not end the walk

        # Restarted, it asks again: the same target, nothing recorded.
        robot = await Peer.dial(link.port)
        await robot.request(2, SocketCommand.NEXT)
        again = await robot.answer()
        assert again.status == Status.OK
        mm, deg = pose_error(transform_from_vendor("abb", again.values[:7]), plan.poses[0])
        assert mm < 1e-3
        assert deg < 1e-3
        assert walk.records == {}
        # Only the skip word records it unreachable; the answer is the next target.
        await robot.request(3, SocketCommand.NEXT, recipe=SKIP)
        nxt = await robot.answer()
        assert nxt.status == Status.OK
        mm, _ = pose_error(transform_from_vendor("abb", nxt.values[:7]), plan.poses[1])
        assert mm < 1e-3
        assert [r.status for r in walk.records.values()] == [UNREACHABLE]
        await robot.close()
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    finally:
        await link.close()
