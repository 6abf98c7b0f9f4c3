"""Pick lists over the OPC UA link: the real daemon with the synthetic pallet camera, asyncua's
client in its own process (``vgripd.sim.opcua_client``) calling ``VisionSystem.Next``, and
asyncua's ``uaread`` reading the pick-list variables.

Accuracy: each pose the client read (KUKA values decoded here with scipy, not with vgripd's
conventions) is turned back into the plate's pose and compared with the renderer's truth
(``check_against_truth``): every plate exactly once, within 0.5 mm / 0.5 deg. The link serves the older namespace alone (``models = ["vgripd"]``: its Next is
tested here; OPC 40100's plain Next is tests/integration/test_daemon_opcua_vision.py).
"""

from __future__ import annotations

import asyncio
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import need
from tests.integration.test_daemon import Plc, Run
from tests.integration.test_daemon_picklinks import (
    PLATES,
    GatedPipeline,
    check_against_truth,
    pallet_config,
    running,
)
from vgripd.peer.registers import Reg
from vgripd.service.daemon import Daemon
from vgripd.service.links.protocol import LinkState
from vgripd.sim.opcua_client import OpcUaClientProcess
from vgripd.types import Status

pytestmark = pytest.mark.timeout(180)

OPEN_LINK = {"type": "opcua", "host": "127.0.0.1", "port": 0, "security": ["None"],
             "allow_anonymous": True, "models": ["vgripd"]}
MODBUS = {"type": "modbus_server", "host": "127.0.0.1", "port": 0}


async def wait_up(run: Run) -> None:
    await run.daemon.wait_for(lambda: all(link.health().state is LinkState.UP
                                          for link in run.daemon.rooms.links.links.values()), 30)


def url(run: Run, index: int) -> str:
    return f"opc.tcp://127.0.0.1:{run.port(index)}/vgripd"


async def uaread(endpoint: str, name: str) -> str:
    """``uaread`` (asyncua's command-line tool) of ``VisionSystem.Result.<name>``."""
    tool = Path(sys.executable).parent / "uaread"
    need(tool.exists(), "needs uaread (asyncua's command-line tools): pip install "
                        "'vgripd[opcua]'")
    proc = await asyncio.create_subprocess_exec(
        str(tool), "-u", endpoint, "-n", f"ns=2;s=VisionSystem.Result.{name}",
        stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    async with asyncio.timeout(60):
        out, err = await proc.communicate()
    assert proc.returncode == 0, err.decode()
    return out.decode().strip()


async def test_opcua_client_walks_the_pallet_with_next() -> None:
    config = pallet_config("kuka", [OPEN_LINK])
    async with running(config) as run:
        await wait_up(run)
        async with OpcUaClientProcess(url(run, 0)) as client:
            assert client.connected["event"] == "connected", client.connected
            walk = [await client.send("job")]
            while walk[-1]["Status"] in (1, 2):
                walk.append(await client.send("next"))
            again = await client.send("next")  # past the end it stays so
        read = {name: await uaread(url(run, 0), name)
                for name in ("Count", "Index", "PickId", "Score", "Status", "JobId")}
        _, rec = await run.job_done(1)
        snap = run.daemon.snapshot()
    end = walk.pop()
    first = walk[0]
    assert (first["Status"], first["Count"], first["Index"]) == (Status.OK, PLATES, 1)
    assert [(r["Count"], r["Index"]) for r in walk] == [(PLATES, i) for i in range(1, PLATES + 1)]
    for r in (end, again):
        assert (r["Status"], r["StatusName"], r["Values"], r["Pose"]) == (
            Status.NOT_FOUND, "NOT_FOUND", [], [])
        assert (r["Count"], r["Index"], r["PickId"], r["Score"]) == (PLATES, PLATES + 1, 0, -1.0)
    answers = [*walk, end, again]
    assert [r["request_id"] for r in answers] == list(range(1, PLATES + 3))
    assert {r["JobId"] for r in answers} == {rec.job_id} == {1}  # the job's id, every answer
    assert {r["captured"] for r in answers} == {1}  # no image for a NEXT
    assert {r["state"] for r in answers} == {"Ready"}
    # float-exact: what the client read is the daemon's instance, in pick order
    listed = [i for i in rec.result.instances if i.status.pose_valid]
    assert [tuple(r["Values"]) for r in walk] == [
        i.target.values for i in listed if i.target is not None]
    assert [r["Score"] for r in walk] == [i.score for i in listed]
    assert [r["PickId"] for r in walk] == [i.pick_id for i in listed]
    for r in answers:  # the event carries the same pick-list fields as the variables
        assert r["ev"] is not None
        assert {k: r["ev"][k] for k in ("Count", "Index", "PickId", "Score", "Values")} == {
            k: r[k] for k in ("Count", "Index", "PickId", "Score", "Values")}
    check_against_truth(config, run, "kuka", [r["Values"] for r in walk])
    assert len(run.jobs) == 1  # NEXT took no image and made no job
    assert snap["next_answers"] == {"OK": PLATES - 1, "NOT_FOUND": 2}
    assert read == {"Count": str(PLATES), "Index": str(PLATES + 1), "PickId": "0",
                    "Score": "-1.0", "Status": str(int(Status.NOT_FOUND)), "JobId": "1"}


async def test_opcua_next_refusals_never_show_a_stale_pose() -> None:
    config = pallet_config("kuka", [MODBUS, OPEN_LINK])
    gated = GatedPipeline(config)
    daemon = Daemon(config, pipeline=gated)
    run = Run(daemon)
    await daemon.start()
    try:
        await wait_up(run)
        async with Plc(run.port(0)) as plc, OpcUaClientProcess(url(run, 1)) as client:
            no_job = await client.send("next")  # nothing located since start
            assert (await client.send("job"))["Count"] == PLATES
            await plc.trigger(1)  # another link's job: the scene may have changed
            assert (await plc.result(1))[Reg.STATUS] == Status.OK
            other = await client.send("next")  # the daemon's refusal, as a result
            no_list = await client.send("next")  # and now the link holds no list either

            assert (await client.send("job"))["Count"] == PLATES
            gated.gate.clear()
            await plc.trigger(2)
            await run.busy()
            busy = await client.send("next")  # another link's job runs
            gated.gate.set()
            assert (await plc.result(2))[Reg.STATUS] == Status.OK

            assert (await client.send("job"))["Count"] == PLATES
            gated.gate.clear()
            started = await client.send("start")
            await run.busy()
            own = await client.send("next")  # this link's job runs
            gated.gate.set()
            done = await client.send(f"wait {started['request_id']}")
        refusals = daemon.rooms.links.links["opcua"].refusals()
    finally:
        gated.gate.set()
        await daemon.stop()
    assert no_job == {"event": "refused", "code": "BadNoData"}
    assert no_list == {"event": "refused", "code": "BadNoData"}
    assert own == {"event": "refused", "code": "BadInvalidState"}
    for r, status in ((other, Status.BAD_REQUEST), (busy, Status.BUSY)):
        assert (r["Status"], r["JobId"], r["Values"], r["Pose"]) == (status, 0, [], [])
        assert (r["Count"], r["Index"], r["PickId"], r["Score"]) == (0, 0, 0, -1.0)
        assert r["state"] == "Ready"
    assert "belongs to link modbus_server" in other["Message"]
    assert (done["Status"], done["Count"], done["Index"]) == (Status.OK, PLATES, 1)
    assert refusals == {"BAD_REQUEST": 2, "BUSY": 1}
