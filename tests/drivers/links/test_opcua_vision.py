"""The OPC 40100 side of OpcUaLink (``drivers/links/opcua_vision.py``) against asyncua's client
over real TCP on 127.0.0.1: the official NodeSet's types, the PLC sequence of the standard
(SelectModeAutomatic -> PrepareRecipe -> StartSingleJob per part -> ResultReady /
GetResultById), wrong-state calls refused, results, recipes, configuration and the plain
variables. The daemon is stood in for by test_opcua's ``Daemon`` (fixed results), so the pose a
client reads is compared with the numbers the stand-in published. The second, independent
client stack (node-opcua) is tests/drivers/links/test_opcua_node.py; the real daemon
tests/integration/test_daemon_opcua_vision.py.
"""

from __future__ import annotations

import asyncio
import hashlib
from collections.abc import AsyncIterator
from typing import Any

import pytest
from asyncua import Client, ua
from asyncua.common.subscription import Subscription

from drivers.links.opcua import OpcUaLink
from drivers.links.opcua_nodeset import references_to_missing
from drivers.links.opcua_vision import (
    INSTANCE_URI,
    MV_URI,
    NODESET,
    NOT_IMPLEMENTED,
    register_binary_ids,
)
from tests.conftest import ua_client
from tests.drivers.links.test_opcua import POSE, Daemon, open_link, options, url

pytestmark = pytest.mark.timeout(120)

WAIT_S = 30.0
SHA256 = "3e67454155a9618e0981aa8b3ee248f7a9ee216f9f915b53eb26a69533c0cc62"
AUTO = "VisionStateMachine/AutomaticModeStateMachine"
RESULT_READY = 1024  # ResultReadyEventType in the NodeSet


class Events:
    """ResultReady (and the other) events of the VisionSystem object, as a client gets them."""

    def __init__(self, mv: int) -> None:
        self.mv = mv
        self.queue: asyncio.Queue[Any] = asyncio.Queue()

    def event_notification(self, event: Any) -> None:
        self.queue.put_nowait(event)

    async def next(self, type_id: int) -> Any:
        """The next event of type ``type_id`` (the NodeSet's number: 1024 ResultReady)."""
        async with asyncio.timeout(WAIT_S):
            while True:
                ev = await self.queue.get()
                if ev.EventType == ua.NodeId(type_id, self.mv):
                    return ev


class Vision:
    """A client's view of the VisionSystem: its namespaces, nodes by browse path, calls."""

    def __init__(self, client: Client, mv: int, idx: int) -> None:
        self.client, self.mv, self.idx = client, mv, idx
        self.vs = client.get_node(ua.NodeId("VisionSystem", idx))

    async def node(self, path: str) -> Any:
        parts = [p if ":" in p else f"{self.idx if p in PLAIN else self.mv}:{p}"
                 for p in path.split("/")]
        return await self.vs.get_child(parts)

    async def call(self, path: str, *args: Any) -> list[Any]:
        method = await self.node(path)
        parent = await self.node(path.rsplit("/", 1)[0]) if "/" in path else self.vs
        out = await parent.call_method(method, *args)
        return out if isinstance(out, list) else [out]

    async def refused(self, path: str, *args: Any) -> str:
        with pytest.raises(ua.UaStatusCodeError) as info:
            await self.call(path, *args)
        return type(info.value).__name__

    async def state(self) -> tuple[str, str]:
        top = await (await self.node("VisionStateMachine/0:CurrentState")).read_value()
        auto = await (await self.node(f"{AUTO}/0:CurrentState")).read_value()
        return top.Text, auto.Text or ""

    async def plain(self, name: str) -> Any:
        return await (await self.node(f"Plc/{name}")).read_value()


PLAIN = {"Plc", "State", "StateNumber", "AutoStateNumber", "PreparedRecipe", "JobId", "ResultJobId",
         "ResultState", "Status", "StatusName", "Vendor", "ValueNames", "Values", "Pose",
         "Count", "Index", "PickId", "Score", "ResultId", "Sequence", "StartJob", "Next",
         "ResultCount", "LatchSource", "LatchErrMm", "Along", "Across", "Theta", "Queued",
         "LatchCount", "LatchFrame", "Predict"}


@pytest.fixture
async def daemon() -> AsyncIterator[Daemon]:
    d = Daemon()
    yield d
    for task in list(d.tasks):
        task.cancel()


@pytest.fixture
async def link(daemon: Daemon) -> AsyncIterator[OpcUaLink]:
    lk = await open_link(daemon, options(old_only=False))  # the default models
    lk.set_recipes({0: "default", 2: "pallet"})
    yield lk
    await lk.close()


