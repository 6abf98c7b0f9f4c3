"""Modbus poll latency of the real daemon while jobs run back to back, recording on.

Target: poll p99 <= 2 ms
and max <= 10 ms at 100 Hz while jobs run back to back with recording on, the job cycle no
slower than the in-process path.

Everything is a real process: ``python -m vgripd run -c CFG`` (synthetic stereo camera,
1280x1024, rendered by the driver as in production; Modbus/TCP server link on 127.0.0.1;
recording on, to a temporary folder), and a PLC stand-in in its own process (pymodbus'
synchronous client, so its timing shares no GIL with the server) that reads all registers at
100 Hz, triggering the next job as soon as it reads the previous result. Rows:

- ``vgripd, daemon.worker = false``: the old in-process path (camera thread, job executor,
  recorder thread in the daemon's interpreter): "before".
- ``vgripd, daemon.worker = true``: camera, pipeline and recorder in the worker process: "after".
- ``vgripd idle``: the same daemon, no jobs.
- ``pymodbus static, vgripd jobs in another process``: the named peer, a plain pymodbus
  ``ModbusTcpServer`` with a static datastore in this process, polled at 100 Hz while a worker
  daemon runs jobs back to back (driven by a second PLC stand-in): what the machine allows a
  server with nothing else to do.
- ``pymodbus static, Pipeline.process in its thread``: the peer as this bench ran it before,
  the job in an executor thread of the server's own process (no camera, no recording).

Job cycle: the daemon's own (trigger received -> result published, ``GET /status``) and the
PLC's (trigger written -> result read, quantised by its 10 ms poll).

The PLC stand-in runs under SCHED_FIFO when the system allows it (``--no-realtime-client`` to
not): a real PLC is a device of its own, and on a loaded machine the stand-in's own wake-ups
would otherwise be in every figure, the peer's too.

``--paired``: the daemon as shipped and a plain pymodbus server of the same register count in a
process scheduled the same way, read in turn by one client under the same load, with the ratio.

Run: ``.venv/bin/python bench/bench_poll.py [--seconds 20] [--print-only] [--paired --rounds 3]``
"""

from __future__ import annotations

import asyncio
import math
import os
import statistics
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.harness import (  # noqa: E402
    DaemonProcess,
    Stamp,
    bench_command,
    load_average,
    percentile,
    report,
    run_client,
    run_pair_client,
    static_modbus_server,
)
from bench.harness import parser as bench_parser  # noqa: E402
from vgripd.peer.registers import MAP_SIZE  # noqa: E402

SUBJECT = "Daemon: polls, jobs, memory"
SECTION = "Modbus poll latency while jobs run"
TARGET_P99_MS = 2.0
TARGET_MAX_MS = 10.0


def realtime_command(config: Path) -> list[str]:
    """``vgripd run`` with the daemon under SCHED_FIFO, as systemd's
    ``CPUSchedulingPolicy=fifo`` / ``CPUSchedulingPriority=5`` would start it."""
    code = ("import os, sys; os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(5)); "
            "from vgripd.__main__ import main; sys.exit(main(sys.argv[1:]))")
    return [sys.executable, "-c", code, "run", "-c", str(config)]


def realtime_allowed() -> bool:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except PermissionError:
        return False
    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    return True


async def bench_daemon(folder: Path, worker: bool, seconds: float, jobs: bool = True,
                       realtime: bool = False) -> dict[str, Any]:
    command = realtime_command(folder / "vgripd.toml") if realtime else None
    async with DaemonProcess(folder, worker, command=command) as daemon:
        got = await run_client(daemon.port, "cycle" if jobs else "poll", seconds)
        status = await daemon.status()
    got["daemon_cycle_ms"] = status["cycle_ms"]
    got["worker"] = status.get("worker")
    return got


async def bench_peer_beside_daemon(folder: Path, seconds: float) -> dict[str, Any]:
    """The plain pymodbus server polled while a worker daemon runs jobs back to back."""
    server, port = await static_modbus_server()
    try:
        async with DaemonProcess(folder, worker=True) as daemon:
            driver = asyncio.create_task(run_client(daemon.port, "cycle", seconds + 4))
            await asyncio.sleep(2)  # jobs are running
            got = await run_client(port, "poll", seconds)
            jobs = await driver
        got["load_jobs"] = len(jobs["cycle_ms"])
        return got
    finally:
        await server.shutdown()


