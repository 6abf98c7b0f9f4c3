"""A pallet of plates walked as a pick list over every link, through the real daemon (worker
process, vision pipeline, synthetic pallet camera): the mock PLC over Modbus/TCP, the real
ur_rtde client against the mock UR controller, snap7's server as an S7 PLC, the mock robot's
Modbus registers (modbus_client), and each brand's generated robot program (its twin) with its
locate and next routines over the robot socket.

Accuracy: each pose the peer read (vendor values decoded here with scipy, not vgripd's
conventions) is turned back into the plate's pose and compared with the renderer's truth of
the plate it is nearest to: every plate exactly once, within 0.5 mm / 0.5 deg.
"""

from __future__ import annotations

import asyncio
import contextlib
import struct
import threading
from collections.abc import AsyncIterator, Sequence
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tests.conftest import lo
from tests.integration.test_daemon import Run, make_config
from tests.integration.test_robot_programs import cell, free_port
from vgripd.cli.robot_program import render
from vgripd.cli.status import format_status
from vgripd.config import Config, config_from_dict
from vgripd.geometry.transforms import pose_error
from vgripd.peer.jobcore import Command
from vgripd.peer.registers import Reg
from vgripd.peer.socket_frames import BRANDS, Request, SocketCommand
from vgripd.service.daemon import Daemon
from vgripd.service.links.protocol import LinkState
from vgripd.sim.plc import MockPlc
from vgripd.sim.robot_modbus import MockRobotModbus
from vgripd.sim.robot_socket_client import ProgramSettings, ProgramTwin
from vgripd.sim.s7_plc import MockS7Plc, S7PlcServer, words_of
from vgripd.sim.ur_controller import URController
from vgripd.types import ImagePair, JobResult, Status

pytestmark = [pytest.mark.timeout(180), pytest.mark.slow(minutes=2)]

WAIT_S = 30.0
PLATES = 5
PALLET = {"type": "synthetic", "seed": 5,
          "pallet": {"count": PLATES, "cols": 3, "gap_mm": 0.0}, "drop_features": ["1/m2"]}
LIMITS = {"max_translation_mm": 300.0, "max_rotation_deg": 10.0}
PICKING = {"max_objects": 6, "order": "score"}


#: The pallet scene renders five plates per image: on a machine running two suites a job takes
#: several times the daemon's default 10 s; the tests give it this, and the PLC a little more.
JOB_TIMEOUT_S = 40.0
PLC_TIMEOUT_S = JOB_TIMEOUT_S + 5.0


def pallet_config(vendor: str = "kuka", links: list[dict[str, Any]] | None = None) -> Config:
    daemon = {"job_timeout_s": JOB_TIMEOUT_S}
    if links is None:
        return make_config(PALLET, picking=PICKING, limits=LIMITS, output={"vendor": vendor},
                           daemon=daemon)
    return config_from_dict({"camera": PALLET, "picking": PICKING, "limits": LIMITS,
                             "output": {"vendor": vendor}, "links": links,
                             "status": {"port": 0}, "daemon": daemon})


def T_ref(config: Config) -> np.ndarray:
    """The taught reference pose, from the config's numbers (scipy, not vgripd's geometry)."""
    pose = config.reference.T_base_obj
    if pose.matrix is not None:
        return np.array(pose.matrix, dtype=float)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(pose.rotvec_rad or (0.0, 0.0, 0.0)).as_matrix()
    T[:3, 3] = pose.translation_mm
    return T


def offset_of(vendor: str, values: Sequence[float]) -> np.ndarray:
    """The 4x4 offset (mm) of a published pose, decoded with scipy from each convention's
    definition: KUKA A B C intrinsic Z Y' X''; FANUC W P R and Yaskawa Rx Ry Rz about fixed
    x y z; Staubli Rx Ry Rz intrinsic X Y' Z''; ABB q1..q4 = w x y z (mm, deg); UR x y z in m
    and a rotation vector in rad."""
    T = np.eye(4)
    v = [float(x) for x in values]
    if vendor == "ur":
        T[:3, :3] = Rotation.from_rotvec(v[3:6]).as_matrix()
        T[:3, 3] = np.array(v[:3]) * 1000.0
        return T
    if vendor == "abb":
        rot = Rotation.from_quat([v[4], v[5], v[6], v[3]])  # scipy: scalar last
    else:
        seq = {"kuka": "ZYX", "fanuc": "xyz", "yaskawa": "xyz", "staubli": "XYZ"}[vendor]
        rot = Rotation.from_euler(seq, v[3:6], degrees=True)
    T[:3, :3] = rot.as_matrix()
    T[:3, 3] = v[:3]
    return T


