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

import numpy as np  # noqa: E402

from vgripd.config import config_from_dict  # noqa: E402
from vgripd.geometry.transforms import pose_error  # noqa: E402
from vgripd.service.daemon import Daemon, JobRecord  # noqa: E402
from vgripd.sim.opcua_client import OpcUaClientProcess  # noqa: E402
from vgripd.types import ImagePair, Status  # noqa: E402

PLATES = 6
CONFIG: dict[str, Any] = {
    "camera": {"type": "synthetic", "seed": 3,
               "pallet": {"count": PLATES, "cols": 3, "gap_mm": 0.0, "jitter_mm": 2.0,
                          "jitter_deg": 3.0}},
    "picking": {"max_objects": PLATES, "order": "nearest", "point_mm": [600.0, -150.0, 10.0]},
    "limits": {"max_translation_mm": 200.0, "max_rotation_deg": 10.0},
    "links": [{"type": "opcua", "host": "127.0.0.1", "port": 0, "security": ["None"],
               "allow_anonymous": True}],
    "status": {"enabled": False},
    "daemon": {"log_level": "WARNING"},
}


async def timed(client: OpcUaClientProcess, line: str) -> tuple[dict[str, Any], float]:
    t0 = time.perf_counter()
    answer = await client.send(line)
    assert answer["event"] == "result", answer
    return answer, (time.perf_counter() - t0) * 1e3


async def main(pallets: int) -> None:
    daemon = Daemon(config_from_dict(CONFIG))
    jobs: dict[int, tuple[ImagePair | None, JobRecord]] = {}
    daemon.listeners.append(lambda pair, rec: jobs.__setitem__(rec.job_id, (pair, rec)))
    await daemon.start()
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
                pair, rec = jobs[first["JobId"]]
                assert pair is not None
                truths = pair.truth["instances_T_base_obj"]
                for inst in rec.result.instances:
                    assert inst.T_base_obj is not None
                    errors.append(min((pose_error(T, inst.T_base_obj) for T in truths),
                                      key=lambda e: e[0]))
                t0 = time.perf_counter()
                for _ in range(PLATES):
                    answer, ms = await timed(client, "job")
                    assert answer["Status"] == Status.OK, answer
                    job_ms.append(ms)
                per_plate.append((time.perf_counter() - t0) * 1e3 / PLATES)
    finally:
        await daemon.stop()
    a, b = statistics.median(listed), statistics.median(per_plate)
    n, j = statistics.median(next_ms), statistics.median(job_ms)
    e = np.array(errors)
    print(f"{pallets} pallets of {PLATES} plates, OPC UA (asyncua client process) on 127.0.0.1")
    print(f"pick list (StartSingleJob + Next):    median {a:7.1f} ms per plate "
          f"(min {min(listed):.1f}, max {max(listed):.1f})")
    print(f"a job per plate (StartSingleJob x {PLATES}): median {b:7.1f} ms per plate "
          f"(min {min(per_plate):.1f}, max {max(per_plate):.1f})")
    print(f"ratio (job per plate / pick list): x{b / a:.2f}")
    print(f"one Next: median {n:.1f} ms (min {min(next_ms):.1f}, max {max(next_ms):.1f}, "
          f"{len(next_ms)} calls); one StartSingleJob: median {j:.1f} ms "
          f"({len(job_ms)} calls); ratio x{j / n:.1f}")
    print(f"sanity: pick list poses vs the synthetic camera's truth over {len(e)} plates: "
          f"max {e[:, 0].max():.3f} mm, {e[:, 1].max():.3f} deg (mean {e[:, 0].mean():.3f} mm)")


if __name__ == "__main__":
    asyncio.run(main(int(sys.argv[1]) if len(sys.argv) > 1 else 5))
