"""Siemens S7 link: job round trip through S7Link vs a bare snap7 client loop, same PLC.

The PLC stand-in is python-snap7's own server in a child process (``vgripd/sim/s7_plc.py``);
the PLC program (``MockS7Plc.run_job``, a snap7 asyncio client) writes CMD and RECIPE, then a
new REQ_SEQ, and polls the block until ACK_SEQ equals it. The time is from its REQ_SEQ write to
seeing the acknowledge, over ISO-on-TCP on 127.0.0.1. The daemon stand-in answers at once.

The named peer is a bare synchronous ``snap7.Client`` in a thread doing the minimum a link must
do per job, with no handshake bookkeeping: read the request words, and on a new sequence write
the result data in one request and the acknowledge in a second. Both sides poll every
``POLL_S``; the PLC program polls every ``PLC_POLL_S`` in both runs.
"""

from __future__ import annotations

import asyncio
import struct
import threading
import time

import snap7

from bench.links import LinkRun, Series, answer_at_once
from drivers.links.s7 import S7Link, S7Options
from vgripd.peer.registers import Reg
from vgripd.peer.s7_block import DB_BYTES
from vgripd.sim.s7_plc import MockS7Plc, S7PlcServer
from vgripd.types import RobotTarget, Status

DEFAULT_JOBS = 300
DB = 10
POLL_S = 0.002
PLC_POLL_S = 0.001
POSE = (412.5, -133.25, 287.0625, 12.34, -29.0, 179.5)


async def run_link(server: S7PlcServer, plc: MockS7Plc, jobs: int) -> tuple[list[float], float]:
    link = S7Link("bench", S7Options(host=server.host, port=server.port, db=DB,
                                     poll_ms=round(POLL_S * 1000)))
    target = RobotTarget("kuka", ("x", "y", "z", "a", "b", "c"), POSE)
    await link.open(answer_at_once(link, target))
    times = []
    before = link.transactions
    try:
        for seq in range(1, jobs + 1):
            seen = await plc.run_job(seq, 5.0)
            times.append(seen.done_ms)
        per_job = (link.transactions - before) / jobs
    finally:
        await link.close()
    return times, per_job


def bare_loop(host: str, port: int, stop: threading.Event, counts: list[int]) -> None:
    client = snap7.Client()
    client.connect(host, 0, 1, port)
    data = bytearray(struct.pack(">H", Status.OK) + bytes(DB_BYTES - 2 * Reg.STATUS - 2))
    last = struct.unpack(">H", client.db_read(DB, 2 * Reg.REQ_SEQ, 2))[0]
    try:
        while not stop.is_set():
            cmd = client.db_read(DB, 0, 6)
            counts[0] += 1
            seq = struct.unpack_from(">H", cmd, 2 * Reg.REQ_SEQ)[0]
            if seq != last:
                last = seq
                client.db_write(DB, 2 * Reg.STATUS, data)
                client.db_write(DB, 2 * Reg.ACK_SEQ, bytearray(struct.pack(">H", seq)))
                counts[0] += 2
            time.sleep(POLL_S)
    finally:
        client.disconnect()


async def run_bare(server: S7PlcServer, plc: MockS7Plc, jobs: int) -> tuple[list[float], float]:
    stop = threading.Event()
    counts = [0]
    thread = threading.Thread(target=bare_loop, args=(server.host, server.port, stop, counts))
    thread.start()
    times = []
    try:
        await asyncio.sleep(0.2)  # connected and polling
        start = counts[0]
        base = 10_000  # sequences of their own, so nothing is mistaken for a link answer
        for i in range(jobs):
            seen = await plc.run_job(base + i + 1, 5.0)
            times.append(seen.done_ms)
        per_job = (counts[0] - start) / jobs
    finally:
        stop.set()
        await asyncio.to_thread(thread.join)
    return times, per_job


async def measure(jobs: int) -> LinkRun:
    server = S7PlcServer(DB)
    async with server, MockS7Plc(server.host, server.port, DB, poll_s=PLC_POLL_S) as plc:
        link_ms, link_rq = await run_link(server, plc, jobs)
        bare_ms, bare_rq = await run_bare(server, plc, jobs)
        t0 = time.perf_counter()
        for _ in range(200):
            await plc.read()
        read_ms = (time.perf_counter() - t0) / 200 * 1e3
    peer = "bare snap7 client: read the request, write result, write acknowledge"
    return LinkRun(
        heading="Siemens S7 link",
        setup=(f"{jobs} jobs per row, the link and the peer polling every {POLL_S * 1e3:.0f} ms, "
               f"the PLC program every {PLC_POLL_S * 1e3:.0f} ms; python-snap7 "
               f"{snap7.__version__}'s own server in a child process on 127.0.0.1. Timed: the "
               "mock PLC program (a snap7 asyncio client) from writing REQ_SEQ to seeing "
               "ACK_SEQ; the daemon side answers at once. Peer: a synchronous `snap7.Client` in "
               "a thread with no handshake bookkeeping; the link first, then the peer."),
        series=[Series("vgripd S7Link, full handshake", link_ms, against=peer),
                Series(peer, bare_ms)],
        notes=[f"S7 requests per job: link {link_rq:.1f}, peer {bare_rq:.1f}. One "
               f"{DB_BYTES}-byte DB read by the PLC program: {read_ms:.2f} ms."])
