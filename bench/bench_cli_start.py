"""How long a vgripd command takes from exec to exit, against ``python -c pass`` (the named peer:
the interpreter's own start, which no command can beat).

Each command runs as a fresh process, as an integrator types it, from a temporary folder (not
the checkout); wall time from ``subprocess.run`` to its return. The median of ``--runs`` runs per
command, the commands interleaved round by round so that a change in the machine's load falls on
all of them alike. The load average is printed with the figures.

Commands: ``vgripd --help``; ``vgripd convert`` of one pose (numpy and the vendor conventions);
``vgripd robot-program`` and ``vgripd check`` of config/examples/robot-socket-kuka.toml (the
config model and the drivers; check also the daemon's pipeline: commands that need them).

Run: ``.venv/bin/python bench/bench_cli_start.py [--runs 15] [--before DIR] [--print-only]``
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench import harness  # noqa: E402

VGRIPD = [sys.executable, "-m", "vgripd"]


def commands(out: Path) -> dict[str, list[str]]:
    return {
        "python -c pass (peer)": [sys.executable, "-c", "pass"],
        "vgripd --help": [*VGRIPD, "--help"],
        "vgripd convert (one pose)": [*VGRIPD, "convert", "--from", "kuka", "--to", "abb",
                                      "100", "-20", "300", "-90", "45", "-10"],
        "vgripd robot-program (kuka)": [*VGRIPD, "robot-program", "--brand", "kuka", "-c",
                                        str(REPO / "config/examples/robot-socket-kuka.toml"),
                                        "-o", str(out / "kuka"), "--host", "192.168.1.20"],
        "vgripd check (an example)": [*VGRIPD, "check", "-c",
                                      str(REPO / "config/examples/robot-socket-kuka.toml")],
    }


def main() -> None:
    parser = harness.parser(__doc__)
    stamp = harness.Stamp(harness.bench_command())
    parser.add_argument("--runs", type=int, default=15)
    parser.add_argument("--before", type=Path, default=None, metavar="DIR",
                        help="also time the commands of another source tree (e.g. `git archive "
                             "REV | tar -x -C DIR`), interleaved with these")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        cwd = Path(tmp)
        # the source on the path for `-m vgripd` (ahead of an editable install of this one)
        trees = {"": REPO, **({"before: ": args.before} if args.before else {})}
        cmds = {f"{label}{name}": (argv, {**os.environ, "PYTHONPATH": str(tree)})
                for label, tree in trees.items() for name, argv in commands(cwd).items()
                if not (label and name.startswith("python"))}
        times: dict[str, list[float]] = {name: [] for name in cmds}
        for _ in range(args.runs):
            for name, (argv, env) in cmds.items():
                t0 = time.perf_counter()
                subprocess.run(argv, cwd=cwd, env=env, stdout=subprocess.DEVNULL, check=True,
                               stderr=subprocess.DEVNULL)
                times[name].append(time.perf_counter() - t0)
    load = os.getloadavg()
    peer = statistics.median(times["python -c pass (peer)"])
    lines = [f"{args.runs} runs each, interleaved; load average {load[0]:.1f} {load[1]:.1f} "
             f"{load[2]:.1f}; Python {sys.version.split()[0]}"]
    for name, ts in times.items():
        med = statistics.median(ts)
        lines.append(f"{name:<38} median {med * 1000:7.0f} ms  min {min(ts) * 1000:6.0f} ms  "
                     f"max {max(ts) * 1000:6.0f} ms  median - peer {(med - peer) * 1000:6.0f} ms")
    text = "\n".join(lines)
    print(text)
    harness.report("Start and install", "Command start time", f"""Each command is a fresh process started
from a temporary folder, timed from exec to exit; the peer is the interpreter's own start
(`python -c pass`). "before:" rows (with `--before`) are the same commands from another source
tree, interleaved with the rest. Each command imports only its own module (`vgripd/__main__.py`
builds the parser of the chosen command alone), so `--help` loads no command at all and
`convert` loads numpy and the vendor conventions, not the daemon, aiohttp, OpenCV or pydantic
(tests/unit/cli/test_main_imports.py checks the modules).

```
{text}
```
""", stamp, args.print_only)


if __name__ == "__main__":
    main()
