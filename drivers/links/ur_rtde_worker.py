"""Child-process side of the UR RTDE link: owns the ur_rtde interfaces, talks to the parent over a
pipe.

Why a child process: ur_rtde's constructors hold the GIL with no timeout (a controller that accepts
and stays silent would freeze the whole daemon), and destroying an IO interface whose socket died
aborts the process (SIGABRT). Here the worst case costs a child, which the parent kills and
restarts. The child never runs destructors: it leaves with ``os._exit`` and lets the kernel close
its sockets.

Pipe messages, parent -> child: ``(req, "captured", (seq, job_id))``,
``(req, "publish", (seq, status, job_id, translation | None, rotation | None))``,
``(req, "warnings", (bits,))``, ``(0, "close", ())``. Child -> parent:
``("up", peer, baseline_seq)``, ``("trigger", seq, command, tcp_pose)``, ``("done", req)``,
``("error", fatal, message)`` (the child exits right after).
"""

from __future__ import annotations

import contextlib
import os
import socket
import struct
import time
from collections.abc import Sequence
from multiprocessing.connection import Connection
from typing import Any

from vgripd.service.protocol import URRegisterMap

RTDE_PORT = 30004


class _Lost(Exception):
    """The session is unusable; ``fatal`` means retrying cannot help (configuration problem)."""

    def __init__(self, message: str, fatal: bool = False) -> None:
        super().__init__(message)
        self.fatal = fatal


def io_input_names(upper: bool) -> list[str]:
    """Every input name RTDEIOInterface claims in its 16 recipes (RTDE.md section 3e)."""
    off = 24 if upper else 0
    return [
        f"input_int_register_{23 + off}",
        "standard_digital_output_mask", "standard_digital_output",
        "tool_digital_output_mask", "tool_digital_output",
        "speed_slider_mask", "speed_slider_fraction",
        "standard_analog_output_mask", "standard_analog_output_type",
        "standard_analog_output_0", "standard_analog_output_1",
        "configurable_digital_output_mask", "configurable_digital_output",
        *(f"input_int_register_{n + off}" for n in range(18, 23)),
        *(f"input_double_register_{n + off}" for n in range(18, 23)),
    ]


def _recv_package(sock: socket.socket) -> tuple[str, bytes]:
    def exactly(n: int) -> bytes:
        buf = b""
        while len(buf) < n:
            chunk = sock.recv(n - len(buf))
            if not chunk:
                raise ConnectionError("controller closed the connection")
            buf += chunk
        return buf

    size, letter = struct.unpack(">HB", exactly(3))
    return chr(letter), exactly(size - 3)


def in_use_names(host: str, names: Sequence[str], timeout_s: float) -> list[str]:
    """Ask the controller which of ``names`` are IN_USE (one raw I request, then hang up).

    ur_rtde's own error does not say which register is taken; an operator needs exactly that.
    """
    with socket.create_connection((host, RTDE_PORT), timeout=timeout_s) as sock:
        sock.sendall(struct.pack(">HBH", 5, ord("V"), 2))
        _recv_package(sock)
        body = ",".join(names).encode("ascii")
        sock.sendall(struct.pack(">HB", 3 + len(body), ord("I")) + body)
        letter, payload = _recv_package(sock)
        while letter != "I":  # skip text messages
            letter, payload = _recv_package(sock)
    types = payload[1:].decode("ascii").split(",")
    return [n for n, t in zip(names, types, strict=False) if t == "IN_USE"]


def _connect(host: str, regs: URRegisterMap, frequency_hz: float,
             timeout_s: float) -> tuple[Any, Any]:
    import rtde_io
    import rtde_receive

    peer = f"{host}:{RTDE_PORT}"
    names = ["timestamp", "actual_TCP_pose", *(f"output_int_register_{n}"
                                               for n in (regs.seq, regs.command,
                                                         regs.page_request))]
    try:
        rcv = rtde_receive.RTDEReceiveInterface(host, frequency_hz, names, False, regs.upper)
    except RuntimeError as err:
        text = str(err)
        if "Could not connect" in text:
            raise _Lost(f"{peer} refused the connection (controller off, or not a UR "
                        "controller with RTDE enabled?)") from None
        if "not found" in text:
            raise _Lost(f"{peer}: controller does not know {text.split(':', 1)[-1].strip()} "
                        "(controller software too old for these registers?)", fatal=True) from None
        raise _Lost(f"{peer}: receive interface: {text}") from None
    if not rcv.isConnected():
        raise _Lost(f"{peer} completed the RTDE setup but sent no data package within 2.5 s")
    try:
        io = rtde_io.RTDEIOInterface(host, False, regs.upper)
    except RuntimeError as err:
        if "in use" not in str(err):
            raise _Lost(f"{peer}: IO interface: {err}") from None
        try:
            taken = in_use_names(host, io_input_names(regs.upper), timeout_s)
        except OSError as probe_err:
            taken = [f"(could not ask which: {probe_err})"]
        raise _Lost(f"{peer}: {', '.join(taken) or 'an input register'} IN_USE (owned by an "
                    "EtherNet/IP, PROFINET or Modbus adapter, or by another RTDE client)",
                    fatal=True) from None
    return rcv, io


