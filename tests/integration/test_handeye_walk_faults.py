"""The walk when the robot side misbehaves (``vgripd.service.links.handeye_walk``), over the real
robot_socket link with a raw robot peer: an answer that cannot be delivered (the program gone
before it) does not end the walk, and the restarted program, asking NEXT (recipe 0) while a
target is pending, gets that same target again: nothing is skipped. Only NEXT with recipe 1
(``SKIP``) records the target unreachable. A second connection cannot move the walk (it
belongs to the connection that asked its first NEXT); requests that are no walk requests are
REFUSED and change nothing; every walk answer carries job id 0 (docs/robot_socket.md)."""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path

import numpy as np
import pytest

from drivers.links.robot_socket import RobotSocketLink, RobotSocketOptions
from tests.conftest import stop_task
from tests.drivers.links.test_robot_socket import Peer, until
from vgripd.calib.handeye.plan import load_plan
from vgripd.calib.handeye.walk import NOT_SEEN, UNREACHABLE, Walk
from vgripd.geometry.transforms import pose_error
from vgripd.geometry.vendors import transform_from_vendor, vendor_from_transform
from vgripd.peer.socket_frames import AnswerKind, Request, SocketCommand
from vgripd.service.links.handeye_walk import SKIP, WalkServer
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
        await stop_task(task)
    finally:
        await link.close()


async def blank() -> np.ndarray:
    """A camera that sees no board: every image recorded ``not_seen``."""
    return np.zeros((CAMERA.height, CAMERA.width), np.uint8)


def capture_at(seq: int, T: np.ndarray | tuple[float, ...], recipe: int = 0) -> bytes:
    values = T if isinstance(T, tuple) else vendor_from_transform("kuka", T)
    return Request(SocketCommand.CAPTURE_AT, seq, recipe, values=tuple(values)).encode()


async def dial_from(host: str, port: int) -> Peer:
    """A robot connection from another loopback address (another robot's)."""
    return Peer(*await asyncio.open_connection("127.0.0.1", port, local_addr=(host, 0)))


async def test_the_walk_belongs_to_the_connection_that_asked_its_first_next(
        tmp_path: Path) -> None:
    """A second connection to the walk link's port cannot move the walk: its NEXT with recipe
    1 (skip), its CAPTURE_AT and its LOCATE are REFUSED BUSY and nothing is recorded. Each
    record names the connection it came from. When the walk's connection has closed, a new one
    from the same address takes it over (a program started again); another address stays
    BUSY. Before, the second connection's skip marked the pending target unreachable and its
    CAPTURE_AT (111, 222, 333, 10, 20, 30) was recorded as that target's flange pose."""
    assert make_plan(tmp_path, "eye-in-hand", count=12) == 0
    plan = load_plan(str(tmp_path / "plan.toml"))
    walk = Walk(tmp_path / "walk.json", plan, BOARD, CAMERA)
    link = RobotSocketLink("walk0", RobotSocketOptions(host="127.0.0.1", port=0))
    server = WalkServer(walk, link, blank, "kuka")
    await link.open(server.on_trigger)
    task = asyncio.get_running_loop().create_task(server.serve())
    try:
        robot = await Peer.dial(link.port)
        await robot.request(1, SocketCommand.NEXT)
        first = await robot.answer()
        assert (first.kind, first.status, first.job_id) == (AnswerKind.RESULT, Status.OK, 0)

        other = await Peer.dial(link.port)  # same address, another connection
        await other.request(1, SocketCommand.NEXT, recipe=SKIP)
        await other.send(capture_at(2, (111.0, 222.0, 333.0, 10.0, 20.0, 30.0)))
        await other.request(3, SocketCommand.LOCATE)
        for seq in (1, 2, 3):
            answer = await other.answer()
            assert (answer.kind, answer.request_id, answer.status, answer.job_id) == (
                AnswerKind.REFUSED, seq, Status.BUSY, 0)
        assert walk.records == {}
        assert server.pending == 0
        await other.close()

        await robot.send(capture_at(2, plan.poses[0]))
        captured, second = await robot.answer(), await robot.answer()
        assert (captured.kind, captured.job_id) == (AnswerKind.CAPTURED, 0)
        assert (second.kind, second.status, second.job_id) == (AnswerKind.RESULT, Status.OK, 0)
        host, port = robot.writer.get_extra_info("sockname")[:2]
        record = Walk(tmp_path / "walk.json", plan, BOARD, CAMERA).records[0]  # as saved
        assert record.status == NOT_SEEN
        assert record.peer == f"{host}:{port}"
        mm, _ = pose_error(record.T_base_flange, plan.poses[0])
        assert mm < 1e-3

        # The walk's connection closes: another robot's address stays BUSY, the same
        # address (the program started again) goes on with the pending target.
        await robot.close()
        await until(lambda: not link.connections())
        stranger = await dial_from("127.0.0.2", link.port)
        await stranger.request(1, SocketCommand.NEXT)
        busy = await stranger.answer()
        assert (busy.kind, busy.status) == (AnswerKind.REFUSED, Status.BUSY)
        again = await Peer.dial(link.port)
        await again.request(9, SocketCommand.NEXT)
        resumed = await again.answer()
        assert (resumed.kind, resumed.status) == (AnswerKind.RESULT, Status.OK)
        assert resumed.values == second.values  # target 1, still pending
        await stranger.request(2, SocketCommand.NEXT, recipe=SKIP)
        assert (await stranger.answer()).status == Status.BUSY
        assert sorted(walk.records) == [0]
        await stranger.close()
        await again.close()
    finally:
        await stop_task(task)
        await link.close()


