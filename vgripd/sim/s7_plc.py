"""A stand-in for a Siemens S7 PLC: snap7's own server in a child process, and a PLC program.

``S7PlcServer`` runs python-snap7's ``Server`` in a separate process (``python -m
vgripd.sim.s7_plc serve``) with one data block registered, on 127.0.0.1 (a free port unless
one is given). Being a process of its own, it can fail the way a PLC does:

- ``kill``: the PLC is gone (SIGKILL: every connection drops, nobody listens); ``start`` again
  serves on the same port with a fresh, zeroed DB (a PLC whose DB was re-initialised);
- ``freeze`` / ``thaw``: SIGSTOP / SIGCONT, a silent peer: TCP stays open, nothing answers.

The child reports every DB write it serves, in arrival order, as a line on its stdout; the
parent keeps them in ``writes`` (offset and bytes), so tests can check that ACK_SEQ travelled
alone and last.

``MockS7Plc`` is the PLC program: it drives the handshake of ``vgripd.peer.registers``'s map
through a snap7 client, as a program in the PLC sees its own DB: write CMD and RECIPE (and on a
conveyor, map version 4, the latched encoder count), then a new REQ_SEQ; wait until ACK_SEQ or
REJECT_SEQ equals it; read the block. The layout is the
register map with each 16-bit word at byte ``start + 2 * address``, big-endian, which is S7's
own byte order, so there is no word-order option. The program decodes with ``struct`` at those
offsets, not with vgripd's codec or the UDT generator, so an encoding bug cannot cancel out.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import os
import signal
import struct
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

from snap7 import AsyncClient
from snap7.error import S7Error

from vgripd.errors import LinkError
from vgripd.peer.jobcore import Command
from vgripd.peer.registers import CHECK_F32, CHECK_U16, CHECK_U32, MAP_SIZE, Reg, ValueFormat

DB_BYTES = 2 * MAP_SIZE  # the map's 16-bit words, one after the other
STARTUP_S = 20.0  # a loaded 2-core CI machine can take seconds to start a Python process
CLOSE_S = 2.0  # the goodbye of the mock PLC program; then its socket is dropped
REPO = str(Path(__file__).resolve().parents[2])  # so the child imports this checkout


def offset(reg: int) -> int:
    """Byte offset of map register ``reg`` inside the block."""
    return 2 * int(reg)


def words_of(raw: bytes) -> tuple[int, ...]:
    """The block's bytes as the map's 16-bit words (big-endian)."""
    return struct.unpack(f">{len(raw) // 2}H", raw)


@dataclass(frozen=True)
class DbWrite:
    """One DB write as the server received it: ``start`` is the byte offset in the DB."""

    db: int
    start: int
    data: bytes


class S7PlcServer:
    """snap7's server in a child process, serving DB ``db`` of ``size`` bytes."""

    def __init__(self, db: int = 10, size: int = DB_BYTES, host: str = "127.0.0.1",
                 port: int = 0) -> None:
        self.db = db
        self.size = size
        self.host = host
        self.port = port
        self.writes: list[DbWrite] = []
        self._proc: asyncio.subprocess.Process | None = None
        self._reader: asyncio.Task[None] | None = None
        self._written = asyncio.Event()
        self.frozen = False

    async def __aenter__(self) -> S7PlcServer:
        await self.start()
        return self

    async def __aexit__(self, exc_type: type[BaseException] | None,
                        exc: BaseException | None, tb: TracebackType | None) -> None:
        await self.stop()

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    async def start(self) -> None:
        """Start the child and wait until it listens; with ``port=0`` the port it chose is kept
        for later starts."""
        if self._proc is not None:
            raise LinkError("S7 PLC stand-in: already running")
        env = {**os.environ,
               "PYTHONPATH": os.pathsep.join(p for p in (REPO, os.environ.get("PYTHONPATH"))
                                             if p)}
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "vgripd.sim.s7_plc", "serve", "--host", self.host,
            "--port", str(self.port), "--db", str(self.db), "--size", str(self.size),
            stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE, env=env,
        )
        assert proc.stdout is not None
        try:
            async with asyncio.timeout(STARTUP_S):
                line = (await proc.stdout.readline()).decode().split()
        except TimeoutError:
            proc.kill()
            await proc.wait()
            raise LinkError(f"S7 PLC stand-in did not start within {STARTUP_S} s") from None
        if line[:1] != ["READY"]:
            await proc.wait()
            raise LinkError(f"S7 PLC stand-in did not start (exit {proc.returncode}): {line}")
        self.port = int(line[1])
        self._proc = proc
        self.frozen = False
        self._reader = asyncio.create_task(self._read_journal(proc), name="s7 server journal")

    async def kill(self) -> None:
        """The PLC is gone: SIGKILL, no goodbye on any connection."""
        proc, self._proc = self._proc, None
        if proc is None:
            return
        with contextlib.suppress(ProcessLookupError):
            proc.kill()
            if self.frozen:
                proc.send_signal(signal.SIGCONT)
        await proc.wait()
        self.frozen = False
        reader, self._reader = self._reader, None
        if reader is not None:
            reader.cancel()
            await asyncio.gather(reader, return_exceptions=True)

    async def stop(self) -> None:
        await self.kill()

    def freeze(self) -> None:
        """A silent PLC: the process stops (SIGSTOP); connections stay open, nothing answers."""
        if self._proc is not None:
            self._proc.send_signal(signal.SIGSTOP)
            self.frozen = True

    def thaw(self) -> None:
        if self._proc is not None:
            self._proc.send_signal(signal.SIGCONT)
            self.frozen = False

    async def wait_write(self, pred: Callable[[DbWrite], bool], timeout_s: float) -> int:
        """Index in ``writes`` of the first write that satisfies ``pred`` (waits for it)."""
        async with asyncio.timeout(timeout_s):
            while True:
                for i, w in enumerate(self.writes):
                    if pred(w):
                        return i
                self._written.clear()
                await self._written.wait()

    async def _read_journal(self, proc: asyncio.subprocess.Process) -> None:
        assert proc.stdout is not None
        while line := await proc.stdout.readline():
            parts = line.decode().split()
            if len(parts) == 4 and parts[0] == "W":
                self.writes.append(DbWrite(int(parts[1]), int(parts[2]), bytes.fromhex(parts[3])))
                self._written.set()


