"""vgripd calibrate handeye: the camera's pose on the robot flange (eye-in-hand) or in the robot
base frame (eye-to-hand), from robot poses and images of a calibration board.

``--poses`` is a text file with one flange pose (base frame) per line, in the order of the
images (``--images`` glob sorted by name, numbers by value: img2 before img10), written in
``--pose-format``'s field order and units as ``vgripd convert`` knows them (kuka: X Y Z mm,
A B C deg; ur: x y z m, rx ry rz rad; matrix: 16 numbers row-major, mm; ...). ``#`` starts a
comment. The samples (robot poses and detected corners) are saved beside the output as
``<output stem>.samples.json`` (or ``--save-samples``); ``--samples FILE`` solves again from
such a file without robot or images. See docs/calibration-handeye.md.
"""

from __future__ import annotations

import argparse
import glob
import os
import re
import shlex
import sys
from pathlib import Path
from typing import Any

import numpy as np

from vgripd.calib.boards import Board, detect_files
from vgripd.calib.files import pose_table, write_result
from vgripd.calib.handeye import (
    MODES,
    OBJECTIVES,
    HandEyeResult,
    Sample,
    calibrate_hand_eye,
    load_samples,
    read_poses,
    save_samples,
)
from vgripd.calib.output import add_output_arguments, emit
from vgripd.config import IntrinsicsConfig, read_config_data
from vgripd.errors import CalibrationError, ConfigError, DegenerateInputError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.vendors import VENDORS
from vgripd.imagefiles import natural_key

EXIT_USAGE = 2


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--mode", choices=MODES, default=None,
                        help="eye-in-hand: camera on the flange, board fixed; eye-to-hand: "
                             "camera fixed, board on the flange (with --samples: from the file)")
    parser.add_argument("--poses", metavar="FILE",
                        help="robot flange poses in the base frame, one per line, image order")
    parser.add_argument("--pose-format", default=None, metavar="VENDOR",
                        help=f"convention of --poses: {', '.join(VENDORS)}")
    parser.add_argument("--images", metavar="GLOB", help="board images, e.g. 'he/*.png' (quote)")
    parser.add_argument("--board", metavar="SPEC",
                        help="chessboard:COLSxROWS:SQUARE_MM (inner corners), circles:..., "
                             "acircles:..., charuco:...")
    parser.add_argument("--intrinsics", metavar="TOML",
                        help="camera intrinsics: a result of 'calibrate intrinsics' or a config "
                             "with [calibration.left] (with --samples: overrides the file's)")
    parser.add_argument("--samples", metavar="JSON",
                        help="solve from a saved samples file instead of --poses/--images")
    parser.add_argument("--save-samples", metavar="JSON",
                        help="where to save the samples (default <output stem>.samples.json)")
    parser.add_argument("--exclude", metavar="N[,N...]",
                        help="leave out these samples (numbers as in the per-sample table, "
                             "i.e. positions in the samples file, from 0), e.g. an outlier")
    parser.add_argument("--min-rotation-deg", type=float, default=5.0, metavar="DEG",
                        help="warn about consecutive samples rotating less (default 5)")
    parser.add_argument("--objective", choices=OBJECTIVES, default="auto",
                        help="what the refinement minimises: likelihood (board poses weighted "
                             "by their pixel noise plus an estimated robot pose noise), pixels "
                             "(reprojection, robot taken as exact), poses (board-pose residuals,"
                             " unweighted), none (best linear solver), auto (likelihood with "
                             "board corners, poses without; default)")
    add_output_arguments(parser, "handeye.toml")


def read_intrinsics(path: str) -> CameraModel:
    """``[calibration.left]`` of a result file or config (includes followed) as a camera."""
    try:
        data = read_config_data(path)
        left = data.get("calibration", {}).get("left")
        if left is None:
            raise CalibrationError(f"{path}: no [calibration.left] intrinsics")
        cfg = IntrinsicsConfig.model_validate(left)
        return CameraModel(cfg.fx, cfg.fy, cfg.cx, cfg.cy, cfg.skew, cfg.dist, cfg.width,
                           cfg.height)
    except ConfigError as err:
        raise CalibrationError(f"--intrinsics: {err}") from None
    except ValueError as err:  # pydantic's ValidationError
        raise CalibrationError(f"{path}: calibration.left: {err}") from None


