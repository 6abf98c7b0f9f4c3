"""Several views per job (``vision.views``) through the daemon: one robot-mounted camera moved
through 2-4 poses around config/samples/two_rigs_frame.toml's 1.5 m frame (each view sees one
face of it, never the whole), the synthetic camera rendering each view from its flange pose in
the worker process, the Modbus/TCP server link, and a real pymodbus client (the mock PLC) and
mbpoll as the robot's PLC.

The view poses are the sample's four camera poses seen through a hand-eye transform, so the
N views are the sample's cell taken one image at a time by one camera. Checked: the pose over
all views against the renderer's truth, and every fault of the sequence (a view out of order,
repeated, a TRIGGER in the middle, the wait for the next view running out, a view without a
flange pose) ends the job with its documented status and never a pose.
"""

from __future__ import annotations

import asyncio
import copy
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.conftest import REPO, lo
from tests.integration.test_daemon import WAIT_S, running
from tests.integration.test_daemon_recipes import mbpoll
from vgripd.__main__ import main
from vgripd.config import config_from_dict, read_config_data
from vgripd.geometry.transforms import (
    invert_transform,
    make_transform,
    matrix_from_rotvec,
    pose_error,
    rotvec_from_matrix,
)
from vgripd.peer.jobcore import Command, HandshakeState, capture_word
from vgripd.peer.registers import Reg
from vgripd.serialize import toml_from_dict
from vgripd.service.links.protocol import LinkState
from vgripd.sim.plc import MockPlc
from vgripd.sim.robot_modbus import UR_FIRST_REGISTER, MockRobotModbus
from vgripd.sim.ur_controller import URController
from vgripd.types import Status

SAMPLE = REPO / "config" / "samples" / "two_rigs_frame.toml"
#: The camera on the flange: 120 mm out along the tool axis, 60 mm off it, slightly turned.
T_FLANGE_CAMERA = make_transform(matrix_from_rotvec([0.02, -0.01, 0.03]), [10.0, 60.0, 120.0])
#: The sample's cameras in view order: the first two see the front face, the others the back.
VIEW_ORDER = (0, 1, 2, 3)


def pose_dict(T: np.ndarray) -> dict[str, list[float]]:
    return {"translation_mm": [float(v) for v in T[:3, 3]],
            "rotvec_rad": [float(v) for v in rotvec_from_matrix(T[:3, :3])]}


def view_flanges(n: int) -> list[np.ndarray]:
    """Flange poses that put the camera where the sample's cameras 0..n-1 are."""
    cams = read_config_data(SAMPLE)["calibration"]["cameras"]
    out = []
    for i in VIEW_ORDER[:n]:
        pose = cams[i]["T_base_camera"]
        T_base_camera = make_transform(matrix_from_rotvec(pose["rotvec_rad"]),
                                       pose["translation_mm"])
        out.append(T_base_camera @ invert_transform(T_FLANGE_CAMERA))
    return out


def views_config(n: int, taught: bool = True, timeout_s: float = 30.0,
                 links: int = 1) -> Any:
    data = copy.deepcopy(read_config_data(SAMPLE))
    first = data["calibration"]["cameras"][0]
    data["calibration"] = {"left": first["intrinsics"],
                           "hand_eye": {"mounting": "robot",
                                        "T_flange_camera": pose_dict(T_FLANGE_CAMERA)}}
    data["vision"].update(views=n, view_timeout_s=timeout_s)
    if taught:
        data["vision"]["view_poses"] = [pose_dict(F) for F in view_flanges(n)]
    data["links"] = [{"type": "modbus_server", "host": "127.0.0.1", "port": 0}] * links
    data["status"] = {"port": 0}
    return config_from_dict(data, str(SAMPLE))


def last_message(run: Any) -> str:
    message: str = run.daemon.rooms.jobs.last_job.result.message
    return message


def port(run: Any, index: int = 0) -> int:
    value: int = list(run.daemon.rooms.links.links.values())[index].port
    return value


