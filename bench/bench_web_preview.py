"""Modbus poll latency and job cycle with three live camera previews open, versus none.

The daemon and PLC stand-in of ``bench/harness.py``: the real daemon (``python -m vgripd run``:
synthetic stereo camera 1280x1024, Modbus/TCP server link, worker process, recording on) and a
PLC stand-in in its own process reading all registers at 100 Hz and triggering the next job as
soon as it reads a result (jobs back to back). The previews: a client process with three
"pages", each fetching both cameras' ``/api/cameras/{j}/preview.jpg`` every 0.5 s (what the page
does with "live preview" ticked). Rows: none, three previews, none again (the machine's drift),
then the PLC polling with no job at all, without and with the three previews (the previews then
grab all along: the poll's worst case).

Run: ``.venv/bin/python bench/bench_web_preview.py [--seconds 15] [--print-only]``
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import statistics
import sys
import tempfile
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.harness import DaemonProcess, Stamp, bench_command, percentile, report, run_client  # noqa: E402
from bench.harness import parser as bench_parser  # noqa: E402

PAGES = """
import asyncio, sys
import aiohttp

async def page(http, base):
    while True:
        for j in (0, 1):
            async with http.get(f"{base}/api/cameras/{j}/preview.jpg") as r:
                await r.read()
        await asyncio.sleep(0.5)

async def main(base, n):
    async with aiohttp.ClientSession() as http:
        await asyncio.gather(*(page(http, base) for _ in range(n)))

asyncio.run(main(sys.argv[1], int(sys.argv[2])))
"""


@contextlib.asynccontextmanager
async def previews(base: str, pages: int) -> AsyncIterator[None]:
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-c", PAGES, base, str(pages), stdout=asyncio.subprocess.DEVNULL)
    try:
        await asyncio.sleep(1.0)
        assert proc.returncode is None, "the preview pages exited"
        yield
    finally:
        if proc.returncode is None:
            proc.kill()
        await proc.wait()


async def one_row(folder: Path, seconds: float, pages: int, mode: str = "cycle"
                  ) -> dict[str, Any]:
    """``mode``: "cycle" jobs back to back, "poll" polls only (the previews grab all along)."""
    async with DaemonProcess(folder, worker=True) as daemon:
        if pages:
            async with previews(f"http://127.0.0.1:{daemon.status_port}", pages):
                got = await run_client(daemon.port, mode, seconds)
        else:
            got = await run_client(daemon.port, mode, seconds)
        got["daemon_cycle_ms"] = (await daemon.status())["cycle_ms"]
        import aiohttp

        async with aiohttp.ClientSession() as http, http.get(
                f"http://127.0.0.1:{daemon.status_port}/api/cameras") as r:
            got["grabs"] = (await r.json())["grabs"]
    return got


def line(name: str, got: dict[str, Any]) -> str:
    rtt, cyc = got["rtt_ms"], got["daemon_cycle_ms"]
    p50 = f"{cyc['p50']:.1f}" if cyc.get("window") else "-"
    p99 = f"{cyc['p99']:.1f}" if cyc.get("window") else "-"
    return (f"| {name} | {len(rtt)} | {statistics.median(rtt):.3f} | {percentile(rtt, 99):.3f} | "
            f"{max(rtt):.3f} | {len(got['cycle_ms'])} | {p50} | {p99} | "
            f"{got['grabs']} |")


async def main(seconds: float, print_only: bool) -> None:
    os.environ.setdefault("BENCH_CLIENT_REALTIME", "0")
    stamp = Stamp(bench_command())
    with tempfile.TemporaryDirectory(prefix="bench_web_preview-") as tmp:
        none = await one_row(Path(tmp) / "none", seconds, 0)
        three = await one_row(Path(tmp) / "three", seconds, 3)
        again = await one_row(Path(tmp) / "again", seconds, 0)
        idle = await one_row(Path(tmp) / "idle", seconds, 0, "poll")
        idle_three = await one_row(Path(tmp) / "idle3", seconds, 3, "poll")
    lines = [
        f"The real daemon and the PLC stand-in polling at 100 Hz; {seconds:g} s per row; rows "
        "and what a preview page fetches: bench/bench_web_preview.py's docstring.", "",
        "| previews | polls | median ms | p99 ms | max ms | jobs | daemon cycle p50 ms | "
        "cycle p99 ms | preview grabs |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
        line("none", none),
        line("three pages with live preview (2 cameras each, every 0.5 s)", three),
        line("none, again", again),
        line("no jobs (polls only), no preview", idle),
        line("no jobs (polls only), three pages with live preview", idle_three)]
    report("Web view and setup", "Poll and job cycle with three live camera previews open",
           "\n".join(lines), stamp, print_only)


if __name__ == "__main__":
    parser = bench_parser(__doc__)
    parser.add_argument("--seconds", type=float, default=15.0, help="per row")
    args = parser.parse_args()
    asyncio.run(main(args.seconds, args.print_only))
