"""The issue's acceptance: `vgripd run` on pylon's camera emulation (two "Basler Emulation"
cameras fed the rendered sample pairs through ImageFilename) answers the Modbus handshake with
exactly the pose registers that the same daemon on the replay driver answers for the same files.

Both daemons are real processes (camera and pipeline in the worker process, as deployed), driven
by a pymodbus client over TCP as a PLC would; every wait is on a register value."""

from __future__ import annotations

import asyncio
import importlib.util
import os
import re
import shutil
import socket
import subprocess
import sys
from pathlib import Path

from pymodbus.client import AsyncModbusTcpClient

from tests.conftest import REPO, need
from vgripd.peer.jobcore import Command
from vgripd.peer.registers import MAP_SIZE, Reg
from vgripd.types import Status

WAIT_S = 90.0
FRAMES = 3
SAMPLES = REPO / "config" / "samples"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def cell_config(camera: str, port: int) -> str:
    """config/example.toml (the demo cell's calibration, object and limits) with ``camera``
    as its [camera] section, the Modbus server on ``port`` and no web view."""
    text = (REPO / "config" / "example.toml").read_text()
    text = re.sub(r"(?ms)^\[camera\]\n.*?(?=^# --- calibration)", camera + "\n", text)
    text = text.replace("port = 1502", f"port = {port}")
    text = re.sub(r"(?m)^\[status\]\nenabled = true", "[status]\nenabled = false", text)
    assert f"port = {port}" in text
    assert "enabled = false" in text
    return text


async def _jobs(cfg: Path, env: dict[str, str], port: int) -> list[list[int]]:
    """Start `vgripd run -c cfg`, trigger FRAMES jobs over Modbus, return each job's result
    registers (STATUS, JOB_ID, N_VALUES, VALUES, FIT_RMS) as the PLC reads them."""
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)  # systemd's side of sd_notify
    notify.bind(str(cfg.with_suffix(".sock")))
    notify.setblocking(False)
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "vgripd", "run", "-c", str(cfg), cwd=REPO,
        env={**env, "NOTIFY_SOCKET": str(cfg.with_suffix(".sock"))},
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    client = AsyncModbusTcpClient("127.0.0.1", port=port, timeout=5, retries=0,
                                  reconnect_delay=0)
    results = []
    loop = asyncio.get_running_loop()
    try:
        async with asyncio.timeout(WAIT_S):
            while b"READY=1" not in await loop.sock_recv(notify, 4096):
                pass
            assert await client.connect()
            for seq in range(1, FRAMES + 1):
                rr = await client.write_registers(Reg.CMD, [Command.TRIGGER, seq])
                assert not rr.isError(), rr
                while True:
                    rr = await client.read_holding_registers(0, count=MAP_SIZE)
                    assert not rr.isError(), rr
                    if rr.registers[Reg.ACK_SEQ] == seq:
                        break
                    await asyncio.sleep(0.005)  # the PLC's poll period
                words = rr.registers  # all but RESULT_AGE_MS, which is live
                results.append(words[Reg.STATUS:Reg.RESULT_AGE_MS]
                               + words[Reg.N_VALUES:Reg.FIT_RMS + 2])
    finally:
        client.close()
        notify.close()
        proc.terminate()
        _, err = await proc.communicate()
    assert proc.returncode == 0, err.decode()[-3000:]
    return results


async def test_pylon_emulation_gives_the_replay_drivers_pose_to_the_last_digit(
        tmp_path: Path) -> None:
    need(importlib.util.find_spec("pypylon") is not None,
         "needs pypylon: pip install vgripd[pylon]")
    for side in ("left", "right"):  # one folder per emulated camera: it cycles through it
        (tmp_path / side).mkdir()
        for i in range(FRAMES):
            shutil.copy(SAMPLES / f"{side}_{i:02d}.png", tmp_path / side / f"{i:02d}.png")
    files = 'features = { TestImageSelector = "Off", ImageFileMode = "On", ImageFilename = "%s" }'
    pylon = f"""[camera]
type = "pylon"
roi = {{ x = 0, y = 0, width = 1280, height = 1024 }}
pixel_format = "Mono8"
exposure_us = 5000
[[camera.cameras]]
serial = "0815-0000"
{files % (tmp_path / "left")}
[[camera.cameras]]
serial = "0815-0001"
{files % (tmp_path / "right")}
"""
    replay = f"""[camera]
type = "replay"
folder = "{SAMPLES}"
left_glob = "left_*.png"
right_glob = "right_*.png"
"""
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYLON_CAMEMU": "2"}
    runs = []
    for name, camera in (("pylon", pylon), ("replay", replay)):
        port = _free_port()
        cfg = tmp_path / f"{name}.toml"
        cfg.write_text(cell_config(camera, port))
        runs.append(await _jobs(cfg, env, port))
    from_pylon, from_replay = runs
    for words in from_replay:  # a located plate with a pose, not an error code twice
        assert words[0] == Status.OK, words
        assert words[3] == 6  # N_VALUES
    assert from_pylon == from_replay  # every register word: the pose to the last bit