# --- as the shipped unit runs it, against another checkout, interleaved ---------------------

SHIPPED_SECTION = "Modbus poll latency as the shipped unit runs it"


def unit_nice(tree: Path) -> int:
    """The ``Nice=`` of ``tree``'s systemd unit (0 when it sets none)."""
    unit = (tree / "systemd" / "vgripd.service").read_text()
    found = [int(line.split("=", 1)[1]) for line in unit.splitlines()
             if line.startswith("Nice=")]
    return found[-1] if found else 0


def unit_weight_nice(tree: Path) -> int:
    """The unit's ``CPUWeight=`` (default 100) as the niceness of a scheduler group of the same
    weight relative to the others (each nice step is a factor 1.25): 400 -> -6."""
    unit = (tree / "systemd" / "vgripd.service").read_text()
    found = [int(line.split("=", 1)[1]) for line in unit.splitlines()
             if line.startswith("CPUWeight=")]
    return -round(math.log((found[-1] if found else 100) / 100) / math.log(1.25))


def shipped_command(tree: Path, config: Path) -> list[str]:
    """``vgripd run`` from the checkout ``tree`` as its unit would start it: at the absolute
    niceness of its ``Nice=`` (absolute, so this bench's own ``nice`` does not shift it), in a
    session of its own whose autogroup (the kernel's per-session scheduler group, which is
    what keeps other sessions' work apart here as the unit's cgroup does under systemd) gets
    the weight of its ``CPUWeight=``."""
    code = (f"import os, sys; os.setsid(); "
            f"open('/proc/self/autogroup', 'w').write('{unit_weight_nice(tree)}'); "
            f"os.setpriority(os.PRIO_PROCESS, 0, {unit_nice(tree)}); "
            f"sys.path.insert(0, {str(tree)!r}); "
            "from vgripd.__main__ import main; sys.exit(main(sys.argv[1:]))")
    return [sys.executable, "-c", code, "run", "-c", str(config)]


async def shipped_daemon(folder: Path, tree: Path, seconds: float) -> dict[str, Any]:
    daemon = DaemonProcess(folder, worker=True)
    daemon.command = shipped_command(tree, daemon.config)
    async with daemon:
        got = await run_client(daemon.port, "cycle", seconds)
        got["worker"] = (await daemon.status()).get("worker")
    return got


async def shipped_peer(folder: Path, tree: Path, seconds: float) -> dict[str, Any]:
    """The plain pymodbus server polled beside ``tree``'s daemon as shipped running jobs."""
    server, port = await static_modbus_server()
    try:
        daemon = DaemonProcess(folder, worker=True)
        daemon.command = shipped_command(tree, daemon.config)
        async with daemon:
            driver = asyncio.create_task(run_client(daemon.port, "cycle", seconds + 4))
            await asyncio.sleep(2)  # jobs are running
            got = await run_client(port, "poll", seconds)
            jobs = await driver
        got["load_jobs"] = len(jobs["cycle_ms"])
        return got
    finally:
        await server.shutdown()


def merged(runs: list[dict[str, Any]]) -> dict[str, Any]:
    return {"rtt_ms": [x for r in runs for x in r["rtt_ms"]],
            "cycle_ms": [x for r in runs for x in r["cycle_ms"]],
            "load_jobs": sum(r.get("load_jobs", 0) for r in runs)}


