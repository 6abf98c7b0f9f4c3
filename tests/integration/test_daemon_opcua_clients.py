"""The ``opcua`` link with clients that behave like UaExpert or a cell computer: subscriptions
with a publishing interval (data changes of the result variables and the ResultReady event,
no polling), two clients at once, SelectRecipe with a recipe that does not exist, a client
coming back after the daemon restarted.

The clients are asyncua's ``Client`` over real TCP, in the test's process (the daemon's job
work runs on its job thread, so the loop is free to serve them). The link serves the older
namespace alone (``models = ["vgripd"]``): these clients are written against it.
"""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import tomllib
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import REPO, ua_client
from tests.integration.test_daemon import Run, running
from tests.integration.test_daemon_opcua import free_port
from vgripd.config import config_from_dict
from vgripd.service.links.protocol import LinkState
from vgripd.sim.opcua_client import OpcUaClientProcess
from vgripd.types import Status

asyncua = pytest.importorskip("asyncua")
from asyncua import ua  # noqa: E402
from asyncua.ua.uaerrors import UaStatusCodeError  # noqa: E402

pytestmark = pytest.mark.timeout(180)

SAMPLE = REPO / "config" / "samples" / "recipes.toml"
NS = "urn:vgripd:machine-vision"
WATCHED = ("RequestId", "Sequence", "Status", "RecipeId", "Values", "JobId")
WAIT_S = 60.0


def opcua_config(port: int = 0) -> Any:
    """The two-plate sample, the camera rendering each job's recipe, an open OPC UA link."""
    data = tomllib.loads(SAMPLE.read_text())
    data["camera"].update(recipe="job", seed=4, max_tilt_deg=2.0)
    data["links"] = [{"type": "opcua", "host": "127.0.0.1", "port": port,
                      "security": ["None"], "allow_anonymous": True, "models": ["vgripd"]}]
    data["status"] = {"port": 0}
    data["daemon"] = {"worker": False}
    return config_from_dict(data, str(SAMPLE))


class Watcher:
    """A subscription's handler: every data change and event, in arrival order, into one
    queue (what a client's publish responses carry)."""

    def __init__(self) -> None:
        self.queue: asyncio.Queue[tuple[str, Any]] = asyncio.Queue()
        self.names: dict[Any, str] = {}
        self.latest: dict[str, Any] = {}

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        name = self.names[node]
        self.latest[name] = val
        self.queue.put_nowait((name, val))

    def event_notification(self, event: Any) -> None:
        fields = event.get_event_props_as_fields_dict()
        self.queue.put_nowait(("event", {k: fields[k].Value for k in
                                         ("RequestId", "ResultStatus", "Values", "RecipeId")}))

    async def until(self, name: str, value: Any) -> dict[str, Any]:
        """Wait for a notification ``name == value``; the variables as then known."""
        async with asyncio.timeout(WAIT_S):
            while True:
                got, val = await self.queue.get()
                if got == name and (val == value if name != "event"
                                    else val["RequestId"] == value):
                    return dict(self.latest, event=val if name == "event" else None)


@asynccontextmanager
async def client(url: str, interval_ms: float = 100.0) -> AsyncIterator[tuple[Any, Watcher]]:
    """A connected client with one subscription (``interval_ms`` publishing interval) on the
    result variables and the ResultReady event."""
    c = ua_client(url, timeout=30)
    await c.connect()
    try:
        idx = await c.get_namespace_index(NS)
        watcher = Watcher()
        sub = await c.create_subscription(interval_ms, watcher)
        nodes = [c.get_node(ua.NodeId(ua.String(f"VisionSystem.Result.{n}"), ua.Int16(idx)))
                 for n in WATCHED]
        watcher.names = dict(zip(nodes, WATCHED, strict=True))
        await sub.subscribe_data_change(nodes)
        vs = c.get_node(ua.NodeId(ua.String("VisionSystem"), ua.Int16(idx)))
        etype = c.get_node(ua.NodeId(ua.String("ResultReadyEventType"), ua.Int16(idx)))
        await sub.subscribe_events(vs, etype)
        c.vgripd_idx = idx  # type: ignore[attr-defined]
        c.vgripd_vs = vs  # type: ignore[attr-defined]
        yield c, watcher
    finally:
        await c.disconnect()


async def call(c: Any, method: str, *args: Any) -> Any:
    idx = c.vgripd_idx
    return await c.vgripd_vs.call_method(ua.NodeId(ua.String(f"VisionSystem.{method}"),
                                                   ua.Int16(idx)), *args)


async def link_up(run: Run) -> str:
    await run.daemon.wait_for(lambda: all(link.health().state is LinkState.UP
                                          for link in run.daemon.rooms.links.links.values()), WAIT_S)
    return f"opc.tcp://127.0.0.1:{run.port(0)}/vgripd"


