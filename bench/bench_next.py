"""Emptying a pallet: one request and NEXTs vs a request per plate, over Modbus/TCP or OPC UA.

The real daemon (worker process, vision pipeline) on the synthetic pallet of six touching
plates (config/samples/pallet.toml's scene), its link on 127.0.0.1, and the link's peer client
doing what the link's page tells a PLC to. Per pallet the client needs one pose per plate:

- pick list: one request (every plate located in one job), then NEXT until NOT_FOUND;
- named peer, "a job per plate": what a client without NEXT does, one request per plate taken
  (each a full acquisition and location of the whole pallet, the first pose used).

``--link modbus``: the mock PLC (``vgripd.sim.plc``) polling every 5 ms; time on its clock, from
the first request written to the last answer seen. ``--link opcua`` (security None): asyncua's
client in its own process (``vgripd.sim.opcua_client``): call ``StartSingleJob``, poll
``Result.RequestId`` until it is the call's, read the result in one Read request, wait for the
ResultReady event; time on this process's clock around each command sent to the client process
(the same pipe overhead for both ways), and the median round trip of one ``Next`` against one
``StartSingleJob`` (the job's own time included).

The figure is ms per plate handed out; the two ways alternate pallet by pallet, so load changes
hit both. The pose errors of the pick list's plates against the synthetic camera's truth are a
sanity check that the list is the pallet, not an accuracy benchmark (bench/bench_picklist.py
renders with the independent path of ``bench/render_independent.py``).

    .venv/bin/python bench/bench_next.py [--link modbus|opcua] [--pallets 5] [--print-only]
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

from bench import harness  # noqa: E402
from vgripd.config import config_from_dict  # noqa: E402
from vgripd.geometry.transforms import pose_error  # noqa: E402
from vgripd.service.daemon import Daemon  # noqa: E402
from vgripd.service.jobs.jobrecord import JobRecord  # noqa: E402
from vgripd.sim.opcua_client import OpcUaClientProcess  # noqa: E402
from vgripd.sim.plc import MockPlc  # noqa: E402
from vgripd.types import ImagePair, Status  # noqa: E402

PLATES = 6
CONFIG: dict[str, Any] = {
    "camera": {"type": "synthetic", "seed": 3,
               "pallet": {"count": PLATES, "cols": 3, "gap_mm": 0.0, "jitter_mm": 2.0,
                          "jitter_deg": 3.0}},
    "picking": {"max_objects": PLATES, "order": "nearest", "point_mm": [600.0, -150.0, 10.0]},
    "limits": {"max_translation_mm": 200.0, "max_rotation_deg": 10.0},
    "status": {"enabled": False},
    "daemon": {"log_level": "WARNING"},
}


async def started_daemon(
        links: list[dict[str, Any]]) -> tuple[Daemon, dict[int, tuple[ImagePair | None, JobRecord]]]:
    """The pallet cell with ``links``, started; the second value fills with every job."""
    daemon = Daemon(config_from_dict({**CONFIG, "links": links}))
    jobs: dict[int, tuple[ImagePair | None, JobRecord]] = {}
    daemon.rooms.jobs.listeners.append(lambda pair, rec: jobs.__setitem__(rec.job_id, (pair, rec)))
    await daemon.start()
    return daemon, jobs


def plate_errors(job: tuple[ImagePair | None, JobRecord]) -> list[tuple[float, float]]:
    """Each listed plate's pose error against the nearest true plate (mm, deg)."""
    pair, rec = job
    assert pair is not None
    truths = pair.truth["instances_T_base_obj"]
    errors = []
    for inst in rec.result.instances:
        assert inst.T_base_obj is not None
        errors.append(min((pose_error(T, inst.T_base_obj) for T in truths), key=lambda e: e[0]))
    return errors


