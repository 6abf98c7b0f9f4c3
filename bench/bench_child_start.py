"""How long the daemon takes to start a worker process: forked by the fork server (what the
daemon does, ``vgripd/service/host/children.py``) against a ``multiprocessing`` spawn (the
named peer: what it did before, a fresh interpreter importing everything).

Each round starts one child of each kind, interleaved, whose work is to import the worker's
module (``vgripd.service.worker.child``: numpy, OpenCV, pydantic, the config) and exit, and
times it from ``Process.start`` to its exit. The fork server has imported that module once, at
its own start (timed apart, once: the first worker's start pays it). The spawn child's CPU
time (its own, from ``getrusage``) is printed too; a forked child's is the fork alone.

Run: ``.venv/bin/python bench/bench_child_start.py [--rounds 20] [--print-only]``
"""

from __future__ import annotations

import importlib
import multiprocessing
import resource
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench import harness  # noqa: E402
from vgripd.service.host import children  # noqa: E402

WORKER_MODULE = "vgripd.service.worker.child"


def _children_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def main() -> None:
    parser = harness.parser(__doc__)
    parser.add_argument("--rounds", type=int, default=20)
    args = parser.parse_args()
    stamp = harness.Stamp(harness.bench_command())
    t0 = time.perf_counter()
    children.start_server()
    server_start_s = time.perf_counter() - t0
    kinds = {"fork server (vgripd)": children.context(),
             "spawn (peer)": multiprocessing.get_context("spawn")}
    wall: dict[str, list[float]] = {name: [] for name in kinds}
    spawn_cpu: list[float] = []
    for _ in range(args.rounds):
        for name, ctx in kinds.items():
            cpu0 = _children_cpu_s()
            proc = ctx.Process(target=importlib.import_module, args=(WORKER_MODULE,))
            t0 = time.perf_counter()
            proc.start()
            proc.join()
            wall[name].append(time.perf_counter() - t0)
            assert proc.exitcode == 0, f"{name}: child exit code {proc.exitcode}"
            if name.startswith("spawn"):
                spawn_cpu.append(_children_cpu_s() - cpu0)
    fork = statistics.median(wall["fork server (vgripd)"])
    spawn = statistics.median(wall["spawn (peer)"])
    lines = [f"{args.rounds} rounds, interleaved; the child imports {WORKER_MODULE} and exits"]
    for name, ts in wall.items():
        lines.append(f"{name:<22} median {statistics.median(ts) * 1000:7.1f} ms  "
                     f"min {min(ts) * 1000:7.1f} ms  max {max(ts) * 1000:7.1f} ms")
    lines.append(f"spawn child's CPU       median {statistics.median(spawn_cpu) * 1000:7.0f} ms")
    lines.append(f"spawn / fork server     {spawn / fork:7.1f}x")
    lines.append(f"fork server's own start (once, with its imports): {server_start_s * 1000:.0f} ms")
    text = "\n".join(lines)
    print(text)
    harness.report("Daemon: polls, jobs, memory", "Helper process start", f"""The daemon's helper processes (worker, JPEG helper, board
finder, ur_rtde process) are forks of multiprocessing's fork server, which imported their modules
once; the peer is a spawn, a fresh interpreter importing them at every start (what the daemon
did before). Each child imports the worker's module and exits, timed from `Process.start` to its
exit, the two kinds interleaved. A worker restarted after a crash saves the difference; the
test suite, which starts some 300 such children, saves it on each.

```
{text}
```
""", stamp, args.print_only)


if __name__ == "__main__":
    main()
