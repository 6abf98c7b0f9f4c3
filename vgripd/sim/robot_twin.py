"""The robot of the learning cell: a generated robot-socket program run by its Python twin,
moving a simulated arm, from the command line.

    python -m vgripd.sim.robot_twin walk --brand kuka --program robot --port 50100 \\
        --state robot.json --start "X Y Z A B C"
    python -m vgripd.sim.robot_twin locate --brand kuka --program robot --port 50100

``--program`` is the folder ``vgripd robot-program --brand BRAND -o DIR`` wrote: the twin
(``vgripd.sim.robot_socket_client``) takes its settings (scale, timeouts, command words, walk
speed and settle time) from those files and does what the program does. ``walk`` is the
program's walk routine (docs/calibration-handeye.md, "Walked calibration") with the board
mounted on the flange: the arm starts at ``--start`` (the flange pose in the brand's
convention, where the camera sees the board squarely), and the twin writes the arm's true
flange pose to ``--state`` (JSON: ``T_base_flange`` 4x4 mm, ``board``) at every move, so the
learning cell's camera (``type = "board"`` with ``robot_state``, docs/cameras.md) draws the
board where the arm is; the pose the program sends carries the controller's error
(``--noise-deg``, ``--noise-mm``, one sigma per axis). After a complete walk the board is taken
off the flange (``board`` false): the camera then shows the plate on the table. ``locate``
calls the program's locate routine ``--count`` times and prints each answer.

Exit codes: 0 walk complete / every locate OK; 1 otherwise (the reason printed); 2 bad
arguments.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from vgripd.errors import ConversionError
from vgripd.geometry.vendors import convention, transform_from_vendor
from vgripd.peer.socket_frames import BRANDS
from vgripd.sim.arm import SimulatedArm
from vgripd.sim.robot_socket_client import (
    NOT_FOUND,
    ProgramSettings,
    ProgramStopped,
    ProgramTwin,
)


async def wait_for_vgripd(s: ProgramSettings, host: str, port: int, wait_s: float) -> None:
    """Wait until vgripd listens on ``host:port`` (an operator starts the program once vgripd
    waits for it); a program that vgripd dials (``robot_server``) has nothing to wait for."""
    if s.brand.connection == "robot_server" or wait_s <= 0:
        return
    deadline = time.monotonic() + wait_s
    while True:
        try:
            _, writer = await asyncio.open_connection(host, port)
        except OSError:
            if time.monotonic() > deadline:
                raise OSError(f"nothing listens on {host}:{port} after {wait_s:g} s") from None
            await asyncio.sleep(0.2)
            continue
        writer.close()
        with contextlib.suppress(OSError):
            await writer.wait_closed()
        return


STATUS_NAMES = {1: "OK", 2: "OK_RECALIBRATE", 10: "NOT_FOUND", 40: "BUSY", -1: "no answer"}


def write_state(path: Path, T_base_flange: Any, board: bool) -> None:
    """The arm's true flange pose and whether the board is on it, replaced atomically (a
    reader never sees half a file)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps({"T_base_flange": np.asarray(T_base_flange).tolist(),
                               "board": board}), encoding="utf-8")
    os.replace(tmp, path)


class StateArm(SimulatedArm):
    """The simulated arm, publishing where it really is at every move."""

    def __init__(self, state: Path, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.state_file = state
        write_state(state, self.T_true, True)

    def move(self, T: Any) -> None:
        super().move(T)
        write_state(self.state_file, self.T_true, True)


def settings(brand: str, folder: Path) -> ProgramSettings:
    if brand not in BRANDS:
        raise ValueError(f"--brand {brand!r}: one of {', '.join(sorted(BRANDS))}")
    b = BRANDS[brand]
    texts = {}
    for name in b.files:
        try:
            texts[name] = (folder / name).read_text(encoding="utf-8")
        except OSError as err:
            raise ValueError(f"--program {folder}: {name}: {err.strerror} (write it with "
                             f"vgripd robot-program --brand {brand} -o {folder})") from None
    return ProgramSettings.parse(b, texts)


async def walk(args: argparse.Namespace, s: ProgramSettings) -> int:
    conv = convention(s.brand.convention)
    T_start = transform_from_vendor(conv.name, args.start.replace(",", " ").split())
    state = Path(args.state)
    arm = StateArm(state, T_start, reach_mm=args.reach, settle_cycles=3,
                   noise_deg=args.noise_deg, noise_mm=args.noise_mm,
                   rng=np.random.default_rng(args.seed))
    await wait_for_vgripd(s, args.host, args.port, args.wait_s)
    async with ProgramTwin(s, args.host, args.port) as twin:
        outcome = await twin.walk(arm)
    print(f"walk: {len(outcome.reached)} targets reached, {len(outcome.skipped)} skipped, "
          f"ended with status {outcome.status} ({STATUS_NAMES.get(outcome.status, '?')})")
    if outcome.status != NOT_FOUND:
        print("walk: not complete (vgripd ends a walk with NOT_FOUND): the board stays on "
              "the flange")
        return 1
    write_state(state, arm.T_true, False)
    print(f"walk complete: the board is taken off the flange ({state})")
    return 0


async def locate(args: argparse.Namespace, s: ProgramSettings) -> int:
    fields = convention(s.brand.convention).fields
    ok = True
    await wait_for_vgripd(s, args.host, args.port, args.wait_s)
    async with ProgramTwin(s, args.host, args.port) as twin:
        for _ in range(args.count):
            out = await twin.locate()
            name = STATUS_NAMES.get(out.status, str(out.status))
            values = " ".join(f"{f}={v:.3f}" for f, v in zip(fields, out.values, strict=False))
            print(f"locate: {name} job {out.job_id} {values}".rstrip(), flush=True)
            ok = ok and out.status in (1, 2)
    return 0 if ok else 1


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m vgripd.sim.robot_twin",
                                     description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for name in ("walk", "locate"):
        p = sub.add_parser(name)
        p.add_argument("--brand", required=True, help="the program's brand")
        p.add_argument("--program", required=True, type=Path,
                       help="the folder vgripd robot-program wrote")
        p.add_argument("--host", default="127.0.0.1", help="where vgripd listens")
        p.add_argument("--port", type=int, required=True, help="the link's port")
        p.add_argument("--wait-s", type=float, default=60.0,
                       help="wait this long for vgripd to listen (default 60)")
        if name == "walk":
            p.add_argument("--state", required=True, help="the arm's state file (JSON)")
            p.add_argument("--start", required=True, metavar='"X Y Z A B C"',
                           help="start flange pose, in the brand's convention")
            p.add_argument("--reach", type=float, default=1500.0,
                           help="the arm's reach about the base origin, mm (default 1500)")
            p.add_argument("--noise-deg", type=float, default=0.001)
            p.add_argument("--noise-mm", type=float, default=0.005)
            p.add_argument("--seed", type=int, default=1)
        else:
            p.add_argument("--count", type=int, default=1, help="locates (default 1)")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        s = settings(args.brand, args.program)
        run = walk(args, s) if args.command == "walk" else locate(args, s)
        return asyncio.run(run)
    except (ValueError, ConversionError) as err:
        print(f"robot twin: {err}", file=sys.stderr)
        return 2
    except (ProgramStopped, OSError) as err:
        print(f"robot twin: the program stopped: {err}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
