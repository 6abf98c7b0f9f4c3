"""vgripd calibrate handeye: the camera's pose on the robot flange (eye-in-hand) or in the robot
base frame (eye-to-hand), from robot poses and images of a calibration board.

``--poses`` is a text file with one flange pose (base frame) per line, in the order of the
images (``--images`` glob sorted by name, numbers by value: img2 before img10), written in
``--pose-format``'s field order and units as ``vgripd convert`` knows them (kuka: X Y Z mm,
A B C deg; ur: x y z m, rx ry rz rad; matrix: 16 numbers row-major, mm; ...). ``#`` starts a
comment. The samples (robot poses and detected corners) are saved beside the output as
``<output stem>.samples.json`` (or ``--save-samples``); ``--samples FILE`` solves again from
such a file without robot or images.

A fit whose residuals are far beyond what noise explains (corner noise plus robot poses off by
up to 1 deg / 10 mm per axis) is refused: exit 1, nothing written, the message gives the
residual against the expected one and the likely causes (pose format, units, pose order,
mounting), naming the reading of the input that the data do fit when one does. ``--force``
writes it anyway, with a warning. Exit status: 0 written, 1 calibration failure or refused
fit, 2 missing arguments. See docs/calibration-handeye.md.
"""

from __future__ import annotations

import argparse
import glob
import math
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
    ROBOT_SIGMA_DEG,
    ROBOT_SIGMA_MM,
    HandEyeResult,
    Sample,
    calibrate_hand_eye,
    load_samples,
    read_poses,
    refusal_lines,
    robot_noise_text,
    save_samples,
)
from vgripd.calib.handeye.walk import walk_info
from vgripd.calib.output import add_output_arguments, emit
from vgripd.cli.calibrate_handeye_plan import add_plan_arguments, run_plan
from vgripd.cli.calibrate_handeye_walk import add_walk_arguments, run_walk
from vgripd.config import IntrinsicsConfig, read_config_data
from vgripd.errors import CalibrationError, ConfigError, DegenerateInputError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.fingerprint import camera_about, camera_parts, intrinsics_table
from vgripd.geometry.vendors import VENDORS
from vgripd.imagefiles import natural_key

EXIT_USAGE = 2


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("action", nargs="?", choices=("plan", "walk"), default=None,
                        help="plan: the flange poses of a walked calibration; walk: serve "
                             "them to the robot program and record the images (see below)")
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
    parser.add_argument("--force", action="store_true",
                        help="write the result even when its residuals are far beyond what "
                             "noise explains (it is refused otherwise: exit 1, nothing written)")
    add_output_arguments(parser, "handeye.toml")
    add_plan_arguments(parser)
    add_walk_arguments(parser)


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
    if args.force:
        words.append("--force")
    return shlex.join([*words, "-o", args.output])


def run(args: argparse.Namespace) -> int:
    if args.action == "plan":
        return run_plan(args)
    if args.action == "walk":
        return run_walk(args)
    camera = read_intrinsics(args.intrinsics) if args.intrinsics else None
    rejected: list[dict[str, str]] = []
    walk: dict[str, Any] | None = None
    if args.samples:
        mode, board, saved_camera, samples = load_samples(args.samples)
        if args.mode is not None and args.mode != mode:
            raise CalibrationError(f"--mode {args.mode} but {args.samples} holds {mode} samples")
        camera = saved_camera if camera is None else camera
        samples_file = args.save_samples
        walk = walk_info(args.samples)
        if walk is not None:  # a walked calibration: the targets skipped, the plan's figure
            rejected += [{"image": str(r.get("image") or f"target {r['target']}"),
                          "reason": f"target {r['target']}: {r['status'].replace('_', ' ')}"
                                    + (f": {r['reason']}" if r.get("reason") else "")}
                         for r in walk.get("records", []) if r.get("status") != "seen"]
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
                                    objective=args.objective,
                                    pose_format=None if args.samples else args.pose_format,
                                    refine_refused=args.force)
    except DegenerateInputError as err:
        raise CalibrationError(f"hand-eye: {err}") from None
    check = result.check
    assert check is not None
    refused = not check.ok
    if refused:
        why = refusal_lines(check, mode, None if args.samples else args.pose_format)
        if not args.force:
            kept = f"; the samples are in {samples_file}" if samples_file else ""
            raise CalibrationError("\n  ".join(
                ["calibrate handeye: refused: " + why[0], *why[1:],
                 f"Nothing written to {args.output}{kept}; --force writes the result anyway."]))
        result.warnings = [w for w in result.warnings
                           if not w.startswith("the fit does not explain the data")]
        result.warnings.insert(0, "FORCED (--force): this result is most likely WRONG, do not "
                                  "use it for the robot: " + " ".join(why))
    warnings = [f"{r['image']}: left out: {r['reason']}" for r in rejected] + result.warnings
    symmetric = _board_warning(board)
    if symmetric:
        warnings.insert(0, symmetric)
    summary = _summary(result, warnings, args.output, samples_file, rejected)
    mounting = "robot" if mode == "eye-in-hand" else "fixed"
    about = {
        "command": _command(args), "mode": mode, "board": board, "solver": result.solver,
        "start": result.start, "samples": len(samples), "samples_file": samples_file or "",
        "rms_px": result.rms_px if result.rms_px is not None else (
            "n/a (board behind the camera)" if check.behind else "n/a (board poses only)"),
        "noise": summary["noise"], "fit_check": summary["fit_check"],
        result.board_name: pose_table(result.T_anchor_board),
        "stability": summary["stability"] or {}, "per_sample": summary["per_sample"],
        "rejected": rejected, "warnings": warnings,
        **_camera_about(args.intrinsics, camera)}
    if walk is not None:
        about["plan"] = {"file": str(walk.get("plan", "")), "targets": walk.get("targets", 0),
                         "condition": walk.get("condition", {})}
        summary["plan"] = about["plan"]
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


