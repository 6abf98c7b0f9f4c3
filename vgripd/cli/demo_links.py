"""`vgripd demo --link KIND`: the demo cell on another link, with that link's simulator as the
peer that asks for the jobs.

- ``robot_socket``: the robot socket server (client for Yaskawa); the peer is the Python twin
  of the program ``vgripd robot-program`` writes for ``--vendor``'s brand, its locate routine;
- ``ur_rtde``: the RTDE client (``ur_rtde`` in a child process); the peer is the mock UR
  controller (its own process) running the twin of ``robots/urscript/vgripd.script``;
- ``s7``: the S7 client of a data block; the peer is snap7's server in a child process (the
  PLC) with a PLC program writing the handshake;
- ``opcua``: the OPC UA server; the peer is asyncua's client in a child process calling
  ``StartSingleJob``.

Each peer reads the answer with its own decoding (not vgripd's codec); the demo prints what it
read beside the pose error against the synthetic truth and checks that it is the pose the
daemon published (within the link's encoding).
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.util
import socket
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from typing import Any

from vgripd.errors import LinkError
from vgripd.peer.registers import Reg, Warnings
from vgripd.sim.plc import CycleResult
from vgripd.types import Status

#: ``--link`` kinds besides the default Modbus/TCP server.
LINK_KINDS = ("robot_socket", "ur_rtde", "s7", "opcua")
#: The extra that installs a peer's library (``pip install vgripd[EXTRA]``).
EXTRAS = {"ur_rtde": ("rtde_control", "ur"), "s7": ("snap7", "s7"),
          "opcua": ("asyncua", "opcua")}
RTDE_PORT = 30004  # ur_rtde has no port option: the controller is found by address
S7_DB = 10


def missing_library(kind: str) -> str | None:
    """The install line when the library the link (and its peer) needs is missing."""
    if kind not in EXTRAS:
        return None
    module, extra = EXTRAS[kind]
    if importlib.util.find_spec(module) is not None:
        return None
    return (f"vgripd demo --link {kind} needs the {module} library: "
            f"pip install 'vgripd[{extra}]'")


def vendor_for(kind: str, vendor: str) -> str | None:
    """The output convention of the demo on ``kind`` (None: ``vendor`` cannot be carried)."""
    if kind == "ur_rtde":
        return "ur"
    if kind == "robot_socket":
        from vgripd.peer.socket_frames import BRANDS
        return BRANDS[vendor].convention if vendor in BRANDS else None
    return vendor


def robot_socket_brands() -> list[str]:
    from vgripd.peer.socket_frames import BRANDS
    return sorted(BRANDS)


def free_rtde_host(wanted: str | None) -> str:
    """A loopback address where RTDE's port is free: ``wanted``, else 127.0.0.1 or the first
    free one of 127.0.30.2-254 (ur_rtde cannot be told another port)."""
    candidates = [wanted] if wanted else ["127.0.0.1"] + [f"127.0.30.{i}" for i in range(2, 255)]
    for host in candidates:
        with socket.socket() as probe:
            try:
                probe.bind((host, RTDE_PORT))
            except OSError:
                continue
        return host
    raise LinkError(f"no loopback address with port {RTDE_PORT} free for the mock UR "
                    f"controller (--peer-host names one)")


def _answer(seq: int, status: int, job_id: int, values: Any, cycle_ms: float,
            rejected: bool = False) -> CycleResult:
    st = Status(status)
    return CycleResult(seq=seq, status=st, rejected=rejected, job_id=job_id,
                       values=tuple(float(v) for v in values) if st.pose_valid else (),
                       fit_rms=-1.0, captured_seen=True, age_ms=0, polls=0,
                       cycle_ms=cycle_ms, warnings=Warnings(0))


@dataclass(frozen=True)
class DemoCell:
    """What the Modbus demo (``vgripd.cli.demo``) lends the link demo: its line printer
    (``Demo``), its cell's config, its port choice and its web view line."""

    demo: Callable[[str], Any]
    config: Callable[..., Any]
    port: Callable[[int], int]
    web_view: Callable[[int, float], str]


