"""Job round trip through ModbusClientLink vs a bare pymodbus client, same mock robot, same run.

The robot program (``MockRobotModbus.run_job``) raises a request and waits for the
acknowledge; the time is from its trigger write to the acknowledge arriving, over TCP on
127.0.0.1. The named peer is a bare ``AsyncModbusTcpClient`` loop doing the minimum a link
must do per job with no handshake bookkeeping: poll the request words, then write the result
block and the acknowledge (3 transactions). Both poll every ``POLL_S``.

    cd /work/main && .venv/bin/python bench/bench_modbus_client.py [jobs]
"""

from __future__ import annotations

import asyncio
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pymodbus.client import AsyncModbusTcpClient  # noqa: E402

from drivers.links.modbus_client import ModbusClientLink, ModbusClientOptions  # noqa: E402
from vgripd.service.protocol import MAP_SIZE, Reg, Trigger  # noqa: E402
from vgripd.sim.robot_modbus import MockRobotModbus  # noqa: E402
from vgripd.types import JobResult, RobotTarget, Status  # noqa: E402

POLL_S = 0.002
BASE = 128
POSE = (412.5, -133.25, 287.0625, 0.1234, -2.9, 3.14159)


def summary(name: str, ms: list[float], transactions: float) -> str:
    ms = sorted(ms)
    p95 = ms[int(0.95 * (len(ms) - 1))]
    return (f"{name:<22} median {statistics.median(ms):6.2f} ms  p95 {p95:6.2f} ms  "
            f"max {ms[-1]:6.2f} ms  {transactions:5.1f} Modbus transactions/job")


async def run_link(robot: MockRobotModbus, jobs: int) -> tuple[list[float], float]:
    opts = ModbusClientOptions(host=robot.host, port=robot.port, poll_interval_s=POLL_S)
    link = ModbusClientLink("bench", opts)
    tasks: set[asyncio.Task[None]] = set()

    async def answer(t: Trigger) -> None:
        await link.image_captured(t.seq, t.seq)
        target = RobotTarget("ur", ("x", "y", "z", "rx", "ry", "rz"), POSE)
        await link.publish(t.seq, JobResult(job_id=t.seq, status=Status.OK, target=target))

    def on_trigger(t: Trigger) -> None:
        task = asyncio.create_task(answer(t))
        tasks.add(task)
        task.add_done_callback(tasks.discard)

    await link.open(on_trigger)
    times = []
    before = link.transactions
    for seq in range(1, jobs + 1):
        t0 = time.perf_counter()
        await robot.run_job(seq, 5.0)
        times.append((time.perf_counter() - t0) * 1e3)
    per_job = (link.transactions - before) / jobs
    await link.close()
    return times, per_job


async def run_bare(robot: MockRobotModbus, jobs: int) -> tuple[list[float], float]:
    client = AsyncModbusTcpClient(robot.host, port=robot.port, reconnect_delay=0, retries=0)
    await client.connect()
    count = 0
    stop = asyncio.Event()

    async def serve() -> None:
        nonlocal count
        last = 0
        while not stop.is_set():
            rr = await client.read_holding_registers(BASE, count=3)
            count += 1
            seq = rr.registers[Reg.REQ_SEQ]
            if seq != last:
                last = seq
                await client.write_registers(BASE + Reg.STATUS, [1] * (MAP_SIZE - Reg.STATUS))
                await client.write_registers(BASE + Reg.ACK_SEQ, [seq])
                count += 2
            await asyncio.sleep(POLL_S)

    base_offset = 10_000  # sequences of their own, so nothing is mistaken for a link answer
    task = asyncio.create_task(serve())
    times = []
    start = 0
    for i in range(jobs):
        if i == 0:
            start = count
        t0 = time.perf_counter()
        await robot.run_job(base_offset + i + 1, 5.0)
        times.append((time.perf_counter() - t0) * 1e3)
    per_job = (count - start) / jobs
    stop.set()
    await task
    client.close()
    return times, per_job


async def main(jobs: int) -> None:
    robot = MockRobotModbus()
    await robot.start()
    try:
        link_ms, link_tx = await run_link(robot, jobs)
        bare_ms, bare_tx = await run_bare(robot, jobs)
    finally:
        await robot.stop()
    print(f"{jobs} jobs each, poll {POLL_S * 1e3:.0f} ms, mock robot (pymodbus server) on 127.0.0.1")
    print(summary("ModbusClientLink", link_ms, link_tx))
    print(summary("bare pymodbus client", bare_ms, bare_tx))
    ratio = statistics.median(link_ms) / statistics.median(bare_ms)
    print(f"median ratio link / bare: {ratio:.2f}")


if __name__ == "__main__":
    asyncio.run(main(int(sys.argv[1]) if len(sys.argv) > 1 else 300))