def check_against_truth(config: Config, run: Run, vendor: str,
                        walked: Sequence[Sequence[float]]) -> None:
    """``walked``: the poses the peer read, in order. Every truth plate exactly once, close."""
    pair, _ = run.jobs[0]
    assert pair is not None
    truths = pair.truth["instances_T_base_obj"]
    assert len(truths) == PLATES
    seen: set[int] = set()
    for values in walked:
        T_base_obj = offset_of(vendor, values) @ T_ref(config)  # offset = T_obj inv(T_ref)
        k = int(np.argmin([np.linalg.norm(T[:3, 3] - T_base_obj[:3, 3]) for T in truths]))
        assert k not in seen, f"plate {k} handed out twice"
        seen.add(k)
        dt, dr = pose_error(truths[k], T_base_obj)
        assert dt < 0.5, (k, dt)
        assert dr < 0.5, (k, dr)
    assert seen == set(range(PLATES))


class GatedPipeline:
    """The real pipeline, behind a gate the test closes to keep a job running as long as it
    needs (no timed wait)."""

    def __init__(self, config: Config) -> None:
        from vgripd.vision.pipeline import Pipeline

        self.pipeline = Pipeline(config)
        self.gate = threading.Event()
        self.gate.set()

    def process(self, pair: ImagePair, job_id: int) -> JobResult:
        self.gate.wait(60)
        return self.pipeline.process(pair, job_id)


@contextlib.asynccontextmanager
async def running(config: Config) -> AsyncIterator[Run]:
    daemon = Daemon(config)
    run = Run(daemon)
    await daemon.start()
    try:
        yield run
    finally:
        await daemon.stop()


# --- Modbus/TCP: the mock PLC ---------------------------------------------------------------


async def test_mock_plc_walks_the_pallet_with_next() -> None:
    config = pallet_config()
    async with running(config) as run, MockPlc("127.0.0.1", run.port(), poll_s=0.005,
                                               timeout_s=PLC_TIMEOUT_S) as plc:
        await plc.check_byte_order()  # MAP_VERSION 3
        first = await plc.cycle()
        assert (first.status, first.count, first.index) == (Status.OK, PLATES, 1)
        walk = [first]
        while walk[-1].status.pose_valid:
            walk.append(await plc.next())  # checks job id, index, age itself
        end = walk.pop()
        assert (end.status, end.index, end.values, end.job_id) == (
            Status.NOT_FOUND, PLATES + 1, (), first.job_id)
        assert len(walk) == PLATES
        assert [a.index for a in walk] == list(range(1, PLATES + 1))
        scores = [a.score for a in walk]
        assert scores == sorted(scores, reverse=True)  # order = "score", seen in SCORE
        assert all(0.5 < s <= 1.0 for s in scores)
        assert len(run.jobs) == 1  # NEXT took no image and made no job
        check_against_truth(config, run, "kuka", [a.values for a in walk])
        # The daemon kept count and shows where the list stands.
        snap = run.daemon.snapshot()
        assert snap["pick_list"] == {"job_id": first.job_id, "link": "modbus_server",
                                     "count": PLATES, "index": PLATES + 1,
                                     "instances": PLATES}
        assert snap["next_answers"] == {"OK": PLATES - 1, "NOT_FOUND": 1}
        assert snap["counters"] == {"OK": PLATES, "NOT_FOUND": 1}
        assert f"; pick list {PLATES}/{PLATES}" in run.daemon.status_line()
        assert (f"pick list of job {first.job_id} (modbus_server): used up ({PLATES} handed "
                f"out), {PLATES} instances found; NEXT answers NOT_FOUND 1, OK {PLATES - 1}"
                ) in format_status(snap)
        # A new job starts a new list; CLEAR ends it (refused by the handshake).
        again = await plc.cycle()
        assert (again.job_id, again.count, again.index) == (first.job_id + 1, PLATES, 1)
        assert (await plc.next()).index == 2
        await plc.write(Reg.CMD, [2, plc.next_seq(), 0])  # CLEAR
        refused = await plc.next()
        assert (refused.rejected, refused.status) == (True, Status.BAD_REQUEST)