@pytest.fixture
async def vision(link: OpcUaLink) -> AsyncIterator[Vision]:
    client = ua_client(url(link), timeout=WAIT_S)
    async with client:
        await client.load_data_type_definitions()
        mv = await client.get_namespace_index(MV_URI)
        await register_binary_ids(client.get_node, mv)  # asyncua's own flaw, as the server
        idx = await client.get_namespace_index(INSTANCE_URI)
        yield Vision(client, mv, idx)


async def subscribe(v: Vision) -> tuple[Events, Subscription]:
    events = Events(v.mv)
    sub = await v.client.create_subscription(20, events)
    types = [v.client.get_node(ua.NodeId(i, v.mv)) for i in (1024, 1025, 1022, 1013)]
    await sub.subscribe_events(v.vs, types)
    return events, sub


def ext(kind: str, ident: str) -> Any:
    return getattr(ua, kind)(Id=ident)


def job_args(meas: str, part: str, recipe: str = "") -> list[Any]:
    return [ext("MeasIdDataType", meas), ext("PartIdDataType", part),
            ext("RecipeIdExternalDataType", recipe), ext("ProductIdDataType", ""),
            ua.Variant([], ua.VariantType.Variant)]


def content(result: Any) -> dict[str, Any]:
    """ResultContent's key/value pairs (each in a Variant) as a dict."""
    pairs = [kv.Value if isinstance(kv, ua.Variant) else kv for kv in result.ResultContent]
    return {kv.Key.Name: kv.Value.Value for kv in pairs}


# -- the NodeSet -----------------------------------------------------------------------------


def test_the_nodeset_is_the_official_file_with_its_licence() -> None:
    data = NODESET.read_bytes()
    assert hashlib.sha256(data).hexdigest() == SHA256
    head = data[:2000].decode()
    assert "OPC Foundation MIT License 1.00" in head
    assert '<Model ModelUri="http://opcfoundation.org/UA/MachineVision" Version="1.0.0"' in \
        data[:4000].decode()


async def test_the_type_hierarchy_is_browsed_from_the_official_nodeset(
        vision: Vision, link: OpcUaLink) -> None:
    v = vision
    base = v.client.get_node(ua.ObjectIds.BaseObjectType)
    vst = await base.get_child([f"{v.mv}:VisionSystemType"])
    assert vst.nodeid == ua.NodeId(1003, v.mv)
    assert (await v.vs.read_type_definition()) == vst.nodeid
    names = {(await c.read_browse_name()).to_string() for c in await v.vs.get_children()}
    assert {f"{v.mv}:{n}" for n in ("VisionStateMachine", "RecipeManagement",
                                   "ConfigurationManagement", "ResultManagement",
                                   "SafetyStateManagement")} <= names
    # the profile's mandatory methods are there; what vgripd does not implement is not
    for path in (f"{AUTO}/StartSingleJob", f"{AUTO}/Stop", f"{AUTO}/Abort",
                 "VisionStateMachine/Halt", "VisionStateMachine/Reset",
                 "RecipeManagement/PrepareRecipe", "RecipeManagement/GetRecipeListFiltered",
                 "ResultManagement/GetResultComponentsById",
                 "ConfigurationManagement/GetConfigurationList"):
        assert await (await v.node(path)).read_node_class() == ua.NodeClass.Method
    with pytest.raises(ua.UaError):
        await v.node("RecipeManagement/AddRecipe")
    # the nodes removed from the instance are gone without a trace: no reference to them
    server = link.server
    assert server is not None
    assert references_to_missing(server) == []
    aspace = server.iserver.aspace
    assert not [p for p in NOT_IMPLEMENTED if ua.NodeId(f"VisionSystem.{p}", v.idx) in aspace]
    # the event type's fields come from the NodeSet
    rr = v.client.get_node(ua.NodeId(1024, v.mv))
    fields = {(await c.read_browse_name()).Name for c in await rr.get_properties()}
    assert {"ResultId", "JobId", "ResultState", "ResultContent", "MeasId"} <= fields


# -- the PLC sequence ------------------------------------------------------------------------


