"""Modbus/TCP client link: job round trip through ModbusClientLink vs a bare pymodbus client.

The robot program (``MockRobotModbus.run_job``, a pymodbus server on 127.0.0.1) raises a
request and waits for the acknowledge; the time is from its trigger write to the acknowledge
arriving. The named peer is a bare ``AsyncModbusTcpClient`` loop doing the minimum a link must
do per job with no handshake bookkeeping: poll the request words, then write the result block
and the acknowledge (3 transactions). Both poll every ``POLL_S``.
"""

from __future__ import annotations

import asyncio
import time

from pymodbus.client import AsyncModbusTcpClient

from bench.links import LinkRun, Series, answer_at_once
from drivers.links.modbus_client import ModbusClientLink, ModbusClientOptions
from vgripd.peer.registers import MAP_SIZE, Reg
from vgripd.sim.robot_modbus import MockRobotModbus
from vgripd.types import RobotTarget

DEFAULT_JOBS = 300
POLL_S = 0.002
BASE = 128
POSE = (412.5, -133.25, 287.0625, 0.1234, -2.9, 3.14159)


async def run_link(robot: MockRobotModbus, jobs: int) -> tuple[list[float], float]:
    opts = ModbusClientOptions(host=robot.host, port=robot.port, poll_interval_s=POLL_S)
    link = ModbusClientLink("bench", opts)
    target = RobotTarget("ur", ("x", "y", "z", "rx", "ry", "rz"), POSE)
    await link.open(answer_at_once(link, target))
    times = []
    before = link.transactions
    try:
        for seq in range(1, jobs + 1):
            t0 = time.perf_counter()
            await robot.run_job(seq, 5.0)
            times.append((time.perf_counter() - t0) * 1e3)
        per_job = (link.transactions - before) / jobs
    finally:
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
    start = count
    try:
        for i in range(jobs):
            t0 = time.perf_counter()
            await robot.run_job(base_offset + i + 1, 5.0)
            times.append((time.perf_counter() - t0) * 1e3)
        per_job = (count - start) / jobs
    finally:
        stop.set()
        await task
        client.close()
    return times, per_job


async def measure(jobs: int) -> LinkRun:
    robot = MockRobotModbus()
    await robot.start()
    try:
        link_ms, link_tx = await run_link(robot, jobs)
        bare_ms, bare_tx = await run_bare(robot, jobs)
    finally:
        await robot.stop()
    peer = "bare pymodbus client: poll, write result, write acknowledge"
    return LinkRun(
        heading="Modbus/TCP client link",
        setup=(f"{jobs} jobs per row, both polling every {POLL_S * 1e3:.0f} ms. Timed: how long "
               "the mock robot program (`vgripd/sim/robot_modbus.py`, a pymodbus server on "
               "127.0.0.1) waits from writing REQ_SEQ until ACK_SEQ arrives; the daemon side "
               "answers at once (no vision work). Peer: a bare `AsyncModbusTcpClient` loop with "
               "no handshake, heartbeat or mirror, the link first, then the peer."),
        series=[Series("vgripd ModbusClientLink, full handshake", link_ms, against=peer),
                Series(peer, bare_ms)],
        notes=[f"Modbus transactions per job: link {link_tx:.1f}, peer {bare_tx:.1f}."])
