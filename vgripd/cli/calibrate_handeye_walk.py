"""vgripd calibrate handeye walk: serve a plan's targets to the robot program over the cell's
link and record an image with the flange pose at each (``vgripd.service.links.handeye_walk``).

Run it instead of the daemon (it opens the config's camera and its first link, or ``--link``).
The robot program walks: NEXT asks for a target, TRIGGER for the image once settled there, NEXT
again when it cannot reach the target; the answer NOT_FOUND ends the walk. The record
(``--walk``, default beside the plan) is saved after every target: run the command again to
resume. Then solve it: ``vgripd calibrate handeye --samples WALK --intrinsics CONFIG``.

``--running [URL]`` asks the running daemon instead (its web view, default from ``-c``'s
``[status]``; the token from ``$VGRIPD_TOKEN`` or the config): the daemon walks the plan (a file
in its config's folder) over its link ``--link`` with its own camera, answering every other
link BUSY meanwhile; the command prints each target as it is recorded and ends with the walk.
Ctrl-C stops the walk (the record stays: run again to resume). Solve and accept on the page
(``/handeye/walk``) or with the command above.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import sys
from pathlib import Path

import numpy as np

from vgripd.calib.boards import Board
from vgripd.calib.handeye.plan import load_plan
from vgripd.calib.handeye.walk import Walk
from vgripd.config import load_config
from vgripd.errors import CalibrationError
from vgripd.geometry.camera_model import CameraModel
from vgripd.registry import CAMERAS, LINKS, load_class, validate_options
from vgripd.service.links.handeye_walk import WalkServer, walk_refusal


def add_walk_arguments(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("walk (vgripd calibrate handeye walk ...)")
    g.add_argument("--plan", metavar="TOML", help="the plan from 'calibrate handeye plan'")
    g.add_argument("--walk", metavar="JSON",
                   help="the walk record (default <plan stem>.walk.json); resumed when present")
    g.add_argument("--link", type=int, default=0, metavar="N",
                   help="which [[links]] entry the robot program uses (default 0)")
    g.add_argument("--running", nargs="?", const="", metavar="URL",
                   help="ask the running daemon to walk (its web view, default from -c)")


async def _walk(server: WalkServer, camera: object, link: object) -> None:
    await camera.open()  # type: ignore[attr-defined]
    try:
        await link.open(server.on_trigger)  # type: ignore[attr-defined]
        try:
            await server.serve()
        finally:
            await link.close()  # type: ignore[attr-defined]
    finally:
        await camera.close()  # type: ignore[attr-defined]


def run_walk(args: argparse.Namespace) -> int:
    if args.running is not None:
        from vgripd.cli.calibrate_handeye_running import run_running

        return run_running(args)
    if args.config is None or args.plan is None:
        raise CalibrationError("calibrate handeye walk: give -c CONFIG and --plan PLAN")
    config = load_config(args.config, redo="hand_eye")
    for warning in config.load_warnings:  # what this command measures again
        print(f"warning: {warning}", file=sys.stderr)
    if config.calibration is None:
        raise CalibrationError(f"{args.config}: no [calibration]: calibrate the camera first")
    if not 0 <= args.link < len(config.links):
        raise CalibrationError(f"--link {args.link}: {args.config} has {len(config.links)} "
                               "[[links]]")
    plan = load_plan(args.plan)
    left = config.calibration.left
    camera_model = CameraModel(left.fx, left.fy, left.cx, left.cy, left.skew, left.dist,
                               left.width, left.height)
    walk_path = args.walk or str(Path(args.plan).with_suffix(".walk.json"))
    walk = Walk(walk_path, plan, Board.parse(plan.board), camera_model)
    cam_cls = load_class(CAMERAS, "camera", config.camera.type)
    camera = cam_cls(validate_options(cam_cls, config.camera, "camera"), config)
    section = config.links[args.link]
    link_cls = load_class(LINKS, "link", section.type)
    link = link_cls(f"walk{args.link}", validate_options(link_cls, section,
                                                         f"links.{args.link}"))

    async def grab() -> np.ndarray:
        pair = await camera.grab(config.daemon.job_timeout_s)
        return np.asarray(pair.left)

    refusal = walk_refusal(link, f"links.{args.link}")
    if refusal is not None:
        raise CalibrationError(f"{args.config}: {refusal}")
    server = WalkServer(walk, link, grab, config.output.vendor)
    start = walk.next_index()
    print(f"walk {walk_path}: {len(plan.poses)} targets, "
          + ("complete already" if start is None else f"from target {start}")
          + f"; waiting for the robot program on links.{args.link} ({section.type})")
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(_walk(server, camera, link))
    seen = len(walk.samples())
    print(f"walk {walk_path}: {seen} images with the board, {len(walk.skipped())} skipped"
          + ("" if walk.next_index() is None else
             f", stopped before target {walk.next_index()} (run again to resume)"))
    print(f"solve: vgripd calibrate handeye --samples {walk_path} --intrinsics {args.config} "
          "-o handeye.toml")
    return 0
