"""Emptying a pallet over OPC UA: one StartSingleJob and Next calls vs a job per plate, same run.

The real daemon (worker process, vision pipeline) on the synthetic pallet of six touching
plates (bench/bench_next.py's scene), its ``opcua`` link on 127.0.0.1 (security None), and
asyncua's client in its own process (``vgripd.sim.opcua_client``) doing what docs/opcua.md
tells a client to: call the method, poll ``Result.RequestId`` until it is the call's, read the
result in one Read request, wait for the ResultReady event. Per pallet the client needs one
pose per plate:

- pick list: one ``StartSingleJob`` (every plate located in one job), then ``Next`` until
  NOT_FOUND;
- named peer, "a job per plate": one ``StartSingleJob`` per plate (each a full acquisition and
  location of the whole pallet, the first pose used): a client without ``Next``.

Time is on this process's clock around each command sent to the client process (the same pipe
overhead for both ways), per plate handed out; the two alternate pallet by pallet. Also the
median round trip of one ``Next`` against one ``StartSingleJob`` (the job's own time included),
and, as a sanity check, the Next poses against the synthetic camera's truth of the nearest
plate (not an accuracy benchmark: bench/bench_picklist.py renders independently).

    .venv/bin/python bench/bench_next_opcua.py [pallets]
"""

from __future__ import annotations

import asyncio
import statistics
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.bench_next import PLATES, plate_errors, report, started_daemon  # noqa: E402
from vgripd.sim.opcua_client import OpcUaClientProcess  # noqa: E402
from vgripd.types import Status  # noqa: E402

LINK = {"type": "opcua", "host": "127.0.0.1", "port": 0, "security": ["None"],
        "allow_anonymous": True}


async def timed(client: OpcUaClientProcess, line: str) -> tuple[dict[str, Any], float]:
    t0 = time.perf_counter()
    answer = await client.send(line)
    assert answer["event"] == "result", answer
    return answer, (time.perf_counter() - t0) * 1e3


async def main(pallets: int) -> None:
    daemon, jobs = await started_daemon([LINK])
    listed: list[float] = []
    per_plate: list[float] = []
    next_ms: list[float] = []
    job_ms: list[float] = []
    errors: list[tuple[float, float]] = []
    try:
        port: int = next(iter(daemon.links.values())).port  # type: ignore[attr-defined]
        async with OpcUaClientProcess(f"opc.tcp://127.0.0.1:{port}/vgripd") as client:
            assert client.connected["event"] == "connected", client.connected
            await timed(client, "job")  # warm-up: the worker's first job
            for _ in range(pallets):
                t0 = time.perf_counter()
                first, ms = await timed(client, "job")
                job_ms.append(ms)
                answers = [first]
                while answers[-1]["Status"] in (1, 2):
                    answer, ms = await timed(client, "next")
                    next_ms.append(ms)
                    answers.append(answer)
                listed.append((time.perf_counter() - t0) * 1e3 / PLATES)
                assert len(answers) == PLATES + 1, [a["StatusName"] for a in answers]
                errors += plate_errors(jobs[first["JobId"]])
                t0 = time.perf_counter()
                for _ in range(PLATES):
                    answer, ms = await timed(client, "job")
                    assert answer["Status"] == Status.OK, answer
                    job_ms.append(ms)
                per_plate.append((time.perf_counter() - t0) * 1e3 / PLATES)
    finally:
        await daemon.stop()
    report(f"{pallets} pallets of {PLATES} plates, OPC UA (asyncua client process) on 127.0.0.1",
           listed, per_plate, errors, "StartSingleJob + Next", "StartSingleJob")
    n, j = statistics.median(next_ms), statistics.median(job_ms)
    print(f"one Next: median {n:.1f} ms (min {min(next_ms):.1f}, max {max(next_ms):.1f}, "
          f"{len(next_ms)} calls); one StartSingleJob: median {j:.1f} ms "
          f"({len(job_ms)} calls); ratio x{j / n:.1f}")


if __name__ == "__main__":
    asyncio.run(main(int(sys.argv[1]) if len(sys.argv) > 1 else 5))
