"""Soak: N jobs back to back through the real daemon with its worker process, recording on, a PLC
stand-in polling at 100 Hz. Memory and open file descriptors must stay flat. Not run in CI.

The daemon is ``python -m vgripd run`` (synthetic stereo camera, Modbus/TCP server link,
recording on with a 200 MB cap so old jobs are deleted as new ones are written); the PLC
stand-in is ``bench/bench_poll.py``'s client in cycle mode. Every ``--every`` jobs (read from
``GET /status``) this samples, for the daemon and its worker process: resident memory (VmRSS),
open file descriptors, threads; plus the daemon's shared-memory segments in /dev/shm, worker
restarts and the recording folder's size.

Flatness is judged after a warm-up (the first sample at or after ``--warmup`` jobs): the
least-squares slope of RSS (MB per 1000 jobs) and the change from that sample to the last;
file descriptors and threads must not change at all.

Run (takes a while; progress on stdout):
``.venv/bin/python bench/bench_soak.py [--jobs 10000] [--every 250] [--print-only]``
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.harness import DaemonProcess, Stamp, bench_command, percentile, report, run_client  # noqa: E402
from bench.harness import parser as bench_parser  # noqa: E402

SUBJECT = "Daemon: polls, jobs, memory"
SECTION = "Soak: memory and file descriptors over many jobs"


def proc_figures(pid: int) -> tuple[float, int, int]:
    """(RSS in MB, open file descriptors, threads) of a process."""
    fields = dict(line.split(":", 1) for line in
                  Path(f"/proc/{pid}/status").read_text().splitlines() if ":" in line)
    rss_mb = int(fields["VmRSS"].split()[0]) / 1024
    return rss_mb, len(os.listdir(f"/proc/{pid}/fd")), int(fields["Threads"])


def folder_mb(path: Path) -> float:
    """Size of a folder the recorder is writing and pruning meanwhile."""
    total = 0
    for root, _dirs, files in os.walk(path):  # folders that vanish meanwhile are skipped
        for name in files:
            with contextlib.suppress(FileNotFoundError):
                total += os.stat(os.path.join(root, name)).st_size
    return total / 1e6


def slope_per_1000(jobs: list[int], values: list[float]) -> float:
    if len(jobs) < 2:
        return float("nan")
    return float(np.polyfit(np.asarray(jobs, float), np.asarray(values, float), 1)[0] * 1000)


async def main(n_jobs: int, every: int, warmup: int, print_only: bool, keep: Path | None) -> None:
    stamp = Stamp(bench_command())
    t_start = time.monotonic()
    samples: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="bench_soak-") as tmp:
        folder = keep or Path(tmp)
        # The real daemon (``vgripd run``), started through this file so that a stray
        # ``pkill -f "vgripd run"`` elsewhere on a shared machine does not end the soak.
        command = [sys.executable, __file__, "--daemon", str(folder / "vgripd.toml")]
        async with DaemonProcess(folder, worker=True, max_mb=200.0, command=command) as daemon:
            client = asyncio.create_task(
                run_client(daemon.port, "cycle", 0, n_jobs, allow_error=True))
            next_at = 0
            print(f"{'jobs':>6} {'min':>6} {'daemon MB':>9} {'fds':>4} {'thr':>3} "
                  f"{'worker MB':>9} {'fds':>4} {'thr':>3} {'shm':>3} {'restarts':>8} "
                  f"{'record MB':>9}", flush=True)
            while True:
                status = await daemon.status()
                jobs = sum(status["counters"].values())
                if jobs >= next_at or client.done():
                    worker = status["worker"]
                    d_rss, d_fds, d_thr = proc_figures(daemon.pid)
                    w_rss, w_fds, w_thr = proc_figures(worker["pid"])
                    shm = [p for p in os.listdir("/dev/shm")
                           if p.startswith(f"vgripd-{daemon.pid}-")]
                    s = {"jobs": jobs, "min": (time.monotonic() - t_start) / 60,
                         "daemon_mb": d_rss, "daemon_fds": d_fds, "daemon_threads": d_thr,
                         "worker_mb": w_rss, "worker_fds": w_fds, "worker_threads": w_thr,
                         "shm": len(shm), "restarts": worker["restarts"],
                         "record_mb": folder_mb(folder / "record"),
                         "cycle_p50": status["cycle_ms"].get("p50", float("nan"))}
                    samples.append(s)
                    print(f"{jobs:>6} {s['min']:>6.1f} {d_rss:>9.1f} {d_fds:>4} {d_thr:>3} "
                          f"{w_rss:>9.1f} {w_fds:>4} {w_thr:>3} {len(shm):>3} "
                          f"{worker['restarts']:>8} {s['record_mb']:>9.1f}", flush=True)
                    next_at = (jobs // every + 1) * every
                if client.done():
                    break
                await asyncio.sleep(1.0)
            got = await client
            final = await daemon.status()
    minutes = (time.monotonic() - t_start) / 60

    warm = [s for s in samples if s["jobs"] >= warmup] or samples[-1:]
    first, last = warm[0], samples[-1]
    jobs_axis = [s["jobs"] for s in warm]
    rtt = got["rtt_ms"]
    stopped = (f" **Stopped early** after {len(got['cycle_ms'])} of {n_jobs} jobs: "
               f"{got['error']}." if got["error"] else "")
    lines = [
        "The real daemon with its "
        "worker process (synthetic stereo camera 1280x1024, Modbus/TCP server, recording on "
        "with a 200 MB cap), jobs back to back from a PLC stand-in polling at 100 Hz; "
        f"{len(got['cycle_ms'])} jobs in {minutes:.0f} min ({got['statuses']}), sampled every "
        f"{every} jobs.{stopped}",
        "",
        "| jobs | daemon RSS MB | daemon fds | daemon threads | worker RSS MB | worker fds | "
        "worker threads | /dev/shm segments | worker restarts | record MB |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    shown = samples if len(samples) <= 14 else (
        samples[:3] + samples[3:-3:max(1, (len(samples) - 6) // 8)] + samples[-3:])
    for s in shown:
        lines.append(f"| {s['jobs']} | {s['daemon_mb']:.1f} | {s['daemon_fds']} | "
                     f"{s['daemon_threads']} | {s['worker_mb']:.1f} | {s['worker_fds']} | "
                     f"{s['worker_threads']} | {s['shm']} | {s['restarts']} | "
                     f"{s['record_mb']:.0f} |")
    d_slope = slope_per_1000(jobs_axis, [s["daemon_mb"] for s in warm])
    w_slope = slope_per_1000(jobs_axis, [s["worker_mb"] for s in warm])
    fds = {(s["daemon_fds"], s["worker_fds"]) for s in warm}
    threads = {(s["daemon_threads"], s["worker_threads"]) for s in warm}
    lines += [
        "",
        f"From {first['jobs']} jobs (after warm-up) to {last['jobs']}: daemon RSS "
        f"{first['daemon_mb']:.1f} -> {last['daemon_mb']:.1f} MB (slope {d_slope:+.3f} MB per "
        f"1000 jobs), worker RSS {first['worker_mb']:.1f} -> {last['worker_mb']:.1f} MB (slope "
        f"{w_slope:+.3f} MB per 1000 jobs); open fds (daemon, worker) {sorted(fds)}; threads "
        f"{sorted(threads)}; shared-memory segments {sorted({s['shm'] for s in samples})}; "
        f"worker restarts {final['worker']['restarts']}.",
        f"Poll over the whole soak ({len(rtt)} polls): median {statistics.median(rtt):.3f} ms, "
        f"p99 {percentile(rtt, 99):.3f} ms, p99.9 {percentile(rtt, 99.9):.3f} ms, max {max(rtt):.3f} ms. "
        f"Job cycle (PLC, trigger to result): median {statistics.median(got['cycle_ms']):.1f} "
        f"ms, p99 {percentile(got['cycle_ms'], 99):.1f} ms.",
        "",
    ]
    report(SUBJECT, SECTION, "\n".join(lines), stamp, print_only)


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--daemon":
        from vgripd.__main__ import main as vgripd_main

        sys.exit(vgripd_main(["run", "-c", sys.argv[2]]))
    parser = bench_parser(__doc__)
    parser.add_argument("--jobs", type=int, default=10_000)
    parser.add_argument("--every", type=int, default=250, help="sample every N jobs")
    parser.add_argument("--warmup", type=int, default=500,
                        help="judge flatness from the first sample at or after this many jobs")
    parser.add_argument("--folder", type=Path,
                        help="keep the daemon's config, log and recordings here (default: a "
                             "temporary folder, removed)")
    args = parser.parse_args()
    asyncio.run(main(args.jobs, args.every, args.warmup, args.print_only, args.folder))
