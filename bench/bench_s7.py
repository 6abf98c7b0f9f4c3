"""Job round trip through S7Link vs a bare snap7 client loop, same PLC stand-in, same run.

The PLC stand-in is python-snap7's own server in a child process (``vgripd/sim/s7_plc.py``);
the PLC program (``MockS7Plc.run_job``, a snap7 asyncio client) writes CMD and RECIPE, then a
new REQ_SEQ, and polls the block until ACK_SEQ equals it. The time is from its REQ_SEQ write to
seeing the acknowledge, over ISO-on-TCP on 127.0.0.1. The daemon side answers at once
(image_captured, then publish; no vision work).

The named peer is a bare synchronous ``snap7.Client`` in a thread doing the minimum a link must
do per job, with no handshake bookkeeping: read the request words, and on a new sequence write
the result data in one request and the acknowledge in a second. Both sides poll every
``POLL_S``; the PLC program polls every ``PLC_POLL_S`` in both runs.

    cd /work/main && .venv/bin/python bench/bench_s7.py [jobs]
"""

from __future__ import annotations

import asyncio
import statistics
import struct
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import snap7  # noqa: E402

from drivers.links.s7 import DB_BYTES, S7Link, S7Options  # noqa: E402
from vgripd.service.protocol import Reg, Trigger  # noqa: E402
from vgripd.sim.s7_plc import MockS7Plc, S7PlcServer  # noqa: E402
from vgripd.types import JobResult, RobotTarget, Status  # noqa: E402

DB = 10
POLL_S = 0.002
PLC_POLL_S = 0.001
POSE = (412.5, -133.25, 287.0625, 12.34, -29.0, 179.5)


def summary(name: str, ms: list[float], requests: float) -> str:
    ms = sorted(ms)
    p95 = ms[int(0.95 * (len(ms) - 1))]
    return (f"{name:<20} median {statistics.median(ms):6.2f} ms  p95 {p95:6.2f} ms  "
            f"max {ms[-1]:6.2f} ms  {requests:5.1f} S7 requests/job")


async def run_link(server: S7PlcServer, plc: MockS7Plc, jobs: int) -> tuple[list[float], float]:
    link = S7Link("bench", S7Options(host=server.host, port=server.port, db=DB,
                                     poll_ms=round(POLL_S * 1000)))
    tasks: set[asyncio.Task[None]] = set()

    async def answer(t: Trigger) -> None:
        await link.image_captured(t.seq, t.seq)
        target = RobotTarget("kuka", ("x", "y", "z", "a", "b", "c"), POSE)
        await link.publish(t.seq, JobResult(job_id=t.seq, status=Status.OK, target=target))

    def on_trigger(t: Trigger) -> None:
        task = asyncio.create_task(answer(t))
        tasks.add(task)
        task.add_done_callback(tasks.discard)

    await link.open(on_trigger)
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


async def main(jobs: int) -> None:
    server = S7PlcServer(DB)
    async with server, MockS7Plc(server.host, server.port, DB, poll_s=PLC_POLL_S) as plc:
        link_ms, link_rq = await run_link(server, plc, jobs)
        bare_ms, bare_rq = await run_bare(server, plc, jobs)
        t0 = time.perf_counter()
        for _ in range(200):
            await plc.read()
        read_ms = (time.perf_counter() - t0) / 200 * 1e3
    print(f"{jobs} jobs each, poll {POLL_S * 1e3:.0f} ms (PLC program {PLC_POLL_S * 1e3:.0f} ms), "
          f"python-snap7 {snap7.__version__} server in its own process on 127.0.0.1")
    print(f"one {DB_BYTES}-byte DB read by the PLC program: {read_ms:.2f} ms")
    print(summary("S7Link", link_ms, link_rq))
    print(summary("bare snap7 client", bare_ms, bare_rq))
    ratio = statistics.median(link_ms) / statistics.median(bare_ms)
    print(f"median ratio link / bare: {ratio:.2f}")


if __name__ == "__main__":
    asyncio.run(main(int(sys.argv[1]) if len(sys.argv) > 1 else 300))
