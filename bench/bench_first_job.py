"""The first job after start against the tenth: the real daemon, worker process, recording on.

Goal: the first job after start as fast as the tenth. Each round starts
``python -m vgripd run`` (synthetic stereo camera 1280x1024 rendered by its driver, Modbus/TCP
server link on 127.0.0.1, recording on, the worker process), waits until it reports running
(READY=1 under systemd), then a PLC stand-in in its own process (bench_poll's, pymodbus'
synchronous client polling at 100 Hz) triggers 10 jobs one after the other. Timed: the daemon's
own cycle of each job (trigger received -> result published, from its log) and the PLC's
(trigger written -> result read, quantised by its 10 ms poll).

``--base DIR`` also runs another checkout of vgripd (e.g. the commit before the warm-up, from
``git archive``) in the same rounds, interleaved, so both see the same machine load.

Run: ``.venv/bin/python bench/bench_first_job.py [--rounds 3] [--base DIR] [--print-only]``
"""

from __future__ import annotations

import asyncio
import re
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.harness import DaemonProcess, Stamp, bench_command, report, run_client  # noqa: E402
from bench.harness import parser as bench_parser  # noqa: E402

SUBJECT = "Daemon: polls, jobs, memory"
SECTION = "First job after start against the tenth"
JOBS = 10


def command_for(tree: Path, config: Path) -> list[str]:
    """``vgripd run -c config`` from the checkout ``tree`` (first on sys.path, the worker too)."""
    code = (f"import sys; sys.path.insert(0, {str(tree)!r}); "
            "from vgripd.__main__ import main; sys.exit(main(sys.argv[1:]))")
    return [sys.executable, "-c", code, "run", "-c", str(config)]


def with_sample(daemon: DaemonProcess, sample: Path) -> None:
    """Make ``daemon``'s config the ``sample``'s, with its port, status, daemon and record."""
    ours = daemon.config.read_text()
    text = re.sub(r"(?m)^port = \d+", f"port = {daemon.port}", sample.read_text())
    daemon.config.write_text(text + ours[ours.index("[status]"):])


async def one_round(folder: Path, tree: Path, sample: Path | None = None) -> dict[str, object]:
    """Start a daemon from ``tree`` (on bench_poll's config, or on ``sample`` with the port,
    status endpoint and recording of bench_poll's); the start time and the PLC's cycle of 10
    jobs."""
    daemon = DaemonProcess(folder, worker=True)
    if sample is not None:
        with_sample(daemon, sample)
    daemon.command = command_for(tree, daemon.config)
    t0 = time.monotonic()
    async with daemon:
        started_s = time.monotonic() - t0
        got = await run_client(daemon.port, "cycle", 0, jobs=JOBS)
    cycle = [float(x) for x in got["cycle_ms"]]
    assert len(cycle) == JOBS, got
    assert set(got["statuses"]) <= {"OK", "OK_RECALIBRATE"}, got
    return {"start_s": started_s, "cycle_ms": cycle}


def line(name: str, rounds: list[dict[str, object]]) -> str:
    firsts = [r["cycle_ms"][0] for r in rounds]  # type: ignore[index]
    tenths = [r["cycle_ms"][-1] for r in rounds]  # type: ignore[index]
    rest = [statistics.median(r["cycle_ms"][1:]) for r in rounds]  # type: ignore[index]
    starts = [r["start_s"] for r in rounds]
    fmt = " / ".join
    return (f"| {name} | {fmt(f'{s:.1f}' for s in starts)} | {fmt(f'{f:.0f}' for f in firsts)} "
            f"| {fmt(f'{t:.0f}' for t in tenths)} | {fmt(f'{m:.0f}' for m in rest)} "
            f"| {statistics.median(firsts) / statistics.median(rest):.2f} |")


async def main(rounds: int, base: Path | None, print_only: bool, samples: list[Path]) -> None:
    stamp = Stamp(bench_command())
    trees = {"this tree": REPO, **({"base": base} if base is not None else {})}
    results: dict[str, list[dict[str, object]]] = {}
    with tempfile.TemporaryDirectory(prefix="bench_first_job-") as tmp:
        for i in range(rounds):
            for sample in [None, *samples]:
                for name, tree in trees.items():  # interleaved: both see the same load
                    key = name if sample is None else f"{name}, {sample.name}"
                    folder = Path(tmp) / f"{key.replace(' ', '_').replace(',', '')}{i}"
                    got = await one_round(folder, tree, sample)
                    print(key, i, got, flush=True)
                    results.setdefault(key, []).append(got)
    lines = [
        f"Each round starts the real daemon (worker process, synthetic stereo camera "
        f"1280x1024, Modbus/TCP server, recording on), waits until it runs, and a PLC "
        f"stand-in triggers {JOBS} jobs one after the other; PLC trigger-to-result times in "
        "ms (quantised by its 10 ms poll), one figure per round"
        + (", the two trees interleaved round by round" if base is not None else "") + ".",
        "",
        "| daemon | start s | first job ms | tenth job ms | median of jobs 2-10 ms "
        "| first / jobs 2-10 (medians over rounds) |",
        "|---|---:|---:|---:|---:|---:|",
        *(line(name, got) for name, got in results.items()),
        "",
    ]
    report(SUBJECT, SECTION, "\n".join(lines), stamp, print_only)


if __name__ == "__main__":
    parser = bench_parser(__doc__)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--base", type=Path, help="another vgripd checkout, run interleaved")
    parser.add_argument("--sample", type=Path, action="append", default=[],
                        help="also a config of config/samples (its link port is replaced)")
    args = parser.parse_args()
    asyncio.run(main(args.rounds, args.base, args.print_only,
                     [p.resolve() for p in args.sample]))