class _Session:
    def __init__(self, conn: Connection, rcv: Any, io: Any, regs: URRegisterMap,
                 peer: str, last_seq: int | None, stale_after_s: float) -> None:
        self.conn, self.rcv, self.io, self.regs, self.peer = conn, rcv, io, regs, peer
        self.stale_after_s = stale_after_s
        # A request already pending at the first connect is older than this link: not served.
        self.last_seq = self.snapshot()[1] if last_seq is None else last_seq
        self.pending_rotation: tuple[int, Sequence[float]] | None = None
        self.last_ts = -1.0
        self.last_ts_change = time.monotonic()

    def write_int(self, reg: int, value: int) -> None:
        try:
            ok = self.io.setInputIntRegister(reg, int(value))
        except RuntimeError as err:
            raise _Lost(f"{self.peer}: writing input_int_register_{reg}: {err}") from None
        if not ok:
            raise _Lost(f"{self.peer}: writing input_int_register_{reg} failed")

    def write_double(self, reg: int, value: float) -> None:
        try:
            ok = self.io.setInputDoubleRegister(reg, float(value))
        except RuntimeError as err:
            raise _Lost(f"{self.peer}: writing input_double_register_{reg}: {err}") from None
        if not ok:
            raise _Lost(f"{self.peer}: writing input_double_register_{reg} failed")

    def write_page(self, values: Sequence[float]) -> None:
        for reg, value in zip(self.regs.page, values, strict=True):
            self.write_double(reg, value)

    def snapshot(self) -> tuple[float, int, int, int, list[float]]:
        """Timestamp, seq, command, page request and TCP pose from one data package.

        The getters read the newest package one by one; reading the timestamp before and after
        proves that no new package arrived in between.
        """
        r, regs = self.rcv, self.regs
        while True:
            ts = r.getTimestamp()
            values = (r.getOutputIntRegister(regs.seq), r.getOutputIntRegister(regs.command),
                      r.getOutputIntRegister(regs.page_request), list(r.getActualTCPPose()))
            if r.getTimestamp() == ts:
                return (ts, *values)

    def handle(self, req: int, kind: str, args: tuple[Any, ...]) -> None:
        regs = self.regs
        if kind == "captured":
            seq, job_id = args
            self.write_int(regs.job_id, job_id)
            self.write_int(regs.captured, seq)
        elif kind == "publish":
            seq, status, job_id, translation, rotation = args
            if translation is not None:
                self.write_page(translation)
            self.write_int(regs.status, status)
            self.write_int(regs.job_id, job_id)
            self.write_int(regs.ack, seq)  # last: the robot reads nothing before it sees this
            self.pending_rotation = (seq, rotation) if rotation is not None else None
        elif kind == "warnings":
            self.write_double(regs.warnings, args[0])
        self.conn.send(("done", req))

    def step(self) -> None:
        if not self.rcv.isConnected():
            raise _Lost(f"{self.peer}: data stream closed by the controller")
        ts, seq, command, page_request, pose = self.snapshot()
        now = time.monotonic()
        if ts != self.last_ts:
            self.last_ts, self.last_ts_change = ts, now
        elif now - self.last_ts_change > self.stale_after_s:
            raise _Lost(f"{self.peer}: no new data package for {self.stale_after_s} s")
        if seq != self.last_seq and seq != 0:
            self.last_seq = seq
            self.pending_rotation = None
            self.conn.send(("trigger", seq, command, pose))
        pending = self.pending_rotation
        if pending is not None and page_request == pending[0]:
            self.write_page(pending[1])
            self.write_int(self.regs.page_ack, pending[0])  # last
            self.pending_rotation = None

    def run(self, poll_s: float) -> None:
        while True:
            if self.conn.poll(poll_s):
                while self.conn.poll():
                    req, kind, args = self.conn.recv()
                    if kind == "close":
                        return
                    self.handle(req, kind, args)
            self.step()


def main(conn: Connection, host: str, upper: bool, frequency_hz: float, stale_after_s: float,
         probe_timeout_s: float, last_seq: int | None) -> None:
    """Process entry point: connect, report ``up`` or ``error``, serve until closed or lost."""
    regs = URRegisterMap(upper)
    peer = f"{host}:{RTDE_PORT}"
    code = 0
    try:
        rcv, io = _connect(host, regs, frequency_hz, probe_timeout_s)
        session = _Session(conn, rcv, io, regs, peer, last_seq, stale_after_s)
        conn.send(("up", peer, session.last_seq))
        session.run(1.0 / frequency_hz)
    except _Lost as err:
        with contextlib.suppress(OSError):
            conn.send(("error", err.fatal, str(err)))
        code = 1
    except (EOFError, OSError):  # the parent is gone
        code = 1
    # No destructors: ur_rtde aborts the process when it destroys an IO interface on a dead socket.
    os._exit(code)
