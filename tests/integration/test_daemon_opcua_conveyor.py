"""Conveyor tracking over OPC UA end to end: the daemon in-process with a conveyor recipe and an
``opcua`` link (the default models), and asyncua's client acting as a PLC without structure
support on ``VisionSystem/Plc``: it writes ``LatchCount`` before each ``StartJob`` and ``Next``,
polls ``ResultId`` until it changes, reads the result variables in one Read request, and asks
``Predict(Count)`` for an intercept.

The belt is tests/integration/belt_cell.py's, simulated independently of the code under test,
with its 32-bit counter wrapping during the run; every answer is checked against its truth at
the count the answer names (``ResultCount``): the pose, Along/Across/Theta, each part served
once in belt order, a part past the window dropped, Predict answered inside the window and
refused past it. The same walk on Modbus: tests/integration/test_daemon_conveyor.py."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua

from drivers.links.opcua_vision import INSTANCE_URI
from tests.conftest import ua_client
from tests.integration.belt_cell import (
    COUNTS_PER_MM,
    PARTS,
    WINDOW,
    conveyor_data,
    count_at,
    located,
    render,
    travel_of,
    visible,
)
from tests.integration.test_daemon import running
from vgripd.config import config_from_dict
from vgripd.service.links.protocol import LinkState
from vgripd.types import Status
from vgripd.vision.scene import T_base_obj_ref

pytestmark = pytest.mark.timeout(300)

WAIT_S = 60.0
LINK = {"type": "opcua", "host": "127.0.0.1", "port": 0, "security": ["None"],
        "allow_anonymous": True}
#: What the PLC reads after each answer, in one Read request.
READ = ("Status", "Values", "Count", "ResultCount", "LatchSource", "LatchErrMm", "Along",
        "Across", "Theta", "Queued", "ResultId")


class PlainPlc:
    """A PLC's OPC UA client without structures: plain variables and plain methods only."""

    def __init__(self, client: Client, idx: int) -> None:
        self.client, self.idx = client, idx
        self.plc = client.get_node(self.id("Plc"))

    def id(self, path: str) -> ua.NodeId:
        return ua.NodeId(ua.String(f"VisionSystem.{path}"), ua.Int16(self.idx))

    async def read(self, names: tuple[str, ...]) -> dict[str, Any]:
        nodes = [self.client.get_node(self.id(f"Plc.{n}")) for n in names]
        return dict(zip(names, await self.client.read_values(nodes), strict=True))

    async def call(self, method: str, *args: Any) -> Any:
        return await self.plc.call_method(self.id(f"Plc.{method}"), *args)

    async def request(self, method: str, *args: Any, count: int | None = None) -> dict[str, Any]:
        """``count`` written to LatchCount, then the call; the answer once ResultId shows a
        new result."""
        if count is not None:
            await self.client.get_node(self.id("Plc.LatchCount")).write_value(
                ua.DataValue(ua.Variant(count, ua.VariantType.UInt32)))
        before = (await self.read(("ResultId",)))["ResultId"]
        job, error = await self.call(method, *args)
        assert (error, job != "") == (0, True)
        async with asyncio.timeout(WAIT_S):
            while True:
                answer = await self.read(READ)  # one Read request, as a PLC's cycle does
                if answer["ResultId"] not in ("", before):
                    return answer
                await asyncio.sleep(0.02)  # polled: the PLC reads, nothing is pushed


async def test_a_plc_on_opc_ua_walks_the_belt_once_per_part_at_the_latched_counts(
        tmp_path: Path) -> None:
    frames = [0.0, 150.0, 300.0, 450.0, 600.0]
    await render(tmp_path, frames)
    data = conveyor_data({"type": "replay", "folder": str(tmp_path), "left_glob": "left_*.png",
                          "right_glob": "right_*.png"})
    config = config_from_dict({**data, "links": [LINK]})
    T_ref = T_base_obj_ref(config)
    served: list[int] = []

    async def trigger(frame: int) -> None:
        r = await plc.request("StartJob", "", count=count_at(frames[frame]))
        assert r["Status"] == Status.OK, r
        assert r["ResultCount"] == count_at(frames[frame])
        assert r["LatchSource"] == 1
        assert r["LatchErrMm"] == pytest.approx(0.5 / COUNTS_PER_MM, abs=1e-6)
        assert r["Count"] == len(visible(frames[frame]))
        part = located(r["Values"], r["Along"], r["Across"], r["Theta"], frames[frame], T_ref)
        assert part in visible(frames[frame])

    async def next_part(travel_now: float) -> int | None:
        r = await plc.request("Next", count=count_at(travel_now))
        if r["Status"] == Status.NOT_FOUND:
            assert r["Values"] in (None, [])
            return None
        assert r["Status"] == Status.OK, r
        at = travel_of(r["ResultCount"])  # the count of the image that saw it, not now
        assert at in frames
        part = located(r["Values"], r["Along"], r["Across"], r["Theta"], at, T_ref)
        assert PARTS[part][0] + travel_now <= WINDOW[1]  # still in reach now
        served.append(part)
        return part

    def u32(n: int) -> ua.Variant:
        return ua.Variant(n, ua.VariantType.UInt32)

    async with running(config) as run:
        await run.daemon.wait_for(lambda: all(link.health().state is LinkState.UP
                                              for link in run.daemon.rooms.links.links.values()), WAIT_S)
        async with ua_client(f"opc.tcp://127.0.0.1:{run.port()}/vgripd", timeout=WAIT_S) as client:
            plc = PlainPlc(client, await client.get_namespace_index(INSTANCE_URI))
            vsm = client.get_node(plc.id("VisionStateMachine"))
            await vsm.call_method(plc.id("VisionStateMachine.SelectModeAutomatic"))
            assert await plc.call("PrepareRecipe", "0") == ["0", 0]
            await trigger(0)  # parts 0 and 1
            await trigger(1)  # parts 1 (again) and 2
            await trigger(2)  # parts 2 (again) and 3; the counter wrapped at travel 300
            # at travel 350 part 0 is at 1050, past the window's end (1000): dropped
            assert await next_part(350.0) == 1
            # Predict: where part 1 will be at travel 380 (inside the window), at 500 (past)
            r = await plc.request("Predict", u32(count_at(380.0)))
            assert (r["Status"], r["ResultCount"]) == (Status.OK, count_at(380.0))
            assert located(r["Values"], r["Along"], r["Across"], r["Theta"], 380.0, T_ref) == 1
            r = await plc.request("Predict", u32(count_at(500.0)))
            assert r["Status"] == Status.OUT_OF_WORKSPACE
            assert r["Values"] in (None, [])
            await trigger(3)  # parts 3 (again) and 4
            assert [await next_part(455.0) for _ in range(3)] == [2, 3, 4]
            await trigger(4)  # part 4 again, already served: not queued again
            assert await next_part(610.0) is None
            queued = (await plc.read(("Queued",)))["Queued"]
        conveyor = run.daemon.snapshot()["conveyor"]["0"]
    assert served == [1, 2, 3, 4]  # each once, downstream first; part 0 missed
    sightings = sum(len(visible(t)) for t in frames)
    assert conveyor["seen"] == sightings == 9
    assert conveyor["duplicates"] == sightings - len(PARTS) == 4
    assert (conveyor["dropped"], conveyor["served"], conveyor["queued"], queued) == (1, 4, 0, 0)
