"""A walk request the robot program sends again (docs/robot_socket.md, "Walks"): the program's
timeout ran out before the answer came (a loaded machine, a slow image), so it dropped the
connection and sent the same request with a new id. The request gets the same answer again
and nothing is recorded twice: a CAPTURE_AT at the pose of a target already recorded is that
target's request again (the robot has not moved), a skip of a target the program was never
told is the skip before it again, and after the walk the CAPTURE_AT that completed it gets
NOT_FOUND again instead of running a job.

Reproduced deterministically: a raw robot connection over loopback (the image held until the
connection is gone, or the request simply sent twice), the walk server held while a skip's
connection closes, each brand's twin whose first image answer is held past its own timeout
until it has asked again, and the daemon's walk whose last CAPTURE_AT is sent again.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path

import numpy as np
import pytest

from drivers.links.robot_socket import RobotSocketLink
from tests.conftest import stop_task
from tests.drivers.links.test_robot_socket import Peer, until
from tests.integration.test_robot_programs import free_port
from tests.integration.test_robot_programs_walk import (
    BOARD,
    CAMERA,
    COUNT,
    ReportingArm,
    daemon_walking,
    image_at,
    link_options,
    make_plan,
    new_arm,
    settings_for,
)
from vgripd.calib.handeye.plan import LoadedPlan, load_plan
from vgripd.calib.handeye.walk import SEEN, UNREACHABLE, Walk
from vgripd.geometry.transforms import pose_error
from vgripd.geometry.vendors import vendor_from_transform
from vgripd.peer.socket_frames import (
    BRANDS,
    Answer,
    AnswerKind,
    Request,
    SocketCommand,
    header_word,
)
from vgripd.service.links.handeye_walk import WalkServer
from vgripd.sim.robot_socket_client import WALK_SKIP, ProgramTwin
from vgripd.types import Status

pytestmark = [pytest.mark.timeout(240), pytest.mark.slow]
BRAND, MODE = "kuka", "eye-in-hand"  # int32 x 10000, the kuka convention


def plan_in(folder: Path) -> LoadedPlan:
    assert make_plan(folder, MODE, count=COUNT) == 0
    return load_plan(str(folder / "plan.toml"))


def values(T: np.ndarray) -> tuple[float, ...]:
    return tuple(float(v) for v in vendor_from_transform("kuka", T))


def capture_at(seq: int, T: np.ndarray) -> bytes:
    return Request(SocketCommand.CAPTURE_AT, seq, values=values(T)).encode()


def is_target(answer: Answer, T: np.ndarray) -> bool:
    """A RESULT OK (job 0) carrying target ``T`` to the encoding's resolution."""
    return (answer.kind is AnswerKind.RESULT and answer.status == Status.OK
            and answer.job_id == 0
            and np.allclose(answer.values, values(T), atol=2e-4))


@contextlib.asynccontextmanager
async def serving(walk: Walk, grab: Callable[[], Awaitable[np.ndarray]], port: int = 0,
                  brand: str = BRAND) -> AsyncIterator[tuple[WalkServer, RobotSocketLink]]:
    """The WalkServer of ``vgripd calibrate handeye walk`` on a robot_socket link, in-process
    (``port`` 0: any free one, ``link.port``)."""
    link = RobotSocketLink("walk0", link_options(brand, port))
    server = WalkServer(walk, link, grab, BRANDS[brand].convention)
    await link.open(server.on_trigger)
    try:
        yield server, link
    finally:
        await link.close()


@contextlib.asynccontextmanager
async def running(server: WalkServer) -> AsyncIterator[asyncio.Task[None]]:
    task = asyncio.get_running_loop().create_task(server.serve())
    try:
        yield task
    finally:
        await stop_task(task)


async def captured_then_result(peer: Peer) -> Answer:
    first = await peer.answer()
    assert (first.kind, first.job_id) == (AnswerKind.CAPTURED, 0), first
    return await peer.answer()


