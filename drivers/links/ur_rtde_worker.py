"""Child-process side of the UR RTDE link: owns the ur_rtde interfaces, talks to the parent over a
pipe.

Why a child process: ur_rtde's constructors hold the GIL with no timeout (a controller that accepts
and stays silent would freeze the whole daemon), and destroying an IO interface whose socket died
aborts the process (SIGABRT). Here the worst case costs a child, which the parent kills and
restarts. The child never runs destructors: it leaves with ``os._exit`` and lets the kernel close
its sockets.

The child is the RTDE I/O shell: it decides nothing about requests. It reports every change of
the robot's request sequence with the data package it came in, and carries out the register
writes the parent's handshake planned (``vgripd.peer.ur_wire``), in order. The one rule it
keeps is the rotation page: the robot's page request is answered here, at the polling rate,
without a round trip through the parent (the pose's second half is as quick as before).

Pipe messages, parent -> child: ``(req, "write", (writes,))`` (``ur_wire.writes``),
``(req, "pose", ())``, ``(0, "close", ())``. Child -> parent:
``("started",)`` (the process runs, ur_rtde is loaded: the setup begins),
``("up", peer, baseline_seq, note)``,
``("request", seq, command, tcp_pose, recipe, latch_count | None)`` (the sequence changed: the
parent's ``Handshake`` judges it), ``("done", req)`` or ``("done", req, tcp_pose)``,
``("error", fatal, message)`` (the child exits right after).

Conveyor (``conveyor``, the link's ``map_version = 4``): the latch count is read from the
same data package as the trigger; the belt block goes into input registers ur_rtde cannot
write, through the child's own RTDE connection with one input recipe (``BeltWriter``), so the
whole block lands in one data package, before ur_rtde writes the acknowledge.

The child's stdout and stderr (ur_rtde prints its errors there, e.g. ``RTDEReceiveInterface
boost system Exception: (asio.misc:2) End of file``) are a pipe the parent reads and logs line by
line through vgripd's logging.

Pending request at the first connect: ur_rtde cannot read input registers, so the child asks the
controller once over a raw RTDE connection for the robot's request sequence and vgripd's
acknowledge register together (RTDE outputs may name input registers: "input read back"). A
sequence that differs from the acknowledge is a request nobody answered yet: it is served.
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

from vgripd.peer.ur_registers import URRegisterMap
from vgripd.service.host.children import ChildSetup, start_child

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


def read_pending(host: str, regs: URRegisterMap, timeout_s: float) -> tuple[int, int] | None:
    """(robot's request sequence, vgripd's acknowledge) from one data package of a raw RTDE
    connection; None when the controller does not offer input registers as outputs."""
    names = f"output_int_register_{regs.seq},input_int_register_{regs.ack}".encode("ascii")
    with socket.create_connection((host, RTDE_PORT), timeout=timeout_s) as sock:
        sock.sendall(struct.pack(">HBH", 5, ord("V"), 2))
        _recv_package(sock)
        setup = struct.pack(">d", 125.0) + names
        sock.sendall(struct.pack(">HB", 3 + len(setup), ord("O")) + setup)
        letter, payload = _recv_package(sock)
        while letter != "O":
            letter, payload = _recv_package(sock)
        if b"NOT_FOUND" in payload or not payload or payload[0] == 0:
            return None
        sock.sendall(struct.pack(">HB", 3, ord("S")))
        while True:
            letter, payload = _recv_package(sock)
            if letter == "U" and len(payload) == 9:
                seq, ack = struct.unpack(">ii", payload[1:])
                break
        with contextlib.suppress(OSError):
            sock.sendall(struct.pack(">HB", 3, ord("P")))
    return seq, ack


class BeltWriter:
    """The belt block's input registers over a raw RTDE connection of the child's own (one
    input recipe; data packages need no start and get no reply). A register another client or
    a fieldbus adapter owns (IN_USE) or the controller does not know (NOT_FOUND, software
    older than 3.9 / 5.3) is an outage that names it."""

    def __init__(self, host: str, regs: URRegisterMap, timeout_s: float) -> None:
        self.peer = f"{host}:{RTDE_PORT}"
        self.names = regs.belt_names
        try:
            self.sock = socket.create_connection((host, RTDE_PORT), timeout=timeout_s)
        except OSError as err:
            raise _Lost(f"{self.peer}: belt registers: {err}") from None
        try:
            self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.sock.sendall(struct.pack(">HBH", 5, ord("V"), 2))
            _recv_package(self.sock)
            body = ",".join(self.names).encode("ascii")
            self.sock.sendall(struct.pack(">HB", 3 + len(body), ord("I")) + body)
            letter, payload = _recv_package(self.sock)
            while letter != "I":  # skip text messages
                letter, payload = _recv_package(self.sock)
        except (OSError, ConnectionError, struct.error) as err:
            self.sock.close()
            raise _Lost(f"{self.peer}: belt registers: {err}") from None
        types = payload[1:].decode("ascii", "replace").split(",")
        bad = [f"{n} {t}" for n, t in zip(self.names, types, strict=False)
               if t in ("IN_USE", "NOT_FOUND")]
        if bad or not payload or payload[0] == 0:
            self.sock.close()
            raise _Lost(f"{self.peer}: {', '.join(bad) or 'the belt registers refused'} "
                        "(map_version = 4 needs these input registers free: a fieldbus "
                        "adapter or another RTDE client owns them, or the controller is "
                        "older than 3.9 / 5.3)", fatal=True)
        self.recipe = payload[0]

    def write(self, values: Sequence[int | float]) -> None:
        body = struct.pack(">B4i4d", self.recipe, *(int(v) for v in values[:4]),
                           *(float(v) for v in values[4:]))
        try:
            self.sock.sendall(struct.pack(">HB", 3 + len(body), ord("U")) + body)
        except OSError as err:
            raise _Lost(f"{self.peer}: writing the belt registers: {err}") from None


def _connect(host: str, regs: URRegisterMap, frequency_hz: float,
             timeout_s: float) -> tuple[Any, Any]:
    import rtde_io
    import rtde_receive

    peer = f"{host}:{RTDE_PORT}"
    names = ["timestamp", "actual_TCP_pose", *(f"output_int_register_{n}"
                                               for n in (regs.seq, regs.command,
                                                         regs.page_request, regs.recipe))]
    if regs.conveyor:
        names.append(f"output_int_register_{regs.latch}")
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


def first_baseline(seq: int, pending: tuple[int, int] | None) -> tuple[int, str]:
    """The sequence taken as already seen at the first connect, and a note for the log.

    ``seq``: the robot's sequence now; ``pending``: (sequence, acknowledge) read together by
    ``read_pending``. An unanswered request (sequence != acknowledge) is served: the baseline
    is its acknowledge. An answered one is not run again. Without the acknowledge nothing
    tells them apart, and the request is not served (the robot's retry asks again).
    """
    if pending is None:
        note = "" if seq == 0 else (
            f"cannot read the acknowledge register back (controller too old?): request {seq}, "
            "if it is still pending, is left to the robot's retry")
        return seq, note
    req, ack = pending
    if req != 0 and req != ack:
        return ack, f"request {req} was pending at start (acknowledge {ack}): serving it"
    return req, ""


class _Session:
    def __init__(self, conn: Connection, rcv: Any, io: Any, regs: URRegisterMap,
                 peer: str, last_seq: int | None, stale_after_s: float,
                 pending: tuple[int, int] | None = None,
                 belt: BeltWriter | None = None) -> None:
        self.conn, self.rcv, self.io, self.regs, self.peer = conn, rcv, io, regs, peer
        self.belt = belt
        self.stale_after_s = stale_after_s
        self.note = ""
        if last_seq is None:  # first connect: serve a request nobody answered yet
            self.last_seq, self.note = first_baseline(self.snapshot()[1], pending)
        else:
            self.last_seq = last_seq
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

    def snapshot(self) -> tuple[float, int, int, int, list[float], int, int | None]:
        """Timestamp, seq, command, page request, TCP pose, recipe and (``conveyor``) the
        latch count (32 bits, unsigned) from one data package.

        The getters read the newest package one by one; reading the timestamp before and after
        proves that no new package arrived in between.
        """
        r, regs = self.rcv, self.regs
        while True:
            ts = r.getTimestamp()
            values = (r.getOutputIntRegister(regs.seq), r.getOutputIntRegister(regs.command),
                      r.getOutputIntRegister(regs.page_request), list(r.getActualTCPPose()),
                      r.getOutputIntRegister(regs.recipe),
                      r.getOutputIntRegister(regs.latch) & 0xFFFFFFFF if regs.conveyor
                      else None)
            if r.getTimestamp() == ts:
                return (ts, *values)

    def handle(self, req: int, kind: str, args: tuple[Any, ...]) -> None:
        if kind == "write":  # the parent's plan (``ur_wire.writes``), in order
            for write in args[0]:
                self.write(write)
        elif kind == "pose":  # the robot's TCP pose now, from the newest data package
            self.conn.send(("done", req, self.snapshot()[4]))
            return
        self.conn.send(("done", req))

    def write(self, write: tuple[Any, ...]) -> None:
        what = write[0]
        if what == "int":
            self.write_int(write[1], write[2])
        elif what == "double":
            self.write_double(write[1], write[2])
        elif what == "belt":
            if self.belt is not None:
                self.belt.write(write[1])
        elif what == "page":  # the rotation page, handed out when the robot asks for it
            seq, rotation = write[1], write[2]
            self.pending_rotation = (seq, rotation) if rotation is not None else None

    def step(self) -> None:
        if not self.rcv.isConnected():
            raise _Lost(f"{self.peer}: data stream closed by the controller")
        ts, seq, command, page_request, pose, recipe, latch = self.snapshot()
        now = time.monotonic()
        if ts != self.last_ts:
            self.last_ts, self.last_ts_change = ts, now
        elif now - self.last_ts_change > self.stale_after_s:
            raise _Lost(f"{self.peer}: no new data package for {self.stale_after_s} s")
        if seq != self.last_seq:  # the parent's handshake judges whether it is a request
            self.last_seq = seq
            if seq != 0:  # a new sequence: the previous answer's rotation page is not wanted
                self.pending_rotation = None
            self.conn.send(("request", seq, command, pose, recipe, latch))
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


def link_child_setup() -> ChildSetup:
    """How the link's process starts (``start_child``): it ends with the daemon and ignores a
    terminal's SIGINT (the link closes it); it keeps the daemon's priority (it answers the
    robot at the polling rate) and logs nothing itself (its output goes to the parent)."""
    return ChildSetup.here()


def _redirect_output(output: Connection | None) -> None:
    """Send this process's stdout and stderr (C++ and Python alike) into the parent's pipe."""
    if output is None:
        return
    fd = output.fileno()
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    output.close()


def main(conn: Connection, output: Connection | None, host: str, upper: bool,
         frequency_hz: float, stale_after_s: float, probe_timeout_s: float,
         last_seq: int | None, setup: ChildSetup | None = None, conveyor: bool = False
         ) -> None:
    """Process entry point: connect, report ``up`` or ``error``, serve until closed or lost.

    ``setup``: the daemon's child set-up (``link_child_setup``: it ends with the daemon).
    ``conveyor``: the link's ``map_version = 4`` (the latch and the belt block).
    """
    if setup is not None:
        start_child(setup)
    _redirect_output(output)
    regs = URRegisterMap(upper, conveyor)
    peer = f"{host}:{RTDE_PORT}"
    code = 0
    try:
        import rtde_io  # noqa: F401 - loaded before "started": the parent's setup clock
        import rtde_receive  # noqa: F401 - then times the controller, not this start

        conn.send(("started",))
        rcv, io = _connect(host, regs, frequency_hz, probe_timeout_s)
        belt = BeltWriter(host, regs, probe_timeout_s) if conveyor else None
        pending = None
        if last_seq is None:
            try:
                pending = read_pending(host, regs, min(probe_timeout_s, 2.0))
            except (OSError, ConnectionError, struct.error):
                pending = None
        session = _Session(conn, rcv, io, regs, peer, last_seq, stale_after_s, pending, belt)
        conn.send(("up", peer, session.last_seq, session.note))
        session.run(1.0 / frequency_hz)
    except _Lost as err:
        with contextlib.suppress(OSError):
            conn.send(("error", err.fatal, str(err)))
        code = 1
    except (EOFError, OSError):  # the parent is gone
        code = 1
    # No destructors: ur_rtde aborts the process when it destroys an IO interface on a dead socket.
    os._exit(code)