@pytest.mark.parametrize("n", [2, 3, 4])
async def test_views_locate_the_frame_against_the_renderer_truth(n: int) -> None:
    """2 views see the front face only, 3 add one view of the back (its marks seen once, added
    where the fit predicts them), 4 see both faces twice. Each ends OK within 0.1 mm /
    0.02 deg of the truth; between the views the registers show no result."""
    async with running(views_config(n)) as run, MockPlc("127.0.0.1", port(run), timeout_s=WAIT_S) as plc:
        for job in (1, 2):
            answer = await plc.views_cycle(n)
            pair, rec = await run.job_done(job)
            assert answer.status is Status.OK, rec.result.message
            assert len(answer.values) == 6
            assert pair is not None
            assert len(pair.views) == n
            assert pair.T_base_flange is not None
            assert pair.T_base_flange.shape == (n, 4, 4)
            est = rec.result.T_base_obj
            assert est is not None
            dt, dr = pose_error(est, pair.truth["T_base_obj"])
            assert dt < 0.1, (n, dt)
            assert dr < 0.02, (n, dr)
            # Every view is a group of its own in the residuals.
            for k in range(1, n + 1):
                assert rec.result.residuals[f"rig.view{k}.marks"] >= 4
            assert rec.cycle_ms > 0


async def _ended(plc: MockPlc, view: int, status: Status) -> int:
    """CAPTURE ``view``, which must end the job with ``status`` and no pose; the job id."""
    answer = await plc.capture_view(view)
    assert answer is not None, f"view {view} was taken"
    assert not answer.rejected
    assert answer.status is status, answer
    assert answer.values == ()
    return answer.job_id


async def test_views_out_of_order_repeated_or_interrupted_end_the_job_bad_request() -> None:
    async with running(views_config(3)) as run, MockPlc("127.0.0.1", port(run), timeout_s=WAIT_S) as plc:
        # A view > 1 without a job: refused by the daemon (no job id).
        assert await _ended(plc, 2, Status.BAD_REQUEST) == 0
        # Out of order: 1, 3. The job ends under view 3's request with its own job id.
        assert await plc.capture_view(1) is None
        job = await _ended(plc, 3, Status.BAD_REQUEST)
        assert job > 0
        assert run.daemon.rooms.jobs.last_job.job_id == job
        assert "view 3 out of order" in last_message(run)
        assert await _ended(plc, 2, Status.BAD_REQUEST) == 0  # that job is gone
        # Repeated: 1, 2, 2.
        assert await plc.capture_view(1) is None
        assert await plc.capture_view(2) is None
        assert await _ended(plc, 2, Status.BAD_REQUEST) > job
        assert "view 2 repeated" in last_message(run)
        # 1, then view 1 again: repeated as well (start over with a fresh view 1).
        assert await plc.capture_view(1) is None
        await _ended(plc, 1, Status.BAD_REQUEST)
        # A TRIGGER in the middle ends the job; a TRIGGER alone is refused.
        assert await plc.capture_view(1) is None
        seq = await plc.trigger()
        answer = await plc.wait_answer(seq)
        assert answer.status is Status.BAD_REQUEST
        assert answer.job_id > 0
        assert "not TRIGGER" in last_message(run)
        assert await _ended(plc, 2, Status.BAD_REQUEST) == 0
        seq = await plc.trigger()
        answer = await plc.wait_answer(seq)
        assert answer.status is Status.BAD_REQUEST
        assert answer.job_id == 0
        # NEXT in the middle is refused by the link (no pick list); the job goes on.
        assert await plc.capture_view(1) is None
        seq = await plc.trigger(command=Command.NEXT)
        answer = await plc.wait_answer(seq)
        assert answer.rejected
        assert answer.status is Status.BAD_REQUEST
        assert await plc.capture_view(2) is None
        answer = await plc.capture_view(3)
        assert answer is not None
        assert answer.status is Status.OK
        # After all of it the daemon serves a clean job.
        answer = await plc.views_cycle(3)
        assert answer.status is Status.OK
        assert run.daemon.rooms.jobs.views is None


