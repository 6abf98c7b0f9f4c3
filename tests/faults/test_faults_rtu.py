"""Modbus RTU faults on a real pty line (socat): a port that refuses the configuration, an
adapter unplugged while running, a stray byte before a request.

- A parity the port cannot set (the kernel's EINVAL, simulated by refusing PARENB in
  ``tcsetattr``) or a path that is not a tty is a config error naming the port: the link is
  FAILED, nothing crashes, and a daemon with another link keeps serving; ``vgripd run`` with
  only that link exits 1 with one line.
- socat killed (the adapter unplugged): DOWN with the reason, logged once; socat started again
  at the same paths: UP, answering.
- One stray byte, then silence, then a request: the request is answered.
"""

from __future__ import annotations

import asyncio
import errno
import logging
import subprocess
import sys
import termios
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from drivers.links.modbus_rtu import ModbusRtuLink
from tests.faults.rtu_line import BAUD, PtyLine, RawMaster, read_request, read_words
from tests.integration.test_daemon import Plc, running, values
from vgripd.config import config_from_dict
from vgripd.errors import LinkError
from vgripd.peer.registers import CHECK_U16, MAP_SIZE, Reg
from vgripd.service.links.protocol import LinkState
from vgripd.types import Status

pytestmark = pytest.mark.timeout(120)
UNIT = 7
LOGGER = "drivers.links.modbus_rtu"


@pytest.fixture
def line(tmp_path: Path) -> Iterator[PtyLine]:
    pty = PtyLine(tmp_path)
    pty.plug()
    try:
        yield pty
    finally:
        pty.unplug()


def rtu_link(path: Path, **options: Any) -> ModbusRtuLink:
    opts: dict[str, Any] = {"port": str(path), "baudrate": BAUD, "parity": "N", "unit_id": UNIT}
    opts.update(options)
    return ModbusRtuLink("rtu", ModbusRtuLink.Options(**opts))


def refuse_parity(monkeypatch: pytest.MonkeyPatch) -> None:
    """The port's driver refuses any parity (as some pty and USB drivers do: EINVAL)."""
    real = termios.tcsetattr

    def tcsetattr(fd: int, when: int, attributes: list[Any]) -> None:
        if attributes[2] & termios.PARENB:
            raise termios.error(errno.EINVAL, "Invalid argument")
        real(fd, when, attributes)

    monkeypatch.setattr(termios, "tcsetattr", tcsetattr)


class LogEvent(logging.Handler):
    """Sets ``event`` when a record containing ``text`` is logged."""

    def __init__(self, text: str) -> None:
        super().__init__(logging.DEBUG)
        self.text = text
        self.event = asyncio.Event()

    def emit(self, record: logging.LogRecord) -> None:
        if self.text in record.getMessage():
            self.event.set()


async def read_map(master: RawMaster) -> list[int]:
    answer = await asyncio.to_thread(master.request, read_request(UNIT, 0, MAP_SIZE))
    return read_words(answer, MAP_SIZE)


async def test_parity_the_port_refuses_is_a_config_error(
        line: PtyLine, monkeypatch: pytest.MonkeyPatch) -> None:
    refuse_parity(monkeypatch)
    link = rtu_link(line.server, parity="E")
    with pytest.raises(LinkError) as raised:
        await link.open(lambda t: None)
    assert str(raised.value) == (
        f"link rtu: serial port {line.server} ({BAUD} 8E1, unit {UNIT}) refuses the "
        "configuration: [Errno 22] Invalid argument (check baudrate, parity and stopbits for "
        "this adapter)")
    assert link.health().state is LinkState.FAILED
    await link.close()
    # The same port without parity works.
    link = rtu_link(line.server, parity="N")
    await link.open(lambda t: None)
    try:
        assert link.health().state is LinkState.UP
    finally:
        await link.close()


