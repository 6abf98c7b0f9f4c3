"""A cell's OPC UA client, the peer of the ``opcua`` link: asyncua's ``Client`` in its own process.

``python -m vgripd.sim.opcua_client --url opc.tcp://127.0.0.1:4840/vgripd [security options]``
connects, prints one JSON line (``{"event": "connected", ...}`` or ``{"event": "error", ...}``
and exit 1), then reads commands from stdin, one per line, and answers each with a JSON line:

- ``job`` runs one job the way docs/opcua.md tells a client to: call ``StartSingleJob``, wait
  until ``Result.RequestId`` equals the returned id, read every result variable in one Read
  request, and wait for the ``ResultReadyEventType`` event of that id (subscribed at connect);
  answers ``{"event": "result", "request_id", "status", ..., "ev": {the event's fields}}``;
- ``next`` does the same with the ``Next`` method (the next object of the last job's pick
  list): ``result``, or ``refused`` with the OPC UA status name;
- ``start`` only calls ``StartSingleJob`` (``started`` with the id, or ``refused`` with the
  OPC UA status name); ``wait ID`` then does the rest of ``job`` for that id; ``fetch ID``
  the same without waiting for the event (a client that connected after it was raised);
- ``recipe N`` calls ``SelectRecipe(N)`` (``ok`` or ``refused``); ``reset`` calls ``Reset``;
- ``quit`` disconnects and exits 0.

Being a process of its own it can fail the way a client does: killed (connection gone) or
stopped with SIGSTOP (a silent peer, TCP open). ``OpcUaClientProcess`` runs it for tests and the
benchmark. Security: ``--security None|Basic256Sha256_Sign|Basic256Sha256_SignAndEncrypt``
(the client makes its own self-signed certificate in ``--client-cert-dir``), ``--user`` with the
password in the environment variable named by ``--password-env``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any

RESULT_NAMES = ("RequestId", "Sequence", "JobId", "RecipeId", "Status", "StatusName", "Message",
                "Vendor", "ValueNames", "Values", "Pose", "FitRmsMm", "ResidualNames",
                "Residuals", "Timestamp", "Count", "Index", "PickId", "Score")
EVENT_NAMES = ("RequestId", "JobId", "RecipeId", "ResultStatus", "StatusName", "Vendor",
               "ValueNames", "Values", "Pose", "FitRmsMm", "Sequence", "Count", "Index",
               "PickId", "Score")
NAMESPACE = "urn:vgripd:machine-vision"


def _plain(value: Any) -> Any:
    """JSON-ready: datetimes as ISO text, LocalizedText as its text."""
    if hasattr(value, "isoformat"):
        return value.isoformat()
    if hasattr(value, "Text"):
        return value.Text
    if isinstance(value, list):
        return [_plain(v) for v in value]
    return value


class _Events:
    def __init__(self) -> None:
        self.results: dict[int, dict[str, Any]] = {}
        self.arrived = asyncio.Event()

    def event_notification(self, event: Any) -> None:
        fields = event.get_event_props_as_fields_dict()
        got = {name: _plain(fields[name].Value) for name in EVENT_NAMES if name in fields}
        if "RequestId" in got:
            self.results[int(got["RequestId"])] = got
            self.arrived.set()


class Session:
    """One connected client and the nodes it uses."""

    def __init__(self, client: Any, idx: int) -> None:
        from asyncua import ua

        self.client = client
        self.idx = idx
        self.ua = ua
        self.vs = client.get_node(self.node_id("VisionSystem"))
        self.result = {n: client.get_node(self.node_id(f"VisionSystem.Result.{n}"))
                       for n in RESULT_NAMES}
        self.captured = client.get_node(self.node_id("VisionSystem.CapturedRequestId"))
        self.events = _Events()
        self.keep_alive: asyncio.Task[None] | None = None

    def node_id(self, path: str) -> Any:
        """vgripd's string node id of ``path`` in its namespace."""
        return self.ua.NodeId(self.ua.String(path), self.ua.Int16(self.idx))

    async def subscribe(self) -> None:
        """Result events at a 10 ms publishing interval, a keep-alive every 10 s when none
        come. asyncua's client recreates a subscription it has heard nothing from for 1.5
        keep-alive periods (its stale watchdog), and its publish loop can end for good in that
        recreation (a Publish answered BadNoSubscription between the delete and the create):
        with its default keep-alive (3/4 of the session timeout, 3 s at a 4 s session) a loaded
        machine that held the server 1.5 s lost every later event."""
        params = self.ua.CreateSubscriptionParameters(
            RequestedPublishingInterval=10, RequestedLifetimeCount=10_000,
            RequestedMaxKeepAliveCount=1000, MaxNotificationsPerPublish=10_000,
            PublishingEnabled=True, Priority=0)
        sub = await self.client.create_subscription(params, self.events)
        etype = self.client.get_node(self.node_id("ResultReadyEventType"))
        await sub.subscribe_events(self.vs, etype)

    async def call(self, method: str, *args: Any) -> Any:
        return await self.vs.call_method(self.node_id(f"VisionSystem.{method}"), *args)

    async def start(self, method: str = "StartSingleJob") -> dict[str, Any]:
        from asyncua.ua.uaerrors import UaStatusCodeError

        try:
            rid = await self.call(method)
        except UaStatusCodeError as err:
            return {"event": "refused", "code": self.ua.StatusCode(err.code).name}
        return {"event": "started", "request_id": int(rid), "t_start": time.monotonic()}

    async def wait(self, rid: int, timeout_s: float, event: bool = True) -> dict[str, Any]:
        async with asyncio.timeout(timeout_s):
            node = self.result["RequestId"]
            while True:  # a PLC's way: poll the id (the event is checked below)
                if await node.read_value() == rid:
                    break
                await asyncio.sleep(0.001)
            t_seen = time.monotonic()
            nodes = [*self.result.values(), self.captured]
            values = await self.client.read_values(nodes)  # one Read request
            while event and rid not in self.events.results:
                self.events.arrived.clear()
                await self.events.arrived.wait()
        shown = {name: _plain(v) for name, v in zip(RESULT_NAMES, values, strict=False)}
        state = await self.state()
        return {"event": "result", "request_id": rid, "t_seen": t_seen,
                "captured": values[-1], "state": state, **shown,
                "ev": self.events.results.pop(rid, None)}

    async def state(self) -> str:
        node = await self.vs.get_child([f"{self.idx}:VisionStateMachine", "0:CurrentState"])
        return str((await node.read_value()).Text)


