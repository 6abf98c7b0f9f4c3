"""OPC 40100 end to end: the real daemon (synthetic pallet camera, the whole vision pipeline)
with an ``opcua`` link on its default models, and asyncua's client running the standard's PLC
sequence: SelectModeAutomatic -> PrepareRecipe -> StartSingleJob per part -> ResultReady event
-> GetResultById, then the last job's pick list walked with the plain ``Plc.Next``.

Accuracy: each pose a client read (KUKA values decoded with scipy, not vgripd's conventions)
is turned back into a plate's pose and compared with the renderer's truth of that job's image
(``ImagePair.truth``), within 0.5 mm / 0.5 deg; the walk hands out every plate once.
A Halt while a job runs ends it ABORTED (ResultState 3) without a pose, in the event, the
stored result and the plain variables, though the daemon's pipeline located the plates.
StartContinuous runs jobs one after another until Stop (the running one finishes): each a
ResultReady of the same JobId with a pose close to its own image's truth.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Sequence
from typing import Any

import numpy as np
import pytest

from drivers.links.opcua_vision import INSTANCE_URI, MV_URI, register_binary_ids
from tests.conftest import ua_client
from tests.drivers.links.test_opcua_vision import (
    AUTO,
    RESULT_READY,
    Vision,
    content,
    ext,
    job_args,
    subscribe,
)
from tests.integration.test_daemon import Run
from tests.integration.test_daemon_picklinks import (
    LIMITS,
    PALLET,
    PICKING,
    PLATES,
    GatedPipeline,
    T_ref,
    offset_of,
)
from vgripd.config import Config, config_from_dict
from vgripd.geometry.transforms import pose_error
from vgripd.service.daemon import Daemon
from vgripd.service.jobs.runner import JobState
from vgripd.service.links.protocol import LinkState
from vgripd.types import Status

pytestmark = pytest.mark.timeout(240)

WAIT_S = 60.0
LINK = {"type": "opcua", "host": "127.0.0.1", "port": 0, "security": ["None"],
        "allow_anonymous": True}  # the default models: OPC 40100 beside the older namespace


def config() -> Config:
    return config_from_dict({"camera": PALLET, "picking": PICKING, "limits": LIMITS,
                             "output": {"vendor": "kuka"}, "links": [LINK],
                             "status": {"enabled": False}, "daemon": {"worker": False}})


@contextlib.asynccontextmanager
async def cell() -> AsyncIterator[tuple[Run, GatedPipeline, Vision]]:
    """The daemon (its pipeline behind a gate the test may close) and a connected client."""
    cfg = config()
    gated = GatedPipeline(cfg)
    daemon = Daemon(cfg, pipeline=gated)
    run = Run(daemon)
    await daemon.start()
    try:
        await daemon.wait_for(lambda: all(link.health().state is LinkState.UP
                                          for link in daemon.rooms.links.links.values()), WAIT_S)
        client = ua_client(f"opc.tcp://127.0.0.1:{run.port(0)}/vgripd", timeout=WAIT_S)
        async with client:
            await client.load_data_type_definitions()
            mv = await client.get_namespace_index(MV_URI)
            await register_binary_ids(client.get_node, mv)
            yield run, gated, Vision(client, mv, await client.get_namespace_index(INSTANCE_URI))
    finally:
        gated.gate.set()
        await daemon.stop()


def plate_near(cfg: Config, truths: Sequence[np.ndarray], values: Sequence[float]) -> int:
    """The truth plate the published KUKA offset ``values`` puts the object on (index), after
    checking it is within 0.5 mm / 0.5 deg of it."""
    T_base_obj = offset_of("kuka", values) @ T_ref(cfg)  # offset = T_obj inv(T_ref)
    k = int(np.argmin([np.linalg.norm(T[:3, 3] - T_base_obj[:3, 3]) for T in truths]))
    dt, dr = pose_error(truths[k], T_base_obj)
    assert dt < 0.5, (k, dt)
    assert dr < 0.5, (k, dr)
    return k


async def truths_of(run: Run, n: int) -> list[np.ndarray]:
    pair, _ = await run.job_done(n)
    assert pair is not None
    truths = list(pair.truth["instances_T_base_obj"])
    assert len(truths) == PLATES
    return truths


async def ready(v: Vision) -> None:
    """The PLC's start-up: automatic mode, recipe 0 prepared."""
    assert await v.call("VisionStateMachine/SelectModeAutomatic") == [0]
    internal, done, error = await v.call("RecipeManagement/PrepareRecipe",
                                         ext("RecipeIdExternalDataType", "0"),
                                         ext("RecipeIdInternalDataType", ""))
    assert (internal.Id, done, error) == ("0", True, 0)
    assert await v.state() == ("Operational", "Ready")