@dataclass(frozen=True)
class S7JobSeen:
    """What the PLC program saw for one request.

    ``raw``: the block's bytes when ACK_SEQ or REJECT_SEQ matched; ``captured_ms`` and
    ``done_ms``: from writing REQ_SEQ to seeing CAPTURED_SEQ (None if the program never saw it
    before the answer) and to the answer, on the program's clock.
    """

    seq: int
    raw: bytes
    captured_ms: float | None
    done_ms: float

    @property
    def words(self) -> tuple[int, ...]:
        return words_of(self.raw)

    @property
    def rejected(self) -> bool:
        w = self.words
        return w[Reg.REJECT_SEQ] == self.seq and w[Reg.ACK_SEQ] != self.seq

    def u32(self, reg: int) -> int:
        value: int = struct.unpack_from(">I", self.raw, offset(reg))[0]
        return value

    def values(self, value_format: ValueFormat = "float32", scale: int = 10000) -> list[float]:
        """The N_VALUES pose values: S7 ``Real`` (float32) or ``DInt`` / ``scale``."""
        n = self.words[Reg.N_VALUES]
        if value_format == "float32":
            return list(struct.unpack_from(f">{n}f", self.raw, offset(Reg.VALUES)))
        return [v / scale for v in struct.unpack_from(f">{n}i", self.raw, offset(Reg.VALUES))]