async def test_requests_that_are_no_walk_requests_are_refused_and_change_nothing(
        tmp_path: Path) -> None:
    """The walk's frames as docs/robot_socket.md gives them: every answer job id 0 (a walk
    runs no job); REFUSED (nothing recorded, the target still pending) for CAPTURE_AT with
    no target pending, a NEXT recipe other than 0 or 1, CAPTURE_AT with a recipe, a plain
    LOCATE; RESULT for the targets and the NOT_FOUND that ends the walk; after it, NEXT is
    REFUSED BAD_REQUEST as before the walk. Before, CAPTURE_AT with nothing pending was a
    RESULT with a job id of the walk's own counter, a NEXT recipe 2 asked for the target, and
    a NEXT right after the walk was left unanswered."""
    assert make_plan(tmp_path, "eye-in-hand", count=12) == 0
    plan = load_plan(str(tmp_path / "plan.toml"))
    walk = Walk(tmp_path / "walk.json", plan, BOARD, CAMERA)
    link = RobotSocketLink("walk0", RobotSocketOptions(host="127.0.0.1", port=0))
    await link.open(lambda trigger: None)
    robot = await Peer.dial(link.port)
    try:
        await robot.request(1, SocketCommand.NEXT)  # before the walk: no pick list
        before = await robot.answer()
        assert (before.kind, before.status, before.job_id) == (
            AnswerKind.REFUSED, Status.BAD_REQUEST, 0)
        await link.close()
        server = WalkServer(walk, link, blank, "kuka")
        await link.open(server.on_trigger)
        await robot.close()
        robot = await Peer.dial(link.port)
        task = asyncio.get_running_loop().create_task(server.serve())

        async def refused(frame: bytes, status: Status = Status.BAD_REQUEST) -> None:
            await robot.send(frame)
            answer = await robot.answer()
            assert (answer.kind, answer.status, answer.job_id) == (
                AnswerKind.REFUSED, status, 0), frame[:4]

        await refused(capture_at(2, plan.poses[0]))  # no target pending
        await robot.request(3, SocketCommand.NEXT)
        target = await robot.answer()
        assert (target.kind, target.status, target.job_id) == (AnswerKind.RESULT, Status.OK, 0)
        await refused(Request(SocketCommand.NEXT, 4, 2).encode())
        await refused(Request(SocketCommand.NEXT, 5, 65535).encode())
        await refused(capture_at(6, plan.poses[0], recipe=3))
        await refused(Request(SocketCommand.LOCATE, 7).encode())
        assert walk.records == {}
        assert server.pending == 0
        await robot.request(8, SocketCommand.NEXT)
        same = await robot.answer()
        assert same.values == target.values  # still target 0
        for seq in range(9, 9 + len(plan.poses)):  # skip every target: the walk completes
            await robot.request(seq, SocketCommand.NEXT, recipe=SKIP)
            answer = await robot.answer()
            assert (answer.kind, answer.job_id) == (AnswerKind.RESULT, 0)
        assert answer.status == Status.NOT_FOUND
        await robot.request(100, SocketCommand.NEXT)  # at once after the end
        after = await robot.answer()
        assert (after.kind, after.status, after.job_id) == (
            AnswerKind.REFUSED, Status.BAD_REQUEST, 0)
        await asyncio.wait_for(task, 30)
    finally:
        await robot.close()
        await link.close()
