"""OpcUaLink against asyncua's client in another process (``vgripd.sim.opcua_client``), asyncua's
command-line tools (``uals``, ``uaread``) and raw sockets, over real TCP on 127.0.0.1.

The daemon is stood in for by ``Daemon`` below (it answers triggers with fixed results), so
each check is about the link: the values a client reads are compared with the numbers the
stand-in published, never with what the link thinks it wrote. The real daemon with the
synthetic camera is tests/integration/test_daemon_opcua.py.

These tests are about the older namespace and the link's transport and security: ``options``
serves only it (``models = ["vgripd"]``), without the OPC 40100 NodeSet they do not need.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import re
import shlex
import socket
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.links.opcua import OpcUaLink, OpcUaOptions
from tests.conftest import REPO, need, ua_client
from vgripd.errors import ConfigError, LinkError
from vgripd.geometry.vendors import CONVENTIONS
from vgripd.service.links.protocol import LinkState, Trigger
from vgripd.sim.opcua_client import OpcUaClientProcess
from vgripd.sim.opcua_raw import RawOpcUa, client_policy, status_of
from vgripd.types import JobResult, RobotTarget, Status

pytestmark = [pytest.mark.timeout(120), pytest.mark.slow(minutes=3)]

WAIT_S = 20.0
POSE = (412.5, -133.25, 287.0625, 12.34, -29.0, 179.5)  # KUKA X Y Z A B C (mm, deg)
OFFSET = np.array([[0.0, -1.0, 0.0, 12.5], [1.0, 0.0, 0.0, -3.25],
                   [0.0, 0.0, 1.0, 0.125], [0.0, 0.0, 0.0, 1.0]])
BIN = Path(sys.executable).parent


def kuka_result(job_id: int, values: tuple[float, ...] = POSE,
                status: Status = Status.OK) -> JobResult:
    if not status.pose_valid:
        return JobResult(job_id=job_id, status=status, message="no marks")
    target = RobotTarget("kuka", CONVENTIONS["kuka"].fields, values)
    return JobResult(job_id=job_id, status=status, target=target, offset=OFFSET,
                     residuals={"fit_rms_mm": 0.042, "reprojection_px": 0.31})


class Daemon:
    """Stands in for vgripd's daemon: answers every trigger with ``result_for`` (captured, then
    published), or holds it until ``release`` when ``hold`` is set."""

    def __init__(self, result_for: Callable[[Trigger], JobResult] | None = None) -> None:
        self.link: OpcUaLink | None = None
        self.triggers: list[Trigger] = []
        self.result_for = result_for or (lambda t: kuka_result(100 + t.seq))
        self.hold = False
        self.released = asyncio.Event()
        self.tasks: set[asyncio.Task[None]] = set()

    def on_trigger(self, trigger: Trigger) -> None:
        self.triggers.append(trigger)
        task = asyncio.create_task(self.answer(trigger))
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)

    async def answer(self, trigger: Trigger) -> None:
        assert self.link is not None
        result = self.result_for(trigger)
        if result.job_id:
            await self.link.image_captured(trigger.seq, result.job_id)
        if self.hold:
            await self.released.wait()
        await self.link.publish(trigger.seq, result)


def options(*, old_only: bool = True, **extra: Any) -> OpcUaOptions:
    """An open test server; ``old_only``: the older namespace alone (False: the default
    models, OPC 40100 on the NodeSet beside it)."""
    base: dict[str, Any] = {"host": "127.0.0.1", "port": 0, "security": ["None"],
                            "allow_anonymous": True, "activation_timeout_s": 0.5,
                            "log_interval_s": 60}
    if old_only:
        base["models"] = ["vgripd"]
    return OpcUaOptions.model_validate({**base, **extra})


async def open_link(daemon: Daemon, opts: OpcUaOptions) -> OpcUaLink:
    link = OpcUaLink("cell", opts)
    daemon.link = link
    await link.open(daemon.on_trigger)
    return link


@pytest.fixture
async def daemon() -> AsyncIterator[Daemon]:
    d = Daemon()
    yield d
    for task in list(d.tasks):
        task.cancel()


@pytest.fixture
async def link(daemon: Daemon) -> AsyncIterator[OpcUaLink]:
    lk = await open_link(daemon, options())
    yield lk
    await lk.close()


def url(link: OpcUaLink) -> str:
    return f"opc.tcp://127.0.0.1:{link.port}/vgripd"


async def until(pred: Callable[[], bool], what: str) -> None:
    async with asyncio.timeout(WAIT_S):
        while True:
            if pred():
                return
            await asyncio.sleep(0.01)  # polled: the link has no event for each of these


def lines(caplog: pytest.LogCaptureFixture, text: str) -> list[logging.LogRecord]:
    return [r for r in caplog.records if text in r.getMessage()]


# -- jobs ------------------------------------------------------------------------------------


async def test_jobs_results_exact_event_equal_and_state_ready(
        link: OpcUaLink, daemon: Daemon) -> None:
    async with OpcUaClientProcess(url(link)) as client:
        assert client.connected["event"] == "connected", client.connected
        seen = [await client.send("job") for _ in range(2)]
    for n, r in enumerate(seen, start=1):
        assert r["event"] == "result", r
        assert r["request_id"] == n == daemon.triggers[n - 1].seq
        assert (r["Status"], r["StatusName"], r["JobId"]) == (1, "OK", 100 + n)
        assert r["Sequence"] == n
        assert r["captured"] == n  # CapturedRequestId: the image of this request was taken
        assert r["Vendor"] == "kuka"
        assert r["ValueNames"] == ["X", "Y", "Z", "A", "B", "C"]  # the convention's case
        assert tuple(r["Values"]) == POSE  # Double: bit-exact
        assert np.array_equal(np.array(r["Pose"]).reshape(4, 4), OFFSET)
        assert r["FitRmsMm"] == 0.042
        assert dict(zip(r["ResidualNames"], r["Residuals"], strict=True)) == {
            "fit_rms_mm": 0.042, "reprojection_px": 0.31}
        assert r["state"] == "Ready"
        # The event carries the same result in one notification.
        ev = r["ev"]
        assert (ev["RequestId"], ev["JobId"], ev["ResultStatus"], ev["Sequence"]) == (
            n, 100 + n, 1, n)
        assert tuple(ev["Values"]) == POSE
        assert ev["Pose"] == r["Pose"]
    assert link.refusals() == {}


async def test_recipe_reaches_the_daemon_and_the_result(link: OpcUaLink, daemon: Daemon) -> None:
    async with OpcUaClientProcess(url(link)) as client:
        assert (await client.send("recipe 12"))["event"] == "ok"
        r = await client.send("job")
    assert daemon.triggers[0].recipe == 12
    assert r["RecipeId"] == 12
    assert r["ev"]["RecipeId"] == 12


async def test_busy_start_is_refused_and_the_running_job_completes(
        link: OpcUaLink, daemon: Daemon) -> None:
    daemon.hold = True
    async with OpcUaClientProcess(url(link)) as client:
        started = await client.send("start")
        assert started["event"] == "started"
        assert (await client.send("state"))["state"] == "SingleExecution"
        refused = await client.send("start")
        assert refused == {"event": "refused", "code": "BadInvalidState"}
        assert (await client.send("reset"))["code"] == "BadInvalidState"
        daemon.released.set()
        r = await client.send(f"wait {started['request_id']}")
    assert r["Status"] == Status.OK
    assert len(daemon.triggers) == 1  # the refused start reached nobody
    assert link.refusals() == {"BUSY": 2}


async def test_wrong_arguments_are_bad_request(link: OpcUaLink) -> None:
    from asyncua import ua
    from asyncua.ua.uaerrors import UaStatusCodeError

    async with ua_client(url(link)) as c:
        idx = await c.get_namespace_index("urn:vgripd:machine-vision")
        vs = c.get_node(ua.NodeId("VisionSystem", idx))
        codes = []
        for method, args in [("SelectRecipe", [ua.Variant(70000, ua.VariantType.UInt32)]),
                             ("SelectRecipe", [ua.Variant(-1, ua.VariantType.Int32)]),
                             ("SelectRecipe", [ua.Variant("3", ua.VariantType.String)]),
                             ("SelectRecipe", []),
                             ("StartSingleJob", [ua.Variant(1, ua.VariantType.UInt16)]),
                             ("Next", [ua.Variant(1, ua.VariantType.UInt16)]),
                             ("Next", [])]:  # no pick list: nothing published yet
            with pytest.raises(UaStatusCodeError) as err:
                await vs.call_method(ua.NodeId(f"VisionSystem.{method}", idx), *args)
            codes.append(ua.StatusCode(err.value.code).name)
        selected = await c.get_node(ua.NodeId("VisionSystem.SelectedRecipe", idx)).read_value()
        # Result variables are read-only for clients.
        with pytest.raises(UaStatusCodeError):
            await c.get_node(ua.NodeId("VisionSystem.Result.Status", idx)).write_value(
                ua.Variant(1, ua.VariantType.UInt16))
    assert codes == ["BadInvalidArgument", "BadInvalidArgument", "BadInvalidArgument",
                     "BadArgumentsMissing", "BadTooManyArguments", "BadTooManyArguments",
                     "BadNoData"]
    assert selected == 0
    assert link.refusals() == {"BAD_REQUEST": 7}


async def test_failures_show_no_pose_and_system_errors_enter_error_state(daemon: Daemon) -> None:
    outcomes = iter([
        kuka_result(1, status=Status.CAMERA_ERROR),
        JobResult(job_id=0, status=Status.BUSY, message="refused: BUSY"),  # daemon refusal
        kuka_result(3, values=(1.0, float("nan"), 3.0, 4.0, 5.0, 6.0)),  # must not reach a robot
        kuka_result(4, status=Status.NOT_FOUND),
    ])
    daemon.result_for = lambda t: next(outcomes)
    link = await open_link(daemon, options())
    try:
        async with OpcUaClientProcess(url(link)) as client:
            camera = await client.send("job")
            assert camera["state"] == "Error"
            assert (await client.send("reset"))["state"] == "Ready"
            busy = await client.send("job")
            nan = await client.send("job")
            not_found = await client.send("job")
    finally:
        await link.close()
    assert (camera["Status"], camera["Values"], camera["Pose"]) == (30, [], [])
    assert (busy["Status"], busy["JobId"], busy["state"]) == (40, 0, "Ready")
    assert (nan["Status"], nan["Values"], nan["Pose"], nan["Vendor"]) == (
        Status.OUT_OF_LIMITS, [], [], "")
    assert nan["ev"]["ResultStatus"] == Status.OUT_OF_LIMITS
    assert (not_found["Status"], not_found["state"], not_found["Message"]) == (
        10, "Ready", "no marks")


async def test_publish_for_another_request_is_a_link_error(link: OpcUaLink) -> None:
    with pytest.raises(LinkError, match="running request is none"):
        await link.publish(5, kuka_result(1))


async def test_warnings_are_live(link: OpcUaLink) -> None:
    from asyncua import ua

    await link.set_warnings(1)
    with pytest.raises(LinkError):
        await link.set_warnings(4)
    async with ua_client(url(link)) as c:
        idx = await c.get_namespace_index("urn:vgripd:machine-vision")
        assert await c.get_node(ua.NodeId("VisionSystem.Warnings", idx)).read_value() == 1
        maker = ua.NodeId(ua.ObjectIds.Server_ServerStatus_BuildInfo_ManufacturerName)
        assert await c.get_node(maker).read_value() == "vgripd"


async def test_state_machine_current_state_id_and_number(
        link: OpcUaLink, daemon: Daemon) -> None:
    from asyncua import ua

    daemon.hold = True
    async with ua_client(url(link)) as c:
        idx = await c.get_namespace_index("urn:vgripd:machine-vision")
        vs = c.get_node(ua.NodeId(ua.String("VisionSystem"), ua.Int16(idx)))
        sm = await vs.get_child([f"{idx}:VisionStateMachine"])
        current = await sm.get_child(["0:CurrentState"])

        async def state() -> tuple[str, Any, int]:
            text = (await current.read_value()).Text
            sid = await (await current.get_child(["0:Id"])).read_value()
            number = await (await current.get_child(["0:Number"])).read_value()
            return text, sid, number

        ready = (await sm.get_child([f"{idx}:Ready"])).nodeid
        running = (await sm.get_child([f"{idx}:SingleExecution"])).nodeid
        before = await state()
        await vs.call_method(ua.NodeId(ua.String("VisionSystem.StartSingleJob"), ua.Int16(idx)))
        during = await state()
        daemon.released.set()
        await until(lambda: not daemon.tasks, "published")
        after = await state()
    assert before == ("Ready", ready, 1)
    assert during == ("SingleExecution", running, 2)
    assert after == ("Ready", ready, 1)


async def test_a_publish_never_shows_a_request_id_with_other_data(daemon: Daemon) -> None:
    """Between any two steps of the loop (where a Read request could be served), the result
    variables show either no request (RequestId 0) or a request with its own values, also
    while a client's subscription on them publishes at once (interval 0)."""
    from asyncua import ua

    daemon.result_for = lambda t: kuka_result(t.seq, values=(float(t.seq),) * 6)
    link = await open_link(daemon, options())
    seen: list[tuple[int, list[float]]] = []
    assert link.server is not None
    server = link.server
    space = link.space
    assert space is not None
    rid_node, values_node = space.nodes["Result.RequestId"], space.nodes["Result.Values"]
    stop = asyncio.Event()

    async def observe() -> None:
        while not stop.is_set():
            rid = server.read_attribute_value(rid_node).Value.Value
            values = server.read_attribute_value(values_node).Value.Value
            seen.append((rid, list(values or [])))
            await asyncio.sleep(0)

    class Changes:
        def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
            pass

    try:
        async with ua_client(url(link)) as c:
            sub = await c.create_subscription(0, Changes())
            await sub.subscribe_data_change([c.get_node(rid_node), c.get_node(values_node)])
            observer = asyncio.create_task(observe())
            vs = c.get_node(ua.NodeId(ua.String("VisionSystem"), ua.Int16(space.idx)))
            start = ua.NodeId(ua.String("VisionSystem.StartSingleJob"), ua.Int16(space.idx))
            for _ in range(20):
                await vs.call_method(start)
                await until(lambda: not daemon.tasks, "published")
            stop.set()
            await observer
    finally:
        await link.close()
    shown = {rid for rid, _ in seen}
    assert {0, 20} <= shown
    for rid, values in seen:
        assert rid == 0 or values == [float(rid)] * 6, (rid, values)