def report(what: str, listed: list[float], per_plate: list[float],
           errors: list[tuple[float, float]], list_way: str, peer_way: str) -> list[str]:
    a, b = statistics.median(listed), statistics.median(per_plate)
    e = np.array(errors)
    return [
        what, "",
        "| way to get six poses | median ms per plate | min | max |", "|---|---:|---:|---:|",
        f"| pick list: {list_way} | {a:.1f} | {min(listed):.1f} | {max(listed):.1f} |",
        f"| a job per plate: {peer_way} x {PLATES} | {b:.1f} | {min(per_plate):.1f} | "
        f"{max(per_plate):.1f} |", "",
        f"Ratio (job per plate / pick list): x{b / a:.2f}. Sanity: the pick list's poses against "
        f"the synthetic camera's truth over {len(e)} plates: max {e[:, 0].max():.3f} mm, "
        f"{e[:, 1].max():.3f} deg (mean {e[:, 0].mean():.3f} mm)."]


async def over_modbus(pallets: int) -> list[str]:
    daemon, jobs = await started_daemon([{"type": "modbus_server", "host": "127.0.0.1",
                                          "port": 0}])
    listed: list[float] = []
    per_plate: list[float] = []
    errors: list[tuple[float, float]] = []
    try:
        port: int = next(iter(daemon.rooms.links.links.values())).port  # type: ignore[attr-defined]
        async with MockPlc("127.0.0.1", port, poll_s=0.005) as plc:
            await plc.cycle()  # warm-up: the worker's first job
            for _ in range(pallets):
                t0 = time.perf_counter()
                answers = [await plc.cycle()]
                while answers[-1].status.pose_valid:
                    answers.append(await plc.next())
                listed.append((time.perf_counter() - t0) * 1e3 / PLATES)
                assert len(answers) == PLATES + 1, [a.status.name for a in answers]
                errors += plate_errors(jobs[answers[0].job_id])
                t0 = time.perf_counter()
                for _ in range(PLATES):
                    assert (await plc.cycle()).status is Status.OK
                per_plate.append((time.perf_counter() - t0) * 1e3 / PLATES)
    finally:
        await daemon.stop()
    return report(f"{pallets} pallets of {PLATES} plates, Modbus/TCP on 127.0.0.1, PLC polling "
                  "5 ms.", listed, per_plate, errors, "1 TRIGGER + NEXT", "TRIGGER")


OPCUA_LINK = {"type": "opcua", "host": "127.0.0.1", "port": 0, "security": ["None"],
        "allow_anonymous": True}


async def timed(client: OpcUaClientProcess, line: str) -> tuple[dict[str, Any], float]:
    t0 = time.perf_counter()
    answer = await client.send(line)
    assert answer["event"] == "result", answer
    return answer, (time.perf_counter() - t0) * 1e3


async def over_opcua(pallets: int) -> list[str]:
    daemon, jobs = await started_daemon([OPCUA_LINK])
    listed: list[float] = []
    per_plate: list[float] = []
    next_ms: list[float] = []
    job_ms: list[float] = []
    errors: list[tuple[float, float]] = []
    try:
        port: int = next(iter(daemon.rooms.links.links.values())).port  # type: ignore[attr-defined]
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
    lines = report(f"{pallets} pallets of {PLATES} plates, OPC UA (asyncua client process) on "
                   "127.0.0.1, security None.", listed, per_plate, errors,
                   "StartSingleJob + Next", "StartSingleJob")
    n, j = statistics.median(next_ms), statistics.median(job_ms)
    return [*lines, "", f"One Next: median {n:.1f} ms (min {min(next_ms):.1f}, max "
            f"{max(next_ms):.1f}, {len(next_ms)} calls); one StartSingleJob: median {j:.1f} ms "
            f"({len(job_ms)} calls); ratio x{j / n:.1f}."]

SECTIONS = {
    "modbus": ("Pick lists over Modbus/TCP: one TRIGGER and NEXT vs a job per plate", over_modbus),
    "opcua": ("Pick lists over OPC UA: StartSingleJob and Next vs a job per plate", over_opcua),
}


def main() -> None:
    ap = harness.parser(__doc__)
    ap.add_argument("--link", choices=sorted(SECTIONS), default="modbus")
    ap.add_argument("--pallets", type=int, default=5)
    args = ap.parse_args()
    stamp = harness.Stamp(harness.bench_command())
    heading, run = SECTIONS[args.link]
    lines = asyncio.run(run(args.pallets))
    harness.report("Pick lists", heading, "\n".join(lines), stamp, args.print_only)


if __name__ == "__main__":
    main()