async def test_next_after_another_links_job_is_bad_request_never_a_stale_pose() -> None:
    config = make_config(PALLET, links=2, picking=PICKING, limits=LIMITS,
                         daemon={"job_timeout_s": JOB_TIMEOUT_S})
    async with running(config) as run, \
            MockPlc("127.0.0.1", run.port(0), poll_s=0.005, timeout_s=PLC_TIMEOUT_S) as a, \
            MockPlc("127.0.0.1", run.port(1), poll_s=0.005, timeout_s=PLC_TIMEOUT_S) as b:
        listed = await a.cycle()
        assert listed.count == PLATES
        other = await b.cycle()  # the other PLC's job: the scene may have changed
        assert other.status is Status.OK
        answer = await a.next()  # A's handshake still holds a list; the daemon refuses it
        assert (answer.rejected, answer.status, answer.values, answer.job_id) == (
            False, Status.BAD_REQUEST, (), 0)
        assert (answer.count, answer.index) == (0, 0)
        # and now A's handshake has no list either
        assert (await a.next()).rejected
        # b walks its own list
        assert (await b.next()).index == 2


async def test_next_while_another_links_job_runs_is_busy() -> None:
    config = make_config(PALLET, links=2, picking=PICKING, limits=LIMITS,
                         daemon={"job_timeout_s": JOB_TIMEOUT_S})
    async with running(config) as run, \
            MockPlc("127.0.0.1", run.port(0), poll_s=0.005, timeout_s=PLC_TIMEOUT_S) as a, \
            MockPlc("127.0.0.1", run.port(1), poll_s=0.005, timeout_s=PLC_TIMEOUT_S) as b:
        assert (await a.cycle()).count == PLATES
        seq_b = await b.trigger()
        await run.busy()
        busy = await a.next()  # the daemon's refusal, acknowledged, no pose
        assert (busy.rejected, busy.status, busy.job_id, busy.values) == (
            False, Status.BUSY, 0, ())
        assert (await b.wait_answer(seq_b)).status is Status.OK
        assert (await a.next()).status is Status.BAD_REQUEST  # A's list went with B's job
        assert run.daemon.snapshot()["pick_list"]["link"] == "modbus_server.1"


async def test_next_with_no_job_since_start_is_refused() -> None:
    async with running(pallet_config()) as run, \
            MockPlc("127.0.0.1", run.port(), timeout_s=PLC_TIMEOUT_S) as plc:
        refused = await plc.next()
        assert (refused.rejected, refused.status) == (True, Status.BAD_REQUEST)
        assert run.daemon.snapshot()["refusals"] == {"BAD_REQUEST": 1}
        assert not run.jobs


# --- UR RTDE: the real ur_rtde client against the mock controller --------------------------


async def test_ur_program_walks_the_pallet_with_next() -> None:
    with URController(lo("127.0.7.31")) as robot:
        config = pallet_config("ur", [{"type": "ur_rtde", "host": robot.host}])
        async with running(config) as run:
            link = run.daemon.rooms.links.links["ur_rtde"]
            await run.daemon.wait_for(lambda: link.health().state is LinkState.UP, WAIT_S)
            seq = robot.start_program(1)
            results = [await asyncio.to_thread(robot.program_result, seq)]
            while results[-1]["status"] in (1, 2):
                seq = robot.start_program(3)  # next
                results.append(await asyncio.to_thread(robot.program_result, seq))
    end = results.pop()
    assert (end["status"], end["offset"], end["count"], end["index"]) == (
        int(Status.NOT_FOUND), None, PLATES, PLATES + 1)
    assert [(r["count"], r["index"]) for r in results] == [
        (PLATES, i) for i in range(1, PLATES + 1)]
    assert {r["job_id"] for r in results} == {end["job_id"]} == {1}
    assert len(run.jobs) == 1
    _, rec = run.jobs[0]
    # float-exact: what the robot read is the daemon's instance, in pick order
    assert [tuple(r["offset"]) for r in results] == [
        i.target.values for i in rec.result.instances if i.target is not None]
    check_against_truth(config, run, "ur", [r["offset"] for r in results])


