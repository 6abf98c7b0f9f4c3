"""What every bench shares: figures, the machine stamp, the results writer and the processes a
bench starts (the daemon, the PLC stand-in, a static Modbus server, a serial pty pair).

A bench measures, then calls :func:`write_section` with its subject (one of :data:`SUBJECTS`),
its own heading and its text; the writer replaces that one section of bench/RESULTS.md and
leaves every other byte alone. :class:`Stamp` is taken when the bench starts and closed when it
writes: the commit measured, the machine (cores, CPU model) and the load average before and
after, since every figure here comes from a machine shared with other work.

The PLC stand-in runs as ``python -m bench.harness --plc-client PORT MODE SECONDS JOBS`` (its
own process, so its timing shares no GIL with the server it polls); ``--pair-client A B
SECONDS`` polls two servers interleaved, and ``--bare-server`` is the plain pymodbus server as a
process of its own.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import os
import platform
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import AsyncIterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "RESULTS.md"
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

#: The groups of RESULTS.md, in the order the file shows them.
SUBJECTS = (
    "Vision: accuracy and locate time",
    "Calibration",
    "Links",
    "Daemon: polls, jobs, memory",
    "Pick lists",
    "Cameras",
    "Conveyor",
    "Web view and setup",
    "Start and install",
)
TITLE = "# Benchmark results"
INTRO = (
    "Every figure below comes from a bench in this folder against a named peer measured in the "
    "same run, on a machine shared with other work (the load average is in each stamp). "
    "`make bench` reruns them all and each bench rewrites its own section only; a section "
    "stamped \"measured before the harness\" keeps the figures of an earlier run until its "
    "bench runs again."
)
PRE_HARNESS = "Measured before the harness (the stamp below is the run's own); `make bench` replaces it."


# --- figures -------------------------------------------------------------------------------------

def percentile(values: Sequence[float], q: float) -> float:
    """The ``q``-th percentile (0-100), linear between the two nearest ranks (numpy's default);
    ``nan`` for no values."""
    if not 0 <= q <= 100:
        raise ValueError(f"percentile: q must be within 0..100, got {q}")
    s = sorted(values)
    if not s:
        return math.nan
    pos = (len(s) - 1) * q / 100
    lo = math.floor(pos)
    hi = min(lo + 1, len(s) - 1)
    return s[lo] + (s[hi] - s[lo]) * (pos - lo)


@dataclass(frozen=True)
class Spread:
    """Median, tail and count of one series (its unit is the caller's)."""

    n: int
    median: float
    p95: float
    p99: float
    max: float

    @classmethod
    def of(cls, values: Sequence[float]) -> Spread:
        return cls(len(values), percentile(values, 50), percentile(values, 95),
                   percentile(values, 99), max(values, default=math.nan))

    def cells(self, digits: int = 2) -> str:
        """``| n | median | p95 | p99 | max |`` cells (without the leading name cell)."""
        f = f"{{:.{digits}f}}"
        return (f"| {self.n} | {f.format(self.median)} | {f.format(self.p95)} | "
                f"{f.format(self.p99)} | {f.format(self.max)} |")

    def text(self, unit: str = "ms", digits: int = 2) -> str:
        f = f"{{:.{digits}f}}"
        return (f"median {f.format(self.median)} {unit}, p95 {f.format(self.p95)} {unit}, "
                f"p99 {f.format(self.p99)} {unit}, max {f.format(self.max)} {unit} (n={self.n})")


SPREAD_HEADER = "| n | median | p95 | p99 | max |"
SPREAD_RULE = "|---:|---:|---:|---:|---:|"


def load_average() -> str:
    return "{:.2f} {:.2f} {:.2f}".format(*os.getloadavg())


# --- the stamp -----------------------------------------------------------------------------------

def commit() -> str:
    """The short commit of the tree measured, ``+ changes`` when it has uncommitted edits."""
    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True,
                              check=False).stdout.strip()

    head = git("rev-parse", "--short", "HEAD") or "unknown"
    dirty = git("status", "--porcelain", "--untracked-files=no", "--", "vgripd", "drivers")
    return f"{head} + changes" if dirty else head


def cpu_model() -> str:
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.partition(":")[2].strip()
    return platform.processor() or platform.machine()


def machine() -> str:
    return f"{os.cpu_count()} cores, {cpu_model()}, {platform.machine()}"


@dataclass
class Stamp:
    """Taken when a bench starts; :meth:`line` closes it when the bench writes."""

    command: str
    load_before: str = field(default_factory=load_average)
    started: str = field(default_factory=lambda: time.strftime("%Y-%m-%d %H:%M"))

    def line(self) -> str:
        return (f"`{self.command}`, commit {commit()}, {self.started}, {machine()}, "
                f"load average {self.load_before} before, {load_average()} after, "
                f"Python {platform.python_version()}.")


def bench_command() -> str:
    """The command line this bench was started with, as a reader would type it."""
    main = sys.modules.get("__main__")
    spec = getattr(main, "__spec__", None)
    name = f"-m {spec.name}" if spec is not None else f"bench/{Path(sys.argv[0]).name}"
    return " ".join([".venv/bin/python", name, *sys.argv[1:]])


# --- RESULTS.md ----------------------------------------------------------------------------------

@dataclass
class _Group:
    subject: str
    sections: list[tuple[str, str]] = field(default_factory=list)  # (heading, whole text)


def parse_results(text: str) -> list[_Group]:
    """The ``## subject`` groups of RESULTS.md with their ``### heading`` sections."""
    groups: list[_Group] = []
    for chunk in re.split(r"^(?=## )", text, flags=re.M):
        if not chunk.startswith("## "):
            continue  # the title and intro: rewritten from TITLE and INTRO
        first, _, rest = chunk.partition("\n")
        group = _Group(first[3:].strip())
        for part in re.split(r"^(?=### )", rest, flags=re.M):
            if part.startswith("### "):
                group.sections.append((part.partition("\n")[0], part.rstrip("\n")))
        groups.append(group)
    return groups


def render_results(groups: list[_Group]) -> str:
    out = [TITLE, "", INTRO, ""]
    for group in sorted(groups, key=lambda g: _subject_rank(g.subject)):
        if not group.sections:
            continue
        out += [f"## {group.subject}", ""]
        for _, body in group.sections:
            out += [body, ""]
    return "\n".join(out).rstrip("\n") + "\n"


def _subject_rank(subject: str) -> int:
    return SUBJECTS.index(subject) if subject in SUBJECTS else len(SUBJECTS)


def replace_section(text: str, subject: str, heading: str, body: str) -> str:
    """``text`` (RESULTS.md) with the section ``### heading`` set to ``body`` under ``## subject``.

    The section is replaced where it stands, or moved there from another subject, or added as
    the subject's last; every other section keeps its bytes."""
    if subject not in SUBJECTS:
        raise ValueError(f"bench results: unknown subject {subject!r} (one of {SUBJECTS})")
    if heading.startswith("#") or "\n" in heading or not heading.strip():
        raise ValueError(f"bench results: a heading is one line of words, got {heading!r}")
    title = f"### {heading}"
    section = (title + "\n\n" + body.strip("\n")).rstrip("\n")
    groups = parse_results(text)
    for group in groups:
        hits = [i for i, (h, _) in enumerate(group.sections) if h == title]
        if group.subject == subject and hits:
            group.sections[hits[0]] = (title, section)
            for i in reversed(hits[1:]):
                del group.sections[i]
        else:
            group.sections = [(h, s) for h, s in group.sections if h != title]
    target = next((g for g in groups if g.subject == subject), None)
    if target is None:
        target = _Group(subject)
        groups.append(target)
    if all(h != title for h, _ in target.sections):
        target.sections.append((title, section))
    return render_results(groups)


def write_section(subject: str, heading: str, body: str, stamp: Stamp | None = None,
                  path: Path = RESULTS) -> str:
    """Replace this bench's section of RESULTS.md (atomically) and return the section's text.

    ``body`` is the text under the heading; with ``stamp`` its line comes first."""
    if stamp is not None:
        body = stamp.line() + "\n\n" + body.strip("\n")
    old = path.read_text() if path.exists() else ""
    new = replace_section(old, subject, heading, body)
    with tempfile.NamedTemporaryFile("w", dir=path.parent, prefix=".RESULTS.",
                                     delete=False) as tmp:
        tmp.write(new)
    os.replace(tmp.name, path)
    return f"### {heading}\n\n{body.strip()}"


def parser(doc: str | None) -> argparse.ArgumentParser:
    """A bench's command line: its docstring's first line as the description, and the one
    write policy every bench shares (write its own section unless ``--print-only``)."""
    ap = argparse.ArgumentParser(description=(doc or "").strip().splitlines()[0])
    ap.add_argument("--print-only", action="store_true",
                    help="print the section instead of writing it to bench/RESULTS.md")
    return ap


def report(subject: str, heading: str, body: str, stamp: Stamp, print_only: bool = False) -> None:
    """Print the section and, unless ``print_only``, write it (:func:`write_section`)."""
    if print_only:
        print(f"### {heading}\n\n{stamp.line()}\n\n{body.strip()}")
    else:
        print(write_section(subject, heading, body, stamp))


# --- processes a bench starts --------------------------------------------------------------------

START_TIMEOUT_S = 120.0
POLL_PERIOD_S = 0.01


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


async def get_status(port: int) -> dict[str, Any]:
    """``GET /status`` of a daemon (plain asyncio, no thread)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(b"GET /status HTTP/1.0\r\n\r\n")
    data = await reader.read()
    writer.close()
    with contextlib.suppress(ConnectionError):
        await writer.wait_closed()
    status: dict[str, Any] = json.loads(data.partition(b"\r\n\r\n")[2])
    return status


class DaemonProcess:
    """``python -m vgripd run`` on a generated config (synthetic stereo camera, Modbus/TCP
    server on 127.0.0.1, status port); its log goes to ``folder/daemon.log``."""

    def __init__(self, folder: Path, worker: bool, record: bool = True, max_mb: float = 200.0,
                 log_level: str = "INFO", command: list[str] | None = None) -> None:
        self.folder = folder
        self.port = free_port()
        self.status_port = free_port()
        self.config = folder / "vgripd.toml"
        folder.mkdir(parents=True, exist_ok=True)
        self.config.write_text(f"""
[camera]
type = "synthetic"
seed = 3
max_tilt_deg = 2.0

[[links]]
type = "modbus_server"
host = "127.0.0.1"
port = {self.port}

[status]
port = {self.status_port}

[daemon]
worker = {str(worker).lower()}
log_level = "{log_level}"

[record]
enabled = {str(record).lower()}
folder = "{folder / 'record'}"
max_mb = {max_mb}
""")
        self.proc: asyncio.subprocess.Process | None = None
        self.command = command or [sys.executable, "-m", "vgripd", "run", "-c", str(self.config)]

    async def __aenter__(self) -> DaemonProcess:
        log = (self.folder / "daemon.log").open("ab")
        self.proc = await asyncio.create_subprocess_exec(
            *self.command, cwd=REPO,
            env={**os.environ, "PYTHONPATH": str(REPO)}, stdout=log, stderr=log)
        log.close()
        deadline = time.monotonic() + START_TIMEOUT_S
        while True:
            assert self.proc.returncode is None, f"daemon exited, see {self.folder}/daemon.log"
            with contextlib.suppress(OSError, ValueError):
                if (await self.status())["run_state"] == "running":
                    return self
            assert time.monotonic() < deadline, "daemon did not start"
            await asyncio.sleep(0.2)

    async def __aexit__(self, *exc: object) -> None:
        assert self.proc is not None
        if self.proc.returncode is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                async with asyncio.timeout(30):
                    await self.proc.wait()
            except TimeoutError:
                self.proc.kill()
                await self.proc.wait()

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    async def status(self) -> dict[str, Any]:
        return await get_status(self.status_port)


def plc_client_main(port: int, mode: str, seconds: float, jobs: int) -> None:
    """The PLC stand-in: poll all registers at 100 Hz for ``seconds`` (or until ``jobs`` results
    in ``cycle`` mode, where it triggers the next job as soon as it reads the last result).
    JSON on stdout: read round trips, trigger-to-result times, statuses."""
    from pymodbus.client import ModbusTcpClient

    realtime = os.environ.get("BENCH_CLIENT_REALTIME") == "1"
    if realtime:
        try:  # a real PLC is a device of its own: keep our stand-in's wake-ups out of the figures
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
        except PermissionError:
            realtime = False
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=5, retries=0)
    assert client.connect()
    rtt_ms: list[float] = []
    cycle_ms: list[float] = []
    statuses: dict[str, int] = {}
    end = time.monotonic() + seconds if seconds > 0 else float("inf")
    try:
        _poll_loop(client, mode, end, jobs, rtt_ms, cycle_ms, statuses)
        error = ""
    except Exception as err:  # the server went away: report what was measured until then
        error = f"{type(err).__name__}: {err}"
    client.close()
    print(json.dumps({"rtt_ms": rtt_ms, "cycle_ms": cycle_ms, "statuses": statuses,
                      "realtime": realtime, "error": error}))


def wait_for_tick(tick: float) -> float:
    """Sleep until the monotonic time ``tick``; a tick already past (the client fell behind)
    restarts the pace from now. Returns the tick the next period counts from."""
    delay = tick - time.monotonic()
    if delay > 0:
        time.sleep(delay)
        return tick
    return time.monotonic()


def _poll_loop(client: Any, mode: str, end: float, jobs: int, rtt_ms: list[float],
               cycle_ms: list[float], statuses: dict[str, int]) -> None:
    from vgripd.peer.registers import MAP_SIZE, Reg
    from vgripd.types import Status

    seq = 0
    pending: tuple[int, float] | None = None
    next_tick = time.monotonic()
    while time.monotonic() < end and (not jobs or len(cycle_ms) < jobs):
        if mode == "cycle" and pending is None:
            seq = seq % 0xFFFF + 1
            pending = (seq, time.perf_counter())
            r = client.write_registers(Reg.CMD, [1, seq, 0], device_id=1)
            assert not r.isError(), r
        t0 = time.perf_counter()
        r = client.read_holding_registers(0, count=MAP_SIZE, device_id=1)
        t1 = time.perf_counter()
        assert not r.isError(), r
        rtt_ms.append(round((t1 - t0) * 1000, 4))
        if pending is not None and r.registers[Reg.ACK_SEQ] == pending[0]:
            name = Status(r.registers[Reg.STATUS]).name
            statuses[name] = statuses.get(name, 0) + 1
            cycle_ms.append(round((t1 - pending[1]) * 1000, 3))
            pending = None
        next_tick = wait_for_tick(next_tick + POLL_PERIOD_S)


def pair_client_main(port_a: int, port_b: int, seconds: float) -> None:
    """One PLC stand-in reading all registers of two servers at 100 Hz each, interleaved: each
    tick reads both, the order alternating tick by tick so neither always goes second. Same
    client library, same process, same moment: the two series see the same load. JSON on
    stdout: ``{"a": [ms...], "b": [ms...], "realtime": bool, "error": str}``."""
    from pymodbus.client import ModbusTcpClient

    from vgripd.peer.registers import MAP_SIZE

    realtime = os.environ.get("BENCH_CLIENT_REALTIME") == "1"
    if realtime:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
        except PermissionError:
            realtime = False
    clients = {name: ModbusTcpClient("127.0.0.1", port=port, timeout=5, retries=0)
               for name, port in (("a", port_a), ("b", port_b))}
    for client in clients.values():
        assert client.connect()
    rtt_ms: dict[str, list[float]] = {"a": [], "b": []}
    end = time.monotonic() + seconds
    next_tick = time.monotonic()
    error = ""
    try:
        tick = 0
        while time.monotonic() < end:
            for name in (("a", "b") if tick % 2 == 0 else ("b", "a")):
                t0 = time.perf_counter()
                r = clients[name].read_holding_registers(0, count=MAP_SIZE, device_id=1)
                t1 = time.perf_counter()
                assert not r.isError(), r
                rtt_ms[name].append(round((t1 - t0) * 1000, 4))
            tick += 1
            next_tick = wait_for_tick(next_tick + POLL_PERIOD_S)
    except Exception as err:  # a server went away: report what was measured until then
        error = f"{type(err).__name__}: {err}"
    for client in clients.values():
        client.close()
    print(json.dumps({**rtt_ms, "realtime": realtime, "error": error}))


async def run_pair_client(port_a: int, port_b: int, seconds: float) -> dict[str, Any]:
    """Run :func:`pair_client_main` in its own process and return its figures."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "bench.harness", "--pair-client", str(port_a), str(port_b),
        str(seconds), cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)},
        stdout=asyncio.subprocess.PIPE,
    )
    out, _ = await proc.communicate()
    assert proc.returncode == 0, "bench pair client failed"
    result: dict[str, Any] = json.loads(out)
    if result["error"]:
        raise RuntimeError(f"bench pair client: {result['error']}")
    return result