async def test_the_plc_sequence_with_wrong_state_calls_refused(
        vision: Vision, daemon: Daemon) -> None:
    v = vision
    assert await v.state() == ("Preoperational", "")
    # wrong state: StartSingleJob before SelectModeAutomatic, and in Initialized
    assert await v.refused(f"{AUTO}/StartSingleJob", *job_args("m0", "p0")) == \
        "BadInvalidState"
    assert await v.call("VisionStateMachine/SelectModeAutomatic") == [0]
    assert await v.state() == ("Operational", "Initialized")
    assert await v.refused(f"{AUTO}/StartSingleJob", *job_args("m0", "p0")) == \
        "BadInvalidState"
    assert await v.refused(f"{AUTO}/Stop", 0, "") == "BadInvalidState"
    assert await v.refused("RecipeManagement/PrepareRecipe",
                           ext("RecipeIdExternalDataType", "nope"),
                           ext("RecipeIdInternalDataType", "")) == "BadInvalidArgument"
    internal, done, error = await v.call("RecipeManagement/PrepareRecipe",
                                         ext("RecipeIdExternalDataType", "pallet"),
                                         ext("RecipeIdInternalDataType", ""))
    assert (internal.Id, done, error) == ("2", True, 0)
    assert await v.state() == ("Operational", "Ready")
    events, sub = await subscribe(v)
    for n in (1, 2):
        job_id, error = await v.call(f"{AUTO}/StartSingleJob", *job_args(f"m{n}", f"p{n}"))
        assert error == 0
        ready = await events.next(RESULT_READY)
        assert ready.JobId.Id == job_id.Id
        assert (ready.MeasId.Id, ready.PartId.Id, ready.ResultState) == (f"m{n}", f"p{n}", 1)
        assert ready.InternalRecipeId.Id == "2"
        trigger = daemon.triggers[-1]
        assert (trigger.seq, trigger.recipe) == (int(job_id.Id), 2)
        _handle, result, error = await v.call("ResultManagement/GetResultById",
                                               ready.ResultId, 1000.0)
        assert error == 0
        assert result.JobId.Id == job_id.Id
        c = content(result)
        assert tuple(c["Values"]) == POSE  # exactly what the stand-in published
        assert (c["StatusName"], c["DaemonJobId"], c["Count"], c["Index"]) == (
            "OK", 100 + trigger.seq, 1, 1)
        assert content(ready) == c
        assert await v.state() == ("Operational", "Ready")
        assert (await v.plain("ResultId"), tuple(await v.plain("Values"))) == (
            ready.ResultId.Id, POSE)
    await sub.delete()
    # the list of results, newest last, filtered by PartId
    complete, count, _h, found, error = await v.call(
        "ResultManagement/GetResultListFiltered", 0, None, ext("PartIdDataType", "p2"),
        None, None, None, None, None, None, 0, 0, 1000.0)
    assert (complete, count, error, [r.PartId.Id for r in found]) == (True, 1, 0, ["p2"])
    assert await v.refused("ResultManagement/GetResultById",
                           ext("ResultIdDataType", "999"), 1000.0) == "BadNoMatch"


async def test_halt_during_a_job_ends_it_aborted_without_a_pose(
        vision: Vision, daemon: Daemon) -> None:
    v = vision
    daemon.hold = True
    await v.call("VisionStateMachine/SelectModeAutomatic")
    await v.call("RecipeManagement/PrepareRecipe", ext("RecipeIdExternalDataType", "0"),
                 ext("RecipeIdInternalDataType", ""))
    events, sub = await subscribe(v)
    job_id, _ = await v.call(f"{AUTO}/StartSingleJob", *job_args("m", "p"))
    assert await v.state() == ("Operational", "SingleExecution")
    assert await v.refused(f"{AUTO}/StartSingleJob", *job_args("m", "p")) == "BadInvalidState"
    assert await v.call("VisionStateMachine/Halt", 0, "") == [0]
    assert await v.state() == ("Halted", "")
    daemon.released.set()
    ready = await events.next(RESULT_READY)
    assert (ready.JobId.Id, ready.ResultState) == (job_id.Id, 3)  # Aborted
    assert content(ready)["Values"] in (None, [])
    assert await v.plain("Pose") in (None, [])
    assert await v.refused("VisionStateMachine/SelectModeAutomatic") == "BadInvalidState"
    assert await v.call("VisionStateMachine/Reset", 0, "") == [0]
    assert await v.state() == ("Preoperational", "")
    await sub.delete()


class Permits(Daemon):
    """The stand-in daemon answering one job per permit the test gives (``go``)."""

    def __init__(self) -> None:
        super().__init__()
        self.permits = asyncio.Semaphore(0)
        self.asked = asyncio.Condition()

    def on_trigger(self, trigger: Any) -> None:
        super().on_trigger(trigger)
        task = asyncio.create_task(self._told())
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)

    async def _told(self) -> None:
        async with self.asked:
            self.asked.notify_all()

    async def answer(self, trigger: Any) -> None:
        assert self.link is not None
        result = self.result_for(trigger)
        await self.link.image_captured(trigger.seq, result.job_id)
        await self.permits.acquire()
        await self.link.publish(trigger.seq, result)

    async def started(self, n: int) -> None:
        """Until the daemon was asked for its ``n``-th job."""
        async with asyncio.timeout(WAIT_S), self.asked:
            await self.asked.wait_for(lambda: len(self.triggers) >= n)


@pytest.fixture
async def permits() -> AsyncIterator[Permits]:
    d = Permits()
    yield d
    for task in list(d.tasks):
        task.cancel()


