"""How long the cell is blind after the worker process is SIGKILLed while it holds the camera.

The daemon in this process (camera and pipeline in its worker, as deployed; Modbus/TCP server on
127.0.0.1, a pymodbus client as the PLC) on Aravis' fake GigE cameras (two, 127.0.0.1 and
127.0.0.2) or pylon's camera emulation (two cameras fed the sample images). Each round: one job,
then SIGKILL of the worker and a trigger at once. Timed from the kill:

- ``answer``: the PLC reads the answer of that trigger (its status is counted: it should be
  the status a working camera gives, never CAMERA_ERROR);
- ``healthy``: ``/api/status`` healthy again (the camera open in the new worker).

Most of both is the new worker's start (spawn, imports, warm-up); a GigE camera also waits out
the dead process's control channel (its heartbeat timeout), which runs meanwhile.

Run: ``.venv/bin/python bench/bench_worker_crash.py [--rounds 5] [--camera aravis|pylon|both]
[--print-only]``
"""

from __future__ import annotations

import asyncio
import os
import signal
import statistics
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
os.environ.setdefault("PYLON_CAMEMU", "3")

from bench.harness import Stamp, bench_command, report  # noqa: E402
from bench.harness import parser as bench_parser  # noqa: E402
from tests.drivers.cameras.test_cameras_aravis import (  # noqa: E402
    FakeCamera,
    _aravis,
    gige_exclusive,
    second_loopback,
)
from tests.integration.test_daemon import Plc, Run  # noqa: E402
from tests.integration.test_daemon_worker_crash import (  # noqa: E402
    aravis_cell,
    pylon_cell,
    running,
)
from vgripd.peer.registers import Reg  # noqa: E402

SUBJECT = "Daemon: polls, jobs, memory"
SECTION = "Worker process killed while it holds the camera"


async def rounds(config: Any, n: int) -> dict[str, Any]:
    answer_s, healthy_s, statuses = [], [], Counter[str]()
    async with running(config) as run, Plc(run.port()) as plc:
        daemon = run.daemon
        seq = 1
        await plc.trigger(seq)
        await plc.until(lambda w: w[Reg.ACK_SEQ] == seq)
        for _ in range(n):
            pid = daemon.snapshot()["worker"]["pid"]
            t0 = time.monotonic()
            os.kill(pid, signal.SIGKILL)
            seq += 1
            await plc.trigger(seq)
            await plc.until(lambda w, s=seq: w[Reg.ACK_SEQ] == s)
            answer_s.append(time.monotonic() - t0)
            _, rec = await run.job_done(seq)
            statuses[rec.result.status.name] += 1
            await daemon.wait_for(daemon.healthy, 120.0)
            healthy_s.append(time.monotonic() - t0)
            seq += 1  # one more job, so the next kill finds the camera grabbing normally
            await plc.trigger(seq)
            await plc.until(lambda w, s=seq: w[Reg.ACK_SEQ] == s)
        return {"answer": answer_s, "healthy": healthy_s, "statuses": dict(statuses),
                "first": rec_status(run)}


def rec_status(run: Run) -> str:
    return run.jobs[0][1].result.status.name


def line(name: str, values: list[float]) -> str:
    return (f"{name:<8} median {statistics.median(values):5.2f} s  min {min(values):5.2f} s  "
            f"max {max(values):5.2f} s")


async def main() -> None:
    ap = bench_parser(__doc__)
    stamp = Stamp(bench_command())
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--camera", choices=("aravis", "pylon", "both"), default="both")
    args = ap.parse_args()
    out = ["```"]
    if args.camera in ("aravis", "both"):
        _aravis()
        second_loopback()
        with gige_exclusive():
            fakes = [FakeCamera("127.0.0.1", "GV01").start(),
                     FakeCamera("127.0.0.2", "GV02").start()]
            try:
                got = await rounds(aravis_cell(), args.rounds)
            finally:
                for fake in fakes:
                    fake.kill()
        out += [f"aravis, 2 fake GigE cameras: answers {got['statuses']} (before the kills: "
                f"{got['first']})", line("answer", got["answer"]), line("healthy", got["healthy"])]
    if args.camera in ("pylon", "both"):
        got = await rounds(pylon_cell(), args.rounds)
        out += [f"pylon emulation, 2 cameras: answers {got['statuses']} (before the kills: "
                f"{got['first']})", line("answer", got["answer"]), line("healthy", got["healthy"])]
    out.append("```")
    report(SUBJECT, SECTION, "\n".join(out), stamp, args.print_only)


if __name__ == "__main__":
    asyncio.run(main())
