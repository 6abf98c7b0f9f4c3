"""The walk routine of every generated robot-socket program (``vgripd robot-program``): its
Python twin (settings, speed, settle time, command words and frame sizes parsed from the text
the CLI wrote) walks a hand-eye plan against vgripd serving the walk over the real
``robot_socket`` link, moving a simulated arm (reach limit, settle cycles, noise on the pose it
reports). The twin asks NEXT, skips the target beyond the arm's reach with NEXT, moves to the
others and sends CAPTURE_AT with the pose the arm reports, in the brand's convention and
encoding; the image is rendered from the pose the arm really reached
(tests/unit/calib/test_calib_handeye_walk.py's scene).

Checked for each brand: the walk completes (NOT_FOUND), one target recorded unreachable, every
other seen, each recorded flange pose the arm's within the encoding's resolution, the bytes on
the wire the documented frames (44-byte CAPTURE_AT). Solved for one brand per mounting (KUKA
eye-in-hand, ABB eye-to-hand) within 0.05 mm / 0.01 deg of the truth; a walk stopped halfway
resumes (Staubli). vgripd's side: for every brand the running daemon (``daemon_walking``: the
walk started over its web API with the token, its replay camera showing the board as seen from
each target the arm reaches), and the ``WalkServer`` as ``vgripd calibrate handeye walk`` runs
it, in-process (``serving_walk``), for the resumed walk.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import struct
import sys
import tomllib
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import cv2
import numpy as np
import pytest

from drivers.links.robot_socket import RobotSocketLink, RobotSocketOptions
from tests.conftest import stop_task
from tests.drivers.links.test_robot_socket import Peer
from tests.integration.test_daemon import running
from tests.integration.test_daemon_handeye_walk import PLATE
from tests.integration.test_robot_programs import cell, free_port, program
from tests.integration.test_web_reload import TOKEN, post, running_file
from vgripd.__main__ import main
from vgripd.calib.handeye.plan import LoadedPlan, load_plan
from vgripd.calib.handeye.walk import SEEN, UNREACHABLE, Walk
from vgripd.config import config_from_dict
from vgripd.geometry.transforms import pose_error
from vgripd.geometry.vendors import convention, transform_from_vendor
from vgripd.peer.socket_frames import (
    BRANDS,
    CAPTURE_AT_SIZE,
    REQUEST_SIZE,
    AnswerKind,
    SocketCommand,
    header_word,
)
from vgripd.serialize import toml_from_dict
from vgripd.service.links.handeye_walk import WalkServer
from vgripd.service.links.protocol import LinkState
from vgripd.sim.arm import SimulatedArm
from vgripd.sim.robot_socket_client import (
    AT_ELSEWHERE,
    WALK_SKIP,
    ProgramSettings,
    ProgramTwin,
    WalkOutcome,
)
from vgripd.types import Status

# the rendered scene of the walk test (bare module names, as pytest imports them there)
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "unit" / "calib"))
import test_calib_boards  # noqa: E402
from test_calib_handeye_walk import (  # noqa: E402
    BOARD,
    CAMERA,
    image_at,
    make_plan,
    truth,
)

pytestmark = [pytest.mark.timeout(480), pytest.mark.slow(minutes=4)]
COUNT = 12  # plan poses: one beyond the arm's reach, eleven seen
#: How long a whole walk may take: eleven images found in the worker, each move simulated; on a
#: busy 2-core machine (two suites side by side) well over a minute. A bound, not a target.
WALK_S = 240.0
SPEED_MM_S = 40.0
#: the mounting each brand walks (one brand per mounting is also solved)
MODES = {"kuka": "eye-in-hand", "abb": "eye-to-hand", "fanuc": "eye-in-hand",
         "staubli": "eye-to-hand", "yaskawa": "eye-in-hand", "ur": "eye-to-hand"}
SOLVED = {"kuka", "abb"}


@pytest.fixture(autouse=True)
def sharp_texture(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(test_calib_boards, "PPM", 4.0)


class ReportingArm(SimulatedArm):
    """The simulated arm, keeping every pose it reported (what the controller read)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.reported: list[np.ndarray] = []

    def reported_pose(self) -> np.ndarray:
        T = super().reported_pose()
        self.reported.append(T)
        return T