@pytest.mark.parametrize("lost", [False, True], ids=["read-then-sent-again", "answer-lost"])
async def test_a_capture_at_sent_again_gets_the_same_answer_and_records_nothing(
        tmp_path: Path, lost: bool) -> None:
    """CAPTURE_AT at target 0, then the same CAPTURE_AT again with a new id (the program's
    retry: its timer ran out just before the answer came, or the connection was dropped before
    the answer, which the link could then not deliver): the second gets CAPTURED and RESULT
    with target 1 again, target 1 stays pending, no image is taken for it; a CAPTURE_AT at
    target 1 then records target 1. Before, the repeat was recorded as target 1 (with target
    0's pose and a second image from there) and answered target 2: target 1 never visited."""
    plan = plan_in(tmp_path)
    walk = Walk(tmp_path / "walk.json", plan, BOARD, CAMERA)
    grabs: list[int] = []
    release = asyncio.Event()
    T0, T1, T2 = plan.poses[0], plan.poses[1], plan.poses[2]

    async def grab() -> np.ndarray:
        index = server.pending
        assert index is not None
        grabs.append(index)
        if lost and len(grabs) == 1:
            await release.wait()  # the camera is slow: the program's timeout runs out
        return await asyncio.to_thread(image_at, MODE, plan.poses[index], index)

    async with serving(walk, grab) as (server, link), running(server):
        robot = await Peer.dial(link.port)
        await robot.request(1, SocketCommand.NEXT)
        assert is_target(await robot.answer(), T0)
        await robot.send(capture_at(2, T0))
        if lost:
            await until(lambda: grabs == [0])
            await robot.close()  # the program gives up on request 2 and drops the connection
            await until(lambda: not link.connections())
            release.set()
            await until(lambda: 0 in walk.records and server.pending == 1)
            robot = await Peer.dial(link.port)
        else:
            assert is_target(await captured_then_result(robot), T1)
        await robot.send(capture_at(3, T0))  # the program asks again, at target 0
        again = await captured_then_result(robot)
        assert again.request_id == 3
        assert is_target(again, T1), again  # target 1 again, not target 2
        assert sorted(walk.records) == [0]
        assert server.pending == 1
        assert grabs == [0]  # no second image
        await robot.send(capture_at(4, T1))  # moved to target 1
        assert is_target(await captured_then_result(robot), T2)
        await robot.close()
    assert grabs == [0, 1]
    final = Walk(tmp_path / "walk.json", plan, BOARD, CAMERA)
    assert sorted(final.records) == [0, 1]
    for index in (0, 1):
        record = final.records[index]
        assert record.status == SEEN
        mm, deg = pose_error(record.T_base_flange, plan.poses[index])
        assert mm < 1e-3
        assert deg < 1e-3


async def test_a_skip_whose_answer_was_lost_is_answered_again_not_taken_twice(
        tmp_path: Path) -> None:
    """NEXT with recipe 1 (skip target 0), the program's connection gone before the walk
    answers it (target 1 not delivered), then the same skip again on a new connection: target
    0 is recorded unreachable once, target 1 is answered again and stays pending. Before, the
    repeat skipped target 1 too, a target the program had never been given."""
    plan = plan_in(tmp_path)
    walk = Walk(tmp_path / "walk.json", plan, BOARD, CAMERA)

    async def grab() -> np.ndarray:
        raise AssertionError("no image in this test")

    async with serving(walk, grab) as (server, link):
        robot = await Peer.dial(link.port)
        async with running(server):
            await robot.request(1, SocketCommand.NEXT)
            assert is_target(await robot.answer(), plan.poses[0])
        # the walk server is held (a loaded machine) while the skip comes and its
        # connection goes: its answer cannot be delivered
        await robot.request(2, SocketCommand.NEXT, WALK_SKIP)
        await robot.close()
        await until(lambda: not link.connections())
        async with running(server):
            await until(lambda: 0 in walk.records and server.current is None)
            robot = await Peer.dial(link.port)
            await robot.request(3, SocketCommand.NEXT, WALK_SKIP)  # the program's retry
            again = await robot.answer()
            assert again.request_id == 3
            assert is_target(again, plan.poses[1]), again
            assert sorted(walk.records) == [0]
            assert server.pending == 1
            # told now: a skip of target 1 is a skip
            await robot.request(4, SocketCommand.NEXT, WALK_SKIP)
            assert is_target(await robot.answer(), plan.poses[2])
            await robot.close()
    final = Walk(tmp_path / "walk.json", plan, BOARD, CAMERA)
    assert {k: r.status for k, r in final.records.items()} == {0: UNREACHABLE, 1: UNREACHABLE}


