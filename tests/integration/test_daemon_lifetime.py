"""Every child process of `vgripd run` (the worker and the web view's JPEG helper, forked by
multiprocessing's fork server, the server itself, and the resource tracker) ends with the daemon: on SIGTERM to the whole process group (what systemd's
``KillMode=control-group`` does on ``systemctl stop``) with a job in flight and a browser's event
stream open, and on SIGKILL of the daemon alone, which no code of the daemon sees.

The daemon runs as a real process in its own session; its descendants are found in /proc.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

import aiohttp
from pymodbus.client import AsyncModbusTcpClient

from tests.conftest import REPO
from vgripd.peer.jobcore import Command
from vgripd.peer.registers import MAP_SIZE, Reg
from vgripd.service.worker.process import segments_of

WAIT_S = 60.0
#: `systemctl stop` with a job in flight and an open browser completes within this.
STOP_BOUND_S = 3.0
ENV = {**os.environ, "PYTHONPATH": str(REPO)}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def _alive(pid: int) -> bool:
    """Running (a zombie waiting for a reaper counts as gone)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


def _descendants(root: int) -> dict[int, str]:
    """pid -> command line of every living descendant of ``root``."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                ppid = int(f.read().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        children.setdefault(ppid, []).append(int(entry))
    found: dict[int, str] = {}
    todo = [root]
    while todo:
        for pid in children.get(todo.pop(), []):
            with contextlib.suppress(OSError):
                with open(f"/proc/{pid}/cmdline", "rb") as f:
                    found[pid] = f.read().replace(b"\0", b" ").decode(errors="replace")
                todo.append(pid)
    return found


async def _survivors(pids: dict[int, str], until_mono: float) -> dict[int, str]:
    """Poll until none of ``pids`` lives or the time is up; those still alive."""
    while True:
        alive = {pid: cmd for pid, cmd in pids.items() if _alive(pid)}
        if not alive or time.monotonic() >= until_mono:
            return alive
        await asyncio.sleep(0.05)


@dataclass
class Daemon:
    proc: asyncio.subprocess.Process
    plc: AsyncModbusTcpClient
    http: aiohttp.ClientSession
    base: str


@contextlib.asynccontextmanager
async def _daemon(tmp_path: Path) -> AsyncIterator[Daemon]:
    port, http_port = _free_port(), _free_port()
    cfg = tmp_path / "vgripd.toml"
    cfg.write_text(f"""
[camera]
type = "synthetic"
seed = 1

[[links]]
type = "modbus_server"
host = "127.0.0.1"
port = {port}

