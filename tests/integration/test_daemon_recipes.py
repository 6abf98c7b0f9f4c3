"""Recipes end to end (docs/recipes.md): the two-plate sample cell, the daemon in-process with
the synthetic camera rendering one plate, triggered over real TCP by the mock PLC and by mbpoll.

The right recipe finds its plate at the rendered pose; the other recipes do not (NOT_FOUND, never
a pose); an unknown recipe number is BAD_REQUEST without an image; a recipe not taught yet
answers NOT_CALIBRATED while the others run; the status API shows the active recipe.
"""

from __future__ import annotations

import asyncio
import json
import re
import tomllib
from pathlib import Path
from typing import Any

import aiohttp
import numpy as np
import pytest

from tests.conftest import REPO, lo, need_tool
from tests.integration.test_daemon import WAIT_S, Run, running
from vgripd.__main__ import main
from vgripd.cli.status import format_status
from vgripd.config import config_from_dict, load_config
from vgripd.geometry.transforms import pose_error
from vgripd.peer.registers import Reg
from vgripd.serialize import toml_from_dict
from vgripd.service.links.protocol import LinkState
from vgripd.sim.plc import MockPlc
from vgripd.types import Status
from vgripd.vision.scene import matrix_from_pose

SAMPLE = REPO / "config" / "samples" / "recipes.toml"
UNTAUGHT = {"name": "plate-c", "object": {"features": [
    {"name": f"c{i}", "kind": "circle", "diameter_mm": 10.0, "xyz_mm": xyz}
    for i, xyz in enumerate([[-50.0, -30.0, 0.0], [55.0, -20.0, 0.0], [0.0, 40.0, 0.0]])]}}


def sample_config(plate: int, worker: bool, **extra_recipes: Any) -> Any:
    """The sample cell with the plate of recipe ``plate`` in view, ephemeral ports."""
    data = tomllib.loads(SAMPLE.read_text())
    data["camera"].update(recipe=plate, seed=20 + plate, max_tilt_deg=2.0)
    data["links"][0]["port"] = 0
    data["status"] = {"port": 0}
    data["daemon"] = {"worker": worker}
    data["recipes"].update(extra_recipes)
    return config_from_dict(data, str(SAMPLE))


async def api_status(run: Run) -> dict[str, Any]:
    assert run.daemon.status_server is not None
    url = f"http://127.0.0.1:{run.daemon.status_server.port}/api/status"
    async with aiohttp.ClientSession() as http, http.get(url) as response:
        assert response.status == 200
        status: dict[str, Any] = await response.json()
        return status


@pytest.mark.parametrize(("plate", "worker"), [(1, False), (2, True)])
async def test_each_recipe_finds_its_own_plate_only(plate: int, worker: bool) -> None:
    config = sample_config(plate, worker, **{"3": UNTAUGHT})
    async with running(config) as run, MockPlc("127.0.0.1", run.port(), timeout_s=WAIT_S) as plc:
        status = await api_status(run)
        assert status["recipe"]["active"] is None
        assert [(r["number"], r["name"]) for r in status["recipe"]["recipes"]] == [
            (0, "default"), (1, "plate-a"), (2, "plate-b"), (3, "plate-c")]
        assert status["recipe"]["recipes"][3]["problem"]  # not taught
        seen = []
        for n, recipe in enumerate((plate, 3 - plate, 0, 3, plate), start=1):
            answer = await plc.cycle(recipe)
            pair, record = await run.job_done(n)
            assert (record.recipe, record.result.recipe) == (recipe, recipe)
            seen.append((recipe, answer.status))
            if recipe == plate:
                assert answer.status is Status.OK, record.result.message
                assert pair is not None
                assert record.result.T_base_obj is not None
                err_mm, err_deg = pose_error(record.result.T_base_obj, pair.truth["T_base_obj"])
                assert err_mm < 0.1
                assert err_deg < 0.1
                # The offset is against this recipe's own taught reference.
                ref = config.for_recipe(recipe).reference.T_base_obj
                assert ref is not None
                np.testing.assert_allclose(
                    record.result.offset,
                    record.result.T_base_obj @ np.linalg.inv(matrix_from_pose(ref)), atol=1e-9)
            elif recipe == 3:
                assert answer.status is Status.NOT_CALIBRATED
                assert "recipe 3 (plate-c)" in record.result.message
            else:  # another plate's recipe on this plate: never a pose
                assert answer.status is Status.NOT_FOUND, record.result.message
                assert answer.values == ()
            status = await api_status(run)
            assert (status["recipe"]["active"], status["last_job"]["recipe"]) == (recipe, recipe)
            assert status["recipe"]["active_name"] == config.recipe_name(recipe)
        assert [s for r, s in seen if r == plate] == [Status.OK, Status.OK]
        text = format_status(await api_status(run))  # what `vgripd status` prints
        assert (f"recipe {plate} {config.recipe_name(plate)} (configured: 0 default, 1 plate-a, "
                "2 plate-b, 3 plate-c NOT CALIBRATED)") in text
        assert run.daemon.status_line().endswith(f"; recipe {plate} ({config.recipe_name(plate)})")


