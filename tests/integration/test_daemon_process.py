"""`python -m vgripd run` as a real process: sd_notify on a socket the test binds (as systemd
would), SIGTERM in the middle of a job, and config errors exiting 78 with the field path."""

from __future__ import annotations

import asyncio
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from pymodbus.client import AsyncModbusTcpClient

from tests.conftest import REPO
from vgripd.peer.jobcore import Command, HandshakeState
from vgripd.peer.registers import MAP_SIZE, Reg
from vgripd.types import Status

WAIT_S = 60.0
ENV = {**os.environ, "PYTHONPATH": str(REPO)}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


async def _recv_until(sock: socket.socket, wanted: str, seen: list[str]) -> None:
    loop = asyncio.get_running_loop()
    async with asyncio.timeout(WAIT_S):
        while not any(wanted in m.split("\n") for m in seen):
            seen.append((await loop.sock_recv(sock, 4096)).decode())


async def _poll(client: AsyncModbusTcpClient, reg: int, value: int) -> list[int]:
    async with asyncio.timeout(WAIT_S):
        while True:
            rr = await client.read_holding_registers(0, count=MAP_SIZE)
            assert not rr.isError(), rr
            if rr.registers[reg] == value:
                return list(rr.registers)
            await asyncio.sleep(0.005)  # the PLC's poll period


async def test_sigterm_mid_job_publishes_aborted_and_exits_cleanly(tmp_path: Path) -> None:
    port = _free_port()
    cfg = tmp_path / "vgripd.toml"
    # supersample = 32 makes each synthetic frame take seconds to render: a slow job.
    cfg.write_text(f"""
[camera]
type = "synthetic"
seed = 1
supersample = 32

[[links]]
type = "modbus_server"
host = "127.0.0.1"
port = {port}

[status]
enabled = false
""")
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(tmp_path / "notify.sock"))
    notify.setblocking(False)
    env = {**ENV, "NOTIFY_SOCKET": str(tmp_path / "notify.sock"), "WATCHDOG_USEC": "2000000",
           "JOURNAL_STREAM": "8:1234"}
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "vgripd", "run", "-c", str(cfg), cwd=REPO, env=env,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    messages: list[str] = []
    client = AsyncModbusTcpClient("127.0.0.1", port=port, timeout=5, retries=0,
                                  reconnect_delay=0)
    try:
        await _recv_until(notify, "READY=1", messages)
        await _recv_until(notify, "WATCHDOG=1", messages)
        assert await client.connect()
        await client.write_registers(Reg.CMD, [Command.TRIGGER, 1])
        await _poll(client, Reg.STATE, HandshakeState.TRIGGERED)  # the job is running
        proc.send_signal(signal.SIGTERM)
        words = await _poll(client, Reg.ACK_SEQ, 1)
        assert words[Reg.STATUS] == Status.ABORTED
        assert words[Reg.N_VALUES] == 0
        await _recv_until(notify, "STOPPING=1", messages)
        async with asyncio.timeout(WAIT_S):
            _, err = await proc.communicate()
    finally:
        client.close()
        notify.close()
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    stderr = err.decode()
    assert proc.returncode == 0, stderr
    assert "job 1: ABORTED" in stderr
    assert "stopped" in stderr
    # Under systemd (JOURNAL_STREAM set) lines carry no timestamp: journald adds its own.
    assert all(line.split(" ", 1)[0] in ("DEBUG", "INFO", "WARNING", "ERROR")
               for line in stderr.splitlines() if line.strip())
    ready = next(m for m in messages if "READY=1" in m)
    assert "STATUS=idle" in ready
    # STATUS= follows the job through its states.
    assert any(m.startswith("STATUS=acquiring") for m in messages), messages


def _vgripd(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "vgripd", *args], capture_output=True,
                          text=True, cwd=REPO, env=ENV, timeout=120, check=False)


def test_config_errors_exit_78_naming_the_field(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    """Every case of both commands through ``main`` (what ``python -m vgripd`` exits with), the
    first one of ``run`` (the exit status systemd sees) also as a real process: a process start
    per case would add seconds each and test nothing more (``__main__`` is
    ``sys.exit(main())``; test_check_accepts_a_good_config... runs ``check`` as a process)."""
    from vgripd.__main__ import main

    cases = {
        "[daemon]\njob_timeout_s = -1\n": "daemon.job_timeout_s",
        "[deamon]\nlog_level = 'INFO'\n": "deamon",
        "[[links]]\ntype = 'modbus_server'\nprot = 5020\n": "links.0: prot",
        "[record]\nmax_mb = 0\n": "record.max_mb",
        "[status]\nport = 70000\n": "status.port",
        # a link that cannot carry the vendor: both fields named (LinkCapabilities)
        "[output]\nvendor = 'kuka'\n[[links]]\ntype = 'ur_rtde'\nhost = '10.0.0.2'\n":
            'links[0].type = "ur_rtde" cannot carry output.vendor = "kuka"',
        "[output]\nvendor = 'matrix'\n[[links]]\ntype = 'modbus_server'\nport = 5020\n":
            'links[0].type = "modbus_server" cannot carry output.vendor = "matrix"',
    }
    for i, (text, field) in enumerate(cases.items()):
        cfg = tmp_path / "bad.toml"
        cfg.write_text(text)
        for command in ("run", "check"):
            if i == 0 and command == "run":
                proc = _vgripd(command, "-c", str(cfg))
                assert proc.returncode == 78, (command, text, proc.stderr)
                assert field in proc.stderr, (command, text, proc.stderr)
            rc = main([command, "-c", str(cfg)])
            stderr = capsys.readouterr().err
            assert rc == 78, (command, text, stderr)
            assert field in stderr, (command, text, stderr)


def test_check_accepts_a_good_config_and_refuses_an_uncalibrated_one(tmp_path: Path) -> None:
    good = tmp_path / "good.toml"
    good.write_text("[[links]]\ntype = 'modbus_server'\nport = 5020\n")
    proc = _vgripd("check", "-c", str(good))
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith(f"OK {good}")
    uncalibrated = tmp_path / "uncal.toml"
    uncalibrated.write_text(f"[camera]\ntype = 'replay'\nfolder = '{tmp_path}'\nglob = '*.png'\n")
    proc = _vgripd("check", "-c", str(uncalibrated))
    assert proc.returncode == 78
    assert "not calibrated" in proc.stderr