@dataclass
class LinkPeer:
    """One link kind in the demo: the link section, what it says, the peer's cycle."""

    kind: str
    link: dict[str, Any]
    what: str
    peer: str
    #: resolution of the values the peer reads (int32 scale), 0: floats
    resolution: float
    cycle: Callable[[], Awaitable[CycleResult]] | None = None


class Peers:
    """Starts the peers around the daemon: ``before`` the daemon (servers it connects to),
    ``after`` it is up (clients of its servers)."""

    def __init__(self, kind: str, vendor: str, peer_host: str | None, timeout_s: float) -> None:
        self.kind = kind
        self.vendor = vendor
        self.timeout_s = timeout_s
        self.stack = contextlib.AsyncExitStack()
        self.seq = 0
        self.peer_host = peer_host
        self.spec: LinkPeer | None = None
        self._brand: Any = None
        self._settings: Any = None

    async def before(self) -> LinkPeer:
        """Start what the daemon connects to; the link section to configure."""
        if self.kind == "ur_rtde":
            from vgripd.sim.ur_controller import URController
            host = free_rtde_host(self.peer_host)
            robot = URController(host)
            await asyncio.to_thread(robot.start)
            self.stack.callback(robot.stop)
            self.spec = LinkPeer(self.kind, {"type": "ur_rtde", "host": host},
                                 f"RTDE client of the controller at {host}:{RTDE_PORT}",
                                 "the mock UR controller running vgripd.script's locate",
                                 0.0, lambda: self._ur(robot))
        elif self.kind == "s7":
            from vgripd.sim.s7_plc import S7PlcServer
            server = await self.stack.enter_async_context(
                S7PlcServer(db=S7_DB, host=self.peer_host or "127.0.0.1"))
            self.spec = LinkPeer(self.kind, {"type": "s7", "host": server.host,
                                             "port": server.port, "db": S7_DB, "slot": 1},
                                 f"S7 client of DB{S7_DB} on {server.host}:{server.port}",
                                 "snap7's server as the PLC, a PLC program on its DB", 0.0)
        elif self.kind == "opcua":
            self.spec = LinkPeer(self.kind, {"type": "opcua", "host": "127.0.0.1", "port": 0,
                                             "security": ["None"], "allow_anonymous": True},
                                 "OPC UA server (security None, anonymous: a demo on "
                                 "loopback only)", "asyncua's client calling StartSingleJob",
                                 0.0)
        else:
            self.spec = await self._robot_socket()
        return self.spec

    async def _robot_socket(self) -> LinkPeer:
        from vgripd.peer.socket_frames import BRANDS
        self._brand = brand = BRANDS[self.vendor]
        scale = 1000000 if brand.name == "ur" else 10000
        link: dict[str, Any] = {"type": "robot_socket", "mode": brand.mode,
                                "host": self.peer_host or "127.0.0.1",
                                "value_format": brand.value_format, "scale": scale}
        if brand.connection == "robot_server":  # the program listens, vgripd dials in
            from vgripd.sim.robot_socket_client import ProgramTwin
            twin = await self.stack.enter_async_context(
                ProgramTwin(await self._program_settings(link | {"port": 1}),
                            link["host"], 0))
            link["port"] = twin.port
            self._twin = twin
            what = f"robot socket client of the program at {link['host']}:{twin.port}"
        else:
            link["port"] = 0
            what = "robot socket server"
        resolution = 0.0 if brand.value_format == "float32" else 1.0 / scale
        return LinkPeer(self.kind, link, what,
                        f"the Python twin of the {brand.name.upper()} program "
                        f"(vgripd robot-program --brand {brand.name}), its locate routine",
                        resolution)

    async def _program_settings(self, link: dict[str, Any]) -> Any:
        """The brand's program as ``vgripd robot-program`` writes it for this link."""
        if self._settings is None:
            from vgripd.cli.robot_program import render
            from vgripd.config import config_from_dict
            from vgripd.sim.robot_socket_client import ProgramSettings
            config = config_from_dict({"camera": {"type": "synthetic"},
                                       "output": {"vendor": self._brand.convention},
                                       "links": [link]})
            self._settings = ProgramSettings.parse(self._brand, render(self._brand, config))
        return self._settings

    async def after(self, daemon: Any) -> None:
        """The daemon is up: connect the clients of its servers."""
        assert self.spec is not None
        spec = self.spec
        link = next(iter(daemon.rooms.links.links.values()))
        if self.kind == "s7":
            from vgripd.sim.s7_plc import MockS7Plc
            plc = await self.stack.enter_async_context(
                MockS7Plc(spec.link["host"], spec.link["port"], db=S7_DB))
            spec.cycle = lambda: self._s7(plc)
        elif self.kind == "opcua":
            from vgripd.sim.opcua_client import OpcUaClientProcess
            url = f"opc.tcp://127.0.0.1:{link.port}/vgripd"
            client = await self.stack.enter_async_context(
                OpcUaClientProcess(url, timeout_s=self.timeout_s))
            if client.connected.get("event") != "connected":
                raise LinkError(f"the OPC UA client did not connect to {url}: "
                                f"{client.connected}")
            spec.peer += f" at {url}"
            spec.cycle = lambda: self._opcua(client)
        elif self.kind == "robot_socket":
            if self._brand.connection != "robot_server":
                from vgripd.sim.robot_socket_client import ProgramTwin
                port = link.port
                settings = await self._program_settings(spec.link | {"port": port})
                self._twin = await self.stack.enter_async_context(
                    ProgramTwin(settings, spec.link["host"], port))
                spec.what += f" on {spec.link['host']}:{port}"
            spec.cycle = self._socket

    async def close(self) -> None:
        await self.stack.aclose()

    # ---- one job asked by each peer; the answer as the PLC demo's CycleResult
    async def _ur(self, robot: Any) -> CycleResult:
        t0 = time.perf_counter()
        seq = await asyncio.to_thread(robot.start_program, 1, timeout_s=self.timeout_s)
        out = await asyncio.to_thread(robot.program_result, seq, self.timeout_s + 5.0)
        if out.get("error"):
            raise LinkError(f"the UR program gave up: {out['error']}")
        return _answer(out["seq"], out["status"], out["job_id"], out["offset"] or (),
                       (time.perf_counter() - t0) * 1e3)

    async def _s7(self, plc: Any) -> CycleResult:
        self.seq = self.seq % 65535 + 1
        seen = await plc.run_job(self.seq, self.timeout_s)
        w = seen.words
        if seen.rejected:
            return _answer(self.seq, w[Reg.REJECT_CODE], 0, (), seen.done_ms, rejected=True)
        return _answer(self.seq, w[Reg.STATUS], seen.u32(Reg.JOB_ID), seen.values(),
                       seen.done_ms)

    async def _opcua(self, client: Any) -> CycleResult:
        t0 = time.perf_counter()
        r = await client.send("job")
        if r.get("event") != "result":
            raise LinkError(f"the OPC UA client's job ended {r}")
        return _answer(r["request_id"], r["Status"], r["JobId"], r["Values"] or (),
                       (time.perf_counter() - t0) * 1e3)

    async def _socket(self) -> CycleResult:
        t0 = time.perf_counter()
        out = await self._twin.locate()
        if out.status < 0:
            raise LinkError("the robot program got no answer and gave up")
        conv_len = self._settings.n_values
        return _answer(out.request_ids[-1] if out.request_ids else 0, out.status,
                       out.job_id, out.values[:conv_len], (time.perf_counter() - t0) * 1e3)