# --- robot socket: each brand's program twin ------------------------------------------------


@pytest.mark.parametrize("brand", sorted(BRANDS))
async def test_each_robot_program_walks_the_pallet_with_next(brand: str) -> None:
    """The program's locate, then its next until NOT_FOUND, as its twin sends them (the NEXT
    word read from the generated program), against the daemon with the synthetic pallet."""
    port = free_port()
    data = cell(brand, port)
    data.update(camera=PALLET, picking=PICKING, limits=LIMITS)
    data.setdefault("daemon", {})["job_timeout_s"] = JOB_TIMEOUT_S
    config = config_from_dict(data)
    settings = ProgramSettings.parse(brand, render(BRANDS[brand], config, source="pallet.toml"))
    async with ProgramTwin(settings, "127.0.0.1", port) as twin, running(config) as run:
        link = run.daemon.rooms.links.links["robot_socket"]
        await run.daemon.wait_for(lambda: link.health().state is LinkState.UP, WAIT_S)
        walk = [await twin.locate()]
        assert walk[0].captured
        while walk[-1].status in (1, 2):
            walk.append(await twin.next())
        again = await twin.next()  # past the end it stays so
        _, rec = await run.job_done(1)
    end = walk.pop()
    for o in (end, again):
        assert (o.status, o.values, o.remaining, o.captured, o.job_id) == (
            Status.NOT_FOUND, (), 0, False, 1)
    assert [o.remaining for o in walk] == list(range(PLATES - 1, -1, -1))
    assert {o.job_id for o in walk} == {1}
    assert not any(o.captured for o in walk[1:])  # no image for a NEXT
    assert len(run.jobs) == 1
    # the bytes on the wire: the protocol's own LOCATE and NEXT frames, recipe 0, ids 1, 2, ...
    assert twin.sent == [Request(SocketCommand.LOCATE, 1, 0).encode()] + [
        Request(SocketCommand.NEXT, i, 0).encode() for i in range(2, PLATES + 3)]
    # what the program decoded is the daemon's instance, in pick order, to its resolution
    targets = [i.target.values for i in rec.result.instances if i.target is not None]
    assert len(targets) == PLATES
    for o, want in zip(walk, targets, strict=True):
        tol = 0.5 / settings.scale + 1e-12 if settings.scale else 1e-6 * max(map(abs, want))
        assert max(abs(a - b) for a, b in zip(o.values, want, strict=True)) <= tol
    check_against_truth(config, run, BRANDS[brand].convention, [o.values for o in walk])