async def test_no_next_view_in_time_ends_the_job_camera_error_under_the_last_view() -> None:
    async with running(views_config(2, timeout_s=0.3)) as run, MockPlc("127.0.0.1", port(run), timeout_s=WAIT_S) as plc:
        assert await plc.capture_view(1) is None
        seq = plc.seq
        # The robot does not come back: the job ends under view 1's request.
        answer = await plc.wait_answer(seq)
        assert answer.status is Status.CAMERA_ERROR
        assert answer.values == ()
        assert "vision.view_timeout_s" in last_message(run)
        assert await _ended(plc, 2, Status.BAD_REQUEST) == 0  # too late: start again
        # A robot in time still works on the same daemon.
        assert await plc.capture_view(1) is None
        answer = await plc.capture_view(2)
        assert answer is not None


async def test_a_view_without_a_flange_pose_is_not_calibrated() -> None:
    """No taught view poses and a Modbus link, which cannot report the robot's pose."""
    async with running(views_config(2, taught=False)) as run, \
            MockPlc("127.0.0.1", port(run), timeout_s=WAIT_S) as plc:
        job = await _ended(plc, 1, Status.NOT_CALIBRATED)
        assert job > 0
        assert "no flange pose" in last_message(run)
        assert await _ended(plc, 2, Status.BAD_REQUEST) == 0


async def test_another_links_capture_is_busy_while_a_views_job_waits() -> None:
    async with running(views_config(2, links=2)) as run, \
            MockPlc("127.0.0.1", port(run, 0), timeout_s=WAIT_S) as plc, MockPlc("127.0.0.1", port(run, 1), timeout_s=WAIT_S) as other:
        assert await plc.capture_view(1) is None
        assert await _ended(other, 1, Status.BUSY) == 0
        answer = await plc.capture_view(2)
        assert answer is not None
        assert answer.status is Status.OK


async def test_mbpoll_drives_a_two_view_job() -> None:
    """mbpoll writes CMD = view * 256 + 4, REQ_SEQ and RECIPE in one request per view."""
    async with running(views_config(2)) as run:
        p = port(run)
        await mbpoll(p, "-t", "4", "-r", str(Reg.CMD), "127.0.0.1", str(capture_word(1)), "7",
                     "0")
        await run.daemon.wait_for(lambda: run.daemon.rooms.jobs.views is not None
                                  and run.daemon.rooms.jobs.views.next_view == 2
                                  and run.daemon.rooms.jobs.views.timer is not None, WAIT_S)
        assert (await mbpoll(p, "-t", "4", "-r", str(Reg.STATE), "-c", "2", "127.0.0.1")
                == {Reg.STATE: int(HandshakeState.VIEWS), Reg.CAPTURED_SEQ: 7})
        assert await mbpoll(p, "-t", "4", "-r", str(Reg.ACK_SEQ), "127.0.0.1") == {
            Reg.ACK_SEQ: 0}
        await mbpoll(p, "-t", "4", "-r", str(Reg.CMD), "127.0.0.1", str(capture_word(2)), "8",
                     "0")
        await run.job_done(1)
        answer = await mbpoll(p, "-t", "4", "-r", str(Reg.ACK_SEQ), "-c", "2", "127.0.0.1")
        assert answer == {Reg.ACK_SEQ: 8, Reg.STATUS: int(Status.OK)}
        assert (await mbpoll(p, "-t", "4", "-r", str(Reg.N_VALUES), "127.0.0.1")
                == {Reg.N_VALUES: 6})


def ur_pose(T: np.ndarray) -> list[float]:
    """A flange pose as UR's actual_TCP_pose: metres and a rotation vector."""
    return [*(T[:3, 3] / 1000.0), *rotvec_from_matrix(T[:3, :3])]


