"""The conveyor on OpcUaLink (``drivers/links/opcua_belt.py``) against asyncua's client over TCP
on 127.0.0.1, both address spaces (the default models): the latch variables a client writes
travel with the request that follows, in each namespace; ``Predict(Count)`` hands its count to
the daemon; a belt result shows in the variables (data before the request's id), in both
ResultReady events and in OPC 40100's ResultContent; Predict without a conveyor and bad
arguments are refused. The daemon is test_opcua's stand-in: what a client reads is compared
with the numbers it published. The real daemon on a simulated belt is
tests/integration/test_daemon_opcua_conveyor.py."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
from collections.abc import AsyncIterator
from typing import Any

import pytest
from asyncua import Client, ua

from drivers.links.opcua import OpcUaLink
from drivers.links.opcua_vision import INSTANCE_URI, MV_URI, register_binary_ids
from tests.conftest import ua_client
from tests.drivers.links.test_opcua import POSE, Daemon, kuka_result, options, until, url
from tests.drivers.links.test_opcua_vision import AUTO, RESULT_READY, Vision, content, job_args
from vgripd.peer.jobcore import Command
from vgripd.service.links.protocol import Trigger
from vgripd.types import BeltPose, JobResult

pytestmark = pytest.mark.timeout(120)

WAIT_S = 30.0
OLD_URI = "urn:vgripd:machine-vision"
WRAP = 1 << 32
BELT_NAMES = ("ResultCount", "LatchSource", "LatchErrMm", "Along", "Across", "Theta", "Queued")


def count_for(seq: int) -> int:
    """The count a client latches for request ``seq``: the 32-bit counter wraps at seq 3."""
    return (WRAP - 25 + 10 * seq) % WRAP


def belt_of(trigger: Trigger) -> BeltPose:
    """What the stand-in publishes for ``trigger``: the count the request carried, numbers
    that name the request."""
    seq = trigger.seq
    return BeltPose(trigger.latch_count or 0, 1, 0.05, 500.0 + seq, -7.5 - seq, 12.25 + seq,
                    seq % 5)


def belt_result(trigger: Trigger) -> JobResult:
    return dataclasses.replace(kuka_result(100 + trigger.seq), belt=belt_of(trigger))


def shown(belt: BeltPose) -> dict[str, Any]:
    return dict(zip(BELT_NAMES, (belt.count, belt.source, belt.error_mm, belt.along_mm,
                                 belt.across_mm, belt.theta_deg, belt.queued), strict=True))


@pytest.fixture
async def daemon() -> AsyncIterator[Daemon]:
    d = Daemon(belt_result)
    yield d
    for task in list(d.tasks):
        task.cancel()


async def opened(daemon: Daemon, conveyor: bool) -> OpcUaLink:
    """The link as the daemon opens it: told whether a recipe has a conveyor, then opened."""
    link = OpcUaLink("cell", options(old_only=False))
    link.set_recipes({0: "default"})
    link.set_conveyor(conveyor)
    daemon.link = link
    await link.open(daemon.on_trigger)
    return link


class Cell:
    """A client of both namespaces: OPC 40100 (``v``) and the older one (``old``)."""

    def __init__(self, client: Client, v: Vision, old: int) -> None:
        self.client, self.v, self.old = client, v, old
        self.old_vs = client.get_node(self.old_id("VisionSystem"))

    def old_id(self, path: str) -> ua.NodeId:
        return ua.NodeId(ua.String(path), ua.Int16(self.old))

    def plain_id(self, name: str) -> ua.NodeId:
        return ua.NodeId(ua.String(f"VisionSystem.Plc.{name}"), ua.Int16(self.v.idx))

    async def latch(self, node: ua.NodeId, count: int, frame: int | None = None) -> None:
        """LatchCount (and LatchFrame, the next node) written in one Write request."""
        nodes = [self.client.get_node(node)]
        values = [ua.DataValue(ua.Variant(count, ua.VariantType.UInt32))]
        if frame is not None:
            name = node.Identifier.replace("LatchCount", "LatchFrame")
            nodes.append(self.client.get_node(ua.NodeId(ua.String(name), node.NamespaceIndex)))
            values.append(ua.DataValue(ua.Variant(frame, ua.VariantType.UInt32)))
        await self.client.write_values(nodes, values)

    async def old_call(self, method: str, *args: Any) -> Any:
        return await self.old_vs.call_method(self.old_id(f"VisionSystem.{method}"), *args)

    async def ready(self) -> None:
        await self.v.call("VisionStateMachine/SelectModeAutomatic")
        assert await self.v.call(f"Plc/{self.v.idx}:PrepareRecipe", "0") == ["0", 0]


@contextlib.asynccontextmanager
async def cell(link: OpcUaLink) -> AsyncIterator[Cell]:
    client = ua_client(url(link), timeout=WAIT_S)
    async with client:
        await client.load_data_type_definitions()
        mv = await client.get_namespace_index(MV_URI)
        await register_binary_ids(client.get_node, mv)
        v = Vision(client, mv, await client.get_namespace_index(INSTANCE_URI))
        yield Cell(client, v, await client.get_namespace_index(OLD_URI))


def u32(n: int) -> ua.Variant:
    return ua.Variant(n, ua.VariantType.UInt32)


async def test_the_latch_in_place_at_a_request_travels_with_it_in_both_namespaces(
        daemon: Daemon) -> None:
    link = await opened(daemon, conveyor=True)
    try:
        async with cell(link) as c:
            async def answered() -> None:
                await until(lambda: not daemon.tasks, "published")

            # the older namespace: LatchCount/LatchFrame, then the call
            await c.latch(c.old_id("VisionSystem.LatchCount"), WRAP - 1, 17)
            await c.old_call("StartSingleJob")
            await answered()
            await c.old_call("Next")  # a conveyor: the queue's, no list needed here
            await answered()
            await c.old_call("Predict", u32(WRAP - 1))
            await answered()
            # OPC 40100: Plc.LatchCount/LatchFrame for the plain and the standard's calls
            await c.ready()
            await c.latch(c.plain_id("LatchCount"), 5, 6)
            _job, error = await c.v.call("Plc/StartJob", "")
            assert error == 0
            await answered()
            await c.latch(c.plain_id("LatchCount"), 0)  # the frame stays as written
            await c.v.call("Plc/Next")
            await answered()
            await c.v.call("Plc/Predict", u32(300))
            await answered()
            await c.latch(c.plain_id("LatchCount"), 7)
            await c.v.call(f"{AUTO}/StartSingleJob", *job_args("m", "p"))
            await answered()
            plain = await c.client.read_values(
                [c.client.get_node(c.plain_id(n)) for n in ("LatchCount", "LatchFrame")])
    finally:
        await link.close()
    assert [(t.command, t.latch_count, t.latch_frame) for t in daemon.triggers] == [
        (Command.TRIGGER, WRAP - 1, 17), (Command.NEXT, WRAP - 1, 17),
        (Command.PREDICT, WRAP - 1, None),
        (Command.TRIGGER, 5, 6), (Command.NEXT, 0, 6), (Command.PREDICT, 300, None),
        (Command.TRIGGER, 7, 6)]
    assert plain == [7, 6]  # the client's, not touched by vgripd


async def test_a_belt_result_is_shown_whole_before_its_id_in_both_namespaces(
        daemon: Daemon) -> None:
    """Between any two steps of the loop (where a Read could be served) the result names no
    request or shows that request's belt result; the events and ResultContent carry it."""
    link = await opened(daemon, conveyor=True)
    assert link.server is not None
    assert link.space is not None
    assert link.vision is not None
    server, space, vision = link.server, link.space, link.vision
    old_nodes = [space.nodes[f"Result.{n}"] for n in ("RequestId", "ResultCount", "Along")]
    plain_nodes = [vision._plain[n][0] for n in ("ResultId", "ResultJobId", "ResultCount",
                                                  "Along")]
    seen: list[tuple[Any, ...]] = []
    stop = asyncio.Event()

    async def observe() -> None:
        while not stop.is_set():
            seen.append(tuple(server.read_attribute_value(n).Value.Value
                              for n in old_nodes + plain_nodes))
            await asyncio.sleep(0)

    events: list[Any] = []
    all_in = asyncio.Event()  # both events of every result

    class Handler:
        def event_notification(self, event: Any) -> None:
            events.append(event)
            if len(events) == 2 * 20:
                all_in.set()

    try:
        async with cell(link) as c:
            sub = await c.client.create_subscription(20, Handler())
            await sub.subscribe_events(c.v.vs, c.client.get_node(ua.NodeId(RESULT_READY,
                                                                           c.v.mv)))
            await sub.subscribe_events(c.old_vs, c.client.get_node(
                c.old_id("ResultReadyEventType")))
            observer = asyncio.create_task(observe())
            for seq in range(1, 11):
                await c.latch(c.old_id("VisionSystem.LatchCount"), count_for(seq))
                await c.old_call("StartSingleJob")
                await until(lambda: not daemon.tasks, "published")
            await c.ready()
            for seq in range(11, 21):
                await c.latch(c.plain_id("LatchCount"), count_for(seq))
                await c.v.call("Plc/StartJob", "")
                await until(lambda: not daemon.tasks, "published")
            stop.set()
            await observer
            async with asyncio.timeout(WAIT_S):
                await all_in.wait()
            await sub.delete()
            old = await c.client.read_values([c.client.get_node(c.old_id(
                f"VisionSystem.Result.{n}")) for n in BELT_NAMES])
            plain = await c.client.read_values([c.client.get_node(c.plain_id(n))
                                                for n in BELT_NAMES])
    finally:
        await link.close()
    want = {t.seq: shown(belt_of(t)) for t in daemon.triggers}
    assert [w["ResultCount"] for w in want.values()] == [count_for(s) for s in range(1, 21)]
    for rid, count, along, result_id, job, plain_count, plain_along in seen:
        assert rid == 0 or (count, along) == (want[rid]["ResultCount"], want[rid]["Along"])
        assert result_id == "" or (plain_count, plain_along) == (
            want[int(job)]["ResultCount"], want[int(job)]["Along"])
    assert {s[0] for s in seen} >= {0, 20}
    assert dict(zip(BELT_NAMES, old, strict=True)) == want[20]
    assert dict(zip(BELT_NAMES, plain, strict=True)) == want[20]
    ready = [e for e in events if hasattr(e, "ResultContent")]
    old_events = [e for e in events if not hasattr(e, "ResultContent")]
    assert [int(e.JobId.Id) for e in ready] == list(range(1, 21))
    for e in ready:
        c40100 = content(e)
        assert {n: c40100[n] for n in BELT_NAMES} == want[int(e.JobId.Id)]
        assert tuple(c40100["Values"]) == POSE
    assert [e.RequestId for e in old_events] == list(range(1, 21))
    for e in old_events:
        assert {n: getattr(e, n) for n in BELT_NAMES} == want[e.RequestId]