[status]
host = "127.0.0.1"
port = {http_port}
""")
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "vgripd", "run", "-c", str(cfg), cwd=REPO, env=ENV,
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    plc = AsyncModbusTcpClient("127.0.0.1", port=port, timeout=5, retries=0,
                                  reconnect_delay=0)
    try:
        async with aiohttp.ClientSession() as http:
            base = f"http://127.0.0.1:{http_port}"
            async with asyncio.timeout(WAIT_S):
                while True:  # up once the web view answers (it starts before the links)
                    with contextlib.suppress(aiohttp.ClientError):
                        async with http.get(f"{base}/api/status") as resp:
                            if resp.status == 200:
                                break
                    assert proc.returncode is None, "vgripd run exited"
                    await asyncio.sleep(0.1)
                while not await plc.connect():  # noqa: ASYNC110 - a peer's answer, no event
                    await asyncio.sleep(0.1)
            yield Daemon(proc, plc, http, base)
    finally:
        plc.close()
        if proc.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            await proc.wait()


async def _job_with_image(d: Daemon, seq: int) -> None:
    """Run job ``seq`` to its end, then fetch its JPEG (so the image helper runs)."""
    await d.plc.write_registers(Reg.CMD, [Command.TRIGGER, seq])
    async with asyncio.timeout(WAIT_S):
        while True:
            rr = await d.plc.read_holding_registers(0, count=MAP_SIZE)
            assert not rr.isError(), rr
            if rr.registers[Reg.ACK_SEQ] == seq:
                break
            await asyncio.sleep(0.01)
    async with asyncio.timeout(WAIT_S), d.http.get(
            f"{d.base}/api/jobs/{seq}/image/left.jpg") as resp:
        assert resp.status == 200, await resp.text()
        assert (await resp.read())[:2] == b"\xff\xd8"


def _parent(pid: int) -> int:
    with open(f"/proc/{pid}/stat") as f:
        return int(f.read().rsplit(")", 1)[1].split()[1])


def _children_of_kind(pids: dict[int, str]) -> dict[str, list[int]]:
    """The daemon's descendants by kind: multiprocessing's resource tracker, its fork server,
    and the children forked by that server (which show the server's command line)."""
    kinds: dict[str, list[int]] = {"tracker": [], "server": [], "forked": []}
    servers = {pid for pid, cmd in pids.items() if "multiprocessing.forkserver" in cmd}
    for pid, cmd in pids.items():
        if "resource_tracker" in cmd:
            kinds["tracker"].append(pid)
        elif pid in servers:
            kinds["forked" if _parent(pid) in servers else "server"].append(pid)
    return kinds


async def test_systemd_stop_ends_every_child_with_a_job_in_flight_and_a_browser_open(
        tmp_path: Path) -> None:
    async with _daemon(tmp_path) as d:
        await _job_with_image(d, 1)
        children = _descendants(d.proc.pid)
        kinds = _children_of_kind(children)
        assert len(kinds["forked"]) == 2, children  # the worker and the JPEG helper
        assert len(kinds["server"]) == 1, children
        assert len(kinds["tracker"]) == 1, children
        # A browser: the live event stream stays open.
        events = await d.http.get(f"{d.base}/api/events")
        assert events.status == 200
        # A job in flight: triggered, not yet answered.
        await d.plc.write_registers(Reg.CMD, [Command.TRIGGER, 2])
        async with asyncio.timeout(WAIT_S):
            while True:  # the PLC's poll
                rr = await d.plc.read_holding_registers(Reg.STATE, count=1)
                if rr.registers[0] != 0:
                    break
                await asyncio.sleep(0.01)
        t0 = time.monotonic()
        os.killpg(d.proc.pid, signal.SIGTERM)  # systemd signals the whole control group
        left = await _survivors({d.proc.pid: "vgripd run", **children}, t0 + STOP_BOUND_S)
        events.close()
        assert not left, f"still running {STOP_BOUND_S:g} s after SIGTERM: {left}"
        async with asyncio.timeout(WAIT_S):
            await d.proc.wait()
            assert d.proc.stderr is not None
            stderr = (await d.proc.stderr.read()).decode()
    assert d.proc.returncode == 0, stderr
    assert "stopped" in stderr
    assert "leaked" not in stderr, stderr  # the resource tracker found nothing to clean up
    assert "Traceback" not in stderr, stderr


async def test_sigkill_of_the_daemon_ends_every_child(tmp_path: Path) -> None:
    async with _daemon(tmp_path) as d:
        await _job_with_image(d, 1)
        children = _descendants(d.proc.pid)
        assert len(_children_of_kind(children)["forked"]) == 2, children
        assert segments_of(f"vgripd-{d.proc.pid}-")  # the daemon's shared memory
        d.proc.kill()  # the daemon alone: no code of it runs any more
        await d.proc.wait()
        left = await _survivors(children, time.monotonic() + WAIT_S)
        assert not left, f"outlived the daemon's SIGKILL: {left}"
        # The resource tracker, last to go, unlinked the dead daemon's shared memory.
        assert segments_of(f"vgripd-{d.proc.pid}-") == []


async def test_the_image_helper_ends_on_sigterm_and_the_next_image_gets_a_new_one(
        tmp_path: Path) -> None:
    async with _daemon(tmp_path) as d:
        await _job_with_image(d, 1)
        helper = _descendants(d.proc.pid)
        worker_pid = int((await (await d.http.get(f"{d.base}/api/status")).json())
                         ["worker"]["pid"])
        helpers = [pid for pid in _children_of_kind(helper)["forked"] if pid != worker_pid]
        assert len(helpers) == 1, helper
        os.kill(helpers[0], signal.SIGTERM)
        assert not await _survivors({helpers[0]: "image helper"}, time.monotonic() + WAIT_S)
        # The daemon keeps serving: the next job's image comes from a new helper.
        await _job_with_image(d, 2)
        now = _children_of_kind(_descendants(d.proc.pid))["forked"]
        assert worker_pid in now
        assert len(now) == 2, now
        assert helpers[0] not in now, now
        assert d.proc.returncode is None
