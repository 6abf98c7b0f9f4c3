"""A serial line for RTU fault tests: a socat pty pair that can be unplugged (socat killed) and
plugged back at the same paths, and a raw RTU master on the other end that writes any bytes it
is given (noise, bad CRCs, truncated frames) and reads answers byte by byte.

The master's calls block: tests run them with ``asyncio.to_thread`` so the link under test keeps
answering on the test's event loop.
"""

from __future__ import annotations

import struct
import subprocess
import time
from pathlib import Path

import serial

from tests.conftest import need_tool
from vgripd.peer.rtu import crc_ok, with_crc

BAUD = 115200


class PtyLine:
    """``server``/``client``: the two pty paths (symlinks made by socat)."""

    def __init__(self, folder: Path) -> None:
        self.server = folder / "rtu-server"
        self.client = folder / "rtu-client"
        self._proc: subprocess.Popen[bytes] | None = None

    def plug(self) -> None:
        socat = need_tool("socat")
        self._proc = subprocess.Popen(
            [socat, f"pty,raw,echo=0,link={self.server}", f"pty,raw,echo=0,link={self.client}"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 5
        while not (self.server.exists() and self.client.exists()):
            assert self._proc.poll() is None, "socat exited"
            assert time.monotonic() < deadline, "socat did not create the pty links"
            time.sleep(0.01)

    def unplug(self) -> None:
        """The adapter goes away: the server end hangs up and its path disappears."""
        if self._proc is not None:
            self._proc.terminate()
            self._proc.wait(5)
            self._proc = None
        deadline = time.monotonic() + 5
        while self.server.exists() or self.client.exists():
            assert time.monotonic() < deadline, "socat left its pty links behind"
            time.sleep(0.01)


class RawMaster:
    """A Modbus RTU master that sends raw bytes and reads one answer frame."""

    def __init__(self, path: Path, baud: int = BAUD) -> None:
        self.port = serial.Serial(str(path), baud, timeout=0.5, exclusive=True)

    def close(self) -> None:
        self.port.close()

    def send(self, data: bytes) -> None:
        self.port.write(data)
        self.port.flush()

    def answer(self, timeout_s: float = 0.5) -> bytes | None:
        """The next answer frame (CRC checked by the caller), None if nothing comes."""
        self.port.timeout = timeout_s
        head = self.port.read(3)
        if len(head) < 3:
            return None
        function = head[1]
        if function & 0x80:
            rest = 2
        elif function in (3, 4, 23):
            rest = head[2] + 2
        elif function == 22:
            rest = 7
        else:
            rest = 5
        return head + self.port.read(rest)

    def request(self, frame: bytes, timeout_s: float = 0.5) -> bytes | None:
        self.port.reset_input_buffer()
        self.send(frame)
        return self.answer(timeout_s)


def read_request(unit: int, address: int, count: int) -> bytes:
    return with_crc(struct.pack(">BBHH", unit, 3, address, count))


def read_words(answer: bytes | None, count: int) -> list[int]:
    """The registers of a read answer; AssertionError for anything else."""
    assert answer is not None, "no answer"
    assert crc_ok(answer), f"bad CRC in {answer.hex()}"
    assert answer[1:3] == bytes((3, 2 * count)), f"not a read answer: {answer.hex()}"
    return list(struct.unpack(f">{count}H", answer[3:-2]))
