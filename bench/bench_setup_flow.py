"""The browser setup's road, measured: ``vgripd demo --setup`` driven in headless Chromium from
empty includes to the first OK job of a pymodbus PLC (tests/integration/setup_browser.py, the
acceptance test's drive): page actions (clicks and form submits the integrator makes) and wall
time per step.

    .venv/bin/python -m bench.bench_setup_flow [--runs 1] [--print-only]

Writes the "Setup in the browser" section of bench/RESULTS.md.
"""

from __future__ import annotations

import asyncio
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench import harness  # noqa: E402
from tests.integration.setup_browser import SETS, Flow, demo_setup, drive  # noqa: E402

HEADING = "Setup in the browser"


async def one(tmp: Path) -> tuple[Flow, float]:
    t0 = time.monotonic()
    async with demo_setup(tmp / "cell") as cell:
        flow = await drive(cell, tmp)
    return flow, time.monotonic() - t0


def main() -> int:
    parser = harness.parser(__doc__)
    stamp = harness.Stamp(harness.bench_command())
    parser.add_argument("--runs", type=int, default=1)
    args = parser.parse_args()
    lines = []
    for run in range(args.runs):
        with tempfile.TemporaryDirectory(prefix="vgripd-bench-setup-") as tmp:
            flow, wall = asyncio.run(one(Path(tmp)))
        steps = ", ".join(f"{k} {v:.0f} s" for k, v in flow.seconds.items())
        line = (f"run {run + 1}: {flow.actions} page actions, {wall:.0f} s wall (from the "
                f"command's start to the PLC's answer), PLC status {flow.plc_status}; {steps}")
        print(line, flush=True)
        lines.append(line)
    load = " ".join(f"{x:.1f}" for x in os.getloadavg())
    text = "\n".join([
        "`vgripd demo --setup` (the learning cell, empty "
        "includes) driven in headless Chromium through every step of `/setup` by the page's own "
        f"buttons (auto-capture until {SETS} sets, calibrate, accept, the learning cell's camera "
        "pose, the plate's six marks, three teaching shots, the register map, a test pick), then "
        "one job triggered by a pymodbus PLC client over Modbus/TCP. Page actions are clicks and "
        "form submits; the capture's seconds are mostly grabs (the board rendered, its corners "
        "found in both 1280x1024 images, two JPEGs) one after the other; the board camera holds "
        "each place for two grabs (the first is refused: the board just moved there).", "",
        "```",
        f"load average {load}; {os.cpu_count()} CPUs; Python {platform.python_version()}",
        *lines,
        "```"])
    harness.report("Web view and setup", HEADING, text, stamp, args.print_only)
    return 0 if all(" PLC status 1;" in line for line in lines) else 1


if __name__ == "__main__":
    sys.exit(main())
