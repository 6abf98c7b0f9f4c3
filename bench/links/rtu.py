"""Modbus RTU link: trigger to result over a socat pty pair vs a static pymodbus RTU server.

A master (pymodbus' synchronous serial client, in its own process so that its timing does not
share a GIL with the server) runs handshake cycles against:

- ``ModbusRtuLink`` with the daemon stand-in: trigger write -> poll ACK_SEQ every 2 ms ->
  result in hand;
- the named peer, a plain pymodbus ``ModbusSerialServer`` with a static datastore; the master
  does the same transactions a cycle needs at the least (one write, one 40-register read), with
  no vgripd logic behind them.

A pty has no baud rate: the figures are software latency. On a real line add the wire time,
given in the notes for two baud rates (11 bits per byte, 8N1 + start).

The master runs as ``python -m bench.links.rtu --master PORT MODE CYCLES``.
"""

from __future__ import annotations

import asyncio
import json
import os
import sys
import time
from pathlib import Path

from bench.harness import REPO, pty_pair
from bench.links import LinkRun, Series, answer_at_once
from drivers.links.modbus_rtu import ModbusRtuLink
from vgripd.peer.registers import MAP_SIZE, Reg
from vgripd.types import RobotTarget, Status

DEFAULT_JOBS = 300
BAUD = 115200
UNIT = 1
POLL_S = 0.002
POSE = (612.5, -98.125, 10.75, 2.5, -0.75, 179.5)


def master_main(port: str, mode: str, cycles: int) -> None:
    from pymodbus.client import ModbusSerialClient

    client = ModbusSerialClient(port, baudrate=BAUD, parity="N", timeout=1, retries=0)
    assert client.connect()
    times_ms: list[float] = []
    for seq in range(1, cycles + 1):
        t0 = time.perf_counter()
        assert not client.write_registers(Reg.CMD, [1, seq, 0], device_id=UNIT).isError()
        while True:
            r = client.read_holding_registers(0, count=MAP_SIZE, device_id=UNIT)
            assert not r.isError(), r
            if mode == "peer" or r.registers[Reg.ACK_SEQ] == seq:
                break
            time.sleep(POLL_S)
        times_ms.append((time.perf_counter() - t0) * 1000)
        if mode == "vgripd":
            assert (r.registers[Reg.STATUS], r.registers[Reg.N_VALUES]) == (Status.OK, 6)
    client.close()
    print(json.dumps(times_ms))


async def run_master(port: Path, mode: str, cycles: int) -> list[float]:
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "bench.links.rtu", "--master", str(port), mode, str(cycles),
        cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, stdout=asyncio.subprocess.PIPE)
    out, _ = await proc.communicate()
    assert proc.returncode == 0, "bench RTU master failed"
    times: list[float] = json.loads(out)
    return times


async def bench_vgripd(server_end: Path, client_end: Path, cycles: int) -> list[float]:
    link = ModbusRtuLink("rtu", ModbusRtuLink.Options(port=str(server_end), baudrate=BAUD,
                                                      parity="N", unit_id=UNIT))
    await link.open(answer_at_once(link, RobotTarget("kuka", tuple("XYZABC"), POSE)))
    try:
        return await run_master(client_end, "vgripd", cycles)
    finally:
        await link.close()


async def bench_peer(server_end: Path, client_end: Path, cycles: int) -> list[float]:
    from pymodbus.framer import FramerType
    from pymodbus.server import ModbusSerialServer
    from pymodbus.simulator import DataType, SimData, SimDevice

    device = SimDevice(UNIT, simdata=[SimData(0, values=[0] * MAP_SIZE,
                                              datatype=DataType.REGISTERS)])
    server = ModbusSerialServer(device, framer=FramerType.RTU, port=str(server_end),
                                baudrate=BAUD, parity="N", bytesize=8, stopbits=1)
    await server.serve_forever(background=True)
    try:
        return await run_master(client_end, "peer", cycles)
    finally:
        await server.shutdown()


async def measure(jobs: int) -> LinkRun:
    async with pty_pair() as (a, b):
        peer = await bench_peer(a, b, jobs)
        ours = await bench_vgripd(a, b, jobs)
    # Wire bytes of one minimal cycle: FC16 write of 3 registers (request 15, reply 8 bytes)
    # plus one 40-register read (request 8, reply 5 + 80 bytes).
    wire_bytes = 15 + 8 + 8 + 5 + 2 * MAP_SIZE
    wire_ms = {baud: wire_bytes * 11 / baud * 1000 for baud in (19200, 115200)}
    peer_name = "pymodbus static RTU server (write + read)"
    return LinkRun(
        heading="Modbus RTU link",
        setup=(f"{jobs} cycles per row over a socat pty pair (no baud-rate timing: software "
               "latency only). Trigger write -> ACK_SEQ seen (polling every 2 ms) -> result in "
               "hand, as the master (pymodbus' serial client in its own process) sees it; the "
               "daemon side answers at once. Peer: a plain pymodbus RTU server with a static "
               "datastore, one write + one 40-register read per cycle (the least a cycle "
               "needs); the peer first, then the link."),
        series=[Series("vgripd ModbusRtuLink, full handshake", ours, against=peer_name),
                Series(peer_name, peer)],
        notes=[f"On a real line the minimal cycle's {wire_bytes} bytes add "
               f"{wire_ms[19200]:.0f} ms at 19200 baud and {wire_ms[115200]:.1f} ms at 115200 "
               "baud (plus one more 40-register read per extra poll)."])


if __name__ == "__main__":
    if len(sys.argv) == 5 and sys.argv[1] == "--master":
        master_main(sys.argv[2], sys.argv[3], int(sys.argv[4]))
    else:
        sys.exit("usage: python -m bench.links.rtu --master PORT MODE CYCLES")