def settings_for(brand: str) -> ProgramSettings:
    """The brand's program as the CLI writes it for a walk at SPEED_MM_S without settling."""
    data = cell(brand, 50100)
    data["calibration_walk"] = {"speed_mm_s": SPEED_MM_S, "settle_s": 0.0}
    return ProgramSettings.parse(brand, program(brand, data))


def link_options(brand: str, port: int) -> RobotSocketOptions:
    b = BRANDS[brand]
    return RobotSocketOptions(mode=b.mode, host="127.0.0.1", port=port,
                              value_format=b.value_format,
                              scale=1000000 if brand == "ur" else 10000)


@contextlib.asynccontextmanager
async def serving_walk(brand: str, port: int, walk: Walk, arm: SimulatedArm, mode: str
                       ) -> AsyncIterator[asyncio.Task[None]]:
    """vgripd serving ``walk`` on a robot_socket link (``port``: where it listens, or for a
    robot-server brand where it dials): today the WalkServer of ``vgripd calibrate handeye
    walk``, in-process. The images come from the pose the arm really reached."""

    async def grab() -> np.ndarray:
        return await asyncio.to_thread(image_at, mode, arm.T_true.copy(), arm.moves)

    link = RobotSocketLink("walk0", link_options(brand, port))
    server = WalkServer(walk, link, grab, BRANDS[brand].convention)
    await link.open(server.on_trigger)
    task = asyncio.get_running_loop().create_task(server.serve())
    try:
        yield task
    finally:
        await stop_task(task)
        await link.close()


@contextlib.asynccontextmanager
async def daemon_walking(brand: str, port: int, walk: Walk, arm: SimulatedArm, mode: str
                         ) -> AsyncIterator[asyncio.Future[None]]:
    """The running daemon (``vgripd run``'s Daemon, config file beside the plan) serving the
    walk on its robot_socket link, started over the web API with the token. Its replay camera
    holds the board as seen from each target the arm can reach, in the order the program visits
    them. Yields a future done once the walk is complete."""
    folder = walk.path.parent
    frames = folder / "frames"
    frames.mkdir()
    reachable = [k for k, T in enumerate(walk.plan.poses) if arm.reachable(T)]
    for n, k in enumerate(reachable):
        cv2.imwrite(str(frames / f"{n:02d}.png"), image_at(mode, walk.plan.poses[k], seed=k))
    data = cell(brand, port)
    data["camera"] = {"type": "replay", "folder": str(frames), "glob": "*.png"}
    data["object"] = PLATE
    data["calibration"] = tomllib.loads((folder / "cell.toml").read_text())["calibration"]
    data["status"] = {"port": 0, "token": TOKEN, "allow_config_edit": True}
    path = folder / "vgripd.toml"
    path.write_text(toml_from_dict(data), encoding="utf-8")
    async with running_file(path) as run, aiohttp.ClientSession() as session:
        assert run.daemon.status_server is not None
        url = f"http://127.0.0.1:{run.daemon.status_server.port}/api/handeye/walk/start"
        code, out = await post(session, url, {"plan": Path(walk.plan.path).name, "link": 0})
        assert code == 200, out
        walks = run.daemon.rooms.walks
        yield asyncio.ensure_future(
            run.daemon.wait_for(lambda: walks.state.value == "complete", WALK_S))


async def walk_with(brand: str, settings: ProgramSettings, walk: Walk, arm: SimulatedArm,
                    mode: str, stop_after: int | None = None, serve: Any = serving_walk
                    ) -> tuple[WalkOutcome, list[bytes]]:
    """The twin walks against vgripd served by ``serve`` (``serving_walk`` or
    ``daemon_walking``), started in the order the brand's TCP roles need."""
    robot_server = BRANDS[brand].connection == "robot_server"
    async with contextlib.AsyncExitStack() as stack:
        if robot_server:  # the program listens, vgripd dials in
            twin = await stack.enter_async_context(ProgramTwin(settings, "127.0.0.1", 0))
            task = await stack.enter_async_context(serve(brand, twin.port, walk, arm, mode))
        else:
            port = free_port()
            task = await stack.enter_async_context(serve(brand, port, walk, arm, mode))
            twin = await stack.enter_async_context(ProgramTwin(settings, "127.0.0.1", port))
        outcome = await twin.walk(arm, stop_after)
        if stop_after is None:
            await asyncio.wait_for(task, WALK_S)  # done once it answered NOT_FOUND
        return outcome, twin.sent


