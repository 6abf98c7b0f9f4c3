"""Run the whole cell on this computer: the daemon, a synthetic stereo camera and a PLC.

The daemon runs in-process on built-in defaults: the synthetic camera renders the demo object at
a random pose around the taught reference (the truth is known), the Modbus/TCP server link
listens on 127.0.0.1, and a scripted PLC (``vgripd.sim.plc``) triggers cycles over real TCP,
polls for each answer and checks the handshake. One cycle also triggers a second time while the
job runs, to show the refusal (BUSY). A last fault cycle restarts the daemon with the object
placed beyond the offset limit, to show the safety gate (OUT_OF_LIMITS, no pose published).
A last daemon has two recipes (docs/recipes.md) with a second plate in view: the PLC selects
them by number with the RECIPE register; the second plate's recipe finds it, the demo plate's
recipe does not (NOT_FOUND), an unknown number is BAD_REQUEST without an image.
Each result is printed with the offset in the robot vendor's convention and the pose error
against the synthetic truth; a summary follows.

Exit code 0 when every cycle got a consistent handshake answer (and the fault cycle was
refused by the gate), 1 otherwise.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import socket
from collections.abc import Awaitable, Callable
from typing import Any

import numpy as np

from vgripd.config import config_from_dict
from vgripd.errors import LinkError
from vgripd.geometry.transforms import pose_error
from vgripd.geometry.vendors import CONVENTIONS, convention
from vgripd.service.daemon import Daemon, JobRecord, configure_logging
from vgripd.service.protocol import MAX_VALUES
from vgripd.sim.plc import CycleResult, MockPlc
from vgripd.types import ImagePair, Status

DEFAULT_PORT = 5020
DEFAULT_WEB_PORT = 8730
REGISTER_VENDORS = [n for n, c in CONVENTIONS.items() if len(c.fields) <= MAX_VALUES]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cycles", type=int, default=10, help="PLC cycles (default 10)")
    parser.add_argument("--seed", type=int, default=1, help="synthetic poses/noise (default 1)")
    parser.add_argument("--vendor", default="kuka", choices=REGISTER_VENDORS,
                        help="robot convention of the published offset (default kuka)")
    parser.add_argument("--port", type=int, default=DEFAULT_PORT,
                        help=f"Modbus/TCP port on 127.0.0.1 (default {DEFAULT_PORT}; "
                             "a free one if taken)")
    parser.add_argument("--web-port", type=int, default=DEFAULT_WEB_PORT,
                        help=f"web view port on 127.0.0.1 (default {DEFAULT_WEB_PORT}; "
                             "a free one if taken)")
    parser.add_argument("--linger", type=float, default=0.0, metavar="SECONDS",
                        help="keep the daemon and its web view up this long after the cycles, "
                             "to look at the jobs in a browser (default 0; Ctrl-C ends it)")
    parser.add_argument("--verbose", action="store_true", help="show the daemon's log")


def _port(wanted: int) -> int:
    """``wanted`` if it can be bound on 127.0.0.1, else 0 (any free port)."""
    with socket.socket() as probe:
        try:
            probe.bind(("127.0.0.1", wanted))
        except OSError:
            return 0
    return wanted


def demo_config(port: int, seed: int, vendor: str, pose: dict[str, Any] | None = None,
                web_port: int = 0) -> Any:
    """The demo cell; ``pose`` fixes the object pose (else random around the reference)."""
    return config_from_dict({
        # Ordinary placements: up to 10 mm and 3 deg from the taught pose (the limits judge
        # the object's own displacement, docs/pipeline.md "Limits"; the fault cycle exceeds them).
        "camera": {"type": "synthetic", "seed": seed, "max_shift_mm": 10.0, "max_tilt_deg": 3.0,
                   **({"pose": pose} if pose else {})},
        "output": {"vendor": vendor},
        "links": [{"type": "modbus_server", "host": "127.0.0.1", "port": port}],
        "status": {"port": web_port},
        "daemon": {"log_level": "WARNING"},
    })


#: The second plate of the recipe cycles: five 14 mm marks in another layout.
PLATE_B = {"name": "plate_b", "features": [
    {"name": f"b{i + 1}", "kind": "circle", "diameter_mm": 14.0, "xyz_mm": xyz}
    for i, xyz in enumerate([[-61.0, -2.0, 0.0], [68.0, 30.0, 0.0], [49.0, -35.0, 0.0],
                             [-29.0, 11.0, 10.0], [22.0, 19.0, 0.0]])]}
#: (recipe the PLC asks for, the answer that must come) with plate B in view.
RECIPE_CYCLES = ((1, Status.OK), (0, Status.NOT_FOUND), (1, Status.OK), (7, Status.BAD_REQUEST))


def recipes_config(port: int, seed: int, vendor: str, web_port: int = 0) -> Any:
    """The demo cell with recipe 1 = plate B (taught), plate B in view of the camera."""
    data = demo_config(port, seed, vendor, web_port=web_port).model_dump(
        mode="json", exclude_unset=True)
    data["camera"]["recipe"] = 1
    data["recipes"] = {"1": {"name": "plate-b", "object": PLATE_B, "reference": {
        "T_base_obj": {"translation_mm": [590.0, 110.0, 12.0], "rotvec_rad": [0.0, 0.0, -0.1]}}}}
    return config_from_dict(data)


def fault_pose(config: Any) -> dict[str, Any]:
    """The taught reference pose moved along base x by 1.6 times the translation limit."""
    ref = config.reference.T_base_obj
    x, y, z = ref.translation_mm
    shift = 1.6 * config.limits.max_translation_mm
    return {"translation_mm": [x + shift, y, z], "rotvec_rad": list(ref.rotvec_rad or (0, 0, 0))}


class Demo:
    def __init__(self, vendor: str) -> None:
        self.conv = convention(vendor)
        self.jobs: dict[int, tuple[ImagePair | None, JobRecord]] = {}
        self.errors: list[tuple[float, float]] = []
        self.answers: list[CycleResult] = []
        self.daemon: Daemon | None = None

    def attach(self, daemon: Daemon) -> None:
        """Follow this daemon's jobs (job ids restart with each daemon)."""
        self.daemon = daemon
        self.jobs.clear()
        daemon.listeners.append(lambda pair, rec: self.jobs.__setitem__(rec.job_id, (pair, rec)))

    def header(self) -> str:
        units = [self.conv.length_unit] * 3 + [self.conv.angle_unit] * (len(self.conv.fields) - 3)
        cols = "".join(f"{f + (' ' + u if u else ''):>10}" for f, u in
                       zip(self.conv.fields, units, strict=True))
        return f"{'seq':>4}  {'status':<15}{cols}{'cycle ms':>10}{'err mm':>9}{'err deg':>9}"

    async def line(self, answer: CycleResult, note: str = "", recipe: int | None = None) -> str:
        self.answers.append(answer)
        head = f"{answer.seq:>4}  {answer.status.name:<15}"
        tail = "" if recipe is None else f"  recipe {recipe}"
        if answer.rejected:
            return head + f"refused: {note or 'by the handshake'}"
        assert self.daemon is not None
        await self.daemon.wait_for(lambda: answer.job_id in self.jobs, 5.0)
        pair, rec = self.jobs[answer.job_id]
        cols = "".join(f"{v:>10.3f}" for v in answer.values) if answer.values else (
            f"{'(no pose: ' + rec.result.message + ')':<{10 * len(self.conv.fields)}}")
        err = ""
        if pair is not None and rec.result.T_base_obj is not None and "T_base_obj" in pair.truth:
            dt, dr = pose_error(pair.truth["T_base_obj"], rec.result.T_base_obj)
            self.errors.append((dt, dr))
            err = f"{dt:>9.3f}{dr:>9.3f}"
        return f"{head}{cols}{answer.cycle_ms:>10.1f}{err}{tail}"

    def summary(self) -> list[str]:
        counts: dict[str, int] = {}
        for a in self.answers:
            counts[a.status.name] = counts.get(a.status.name, 0) + 1
        cycles = np.array([a.cycle_ms for a in self.answers if not a.rejected])
        lines = ["counts: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))]
        if cycles.size:
            p50, p95 = np.percentile(cycles, (50, 95))
            lines.append(f"cycle time (PLC trigger -> answer seen): p50 {p50:.1f} ms, "
                         f"p95 {p95:.1f} ms, max {cycles.max():.1f} ms over {cycles.size} jobs")
        if self.errors:
            e = np.array(self.errors)
            lines.append(f"pose error vs synthetic truth: max {e[:, 0].max():.3f} mm, "
                         f"{e[:, 1].max():.4f} deg (mean {e[:, 0].mean():.3f} mm)")
        return lines


async def _with_daemon(demo: Demo, config: Any,
                       script: Callable[[Daemon, MockPlc], Awaitable[None]]) -> None:
    """Start a daemon on ``config``, run ``script`` with a PLC connected to it, stop it."""
    daemon = Daemon(config)
    demo.attach(daemon)
    await daemon.start()
    try:
        link_port: int = next(iter(daemon.links.values())).port  # type: ignore[attr-defined]
        async with MockPlc("127.0.0.1", link_port) as plc:
            await plc.check_byte_order()
            await script(daemon, plc)
    finally:
        await daemon.stop()


async def run_demo(args: argparse.Namespace) -> int:
    port = _port(args.port)
    web_port = _port(args.web_port)
    demo = Demo(args.vendor)
    config = demo_config(port, args.seed, args.vendor, web_port=web_port)

    async def cycles(daemon: Daemon, plc: MockPlc) -> None:
        nonlocal web_port
        assert daemon.status_server is not None
        web_port = daemon.status_server.port  # the real one; the fault daemon reuses it
        print(f"vgripd demo: daemon serving Modbus/TCP on {plc.where}, web view on "
              f"http://127.0.0.1:{web_port}/", flush=True)
        print(f"synthetic stereo camera, object {config.object.name!r}, offset against "
              f"the taught reference as {args.vendor.upper()} ({demo.conv.summary})\n")
        print(demo.header())
        busy_cycle = args.cycles // 2 + 1 if args.cycles >= 2 else 0
        for i in range(1, args.cycles + 1):
            if i != busy_cycle:
                print(await demo.line(await plc.cycle()), flush=True)
                continue
            first = await plc.trigger()
            second = await plc.trigger()  # while the first job runs
            refused = await plc.wait_answer(second)
            answer = await plc.wait_answer(first)
            print(await demo.line(answer), flush=True)
            print(await demo.line(refused, f"job for seq {first} was running"), flush=True)
            if not (refused.rejected and refused.status is Status.BUSY):
                raise LinkError(f"seq {second} sent while busy was not refused with BUSY")
        if args.linger > 0:
            print(f"\nweb view: http://127.0.0.1:{web_port}/ stays up {args.linger:g} s "
                  "(Ctrl-C ends it)", flush=True)
            await asyncio.sleep(args.linger)

    async def fault(daemon: Daemon, plc: MockPlc) -> None:
        answer = await plc.cycle()
        print(await demo.line(answer), flush=True)
        if answer.status is not Status.OUT_OF_LIMITS or answer.values:
            raise LinkError(f"fault cycle answered {answer.status.name}, not OUT_OF_LIMITS")

    async def recipes(daemon: Daemon, plc: MockPlc) -> None:
        for recipe, expected in RECIPE_CYCLES:
            answer = await plc.cycle(recipe)
            print(await demo.line(answer, recipe=recipe), flush=True)
            if answer.status is not expected:
                raise LinkError(f"recipe {recipe} on plate B answered {answer.status.name}, "
                                f"not {expected.name}")

    try:
        await _with_daemon(demo, config, cycles)
        print(f"\nfault cycle (daemon restarted): object placed "
              f"{1.6 * config.limits.max_translation_mm:.0f} mm from the reference, limit "
              f"{config.limits.max_translation_mm:.0f} mm")
        await _with_daemon(demo, demo_config(port, args.seed, args.vendor, fault_pose(config),
                                             web_port=web_port), fault)
        print("\nrecipes (daemon restarted): recipe 1 = plate B (14 mm marks, another layout) "
              "in view, recipe 0 = the demo plate; the PLC writes RECIPE with each trigger")
        await _with_daemon(demo, recipes_config(port, args.seed, args.vendor, web_port),
                           recipes)
    except (LinkError, TimeoutError) as err:
        print(f"\nvgripd demo: FAILED: {err}")
        return 1
    print("\n" + "\n".join(demo.summary()))
    print("every cycle got a consistent handshake answer")
    return 0


def run(args: argparse.Namespace) -> int:
    if args.cycles < 1:
        print("vgripd demo: --cycles must be at least 1")
        return 2
    configure_logging("INFO" if args.verbose else "WARNING")
    if not args.verbose:
        logging.getLogger("vgripd").setLevel(logging.ERROR)
    try:
        return asyncio.run(run_demo(args))
    except KeyboardInterrupt:
        print("\nvgripd demo: interrupted")
        return 130
