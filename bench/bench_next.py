"""Emptying a pallet over Modbus/TCP: one TRIGGER and NEXTs vs one TRIGGER per plate, same run.

The real daemon (worker process, vision pipeline) on the synthetic pallet of six touching
plates (config/samples/pallet.toml's scene), its Modbus/TCP server on 127.0.0.1, and the mock
PLC (``vgripd.sim.plc``) polling every 5 ms. Per pallet the PLC needs one pose per plate:

- pick list: one TRIGGER (every plate located in one job), then NEXT until NOT_FOUND;
- named peer, "a job per plate": what a map version 2 PLC does without NEXT, one TRIGGER per
  plate taken (each a full acquisition and location of the whole pallet, the first pose used).

Time is on the PLC's clock, from the first request written to the last answer seen; the figure
is ms per plate handed out. The two alternate pallet by pallet, so load changes hit both. The
pose errors of the pick list's plates against the synthetic camera's truth are a sanity check
that the list is the pallet, not an accuracy benchmark (the vision's pick list accuracy bench
renders with the independent path of ``bench/render_independent.py``).

    .venv/bin/python bench/bench_next.py [pallets]
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
    daemon.listeners.append(lambda pair, rec: jobs.__setitem__(rec.job_id, (pair, rec)))
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
           errors: list[tuple[float, float]], list_way: str, peer_way: str) -> None:
    a, b = statistics.median(listed), statistics.median(per_plate)
    e = np.array(errors)
    print(what)
    print(f"pick list ({list_way}):  median {a:7.1f} ms per plate "
          f"(min {min(listed):.1f}, max {max(listed):.1f})")
    print(f"a job per plate ({peer_way} x {PLATES}): median {b:7.1f} ms per plate "
          f"(min {min(per_plate):.1f}, max {max(per_plate):.1f})")
    print(f"ratio (job per plate / pick list): x{b / a:.2f}")
    print(f"sanity: pick list poses vs the synthetic camera's truth over {len(e)} plates: "
          f"max {e[:, 0].max():.3f} mm, {e[:, 1].max():.3f} deg (mean {e[:, 0].mean():.3f} mm)")


async def main(pallets: int) -> None:
    daemon, jobs = await started_daemon([{"type": "modbus_server", "host": "127.0.0.1",
                                          "port": 0}])
    listed: list[float] = []
    per_plate: list[float] = []
    errors: list[tuple[float, float]] = []
    try:
        port: int = next(iter(daemon.links.values())).port  # type: ignore[attr-defined]
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
    report(f"{pallets} pallets of {PLATES} plates, Modbus/TCP on 127.0.0.1, PLC polling 5 ms",
           listed, per_plate, errors, "1 TRIGGER + NEXT", "TRIGGER")


if __name__ == "__main__":
    asyncio.run(main(int(sys.argv[1]) if len(sys.argv) > 1 else 5))