# -- faults ----------------------------------------------------------------------------------


async def test_garbage_is_closed_with_one_line_and_the_server_serves_on(
        link: OpcUaLink, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    for payload in (b"GET / HTTP/1.1\r\n\r\n", b"\x00" * 64, b"HEL" + os.urandom(200),
                    b"MSGF\x10\x00\x00\x00" + os.urandom(8)):
        reader, writer = await asyncio.open_connection("127.0.0.1", link.port)
        writer.write(payload)
        await writer.drain()
        async with asyncio.timeout(WAIT_S):
            await reader.read()  # the server closes the connection
        writer.close()
    await until(lambda: link.health().peers == 0, "connections closed")
    server = link.server
    assert server is not None
    assert server.bserver is not None
    assert server.bserver.clients == []  # asyncua kept nothing of them
    assert server.iserver.asyncio_transports == []
    async with OpcUaClientProcess(url(link)) as client:
        answer = await client.send("job")
        assert answer.get("Status") == Status.OK, answer
    assert link.faults["garbage"] >= 2
    assert len(lines(caplog, "not OPC UA")) == 1  # rate limited: one line per client and kind
    assert not [r for r in caplog.records if r.exc_info or "Traceback" in r.getMessage()]
    assert link.health().state is LinkState.UP


async def test_silent_peers_are_closed_once_each(
        daemon: Daemon, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    # 4 s: the second client's requests (one every third of it) keep its session on a machine
    # running two suites; at 1.5 s a starved client was once taken for a silent one
    link = await open_link(daemon, options(max_session_timeout_s=4.0))
    try:
        # A TCP peer that never says Hello: closed after activation_timeout_s.
        reader, writer = await asyncio.open_connection("127.0.0.1", link.port)
        async with asyncio.timeout(WAIT_S):
            assert await reader.read() == b""
        writer.close()
        # A client with a session that goes silent (SIGSTOP): closed after its session timeout.
        async with OpcUaClientProcess(url(link)) as client:
            answer = await client.send("job")
            assert answer.get("Status") == Status.OK, answer
            await until(lambda: link.health().peers == 1, "client connected")
            client.freeze()
            await until(lambda: link.health().peers == 0, "silent client closed")
            client.thaw()
        # ... and the server still serves.
        async with OpcUaClientProcess(url(link)) as client:
            answer = await client.send("job")
            assert answer.get("Status") == Status.OK, answer
    finally:
        await link.close()
    assert len(lines(caplog, "no session within 0.5 s")) == 1
    assert len(lines(caplog, "session timeout 4 s")) == 1
    assert link.faults["silent"] == 2
    assert not [r for r in caplog.records if r.exc_info]


async def test_a_server_stalled_for_seconds_keeps_its_client(daemon: Daemon) -> None:
    """A loaded machine can hold the server's process for seconds. The demo's OPC UA client
    (``vgripd.sim.opcua_client``) keeps its session through it: with asyncua's own watchdog (a
    probe every 1 s, 1 s to answer) it dropped the connection and the next job ended "client
    is disconnected" (seen under two suites side by side)."""
    link = await open_link(daemon, options())
    try:
        async with OpcUaClientProcess(url(link)) as client:
            answer = await client.send("job")
            assert answer.get("Status") == Status.OK, answer
            time.sleep(3.0)  # noqa: ASYNC251 - the point: the server's event loop stalls
            answer = await client.send("job")
            assert answer.get("Status") == Status.OK, answer
    finally:
        await link.close()


async def test_a_flood_of_silent_connections_neither_evicts_a_session_nor_locks_out_a_client(
        daemon: Daemon, caplog: pytest.LogCaptureFixture) -> None:
    """Connections that never say Hello held every slot (asyncua refused newcomers at
    max_connections) until activation_timeout_s. Through the gate they evict each other, the
    oldest first; the client with an activated session is never evicted and a new client is
    served at once."""
    link = await open_link(daemon, options(max_connections=3, activation_timeout_s=60))
    flood: list[asyncio.StreamWriter] = []
    try:
        async with OpcUaClientProcess(url(link)) as client:
            answer = await client.send("job")
            assert answer.get("Status") == Status.OK, answer
            for _ in range(30):
                _, writer = await asyncio.open_connection("127.0.0.1", link.port)
                flood.append(writer)
            await until(lambda: link.faults["evicted"] >= 28, "flood evicted")
            assert link.health().peers <= 3
            async with OpcUaClientProcess(url(link)) as newcomer:
                answer = await newcomer.send("job")
                assert answer.get("Status") == Status.OK, answer
            answer = await client.send("job")
            assert answer.get("Status") == Status.OK, answer  # never evicted
    finally:
        for writer in flood:
            writer.close()
        await link.close()
    assert len(lines(caplog, " evicted for ")) <= 2
    assert not [r for r in caplog.records if r.exc_info]


async def test_allow_list_closes_other_addresses_at_accept(
        daemon: Daemon, caplog: pytest.LogCaptureFixture) -> None:
    link = await open_link(daemon, options(allow=["127.0.0.1"]))
    loop = asyncio.get_running_loop()
    try:
        for _ in range(3):
            sock = socket.socket()
            sock.bind(("127.0.0.2", 0))
            sock.setblocking(False)
            await loop.sock_connect(sock, ("127.0.0.1", link.port))
            reader, writer = await asyncio.open_connection(sock=sock)
            with contextlib.suppress(ConnectionError):
                writer.write(b"HEL" + bytes(29))
                async with asyncio.timeout(WAIT_S):
                    assert await reader.read() == b""
            writer.close()
        async with OpcUaClientProcess(url(link)) as client:
            answer = await client.send("job")
            assert answer.get("Status") == Status.OK, answer
        assert link.faults["not_allowed"] == 3
        assert len(lines(caplog, "not in allow")) == 1  # the count follows at the interval
    finally:
        await link.close()


async def test_client_killed_mid_job_then_a_new_client_works(
        link: OpcUaLink, daemon: Daemon, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    daemon.hold = True
    async with OpcUaClientProcess(url(link)) as client:
        started = await client.send("start")
        await client.kill()
    await until(lambda: link.health().peers == 0, "killed client gone")
    daemon.released.set()
    await until(lambda: not daemon.tasks, "job published")
    # The result stays readable for a client that comes back.
    daemon.hold = False
    async with OpcUaClientProcess(url(link)) as client:
        assert (await client.send(f"fetch {started['request_id']}"))["Status"] == Status.OK
        assert (await client.send("job"))["request_id"] == started["request_id"] + 1
    assert len(lines(caplog, "connection reset")) + len(lines(caplog, "closed the connection")) >= 1
    assert not [r for r in caplog.records if r.exc_info]


async def test_port_in_use_fails_naming_the_address(daemon: Daemon) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        link = OpcUaLink("cell", options(port=port))
        with pytest.raises(LinkError, match=f"cannot listen on 127.0.0.1:{port}"):
            await link.open(daemon.on_trigger)
        assert link.health().state is LinkState.FAILED
        await link.close()


# -- security --------------------------------------------------------------------------------


def secure_options(tmp_path: Path, **extra: Any) -> OpcUaOptions:
    base: dict[str, Any] = {
        "security": ["Basic256Sha256_SignAndEncrypt"], "allow_anonymous": False,
        "certificate_dir": str(tmp_path / "pki"),
        "users": [{"name": "robot", "password_env": "VGRIPD_TEST_OPCUA_PW"}]}
    return options(**{**base, **extra})


async def test_encrypted_session_with_generated_certificate_and_password(
        daemon: Daemon, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("VGRIPD_TEST_OPCUA_PW", "s3cret pass")
    link = await open_link(daemon, secure_options(tmp_path))
    try:
        cert = link.certificate
        assert cert is not None
        assert cert.exists()
        assert (tmp_path / "pki" / "vgripd-server-key.pem").stat().st_mode & 0o077 == 0
        common = ["--security", "Basic256Sha256_SignAndEncrypt", "--server-cert", str(cert),
                  "--client-cert-dir", str(tmp_path / "client")]
        env = {"PW": "s3cret pass", "BAD": "wrong"}
        async with OpcUaClientProcess(url(link), *common, "--user", "robot",
                                      "--password-env", "PW", env=env) as good:
            assert good.connected["event"] == "connected", good.connected
            r = await good.send("job")
            assert tuple(r["Values"]) == POSE
        async with OpcUaClientProcess(url(link), *common, "--user", "robot",
                                      "--password-env", "BAD", env=env) as bad:
            assert bad.connected["event"] == "error"
            assert "BadUserAccessDenied" in bad.connected["error"]
        async with OpcUaClientProcess(url(link), *common) as anonymous:
            assert anonymous.connected["event"] == "error"
        async with OpcUaClientProcess(url(link)) as plain:  # security None: no such endpoint
            assert plain.connected["event"] == "error"
        assert link.faults["login"] == 2  # the wrong password, the refused anonymous login
        first = cert.read_bytes()
    finally:
        await link.close()
    # The next start uses the same certificate (clients trust it once).
    link = await open_link(daemon, secure_options(tmp_path))
    try:
        assert link.certificate is not None
        assert link.certificate.read_bytes() == first
    finally:
        await link.close()


async def test_missing_password_fails_naming_the_field(
        daemon: Daemon, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("VGRIPD_TEST_OPCUA_PW", raising=False)
    link = OpcUaLink("cell", secure_options(tmp_path))
    with pytest.raises(LinkError, match=r"users\[0\] \('robot'\)\.password_env: environment "
                                        r"variable VGRIPD_TEST_OPCUA_PW is not set"):
        await link.open(daemon.on_trigger)
    assert link.health().state is LinkState.FAILED
    await link.close()
    pw = tmp_path / "missing.txt"
    link = OpcUaLink("cell", options(users=[{"name": "robot", "password_file": str(pw)}],
                                     allow_anonymous=False))
    with pytest.raises(LinkError, match=r"password_file: cannot read .*missing.txt"):
        await link.open(daemon.on_trigger)
    await link.close()


def test_options_and_registry() -> None:
    from vgripd.config import DriverSection, config_from_dict
    from vgripd.registry import LINKS, load_class, validate_options

    cls = load_class(LINKS, "link", "opcua")
    assert cls is OpcUaLink

    def check(**opts: Any) -> Any:
        return validate_options(cls, DriverSection.model_validate({"type": "opcua", **opts}),
                                "links.0")

    ok = check(certificate_dir="/var/lib/vgripd/pki",
               users=[{"name": "plc", "password_file": "/etc/vgripd/plc.pw"}])
    assert (ok.port, ok.security, ok.allow_anonymous) == (
        4840, ["Basic256Sha256_SignAndEncrypt"], False)
    for bad, text in [
        ({"allow_anonymous": True}, "certificate_dir: Value error, needed for security"),
        ({"security": ["None"]}, "users: Value error, give at least one user"),
        ({"security": ["None"], "allow_anonymous": True, "users": [{"name": "a"}]},
         "users.0: .*exactly one of password_file and password_env"),
        ({"security": ["None"], "allow_anonymous": True,
          "users": [{"name": "a", "password": "x"}]}, "password"),
        ({"security": ["Basic128"], "allow_anonymous": True}, "security"),
        ({"security": ["None", "None"], "allow_anonymous": True}, "listed once"),
        ({"security": ["None"], "allow_anonymous": True, "path": "x"}, "path"),
    ]:
        with pytest.raises(ConfigError, match=text):
            check(**bad)
    # Any convention fits, the 16 values of a 4x4 matrix included.
    base = {"camera": {"type": "synthetic"},
            "links": [{"type": "opcua", "security": ["None"], "allow_anonymous": True}]}
    config_from_dict({**base, "output": {"vendor": "matrix"}})


def test_check_tries_the_opcua_port() -> None:
    from vgripd.config import config_from_dict
    from vgripd.service.host.commissioning import _listening

    config = config_from_dict({
        "camera": {"type": "synthetic"}, "status": {"enabled": False},
        "links": [{"type": "opcua", "host": "127.0.0.1", "port": 4841, "security": ["None"],
                   "allow_anonymous": True}]})
    assert _listening(config) == [("links[0]", "127.0.0.1", 4841)]


def test_missing_asyncua_says_how_to_install_it() -> None:
    code = ("import sys; sys.modules['asyncua'] = None\n"
            "from vgripd.registry import LINKS, load_class\n"
            "try:\n    load_class(LINKS, 'link', 'opcua')\n"
            "except Exception as err:\n    print(type(err).__name__, err)\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True,
                         text=True, timeout=60, check=True).stdout
    assert out.startswith("DriverError")
    assert "pip install 'vgripd[opcua]'" in out


# -- asyncua's command-line tools -----------------------------------------------------------


def tool(name: str) -> str:
    path = BIN / name
    need(path.exists(), f"needs {name} (asyncua's command-line tools): pip install "
                        "'vgripd[opcua]'")
    return str(path)


async def run_tool(*argv: str) -> str:
    proc = await asyncio.create_subprocess_exec(*argv, stdout=subprocess.PIPE,
                                                stderr=subprocess.PIPE)
    async with asyncio.timeout(60):
        out, err = await proc.communicate()
    assert proc.returncode == 0, err.decode()
    return out.decode()


async def test_uals_and_uaread_browse_and_read_the_result(link: OpcUaLink,
                                                        daemon: Daemon) -> None:
    uals, uaread = tool("uals"), tool("uaread")
    async with OpcUaClientProcess(url(link)) as client:
        r = await client.send("job")
    listing = await run_tool(uals, "-u", url(link), "-n", "ns=2;s=VisionSystem.Result")
    for name in ("RequestId", "Sequence", "Status", "Values", "ValueNames", "Pose", "JobId",
                 "Timestamp", "FitRmsMm", "Count", "Index", "PickId", "Score"):
        assert f"2:{name}" in listing, listing
    top = await run_tool(uals, "-u", url(link), "-n", "ns=2;s=VisionSystem")
    for name in ("StartSingleJob", "SelectRecipe", "Reset", "Next", "VisionStateMachine",
                 "Result"):
        assert f"2:{name}" in top, top
    status = await run_tool(uaread, "-u", url(link), "-n", "ns=2;s=VisionSystem.Result.Status")
    values = await run_tool(uaread, "-u", url(link), "-n", "ns=2;s=VisionSystem.Result.Values")
    rid = await run_tool(uaread, "-u", url(link), "-n",
                         "ns=2;s=VisionSystem.Result.RequestId")
    assert status.strip() == "1"
    assert [float(v) for v in values.strip().strip("[]").split(",")] == list(POSE)
    assert int(rid.strip()) == r["request_id"]
    # docs/opcua.md's uacall line (asyncua 2.1: -m takes the method's browse name)
    await run_tool(tool("uacall"), "-u", url(link), "-n", "ns=2;s=VisionSystem",
                   "-m", "2:StartSingleJob")
    await until(lambda: len(daemon.triggers) == 2, "the second job")


async def test_the_tool_lines_of_the_docs_run_as_written(link: OpcUaLink, daemon: Daemon) -> None:
    """docs/opcua.md's ``uals`` / ``uacall`` / ``uaread`` lines, with only the port changed:
    each runs, the ``uacall`` starts a job and the ``uaread`` reads its values."""
    text = (REPO / "docs" / "opcua.md").read_text()
    block = re.search(r"```sh\n(uals.*?)```", text, re.S)
    assert block is not None
    argvs = [shlex.split(line.replace("opc.tcp://127.0.0.1:4840/vgripd", url(link)))
             for line in block.group(1).splitlines() if line.strip()]
    assert [a[0] for a in argvs] == ["uals", "uacall", "uaread"]
    listing = await run_tool(tool("uals"), *argvs[0][1:])
    assert "2:Values" in listing, listing
    await run_tool(tool("uacall"), *argvs[1][1:])
    await until(lambda: len(daemon.triggers) == 1 and not daemon.tasks, "the job of uacall")
    values = await run_tool(tool("uaread"), *argvs[2][1:])
    assert [float(v) for v in values.strip().strip("[]").split(",")] == list(POSE)


async def test_client_trust_list_refuses_unknown_certificates_and_keeps_them(
        daemon: Daemon, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    monkeypatch.setenv("VGRIPD_TEST_OPCUA_PW", "pw")
    trusted = tmp_path / "trusted"
    trusted.mkdir()
    opts = secure_options(tmp_path, trusted_clients_dir=str(trusted))
    args = ["--security", "Basic256Sha256_SignAndEncrypt", "--client-cert-dir",
            str(tmp_path / "client"), "--user", "robot", "--password-env", "PW"]
    link = await open_link(daemon, opts)
    try:
        assert link.certificate is not None
        async with OpcUaClientProcess(url(link), *args, "--server-cert", str(link.certificate),
                                      env={"PW": "pw"}) as client:
            assert client.connected["event"] == "error"
    finally:
        await link.close()
    rejected = list((tmp_path / "pki" / "rejected").iterdir())
    assert len(rejected) == 1
    assert rejected[0].read_bytes() == (tmp_path / "client" / "client-cert.der").read_bytes()
    assert len(lines(caplog, "refused: not in trusted_clients_dir")) == 1
    assert link.faults["untrusted"] == 1
    # The integrator moves it into the trust list; after a restart the client is let in.
    rejected[0].rename(trusted / rejected[0].name)
    link = await open_link(daemon, opts)
    try:
        assert link.certificate is not None
        async with OpcUaClientProcess(url(link), *args, "--server-cert", str(link.certificate),
                                      env={"PW": "pw"}) as client:
            assert client.connected["event"] == "connected", client.connected
            answer = await client.send("job")
            assert answer.get("Status") == Status.OK, answer
    finally:
        await link.close()
    assert not [r for r in caplog.records if r.exc_info]


def test_trust_list_needs_signed_endpoints() -> None:
    with pytest.raises(ValueError, match="trusted_clients_dir"):
        options(trusted_clients_dir="/tmp")


# -- a raw client doing what an attacker does ----------------------------------------------
# asyncua's high-level Client refuses SecurityPolicy None against a secure server on its own;
# RawOpcUa builds the channel and the session requests itself.

RESULT = "ns=2;s=VisionSystem.Result"


def library_errors(caplog: pytest.LogCaptureFixture) -> list[logging.LogRecord]:
    """ERROR lines and tracebacks: a refused client must leave neither."""
    return [r for r in caplog.records if r.levelno >= logging.ERROR or r.exc_info]


async def refused(coro: Any) -> str:
    """The status name a raw request was refused with ("" when it was answered)."""
    from asyncua import ua

    try:
        await coro
    except ua.UaStatusCodeError as err:
        return status_of(err)
    return ""


async def test_raw_none_channel_serves_discovery_only_on_a_secure_server(
        daemon: Daemon, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    """OpenSecureChannel with SecurityPolicy None, then CreateSession +
    ActivateSession with the password in clear, against a Basic256Sha256 SignAndEncrypt
    server: discovery answers, every session step is refused, no job runs."""
    caplog.set_level(logging.INFO)
    monkeypatch.setenv("VGRIPD_TEST_OPCUA_PW", "s3cret")
    link = await open_link(daemon, secure_options(tmp_path))
    try:
        async with RawOpcUa("127.0.0.1", link.port) as raw:
            endpoints = await raw.get_endpoints()
            assert {e.SecurityPolicyUri.rsplit("#")[-1] for e in endpoints} == {"Basic256Sha256"}
            assert await refused(raw.create_session()) == "BadSecurityPolicyRejected"
            await until(lambda: raw.closed, "the server closes the connection")
        # skipping CreateSession: ActivateSession, Read and Call straight away
        for step in ("activate", "read", "call"):
            async with RawOpcUa("127.0.0.1", link.port) as raw:
                coro = {"activate": lambda: raw.activate("robot", "s3cret"),
                        "read": lambda: raw.read(f"{RESULT}.Status"),
                        "call": lambda: raw.call("ns=2;s=VisionSystem",
                                                 "ns=2;s=VisionSystem.StartSingleJob")}[step]()
                assert await refused(coro) == "BadSecurityPolicyRejected", step
        async with RawOpcUa("127.0.0.1", link.port) as raw:  # vgripd is no discovery server
            from asyncua import ua

            server = ua.RegisteredServer(ServerUri="urn:evil", IsOnline=True)
            assert await refused(raw.client.register_server(server)) == "BadServiceUnsupported"
        assert daemon.triggers == []
        assert link.faults["insecure"] == 4
    finally:
        await link.close()
    # one line per client address and interval: the first, and the count of the others
    # when the link closes
    first, *rest = lines(caplog, "refused (BadSecurityPolicyRejected")
    assert "CreateSession on a channel with SecurityPolicy None, mode None" in first.getMessage()
    assert len(rest) <= 1
    assert not library_errors(caplog)


async def test_raw_anonymous_on_none_channel_does_not_bypass_the_trust_list(
        daemon: Daemon, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """``trusted_clients_dir`` and ``allow_anonymous``: a None channel has no
    certificate to judge, so it carries no session at all."""
    trusted = tmp_path / "trusted"
    trusted.mkdir()
    opts = options(security=["Basic256Sha256_SignAndEncrypt"], allow_anonymous=True,
                   certificate_dir=str(tmp_path / "pki"), trusted_clients_dir=str(trusted))
    link = await open_link(daemon, opts)
    try:
        async with RawOpcUa("127.0.0.1", link.port) as raw:
            assert await refused(raw.create_session()) == "BadSecurityPolicyRejected"
        async with RawOpcUa("127.0.0.1", link.port) as raw:
            assert await refused(raw.activate()) == "BadSecurityPolicyRejected"
        assert daemon.triggers == []
    finally:
        await link.close()
    assert not library_errors(caplog)


async def test_raw_password_guessing_is_slowed_then_locked_out(
        daemon: Daemon, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    """60 ActivateSession guesses on one SignAndEncrypt connection: the first
    ``login_failures`` are checked (BadUserAccessDenied), the rest refused unchecked
    (BadRequestNotAllowed), the right password too; one lockout line, no library ERROR."""
    from asyncua import ua

    caplog.set_level(logging.INFO)
    monkeypatch.setenv("VGRIPD_TEST_OPCUA_PW", "s3cret")
    link = await open_link(daemon, secure_options(tmp_path))  # login_failures = 10
    try:
        assert link.certificate is not None
        policy = await asyncio.to_thread(client_policy, link.certificate.read_bytes(),
                                         ua.MessageSecurityMode.SignAndEncrypt)
        async with RawOpcUa("127.0.0.1", link.port, policy=policy) as raw:
            await raw.create_session()
            answers = [await refused(raw.activate("robot", f"guess{n}")) for n in range(60)]
            assert answers.count("BadUserAccessDenied") == 10, answers
            assert answers[10:] == ["BadRequestNotAllowed"] * 50
            assert await refused(raw.activate("robot", "s3cret")) == "BadRequestNotAllowed"
            assert not raw.closed
        assert (link.faults["login"], link.faults["lockout"]) == (10, 1)
        assert link.faults["locked"] == 51
        assert daemon.triggers == []
    finally:
        await link.close()
    assert len(lines(caplog, "10 failed logins in a row")) == 1
    assert len(lines(caplog, "refused for 60 s (login_lockout_s)")) == 1
    assert not library_errors(caplog)


async def test_raw_right_password_after_a_few_guesses_is_let_in(
        daemon: Daemon, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    """An operator who mistypes gets in on the next try; a password in clear on a channel that
    does not encrypt (Sign) is refused even when right, the answer is the same without
    library ERROR lines; a refused anonymous login counts as a failed login."""
    from asyncua import ua

    monkeypatch.setenv("VGRIPD_TEST_OPCUA_PW", "s3cret")
    opts = secure_options(tmp_path, security=["Basic256Sha256_Sign",
                                              "Basic256Sha256_SignAndEncrypt"])
    link = await open_link(daemon, opts)
    try:
        assert link.certificate is not None
        server_cert = link.certificate.read_bytes()
        policy = await asyncio.to_thread(client_policy, server_cert,
                                         ua.MessageSecurityMode.SignAndEncrypt)
        async with RawOpcUa("127.0.0.1", link.port, policy=policy) as raw:
            await raw.create_session()
            assert await refused(raw.activate("robot", "typo")) == "BadUserAccessDenied"
            assert await refused(raw.activate()) == "BadIdentityTokenRejected"
            assert await refused(raw.activate("robot", "s3cret")) == ""
            values = await raw.read(f"{RESULT}.Status")
            assert values[0].StatusCode.is_good()
        sign = await asyncio.to_thread(client_policy, server_cert, ua.MessageSecurityMode.Sign)
        async with RawOpcUa("127.0.0.1", link.port, policy=sign) as raw:
            await raw.create_session()
            assert await refused(raw.activate("robot", "s3cret")) == "BadIdentityTokenRejected"
        assert link.faults["login"] == 3
        assert link.faults["lockout"] == 0
    finally:
        await link.close()
    assert not library_errors(caplog)


async def test_raw_clear_password_on_a_listed_none_channel_is_refused(
        daemon: Daemon, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    """``"None"`` listed beside an encrypting mode: a None channel carries sessions, but a
    password in clear on it is refused even when right (the endpoint asks for it encrypted
    with the server certificate); the None channel's own session works when the config says
    so (anonymous here)."""
    monkeypatch.setenv("VGRIPD_TEST_OPCUA_PW", "s3cret")
    opts = secure_options(tmp_path, security=["None", "Basic256Sha256_SignAndEncrypt"],
                          allow_anonymous=True)
    link = await open_link(daemon, opts)
    try:
        async with RawOpcUa("127.0.0.1", link.port) as raw:
            await raw.create_session()
            assert await refused(raw.activate("robot", "s3cret")) == "BadIdentityTokenRejected"
            assert await refused(raw.activate()) == ""
            (value,) = await raw.read(f"{RESULT}.Status")
            assert value.StatusCode.is_good()
        assert link.faults["login"] == 1
    finally:
        await link.close()
    assert not library_errors(caplog)


async def test_raw_session_is_not_taken_over_from_another_certificate(
        daemon: Daemon, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A session activated by one client certificate cannot be activated on another client's
    channel, even by one that knows its AuthenticationToken and nonce; its owner goes on."""
    from asyncua import ua

    opts = options(security=["Basic256Sha256_SignAndEncrypt"], allow_anonymous=True,
                   certificate_dir=str(tmp_path / "pki"))
    link = await open_link(daemon, opts)
    try:
        assert link.certificate is not None
        server_cert = link.certificate.read_bytes()
        mode = ua.MessageSecurityMode.SignAndEncrypt
        owner_policy, thief_policy = [await asyncio.to_thread(client_policy, server_cert, mode)
                                      for _ in range(2)]
        async with RawOpcUa("127.0.0.1", link.port, policy=owner_policy) as owner:
            await owner.create_session()
            await owner.activate()
            async with RawOpcUa("127.0.0.1", link.port, policy=thief_policy) as thief:
                thief.adopt(owner)
                assert await refused(thief.activate()) == "BadSecurityChecksFailed"
                assert await refused(thief.read(f"{RESULT}.Status")) == "BadSessionIdInvalid"
            (value,) = await owner.read(f"{RESULT}.Status")
            assert value.StatusCode.is_good()
    finally:
        await link.close()
    assert not library_errors(caplog)


async def test_raw_create_session_flood_on_one_connection_holds_one_session(
        link: OpcUaLink) -> None:
    """300 CreateSession requests on one connection: asyncua alone kept 300 sessions and 300
    watchdog tasks; the link closes the previous session, so one of each is left."""
    assert link.server is not None

    def watchdogs() -> int:
        return sum(1 for t in asyncio.all_tasks()
                   if getattr(t.get_coro(), "__name__", "") == "_session_watchdog_loop")

    async with RawOpcUa("127.0.0.1", link.port) as raw:
        for _ in range(300):
            await raw.create_session()
        await raw.activate()
        (value,) = await raw.read(f"{RESULT}.Status")
        assert value.StatusCode.is_good()
        assert len(link.server.iserver._external_sessions) == 1
        assert watchdogs() == 1


async def test_rejected_certificates_are_capped_and_deduplicated(
        daemon: Daemon, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """70 distinct self-signed client certificates against a trust list, then
    the first again: the rejected store keeps the last ``rejected_max_files`` (64), one file
    per thumbprint (the first's file refreshed, not doubled)."""
    from asyncua import ua
    from asyncua.crypto import cert_gen

    monkeypatch.setenv("VGRIPD_TEST_OPCUA_PW", "pw")
    trusted = tmp_path / "trusted"
    trusted.mkdir()
    # An encrypted handshake on a loaded machine can outlast the test servers' 0.5 s activation
    # timeout: that connection was then closed for "no session" before its certificate was
    # judged, and never counted as refused.
    link = await open_link(daemon, secure_options(tmp_path, trusted_clients_dir=str(trusted),
                                                  activation_timeout_s=30))
    rejected = tmp_path / "pki" / "rejected"
    try:
        assert link.certificate is not None
        server_cert = link.certificate.read_bytes()
        key = await asyncio.to_thread(cert_gen.generate_private_key)
        policies = [client_policy(server_cert, ua.MessageSecurityMode.SignAndEncrypt,
                                  f"raw{n}", key) for n in range(70)]
        for n, policy in enumerate([*policies, policies[0]]):
            with contextlib.suppress(Exception):  # the server drops the channel
                async with RawOpcUa("127.0.0.1", link.port, policy=policy) as raw:
                    await raw.create_session()
            await until(lambda n=n: link.faults["untrusted"] == n + 1, "refused")
    finally:
        await link.close()
    kept = {p.read_bytes() for p in rejected.iterdir()}
    assert len(kept) == 64
    assert kept == {p.host_certificate for p in [policies[0], *policies[7:]]}


async def test_timestamp_before_the_first_result_reads_in_one_read(
        link: OpcUaLink, caplog: pytest.LogCaptureFixture) -> None:
    """Before any result, Result.Timestamp is the null DateTime and the Read's other values are
    answered with it (not BadInternalError with an AttributeError logged)."""
    import datetime

    async with RawOpcUa("127.0.0.1", link.port) as raw:  # security None is listed here
        await raw.create_session()
        await raw.activate()
        stamp, status, rid = await raw.read(f"{RESULT}.Timestamp", f"{RESULT}.Status",
                                            f"{RESULT}.RequestId")
    assert stamp.StatusCode.is_good()
    assert status.StatusCode.is_good()
    assert stamp.Value.Value == datetime.datetime(1601, 1, 1, tzinfo=datetime.UTC)
    assert (status.Value.Value, rid.Value.Value) == (int(Status.IDLE), 0)
    assert not library_errors(caplog)


def test_check_warns_about_security_none_and_open_anonymous_sessions(tmp_path: Path) -> None:
    from vgripd.config import config_from_dict
    from vgripd.service.host.commissioning import check_link_exposure

    def found(**link: Any) -> list[str]:
        config = config_from_dict({
            "camera": {"type": "synthetic"}, "status": {"enabled": False},
            "links": [{"type": "opcua", "host": "127.0.0.1", "port": 0, **link}]})
        return [f"{f.level} {f.key}: {f.message}" for f in check_link_exposure(config)]

    user = [{"name": "plc", "password_env": "X"}]
    none = found(security=["None"], users=user)
    assert len(none) == 1
    assert none[0].startswith('WARNING links[0].security: "None" is listed')
    assert "as user plc (passwords travel in clear)" in none[0]
    pki = str(tmp_path / "pki")
    both = found(security=["None", "Basic256Sha256_SignAndEncrypt"], certificate_dir=pki,
                 users=user, allow_anonymous=True)
    assert both == ['WARNING links[0].security: "None" is listed: any client on the network '
                    'opens a session without a certificate, unsigned and unencrypted, as user '
                    'plc, anonymous']
    assert "allow_anonymous" in found(certificate_dir=pki, allow_anonymous=True)[0]
    assert found(certificate_dir=pki, users=user) == []
    trusted = found(certificate_dir=pki, allow_anonymous=True, trusted_clients_dir=pki)
    assert trusted == []