async def test_the_plc_sequence_locates_each_part_and_walks_the_pick_list() -> None:
    cfg = config()
    async with cell() as (run, _gated, v):
        events, sub = await subscribe(v)
        await ready(v)
        parts = []
        for n in (1, 2):
            job_id, error = await v.call(f"{AUTO}/StartSingleJob",
                                         *job_args(f"meas-{n}", f"part-{n}"))
            assert error == 0
            got = await events.next(RESULT_READY)
            assert (got.JobId.Id, got.MeasId.Id, got.PartId.Id, got.ResultState) == (
                job_id.Id, f"meas-{n}", f"part-{n}", 1)
            _handle, result, error = await v.call("ResultManagement/GetResultById",
                                                   got.ResultId, 1000.0)
            assert error == 0
            parts.append(content(result))
            assert content(got) == parts[-1]
        # the pick list of the last job, walked with the plain Next until it is used up
        walked = [parts[-1]]
        while walked[-1]["StatusName"] == "OK":
            _job, error = await v.call("Plc/Next")
            assert error == 0
            walked.append(content(await events.next(RESULT_READY)))
        plain = {name: await v.plain(name) for name in ("Count", "Index", "Pose", "StatusName")}
        await sub.delete()
        assert await v.state() == ("Operational", "Ready")
        records = [(await run.job_done(n))[1] for n in (1, 2)]
        truths = [await truths_of(run, n) for n in (1, 2)]
    assert len(run.jobs) == 2  # Next took no image
    for part, rec, truth in zip(parts, records, truths, strict=True):
        assert (part["StatusName"], part["DaemonJobId"]) == ("OK", rec.job_id)
        assert (part["Count"], part["Index"]) == (PLATES, 1)
        plate_near(cfg, truth, part["Values"])  # this job's own image
    end = walked.pop()
    assert (end["StatusName"], end["Values"] or [], end["Count"], end["Index"]) == (
        "NOT_FOUND", [], PLATES, PLATES + 1)
    assert [(w["Count"], w["Index"]) for w in walked] == [
        (PLATES, i) for i in range(1, PLATES + 1)]
    assert {w["DaemonJobId"] for w in walked} == {records[1].job_id}
    assert sorted(plate_near(cfg, truths[1], w["Values"]) for w in walked) == list(range(PLATES))
    assert (plain["Count"], plain["Index"], plain["StatusName"]) == (
        PLATES, PLATES + 1, "NOT_FOUND")
    assert plain["Pose"] in (None, [])


async def test_halt_during_a_job_ends_it_aborted_without_a_pose() -> None:
    async with cell() as (run, gated, v):
        events, sub = await subscribe(v)
        await ready(v)
        gated.gate.clear()
        job_id, error = await v.call(f"{AUTO}/StartSingleJob", *job_args("meas", "part"))
        assert error == 0
        await run.busy()
        assert await v.state() == ("Operational", "SingleExecution")
        assert await v.call("VisionStateMachine/Halt", 0, "") == [0]
        assert await v.state() == ("Halted", "")
        gated.gate.set()
        got = await events.next(RESULT_READY)
        _handle, stored, error = await v.call("ResultManagement/GetResultById",
                                               got.ResultId, 1000.0)
        plain: dict[str, Any] = {name: await v.plain(name) for name in (
            "StatusName", "ResultState", "Values", "Pose", "Count", "Index")}
        await sub.delete()
        _, rec = await run.job_done(1)
    assert rec.result.status is Status.OK  # the pipeline located the plates ...
    assert (got.JobId.Id, got.ResultState, stored.ResultState) == (job_id.Id, 3, 3)
    for c in (content(got), content(stored)):  # ... the client gets no pose of them
        assert (c["StatusName"], c["Values"] or [], c["Pose"] or [], c["Count"], c["Index"]) == (
            "ABORTED", [], [], 0, 0)
    assert (plain["StatusName"], plain["ResultState"], plain["Count"]) == ("ABORTED", 3, 0)
    assert plain["Values"] in (None, [])
    assert plain["Pose"] in (None, [])


async def test_start_continuous_locates_part_after_part_until_stop() -> None:
    cfg = config()
    async with cell() as (run, _gated, v):
        events, sub = await subscribe(v)
        await ready(v)
        job_id, error = await v.call(f"{AUTO}/StartContinuous", *job_args("meas", "part"))
        assert error == 0
        got = [await events.next(RESULT_READY) for _ in range(3)]
        assert await v.call(f"{AUTO}/Stop", 0, "") == [0]
        async with asyncio.timeout(WAIT_S):  # the running job ends, then Ready
            while True:
                if await v.state() == ("Operational", "Ready"):
                    break
                await asyncio.sleep(0.01)  # polled: a PLC reads the state
        await run.daemon.wait_for(lambda: run.daemon.rooms.jobs.state is JobState.IDLE, WAIT_S)
        n = len(run.jobs)
        assert n in (3, 4)  # Stop between two jobs, or during the fourth
        while len(got) < n:
            got.append(await events.next(RESULT_READY))
        # the chain has ended: the daemon's next job is this single one
        single, error = await v.call(f"{AUTO}/StartSingleJob", *job_args("m", "p"))
        assert error == 0
        assert (await events.next(RESULT_READY)).JobId.Id == single.Id
        _, after = await run.job_done(n + 1)
        await sub.delete()
        records = [(await run.job_done(i))[1] for i in range(1, n + 1)]
        truths = [await truths_of(run, i) for i in range(1, n + 1)]
    assert after.seq == int(single.Id)
    assert {r.JobId.Id for r in got} == {job_id.Id}  # one job, a result per part
    assert len({r.ResultId.Id for r in got}) == n
    for result, rec, truth in zip(got, records, truths, strict=True):
        c = content(result)
        assert (result.ResultState, c["StatusName"], c["DaemonJobId"]) == (1, "OK", rec.job_id)
        plate_near(cfg, truth, c["Values"])  # each job's own image