def _samples_from_robot(args: argparse.Namespace, camera: CameraModel,
                        ) -> tuple[list[Sample], list[dict[str, str]]]:
    board = Board.parse(args.board)
    poses = read_poses(args.poses, args.pose_format)
    paths = sorted(glob.glob(os.path.expanduser(args.images), recursive=True), key=natural_key)
    if not paths:
        raise CalibrationError(f"--images {args.images!r}: no file matches (relative to "
                               f"{os.getcwd()})")
    if len(paths) != len(poses):
        raise CalibrationError(
            f"{args.poses} has {len(poses)} poses but --images matches {len(paths)} images "
            f"({paths[0]} ... {paths[-1]}); give one pose per image, in image order")
    found, failed = detect_files(board, paths)
    by_name = {d.image: d for d in found}
    points = board.object_points()
    samples = []
    for path, T in zip(paths, poses, strict=True):
        d = by_name.get(path)
        if d is None:
            continue
        if camera.width and (camera.width, camera.height) != d.size:
            raise CalibrationError(
                f"{path}: image is {d.size[0]}x{d.size[1]} but the intrinsics are for "
                f"{camera.width}x{camera.height}")
        samples.append(Sample(T, None, path, points[d.ids], d.px))
    return samples, [{"image": name, "reason": reason} for name, reason in failed]


def _command(args: argparse.Namespace) -> str:
    words = ["vgripd", "calibrate", "handeye"]
    for flag in ("mode", "poses", "pose_format", "images", "board", "intrinsics", "samples",
                 "exclude", "objective"):
        value = getattr(args, flag)
        if value is not None:
            words += [f"--{flag.replace('_', '-')}", str(value)]
    return shlex.join([*words, "-o", args.output])


def run(args: argparse.Namespace) -> int:
    camera = read_intrinsics(args.intrinsics) if args.intrinsics else None
    rejected: list[dict[str, str]] = []
    if args.samples:
        mode, board, saved_camera, samples = load_samples(args.samples)
        if args.mode is not None and args.mode != mode:
            raise CalibrationError(f"--mode {args.mode} but {args.samples} holds {mode} samples")
        camera = saved_camera if camera is None else camera
        samples_file = args.save_samples
    else:
        missing = [f"--{n.replace('_', '-')}" for n in
                   ("mode", "poses", "pose_format", "images", "board", "intrinsics")
                   if getattr(args, n) is None]
        if missing:
            print(f"vgripd calibrate handeye: missing {', '.join(missing)} (or give --samples)",
                  file=sys.stderr)
            return EXIT_USAGE
        assert camera is not None
        mode, board = args.mode, Board.parse(args.board).spec
        samples, rejected = _samples_from_robot(args, camera)
        samples_file = args.save_samples or str(
            Path(args.output).with_name(Path(args.output).stem + ".samples.json"))
    if samples_file:
        save_samples(samples_file, samples, mode, board, camera)
    for k, s in enumerate(samples):
        s.number = k
    if args.exclude:
        excluded = _parse_exclude(args.exclude, len(samples))
        rejected += [{"image": samples[k].image or f"sample {k}",
                      "reason": "excluded with --exclude"} for k in sorted(excluded)]
        samples = [s for k, s in enumerate(samples) if k not in excluded]
    if any(s.T_cam_board is None for s in samples) and camera is None:
        raise CalibrationError("the samples hold board corners: give --intrinsics")
    try:
        result = calibrate_hand_eye(samples, mode, camera,
                                    min_rotation_deg=args.min_rotation_deg,
                                    objective=args.objective)
    except DegenerateInputError as err:
        raise CalibrationError(f"hand-eye: {err}") from None
    warnings = [f"{r['image']}: left out: {r['reason']}" for r in rejected] + result.warnings
    summary = _summary(result, warnings, args.output, samples_file, rejected)
    mounting = "robot" if mode == "eye-in-hand" else "fixed"
    about = {
        "command": _command(args), "mode": mode, "board": board, "solver": result.solver,
        "start": result.start, "samples": len(samples), "samples_file": samples_file or "",
        "rms_px": result.rms_px if result.rms_px is not None else "n/a (board poses only)",
        "noise": summary["noise"],
        result.board_name: pose_table(result.T_anchor_board),
        "stability": summary["stability"] or {}, "per_sample": summary["per_sample"],
        "rejected": rejected, "warnings": warnings}
    write_result(args.output, {"calibration": {"hand_eye": {
        "mounting": mounting, result.transform_name: pose_table(result.T)}}}, _plain(about),
        header=f"hand-eye calibration ({mode}): include this file from a config.\n"
               "[about] (provenance) is ignored by the loader.")
    lines = _human(result, warnings, args.output, samples_file)
    if args.report:
        _report(args.report, result, samples, camera, lines)
        summary["report"] = str(args.report)
        lines.append(f"report: {args.report}")
    emit(args, summary, lines)
    return 0


def _parse_exclude(text: str, n: int) -> set[int]:
    """Sample numbers from ``--exclude`` ("3,7" or "3 7"), each checked against 0..n-1."""
    out = set()
    for word in re.split(r"[,\s]+", text.strip()):
        try:
            k = int(word)
        except ValueError:
            raise CalibrationError(f"--exclude {text!r}: {word!r} is not a sample number") from None
        if not 0 <= k < n:
            raise CalibrationError(f"--exclude {text!r}: sample {k} does not exist (the samples "
                                   f"are numbered 0 to {n - 1})")
        out.add(k)
    return out