def new_arm(plan: LoadedPlan, seed: int) -> ReportingArm:
    """An arm that reaches every target but the farthest."""
    reach = sorted(np.linalg.norm(T[:3, 3]) for T in plan.poses)
    return ReportingArm(plan.poses[0], reach_mm=(reach[-1] + reach[-2]) / 2, settle_cycles=3,
                        noise_deg=0.001, noise_mm=0.005, rng=np.random.default_rng(seed))


def check_wire(sent: list[bytes], settings: ProgramSettings, captures: int) -> None:
    """The twin's frames: NEXT twice (the first target with recipe 0, the skip with recipe
    1), then CAPTURE_AT at each target reached, 44 bytes with the values in the program's
    encoding."""
    commands = [struct.unpack(">I", f[:4])[0] for f in sent]
    nexts = [struct.unpack(">I", f[8:12])[0] for f, word in zip(sent, commands, strict=True)
             if word == header_word(SocketCommand.NEXT)]
    assert nexts == [0, WALK_SKIP] == [0, 1]  # the recipe word: ask, then skip
    # one CAPTURE_AT per target reached; a program asks again (the same frame) after BUSY or
    # an answer later than its timeout, which a busy machine gives: repeats follow each other
    poses = [f[16:] for f, word in zip(sent, commands, strict=True)
             if word == header_word(SocketCommand.CAPTURE_AT)]
    distinct = [p for i, p in enumerate(poses) if i == 0 or p != poses[i - 1]]
    assert len(distinct) == captures, (len(poses), captures)
    assert settings.words["CAPTURE_AT"] == header_word(SocketCommand.CAPTURE_AT)
    assert settings.at_bytes == CAPTURE_AT_SIZE
    for frame, word in zip(sent, commands, strict=True):
        at = word == header_word(SocketCommand.CAPTURE_AT)
        assert len(frame) == (CAPTURE_AT_SIZE if at else REQUEST_SIZE)
        assert frame[12:16] == bytes(4)  # reserved word 0