class MockS7Plc:
    """The PLC program, as a snap7 (asyncio) client of the PLC stand-in's DB.

    ``start`` is the block's byte offset in the DB (the link's ``start`` option); ``size`` the
    block's bytes (``DB_BYTES``: map version 3; 124 for version 4).
    """

    def __init__(self, host: str, port: int, db: int = 10, start: int = 0, rack: int = 0,
                 slot: int = 1, poll_s: float = 0.001, size: int = DB_BYTES) -> None:
        self.host = host
        self.port = port
        self.db = db
        self.start = start
        self.size = size
        self.rack = rack
        self.slot = slot
        self.poll_s = poll_s
        self._client: AsyncClient | None = None

    async def __aenter__(self) -> MockS7Plc:
        await self.connect()
        return self

    async def __aexit__(self, exc_type: type[BaseException] | None,
                        exc: BaseException | None, tb: TracebackType | None) -> None:
        await self.close()

    async def connect(self, timeout_s: float = 10.0) -> None:
        """Connect, retrying until the server answers (it may be restarting)."""
        await self.close()
        async with asyncio.timeout(timeout_s):
            while True:
                client = AsyncClient()
                try:
                    await client.connect(self.host, self.rack, self.slot, self.port)
                except (S7Error, OSError):
                    await asyncio.sleep(0.05)
                    continue
                self._client = client
                return

    async def close(self) -> None:
        """Say goodbye if the PLC still listens; a dead or half-read connection is aborted.

        snap7's ``disconnect`` writes a disconnect request and waits for the socket to close,
        with no bound: after a request cancelled half-way, or a server killed under it, that
        wait can last for ever, so it gets ``CLOSE_S`` and then the socket is dropped.
        """
        client, self._client = self._client, None
        if client is None:
            return
        writer = getattr(getattr(client, "connection", None), "_writer", None)
        try:
            async with asyncio.timeout(CLOSE_S):
                await client.disconnect()
        except Exception:  # noqa: BLE001 - a timeout or a dead peer: drop the socket either way
            if writer is not None:
                writer.transport.abort()

    def _c(self) -> AsyncClient:
        if self._client is None:
            raise LinkError("mock S7 PLC: not connected")
        return self._client

    async def read(self) -> bytes:
        """The whole block (``size`` bytes from ``start``)."""
        return bytes(await self._c().db_read(self.db, self.start, self.size))

    async def until(self, pred: Callable[[bytes], bool], timeout_s: float) -> bytes:
        """Poll the block every ``poll_s`` until ``pred(block)``; returns that block."""
        async with asyncio.timeout(timeout_s):
            while True:
                raw = await self.read()
                if pred(raw):
                    return raw
                await asyncio.sleep(self.poll_s)

    async def write(self, reg: int, data: bytes) -> None:
        """Write raw bytes at map register ``reg`` (the PLC program's own writes)."""
        await self._c().db_write(self.db, self.start + offset(reg), bytearray(data))

    async def write_words(self, reg: int, words: list[int]) -> None:
        await self.write(reg, struct.pack(f">{len(words)}H", *words))

    async def run_job(self, seq: int, timeout_s: float, command: int = Command.TRIGGER,
                      recipe: int = 0, latch: int | None = None,
                      frame: int | None = None) -> S7JobSeen:
        """One request: CMD (and RECIPE) first, then REQ_SEQ; wait for its answer.

        ``latch`` (and ``frame``): map version 4, the encoder count the PLC latched (PREDICT:
        the count N) as a DInt at LATCH_COUNT (LATCH_FRAME), written before REQ_SEQ.

        Raises ``LinkError`` when the check words are wrong (wrong DB, start or layout) and
        ``TimeoutError`` when no answer comes within ``timeout_s``.
        """
        await self.write_words(Reg.CMD, [command])
        await self.write_words(Reg.RECIPE, [recipe])
        if latch is not None:
            await self.write(Reg.LATCH_COUNT, struct.pack(">I", latch & 0xFFFFFFFF))
        if frame is not None:
            await self.write(Reg.LATCH_FRAME, struct.pack(">I", frame & 0xFFFFFFFF))
        t0 = time.perf_counter()
        await self.write_words(Reg.REQ_SEQ, [seq])
        captured_ms: float | None = None
        async with asyncio.timeout(timeout_s):
            while True:
                raw = await self.read()
                w = words_of(raw)
                now_ms = (time.perf_counter() - t0) * 1e3
                if captured_ms is None and w[Reg.CAPTURED_SEQ] == seq:
                    captured_ms = now_ms
                if seq in (w[Reg.ACK_SEQ], w[Reg.REJECT_SEQ]):
                    break
                await asyncio.sleep(self.poll_s)
        check = (w[Reg.CHECK_U16], struct.unpack_from(">I", raw, offset(Reg.CHECK_U32))[0],
                 struct.unpack_from(">f", raw, offset(Reg.CHECK_F32))[0])
        if check[:2] != (CHECK_U16, CHECK_U32) or abs(check[2] - CHECK_F32) > 1e-3:
            raise LinkError(f"mock S7 PLC: check words {check} in DB{self.db} at {self.start} "
                            f"are not ({CHECK_U16:#x}, {CHECK_U32:#x}, {CHECK_F32})")
        return S7JobSeen(seq, raw, captured_ms, now_ms)


# -- the child process -----------------------------------------------------------------------


def serve(host: str, port: int, db: int, size: int) -> int:
    """Run snap7's server with DB ``db`` until stdin closes (the parent went away)."""
    from snap7 import Server
    from snap7.server import EVC_DATA_WRITE
    from snap7.type import SrvArea, SrvEvent

    logging.basicConfig(level=logging.CRITICAL)  # the parent sees faults on its own side
    area = bytearray(size)
    server = Server(log=False)
    server.host = host
    out = threading.Lock()

    def on_event(event: SrvEvent) -> None:
        # Called in the client's handler thread after the write, before it is answered: the
        # order of these lines is the order the writes were served in.
        if event.EvtCode == EVC_DATA_WRITE and event.EvtParam2 == db:
            start, n = int(event.EvtParam3), int(event.EvtParam4)
            with out:
                sys.stdout.write(f"W {db} {start} {bytes(area[start:start + n]).hex()}\n")
                sys.stdout.flush()

    server.set_events_callback(on_event)
    server.register_area(SrvArea.DB, db, area)
    server.start(tcp_port=port)
    assert server.server_socket is not None
    print(f"READY {server.server_socket.getsockname()[1]}", flush=True)
    try:
        sys.stdin.read()
    finally:
        server.stop()
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="snap7 server as an S7 PLC stand-in")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("serve")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=0)
    p.add_argument("--db", type=int, default=10)
    p.add_argument("--size", type=int, default=DB_BYTES)
    args = parser.parse_args(argv)
    return serve(args.host, args.port, args.db, args.size)


if __name__ == "__main__":
    sys.exit(main())