@pytest.mark.parametrize("brand", ["kuka", "ur"])  # a kept connection, one per request
async def test_a_programs_next_waits_out_busy_and_never_gets_a_stale_pose(brand: str) -> None:
    """NEXT while a PLC's job runs is BUSY; the program asks again as its locate does, and
    since that job took the list the answer is BAD_REQUEST (32) without a pose: locate again."""
    port = free_port()
    data = cell(brand, port)
    data.update(camera=PALLET, picking=PICKING, limits=LIMITS)
    data.setdefault("daemon", {})["job_timeout_s"] = JOB_TIMEOUT_S
    data["links"].append({"type": "modbus_server", "host": "127.0.0.1", "port": 0})
    config = config_from_dict(data)
    settings = ProgramSettings.parse(brand, render(BRANDS[brand], config, source="pallet.toml"))
    gated = GatedPipeline(config)
    daemon = Daemon(config, pipeline=gated)
    run = Run(daemon)
    await daemon.start()
    try:
        async with ProgramTwin(settings, "127.0.0.1", port) as twin, \
                MockPlc("127.0.0.1", run.port(1), poll_s=0.005, timeout_s=PLC_TIMEOUT_S) as plc:
            await run.daemon.wait_for(lambda: all(
                link.health().state is LinkState.UP for link in daemon.rooms.links.links.values()), WAIT_S)
            no_list = await twin.next()  # nothing located yet: refused at once, no retry
            assert (await twin.locate()).remaining == PLATES - 1
            gated.gate.clear()
            seq = await plc.trigger()
            await run.busy()
            after_busy = await twin.next()
            gated.gate.set()
            assert (await plc.wait_answer(seq)).status is Status.OK
            again = await twin.locate()  # a new list of the robot's own
            second = await twin.next()
    finally:
        gated.gate.set()
        await daemon.stop()
    assert (no_list.status, no_list.values, no_list.request_ids) == (Status.BAD_REQUEST, (), [1])
    assert (after_busy.status, after_busy.values, after_busy.job_id) == (
        Status.BAD_REQUEST, (), 0)
    assert after_busy.request_ids == [3, 4]  # BUSY, waited, asked again with a new id
    assert daemon.snapshot()["refusals"]["BUSY"] == 1
    assert (again.job_id, second.job_id, second.remaining) == (3, 3, PLATES - 2)
    assert second.status == Status.OK


# --- the client links: snap7's server as the PLC, the mock robot's Modbus registers ----------


async def test_s7_plc_walks_the_pallet_with_next() -> None:
    async with S7PlcServer(10) as server, MockS7Plc(server.host, server.port, 10) as plc:
        config = pallet_config("kuka", [{"type": "s7", "host": server.host,
                                         "port": server.port, "db": 10}])
        async with running(config) as run:
            link = run.daemon.rooms.links.links["s7"]
            await run.daemon.wait_for(lambda: link.health().state is LinkState.UP, WAIT_S)
            seen = [words_of((await plc.run_job(1, WAIT_S)).raw)]
            for seq in range(2, PLATES + 3):
                seen.append(words_of((await plc.run_job(seq, WAIT_S, Command.NEXT)).raw))
    assert [(w[Reg.ACK_SEQ], w[Reg.COUNT], w[Reg.INDEX]) for w in seen] == [
        (i, PLATES, i) for i in range(1, PLATES + 2)] + [(PLATES + 2, PLATES, PLATES + 1)]
    assert [w[Reg.STATUS] for w in seen] == [Status.OK] * PLATES + [Status.NOT_FOUND] * 2
    assert {w[Reg.JOB_ID + 1] for w in seen} == {1}  # the job's id (low word), every answer
    walked = [struct.unpack(">6f", struct.pack(">12H", *w[Reg.VALUES:Reg.VALUES + 12]))
              for w in seen[:PLATES]]
    check_against_truth(config, run, "kuka", walked)


async def test_robot_modbus_registers_walk_the_pallet_with_next() -> None:
    robot = MockRobotModbus()
    await robot.start()
    try:
        config = pallet_config("ur", [{"type": "modbus_client", "host": robot.host,
                                       "port": robot.port, "poll_interval_s": 0.005}])
        async with running(config) as run:
            link = run.daemon.rooms.links.links["modbus_client"]
            await run.daemon.wait_for(lambda: link.health().state is LinkState.UP, WAIT_S)
            seen = [(await robot.run_job(1, WAIT_S)).words]
            for seq in range(2, PLATES + 2):
                seen.append((await robot.run_job(seq, WAIT_S, command=Command.NEXT)).words)
    finally:
        await robot.stop()
    assert [(w[Reg.STATUS], w[Reg.COUNT], w[Reg.INDEX]) for w in seen] == [
        (Status.OK, PLATES, i) for i in range(1, PLATES + 1)] + [
        (Status.NOT_FOUND, PLATES, PLATES + 1)]
    walked = [struct.unpack(">6f", struct.pack(">12H", *w[Reg.VALUES:Reg.VALUES + 12]))
              for w in seen[:PLATES]]
    check_against_truth(config, run, "ur", walked)