async def main_shipped(seconds: float, rounds: int, base: Path, print_only: bool) -> None:
    """This tree and ``base`` each as its own unit runs it, and the plain pymodbus server
    beside this tree's daemon, interleaved round by round so all see the same load."""
    stamp = Stamp(bench_command())
    runs: dict[str, list[dict[str, Any]]] = {"this": [], "base": [], "peer": []}
    rounds_text = []
    with tempfile.TemporaryDirectory(prefix="bench_poll-") as tmp:
        for i in range(rounds):
            for name, job in (("this", lambda f: shipped_daemon(f, REPO, seconds)),
                              ("base", lambda f: shipped_daemon(f, base, seconds)),
                              ("peer", lambda f: shipped_peer(f, REPO, seconds))):
                got = await job(Path(tmp) / f"{name}{i}")
                runs[name].append(got)
                rtt = got["rtt_ms"]
                rounds_text.append(f"{name} round {i + 1}: p99 {percentile(rtt, 99):.2f} max "
                                   f"{max(rtt):.2f} ms")
                print(rounds_text[-1], flush=True)
    this, old, peer = merged(runs["this"]), merged(runs["base"]), merged(runs["peer"])
    p99, worst = percentile(this["rtt_ms"], 99), max(this["rtt_ms"])
    met = p99 <= TARGET_P99_MS and worst <= TARGET_MAX_MS
    lines = [
        f"Each daemon is `vgripd run` at the "
        f"niceness its own unit sets, in a session of its own whose scheduler autogroup has the "
        f"weight of the unit's CPUWeight= (this tree: Nice={unit_nice(REPO)}, CPUWeight as "
        f"autogroup nice {unit_weight_nice(REPO)}, worker 15 below under SCHED_BATCH, start-up heap frozen; base: "
        f"Nice={unit_nice(base)}, autogroup nice {unit_weight_nice(base)}, worker as that tree "
        "sets it; "
        "the other helpers' work runs in their own sessions), worker process, "
        "synthetic stereo camera 1280x1024, Modbus/TCP server, recording on; jobs back to "
        f"back from a PLC stand-in polling all {MAP_SIZE} registers at 100 Hz (SCHED_FIFO "
        "when allowed). The three rows ran interleaved, "
        f"{rounds} rounds of {seconds:g} s each, so they share the machine's load.",
        "",
        "| server | polls | median ms | p99 ms | max ms |",
        "|---|---:|---:|---:|---:|",
        row("vgripd, this tree as its unit runs it", this),
        row("vgripd, base tree as its unit runs it", old),
        row(f"pymodbus static, beside this tree's daemon running {peer['load_jobs']} jobs",
            peer),
        "",
        "Per round: " + "; ".join(rounds_text) + ".",
        "",
        f"As shipped: p99 {p99:.2f} / max {worst:.2f} ms: **{'MET' if met else 'MISSED'}** "
        f"(p99 <= {TARGET_P99_MS:g} ms and max <= {TARGET_MAX_MS:g} ms); base p99 "
        f"{percentile(old['rtt_ms'], 99):.2f} / max {max(old['rtt_ms']):.2f} ms. PLC trigger-to-result "
        f"p50: this {statistics.median(this['cycle_ms']):.1f} ms, base "
        f"{statistics.median(old['cycle_ms']):.1f} ms.",
        "",
    ]
    report(SUBJECT, SHIPPED_SECTION, "\n".join(lines), stamp, print_only)


# --- the shipped daemon against the bare server, poll by poll --------------------------------

PAIRED_SECTION = "Modbus poll latency as shipped against a bare pymodbus server, interleaved"


def shipped_wrapper(tree: Path, then: str) -> str:
    """Python code that puts this process where ``tree``'s unit puts the daemon (a session of
    its own, autogroup weight of ``CPUWeight=``, niceness of ``Nice=``), then runs ``then``."""
    return (f"import os, sys; os.setsid(); "
            f"open('/proc/self/autogroup', 'w').write('{unit_weight_nice(tree)}'); "
            f"os.setpriority(os.PRIO_PROCESS, 0, {unit_nice(tree)}); "
            f"sys.path.insert(0, {str(REPO)!r}); {then}")


async def bare_server_process() -> tuple[asyncio.subprocess.Process, int]:
    """The plain pymodbus server (same register count) in a process of its own, scheduled as
    the shipped unit schedules the daemon, so the two differ only in the server."""
    code = shipped_wrapper(REPO, "from bench.harness import bare_server_main; bare_server_main()")
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-c", code, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)},
        stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE)
    assert proc.stdout is not None
    line = await asyncio.wait_for(proc.stdout.readline(), 60)
    return proc, int(line)