def _plain(value: Any) -> Any:
    """Drop None values (TOML has no null)."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items() if v is not None}
    if isinstance(value, list):
        return [_plain(v) for v in value]
    return value


def _summary(result: HandEyeResult, warnings: list[str], output: str, samples_file: str | None,
             rejected: list[dict[str, str]]) -> dict[str, Any]:
    solvers = {}
    for name, sol in result.solvers.items():
        solvers[name] = {"matrix_mm": None if sol.error else sol.T, "rms_px": sol.rms_px,
                         "rotation_deg": None if sol.error else sol.rotation_deg,
                         "translation_mm": None if sol.error else sol.translation_mm,
                         "error": sol.error or None}
    stab = result.stability
    return {
        "mode": result.mode, "matrix_mm": result.T, "transform": result.transform_name,
        "solver": result.solver, "start": result.start, "solvers": solvers,
        "rms_px": result.rms_px, result.board_name: result.T_anchor_board,
        "noise": None if result.robot_sigma is None else {
            "corners_px": result.sigma_px, "robot_deg": result.robot_sigma[0],
            "robot_mm": result.robot_sigma[1]},
        "per_sample": [{"sample": r.sample, "image": r.image, "rms_px": r.rms_px,
                        "rotation_deg": r.rotation_deg, "translation_mm": r.translation_mm,
                        "outlier": r.outlier} for r in result.per_sample],
        "stability": None if stab is None else {
            "rotation_deg": stab.rotation_deg, "translation_mm": stab.translation_mm,
            "rotation_deg_rms": stab.rotation_deg_std,
            "translation_mm_rms": stab.translation_mm_std, "worst_sample": stab.worst_sample},
        "rejected": rejected, "warnings": warnings, "output": str(output),
        "samples_file": samples_file}


def _human(result: HandEyeResult, warnings: list[str], output: str,
           samples_file: str | None) -> list[str]:
    T = result.T
    pose = pose_table(T)
    lines = [f"{result.mode}: {result.transform_name} ({result.solver}, from {result.start})"]
    lines += ["  " + " ".join(f"{v:12.6f}" for v in row) for row in T[:3]]
    lines.append("  translation_mm " + " ".join(f"{v:.3f}" for v in pose["translation_mm"])
                 + "  rotvec_rad " + " ".join(f"{v:.6f}" for v in pose["rotvec_rad"]))
    if result.rms_px is not None:
        lines.append(f"reprojection RMS {result.rms_px:.3f} px over {len(result.per_sample)} "
                     "samples")
    if result.robot_sigma is not None:
        lines.append(f"noise (1 sigma per axis): corners {result.sigma_px:.3f} px, robot poses "
                     f"{result.robot_sigma[0]:g} deg {result.robot_sigma[1]:g} mm (most likely)")
    lines.append("solver       RMS px   rot RMS deg  trans RMS mm")
    for name, sol in result.solvers.items():
        if sol.error:
            lines.append(f"  {name:10s} failed: {sol.error}")
            continue
        rms = "   n/a" if sol.rms_px is None else f"{sol.rms_px:6.3f}"
        lines.append(f"  {name:10s} {rms}   {sol.rotation_deg:10.3f}  {sol.translation_mm:11.2f}")
    lines.append("sample  RMS px   rot deg  trans mm  image")
    for r in result.per_sample:
        rms = "   n/a" if r.rms_px is None else f"{r.rms_px:6.3f}"
        flag = "  OUTLIER" if r.outlier else ""
        lines.append(f"  {r.sample:4d}  {rms}  {r.rotation_deg:7.3f}  {r.translation_mm:8.2f}"
                     f"  {Path(r.image).name}{flag}")
    if result.stability is not None:
        s = result.stability
        lines.append(f"stability (leave one out): up to {s.rotation_deg:.3f} deg, "
                     f"{s.translation_mm:.2f} mm (RMS {s.rotation_deg_std:.3f} deg, "
                     f"{s.translation_mm_std:.2f} mm)")
    if warnings:
        lines.append(f"{len(warnings)} warning(s), see stderr")
    if samples_file:
        lines.append(f"samples: {samples_file}")
    lines.append(f"written: {output}")
    return lines


def _report(path: str, result: HandEyeResult, samples: list[Sample],
            camera: CameraModel | None, lines: list[str]) -> None:
    from vgripd.calib.report import ImageResiduals, write_report

    if not result.residuals_px or camera is None:
        raise CalibrationError("--report needs board corners (the samples hold board poses "
                               "only)")
    images = [ImageResiduals(s.image, np.asarray(s.px), r)
              for s, r in zip(samples, result.residuals_px, strict=True)]
    write_report(path, f"vgripd calibrate handeye  {result.mode}",
                 (camera.width, camera.height), images, lines=lines)