async def connect(args: argparse.Namespace) -> tuple[Any, Session]:
    from asyncua import Client, ua
    from asyncua.crypto import security_policies

    client = Client(args.url, timeout=args.timeout, watchdog_intervall=args.watchdog_s)
    client.application_uri = "urn:vgripd:sim:opcua-client"
    client.session_timeout = int(args.session_timeout_s * 1000)
    if args.user:
        client.set_user(args.user)
        client.set_password(os.environ.get(args.password_env or "", ""))
    if args.security != "None":
        folder = Path(args.client_cert_dir)
        cert, key = await client.setup_self_signed_certificate(
            folder / "client-key.pem", folder / "client-cert.der", host_name="localhost")
        mode = (ua.MessageSecurityMode.SignAndEncrypt if args.security.endswith("Encrypt")
                else ua.MessageSecurityMode.Sign)
        await client.set_security(security_policies.SecurityPolicyBasic256Sha256, str(cert),
                                  str(key), server_certificate=args.server_cert, mode=mode)
    await client.connect()
    idx = await client.get_namespace_index(args.namespace)
    session = Session(client, idx)
    await session.subscribe()
    session.keep_alive = asyncio.create_task(_keep_alive(client))
    return client, session


async def _keep_alive(client: Any) -> None:
    """A request every third of the session's timeout (as the server revised it), so the
    server keeps the session: asyncua's watchdog did that with its probe every second, and is
    slowed to ``--watchdog-s`` here because its probe had one second to be answered. No tight
    timeout: a slow answer on a loaded machine is still an answer."""
    period_s = min(10.0, max(0.1, client.session_timeout / 1000 / 3))
    while True:
        await asyncio.sleep(period_s)
        with contextlib.suppress(Exception):  # a dead connection fails the next command
            await client.nodes.server_state.read_value()


async def run(args: argparse.Namespace) -> int:
    try:
        client, session = await connect(args)
    except Exception as err:
        print(json.dumps({"event": "error", "error": f"{type(err).__name__}: {err}"}),
              flush=True)
        return 1
    print(json.dumps({"event": "connected", "url": args.url, "security": args.security}),
          flush=True)
    loop = asyncio.get_running_loop()
    reader = asyncio.StreamReader()
    await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(reader), sys.stdin)
    try:
        while line := (await reader.readline()).decode().strip():
            cmd, *rest = line.split()
            try:
                answer = await command(session, cmd, rest, args.timeout)
            except Exception as err:
                answer = {"event": "error", "error": f"{type(err).__name__}: {err}"}
            print(json.dumps(answer), flush=True)
            if cmd == "quit":
                break
    finally:
        if session.keep_alive is not None:
            session.keep_alive.cancel()
        with contextlib.suppress(Exception):
            await client.disconnect()
    return 0