async def test_web_test_trigger_takes_a_recipe() -> None:
    token = "t" * 20
    data = tomllib.loads(SAMPLE.read_text())
    data["links"][0]["port"] = 0
    data.update(status={"port": 0, "token": token, "allow_trigger": True},
                daemon={"worker": False})
    async with running(config_from_dict(data)) as run, aiohttp.ClientSession() as http:
        assert run.daemon.status_server is not None
        url = f"http://127.0.0.1:{run.daemon.status_server.port}/api/trigger"
        auth = {"Authorization": f"Bearer {token}"}
        for query, status in (("?recipe=2", "OK"), ("?recipe=1", "NOT_FOUND"),
                              ("", "NOT_FOUND"), ("?recipe=5", "BAD_REQUEST")):
            async with http.post(url + query, headers=auth) as resp:
                assert resp.status == 200
                result = await resp.json()
            assert (result["status"], result["recipe"]) == (status, int(query[8:] or 0))
        async with http.post(url + "?recipe=-1", headers=auth) as resp:
            assert resp.status == 400
            assert "a recipe number is 0 .. 65535" in await resp.text()


async def test_unknown_recipe_is_bad_request_without_an_image() -> None:
    config = sample_config(1, worker=False)
    async with running(config) as run, MockPlc("127.0.0.1", run.port(), timeout_s=WAIT_S) as plc:
        grabs = 0
        grab = run.daemon.rooms.cameras.camera.grab

        async def counting_grab(timeout_s: float, *hints: Any, **named: Any) -> Any:
            nonlocal grabs
            grabs += 1
            return await grab(timeout_s, *hints, **named)

        run.daemon.rooms.cameras.camera.grab = counting_grab  # type: ignore[method-assign]
        answer = await plc.cycle(7)
        pair, record = await run.job_done(1)
        assert answer.status is Status.BAD_REQUEST
        assert not answer.rejected
        assert not answer.captured_seen
        assert answer.values == ()
        assert pair is None
        assert grabs == 0
        assert record.result.message == ("recipe 7 is not configured (configured: 0, 1, 2; "
                                         "0 = the top-level config)")
        assert run.daemon.snapshot()["counters"] == {"BAD_REQUEST": 1}
        assert run.daemon.rooms.jobs.active_recipe is None  # an unknown number selects nothing
        answer = await plc.cycle(1)  # the daemon goes on
        assert answer.status is Status.OK
        assert grabs == 1


