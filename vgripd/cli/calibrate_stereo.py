"""vgripd calibrate stereo: both cameras and the left -> right transform from board image pairs.

``--left`` and ``--right`` are globs (quote them); the i-th left image (sorted by name, numbers
by value: img2 before img10) pairs with the i-th right image, so both globs must match the same
number of files. Pairs where the board is found in only one image are left out (saying why).
Before the joint fit, pairs whose left and right board poses do not fit one rigid rig (shifted
pairs, unsynchronised images, globs sorting differently) are refused, naming them. The rig is
fitted as Bouguet's "global stereo optimisation" (both intrinsics, om, T, the board poses; see
``vgripd.calib.rig``), with the distortion model (k3, p1 p2; one for both cameras) chosen from
the data unless ``--fix-k3``/``--free-k3``, ``--fix-tangential``/``--free-tangential`` say;
outlier pairs are dropped, and ``[calibration.left]``, ``[calibration.right]`` and
``[calibration.stereo.T_right_left]`` (``X_R = R X_L + T``, mm) are written to ``-o`` for a
config's ``include``, with the model choice in ``[about.model_choice]``. See
docs/calibration-stereo.md.
"""

from __future__ import annotations

import argparse
import glob
import os
import shlex
from typing import Any

import cv2
import numpy as np

from vgripd.calib.boards import Board, Detection, detect_files
from vgripd.calib.files import pose_table, write_result
from vgripd.calib.intrinsics import DIST_NAMES, empty_regions
from vgripd.calib.output import add_output_arguments, emit
from vgripd.calib.rig import RigResult, calibrate_rig
from vgripd.cli.calibrate_intrinsics import add_model_arguments, model_words
from vgripd.errors import CalibrationError
from vgripd.imagefiles import natural_key


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--left", required=True, metavar="GLOB",
                        help="left board images, e.g. 'calib/left*.png' (quote it)")
    parser.add_argument("--right", required=True, metavar="GLOB",
                        help="right board images, same count, paired by sorted name")
    parser.add_argument("--board", required=True, metavar="SPEC",
                        help="chessboard:COLSxROWS:SQUARE_MM (inner corners), circles:..., "
                             "acircles:..., charuco:COLSxROWS:SQUARE_MM:MARKER_MM[:DICT]")
    add_model_arguments(parser)
    parser.add_argument("--baseline-mm", type=float, default=None, metavar="MM",
                        help="expected distance between the cameras; warn if off by > 5%%")
    parser.add_argument("--subpix-window", type=int, default=None, metavar="N",
                        help="cornerSubPix half-window in px (default: from the corner spacing)")
    add_output_arguments(parser, "rig.toml")


def _paths(pattern: str, option: str) -> list[str]:
    paths = sorted(glob.glob(os.path.expanduser(pattern), recursive=True), key=natural_key)
    if not paths:
        raise CalibrationError(f"{option} {pattern!r}: no file matches (relative to "
                               f"{os.getcwd()})")
    return paths


def _command(args: argparse.Namespace) -> str:
    words = ["vgripd", "calibrate", "stereo", "--left", args.left, "--right", args.right,
             "--board", args.board, *model_words(args)]
    if args.baseline_mm is not None:
        words += ["--baseline-mm", repr(args.baseline_mm)]
    if args.subpix_window is not None:
        words += ["--subpix-window", str(args.subpix_window)]
    return shlex.join([*words, "-o", args.output])


def pair_detections(left_paths: list[str], right_paths: list[str], found: list[Detection],
                    failed: list[tuple[str, str]]) -> tuple[list[tuple[Detection, Detection]],
                                                            list[dict[str, str]]]:
    """Pairs where the board is found in both images, and the others with the reason.

    ``found``/``failed`` are ``detect_files`` results over both sides. For boards that may be
    seen in part (ChArUco) only the points found in both images are kept.
    """
    by_name = {d.image: d for d in found}
    why = dict(failed)
    pairs, rejected = [], []
    for lp, rp in zip(left_paths, right_paths, strict=True):
        dl, dr = by_name.get(lp), by_name.get(rp)
        if dl is None or dr is None:
            reasons = [f"{side} image: {why.get(p, 'board not found')}"
                       for side, p, d in (("left", lp, dl), ("right", rp, dr)) if d is None]
            rejected.append({"left": lp, "right": rp, "reason": "; ".join(reasons)})
            continue
        common = np.intersect1d(dl.ids, dr.ids)
        if len(common) < 6:
            rejected.append({"left": lp, "right": rp,
                             "reason": f"only {len(common)} board points seen in both images"})
            continue
        if len(common) < max(len(dl.ids), len(dr.ids)):
            dl, dr = _subset(dl, common), _subset(dr, common)
        pairs.append((dl, dr))
    return pairs, rejected


