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

``--scene pallet`` shows a pick list instead: the camera renders a pallet of six touching
plates (one with a mark covered), every plate is located, gated and ordered nearest first to a
drop point, and for each cycle the PLC triggers once and then walks the list with NEXT (register
map version 3, docs/registers.md): one line per plate with its INDEX of COUNT, pick point id,
score, pose and error against the renderer's truth of that plate, until NOT_FOUND ends the
list. A NEXT after CLEAR closes the run, refused BAD_REQUEST.

``--scene conveyor`` runs parts on a moving belt instead (``vgripd.cli.demo_conveyor``): images
at the latched counts, the part queue, NEXT and PREDICT, every grip judged against the
simulated belt.

Exit code 0 when every cycle got a consistent handshake answer (and the fault cycle was
refused by the gate), 1 otherwise.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
from collections.abc import Awaitable, Callable
from typing import Any

import numpy as np

from vgripd.cli import demo_conveyor, demo_setup
from vgripd.cli.demo_links import LINK_KINDS
from vgripd.config import config_from_dict
from vgripd.errors import LinkError
from vgripd.geometry.transforms import pose_error
from vgripd.geometry.vendors import CONVENTIONS, convention
from vgripd.peer.registers import MAX_VALUES
from vgripd.service.daemon import Daemon
from vgripd.service.host.logsetup import configure_logging
from vgripd.service.jobs.jobrecord import JobRecord
from vgripd.sim.plc import CycleResult, MockPlc
from vgripd.types import ImagePair, Status

DEFAULT_PORT = 5020
DEFAULT_WEB_PORT = 8730
REGISTER_VENDORS = [n for n, c in CONVENTIONS.items() if len(c.fields) <= MAX_VALUES]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", choices=("plate", "pallet", "conveyor"), default="plate",
                        help="plate: one object per image (default); pallet: six plates, "
                             "walked as a pick list with NEXT; conveyor: parts on a moving "
                             "belt, queued and picked with NEXT and PREDICT")
    parser.add_argument("--cycles", type=int, default=None,
                        help="PLC cycles (default 10; with --scene pallet: 2 pallets)")
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
    parser.add_argument("--link", choices=LINK_KINDS, default=None,
                        help="run the cycles on another link with its simulator as the peer "
                             "(robot_socket: the program of --vendor's brand; ur_rtde: the "
                             "mock UR controller; s7: snap7's server; opcua: asyncua's "
                             "client); default: Modbus/TCP with the scripted PLC")
    parser.add_argument("--peer-host", default=None, metavar="ADDRESS",
                        help="loopback address of the --link peer (default 127.0.0.1; "
                             "ur_rtde: a free one)")
    parser.add_argument("--verbose", action="store_true", help="show the daemon's log")
    demo_conveyor.add_arguments(parser)
    demo_setup.add_arguments(parser)


_port = demo_setup.bindable


def web_view(port: int, linger: float) -> str:
    """The web view's address as the demo announces it, with how long it stays up."""
    url = f"web view on http://127.0.0.1:{port}/"
    if linger > 0:
        return f"{url} (up until {linger:g} s after the cycles)"
    return (f"{url} (up only while the demo runs; `vgripd demo --linger 120` keeps it up "
            f"after the cycles)")


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


# The pallet scene (as config/samples/pallet.toml): six plates in two rows of three, touching,
# plate 4 with its mark m3 covered; nearest first to a drop point; two grip points, the middle
# of the plate first and its edge as the fallback.
PALLET_SCENE: dict[str, Any] = {
    "camera": {"pallet": {"count": 6, "cols": 3, "gap_mm": 0.0, "jitter_mm": 2.0,
                          "jitter_deg": 3.0},
               "drop_features": ["4/m3"]},
    "picking": {"max_objects": 6, "order": "nearest", "point_mm": [600.0, -150.0, 10.0],
                "pick_points": [
                    {"id": 1, "priority": 1, "pose": {"translation_mm": [-10.0, 0.0, 0.0],
                                                      "rotvec_rad": [3.14159265, 0.0, 0.0]}},
                    {"id": 2, "priority": 2, "pose": {"translation_mm": [-50.0, 0.0, 0.0],
                                                      "rotvec_rad": [3.14159265, 0.0, 0.0]}}]},
    "limits": {"max_translation_mm": 200.0, "max_rotation_deg": 10.0, "point": "grip"},
    "output": {"mode": "grip"},
}


