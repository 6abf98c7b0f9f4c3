"""``vgripd demo --scene conveyor``: parts on a running belt, seen, queued and picked.

Parts lie on a simulated belt (``vgripd.sim.conveyor``) at random spacing, across offsets and
rotations, moving at ``--speed``. The stereo images are rendered at the counts the PLC latches,
one every trigger distance of travel, with the motion blur of ``--exposure-us``, and replayed
to the daemon in order. The PLC (pymodbus over TCP, register map version 4) writes the latched
count with each trigger; a robot twin takes the queued parts with NEXT, asks PREDICT where
each will be at its grip and picks it there (``vgripd.sim.belt_robot``; the belt's time is
simulated, so a busy computer changes no result). The summary judges every grip against the
simulated belt's truth: parts on the belt and seen, picked once, missed, picked twice, and the
pose error at the grip.

Exit code 0 when no part was gripped twice, no grip took nothing and every grip lay within
``PASS_MM`` of its part (parts the robot could not reach in time are missed, not a failure:
the summary counts them); 1 otherwise.
"""

from __future__ import annotations

import argparse
import asyncio
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from vgripd.config import Config, config_from_dict
from vgripd.errors import LinkError
from vgripd.service.daemon import Daemon
from vgripd.sim.belt_robot import BeltRun, RobotTiming, run_belt
from vgripd.sim.conveyor import BeltCamera, BeltPlc, SimBelt, footprint_mm, random_parts
from vgripd.vision.scene import T_base_obj_ref

#: The belt of the demo cell: along base +x through y = 100 at z = 10 (under the camera).
BELT: dict[str, Any] = {"counts_per_mm": 10.0, "direction": [1.0, 0.0, 0.0],
                        "origin_mm": [0.0, 100.0, 10.0], "window_mm": [300.0, 1000.0],
                        "trigger_distance_mm": 150.0, "sigma_mm": 0.5}
#: The encoder starts near the top of its 32-bit range: the run crosses the wrap.
COUNT0 = (1 << 32) - 5000
#: A grip farther than this from its part fails the demo (mm).
PASS_MM = 2.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--speed", type=float, default=200.0, metavar="MM_S",
                        help="--scene conveyor: the belt's speed (default 200 mm/s)")
    parser.add_argument("--parts", type=int, default=8,
                        help="--scene conveyor: parts on the belt (default 8)")
    parser.add_argument("--exposure-us", type=float, default=1000.0,
                        help="--scene conveyor: the camera's exposure, the motion blur "
                             "(default 1000 us)")


def conveyor_config(folder: Path, port: int, web_port: int, vendor: str, speed_mm_s: float,
                    latch: str = "link") -> Config:
    """The demo cell with a conveyor recipe; the camera replays the images in ``folder``."""
    demo = Config().calibration
    assert demo is not None
    return config_from_dict({
        "camera": {"type": "replay", "folder": str(folder), "left_glob": "left_*.png",
                   "right_glob": "right_*.png"},
        "output": {"vendor": vendor},
        "links": [{"type": "modbus_server", "host": "127.0.0.1", "port": port,
                   "map_version": 4}],
        "status": {"port": web_port},
        "daemon": {"worker": False, "log_level": "WARNING", "job_timeout_s": 30.0},
        "calibration": demo.model_dump(mode="json", exclude_none=True),
        "picking": {"max_objects": 4},
        "limits": {"max_translation_mm": 400.0, "max_rotation_deg": 60.0},
        "conveyor": {**BELT, "latch": latch, "speed_mm_s": speed_mm_s},
    })


def belt_for(config: Config, parts: int, seed: int) -> tuple[SimBelt, BeltCamera]:
    """``parts`` random parts upstream of the camera's view, clear of each other."""
    assert config.conveyor is not None
    camera = BeltCamera(config, SimBelt(config.conveyor, [], COUNT0))
    lo, _ = camera.view_along()
    size = 2 * footprint_mm(config)
    rng = np.random.default_rng(seed)
    camera.belt.parts = random_parts(rng, parts, lo - 5.0, (size + 10.0, size + 150.0), 15.0,
                                     45.0)
    return camera.belt, camera