def _subset(d: Detection, ids: np.ndarray) -> Detection:
    keep = np.isin(d.ids, ids)
    return Detection(d.image, d.size, d.ids[keep], d.px[keep])


def run(args: argparse.Namespace) -> int:
    board = Board.parse(args.board)
    if args.subpix_window is not None and args.subpix_window < 1:
        raise CalibrationError(f"--subpix-window {args.subpix_window}: must be at least 1 px")
    if args.baseline_mm is not None and not args.baseline_mm > 0:
        raise CalibrationError(f"--baseline-mm {args.baseline_mm}: must be > 0")
    left_paths, right_paths = _paths(args.left, "--left"), _paths(args.right, "--right")
    if len(left_paths) != len(right_paths):
        raise CalibrationError(
            f"--left matches {len(left_paths)} files but --right matches {len(right_paths)}: "
            f"images are paired by sorted name, so the counts must agree (left: "
            f"{left_paths[0]} ... {left_paths[-1]}; right: {right_paths[0]} ... "
            f"{right_paths[-1]})")
    found_l, failed_l = detect_files(board, left_paths, args.subpix_window)
    found_r, failed_r = detect_files(board, right_paths, args.subpix_window)
    pairs, not_paired = pair_detections(left_paths, right_paths, found_l + found_r,
                                        failed_l + failed_r)
    if len(pairs) < 3:
        why = "; ".join(f"{r['left']} / {r['right']}: {r['reason']}" for r in not_paired[:5])
        raise CalibrationError(f"board {board.spec} found in both images of {len(pairs)} of "
                               f"{len(left_paths)} pairs (need at least 3): {why}")
    obj = board.object_points()
    result = calibrate_rig([obj[dl.ids] for dl, _ in pairs], [dl.px for dl, _ in pairs],
                           [dr.px for _, dr in pairs], pairs[0][0].size, pairs[0][1].size,
                           names=[(dl.image, dr.image) for dl, dr in pairs], fix_k3=args.fix_k3,
                           fix_tangential=args.fix_tangential, baseline_hint_mm=args.baseline_mm)
    rejected = not_paired + result.rejected
    warnings = [w for w in [board.symmetry_warning()] if w] + list(result.warnings)
    used = set(result.names)
    for side, k in (("left", 0), ("right", 1)):
        dets = [pair[k] for pair in pairs if (pair[0].image, pair[1].image) in used]
        empty = empty_regions(dets, dets[0].size)
        if empty:
            warnings.append(f"{side} camera: no board point in the image's " + ", ".join(empty)
                            + " (3x3 grid): distortion there is extrapolated")
    summary = _summary(result, rejected, warnings, args)
    about = {
        "command": _command(args), "board": board.spec, "opencv": cv2.__version__,
        "model": f"pinhole fx fy cx cy, skew 0, dist {result.model.model.name} (others 0), "
                 "both cameras; X_R = R(rotvec) X_L + T, mm",
        "model_choice": result.model.summary(),
        "rms_px": result.rms_px, "pairs_used": len(result.names),
        "std": {"left": result.left_std, "right": result.right_std,
                "rotvec_rad": result.rotvec_std, "translation_mm": result.translation_std},
        "epipolar_px": result.epipolar_px, "per_pair": result.per_pair, "rejected": rejected,
        "warnings": warnings}
    sections = {"calibration": {"left": result.left, "right": result.right,
                                "stereo": {"T_right_left": pose_table(result.T_right_left)}}}
    write_result(args.output, sections, about,
                 header="stereo rig (both cameras, left->right): include this file from a "
                        "config.\n[about] (provenance, std = 1 sigma) is ignored by the loader.")
    lines = _human(result, rejected, args)
    if args.report:
        from vgripd.calib.report import ImageResiduals, write_report

        images = [ImageResiduals(name, px, res) for names, pl, pr, rl, rr in zip(
            result.names, result.px_left, result.px_right, result.residuals_left_px,
            result.residuals_right_px, strict=True)
            for name, px, res in ((names[0], pl, rl), (names[1], pr, rr))]
        write_report(args.report, f"vgripd calibrate stereo  {board.spec}",
                     (result.left["width"], result.left["height"]), images,
                     lines=_parameter_lines(result) + [
                         f"model {result.model.model.name}: {result.model.reason}"] + [
                         f"rejected: {r['left']} / {r['right']}: {r['reason']}"
                         for r in rejected])
        summary["report"] = str(args.report)
        lines.append(f"report: {args.report}")
    emit(args, summary, lines)
    return 0