#: The pallet scene's job time (its rendering, not a camera, sets it).
PALLET_JOB_TIMEOUT_S = 30.0


def pallet_config(port: int, seed: int, vendor: str, web_port: int = 0) -> Any:
    """The demo cell with the pallet scene."""
    scene = PALLET_SCENE
    return config_from_dict({
        "camera": {"type": "synthetic", "seed": seed, **scene["camera"]},
        "picking": scene["picking"],
        "limits": scene["limits"],
        "output": {"vendor": vendor, **scene["output"]},
        "links": [{"type": "modbus_server", "host": "127.0.0.1", "port": port}],
        "status": {"port": web_port},
        # the synthetic camera renders six plates per image: on a busy PC that takes longer
        # than a real camera's acquisition, which the default 10 s is sized for
        "daemon": {"log_level": "WARNING", "job_timeout_s": PALLET_JOB_TIMEOUT_S},
    })


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
        self.acquire_ms: list[float] = []  # the synthetic camera rendering the pair
        self.locate_ms: list[float] = []  # the pipeline: features, pose, gates
        self.daemon: Daemon | None = None

    def attach(self, daemon: Daemon) -> None:
        """Follow this daemon's jobs (job ids restart with each daemon)."""
        self.daemon = daemon
        self.jobs.clear()
        daemon.rooms.jobs.listeners.append(
            lambda pair, rec: self.jobs.__setitem__(rec.job_id, (pair, rec)))

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
        await self.daemon.wait_for(lambda: answer.job_id in self.jobs, 30.0)
        pair, rec = self.jobs[answer.job_id]
        timings = rec.result.timings_ms
        if "acquire" in timings and "total" in timings:
            self.acquire_ms.append(timings["acquire"])
            self.locate_ms.append(timings["total"])
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
        if self.acquire_ms:
            lines.append(
                f"  of which the synthetic camera rendering the pair: p50 "
                f"{np.percentile(self.acquire_ms, 50):.1f} ms, locating (features, pose, gates):"
                f" p50 {np.percentile(self.locate_ms, 50):.1f} ms; a real camera delivers its "
                f"images without the rendering (README, \"Accuracy and performance\": locate)")
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
        link_port: int = next(iter(daemon.rooms.links.links.values())).port  # type: ignore[attr-defined]
        # the daemon answers every request within its job timeout: the PLC waits that long
        # (and a little), so a slow machine's job is not given up on by the PLC first
        async with MockPlc("127.0.0.1", link_port,
                           timeout_s=config.daemon.job_timeout_s + 5.0) as plc:
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
        print(f"vgripd demo: daemon serving Modbus/TCP on {plc.where}, "
              f"{web_view(web_port, args.linger)}", flush=True)
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


class PalletDemo(Demo):
    """The pick list lines: one per NEXT answer, the plate matched to the renderer's truth."""

    def header(self) -> str:
        base = super().header()
        head, cols = base[:21], base[21:-28]
        return (f"{head}{'plate':>7}{'pick':>5}{'score':>7}{cols}{'ms':>7}{'err mm':>9}"
                f"{'err deg':>9}")

    def summary(self) -> list[str]:
        lines = super().summary()[:1]
        jobs = np.array([a.cycle_ms for a in self.answers if not a.rejected and a.index <= 1])
        nexts = np.array([a.cycle_ms for a in self.answers if not a.rejected and a.index > 1])
        for what, ms in (("TRIGGER (a new image, every plate located)", jobs),
                         ("NEXT (from the list, no image)", nexts)):
            if ms.size:
                lines.append(f"{what}: p50 {np.percentile(ms, 50):.1f} ms, max {ms.max():.1f} "
                             f"ms over {ms.size} requests")
        if self.errors:
            e = np.array(self.errors)
            lines.append(f"plate pose error vs synthetic truth: max {e[:, 0].max():.3f} mm, "
                         f"{e[:, 1].max():.4f} deg (mean {e[:, 0].mean():.3f} mm) over "
                         f"{len(e)} plates")
        return lines

    async def pick_line(self, answer: CycleResult) -> str:
        self.answers.append(answer)
        head = f"{answer.seq:>4}  {answer.status.name:<15}"
        if answer.rejected:
            return head + "refused: no pick list (after CLEAR)"
        assert self.daemon is not None
        await self.daemon.wait_for(lambda: answer.job_id in self.jobs, 30.0)
        pair, rec = self.jobs[answer.job_id]
        plate = f"{answer.index}/{answer.count}"
        if not answer.values:
            why = rec.result.message if answer.index <= answer.count else (
                f"list used up: all {answer.count} plates handed out")
            return f"{head}{plate:>7}{'':>12}  (no pose: {why})"
        inst = rec.result.instances[answer.index - 1] if rec.result.instances else None
        err = ""
        truths = pair.truth.get("instances_T_base_obj") if pair is not None else None
        if inst is not None and inst.T_base_obj is not None and truths is not None:
            dt, dr = min((pose_error(T, inst.T_base_obj) for T in truths),
                         key=lambda e: e[0])
            self.errors.append((dt, dr))
            err = f"{dt:>9.3f}{dr:>9.3f}"
        cols = "".join(f"{v:>10.3f}" for v in answer.values)
        return (f"{head}{plate:>7}{answer.pick_id:>5}{answer.score:>7.3f}{cols}"
                f"{answer.cycle_ms:>7.1f}{err}")