async def test_start_continuous_runs_jobs_until_stop_and_abort_ends_at_once(
        permits: Permits) -> None:
    d = permits
    link = await open_link(d, options(old_only=False))
    try:
        client = ua_client(url(link), timeout=WAIT_S)
        async with client:
            await client.load_data_type_definitions()
            mv = await client.get_namespace_index(MV_URI)
            await register_binary_ids(client.get_node, mv)
            v = Vision(client, mv, await client.get_namespace_index(INSTANCE_URI))
            assert await v.refused(f"{AUTO}/StartContinuous", *job_args("m", "p")) == \
                "BadInvalidState"  # not in Ready
            await v.call("VisionStateMachine/SelectModeAutomatic")
            await v.call("RecipeManagement/PrepareRecipe", ext("RecipeIdExternalDataType", "0"),
                         ext("RecipeIdInternalDataType", ""))
            events, sub = await subscribe(v)
            job_id, error = await v.call(f"{AUTO}/StartContinuous", *job_args("m", "p"))
            assert error == 0
            assert await v.state() == ("Operational", "ContinuousExecution")
            assert await v.plain("AutoStateNumber") == 8
            results = []
            for n in (1, 2):  # each result, then the next job of the chain
                d.permits.release()
                results.append(await events.next(RESULT_READY))
                await d.started(n + 1)
            # only the chain runs: a single job and a Next are refused meanwhile
            assert await v.refused(f"{AUTO}/StartSingleJob", *job_args("m", "p")) == \
                "BadInvalidState"
            assert await v.refused("Plc/Next") == "BadInvalidState"
            assert await v.call(f"{AUTO}/Stop", 0, "") == [0]  # ends after the running job
            assert await v.state() == ("Operational", "ContinuousExecution")
            d.permits.release()
            results.append(await events.next(RESULT_READY))
            assert await v.state() == ("Operational", "Ready")
            # no job after the stopped one: the next request is this single job
            single, _ = await v.call(f"{AUTO}/StartSingleJob", *job_args("m", "p"))
            assert [t.seq for t in d.triggers] == [1, 2, 3, 4]
            assert single.Id == "4"
            d.permits.release()
            await events.next(RESULT_READY)
            # Abort ends the chain at once: the running job's result is ABORTED, no pose
            chain2, _ = await v.call(f"{AUTO}/StartContinuous", *job_args("m2", "p2"))
            await d.started(5)
            assert await v.call(f"{AUTO}/Abort", 0, "") == [0]
            assert await v.state() == ("Operational", "Ready")
            d.permits.release()
            aborted = await events.next(RESULT_READY)
            await sub.delete()
    finally:
        await link.close()
    assert [r.JobId.Id for r in results] == [job_id.Id] * 3  # one job, one result per run
    assert len({r.ResultId.Id for r in results}) == 3
    for r, seq in zip(results, (1, 2, 3), strict=True):
        assert (r.ResultState, r.MeasId.Id, r.PartId.Id) == (1, "m", "p")
        assert (content(r)["DaemonJobId"], tuple(content(r)["Values"])) == (100 + seq, POSE)
    assert (aborted.JobId.Id, aborted.ResultState, aborted.PartId.Id) == (chain2.Id, 3, "p2")
    assert content(aborted)["Values"] in (None, [])
    assert len(d.triggers) == 5


async def test_a_plc_without_structures_prepares_a_recipe_by_its_plain_name(
        vision: Vision, daemon: Daemon) -> None:
    v = vision
    prepare = f"Plc/{v.idx}:PrepareRecipe"  # the standard's is RecipeManagement/PrepareRecipe
    await v.call("VisionStateMachine/SelectModeAutomatic")
    assert await v.refused(prepare, "nope") == "BadInvalidArgument"
    assert await v.refused(prepare, "") == "BadInvalidArgument"
    assert await v.refused(prepare, 2) == "BadInvalidArgument"  # a String, not a number
    assert await v.state() == ("Operational", "Initialized")
    assert await v.call(prepare, "pallet") == ["2", 0]
    assert await v.state() == ("Operational", "Ready")
    assert await v.plain("PreparedRecipe") == "2"
    events, sub = await subscribe(v)
    job, error = await v.call("Plc/StartJob", "")  # the prepared recipe
    assert error == 0
    got = await events.next(RESULT_READY)
    await sub.delete()
    assert got.JobId.Id == job
    assert (got.InternalRecipeId.Id, daemon.triggers[-1].recipe) == ("2", 2)
    assert await v.call(prepare, "0") == ["0", 0]  # by number too
    assert await v.plain("PreparedRecipe") == "0"
    await v.call("VisionStateMachine/Halt", 0, "")
    assert await v.refused(prepare, "pallet") == "BadInvalidState"
    assert await v.plain("PreparedRecipe") == "0"