async def test_a_ur_robot_reports_its_own_pose_for_each_view() -> None:
    """The real ur_rtde client (in the link's child process) against the mock UR controller:
    no taught view poses, the flange pose of each view is the robot's TCP pose read with its
    request; the synthetic camera renders each view from it."""
    with URController(lo("127.0.7.9")) as robot:
        data = views_config(3, taught=False).model_dump(mode="json", exclude_none=True)
        data["links"] = [{"type": "ur_rtde", "host": robot.host}]
        data["output"] = {"vendor": "ur"}
        async with running(config_from_dict(data)) as run:
            await run.daemon.wait_for(
                lambda: all(link.health().state is LinkState.UP
                            for link in run.daemon.rooms.links.links.values()), WAIT_S)
            flanges = view_flanges(3)
            answers = [await asyncio.to_thread(robot.capture_view, k, ur_pose(F), last=k == 3)
                       for k, F in enumerate(flanges, start=1)]
            pair, rec = await run.job_done(1)
    assert [a["error"] for a in answers] == [None] * 3
    assert [a.get("captured") for a in answers[:2]] == [answers[0]["seq"], answers[1]["seq"]]
    assert answers[2]["status"] == Status.OK, rec.result.message
    assert answers[2]["job_id"] == rec.job_id
    assert rec.result.target is not None
    assert tuple(answers[2]["offset"]) == rec.result.target.values
    assert pair is not None
    np.testing.assert_allclose(pair.T_base_flange, np.stack(flanges), atol=1e-6)
    assert rec.result.T_base_obj is not None
    dt, dr = pose_error(rec.result.T_base_obj, pair.truth["T_base_obj"])
    assert dt < 0.1
    assert dr < 0.02


async def test_views_over_the_modbus_client_link() -> None:
    """The mirror links (``modbus_client`` here, ``s7`` alike) carry the same block: the mock
    robot's own registers, polled and written by vgripd's Modbus client."""
    robot = MockRobotModbus()
    await robot.start()
    try:
        data = views_config(2).model_dump(mode="json", exclude_none=True)
        data["links"] = [{"type": "modbus_client", "host": robot.host, "port": robot.port,
                          "poll_interval_s": 0.005}]
        async with running(config_from_dict(data)) as run:
            link = run.daemon.rooms.links.links["modbus_client"]
            await run.daemon.wait_for(lambda: link.health().state is LinkState.UP, WAIT_S)
            base = UR_FIRST_REGISTER
            await robot.write(base + Reg.CMD, [capture_word(1)])
            await robot.write(base + Reg.REQ_SEQ, [31])
            async with asyncio.timeout(WAIT_S):
                while robot.read(base + Reg.STATE, 2) != [HandshakeState.VIEWS, 31]:
                    await robot.changed()
            assert robot.read(base + Reg.ACK_SEQ) == [0]
            seen = await robot.run_job(32, WAIT_S, command=capture_word(2))
            _, rec = await run.job_done(1)
    finally:
        await robot.stop()
    assert seen.words[Reg.ACK_SEQ] == 32
    assert seen.words[Reg.STATUS] == Status.OK, rec.result.message
    assert seen.words[Reg.N_VALUES] == 6


async def test_stopping_between_views_answers_aborted_under_the_last_view() -> None:
    async with running(views_config(3)) as run, \
            MockPlc("127.0.0.1", port(run), timeout_s=WAIT_S) as plc:
        assert await plc.capture_view(1) is None
        assert await plc.capture_view(2) is None
        stopping = asyncio.ensure_future(run.daemon.stop())
        answer = await plc.wait_answer(plc.seq)  # the links linger for the answer
        await stopping
    assert answer.status is Status.ABORTED
    assert answer.values == ()


def test_check_places_the_object_in_each_taught_view(tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """`vgripd check` projects the reference into every view at its taught flange pose and
    names the view pose that sees nothing (here view 2 turned half round)."""
    data = views_config(3).model_dump(mode="json", exclude_none=True)
    good = tmp_path / "good.toml"
    good.write_text(toml_from_dict(data))
    assert main(["check", "-c", str(good)]) == 0
    assert "view_poses" not in capsys.readouterr().err
    away = view_flanges(3)[1] @ make_transform(matrix_from_rotvec([0.0, np.pi, 0.0]),
                                               [0.0, 0.0, 0.0])
    data["vision"]["view_poses"][1] = pose_dict(away)
    bad = tmp_path / "bad.toml"
    bad.write_text(toml_from_dict(data))
    main(["check", "-c", str(bad)])
    out = capsys.readouterr()
    assert "camera view2 sees none of the marks" in out.out + out.err
    assert "check vision.view_poses.1" in out.out + out.err