async def test_two_subscribed_clients_see_every_result_whole() -> None:
    """Client A selects recipes and starts jobs; both clients learn each result from their
    subscriptions only: at the notification of a RequestId, the Values, Status and RecipeId
    they hold are that request's, and the event carries the same.

    B's publishing interval (3 s) is longer than a job, so the retraction of RequestId at the
    start and the result mostly fall into one publish response: before the fix its
    RequestId notification came first and B held the previous request's values."""
    async with running(opcua_config()) as run:
        url = await link_up(run)
        async with client(url, 50.0) as (a, wa), client(url, 3000.0) as (_, wb):
            for n, recipe in enumerate((1, 2, 0, 2), start=1):
                await call(a, "SelectRecipe", ua.Variant(recipe, ua.VariantType.UInt16))
                rid = await call(a, "StartSingleJob")
                _, record = await run.job_done(n)
                target = record.result.target
                assert target is not None, record.result.message
                for w in (wa, wb):
                    seen = await w.until("RequestId", rid)
                    assert seen["Status"] == Status.OK
                    assert seen["RecipeId"] == recipe
                    assert seen["JobId"] == record.job_id
                    assert tuple(seen["Values"]) == target.values
                    ev = (await w.until("event", rid))["event"]
                    assert (ev["ResultStatus"], ev["RecipeId"]) == (Status.OK, recipe)
                    assert tuple(ev["Values"]) == target.values
        assert run.daemon.snapshot()["counters"]["OK"] == 4


async def test_select_recipe_that_does_not_exist() -> None:
    """SelectRecipe(7) in a config with recipes 0, 1, 2: refused at once, naming nothing it
    cannot know; the selected recipe stays what it was, and a job runs that one."""
    async with running(opcua_config()) as run:
        url = await link_up(run)
        async with client(url) as (a, wa):
            await call(a, "SelectRecipe", ua.Variant(2, ua.VariantType.UInt16))
            with pytest.raises(UaStatusCodeError) as refused:
                await call(a, "SelectRecipe", ua.Variant(7, ua.VariantType.UInt16))
            assert refused.value.code == ua.StatusCodes.BadInvalidArgument
            rid = await call(a, "StartSingleJob")
            seen = await wa.until("RequestId", rid)
            assert (seen["Status"], seen["RecipeId"]) == (Status.OK, 2)
        link = next(iter(run.daemon.rooms.links.links.values()))
        assert link.refusals()["BAD_REQUEST"] == 1


async def test_a_client_comes_back_after_the_daemon_restarts() -> None:
    """The daemon stops with a subscribed client connected and starts again on the same port:
    a client connecting anew gets results; the first one's connection ended cleanly."""
    async with running(opcua_config()) as run:
        url = await link_up(run)
        port = run.port(0)
        c = ua_client(url, timeout=30)
        await c.connect()
        await c.create_subscription(100, Watcher())
    # The daemon is stopped: the client's next request fails, it does not hang.
    with pytest.raises((ConnectionError, UaStatusCodeError, asyncio.TimeoutError)):
        await c.get_namespace_index(NS)
    await c.disconnect()
    async with running(opcua_config(port)) as run:
        url = await link_up(run)
        async with client(url) as (a, wa):
            rid = await call(a, "StartSingleJob")
            assert rid == 1
            assert (await wa.until("RequestId", rid))["Status"] == Status.OK


async def test_sigterm_with_subscribed_clients_connected(tmp_path: Path) -> None:
    """`vgripd run` (what systemd starts) with two connected clients, each subscribed to the
    ResultReady event, one of them with a job just started: SIGTERM ends it with exit 0 and
    no traceback, the worker killed with the aborted job is not replaced, and both clients
    see their connection end (an error, not a hang)."""
    port = free_port()
    cfg = tmp_path / "vgripd.toml"
    cfg.write_text(f"""
[camera]
type = "synthetic"
seed = 3

[[links]]
type = "opcua"
host = "127.0.0.1"
port = {port}
security = ["None"]
allow_anonymous = true
models = ["vgripd"]

[status]
enabled = false
""")
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "vgripd", "run", "-c", str(cfg), cwd=REPO, env=env,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        url = f"opc.tcp://127.0.0.1:{port}/vgripd"
        async with asyncio.timeout(WAIT_S):
            while True:  # up when the port answers
                try:
                    _, w = await asyncio.open_connection("127.0.0.1", port)
                    w.close()
                    break
                except OSError:
                    await asyncio.sleep(0.1)
        async with OpcUaClientProcess(url) as c1, OpcUaClientProcess(url) as c2:
            assert (c1.connected["event"], c2.connected["event"]) == ("connected", "connected")
            answer = await c1.send("job")
            assert answer.get("Status") == Status.OK, answer
            assert (await c2.send("start"))["event"] == "started"
            proc.send_signal(signal.SIGTERM)
            async with asyncio.timeout(WAIT_S):
                _, err = await proc.communicate()
            for c in (c1, c2):
                answer = await c.send("state")
                assert answer["event"] == "error", answer
                assert "disconnected" in answer["error"] or "Connection" in answer["error"]
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    stderr = err.decode()
    assert proc.returncode == 0, stderr
    assert "Traceback" not in stderr
    after_stop = stderr.split("INFO vgripd: stopping", 1)[1]
    assert "starting a new one" not in after_stop
    assert "INFO vgripd: stopped" in after_stop