@pytest.mark.parametrize("brand", ["abb", "fanuc", "kuka"])
async def test_a_program_whose_first_image_answer_came_too_late_walks_every_target(
        brand: str, tmp_path: Path) -> None:
    """Each brand's twin walks the plan; the first CAPTURE_AT's image is held until the
    program, its timeout run out, has asked again (a new connection: it drops the old one
    after a timeout; the link answers BUSY while the first is answered, and the program asks
    again after its busy wait). The walk still visits every reachable target once and records
    each with its own pose. Before, the retry became the next target's record: one target
    never visited, one image a duplicate (10 targets reached of 11)."""
    settings = settings_for(brand)  # its own timeout (job_timeout_s + 2 s) from the 2nd on
    plan = plan_in(tmp_path)
    arm = new_arm(plan, seed=len(brand))
    walk = Walk(tmp_path / "walk.json", plan, BOARD, CAMERA)
    port = free_port()
    twin = ProgramTwin(dataclasses.replace(settings, timeout_s=1.0), "127.0.0.1", port)
    grabs = 0

    async def grab() -> np.ndarray:
        nonlocal grabs
        grabs += 1
        if grabs == 1:  # held until the program, its timeout run out, dialled again
            connects = twin.connects
            await until(lambda: twin.connects > connects)
            twin.s = settings  # the machine less loaded: the answers come in time again
        return await asyncio.to_thread(image_at, MODE, arm.T_true.copy(), arm.moves)

    async with serving(walk, grab, port, brand) as (server, _), running(server) as task:
        async with twin:
            outcome = await twin.walk(arm)
        await asyncio.wait_for(task, 60)
    sent = twin.sent
    assert outcome.status == Status.NOT_FOUND
    assert len(outcome.reached) == COUNT - 1 == arm.moves  # 11 of 12, the far one skipped
    words = [int.from_bytes(f[:4], "big") for f in sent]
    assert words.count(header_word(SocketCommand.CAPTURE_AT)) > COUNT - 1  # it did ask again
    assert grabs == COUNT - 1  # one image per target reached
    final = Walk(tmp_path / "walk.json", plan, BOARD, CAMERA)
    statuses = [r.status for _, r in sorted(final.records.items())]
    assert statuses.count(SEEN) == COUNT - 1
    assert statuses.count(UNREACHABLE) == 1
    for record in final.records.values():  # each record is its own target's
        if record.status == SEEN:
            mm, _ = pose_error(record.T_base_flange, plan.poses[record.index])
            assert mm < 0.1, (record.index, mm)


async def test_the_daemons_walk_answers_the_last_capture_at_again_not_as_a_job(
        tmp_path: Path) -> None:
    """The daemon's walk is complete (NOT_FOUND answered to the last CAPTURE_AT); the program,
    which did not get that answer in time, sends the CAPTURE_AT again: CAPTURED and RESULT
    NOT_FOUND again, job id 0, no job run (the next LOCATE is job 1). Before, the repeat ran
    a job, whose result (a pose, or no image) the program would have taken as its answer."""
    settings = settings_for(BRAND)
    plan = plan_in(tmp_path)
    reach = max(float(np.linalg.norm(T[:3, 3])) for T in plan.poses) + 1.0
    arm = ReportingArm(plan.poses[0], reach_mm=reach, settle_cycles=3)  # reaches every target
    walk = Walk(tmp_path / "plan.walk.json", plan, BOARD, CAMERA)
    port = free_port()
    async with daemon_walking(BRAND, port, walk, arm, MODE) as done:
        async with ProgramTwin(settings, "127.0.0.1", port) as twin:
            outcome = await twin.walk(arm)
        assert outcome.status == Status.NOT_FOUND
        await done
        last = twin.sent[-1]
        assert int.from_bytes(last[:4], "big") == header_word(SocketCommand.CAPTURE_AT)
        robot = await Peer.dial(port)
        await robot.send(last[:4] + (77).to_bytes(4, "big") + last[8:])  # again, new id
        again = await captured_then_result(robot)
        assert (again.kind, again.request_id, again.status, again.job_id) == (
            AnswerKind.RESULT, 77, Status.NOT_FOUND, 0)
        await robot.request(78, SocketCommand.LOCATE)  # the cell's own work: a job
        answers = [await robot.answer()]
        while answers[-1].kind is AnswerKind.CAPTURED:
            answers.append(await robot.answer())
        assert answers[-1].kind is AnswerKind.RESULT
        assert {a.job_id for a in answers} == {1}  # the first job: the repeat ran none
        await robot.close()
