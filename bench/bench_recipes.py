"""What switching recipes costs: by number with the trigger, against restarting the daemon.

The daemon as shipped (worker process) on the two-plate sample cell (config/samples/
recipes.toml) with plate B in view, plus recipe 3 = plate B with a tighter limit (another
recipe that finds the same plate, so both alternatives do the same image work). A mock PLC
over Modbus/TCP on 127.0.0.1 triggers jobs back to back:

- recipes 2, 2, 3, 3, 2, 2, ...: ``same`` = the jobs whose recipe is the previous job's,
  ``switched`` = those whose recipe changed (interleaved job by job, so both see the same
  machine load);
- ``unknown``: recipe 9, answered BAD_REQUEST without an image;
- named peer ``restart``: what a cell without recipes does to change the object: stop the
  daemon and start one on the other recipe's config; timed from the stop to the first job's
  answer on the new daemon (worker process spawned, pipeline built, camera opened). In the
  same interpreter, so a lower bound of ``systemctl restart`` (no interpreter start, imports
  already done in the daemon).

Cycle = the PLC's trigger write to the answer seen (the mock PLC polls every 2 ms).

    .venv/bin/python bench/bench_recipes.py [--jobs 60] [--restarts 3] [--print-only]
"""

from __future__ import annotations

import asyncio
import logging
import statistics
import sys
import time
import tomllib
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench import harness  # noqa: E402
from vgripd.config import Config, config_from_dict  # noqa: E402
from vgripd.service.daemon import Daemon  # noqa: E402
from vgripd.sim.plc import MockPlc  # noqa: E402
from vgripd.types import Status  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "config" / "samples" / "recipes.toml"
SECTION = "Recipes: switching by number against restarting the daemon"
WAIT_S = 30.0


def cell(recipe_in_top_level: int | None = None) -> Config:
    """The sample cell with ephemeral ports and recipe 3 (plate B, tighter limit); with
    ``recipe_in_top_level``, that recipe's effective config as the only one (no recipes)."""
    data: dict[str, Any] = tomllib.loads(SAMPLE.read_text())
    data["links"][0]["port"] = 0
    data["status"] = {"port": 0}
    data["daemon"] = {"log_level": "WARNING"}
    data["recipes"]["3"] = {**data["recipes"]["2"], "name": "plate-b-tight",
                            "limits": {"max_translation_mm": 55.0}}
    config = config_from_dict(data, str(SAMPLE))
    if recipe_in_top_level is None:
        return config
    single = config.for_recipe(recipe_in_top_level).model_dump(exclude_unset=True)
    single["camera"] = {**single["camera"], "recipe": 0}  # plate B is its top-level object
    return config_from_dict(single)


def stats(ms: list[float]) -> str:
    ms = sorted(ms)
    p95 = ms[int(0.95 * (len(ms) - 1))]
    return f"median {statistics.median(ms):7.1f} ms, p95 {p95:7.1f} ms, max {ms[-1]:7.1f} ms"


async def cycles(plc: MockPlc, recipes: list[int], expected: Status) -> list[float]:
    times = []
    for recipe in recipes:
        answer = await plc.cycle(recipe)
        if answer.status is not expected:
            raise SystemExit(f"recipe {recipe}: {answer.status.name}, expected {expected.name}")
        times.append(answer.cycle_ms)
    return times


async def started(config: Config) -> tuple[Daemon, MockPlc]:
    daemon = Daemon(config)
    await daemon.start()
    port: int = next(iter(daemon.rooms.links.links.values())).port  # type: ignore[attr-defined]
    plc = MockPlc("127.0.0.1", port, timeout_s=WAIT_S, poll_s=0.002)
    await plc.connect()
    return daemon, plc


async def main(jobs: int, restarts: int, print_only: bool) -> None:
    stamp = harness.Stamp(harness.bench_command())
    daemon, plc = await started(cell())
    try:
        await cycles(plc, [2, 3], Status.OK)  # warm-up: first grab, first job per recipe
        # Recipes 2, 2, 3, 3, ...: every other job switches, so the jobs that switch and
        # those that do not run side by side and share the machine's load (shared, 2 cores).
        sequence = [2, 2, 3, 3] * max(1, jobs // 2)
        times = await cycles(plc, sequence, Status.OK)
        fixed = [t for i, t in enumerate(times) if sequence[i] == sequence[i - 1]]
        switching = [t for i, t in enumerate(times) if sequence[i] != sequence[i - 1]]
        unknown = await cycles(plc, [9] * 20, Status.BAD_REQUEST)
    finally:
        plc.close()
        await daemon.stop()

    restart_ms: list[float] = []
    configs = [cell(2), cell(3)]
    daemon, plc = await started(configs[0])
    try:
        await cycles(plc, [0], Status.OK)
        for i in range(restarts):
            t0 = time.perf_counter()
            plc.close()
            await daemon.stop()
            daemon, plc = await started(configs[(i + 1) % 2])
            await cycles(plc, [0], Status.OK)
            restart_ms.append((time.perf_counter() - t0) * 1e3)
    finally:
        plc.close()
        await daemon.stop()

    added = statistics.median(switching) - statistics.median(fixed)
    lines = [
        f"same recipe           {stats(fixed)}  ({len(fixed)} jobs)",
        f"recipe switched       {stats(switching)}  ({len(switching)} jobs)",
        f"unknown recipe 9      {stats(unknown)}  (BAD_REQUEST, no image)",
        f"peer: restart         {stats(restart_ms)}  ({len(restart_ms)} restarts, stop -> "
        "first answer)",
        f"a switch by number: {added:+.1f} ms on the median cycle; a switch by restart costs "
        f"{statistics.median(restart_ms):.0f} ms, "
        f"{statistics.median(restart_ms) / statistics.median(switching):.1f}x a whole cycle "
        "with a switch",
    ]
    text = "\n".join([
        "The daemon with its worker "
        "process on config/samples/recipes.toml (synthetic stereo camera 1280x1024 "
        "rendering plate B) plus recipe 3 = plate B with another limit; mock PLC over "
        "Modbus/TCP on 127.0.0.1 polling every 2 ms; cycle = trigger write to answer seen; "
        "recipes 2, 2, 3, 3, ... so that every other job switches.",
        "", "```", *lines, "```", ""])
    harness.report("Daemon: polls, jobs, memory", SECTION, text, stamp, print_only)


if __name__ == "__main__":
    parser = harness.parser(__doc__)
    parser.add_argument("--jobs", type=int, default=60,
                        help="jobs per alternative (default 60)")
    parser.add_argument("--restarts", type=int, default=3)
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)
    asyncio.run(main(args.jobs, args.restarts, args.print_only))