async def command(session: Session, cmd: str, rest: list[str], timeout_s: float) -> Any:
    from asyncua.ua.uaerrors import UaStatusCodeError

    if cmd in ("job", "next"):
        started = await session.start("StartSingleJob" if cmd == "job" else "Next")
        if started["event"] != "started":
            return started
        result = await session.wait(started["request_id"], timeout_s)
        return {**result, "t_start": started["t_start"]}
    if cmd == "start":
        return await session.start()
    if cmd in ("wait", "fetch"):
        return await session.wait(int(rest[0]), timeout_s, event=cmd == "wait")
    if cmd in ("recipe", "reset"):
        try:
            if cmd == "recipe":
                await session.call("SelectRecipe",
                                   session.ua.Variant(int(rest[0]), session.ua.VariantType.UInt16))
            else:
                await session.call("Reset")
        except UaStatusCodeError as err:
            return {"event": "refused", "code": session.ua.StatusCode(err.code).name}
        return {"event": "ok", "state": await session.state()}
    if cmd == "state":
        return {"event": "state", "state": await session.state()}
    if cmd == "quit":
        return {"event": "bye"}
    return {"event": "error", "error": f"unknown command {cmd!r}"}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description="OPC UA client of vgripd's opcua link")
    p.add_argument("--url", required=True)
    p.add_argument("--security", default="None",
                   choices=["None", "Basic256Sha256_Sign", "Basic256Sha256_SignAndEncrypt"])
    p.add_argument("--server-cert", default=None, help="the server certificate (DER) to trust")
    p.add_argument("--client-cert-dir", default=".", help="where the client's own certificate is")
    p.add_argument("--user", default=None)
    p.add_argument("--password-env", default=None)
    p.add_argument("--namespace", default=NAMESPACE)
    p.add_argument("--timeout", type=float, default=30.0)
    p.add_argument("--session-timeout-s", type=float, default=3600.0)
    # asyncua's default probes the server every 1 s and gives it 1 s to answer: a loaded
    # machine (the demo beside other work, a test suite) is taken for a dead server and the
    # connection dropped under a job in flight ("client is disconnected"). The session is
    # kept alive by a request every third of its timeout (``_keep_alive``).
    p.add_argument("--watchdog-s", type=float, default=30.0,
                   help="probe the server's state this often, given as long to answer")
    return p.parse_args(argv)


class OpcUaClientProcess:
    """``python -m vgripd.sim.opcua_client`` as a child process, for tests and the benchmark.

    ``async with OpcUaClientProcess(url, ...) as c``: ``c.connected`` is the first line;
    ``await c.send("job")`` returns the answer line as a dict. ``freeze``/``thaw``: SIGSTOP /
    SIGCONT (a silent client); ``kill``: SIGKILL (a client that vanished).
    """

    def __init__(self, url: str, *args: str, env: dict[str, str] | None = None,
                 timeout_s: float = 60.0) -> None:
        self.argv = ["--url", url, *args]
        self.env = env
        self.timeout_s = timeout_s
        self.proc: asyncio.subprocess.Process | None = None
        self.connected: dict[str, Any] = {}

    async def __aenter__(self) -> OpcUaClientProcess:
        env = {**os.environ, **(self.env or {})}
        self.proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "vgripd.sim.opcua_client", *self.argv,
            stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE, env=env)
        self.connected = await self._line()
        return self

    async def __aexit__(self, *exc: object) -> None:
        proc = self.proc
        if proc is None:
            return
        if proc.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signal.SIGCONT)
            if proc.stdin is not None and not proc.stdin.is_closing():
                with contextlib.suppress(OSError):
                    proc.stdin.write(b"quit\n")
                    proc.stdin.close()
            try:
                async with asyncio.timeout(10):
                    await proc.wait()
            except TimeoutError:
                proc.kill()
                await proc.wait()

    async def send(self, line: str) -> dict[str, Any]:
        assert self.proc is not None
        assert self.proc.stdin is not None
        self.proc.stdin.write(line.encode() + b"\n")
        await self.proc.stdin.drain()
        return await self._line()

    async def _line(self) -> dict[str, Any]:
        assert self.proc is not None
        assert self.proc.stdout is not None
        async with asyncio.timeout(self.timeout_s):
            raw = await self.proc.stdout.readline()
        if not raw:
            return {"event": "exit", "code": await self.proc.wait()}
        answer: dict[str, Any] = json.loads(raw)
        return answer

    def freeze(self) -> None:
        assert self.proc is not None
        self.proc.send_signal(signal.SIGSTOP)

    def thaw(self) -> None:
        assert self.proc is not None
        self.proc.send_signal(signal.SIGCONT)

    async def kill(self) -> None:
        assert self.proc is not None
        self.proc.kill()
        await self.proc.wait()


def main(argv: list[str] | None = None) -> int:
    import logging

    logging.getLogger("asyncua").setLevel(logging.CRITICAL)  # errors go out as JSON lines
    return asyncio.run(run(parse_args(argv)))


if __name__ == "__main__":
    sys.exit(main())