async def paired_round(folder: Path, seconds: float) -> dict[str, Any]:
    """One round: the daemon as shipped runs jobs back to back (driven by one PLC stand-in)
    while a second stand-in reads the daemon and the bare server in turn at 100 Hz each."""
    bare, bare_port = await bare_server_process()
    try:
        daemon = DaemonProcess(folder, worker=True)
        daemon.command = shipped_command(REPO, daemon.config)
        async with daemon:
            driver = asyncio.create_task(run_client(daemon.port, "cycle", seconds + 4))
            await asyncio.sleep(2)  # jobs are running
            got = await run_pair_client(daemon.port, bare_port, seconds)
            jobs = await driver
    finally:
        assert bare.stdin is not None
        bare.stdin.close()
        await bare.wait()
    return {"vgripd": got["a"], "bare": got["b"], "jobs": len(jobs["cycle_ms"]),
            "realtime": got["realtime"]}


def spread_row(name: str, rtt: list[float]) -> str:
    return (f"| {name} | {len(rtt)} | {statistics.median(rtt):.3f} | {percentile(rtt, 99):.3f} "
            f"| {max(rtt):.3f} |")


async def main_paired(seconds: float, rounds: int, print_only: bool) -> None:
    stamp = Stamp(bench_command())
    ours: list[float] = []
    bare: list[float] = []
    jobs = 0
    rounds_text = []
    realtime = False
    with tempfile.TemporaryDirectory(prefix="bench_poll-") as tmp:
        for i in range(rounds):
            got = await paired_round(Path(tmp) / f"round{i}", seconds)
            ours += got["vgripd"]
            bare += got["bare"]
            jobs += got["jobs"]
            realtime = got["realtime"]
            rounds_text.append(
                f"round {i + 1}: vgripd p99 {percentile(got['vgripd'], 99):.2f} max "
                f"{max(got['vgripd']):.2f}, bare p99 {percentile(got['bare'], 99):.2f} max "
                f"{max(got['bare']):.2f} ms ({got['jobs']} jobs)")
            print(rounds_text[-1], flush=True)
    p99, worst = percentile(ours, 99), max(ours)
    bare_p99 = percentile(bare, 99)
    met = p99 <= TARGET_P99_MS and worst <= TARGET_MAX_MS
    lines = [
        f"One PLC stand-in (pymodbus' synchronous client, its own process"
        f"{', SCHED_FIFO' if realtime else ', normal priority'}) reads all {MAP_SIZE} "
        "registers of two servers in turn, 100 Hz each, the order alternating every tick: "
        "`vgripd run` as its unit runs it (this tree: Nice="
        f"{unit_nice(REPO)}, a session whose autogroup has the weight of CPUWeight= "
        f"(autogroup nice {unit_weight_nice(REPO)}), worker process, synthetic stereo camera "
        "1280x1024, Modbus/TCP server, recording on, jobs back to back from a second stand-in), "
        f"and a plain pymodbus `ModbusTcpServer` with a static datastore of the same {MAP_SIZE} "
        "registers in a process of its own, scheduled exactly as the daemon. Same client, same "
        f"moments, same load; {rounds} rounds of {seconds:g} s, {jobs} jobs in all.",
        "",
        "| server | polls | median ms | p99 ms | max ms |",
        "|---|---:|---:|---:|---:|",
        spread_row("vgripd as shipped, running jobs", ours),
        spread_row("plain pymodbus, same scheduling", bare),
        "",
        "Per round: " + "; ".join(rounds_text) + ".",
        "",
        f"vgripd / bare: median {statistics.median(ours) / statistics.median(bare):.2f}, p99 "
        f"{p99 / bare_p99:.2f}, max {worst / max(bare):.2f}; vgripd's p99 no worse than the "
        f"bare server's: **{'MET' if p99 <= bare_p99 else 'MISSED'}**. Absolute target (p99 <= "
        f"{TARGET_P99_MS:g} ms and max <= {TARGET_MAX_MS:g} ms, on a quiet machine): "
        f"**{'MET' if met else 'MISSED'}** (load average in the stamp).",
        "",
    ]
    report(SUBJECT, PAIRED_SECTION, "\n".join(lines), stamp, print_only)


# --- the peer as this bench ran it before: the job in the server's own process ---------------