def bare_server_main() -> None:
    """:func:`static_modbus_server` as a process of its own: prints its port, serves until
    stdin closes (so the bench can run it under the same scheduling as the daemon)."""

    async def serve() -> None:
        server, port = await static_modbus_server()
        print(port, flush=True)
        await asyncio.get_running_loop().run_in_executor(None, sys.stdin.read)
        await server.shutdown()

    asyncio.run(serve())


async def run_client(port: int, mode: str, seconds: float, jobs: int = 0,
                     allow_error: bool = False) -> dict[str, Any]:
    """Run the PLC stand-in against ``port`` in its own process and return its figures."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "bench.harness", "--plc-client", str(port), mode, str(seconds),
        str(jobs), cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)},
        stdout=asyncio.subprocess.PIPE,
    )
    out, _ = await proc.communicate()
    assert proc.returncode == 0, "bench PLC client failed"
    result: dict[str, Any] = json.loads(out)
    if result["error"] and not allow_error:
        raise RuntimeError(f"bench PLC client: {result['error']}")
    return result


async def static_modbus_server() -> tuple[Any, int]:
    """The named Modbus/TCP peer: a plain pymodbus server with a static datastore on 127.0.0.1."""
    from pymodbus.server import ModbusTcpServer
    from pymodbus.simulator import DataType, SimData, SimDevice

    from vgripd.peer.registers import MAP_SIZE

    device = SimDevice(1, simdata=[SimData(0, values=list(range(MAP_SIZE)),
                                           datatype=DataType.REGISTERS)])
    server = ModbusTcpServer(device, address=("127.0.0.1", 0))
    await server.serve_forever(background=True)
    port: int = server.transport.sockets[0].getsockname()[1]
    return server, port


@contextlib.asynccontextmanager
async def pty_pair() -> AsyncIterator[tuple[Path, Path]]:
    """Two linked serial ptys from socat (a null-modem cable without a baud rate)."""
    socat = shutil.which("socat")
    if socat is None:
        raise RuntimeError("this bench needs socat (apt-get install socat)")
    with tempfile.TemporaryDirectory() as tmp:
        a, b = Path(tmp) / "a", Path(tmp) / "b"
        proc = await asyncio.create_subprocess_exec(
            socat, f"pty,raw,echo=0,link={a}", f"pty,raw,echo=0,link={b}",
            stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL)
        try:
            deadline = time.monotonic() + 10
            while not (a.exists() and b.exists()):
                if time.monotonic() > deadline:
                    raise RuntimeError("socat did not create the ptys within 10 s")
                await asyncio.sleep(0.01)
            yield a, b
        finally:
            proc.terminate()
            await proc.wait()


if __name__ == "__main__":
    if len(sys.argv) == 6 and sys.argv[1] == "--plc-client":
        plc_client_main(int(sys.argv[2]), sys.argv[3], float(sys.argv[4]), int(sys.argv[5]))
    elif len(sys.argv) == 5 and sys.argv[1] == "--pair-client":
        pair_client_main(int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4]))
    elif sys.argv[1:] == ["--bare-server"]:
        bare_server_main()
    else:
        sys.exit("usage: python -m bench.harness --plc-client PORT MODE SECONDS JOBS")
