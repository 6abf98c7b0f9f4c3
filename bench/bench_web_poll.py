"""Modbus poll latency with the operator web view open in a browser, versus without it.

The daemon and PLC stand-in of ``bench/harness.py``: the real daemon
(``python -m vgripd run``: synthetic stereo camera 1280x1024, Modbus/TCP server link, worker
process, recording on) and a PLC stand-in in its own process (pymodbus' synchronous client)
reading all registers at 100 Hz and triggering the next job as soon as it reads a result (jobs
back to back). Rows: the daemon without a page open, then the same with the page open in
headless Chromium (event stream connected: every job pushed as an event, the page fetching both
annotated images per job, ``/api/status`` every 5 s and ``/api/registers`` every 2 s), then
Chromium open on ``about:blank`` (the browser's own CPU on this machine, no request to the
daemon), the page's requests made by a plain aiohttp client process (the daemon's share),
then without again (the machine's drift).

Run: ``.venv/bin/python bench/bench_web_poll.py [--seconds 20] [--print-only]`` (needs ``chromium``)
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import shutil
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


@contextlib.asynccontextmanager
async def page_open(url: str, folder: Path) -> AsyncIterator[None]:
    """Headless Chromium showing ``url`` until the block ends."""
    chromium = shutil.which("chromium")
    assert chromium, "needs chromium: apt-get install chromium"
    proc = await asyncio.create_subprocess_exec(
        chromium, "--headless", "--no-sandbox", "--disable-gpu",
        "--disable-background-networking", "--disable-component-update", "--disable-sync",
        "--no-first-run", "--disable-dev-shm-usage", f"--user-data-dir={folder / 'chr'}",
        "--remote-debugging-port=0", url,
        stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL,
        env={**os.environ, "HOME": str(folder)})
    try:
        await asyncio.sleep(4.0)  # loaded, and the event stream opened (1 s after the load)
        assert proc.returncode is None, "chromium exited"
        yield
    finally:
        if proc.returncode is None:
            proc.kill()
        await proc.wait()


MIMIC = """
import asyncio, json, sys
import aiohttp

async def main(base):
    async with aiohttp.ClientSession() as http:
        async def every(path, period):
            while True:
                async with http.get(base + path) as r:
                    await r.read()
                await asyncio.sleep(period)
        tasks = [asyncio.create_task(every("/api/status", 5)),
                 asyncio.create_task(every("/api/registers", 2))]
        async with http.get(base + "/api/events", timeout=aiohttp.ClientTimeout()) as sse:
            event = ""
            async for raw in sse.content:
                line = raw.decode().strip()
                if line.startswith("event: "):
                    event = line[7:]
                elif line.startswith("data: ") and event == "job":
                    job = json.loads(line[6:])
                    for side in ("left", "right"):
                        async with http.get(f"{base}/api/jobs/{job['id']}/image/{side}.jpg") as r:
                            await r.read()

asyncio.run(main(sys.argv[1]))
"""


@contextlib.asynccontextmanager
async def page_requests(base: str) -> AsyncIterator[None]:
    """A process making the page's requests (event stream, both images per job, status and
    registers polls) with no browser: the daemon's share of the page's cost."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-c", MIMIC, base, stdout=asyncio.subprocess.DEVNULL)
    try:
        await asyncio.sleep(1.0)
        assert proc.returncode is None, "the request mimic exited"
        yield
    finally:
        if proc.returncode is None:
            proc.kill()
        await proc.wait()


async def one_row(folder: Path, seconds: float, page: str = "") -> dict[str, Any]:
    """``page``: "" none, "view" the web view, "blank" Chromium on about:blank (its own load)."""
    async with DaemonProcess(folder, worker=True) as daemon:
        url = f"http://127.0.0.1:{daemon.status_port}/" if page == "view" else "about:blank"
        if page == "requests":
            async with page_requests(f"http://127.0.0.1:{daemon.status_port}"):
                got = await run_client(daemon.port, "cycle", seconds)
        elif page:
            async with page_open(url, folder):
                got = await run_client(daemon.port, "cycle", seconds)
        else:
            got = await run_client(daemon.port, "cycle", seconds)
        got["daemon_cycle_ms"] = (await daemon.status())["cycle_ms"]
    return got


def line(name: str, got: dict[str, Any]) -> str:
    rtt = got["rtt_ms"]
    return (f"| {name} | {len(rtt)} | {statistics.median(rtt):.3f} | {percentile(rtt, 99):.3f} | "
            f"{max(rtt):.3f} | {len(got['cycle_ms'])} | {got['daemon_cycle_ms']['p50']:.1f} |")


async def main(seconds: float, print_only: bool) -> None:
    os.environ.setdefault("BENCH_CLIENT_REALTIME", "0")
    stamp = Stamp(bench_command())
    with tempfile.TemporaryDirectory(prefix="bench_web_poll-") as tmp:
        without = await one_row(Path(tmp) / "without", seconds)
        with_page = await one_row(Path(tmp) / "with", seconds, page="view")
        blank = await one_row(Path(tmp) / "blank", seconds, page="blank")
        requests = await one_row(Path(tmp) / "requests", seconds, page="requests")
        again = await one_row(Path(tmp) / "again", seconds)
    w, o = with_page["rtt_ms"], without["rtt_ms"] + again["rtt_ms"]
    lines = [
        f"The real daemon (worker process, synthetic stereo camera 1280x1024, Modbus/TCP server, "
        f"recording on), jobs back to back from the PLC stand-in polling all registers at "
        f"100 Hz ({'SCHED_FIFO' if with_page.get('realtime') else 'normal priority'}); "
        f"{seconds:g} s per row. Rows and the page's traffic: bench/bench_web_poll.py's "
        "docstring.", "",
        "| daemon | polls | median ms | p99 ms | max ms | jobs | daemon cycle p50 ms |",
        "|---|---:|---:|---:|---:|---:|---:|",
        line("no page open", without),
        line("page open in headless Chromium (event stream, images per job)", with_page),
        line("Chromium open on about:blank (the browser's own load, no web view)", blank),
        line("the page's requests from a client process, no browser", requests),
        line("no page open, again", again), ""]
    lines.append(f"With page / without (both without rows): median "
          f"{statistics.median(w) / statistics.median(o):.2f}, p99 {percentile(w, 99) / percentile(o, 99):.2f}, "
          f"max {max(w) / max(o):.2f}; with page / about:blank p99 "
          f"{percentile(w, 99) / percentile(blank['rtt_ms'], 99):.2f}, max {max(w) / max(blank['rtt_ms']):.2f}; requests only / without p99 "
          f"{percentile(requests['rtt_ms'], 99) / percentile(o, 99):.2f}, max "
          f"{max(requests['rtt_ms']) / max(o):.2f}.")
    report("Web view and setup", "Modbus poll latency with the web view open", "\n".join(lines), stamp,
           print_only)


if __name__ == "__main__":
    parser = bench_parser(__doc__)
    parser.add_argument("--seconds", type=float, default=20.0, help="per row")
    args = parser.parse_args()
    asyncio.run(main(args.seconds, args.print_only))