def _summary(r: RigResult, rejected: list[dict[str, str]], warnings: list[str],
             args: argparse.Namespace) -> dict[str, Any]:
    return {"left": r.left, "right": r.right, "left_std": r.left_std, "right_std": r.right_std,
            "rotvec_rad": r.rotvec_rad, "translation_mm": r.translation_mm,
            "rotvec_std": r.rotvec_std, "translation_std": r.translation_std,
            "std_model": r.std_model, "rms_px": r.rms_px, "model": r.model.summary(),
            "per_pair": [{k: p[k] for k in ("left", "right", "rms_px")} for p in r.per_pair],
            "epipolar_px": r.epipolar_px, "rejected": rejected, "warnings": warnings,
            "output": str(args.output)}


def _parameter_lines(r: RigResult) -> list[str]:
    out = []
    for side, cam, std in (("left", r.left, r.left_std), ("right", r.right, r.right_std)):
        out.append(f"{side}:")
        out += [f"  {k:5s} {cam[k]:10.3f} +- {std[k]:.3f} px" for k in ("fx", "fy", "cx", "cy")]
        out += [f"  {name:5s} {v:10.5f} +- {s:.5f}"
                for name, v, s in zip(DIST_NAMES, cam["dist"], std["dist"], strict=True)]
    out.append("rotvec rad  " + "  ".join(f"{v:.5f} +- {s:.5f}" for v, s in
                                          zip(r.rotvec_rad, r.rotvec_std, strict=True)))
    out.append("T mm        " + "  ".join(f"{v:.3f} +- {s:.3f}" for v, s in
                                          zip(r.translation_mm, r.translation_std, strict=True)))
    e = r.epipolar_px
    out.append(f"RMS {r.rms_px:.3f} px over {len(r.names)} pairs; epipolar px median "
               f"{e['median']:.3f}, 95% {e['p95']:.3f}, max {e['max']:.3f}")
    return out


def _human(r: RigResult, rejected: list[dict[str, str]], args: argparse.Namespace) -> list[str]:
    wl = max(len(p["left"]) for p in r.per_pair)
    wr = max(len(p["right"]) for p in r.per_pair)
    lines = [f"{'left':{wl}s}  {'right':{wr}s}  RMS px"]
    lines += [f"{p['left']:{wl}s}  {p['right']:{wr}s}  {p['rms_px']:6.3f}" for p in r.per_pair]
    lines.append("")
    lines.append(f"stereo rig, X_R = R(rotvec) X_L + T, baseline "
                 f"{float(np.linalg.norm(r.translation_mm)):.2f} mm, +- = 1 sigma, covering the "
                 f"distortion terms the model leaves out:")
    lines += ["  " + line for line in _parameter_lines(r)]
    choice = r.model
    lines.append(f"distortion model, both cameras: {choice.model.name} (chosen by "
                 f"{choice.chosen_by}: {choice.reason})")
    lines += choice.table((("left ", "dist"), ("right ", "right_dist")))
    lines += [f"note: {n}" for n in choice.notes]
    if rejected:
        lines.append(f"rejected {len(rejected)} pair(s):")
        lines += [f"  {x['left']} / {x['right']}: {x['reason']}" for x in rejected]
    lines.append(f"written: {args.output}")
    return lines