@pytest.mark.parametrize("brand", sorted(BRANDS))
async def test_each_program_walks_the_plan_skipping_the_unreachable_target(
        brand: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    mode = MODES[brand]
    settings = settings_for(brand)
    assert settings.walk_speed_mm_s == SPEED_MM_S  # from [calibration_walk]
    assert settings.walk_settle_s == 0.0
    assert make_plan(tmp_path, mode, count=COUNT) == 0
    plan = load_plan(str(tmp_path / "plan.toml"))
    arm = new_arm(plan, seed=len(brand))
    walk_file = tmp_path / "plan.walk.json"  # where the daemon keeps the plan's record
    walk = Walk(walk_file, plan, BOARD, CAMERA)
    outcome, sent = await walk_with(brand, settings, walk, arm, mode, serve=daemon_walking)

    assert outcome.status == Status.NOT_FOUND  # the walk is complete
    assert len(outcome.skipped) == 1
    assert len(outcome.reached) == COUNT - 1 == arm.moves
    assert {speed for _, speed in outcome.moves} == {SPEED_MM_S}
    check_wire(sent, settings, COUNT - 1)
    final = Walk(walk_file, plan, BOARD, CAMERA)
    statuses = [r.status for _, r in sorted(final.records.items())]
    assert statuses.count(UNREACHABLE) == 1
    assert statuses.count(SEEN) == COUNT - 1
    far = int(np.argmax([np.linalg.norm(T[:3, 3]) for T in plan.poses]))
    assert final.records[far].status == UNREACHABLE
    # each recorded flange pose is the one the arm reported, to the encoding's resolution
    seen = [r for _, r in sorted(final.records.items()) if r.status == SEEN]
    assert len(arm.reported) == len(seen)
    for record, T in zip(seen, arm.reported, strict=True):
        mm, deg = pose_error(record.T_base_flange, T)
        assert mm < 2e-3, (brand, mm)
        assert deg < 2e-4, (brand, deg)
    # the targets the program moved to are the plan's, as its convention carries them
    n = len(convention(BRANDS[brand].convention).fields)
    assert all(len(target) == n for target in outcome.reached)

    if brand in SOLVED:
        capsys.readouterr()
        out = tmp_path / "handeye.toml"
        assert main(["calibrate", "handeye", "--samples", str(walk_file), "--intrinsics",
                     str(tmp_path / "cell.toml"), "-o", str(out), "--json"]) == 0
        summary = json.loads(capsys.readouterr().out)
        mm, deg = pose_error(np.asarray(summary["matrix_mm"]), truth(mode)[0])
        print(f"{brand} {mode}: {mm:.4f} mm {deg:.5f} deg", file=sys.stderr)
        assert mm < 0.05, (brand, mode, mm, deg)
        assert deg < 0.01, (brand, mode, mm, deg)
        assert any("unreachable" in r["reason"] for r in summary["rejected"])


async def test_a_walk_stopped_halfway_resumes_where_it_stopped(tmp_path: Path) -> None:
    brand, mode = "staubli", "eye-to-hand"
    settings = settings_for(brand)
    assert make_plan(tmp_path, mode, count=COUNT) == 0
    plan = load_plan(str(tmp_path / "plan.toml"))
    arm = new_arm(plan, seed=3)
    walk_file = tmp_path / "walk.json"
    first, _ = await walk_with(brand, settings, Walk(walk_file, plan, BOARD, CAMERA), arm,
                               mode, stop_after=5)
    assert first.status in (1, 2)  # stopped by the operator, the walk not complete
    assert len(Walk(walk_file, plan, BOARD, CAMERA).records) == 5
    resumed, sent = await walk_with(brand, settings, Walk(walk_file, plan, BOARD, CAMERA), arm,
                                    mode)
    assert resumed.status == Status.NOT_FOUND
    final = Walk(walk_file, plan, BOARD, CAMERA)
    assert sorted(final.records) == list(range(COUNT))
    assert arm.moves == COUNT - 1  # no target visited twice across the resume
    statuses = [r.status for r in final.records.values()]
    assert statuses.count(UNREACHABLE) == 1
    assert statuses.count(SEEN) == COUNT - 1


#: The skip in each generated program's walk routine: NEXT with recipe 1 (its start: 0).
SKIP_CALL = {"kuka": "vgAsk(VG_NEXT, 1)", "abb": "vgAsk(VG_NEXT, 1)",
             "fanuc": "vg_cmd = VG_NEXT -- not reachable: skipped (recipe 1), ask for the "
                      "next target\n        vg_recipe = 1",
             "staubli": "call vgAsk(VG_NEXT, 1, x_vgStatus)",
             "yaskawa": "vgAsk(VG_NEXT, 1, 0)", "ur": "vg_ask(VG_NEXT, 1)"}


@pytest.mark.parametrize("brand", sorted(BRANDS))
def test_each_program_skips_with_next_recipe_1(brand: str) -> None:
    """What the twin sends is what the program text does: its one skip is NEXT with recipe 1
    (before, NEXT with recipe 0, which a restarted program also sends for its first target)."""
    text = "\n".join(program(brand, cell(brand, 50100)).values())
    assert text.count(SKIP_CALL[brand]) == 1


async def test_a_program_restarted_with_a_target_pending_gets_it_again(tmp_path: Path) -> None:
    """The robot program is stopped after vgripd answered a target and before it moved there,
    and started again while vgripd's walk keeps running (the same WalkServer, the target
    pending): its first NEXT (recipe 0) gets that target again, and the walk ends with the far
    target the only unreachable one. Before, that NEXT was taken as "unreachable": a good
    target skipped."""
    brand, mode = "kuka", "eye-in-hand"
    settings = settings_for(brand)
    assert make_plan(tmp_path, mode, count=COUNT) == 0
    plan = load_plan(str(tmp_path / "plan.toml"))
    arm = new_arm(plan, seed=5)
    far = int(np.argmax([np.linalg.norm(T[:3, 3]) for T in plan.poses]))
    stop_after = 5 if far != 5 else 6  # the target pending at the stop is a reachable one
    walk_file = tmp_path / "walk.json"
    port = free_port()
    async with serving_walk(brand, port, Walk(walk_file, plan, BOARD, CAMERA), arm,
                            mode) as task:
        async with ProgramTwin(settings, "127.0.0.1", port) as twin:
            first = await twin.walk(arm, stop_after=stop_after)  # the program stopped
        assert first.status in (1, 2)
        assert first.pending  # a target answered, not moved to
        assert len(Walk(walk_file, plan, BOARD, CAMERA).records) == stop_after
        async with ProgramTwin(settings, "127.0.0.1", port) as twin:  # started again
            again = await twin.walk(arm)
            sent = twin.sent
        await asyncio.wait_for(task, WALK_S)
    assert again.status == Status.NOT_FOUND
    assert again.reached[0] == first.pending  # the same target again, not skipped
    first_next = sent[0]
    assert struct.unpack(">I", first_next[:4])[0] == header_word(SocketCommand.NEXT)
    assert struct.unpack(">I", first_next[8:12])[0] == 0
    final = Walk(walk_file, plan, BOARD, CAMERA)
    assert sorted(final.records) == list(range(COUNT))
    unreachable = [k for k, r in final.records.items() if r.status == UNREACHABLE]
    assert unreachable == [far]
    assert arm.moves == COUNT - 1


@pytest.mark.parametrize("brand", ["kuka", "abb"])
async def test_capture_at_outside_a_walk_is_a_locate_with_the_flange_pose(brand: str) -> None:
    """The daemon (no walk) runs a job for CAPTURE_AT like for LOCATE, its image carrying the
    flange pose the program sent (for a robot-mounted camera), in the brand's convention."""
    port = free_port()
    data = cell(brand, port)
    T = transform_from_vendor("kuka", (512.25, -80.5, 640.125, 12.5, -3.25, 178.0))
    async with running(config_from_dict(data)) as run:
        link = next(iter(run.daemon.rooms.links.links.values()))
        await run.daemon.wait_for(lambda: link.health().state is LinkState.UP, 30.0)
        async with ProgramTwin(settings_for(brand), "127.0.0.1", port) as twin:
            outcome = await twin.capture_at(T)
        pair, record = await run.job_done(1)
    assert outcome.status == Status.OK, outcome
    assert outcome.captured
    assert record.job_id == outcome.job_id
    assert len(twin.sent[0]) == CAPTURE_AT_SIZE
    assert pair is not None
    assert pair.T_base_flange is not None
    mm, deg = pose_error(np.asarray(pair.T_base_flange), T)
    assert mm < 1e-3
    assert deg < 1e-3


async def test_a_stop_while_the_image_is_taken_answers_that_request_once_and_whole(
        tmp_path: Path) -> None:
    """The walk is stopped (the daemon's stop, the page's stop) while the camera takes the
    image of a CAPTURE_AT: the answer goes out whole (the target recorded, the next one sent)
    and the request is not left for an ABORTED answer as well. Before, the stop cut the grab
    (or the answer being written) short and the request was answered ABORTED after it."""
    brand, mode = "kuka", "eye-in-hand"
    assert make_plan(tmp_path, mode, count=COUNT) == 0
    plan = load_plan(str(tmp_path / "plan.toml"))
    walk = Walk(tmp_path / "walk.json", plan, BOARD, CAMERA)
    taking, release = asyncio.Event(), asyncio.Event()

    async def grab() -> np.ndarray:
        taking.set()
        await release.wait()  # the camera is exposing
        return await asyncio.to_thread(image_at, mode, plan.poses[0], 0)

    port = free_port()
    link = RobotSocketLink("walk0", link_options(brand, port))
    server = WalkServer(walk, link, grab, BRANDS[brand].convention)
    await link.open(server.on_trigger)
    task = asyncio.get_running_loop().create_task(server.serve())
    try:
        async with ProgramTwin(settings_for(brand), "127.0.0.1", port) as twin:
            first = await twin.next()
            assert first.status == Status.OK
            at = asyncio.ensure_future(twin.capture_at(plan.poses[0]))
            await asyncio.wait_for(taking.wait(), 30)
            task.cancel()  # stop while the image is taken
            release.set()
            with pytest.raises(asyncio.CancelledError):
                await task
            answer = await asyncio.wait_for(at, 30)
    finally:
        await link.close()
    assert answer.status == Status.OK  # the next target, not ABORTED
    assert answer.captured
    assert server.waiting() == []  # nothing left to answer ABORTED
    assert Walk(tmp_path / "walk.json", plan, BOARD, CAMERA).records[0].status == SEEN


class ToolArm(ReportingArm):
    """An arm whose pose is read with a tool that is not the flange (30 mm along z): a Yaskawa
    tool file 0 that is not all 0."""

    def reported_pose(self) -> np.ndarray:
        T = super().reported_pose().copy()
        T[:3, 3] += T[:3, 2] * 30.0
        return T


async def test_the_yaskawa_walk_pauses_when_tool_file_0_is_not_the_flange(
        tmp_path: Path) -> None:
    """The MotoPlus task reads the flange pose with tool file 0 (docs/robot_socket.md,
    "Walks"): a pose read 30 mm off the target the job moved to is not sent (no CAPTURE_AT,
    nothing recorded) and the walk stops with -2. The generated task has the check, with the
    tolerance its twin reads."""
    brand, mode = "yaskawa", "eye-in-hand"
    text = "\n".join(program(brand, cell(brand, 50100)).values())
    assert "if (!vgAtTarget(&vgCoord)) {\n            return -2;" in text
    settings = settings_for(brand)
    assert settings.at_tolerance == (1.0, 0.1)
    assert settings_for("kuka").at_tolerance is None
    assert make_plan(tmp_path, mode, count=COUNT) == 0
    plan = load_plan(str(tmp_path / "plan.toml"))
    reach = sorted(np.linalg.norm(T[:3, 3]) for T in plan.poses)
    arm = ToolArm(plan.poses[0], reach_mm=reach[-1] + 1.0, settle_cycles=1)
    walk = Walk(tmp_path / "walk.json", plan, BOARD, CAMERA)
    outcome, sent = await walk_with(brand, settings, walk, arm, mode, stop_after=COUNT)
    assert outcome.status == AT_ELSEWHERE == -2
    assert len(outcome.reached) == 1
    assert [struct.unpack(">I", f[:4])[0] for f in sent] == [header_word(SocketCommand.NEXT)]
    assert Walk(tmp_path / "walk.json", plan, BOARD, CAMERA).records == {}


async def test_the_daemons_walk_answers_job_0_and_next_after_it_is_refused(
        tmp_path: Path) -> None:
    """The running daemon's walk over a robot socket: its answers carry job id 0 (no job
    runs), a program that asked the first NEXT and went away leaves the walk to the next
    program on its address, a NEXT after the walk is REFUSED BAD_REQUEST as before the walk,
    and the first job after it is job 1. Before, the walk's answers counted their own job ids
    (1, 2, ...) and the next job was job 1 again."""
    brand, mode = "kuka", "eye-in-hand"
    settings = settings_for(brand)
    assert make_plan(tmp_path, mode, count=COUNT) == 0
    plan = load_plan(str(tmp_path / "plan.toml"))
    arm = new_arm(plan, seed=11)
    walk = Walk(tmp_path / "plan.walk.json", plan, BOARD, CAMERA)
    port = free_port()
    async with daemon_walking(brand, port, walk, arm, mode) as done:
        first = await Peer.dial(port)
        await first.request(1, SocketCommand.NEXT)
        target = await first.answer()
        assert (target.kind, target.status, target.job_id) == (AnswerKind.RESULT, Status.OK, 0)
        await first.close()
        async with ProgramTwin(settings, "127.0.0.1", port) as twin:
            outcome = await twin.walk(arm)
        assert outcome.status == Status.NOT_FOUND
        assert len(outcome.reached) == COUNT - 1
        await done
        robot = await Peer.dial(port)
        await robot.request(1, SocketCommand.NEXT)
        after = await robot.answer()
        assert (after.kind, after.status, after.job_id) == (
            AnswerKind.REFUSED, Status.BAD_REQUEST, 0)
        await robot.request(2, SocketCommand.LOCATE)  # the replay frames are used up: no image
        answers = [await robot.answer()]
        while answers[-1].kind is AnswerKind.CAPTURED:
            answers.append(await robot.answer())
        assert answers[-1].kind is AnswerKind.RESULT
        assert {a.job_id for a in answers} == {1}  # the first job, after the walk's answers
        await robot.close()