def _board_warning(spec: str | None) -> str | None:
    """The symmetric-board warning for the board spec (None: not symmetric, or unknown)."""
    if not spec:
        return None
    try:
        return Board.parse(spec).symmetry_warning()
    except CalibrationError:
        return None


def _camera_about(intrinsics: str | None, camera: CameraModel | None) -> dict[str, Any]:
    """The fingerprint of the camera model the hand-eye is computed with: the camera sections
    of ``--intrinsics`` (a rig file covers left, right and stereo), else the samples file's
    camera (left only)."""
    if intrinsics:
        calibration = read_config_data(intrinsics).get("calibration", {})
        return camera_about(calibration, camera_parts(calibration) or ("left",))
    if camera is None:
        return {}
    return camera_about({"left": intrinsics_table(camera)}, ("left",))


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


def _finite(value: float | None) -> float | None:
    """JSON has no inf/nan: None instead."""
    return value if value is None or math.isfinite(value) else None


def _noise(result: HandEyeResult) -> dict[str, Any] | None:
    """The likelihood objective's noise figures. A robot noise at an edge of its search grid
    is a bound, not a figure: ``robot_deg`` / ``robot_mm`` are then None and
    ``robot_deg_at_least`` (upper edge) or ``..._at_most`` (lower edge) holds the bound."""
    if result.robot_sigma is None:
        return None
    out: dict[str, Any] = {"corners_px": result.sigma_px}
    for value, unit, edge in zip(result.robot_sigma, ("deg", "mm"), result.robot_sigma_edges,
                                 strict=True):
        out[f"robot_{unit}"] = None if edge else value
        out[f"robot_{unit}_at_least"] = value if edge == "upper" else None
        out[f"robot_{unit}_at_most"] = value if edge == "lower" else None
    out["robot_at_edge"] = any(result.robot_sigma_edges)
    out["robot_search_range"] = {"deg": [ROBOT_SIGMA_DEG[0], ROBOT_SIGMA_DEG[-1]],
                                 "mm": [ROBOT_SIGMA_MM[0], ROBOT_SIGMA_MM[-1]]}
    out["robot_text"] = robot_noise_text(result.robot_sigma)
    return out


def _fit_check(result: HandEyeResult) -> dict[str, Any]:
    c = result.check
    assert c is not None
    return {
        "ok": c.ok, "ratio": _finite(c.ratio), "limit": c.limit, "behind_camera": c.behind,
        "rms_px": _finite(c.rms_px), "expected_px": c.expected_px, "corners_px": c.corners_px,
        "rotation_deg": c.rotation_deg, "translation_mm": c.translation_mm,
        "expected_deg": c.expected_deg, "expected_mm": c.expected_mm,
        "better_readings": [{"cause": r.cause, "change": r.change, "ratio": r.ratio,
                             "residual": r.residual} for r in c.better],
        "forced": not c.ok}


def _summary(result: HandEyeResult, warnings: list[str], output: str, samples_file: str | None,
             rejected: list[dict[str, str]]) -> dict[str, Any]:
    solvers = {}
    for name, sol in result.solvers.items():
        solvers[name] = {"matrix_mm": None if sol.error else sol.T,
                         "rms_px": _finite(sol.rms_px),
                         "rotation_deg": None if sol.error else sol.rotation_deg,
                         "translation_mm": None if sol.error else sol.translation_mm,
                         "error": sol.error or None}
    stab = result.stability
    return {
        "mode": result.mode, "matrix_mm": result.T, "transform": result.transform_name,
        "solver": result.solver, "start": result.start, "solvers": solvers,
        "rms_px": result.rms_px, result.board_name: result.T_anchor_board,
        "noise": _noise(result), "fit_check": _fit_check(result),
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
    if not (result.check is None or result.check.ok):
        lines.insert(0, "!!! NOT A VALID CALIBRATION: the fit does not explain the data; "
                        "written only because of --force (see the warnings) !!!")
    if result.rms_px is not None:
        lines.append(f"reprojection RMS {result.rms_px:.3f} px over {len(result.per_sample)} "
                     "samples")
    if result.robot_sigma is not None:
        lines.append(f"noise (1 sigma per axis): corners {result.sigma_px:.3f} px, robot poses "
                     f"{robot_noise_text(result.robot_sigma)}, the most likely")
    check = result.check
    if check is not None:
        verdict = "ok" if check.ok else "FAILED, written only because of --force"
        figure = ("the fit puts the board behind the camera" if check.behind else
                  f"{check.ratio:.2g}x what noise explains")
        lines.append(f"fit check: {figure} (limit {check.limit:g}x; residual "
                     f"{check.residual()} RMS): {verdict}")
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
        raise CalibrationError("--report needs board corners in front of the camera (the "
                               "samples hold board poses only, or the fit puts the board "
                               "behind the camera)")
    images = [ImageResiduals(s.image, np.asarray(s.px), r)
              for s, r in zip(samples, result.residuals_px, strict=True)]
    write_report(path, f"vgripd calibrate handeye  {result.mode}",
                 (camera.width, camera.height), images, lines=lines)
