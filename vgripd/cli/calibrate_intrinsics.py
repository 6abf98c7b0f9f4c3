"""vgripd calibrate intrinsics: one camera from images of a calibration board.

Finds the board in every image matching ``--images`` (a glob, relative to the current
directory), calibrates the camera (pinhole + Brown distortion; whether k3 and the tangential
p1 p2 are estimated is chosen from the data by BIC unless ``--fix-k3``/``--free-k3``,
``--fix-tangential``/``--free-tangential`` say), drops images where the board is not found or
whose reprojection error is an outlier (saying why), and writes ``[calibration.left]`` (or
``.right``) to ``-o`` for a config's ``include``; the chosen model, why, and every candidate's
RMS, BIC and k2/k3 go to the output and to ``[about.model_choice]``. See
docs/calibration-intrinsics.md.
"""

from __future__ import annotations

import argparse
import glob
import os
import shlex
from typing import Any

import cv2

from vgripd.calib.boards import Board, detect_files
from vgripd.calib.files import write_result
from vgripd.calib.intrinsics import (
    DIST_NAMES,
    IntrinsicsResult,
    ModelChoice,
    calibrate_intrinsics,
)
from vgripd.calib.output import add_output_arguments, emit
from vgripd.errors import CalibrationError
from vgripd.imagefiles import natural_key


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--images", required=True, metavar="GLOB",
                        help="board images, e.g. 'calib/left*.png' (quote it)")
    parser.add_argument("--board", required=True, metavar="SPEC",
                        help="chessboard:COLSxROWS:SQUARE_MM (inner corners), circles:..., "
                             "acircles:..., charuco:COLSxROWS:SQUARE_MM:MARKER_MM[:DICT]")
    parser.add_argument("--camera", choices=("left", "right"), default="left",
                        help="which [calibration.*] section to write (default left)")
    add_model_arguments(parser)
    parser.add_argument("--subpix-window", type=int, default=None, metavar="N",
                        help="cornerSubPix half-window in px (window 2N+1; default: 35%% of the "
                             "corner spacing in each image)")
    add_output_arguments(parser, "camera.toml")


def add_model_arguments(parser: argparse.ArgumentParser) -> None:
    """``--fix-k3``/``--free-k3`` and ``--fix-tangential``/``--free-tangential`` (default:
    chosen from the data); shared with ``calibrate stereo``."""
    k3 = parser.add_mutually_exclusive_group()
    k3.add_argument("--fix-k3", dest="fix_k3", action="store_const", const=True, default=None,
                    help="hold the 6th-order radial term k3 at 0 (Bouguet's toolbox default) "
                         "instead of choosing from the data")
    k3.add_argument("--free-k3", dest="fix_k3", action="store_const", const=False,
                    help="always estimate k3 (wide-angle lenses)")
    tangential = parser.add_mutually_exclusive_group()
    tangential.add_argument("--fix-tangential", dest="fix_tangential", action="store_const",
                            const=True, default=None, help="hold p1 and p2 at 0")
    tangential.add_argument("--free-tangential", dest="fix_tangential", action="store_const",
                            const=False, help="always estimate p1 and p2 (the toolbox default)")


def model_words(args: argparse.Namespace) -> list[str]:
    """The model options as given, for the command line written to [about]."""
    words = []
    if args.fix_k3 is not None:
        words.append("--fix-k3" if args.fix_k3 else "--free-k3")
    if args.fix_tangential is not None:
        words.append("--fix-tangential" if args.fix_tangential else "--free-tangential")
    return words


def model_lines(choice: ModelChoice) -> list[str]:
    """Human lines: the chosen model, why, the candidates."""
    return [f"distortion model: {choice.model.name} (chosen by {choice.chosen_by}: "
            f"{choice.reason})", *choice.table(), *(f"note: {n}" for n in choice.notes)]


def _command(args: argparse.Namespace) -> str:
    words = ["vgripd", "calibrate", "intrinsics", "--images", args.images, "--board", args.board,
             "--camera", args.camera, *model_words(args)]
    if args.subpix_window is not None:
        words += ["--subpix-window", str(args.subpix_window)]
    return shlex.join([*words, "-o", args.output])


