"""UR RTDE link: trigger to result vs a bare ur_rtde responder, and whether the receive side keeps up with a 500 Hz stream. Everything runs against the mock UR controller
(its own process) with the real ur_rtde 1.6.5 client, in the same run.

Latency is timed by the mock's simulated robot program on its own clock: from writing the
trigger (output_int_register_12) to having read its last value.

- ``URRtdeLink``: full result (status, then the pose in two pages: two robot round trips), and a
  status-only answer (one round trip). The daemon side answers at once (no vision work).
- Named peer, ``bare ur_rtde``: a child process with ur_rtde's two interfaces and nothing else;
  it polls output_int_register_12 and writes status + ack (one round trip, no pipe, no asyncio).

Stream: a child process polls ``getTimestamp()`` of a 500 Hz ``RTDEReceiveInterface`` for
``STREAM_S`` and counts distinct timestamps against the packages the mock sent; a gap is a step
between consecutive timestamps larger than 1.5 periods.
"""

from __future__ import annotations

import asyncio
import multiprocessing
import time
from multiprocessing.connection import Connection

from bench.links import LinkRun, Series
from drivers.links.ur_rtde import URRtdeLink, URRtdeOptions
from vgripd.service.links.protocol import Trigger
from vgripd.sim.ur_controller import URController
from vgripd.types import JobResult, RobotTarget, Status

DEFAULT_JOBS = 200
HOST = "127.0.5.40"
POSE = (0.0123456789, -0.0345678901, 0.1 / 3, 0.0314159, -0.0285714, 0.1111111)
POLL_S = 0.002  # the link's child polls at its stream rate (500 Hz); the bare peer does the same
STREAM_S = 5.0


async def link_cycles(robot: URController, cycles: int, with_pose: bool) -> list[float]:
    queue: asyncio.Queue[Trigger] = asyncio.Queue()
    link = URRtdeLink("ur", URRtdeOptions(host=HOST))
    await link.open(queue.put_nowait)
    elapsed = []
    try:
        for job_id in range(1, cycles + 1):
            seq = robot.start_program(1)
            trigger = await asyncio.wait_for(queue.get(), 5)
            await link.image_captured(trigger.seq, job_id)
            if with_pose:
                result = JobResult(job_id, Status.OK, target=RobotTarget(
                    "ur", ("x", "y", "z", "rx", "ry", "rz"), POSE))
            else:
                result = JobResult(job_id, Status.NOT_FOUND)
            await link.publish(trigger.seq, result)
            answer = robot.program_result(seq)
            assert answer["error"] is None, answer
            assert answer["offset"] == (POSE if with_pose else None), answer
            elapsed.append(answer["elapsed_s"])
    finally:
        await link.close()
    return elapsed


def bare_responder(host: str, conn: Connection) -> None:
    import rtde_io
    import rtde_receive

    rcv = rtde_receive.RTDEReceiveInterface(host, 500.0, ["timestamp", "output_int_register_12"])
    io = rtde_io.RTDEIOInterface(host)
    last = rcv.getOutputIntRegister(12)
    conn.send("up")
    while not conn.poll(POLL_S):
        seq = rcv.getOutputIntRegister(12)
        if seq != last:
            last = seq
            io.setInputIntRegister(19, int(Status.NOT_FOUND))
            io.setInputIntRegister(18, seq)
    io.disconnect()


def bare_cycles(robot: URController, cycles: int) -> list[float]:
    ctx = multiprocessing.get_context("spawn")
    conn, child = ctx.Pipe()
    proc = ctx.Process(target=bare_responder, args=(HOST, child), daemon=True)
    proc.start()
    try:
        assert conn.poll(10)
        assert conn.recv() == "up"
        elapsed = []
        for _ in range(cycles):
            answer = robot.program_result(robot.start_program(1))
            assert answer["error"] is None, answer
            elapsed.append(answer["elapsed_s"])
        return elapsed
    finally:
        conn.send("stop")
        proc.join(10)


def stream_counter(host: str, seconds: float, conn: Connection) -> None:
    import rtde_receive

    rcv = rtde_receive.RTDEReceiveInterface(host, 500.0, ["timestamp"])
    stamps = [rcv.getTimestamp()]
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        ts = rcv.getTimestamp()
        if ts != stamps[-1]:
            stamps.append(ts)
        time.sleep(0.0002)
    conn.send((stamps, rcv.isConnected()))
    rcv.disconnect()


def stream_check(robot: URController) -> str:
    ctx = multiprocessing.get_context("spawn")
    conn, child = ctx.Pipe()
    proc = ctx.Process(target=stream_counter, args=(HOST, STREAM_S, child), daemon=True)
    proc.start()
    assert conn.poll(STREAM_S + 15)
    sent = sum(s["sent"] for s in robot.sessions())
    stamps, connected = conn.recv()
    proc.join(10)
    steps = [b - a for a, b in zip(stamps, stamps[1:], strict=False)]
    gaps = [s for s in steps if s > 1.5 / 500.0]
    return (f"500 Hz stream for {STREAM_S:.0f} s: mock sent {sent} packages, receiver saw "
            f"{len(stamps)} distinct timestamps ({100.0 * len(stamps) / sent:.1f} %), "
            f"{len(gaps)} gaps > 3 ms (largest {1000.0 * max(steps, default=0.0):.1f} ms), "
            f"still connected: {connected}")


async def measure(cycles: int) -> LinkRun:
    with URController(HOST) as robot:
        pose = await link_cycles(robot, cycles, with_pose=True)
        status_only = await link_cycles(robot, cycles, with_pose=False)
        bare = bare_cycles(robot, cycles)
        stream = stream_check(robot)
    peer = "bare ur_rtde, status only (1 round trip)"
    return LinkRun(
        heading="UR RTDE link",
        setup=(f"{cycles} cycles per row against the mock UR controller "
               f"(`vgripd/sim/ur_controller.py`, its own process, {HOST}:30004) with the real "
               "ur_rtde client; the link first (with the pose, then status only), then the "
               "peer. Timed on the mock's clock: its simulated robot program from writing the "
               "trigger (output_int_register_12) to having read its last value; the daemon "
               "side answers at once. Peer: a child process with ur_rtde's two interfaces and "
               "nothing else, polling at the stream rate and writing status + ack."),
        series=[Series("vgripd URRtdeLink, status + pose (2 round trips)",
                       [1000.0 * s for s in pose], against=peer),
                Series("vgripd URRtdeLink, status only (1 round trip)",
                       [1000.0 * s for s in status_only], against=peer),
                Series(peer, [1000.0 * s for s in bare])],
        notes=[stream + "."])