@contextlib.asynccontextmanager
async def peers(kind: str, vendor: str, peer_host: str | None,
                timeout_s: float) -> AsyncIterator[Peers]:
    p = Peers(kind, vendor, peer_host, timeout_s)
    try:
        yield p
    finally:
        await p.close()


def _published_diff(values: tuple[float, ...], published: tuple[float, ...]) -> float:
    """The largest difference between what the peer read and what the daemon published."""
    if len(values) < len(published):
        return float("inf")
    return max((abs(a - b) for a, b in zip(values, published, strict=False)), default=0.0)


async def run_link_demo(args: Any, cell: DemoCell) -> int:
    """The demo cell's cycles on ``args.link`` with its simulator as the peer."""
    import numpy as np

    from vgripd.geometry.vendors import convention
    from vgripd.service.daemon import Daemon
    from vgripd.service.links.protocol import LinkState

    kind = args.link
    if args.scene != "plate":
        print(f"vgripd demo: --link {kind} runs the plate scene (the pallet's pick list "
              "is shown on the Modbus link: vgripd demo --scene pallet)")
        return 2
    missing = missing_library(kind)
    if missing:
        print(missing)
        return 2
    vendor = vendor_for(kind, args.vendor)
    if vendor is None:
        print(f"vgripd demo: --link robot_socket needs --vendor to be a brand of vgripd "
              f"robot-program ({', '.join(robot_socket_brands())}), not {args.vendor!r}")
        return 2
    demo = cell.demo(vendor)
    diffs: list[float] = []
    try:
        async with peers(kind, vendor, args.peer_host, 20.0) as p:
            spec = await p.before()
            base = cell.config(0, args.seed, vendor, web_port=cell.port(args.web_port))
            data = base.model_dump(mode="json", exclude_unset=True)
            data["links"] = [spec.link]
            from vgripd.config import config_from_dict
            config = config_from_dict(data)
            daemon = Daemon(config)
            demo.attach(daemon)
            await daemon.start()
            try:
                await daemon.wait_for(lambda: all(
                    link.health().state is LinkState.UP
                    for link in daemon.rooms.links.links.values()),
                    60.0)
                await p.after(daemon)
                assert daemon.status_server is not None
                assert spec.cycle is not None
                print(f"vgripd demo: daemon on the {kind} link: {spec.what}; "
                      f"{cell.web_view(daemon.status_server.port, args.linger)}", flush=True)
                print(f"peer: {spec.peer}")
                print(f"synthetic stereo camera, object {config.object.name!r}, offset against "
                      f"the taught reference as {vendor.upper()} "
                      f"({convention(vendor).summary})\n")
                print(demo.header())
                for _ in range(args.cycles):
                    answer = await spec.cycle()
                    print(await demo.line(answer), flush=True)
                    if answer.status.pose_valid:
                        rec = demo.jobs[answer.job_id][1]
                        published = rec.result.target.values if rec.result.target else ()
                        diffs.append(_published_diff(answer.values, tuple(published)))
                if args.linger > 0:
                    await asyncio.sleep(args.linger)
            finally:
                await daemon.stop()
    except (LinkError, TimeoutError) as err:
        print(f"\nvgripd demo: FAILED: {err or type(err).__name__}")
        return 1
    print("\n" + "\n".join(demo.summary()))
    if diffs:
        worst = float(np.max(diffs))
        # int32 words: half a step; floats: float32 rounding of values below 10^4
        tolerance = spec.resolution / 2 + 1e-3
        unit = f"int32 steps of {spec.resolution:g}" if spec.resolution else "floats"
        print(f"the peer read the published pose: largest difference {worst:.6g} ({unit})")
        if worst > tolerance:
            print("vgripd demo: FAILED: the peer read another pose than the daemon published")
            return 1
    print(f"every cycle got an answer over the {kind} link")
    return 0
