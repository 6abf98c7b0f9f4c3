"""vgripd calibrate handeye plan: the flange poses of a walked hand-eye calibration.

``--around "X Y Z A B C"`` is the start pose (flange in base, in ``--pose-format``, default
the config's ``output.vendor``) where the camera sees the board's centre squarely at
``--distance`` mm; ``--box "TRAVEL_MM TILT_DEG"`` bounds how far the flange may move from it and
how far it may turn. The plan keeps the board inside the image at a size the detector handles,
spreads the rotation axes, reports its condition figure and is refused (exit 1, nothing
written) when its rotations are too small or nearly parallel. ``--dry-run`` prints the poses in
the robot's convention and writes nothing. Motion stays in the robot program: the plan is only
a list of targets (docs/calibration-handeye.md, "Walked calibration").
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
from typing import Any

from vgripd.calib.boards import Board
from vgripd.calib.files import dumps
from vgripd.calib.handeye.plan import (
    MAX_CONDITION,
    board_size_problem,
    draw_plan,
    plan_data,
    plan_hand_eye,
)
from vgripd.calib.output import emit
from vgripd.config import load_config
from vgripd.errors import CalibrationError, ConversionError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.fingerprint import camera_about
from vgripd.geometry.vendors import convention, transform_from_vendor, vendor_from_transform
from vgripd.vision.scene import matrix_from_pose

DEFAULT_PLAN = "handeye-plan.toml"


def add_plan_arguments(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("plan (vgripd calibrate handeye plan ...)")
    g.add_argument("-c", "--config", metavar="TOML",
                   help="the cell's config: camera model, rough hand-eye, robot convention")
    g.add_argument("--around", metavar='"X Y Z A B C"',
                   help="start pose of the flange in the base frame (in --pose-format)")
    g.add_argument("--box", metavar='"TRAVEL_MM TILT_DEG"',
                   help="how far the flange may move from the start (mm) and turn (deg)")
    g.add_argument("--distance", type=float, metavar="MM",
                   help="camera to board centre at the start pose, mm")
    g.add_argument("--count", type=int, default=15, metavar="N",
                   help="number of poses, 12-30 (default 15)")
    g.add_argument("--board-offset", metavar='"X Y Z"', default="0 0 0",
                   help="eye-to-hand: the board's centre in the flange frame, mm (default 0)")
    g.add_argument("--dry-run", action="store_true",
                   help="print the plan in the robot's convention, write nothing")
    g.add_argument("--draw", metavar="PNG",
                   help="draw each pose's board outline in the image (also with --dry-run)")


def _numbers(text: str, count: int, flag: str) -> list[float]:
    words = text.replace(",", " ").split()
    try:
        values = [float(w) for w in words]
    except ValueError:
        raise CalibrationError(f"{flag} {text!r}: not numbers") from None
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise CalibrationError(f"{flag} {text!r}: expected {count} finite numbers")
    return values


def run_plan(args: argparse.Namespace) -> int:
    missing = [f for f, v in (("-c", args.config), ("--mode", args.mode), ("--board", args.board),
                              ("--around", args.around), ("--box", args.box),
                              ("--distance", args.distance)) if v is None]
    if missing:
        raise CalibrationError(f"calibrate handeye plan: missing {', '.join(missing)}")
    config = load_config(args.config, redo="hand_eye")
    for warning in config.load_warnings:  # what this command measures again
        print(f"warning: {warning}", file=sys.stderr)
    if config.calibration is None:
        raise CalibrationError(f"{args.config}: no [calibration]: calibrate the camera first "
                               "(the order is: cameras/rig -> hand-eye -> teach)")
    left = config.calibration.left
    camera = CameraModel(left.fx, left.fy, left.cx, left.cy, left.skew, left.dist, left.width,
                         left.height)
    pose_format = args.pose_format or config.output.vendor
    try:
        convention(pose_format)
        T_start = transform_from_vendor(pose_format, args.around.replace(",", " ").split())
    except ConversionError as err:
        raise CalibrationError(f"--around: {err}") from None
    travel, tilt = _numbers(args.box, 2, "--box")
    board = Board.parse(args.board)
    problem = board_size_problem(board.cols, board.rows, board.pitch_mm, args.distance,
                                 camera.width, camera.height, camera.fx, camera.fy)
    if problem:
        raise CalibrationError(problem)
    he = config.calibration.hand_eye
    X_guess = None
    if args.mode == "eye-in-hand" and he.mounting == "robot" and he.T_flange_camera:
        X_guess = matrix_from_pose(he.T_flange_camera)
    elif args.mode == "eye-to-hand" and he.mounting == "fixed" and he.T_base_camera:
        X_guess = matrix_from_pose(he.T_base_camera)
    plan = plan_hand_eye(args.mode, T_start, camera, board.object_points(), board.cols,
                         distance_mm=args.distance, travel_mm=travel, tilt_deg=tilt,
                         n=args.count, X_guess=X_guess,
                         board_offset_mm=_numbers(args.board_offset, 3, "--board-offset"))
    c = plan.condition
    problems = c.problems()
    warnings = [w for w in [board.symmetry_warning()] if w]
    output = None if args.dry_run else (DEFAULT_PLAN if args.output == "handeye.toml"
                                        else args.output)
    calibration = config.calibration.model_dump(mode="json")
    about = {"command": _command(args), "config": str(args.config), **camera_about(calibration)}
    data = plan_data(plan, board.spec, pose_format, about)
    fields = " ".join(convention(pose_format).fields)
    lines = [f"hand-eye plan ({args.mode}), {len(plan.poses)} poses in {pose_format} ({fields})"]
    for k, (T, v) in enumerate(zip(plan.poses, plan.views, strict=True)):
        numbers = " ".join(f"{x:.4f}" for x in vendor_from_transform(pose_format, T))
        lines.append(f"  {k:2d}  {numbers}   # board {v.board_px[0]:.0f}..{v.board_px[2]:.0f} x "
                     f"{v.board_px[1]:.0f}..{v.board_px[3]:.0f} px, corners {v.spacing_px:.0f} px "
                     "apart")
    lines.append(f"condition {c.condition:.3g} (1 is ideal, limit {MAX_CONDITION:g}), "
                 f"effective rotation {c.effective_deg:.1f} deg between poses")
    summary: dict[str, Any] = {"mode": args.mode, "pose_format": pose_format,
                               "poses": data["poses"], "condition": data["plan"]["condition"],
                               "refused": problems, "warnings": warnings, "output": output}
    if args.draw:
        draw_plan(args.draw, plan, camera, f"{args.mode}")
        lines.append(f"drawn: {args.draw}")
        summary["drawing"] = args.draw
    if problems:
        emit(args, summary, lines)
        raise CalibrationError("calibrate handeye plan: refused: " + "; ".join(problems))
    if output is not None:
        from pathlib import Path

        Path(output).write_text(dumps(data, "vgripd hand-eye plan: the robot program visits "
                                            "these flange poses.\nCheck them in a dry run first "
                                            "(speed, box, collisions)."), encoding="utf-8")
        lines.append(f"written: {output}")
    else:
        lines.append("dry run: nothing written; check every pose for collisions before a walk")
    emit(args, summary, lines)
    return 0


def _command(args: argparse.Namespace) -> str:
    words = ["vgripd", "calibrate", "handeye", "plan", "--mode", args.mode, "-c", args.config,
             "--board", args.board, "--around", args.around, "--box", args.box,
             "--distance", str(args.distance), "--count", str(args.count)]
    if args.pose_format:
        words += ["--pose-format", args.pose_format]
    return shlex.join(words)