async def test_predict_without_a_conveyor_and_bad_latch_input_are_refused(
        daemon: Daemon) -> None:
    link = await opened(daemon, conveyor=False)
    try:
        async with cell(link) as c:
            refused = []
            for call in (lambda: c.old_call("Predict", u32(5)),
                         lambda: c.old_call("Predict"),
                         lambda: c.old_call("Predict", u32(5), u32(6)),
                         lambda: c.old_call("Predict", "5"),
                         lambda: c.old_call("Predict", ua.Variant(-1, ua.VariantType.Int64)),
                         lambda: c.old_call("Next")):
                with pytest.raises(ua.UaStatusCodeError) as info:
                    await call()
                refused.append(type(info.value).__name__)
            await c.ready()
            assert await c.v.refused("Plc/Predict", u32(5)) == "BadNotSupported"
            assert await c.v.refused("Plc/Predict", "x") == "BadInvalidArgument"
            assert await c.v.plain("State") == "Operational.Ready"  # nothing started
            wrong = []
            for node in (c.old_id("VisionSystem.LatchCount"), c.plain_id("LatchFrame")):
                for variant in (ua.Variant(-1, ua.VariantType.Int32), ua.Variant("12")):
                    with pytest.raises(ua.UaStatusCodeError) as info:
                        await c.client.get_node(node).write_value(ua.DataValue(variant))
                    wrong.append(type(info.value).__name__)
            assert await c.client.get_node(c.plain_id("LatchFrame")).read_value() == 0
    finally:
        await link.close()
    assert refused == ["BadNotSupported", "BadArgumentsMissing", "BadTooManyArguments",
                       "BadInvalidArgument", "BadInvalidArgument", "BadNoData"]
    assert wrong == ["BadTypeMismatch"] * 4
    assert daemon.triggers == []
    assert link.refusals() == {"BAD_REQUEST": 8}
