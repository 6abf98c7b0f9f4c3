"""Trigger-to-result latency of one link against a named peer on the same wire, same run.

One experiment for every link: the link under test runs in this process with a daemon
stand-in that answers each trigger at once (so the figure is the link's own cost, not vision
work), its real peer (a PLC, robot or client program) on loopback, and beside it the least a
program speaking the same wire can do, measured in the same run. What each link's peer and
named comparison are: the docstring of ``bench/links/LINK.py``.

    .venv/bin/python bench/bench_link.py --link modbus|rtu|s7|opcua|robot_socket|ur_rtde
        [--jobs N] [--print-only]

Writes the link's section of bench/RESULTS.md ("Links").
"""

from __future__ import annotations

import asyncio
import importlib
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench import harness  # noqa: E402
from bench.links import LinkRun  # noqa: E402

LINKS = ("modbus", "rtu", "s7", "opcua", "robot_socket", "ur_rtde")
SUBJECT = "Links"


def section(run: LinkRun) -> str:
    """The section's text under its heading: setup, one table, the ratios, the notes."""
    rows = [f"| {s.name} {harness.Spread.of(s.ms).cells()}" for s in run.series]
    by_name = {s.name: s for s in run.series}
    ratios = [f"{s.name}: "
              f"{statistics.median(s.ms) / statistics.median(by_name[s.against].ms):.2f}"
              for s in run.series if s.against is not None]
    return "\n".join([
        run.setup, "",
        "| trigger -> result, ms " + harness.SPREAD_HEADER,
        "|---" + harness.SPREAD_RULE,
        *rows, "",
        "Median against its named peer (the row it is compared with): " + "; ".join(ratios)
        + ".",
        *(["", *run.notes] if run.notes else []),
    ])


def main() -> None:
    ap = harness.parser(__doc__)
    ap.add_argument("--link", choices=LINKS, required=True)
    ap.add_argument("--jobs", type=int, help="jobs per row (default: the link module's)")
    args = ap.parse_args()
    stamp = harness.Stamp(harness.bench_command())
    module = importlib.import_module(f"bench.links.{args.link}")
    run: LinkRun = asyncio.run(module.measure(args.jobs or module.DEFAULT_JOBS))
    harness.report(SUBJECT, run.heading, section(run), stamp, args.print_only)


if __name__ == "__main__":
    main()
