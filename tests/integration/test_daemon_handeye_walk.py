"""The walked hand-eye calibration served by the running daemon ("from the browser
too"): started over the web API with the token, walked by the mock UR controller's simulated
robot program through the real ur_rtde client of the daemon's ``ur_rtde`` link, the images taken
by the daemon's own camera (a replay folder read in the worker process, the frames rendered
from the poses the simulated arm reaches), a PLC job on the Modbus link answered BUSY
meanwhile, stopped and resumed, solved (refused with too few samples, writing nothing; then
within tolerance), accepted into the config's hand-eye include and applied by the reload.
Headless Chromium drives the two pages: the plan page's dry run (poses in the robot's
convention, the drawing, the flange path) and save, and the walk page showing each target as
it is recorded.
"""

from __future__ import annotations

import asyncio
import json
import sys
import threading
import tomllib
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import aiohttp
import cv2
import numpy as np
import pytest

from tests.conftest import lo
from tests.drivers.links.test_ur_rtde_handeye_walk import robot_program
from tests.integration.test_daemon import Plc
from tests.integration.test_web import _chromium, _until
from tests.integration.test_web_reload import TOKEN, post, running_file
from tests.unit.vision.test_pipeline import render_aruco_scene
from vgripd.__main__ import main
from vgripd.calib.files import pose_table
from vgripd.calib.handeye.plan import load_plan
from vgripd.calib.handeye.walk import NOT_SEEN, SEEN, UNREACHABLE, Walk
from vgripd.cli import calibrate_handeye_running
from vgripd.cli.status import format_status
from vgripd.config import load_config
from vgripd.geometry.fingerprint import camera_about, hand_eye_fingerprint, intrinsics_table
from vgripd.geometry.transforms import make_transform, matrix_from_rotvec, pose_error
from vgripd.geometry.vendors import vendor_from_transform
from vgripd.peer.registers import Reg
from vgripd.serialize import toml_from_dict
from vgripd.sim.arm import SimulatedArm
from vgripd.sim.ur_controller import URController
from vgripd.types import Status
from vgripd.vision.scene import matrix_from_pose

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "unit" / "calib"))
import test_calib_boards  # noqa: E402
from test_calib_handeye_walk import (  # noqa: E402
    BOARD,
    CAMERA,
    DISTANCE,
    ROUGH,
    image_at,
    make_plan,
    truth,
)

pytestmark = [pytest.mark.timeout(300), pytest.mark.slow(minutes=2)]
MODE = "eye-to-hand"  # a fixed camera: the replay frames need no flange pose for the check
WAIT_S = 120.0
#: Where the ArUco plate lies in the camera frame in replay frame 0 (the reload's check runs
#: the first frames through the pipeline and needs the object found on one).
T_CAM_OBJ = make_transform(matrix_from_rotvec([np.pi, 0.0, 0.0]), [0.0, 0.0, 600.0])
#: An ArUco plate: the object of a cell whose walk tests need no job to find it.
PLATE = {"name": "plate", "features": [
    {"name": f"a{i}", "kind": "aruco", "marker_id": i, "size_mm": 30.0, "xyz_mm": list(p)}
    for i, p in enumerate([(-60, -40, 0), (55, -45, 0), (65, 40, 0), (-50, 50, 0)])]}