async def run_pallet(args: argparse.Namespace) -> int:
    port = _port(args.port)
    web_port = _port(args.web_port)
    demo = PalletDemo(args.vendor)
    config = pallet_config(port, args.seed, args.vendor, web_port=web_port)

    async def pallets(daemon: Daemon, plc: MockPlc) -> None:
        assert daemon.status_server is not None
        print(f"vgripd demo: daemon serving Modbus/TCP on {plc.where}, "
              f"{web_view(daemon.status_server.port, args.linger)}", flush=True)
        print(f"synthetic stereo camera, a pallet of {config.picking.max_objects} plates "
              f"{config.object.name!r} (touching, one with a mark covered), nearest first to "
              f"{list(config.picking.point_mm or ())} mm; grip pose as "
              f"{args.vendor.upper()} ({demo.conv.summary})")
        print("each pallet: one TRIGGER (CMD 1), then NEXT (CMD 3) until NOT_FOUND\n")
        print(demo.header())
        for _ in range(args.cycles):
            answer = await plc.cycle()
            print(await demo.pick_line(answer), flush=True)
            while answer.status.pose_valid:
                answer = await plc.next()  # checks: same job, INDEX + 1, age
                print(await demo.pick_line(answer), flush=True)
            if answer.index != answer.count + 1 or answer.status is not Status.NOT_FOUND:
                raise LinkError(f"pick list ended with {answer.status.name} at INDEX "
                                f"{answer.index} of {answer.count}, not NOT_FOUND past the end")
            print()
        await plc.write(0, [2, plc.next_seq(), 0])  # CLEAR: the list is gone
        refused = await plc.next()
        print(await demo.pick_line(refused), flush=True)
        if not (refused.rejected and refused.status is Status.BAD_REQUEST):
            raise LinkError("NEXT after CLEAR was not refused with BAD_REQUEST")
        snap = daemon.snapshot()
        print(f"\ndaemon: {sum(snap['next_answers'].values())} NEXT answers "
              f"({', '.join(f'{k} {v}' for k, v in sorted(snap['next_answers'].items()))}), "
              f"{len(demo.jobs)} jobs (images taken)")
        if args.linger > 0:
            await asyncio.sleep(args.linger)

    try:
        await _with_daemon(demo, config, pallets)
    except (LinkError, TimeoutError) as err:
        print(f"\nvgripd demo: FAILED: {err}")
        return 1
    print("\n".join(demo.summary()))
    print("every request got a consistent handshake answer")
    return 0


def run(args: argparse.Namespace) -> int:
    if args.setup:
        return demo_setup.run(args)
    if args.cycles is None:
        args.cycles = 2 if args.scene == "pallet" else 10
    if args.cycles < 1:
        print("vgripd demo: --cycles must be at least 1")
        return 2
    configure_logging("INFO" if args.verbose else "WARNING")
    if not args.verbose:
        logging.getLogger("vgripd").setLevel(logging.ERROR)
    if args.link is not None:
        from vgripd.cli.demo_links import DemoCell, run_link_demo
        main = run_link_demo(args, DemoCell(Demo, demo_config, _port, web_view))
    elif args.scene == "conveyor":
        main = demo_conveyor.run_conveyor(args, _port(args.port), _port(args.web_port))
    else:
        main = run_pallet(args) if args.scene == "pallet" else run_demo(args)
    try:
        return asyncio.run(main)
    except KeyboardInterrupt:
        print("\nvgripd demo: interrupted")
        return 130