def frame_travels(config: Config, belt: SimBelt) -> list[float]:
    """An image every trigger distance until the last part is past the window."""
    assert config.conveyor is not None
    c = config.conveyor
    end = c.window_mm[1] - min(p.along_mm for p in belt.parts)
    return [i * c.trigger_distance_mm for i in range(int(end // c.trigger_distance_mm) + 1)]


async def render_all(camera: BeltCamera, folder: Path, frames: list[float],
                     motion_mm: float, seed: int) -> list[list[int]]:
    return [await camera.render(folder, i, travel, motion_mm, seed + i)
            for i, travel in enumerate(frames)]


def summary(run: BeltRun) -> list[str]:
    e = run.errors()
    lines = [f"parts on the belt {run.parts}, seen by the camera {len(run.seen)} "
             f"(in {sum(map(len, run.shown))} sightings over {len(run.frames)} images)",
             f"picked once {run.picked_once}, missed {run.missed}, duplicated "
             f"{run.duplicated}, grips on no part {run.ghosts}, served too late "
             f"{run.late}"]
    if len(e):
        lines.append(f"error at the pick vs the belt's truth: max {e[:, 0].max():.3f} mm "
                     f"(mean {e[:, 0].mean():.3f} mm), along the belt max "
                     f"{np.abs(e[:, 2]).max():.3f} mm, rotation max {e[:, 1].max():.3f} deg "
                     f"over {len(e)} picks")
    return lines


async def run_conveyor(args: argparse.Namespace, port: int, web_port: int) -> int:
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="vgripd-belt-") as tmp:
        folder = Path(tmp)
        config = conveyor_config(folder, port, web_port, args.vendor, args.speed)
        assert config.conveyor is not None
        belt, camera = belt_for(config, args.parts, args.seed)
        frames = frame_travels(config, belt)
        motion = args.speed * args.exposure_us * 1e-6
        print(f"vgripd demo --scene conveyor: {args.parts} parts at random spacing and "
              f"rotation on a belt at {args.speed:g} mm/s; an image every "
              f"{config.conveyor.trigger_distance_mm:g} mm ({len(frames)} images, exposure "
              f"{args.exposure_us:g} us: {motion:.2f} mm of travel blurred); pick window "
              f"{list(config.conveyor.window_mm)} mm along the belt", flush=True)
        shown = await render_all(camera, folder, frames, motion, args.seed * 1000)
        print(f"images rendered at the latched counts in {time.monotonic() - t0:.1f} s",
              flush=True)
        daemon = Daemon(config)
        await daemon.start()
        try:
            link_port: int = next(iter(daemon.rooms.links.links.values())).port  # type: ignore[attr-defined]
            assert daemon.status_server is not None
            print(f"daemon serving Modbus/TCP (map version 4) on 127.0.0.1:{link_port}, web "
                  f"view on http://127.0.0.1:{daemon.status_server.port}/", flush=True)
            async with BeltPlc("127.0.0.1", link_port, timeout_s=40.0) as plc:
                await plc.check_byte_order()
                run = await run_belt(plc, belt, frames, args.speed,
                                     config.conveyor.window_mm, T_base_obj_ref(config),
                                     args.vendor, RobotTiming(), shown=shown)
                snap = daemon.snapshot()["conveyor"]["0"]
            if args.linger > 0:
                print(f"\nweb view: http://127.0.0.1:{daemon.status_server.port}/ stays up "
                      f"{args.linger:g} s (Ctrl-C ends it)", flush=True)
                await asyncio.sleep(args.linger)
        except (LinkError, TimeoutError, RuntimeError) as err:
            print(f"\nvgripd demo: FAILED: {err}")
            return 1
        finally:
            await daemon.stop()
    print(f"\n{'pick':>4} {'part':>5} {'travel mm':>10} {'err mm':>8} {'along mm':>9} "
          f"{'err deg':>8}")
    for i, p in enumerate(run.picks, 1):
        print(f"{i:>4} {p.part:>5} {p.travel_mm:>10.1f} {p.error_mm:>8.3f} "
              f"{p.along_error_mm:>9.3f} {p.error_deg:>8.3f}")
    print(f"\ndaemon's queue: seen {snap['seen']}, duplicates {snap['duplicates']}, served "
          f"{snap['served']}, dropped {snap['dropped']}, exposure -> queue p50 "
          f"{snap['queue_latency_ms_p50']:.1f} ms")
    print("\n".join(summary(run)))
    print(f"run time {time.monotonic() - t0:.1f} s")
    e = run.errors()
    ok = run.duplicated == 0 and run.ghosts == 0 and (not len(e) or e[:, 0].max() < PASS_MM)
    print(f"no part picked twice, every grip within {PASS_MM:g} mm of its part" if ok else
          f"vgripd demo: FAILED: a part picked twice, a grip on no part or one farther than "
          f"{PASS_MM:g} mm")
    return 0 if ok else 1