def pipeline_job_factory() -> Any:
    """``Pipeline.process`` on pre-rendered demo-cell stereo pairs (1280x1024)."""
    from vgripd.config import Config, DriverSection
    from vgripd.registry import CAMERAS, load_class, validate_options
    from vgripd.vision.pipeline import Pipeline

    config = Config()
    cls = load_class(CAMERAS, "camera", "synthetic")
    camera = cls(validate_options(cls, DriverSection(type="synthetic", seed=3, max_tilt_deg=2.0),
                                  "camera"), config)

    async def grab() -> list[Any]:
        await camera.open()
        try:
            return [await camera.grab(10.0) for _ in range(4)]
        finally:
            await camera.close()

    pairs = asyncio.run(grab())
    pipeline = Pipeline(config)
    count = 0

    def job() -> None:
        nonlocal count
        count += 1
        result = pipeline.process(pairs[count % len(pairs)], count)
        assert result.status.pose_valid, result

    return job


async def bench_peer_in_process(seconds: float) -> dict[str, Any]:
    job = await asyncio.to_thread(pipeline_job_factory)
    server, port = await static_modbus_server()
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    jobs = 0

    async def load(pool: ThreadPoolExecutor) -> None:
        nonlocal jobs
        while not stop.is_set():
            await loop.run_in_executor(pool, job)
            jobs += 1

    with ThreadPoolExecutor(1, thread_name_prefix="bench-load") as pool:
        task = asyncio.create_task(load(pool))
        try:
            got = await run_client(port, "poll", seconds)
        finally:
            stop.set()
            await task
            await server.shutdown()
    got["load_jobs"] = jobs
    return got


# --- report ------------------------------------------------------------------------------------

def row(name: str, got: dict[str, Any]) -> str:
    rtt = got["rtt_ms"]
    return (f"| {name} | {len(rtt)} | {statistics.median(rtt):.3f} | {percentile(rtt, 99):.3f} | "
            f"{max(rtt):.3f} |")


def cycle_text(got: dict[str, Any]) -> str:
    d = got["daemon_cycle_ms"]
    plc = got["cycle_ms"]
    return (f"{len(plc)} jobs {got['statuses']}, daemon cycle (trigger received -> result "
            f"published) p50 {d['p50']:.1f} ms, p99 {d['p99']:.1f} ms; PLC trigger-to-result "
            f"p50 {statistics.median(plc):.1f} ms")


