"""A walked hand-eye calibration over UR RTDE: the real ur_rtde client (the link's child process)
against the mock UR controller (its own process), whose simulated robot program walks the plan
as robots/urscript would: NEXT for the first target, move (a simulated arm: reach limit, settle
cycles, noise on the pose it reports as ``actual_TCP_pose``), TRIGGER for the image, NEXT with
recipe 1 (register 15) for a target it cannot reach, until the answer is NOT_FOUND (walk complete). vgripd's side is
``WalkServer``: it only answers, the link reads the flange pose with each request, and the image
is rendered from the pose the arm really reached. The link is then dropped halfway (the robot
stops), and a new link and server resume the walk. Solved through the command: within
0.05 mm / 0.01 deg of the truth, the unreachable target listed.
"""

from __future__ import annotations

import asyncio
import json
import sys
import threading
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from drivers.links.ur_rtde import URRtdeLink, URRtdeOptions
from tests.conftest import lo, stop_task
from vgripd.__main__ import main
from vgripd.calib.handeye.plan import load_plan
from vgripd.calib.handeye.walk import SEEN, UNREACHABLE, Walk
from vgripd.geometry.transforms import pose_error
from vgripd.geometry.vendors import transform_from_vendor, vendor_from_transform
from vgripd.peer.jobcore import Command
from vgripd.service.links.handeye_walk import WalkServer
from vgripd.service.links.protocol import Trigger
from vgripd.sim.arm import ArmState, SimulatedArm
from vgripd.sim.ur_controller import BUSY_WAIT_S, URController
from vgripd.types import Status

# the rendered scene of the walk test (bare module names, as pytest imports them there)
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "unit" / "calib"))
import test_calib_boards  # noqa: E402
from test_calib_handeye_walk import (  # noqa: E402
    BOARD,
    CAMERA,
    image_at,
    make_plan,
    truth,
)

pytestmark = pytest.mark.timeout(240)
HOST = lo("127.0.5.61")
MODE = "eye-in-hand"
ZERO = (0.0,) * 6  # the walk's targets are absolute: pose_trans(target, zero) = target
SKIP_RECIPE = 1  # vgripd_handeye_walk's recipe for "the target given cannot be reached"


def robot_program(robot: URController, arm: SimulatedArm, stop_after: int | None
                  ) -> dict[str, Any]:
    """The robot side (blocking calls on the mock's pipe; run in a thread)."""
    seq = robot.start_program(int(Command.NEXT), taught_pose=ZERO, timeout_s=30.0)
    result = robot.program_result(seq, timeout_s=60.0)
    visited = 0
    while result["status"] == Status.OK:
        if stop_after is not None and visited == stop_after:
            return {"stopped": True, **result}
        T = transform_from_vendor("ur", result["target"])
        if arm.reachable(T):
            arm.move(T)
            while arm.step() is not ArmState.SETTLED:
                pass
            robot.set_tcp_pose(vendor_from_transform("ur", arm.reported_pose()))
            seq = robot.start_program(int(Command.TRIGGER), taught_pose=ZERO, timeout_s=30.0)
        else:  # the script's skip: next with VGRIPD_RECIPE = 1 (register 15)
            seq = robot.start_program(int(Command.NEXT), taught_pose=ZERO, timeout_s=30.0,
                                      recipe=SKIP_RECIPE)
        result = robot.program_result(seq, timeout_s=60.0)
        visited += 1
    return result


async def serve_walk(robot: URController, arm: SimulatedArm, walk_file: Path, plan_file: Path,
                     stop_after: int | None, nexts: list[int]) -> dict[str, Any]:
    """One run of the robot program against a new link and server; ``nexts`` gets the recipe
    of every NEXT request as the link delivered it."""
    walk = Walk(walk_file, load_plan(str(plan_file)), BOARD, CAMERA)

    async def grab() -> np.ndarray:
        return await asyncio.to_thread(image_at, MODE, arm.T_true.copy(), arm.moves)

    link = URRtdeLink("ur", URRtdeOptions(host=HOST))
    server = WalkServer(walk, link, grab, "ur")

    def on_trigger(trigger: Trigger) -> None:
        if trigger.command == Command.NEXT:
            nexts.append(trigger.recipe)
        server.on_trigger(trigger)

    await link.open(on_trigger)
    task = asyncio.get_running_loop().create_task(server.serve())
    try:
        result = await asyncio.to_thread(robot_program, robot, arm, stop_after)
        if not result.get("stopped"):
            await asyncio.wait_for(task, 30)
    finally:
        await stop_task(task)
        await link.close()
    return result