def run(args: argparse.Namespace) -> int:
    board = Board.parse(args.board)
    if args.subpix_window is not None and args.subpix_window < 1:
        raise CalibrationError(f"--subpix-window {args.subpix_window}: must be at least 1 px")
    paths = sorted(glob.glob(os.path.expanduser(args.images), recursive=True), key=natural_key)
    if not paths:
        raise CalibrationError(f"--images {args.images!r}: no file matches (relative to "
                               f"{os.getcwd()})")
    found, failed = detect_files(board, paths, args.subpix_window)
    not_found = [{"image": name, "reason": reason} for name, reason in failed]
    if len(found) < 3:
        why = "; ".join(f"{r['image']}: {r['reason']}" for r in not_found[:5])
        raise CalibrationError(f"board {board.spec} found in {len(found)} of {len(paths)} images "
                               f"(need at least 3): {why}")
    size = found[0].size
    result = calibrate_intrinsics(board, found, size, fix_k3=args.fix_k3,
                                  fix_tangential=args.fix_tangential)
    rejected = not_found + result.rejected
    summary: dict[str, Any] = {
        "camera": result.camera, "std": result.std, "std_model": result.std_model,
        "rms_px": result.rms_px,
        "model": result.model.summary(), "per_image": result.per_image, "rejected": rejected,
        "warnings": result.warnings, "output": str(args.output)}
    about = {
        "command": _command(args), "board": board.spec, "opencv": cv2.__version__,
        "model": f"pinhole fx fy cx cy, skew 0, dist {result.model.model.name} (others 0)",
        "model_choice": result.model.summary(),
        "subpix_window": "auto" if args.subpix_window is None else args.subpix_window,
        "rms_px": result.rms_px, "std": result.std, "std_model": result.std_model,
        "richest": _richest_table(result),
        "images_used": len(result.detections),
        "per_image": result.per_image, "rejected": rejected, "warnings": result.warnings}
    write_result(args.output, {"calibration": {args.camera: result.camera}}, about,
                 header=f"{args.camera} camera intrinsics: include this file from a config.\n"
                        "[about] (provenance, std = 1 sigma) is ignored by the loader.")
    lines = _human(result, rejected, args)
    if args.report:
        from vgripd.calib.report import ImageResiduals, write_report

        images = [ImageResiduals(d.image, d.px, r)
                  for d, r in zip(result.detections, result.residuals_px, strict=True)]
        write_report(args.report, f"vgripd calibrate intrinsics  {board.spec}  ({args.camera})",
                     size, images, lines=_parameter_lines(result) + [
                         f"model {result.model.model.name}: {result.model.reason}"] + [
                         f"rejected: {r['image']}: {r['reason']}" for r in rejected])
        summary["report"] = str(args.report)
        lines.append(f"report: {args.report}")
    emit(args, summary, lines)
    return 0


def _richest_table(result: IntrinsicsResult) -> dict[str, Any]:
    """The richest model's estimate and 9x9 covariance (fx fy cx cy k1 k2 p1 p2 k3), which
    ``calibrate cameras --intrinsics`` carries into its pose sigmas."""
    rich = result.richest or {}
    return {"model": rich.get("model", ""), "values": list(rich.get("values", [])),
            "covariance": [[float(v) for v in row] for row in rich.get("covariance", [])]}


def _parameter_lines(result: IntrinsicsResult) -> list[str]:
    cam, std = result.camera, result.std
    out = [f"{k:5s} {cam[k]:10.3f} +- {std[k]:.3f} px" for k in ("fx", "fy", "cx", "cy")]
    out += [f"{name:5s} {v:10.5f} +- {s:.5f}"
            for name, v, s in zip(DIST_NAMES, cam["dist"], std["dist"], strict=True)]
    out.append(f"RMS   {result.rms_px:10.3f} px over {len(result.detections)} images")
    return out


def _human(result: IntrinsicsResult, rejected: list[dict[str, str]],
           args: argparse.Namespace) -> list[str]:
    width = max(len(p["image"]) for p in result.per_image)
    lines = [f"{'image':{width}s}  RMS px  points"]
    lines += [f"{p['image']:{width}s}  {p['rms_px']:6.3f}  {p['points']:6d}"
              for p in result.per_image]
    lines.append("")
    lines.append(f"{args.camera} camera, {result.camera['width']}x{result.camera['height']}, "
                 "+- = 1 sigma, covering the distortion terms the model leaves out:")
    lines += ["  " + line for line in _parameter_lines(result)]
    lines += model_lines(result.model)
    if rejected:
        lines.append(f"rejected {len(rejected)} image(s):")
        lines += [f"  {r['image']}: {r['reason']}" for r in rejected]
    lines.append(f"written: {args.output}")
    return lines