async def main(seconds: float, print_only: bool, realtime: bool) -> None:
    os.environ["BENCH_CLIENT_REALTIME"] = "1" if realtime else "0"
    stamp = Stamp(bench_command())
    before_load = load_average()
    with tempfile.TemporaryDirectory(prefix="bench_poll-") as tmp:
        folder = Path(tmp)
        print(f"load average before: {before_load}", flush=True)
        after = await bench_daemon(folder / "after", True, seconds)
        print("after:", cycle_text(after), flush=True)
        fifo = (await bench_daemon(folder / "fifo", True, seconds, realtime=True)
                if realtime_allowed() else None)
        before = await bench_daemon(folder / "before", False, seconds)
        print("before:", cycle_text(before), flush=True)
        idle = await bench_daemon(folder / "idle", True, seconds, jobs=False)
        peer = await bench_peer_beside_daemon(folder / "peer", seconds)
        peer_old = await bench_peer_in_process(seconds)

    a, b = after["rtt_ms"], before["rtt_ms"]
    p99, worst = percentile(a, 99), max(a)
    met = p99 <= TARGET_P99_MS and worst <= TARGET_MAX_MS
    verdict = "MET" if met else "MISSED"
    ca, cb = after["daemon_cycle_ms"]["p50"], before["daemon_cycle_ms"]["p50"]
    cycle_verdict = "MET" if ca <= cb else "MISSED"
    fifo_text = "not measured (SCHED_FIFO not permitted here)"
    if fifo is not None:
        f = fifo["rtt_ms"]
        fifo_met = percentile(f, 99) <= TARGET_P99_MS and max(f) <= TARGET_MAX_MS
        fifo_text = (f"p99 {percentile(f, 99):.2f} / max {max(f):.2f} ms: **"
                     f"{'MET' if fifo_met else 'MISSED'}**; job cycle p50 "
                     f"{fifo['daemon_cycle_ms']['p50']:.1f} ms")
    lines = [
        "The real daemon (`python -m vgripd run`: synthetic "
        "stereo camera 1280x1024 rendered by its driver, Modbus/TCP server link, recording on) "
        f"and a PLC stand-in in its own process reading all {MAP_SIZE} registers at 100 Hz, "
        "triggering the next job as soon as it reads a result (jobs back to back); "
        + ("the stand-in runs under SCHED_FIFO (a real PLC is a device of its own: its wake-ups "
           "are not the daemon's latency). " if after.get("realtime") else
           "the stand-in runs at normal priority (its own wake-ups are in the figures). ")
        + f"{seconds:g} s per row. Target: poll p99 <= {TARGET_P99_MS:g} ms and max <= "
        f"{TARGET_MAX_MS:g} ms while jobs run, the job cycle no slower than before.",
        "",
        "| server | polls | median ms | p99 ms | max ms |",
        "|---|---:|---:|---:|---:|",
        row("vgripd, worker process (after), jobs back to back, recording on", after),
        *([row("vgripd, worker process, daemon under SCHED_FIFO (systemd "
               "`CPUSchedulingPolicy=fifo`), same", fifo)] if fifo is not None else []),
        row("vgripd, in-process (before: `daemon.worker = false`), same", before),
        row("vgripd, worker process, idle", idle),
        row(f"pymodbus static, while a vgripd worker daemon runs {peer['load_jobs']} jobs "
            "in other processes", peer),
        row(f"pymodbus static, Pipeline.process in its own executor thread "
            f"({peer_old['load_jobs']} jobs; the old peer)", peer_old),
        "",
        f"Poll p99 / max: after {p99:.2f} / {worst:.2f} ms, before {percentile(b, 99):.2f} / "
        f"{max(b):.2f} ms (after / before p99 {p99 / percentile(b, 99):.2f}, max "
        f"{worst / max(b):.2f}); after / peer beside the daemon p99 "
        f"{p99 / percentile(peer['rtt_ms'], 99):.2f}. As shipped (normal scheduling): **{verdict}** "
        f"(p99 <= {TARGET_P99_MS:g} ms and max <= {TARGET_MAX_MS:g} ms). With the daemon under "
        f"SCHED_FIFO (its worker drops to time sharing, SCHED_BATCH, nice +15): {fifo_text}.",
        "",
        f"Job cycle, after: {cycle_text(after)}.  ",
        f"Job cycle, before: {cycle_text(before)}.  ",
        f"After / before daemon cycle p50: {ca / cb:.2f}: no slower **{cycle_verdict}**.",
        "",
    ]
    report(SUBJECT, SECTION, "\n".join(lines), stamp, print_only)


if __name__ == "__main__":
    parser = bench_parser(__doc__)
    parser.add_argument("--seconds", type=float, default=20.0, help="per row")
    parser.add_argument("--no-realtime-client", dest="realtime", action="store_false",
                        help="run the PLC stand-in at normal priority (default: SCHED_FIFO when "
                             "allowed)")
    parser.add_argument("--shipped", type=Path, metavar="BASE",
                        help="instead: this tree and the checkout BASE each as its systemd "
                             "unit runs it, and the peer, interleaved")
    parser.add_argument("--paired", action="store_true",
                        help="instead: this tree's daemon as shipped and a plain pymodbus server "
                             "under the same scheduling, polled in turn by one client")
    parser.add_argument("--rounds", type=int, default=3, help="with --shipped or --paired")
    args = parser.parse_args()
    if args.paired:
        os.environ["BENCH_CLIENT_REALTIME"] = "1" if args.realtime else "0"
        asyncio.run(main_paired(args.seconds, args.rounds, args.print_only))
    elif args.shipped is not None:
        os.environ["BENCH_CLIENT_REALTIME"] = "1" if args.realtime else "0"
        asyncio.run(main_shipped(args.seconds, args.rounds, args.shipped.resolve(),
                                 args.print_only))
    else:
        asyncio.run(main(args.seconds, args.print_only, args.realtime))