@pytest.fixture(autouse=True)
def sharp_texture(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(test_calib_boards, "PPM", 4.0)


async def test_walk_over_ur_rtde_resumes_skips_and_calibrates(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert make_plan(tmp_path, MODE) == 0
    plan = load_plan(str(tmp_path / "plan.toml"))
    reach = sorted(np.linalg.norm(T[:3, 3]) for T in plan.poses)
    arm = SimulatedArm(plan.poses[0], reach_mm=(reach[-1] + reach[-2]) / 2, settle_cycles=4,
                       noise_deg=0.001, noise_mm=0.005, rng=np.random.default_rng(7))
    walk_file = tmp_path / "walk.json"
    with URController(HOST) as robot:
        robot.set_tcp_pose(vendor_from_transform("ur", plan.poses[0]))
        nexts: list[int] = []
        first = await serve_walk(robot, arm, walk_file, tmp_path / "plan.toml", stop_after=5,
                                 nexts=nexts)
        assert first["stopped"]
        done = Walk(walk_file, plan, BOARD, CAMERA)
        assert len(done.records) == 5  # five targets visited, the record saved
        last = await serve_walk(robot, arm, walk_file, tmp_path / "plan.toml", stop_after=None,
                                nexts=nexts)
    assert last["status"] == Status.NOT_FOUND  # the walk complete
    assert last["offset"] is None
    final = Walk(walk_file, plan, BOARD, CAMERA)
    statuses = [r.status for _, r in sorted(final.records.items())]
    assert statuses.count(UNREACHABLE) == 1
    assert statuses.count(SEEN) == len(plan.poses) - 1
    assert arm.moves == len(plan.poses) - 1  # no target visited twice across the resume
    # each run's first NEXT asks (recipe 0), the one skip says so with register 15 = 1
    assert sorted(nexts) == [0, 0, SKIP_RECIPE]
    capsys.readouterr()
    out = tmp_path / "handeye.toml"
    assert main(["calibrate", "handeye", "--samples", str(walk_file), "--intrinsics",
                 str(tmp_path / "cell.toml"), "-o", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    mm, deg = pose_error(np.asarray(summary["matrix_mm"]), truth(MODE)[0])
    assert mm < 0.05, (mm, deg)
    assert deg < 0.01, (mm, deg)
    assert any("unreachable" in r["reason"] for r in summary["rejected"])


def test_walk_command_serves_the_plan_with_the_configs_camera_and_link(tmp_path: Path) -> None:
    """``vgripd calibrate handeye walk`` wired to the config's camera (a replay camera showing
    the board as seen from the start pose, the same image at every target) and its ur_rtde
    link: the robot program gets every target and the end of the walk; each target recorded
    with the board seen and the flange pose the link read."""
    host = lo("127.0.5.62")
    assert make_plan(tmp_path, "eye-to-hand", count=12) == 0  # a fixed camera: no flange pose
    plan = load_plan(str(tmp_path / "plan.toml"))
    images = tmp_path / "images"
    images.mkdir()
    _, T0 = truth("eye-to-hand")
    cv2.imwrite(str(images / "board.png"), image_at("eye-to-hand", T0, 0))
    cell = tmp_path / "cell.toml"
    text = cell.read_text(encoding="utf-8").replace(
        'type = "synthetic"', f'type = "replay"\nfolder = "{images}"\nglob = "*.png"\n'
                              'loop = true', 1)
    assert 'type = "replay"' in text
    cell.write_text(text + f'\n[[links]]\ntype = "ur_rtde"\nhost = "{host}"\n',
                    encoding="utf-8")
    arm = SimulatedArm(plan.poses[0], reach_mm=1e4)
    rc: list[int] = []
    with URController(host) as robot:
        robot.set_tcp_pose(vendor_from_transform("ur", plan.poses[0]))
        command = threading.Thread(target=lambda: rc.append(main([
            "calibrate", "handeye", "walk", "-c", str(cell), "--plan",
            str(tmp_path / "plan.toml")])))
        command.start()
        try:
            result = robot_program(robot, arm, None)
        finally:
            command.join(120)
    assert not command.is_alive()
    assert rc == [0]
    assert result["status"] == Status.NOT_FOUND
    walk = Walk(tmp_path / "plan.walk.json", plan, BOARD, CAMERA)
    assert sorted(walk.records) == list(range(12))
    assert {r.status for r in walk.records.values()} == {SEEN}
    reached = [r.T_base_flange for _, r in sorted(walk.records.items())]
    for T, T_plan in zip(reached, plan.poses, strict=True):  # read by the link, as reported
        assert pose_error(T, T_plan)[0] < 1e-6
    assert arm.moves == 12


def test_the_scripts_walk_skips_with_recipe_1_and_asks_with_recipe_0() -> None:
    """robots/urscript's ``vgripd_handeye_walk`` does what ``robot_program`` does: its first
    next goes with VGRIPD_RECIPE (register 15) 0, its skip with 1, and the jobs' recipe is
    given back at the end. Before, both went with the jobs' recipe (0 by default)."""
    text = (Path(__file__).resolve().parents[3] / "robots" / "urscript" / "vgripd.script"
            ).read_text()
    start = text.index("def vgripd_handeye_walk(")
    body = text[start:text.index("\nend\n", start)]
    lines = [line.split("#")[0].strip() for line in body.splitlines()]
    lines = [line for line in lines if line]
    asks = [k for k, line in enumerate(lines) if "vgripd_locate(3," in line]
    assert len(asks) == 2  # the first target, the skip
    assert lines[asks[0] - 1] == "VGRIPD_RECIPE = 0"
    assert lines[asks[1] - 1] == f"VGRIPD_RECIPE = {SKIP_RECIPE}"
    assert lines[asks[1] + 1] == "VGRIPD_RECIPE = 0"
    assert "local recipe = VGRIPD_RECIPE" in lines[:asks[0]]
    assert lines[-2:] == ["VGRIPD_RECIPE = recipe", "return status"]


async def test_an_image_request_asked_again_after_its_timeout_gets_the_same_answer(
        tmp_path: Path) -> None:
    """The first image request's answer is held until the robot program, its timeout run out,
    has asked again with a new sequence (the robot standing at target 0; the link answers BUSY
    while the first request runs, and the program asks again after its BUSY wait): the repeat
    gets the same answer (target 1) and records nothing, and target 1 is then recorded with its own
    pose. Before, the repeat was recorded as target 1 with target 0's pose and image, and
    answered target 2: target 1 never visited."""
    assert make_plan(tmp_path, MODE) == 0
    plan = load_plan(str(tmp_path / "plan.toml"))
    walk = Walk(tmp_path / "walk.json", plan, BOARD, CAMERA)
    triggers: list[Trigger] = []
    grabs: list[int] = []

    async def grab() -> np.ndarray:
        index = server.pending
        assert index is not None
        grabs.append(index)
        if len(grabs) == 1:  # held until the program asked again: the link answers it BUSY
            # while this request runs (polled: the mock's pipe is busy with the program)
            async with asyncio.timeout(60):
                while not link.refusals().get("BUSY"):  # noqa: ASYNC110 - no event to wait on
                    await asyncio.sleep(0.01)
        return await asyncio.to_thread(image_at, MODE, plan.poses[index], index)

    link = URRtdeLink("ur", URRtdeOptions(host=lo("127.0.5.67")))
    server = WalkServer(walk, link, grab, "ur")

    def on_trigger(trigger: Trigger) -> None:
        triggers.append(trigger)
        server.on_trigger(trigger)

    def at_target(robot: URController, index: int, timeout_s: float,
                  busy_wait_s: float = BUSY_WAIT_S) -> dict[str, Any]:
        robot.set_tcp_pose(vendor_from_transform("ur", plan.poses[index]))
        seq = robot.start_program(int(Command.TRIGGER), taught_pose=ZERO, timeout_s=timeout_s,
                                  attempts=10, busy_wait_s=busy_wait_s)
        return robot.program_result(seq, timeout_s=90.0)

    def is_target(result: dict[str, Any], index: int) -> bool:
        if result["status"] != Status.OK:
            return False
        mm, deg = pose_error(transform_from_vendor("ur", result["target"]), plan.poses[index])
        return bool(mm < 1e-3 and deg < 1e-3)

    with URController(lo("127.0.5.67")) as robot:
        robot.set_tcp_pose(vendor_from_transform("ur", plan.poses[0]))
        await link.open(on_trigger)
        task = asyncio.get_running_loop().create_task(server.serve())
        try:
            seq = await asyncio.to_thread(robot.start_program, int(Command.NEXT),
                                          taught_pose=ZERO, timeout_s=30.0)
            first = await asyncio.to_thread(robot.program_result, seq, 60.0)
            assert is_target(first, 0)
            # its timeout: 2 s; one BUSY wait long enough for the first image's work on a
            # busy machine
            again = await asyncio.to_thread(at_target, robot, 0, 2.0, 20.0)
            assert again["unanswered"] >= 1  # it asked again
            assert is_target(again, 1), again  # target 1 again, not target 2
            assert sorted(walk.records) == [0]
            assert server.pending == 1
            assert grabs == [0]
            on = await asyncio.to_thread(at_target, robot, 1, 30.0)
            assert is_target(on, 2), on
        finally:
            await stop_task(task)
            await link.close()
    assert grabs == [0, 1]
    final = Walk(tmp_path / "walk.json", plan, BOARD, CAMERA)
    assert sorted(final.records) == [0, 1]
    for index in (0, 1):
        mm, _ = pose_error(final.records[index].T_base_flange, plan.poses[index])
        assert mm < 1e-3