async def mbpoll(port: int, *args: str) -> dict[int, int]:
    """Run mbpoll once (0-based references); {reference: value} of what it printed."""
    proc = await asyncio.create_subprocess_exec(
        need_tool("mbpoll"), "-m", "tcp", "-a", "1", "-0", "-1", "-o", "2", "-p", str(port),
        *args, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
    out, err = await proc.communicate()
    assert proc.returncode == 0, out.decode() + err.decode()
    return {int(m[1]): int(m[2]) for m in re.finditer(r"^\[(\d+)\]:\s+(-?\d+)", out.decode(), re.M)}


async def test_mbpoll_selects_recipes_by_the_recipe_register() -> None:
    """mbpoll (Debian's Modbus master) writes CMD, REQ_SEQ and RECIPE in one request and reads
    ACK_SEQ and STATUS back: recipe 2 finds plate B, 9 is BAD_REQUEST, 1 finds nothing."""
    config = sample_config(2, worker=False)
    async with running(config) as run:
        port = run.port()
        for seq, recipe, expected in ((41, 2, Status.OK), (42, 9, Status.BAD_REQUEST),
                                      (43, 1, Status.NOT_FOUND)):
            await mbpoll(port, "-t", "4", "-r", str(Reg.CMD), "127.0.0.1", "1", str(seq),
                         str(recipe))
            await run.daemon.wait_for(lambda s=seq: run.daemon.rooms.jobs.last_job is not None
                                      and run.daemon.rooms.jobs.last_job.seq == s, WAIT_S)
            head = await mbpoll(port, "-t", "4", "-r", str(Reg.RECIPE), "127.0.0.1")
            assert head == {Reg.RECIPE: recipe}
            answer = await mbpoll(port, "-t", "4", "-r", str(Reg.ACK_SEQ), "-c", "2", "127.0.0.1")
            assert answer == {Reg.ACK_SEQ: seq, Reg.STATUS: int(expected)}


def test_check_validates_every_recipe(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = tomllib.loads(SAMPLE.read_text())
    data["links"][0]["port"] = 0
    good = tmp_path / "good.toml"
    good.write_text(toml_from_dict(data))
    assert main(["check", "-c", str(good)]) == 0
    assert "recipe 1 (plate-a), recipe 2 (plate-b)" in capsys.readouterr().out
    data["recipes"]["3"] = UNTAUGHT
    bad = tmp_path / "bad.toml"
    bad.write_text(toml_from_dict(data))
    assert main(["check", "-c", str(bad)]) == 78
    err = capsys.readouterr().err
    assert "recipe 3 (plate-c): not calibrated" in err
    assert "recipe 1" not in err
    assert "recipe 2" not in err
    # A recipe whose plate would not be seen: the scene check names it.
    data["recipes"]["3"] = {"name": "far", "reference": {
        "T_base_obj": {"translation_mm": [1600.0, 100.0, 10.0]}}}
    far = tmp_path / "far.toml"
    far.write_text(toml_from_dict(data))
    assert main(["check", "-c", str(far)]) == 78
    err = capsys.readouterr().err
    assert "recipes.3.reference" in err
    assert "recipe 3 (far)" in err


def test_teach_recipe_writes_its_reference(tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    """``teach --recipe 2`` measures plate B (the synthetic camera renders it at a fixed pose)
    and writes [recipes.2.reference]; included, recipe 2 then runs against it."""
    data = tomllib.loads(SAMPLE.read_text())
    truth = {"translation_mm": [597.0, 104.0, 11.0], "rotvec_rad": [0.0, 0.01, -0.06]}
    data["camera"].update(recipe=2, pose=truth)
    del data["recipes"]["2"]["reference"]  # not taught yet
    cell = tmp_path / "cell.toml"
    cell.write_text(toml_from_dict(data))
    assert main(["teach", "-c", str(cell), "--recipe", "2", "--shots", "2", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    out = tmp_path / "reference-recipe-2.toml"
    assert (summary["output"], summary["recipe"], summary["object"]) == (str(out), 2, "plate_b")
    written = tomllib.loads(out.read_text())
    assert set(written) == {"about", "recipes"}
    cell.write_text('include = ["reference-recipe-2.toml"]\n' + toml_from_dict(data))
    taught = load_config(cell).for_recipe(2).reference.T_base_obj
    assert taught is not None
    assert pose_error(matrix_from_pose(taught),
                      matrix_from_pose(config_from_dict({"reference": {"T_base_obj": truth}})
                                       .reference.T_base_obj)) < (0.2, 0.12)
    assert main(["teach", "-c", str(cell), "--recipe", "5"]) == 2
    assert "recipe 5 is not configured" in capsys.readouterr().err


def test_recorded_job_keeps_its_recipe_and_replays_with_it(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The recorder writes the job's recipe in result.json; ``vgripd replay`` of the job
    folder runs that recipe's pipeline unless ``--recipe`` says otherwise."""
    data = tomllib.loads(SAMPLE.read_text())
    data["links"][0]["port"] = 0
    data.update(status={"port": 0}, daemon={"worker": False},
                record={"enabled": True, "folder": str(tmp_path / "rec")})

    async def one_job() -> Status:
        async with running(config_from_dict(data)) as run, \
                MockPlc("127.0.0.1", run.port(), timeout_s=WAIT_S) as plc:
            return (await plc.cycle(2)).status

    assert asyncio.run(one_job()) is Status.OK  # the sample's camera shows plate B
    (job,) = sorted((tmp_path / "rec").iterdir())
    assert json.loads((job / "result.json").read_text())["recipe"] == 2
    capsys.readouterr()
    assert main(["replay", "-c", str(job / "config.toml"), str(job)]) == 0
    line = json.loads(capsys.readouterr().out.splitlines()[0])
    assert (line["recipe"], line["status"]) == (2, "OK")
    assert main(["replay", "-c", str(job / "config.toml"), str(job), "--recipe", "1"]) == 0
    line = json.loads(capsys.readouterr().out.splitlines()[0])
    assert (line["recipe"], line["status"]) == (1, "NOT_FOUND")
    assert main(["replay", "-c", str(job / "config.toml"), str(job), "--recipe", "4"]) == 78


def test_locate_runs_the_recipe_asked_for(tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    import cv2

    from vgripd.config import DriverSection
    from vgripd.registry import CAMERAS, load_class, validate_options

    cls = load_class(CAMERAS, "camera", "synthetic")
    section = DriverSection.model_validate({"type": "synthetic", "recipe": 2, "seed": 5})
    camera = cls(validate_options(cls, section, "camera"), load_config(SAMPLE))

    async def grab() -> Any:
        await camera.open()
        try:
            return await camera.grab(WAIT_S)
        finally:
            await camera.close()

    pair = asyncio.run(grab())
    images = [str(tmp_path / f"{side}.png") for side in ("left", "right")]
    for path, image in zip(images, (pair.left, pair.right), strict=True):
        cv2.imwrite(path, image)
    for recipe, code, status in ((2, 0, "OK"), (1, 1, "NOT_FOUND")):
        assert main(["locate", "-c", str(SAMPLE), *images, "--recipe", str(recipe),
                     "--json"]) == code
        line = json.loads(capsys.readouterr().out)
        assert (line["recipe"], line["status"]) == (recipe, status)
    assert main(["locate", "-c", str(SAMPLE), *images, "--recipe", "9"]) == 78


@pytest.mark.timeout(90)
async def test_ur_robot_program_selects_the_recipe() -> None:
    """The URScript twin with VGRIPD_RECIPE = 2, 1, 5 against the daemon (real ur_rtde client,
    output_int_register 15): plate B found, the other plate's recipe NOT_FOUND, 5 unknown."""
    from vgripd.sim.ur_controller import URController

    data = tomllib.loads(SAMPLE.read_text())
    with URController(lo("127.0.7.20")) as robot:
        data.update(links=[{"type": "ur_rtde", "host": robot.host}], output={"vendor": "ur"},
                    status={"port": 0}, daemon={"worker": False})
        async with running(config_from_dict(data)) as run:
            await run.daemon.wait_for(
                lambda: all(link.health().state is LinkState.UP
                            for link in run.daemon.rooms.links.links.values()), WAIT_S)
            for n, (recipe, status) in enumerate(((2, Status.OK), (1, Status.NOT_FOUND),
                                                  (5, Status.BAD_REQUEST)), start=1):
                seq = robot.start_program(1, taught_pose=(0.3, 0.1, 0.2, 0.0, 3.1, 0.05),
                                          recipe=recipe)
                result = await asyncio.to_thread(robot.program_result, seq)
                _, record = await run.job_done(n)
                assert record.recipe == recipe
                assert record.result.status is status
                assert result["status"] == int(status)
                assert (result["offset"] is not None) == (status is Status.OK)