@pytest.fixture(autouse=True)
def sharp_texture(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(test_calib_boards, "PPM", 4.0)


def write_walk_cell(folder: Path, host: str) -> tuple[Path, SimulatedArm, list[int]]:
    """``vgripd.toml`` (replay camera, links ur_rtde then modbus_server, web view with the
    token and config edits) including ``handeye.toml`` (the rough hand-eye, fingerprinted),
    ``plan.toml`` beside it, and the replay frames: frame 0 the ArUco plate (the board is not
    in it: the first target taken is ``not_seen``), then the board from each later reachable
    target, in the order the robot visits them. Returns the config, the arm (the farthest
    target out of its reach) and the reachable targets."""
    assert make_plan(folder, MODE) == 0
    plan = load_plan(str(folder / "plan.toml"))
    reach = sorted(np.linalg.norm(T[:3, 3]) for T in plan.poses)
    arm = SimulatedArm(plan.poses[0], reach_mm=(reach[-1] + reach[-2]) / 2, settle_cycles=2)
    reachable = [k for k, T in enumerate(plan.poses) if arm.reachable(T)]
    X, _ = truth(MODE)
    left = intrinsics_table(CAMERA)
    (folder / "handeye.toml").write_text(toml_from_dict({
        "calibration": {"hand_eye": {"mounting": "fixed",
                                     "T_base_camera": pose_table(X @ ROUGH)}},
        "about": camera_about({"left": left})}), encoding="utf-8")
    frames = folder / "frames"
    frames.mkdir()
    # the reference taught with the rough hand-eye, in its own include (as vgripd teach writes)
    (folder / "reference.toml").write_text(toml_from_dict({
        "reference": {"T_base_obj": pose_table(X @ T_CAM_OBJ)},
        "about": {**camera_about({"left": left}), "hand_eye": hand_eye_fingerprint(
            {"hand_eye": {"mounting": "fixed", "T_base_camera": pose_table(X @ ROUGH)}})}}),
        encoding="utf-8")
    main = folder / "vgripd.toml"
    main.write_text(toml_from_dict({
        "include": ["handeye.toml", "reference.toml"],
        "camera": {"type": "replay", "folder": str(frames), "glob": "*.png", "loop": True},
        "output": {"vendor": "ur"},
        "calibration": {"left": left},
        "object": PLATE,
        "limits": {"max_translation_mm": 500.0, "max_rotation_deg": 45.0},
        "links": [{"type": "ur_rtde", "host": host},
                  {"type": "modbus_server", "host": "127.0.0.1", "port": 0}],
        "status": {"port": 0, "token": TOKEN, "allow_config_edit": True},
    }), encoding="utf-8")
    cv2.imwrite(str(frames / "00.png"), render_aruco_scene(load_config(main), T_CAM_OBJ))
    for n, k in enumerate(reachable[1:], start=1):
        cv2.imwrite(str(frames / f"{n:02d}.png"), image_at(MODE, plan.poses[k], seed=k))
    return main, arm, reachable


async def get(session: aiohttp.ClientSession, url: str) -> Any:
    async with session.get(url) as resp:
        assert resp.status == 200, await resp.text()
        return await resp.json()


async def test_walk_in_the_running_daemon_busy_resumed_solved_and_accepted(
        tmp_path: Path) -> None:
    host = lo("127.0.5.63")
    main, arm, reachable = write_walk_cell(tmp_path, host)
    plan = load_plan(str(tmp_path / "plan.toml"))
    n = len(plan.poses)
    solved = tmp_path / "plan.handeye.toml"
    with URController(host) as robot:
        robot.set_tcp_pose(vendor_from_transform("ur", plan.poses[0]))
        async with running_file(main) as run, Plc(run.port(1)) as plc, \
                aiohttp.ClientSession() as s:
            assert run.daemon.status_server is not None
            base = f"http://127.0.0.1:{run.daemon.status_server.port}/api/handeye"
            start = {"plan": "plan.toml", "link": 0}

            # An action: without the token nothing starts; a plan outside the folder refused.
            code, _ = await post(s, f"{base}/walk/start", start, headers={})
            assert code == 403
            code, out = await post(s, f"{base}/walk/start", {"plan": "../plan.toml", "link": 0})
            assert code == 409
            assert "inside" in out["refused"]
            code, out = await post(s, f"{base}/walk/start", {"plan": "plan.toml", "link": 5})
            assert code == 409
            assert (await get(s, base))["walk"]["state"] == "idle"

            code, out = await post(s, f"{base}/walk/start", start)
            assert code == 200, out
            assert out["state"] == "walking"
            assert out["link"] == "ur_rtde"
            first = await asyncio.to_thread(robot_program, robot, arm, 2)
            assert first["stopped"]  # the robot program stopped after two targets

            # An ordinary job from the PLC during the walk: BUSY, no image taken.
            await plc.trigger(1)
            words = await plc.result(1)
            assert words[Reg.STATUS] == Status.BUSY
            status = await get(s, base.replace("/handeye", "/status"))
            walk = status["walk"]
            assert walk["state"] == "walking"
            assert walk["seen"] + walk["not_seen"] + walk["unreachable"] == 2
            assert walk["index"] == 2
            assert run.daemon.rooms.jobs.counters["BUSY"] == 1
            assert "hand-eye walk walking on ur_rtde" in format_status(status)  # vgripd status

            # Stopped: the record stays; too few samples to solve: refused, nothing written.
            code, out = await post(s, f"{base}/walk/stop")
            assert code == 200
            assert out["state"] == "stopped"
            code, out = await post(s, f"{base}/solve")
            assert code == 422, out
            assert not out["solution"]["ok"]
            assert "sample" in out["solution"]["reason"], out["solution"]["reason"]
            assert not solved.exists()
            code, out = await post(s, f"{base}/accept")
            assert code == 409  # nothing solved to accept

            # Started again: resumed at target 2, walked to the end (NOT_FOUND).
            code, out = await post(s, f"{base}/walk/start", start)
            assert code == 200, out
            assert out["index"] == 2
            last = await asyncio.to_thread(robot_program, robot, arm, None)
            assert last["status"] == Status.NOT_FOUND
            await run.daemon.wait_for(lambda: run.daemon.rooms.walks.state.value == "complete",
                                      WAIT_S)
            record = Walk(tmp_path / "plan.walk.json", plan, BOARD, CAMERA)
            statuses = [r.status for _, r in sorted(record.records.items())]
            assert len(statuses) == n  # every target recorded
            assert statuses.count(UNREACHABLE) == n - len(reachable) == 1
            assert statuses[reachable[0]] == NOT_SEEN  # frame 0 shows the plate, not the board
            assert statuses.count(SEEN) == len(reachable) - 1
            assert arm.moves == len(reachable)  # no target visited twice across the resume

            # Solved in a child process, then accepted: written into the include, reloaded.
            code, out = await post(s, f"{base}/solve")
            assert code == 200, out
            assert out["solution"]["ok"]
            assert solved.exists()
            about = tomllib.loads(solved.read_text())["about"]
            assert about["plan"]["condition"]["condition"] > 0
            assert about["camera_model"] == camera_about(
                {"left": intrinsics_table(CAMERA)})["camera_model"]
            # The taught reference was measured with the rough hand-eye: accepting is refused,
            # naming it, until told to set it aside; then jobs end NOT_CALIBRATED until taught.
            code, out = await post(s, f"{base}/accept")
            assert code == 409, out
            assert out["stale_references"] == ["reference.toml"]
            assert "set the taught references aside" in out["refused"]
            assert "T_base_obj" in (tmp_path / "reference.toml").read_text()
            code, out = await post(s, f"{base}/accept", {"set_aside_references": True})
            assert code == 200, out
            assert out["applied"], out
            assert out["set_aside"] == ["reference.toml"]
            aside = tomllib.loads((tmp_path / "reference.toml").read_text())
            assert "T_base_obj" not in aside.get("reference", {})
            assert "hand_eye" not in aside["about"]
            assert (tmp_path / "reference.toml.1").exists()  # its backup
            await plc.trigger(2)
            assert (await plc.result(2))[Reg.STATUS] == Status.NOT_CALIBRATED
            assert any(d.startswith("calibration.hand_eye.T_base_camera") for d in out["diff"])
            assert (tmp_path / "handeye.toml.1").exists()  # the backup
            he = run.daemon.config.calibration.hand_eye
            mm, deg = pose_error(matrix_from_pose(he.T_base_camera), truth(MODE)[0])
            assert mm < 0.05, (mm, deg)
            assert deg < 0.01, (mm, deg)
            included = tomllib.loads((tmp_path / "handeye.toml").read_text())
            assert included["about"]["plan"]["targets"] == n


async def test_chromium_plans_dry_runs_saves_and_watches_the_walk(tmp_path: Path) -> None:
    host = lo("127.0.5.64")
    main, arm, reachable = write_walk_cell(tmp_path, host)
    plan = load_plan(str(tmp_path / "plan.toml"))
    _, T0 = truth(MODE)
    around = " ".join(f"{v:.9f}" for v in vendor_from_transform("ur", T0))
    text = "(id) => document.getElementById(id)?.textContent ?? ''"
    with URController(host) as robot:
        robot.set_tcp_pose(vendor_from_transform("ur", plan.poses[0]))
        async with running_file(main) as run:
            assert run.daemon.status_server is not None
            base = f"http://127.0.0.1:{run.daemon.status_server.port}"
            async with _chromium(tmp_path, base + "/handeye/plan") as evaluate:
                assert await _until(evaluate, f"({text})('vendor') === 'ur'")

                def fill(values: dict[str, str]) -> str:
                    sets = "".join(f"document.getElementById({json.dumps(k)}).value = "
                                   f"{json.dumps(v)};" for k, v in values.items())
                    return f"(() => {{ {sets} return true; }})()"

                await evaluate(fill({"token": TOKEN, "mode": MODE, "board": BOARD.spec,
                                     "around": around, "travel": "250", "tilt": "3",
                                     "count": "16", "distance": str(DISTANCE),
                                     "board-offset": "0 0 30", "save": "web.toml"}))
                await evaluate("document.getElementById('btn-save').click(), true")
                refused = await _until(evaluate, f"({text})('plan-result').startsWith("
                                                 f"'REFUSED') && ({text})('plan-result')")
                assert "rotations are too small" in refused, refused
                assert not (tmp_path / "web.toml").exists()

                await evaluate(fill({"tilt": "30"}))
                await evaluate("document.getElementById('btn-dry').click(), true")
                dry = await _until(evaluate, f"({text})('plan-result').startsWith('PLAN') && "
                                             f"({text})('plan-result')")
                assert "16 poses" in dry, dry
                assert "dry run" in dry, dry
                rows = await evaluate("[...document.querySelectorAll('#plan-poses tbody tr')]"
                                      ".map((r) => r.children[1].textContent)")
                assert len(rows) == 16
                first = [float(v) for v in rows[0].split()]
                assert len(first) == 6  # x y z m, rx ry rz rad: the robot's convention
                assert np.allclose(first, vendor_from_transform("ur", plan.poses[0]), atol=1e-3)
                assert await _until(evaluate, """(() => {
                    const img = document.getElementById('plan-drawing');
                    return img && !img.hidden && img.complete && img.naturalWidth > 0;
                })()""")
                assert await evaluate("document.querySelectorAll('#plan-path circle').length") \
                    == 32  # each pose in the top and the side view
                assert not (tmp_path / "web.toml").exists()  # a dry run writes nothing
                await evaluate("document.getElementById('btn-save').click(), true")
                assert await _until(evaluate, f"({text})('plan-result').includes('saved as "
                                              f"web.toml')")
                assert load_plan(str(tmp_path / "web.toml")).poses

            # The walk page (a browser of its own: no navigation racing the evaluations):
            # started with the token, each target shown as it is recorded.
            (tmp_path / "walkpage").mkdir()
            async with _chromium(tmp_path / "walkpage", base + "/handeye/walk") as evaluate:
                assert await _until(evaluate, "document.getElementById('link')?.options.length "
                                              "=== 2")
                await evaluate(fill({"token": TOKEN, "plan": "plan.toml", "link": "0"}))
                await evaluate("document.getElementById('btn-start').click(), true")
                assert await _until(evaluate, f"({text})('walk-state').startsWith("
                                              f"'WALK WALKING')")
                result = await asyncio.to_thread(robot_program, robot, arm, None)
                assert result["status"] == Status.NOT_FOUND
                # shown from the page's event stream (the page fetched nothing since the start)
                done = await _until(evaluate, f"({text})('walk-state').startsWith("
                                              f"'WALK COMPLETE') && [...document."
                                              f"querySelectorAll('#walk-targets tbody tr')]"
                                              f".map((r) => r.className)")
                assert len(done) == len(plan.poses)
                assert done.count("unreachable") == 1
                assert done.count("not_seen") == 1
                assert done.count("seen") == len(reachable) - 1
                counts = await evaluate(f"({text})('walk-counts')")
                assert f"seen {len(reachable) - 1}, not seen 1, unreachable 1" in counts


async def test_a_walk_stopped_by_the_daemons_stop_resumes_through_the_command(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """The daemon stops in the middle of a walk: the record stays. After the restart,
    ``vgripd calibrate handeye walk --running URL`` asks the daemon to walk again: it resumes
    at the first target without a record, the command prints every target as it is recorded
    and returns with the walk complete."""
    host = lo("127.0.5.65")
    main_config, arm, reachable = write_walk_cell(tmp_path, host)
    plan = load_plan(str(tmp_path / "plan.toml"))
    monkeypatch.setenv("VGRIPD_TOKEN", TOKEN)
    with URController(host) as robot:
        robot.set_tcp_pose(vendor_from_transform("ur", plan.poses[0]))
        async with running_file(main_config) as run:
            run.daemon.rooms.walks.start(main_config, "plan.toml", 0)
            first = await asyncio.to_thread(robot_program, robot, arm, 2)
            assert first["stopped"]
            walks = run.daemon.rooms.walks
        assert walks.state.value == "stopped"
        assert "daemon" in walks.message
        assert len(Walk(tmp_path / "plan.walk.json", plan, BOARD, CAMERA).records) == 2
        capsys.readouterr()
        async with running_file(main_config) as run:
            assert run.daemon.status_server is not None
            url = f"http://127.0.0.1:{run.daemon.status_server.port}"
            command = asyncio.ensure_future(asyncio.to_thread(main, [
                "calibrate", "handeye", "walk", "--running", url, "--plan", "plan.toml",
                "--link", "0"]))
            try:
                await run.daemon.wait_for(lambda: run.daemon.rooms.walks.walking, WAIT_S)
                result = await asyncio.to_thread(robot_program, robot, arm, None)
                assert await command == 0
            finally:
                await asyncio.gather(command, return_exceptions=True)
    assert result["status"] == Status.NOT_FOUND
    out = capsys.readouterr().out
    assert f"{len(plan.poses)} targets, from target 2" in out
    lines = [ln for ln in out.splitlines() if ln.startswith("  target ")]
    assert [int(ln.split()[1].rstrip(":")) for ln in lines] == list(range(2, len(plan.poses)))
    assert "walk complete: seen" in out
    assert arm.moves == len(reachable)  # no target visited twice across the restart


async def test_ctrl_c_of_the_command_prints_every_target_and_says_who_stopped(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """``vgripd calibrate handeye walk --running`` stopped with Ctrl-C while it waits between
    two polls: the targets recorded since its last poll are printed too (from the stop's
    answer), and the walk's message says the command's Ctrl-C stopped it. Before, those
    targets were never printed and the message said "stopped from the web view"."""
    host = lo("127.0.5.66")
    main_config, arm, _ = write_walk_cell(tmp_path, host)
    plan = load_plan(str(tmp_path / "plan.toml"))
    monkeypatch.setenv("VGRIPD_TOKEN", TOKEN)
    polled, walked = threading.Event(), threading.Event()

    def sleep(_s: float) -> None:  # the command's wait between polls, ended by Ctrl-C
        polled.set()
        assert walked.wait(WAIT_S)
        raise KeyboardInterrupt

    monkeypatch.setattr(calibrate_handeye_running, "time", SimpleNamespace(sleep=sleep))
    with URController(host) as robot:
        robot.set_tcp_pose(vendor_from_transform("ur", plan.poses[0]))
        async with running_file(main_config) as run, aiohttp.ClientSession() as s:
            assert run.daemon.status_server is not None
            url = f"http://127.0.0.1:{run.daemon.status_server.port}"
            code, text = await post(s, f"{url}/api/handeye/walk/stop?by=nobody", {})
            assert code == 400
            assert "by='nobody'" in text
            command = asyncio.ensure_future(asyncio.to_thread(main, [
                "calibrate", "handeye", "walk", "--running", url, "--plan", "plan.toml"]))
            try:
                assert await asyncio.to_thread(polled.wait, WAIT_S)  # polled: no target yet
                first = await asyncio.to_thread(robot_program, robot, arm, 3)
                assert first["stopped"]
                walked.set()
                assert await command == 1  # stopped, not complete
            finally:
                walked.set()
                await asyncio.gather(command, return_exceptions=True)
            walks = run.daemon.rooms.walks
            assert walks.state.value == "stopped"
            assert "Ctrl-C of vgripd calibrate handeye walk --running" in walks.message
    out = capsys.readouterr().out
    lines = [ln for ln in out.splitlines() if ln.startswith("  target ")]
    assert [int(ln.split()[1].rstrip(":")) for ln in lines] == [0, 1, 2]
    assert "walk stopped: " in out
    assert "Ctrl-C" in out
    assert "web view" not in out