@pytest.mark.parametrize("fault", ["parity", "not_a_tty"])
async def test_daemon_serves_on_when_the_rtu_port_is_misconfigured(
        fault: str, line: PtyLine, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    if fault == "parity":
        refuse_parity(monkeypatch)
        port = line.server
    else:
        port = tmp_path / "not-a-tty"
        port.write_text("")
    config = config_from_dict({
        "camera": {"type": "synthetic", "seed": 11, "max_tilt_deg": 2.0},
        "links": [{"type": "modbus_server", "host": "127.0.0.1", "port": 0},
                  {"type": "modbus_rtu", "port": str(port), "parity": "E", "unit_id": UNIT}],
        "status": {"port": 0},
    })
    async with running(config) as run, Plc(run.port(0)) as plc:
        await plc.trigger(1)
        words = await plc.result(1)
        snapshot = run.daemon.snapshot()
    assert words[Reg.STATUS] == Status.OK
    assert len(values(words)) == 6
    rtu = next(entry for entry in snapshot["links"] if entry["name"] == "modbus_rtu")
    assert rtu["state"] == "failed"
    why = ("refuses the configuration: [Errno 22] Invalid argument" if fault == "parity"
           else "is not a serial port")
    assert why in rtu["last_error"]
    assert str(port) in rtu["last_error"]
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert errors
    assert all(r.exc_info is None for r in caplog.records)
    assert any(r.getMessage().startswith("link modbus_rtu: ")
               and r.getMessage().endswith("; the other links serve without it")
               for r in errors)


def test_vgripd_run_with_only_a_misconfigured_rtu_link_exits_1_in_one_line(
        tmp_path: Path) -> None:
    port = tmp_path / "not-a-tty"
    port.write_text("")
    cfg = tmp_path / "rtu.toml"
    cfg.write_text(f'[camera]\ntype = "synthetic"\n\n[[links]]\ntype = "modbus_rtu"\n'
                   f'port = "{port}"\n\n[status]\nenabled = false\n')
    proc = subprocess.run([sys.executable, "-m", "vgripd", "run", "-c", str(cfg)],
                          capture_output=True, text=True, timeout=90, check=False)
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("vgripd: link modbus_rtu: ")
    assert "is not a serial port" in last


async def test_unplugged_adapter_is_down_once_then_back(
        line: PtyLine, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG, LOGGER)
    link = rtu_link(line.server, backoff_initial_s=0.05, backoff_max_s=0.2)
    await link.open(lambda t: None)
    retried = LogEvent("still down (attempt 3)")
    logging.getLogger(LOGGER).addHandler(retried)
    try:
        master = RawMaster(line.client)
        try:
            assert (await read_map(master))[Reg.CHECK_U16] == CHECK_U16
        finally:
            master.close()

        await asyncio.to_thread(line.unplug)
        down = await link.wait_state(LinkState.DOWN, timeout_s=5)
        assert str(line.server) in down.last_error
        await asyncio.wait_for(retried.event.wait(), 10)  # reopening failed a few times
        assert link.health().state is LinkState.DOWN
        assert "No such file or directory" in link.health().last_error

        await asyncio.to_thread(line.plug)
        up = await link.wait_state(LinkState.UP, timeout_s=5)
        assert (up.reconnects, up.last_error) == (1, "")
        master = RawMaster(line.client)
        try:
            assert (await read_map(master))[Reg.CHECK_U16] == CHECK_U16
        finally:
            master.close()
    finally:
        logging.getLogger(LOGGER).removeHandler(retried)
        await link.close()
    records = [r for r in caplog.records if r.name == LOGGER]
    warnings = [r.getMessage() for r in records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1, warnings  # once per outage
    assert "hung up" in warnings[0] or "reading serial port" in warnings[0]
    assert sum("is back" in r.getMessage() for r in records) == 1
    assert all(r.exc_info is None for r in caplog.records)


@pytest.mark.parametrize("stray", [0x01, 0x07, 0x10, 0xFF])
async def test_stray_byte_then_silence_does_not_cost_the_next_request(
        line: PtyLine, stray: int) -> None:
    link = rtu_link(line.server)
    await link.open(lambda t: None)
    master = RawMaster(line.client)
    try:
        for _ in range(3):
            await asyncio.to_thread(master.send, bytes([stray]))
            await asyncio.sleep(0.02)  # the silence under test: 20 ms >> 3.5 characters
            assert (await read_map(master))[Reg.CHECK_U16] == CHECK_U16
        assert link.frames_answered == 3
    finally:
        master.close()
        await link.close()
