"""vgripd calibrate cameras: 2 to 8 cameras' poses from board images taken at the same instants.

``--camera NAME=GLOB`` once per camera (quote the glob). Images of different cameras belong to
the same instant -- one "image set", one board pose -- when the last number in their file names
is the same (``nl_007.png`` and ``sr-7.png`` are set 7); a camera may miss a set (no file, or
the board not seen). Intrinsics come from ``--intrinsics NAME=FILE`` (a ``calibrate
intrinsics``/``stereo`` result or a config; ``FILE:right`` picks ``[calibration.right]``) or,
for a camera without, from its own images (as ``calibrate intrinsics``). The cameras' poses are
fitted jointly over every board corner (``vgripd.calib.camera_poses``: PnP per image, view graph,
spanning tree -- chaining where two cameras share no set --, sparse bundle adjustment with
intrinsics fixed unless ``--refine-intrinsics``), relative to ``--reference`` (default the
first camera).

Placing the cameras in the robot base frame, one of:

* ``--board-in-base SET=POSE``: the board's pose in the base frame in image set SET (measured
  with the robot's tool, say), POSE in ``--pose-format`` (default ``rotvec``: x y z mm and a
  rotation vector rx ry rz rad; or any vendor of ``vgripd convert``);
* ``--hand-eye NAME=FILE``: a ``calibrate handeye`` result for camera NAME (fixed:
  ``T_base_camera``; robot-mounted: ``T_flange_camera``, then all cameras are on the flange).

With either, ``-o`` gets the ``[[calibration.cameras]]`` tables (and ``[[calibration.rigs]]``
from ``--rig NAME=CAM,CAM``) for a config's ``include``. Without, nothing is placed in a base
frame: the file holds only ``[about]`` with the poses relative to the reference camera (a
config cannot use it by mistake). See docs/calibration-multicamera.md.
"""

from __future__ import annotations

import argparse
import glob
import os
import re
import shlex
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from vgripd.calib.boards import Board, Detection, detect_files
from vgripd.calib.camera_poses import (
    MAX_CAMERAS,
    MIN_POINTS,
    MultiResult,
    Observation,
    base_from_board,
    base_from_camera,
    calibrate_cameras,
    place,
)
from vgripd.calib.files import pose_table, write_result
from vgripd.calib.intrinsics import DIST_NAMES, calibrate_intrinsics
from vgripd.calib.output import add_output_arguments, emit
from vgripd.cli.calibrate_intrinsics import add_model_arguments, model_words
from vgripd.config import HandEyeConfig, IntrinsicsConfig, read_config_data
from vgripd.errors import CalibrationError, ConfigError, ConversionError
from vgripd.geometry.transforms import make_transform, matrix_from_rotvec
from vgripd.geometry.vendors import VENDORS, transform_from_vendor
from vgripd.imagefiles import natural_key

NAME = re.compile(r"[a-z0-9_]+")
_LAST_NUMBER = re.compile(r"(\d+)(?!.*\d)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--camera", action="append", required=True, metavar="NAME=GLOB",
                        help="a camera and its board images (repeat for each camera, 2..8); "
                             "the last number in a file name is its image set")
    parser.add_argument("--board", required=True, metavar="SPEC",
                        help="chessboard:COLSxROWS:SQUARE_MM (inner corners), circles:..., "
                             "acircles:..., charuco:COLSxROWS:SQUARE_MM:MARKER_MM[:DICT]")
    parser.add_argument("--intrinsics", action="append", default=[], metavar="NAME=FILE[:right]",
                        help="known intrinsics of a camera (else calibrated from its images)")
    parser.add_argument("--refine-intrinsics", action="store_true",
                        help="also refine fx fy cx cy and the free distortion terms of every "
                             "camera in the joint fit (default: held)")
    parser.add_argument("--reference", metavar="NAME", default=None,
                        help="the camera the poses are relative to (default the first)")
    base = parser.add_mutually_exclusive_group()
    base.add_argument("--board-in-base", metavar="SET=POSE", default=None,
                      help="the board's pose in the robot base frame in image SET, e.g. "
                           "'7=600,100,0,0,0,1.57' (see --pose-format)")
    base.add_argument("--hand-eye", metavar="NAME=FILE", default=None,
                      help="a calibrate handeye result for camera NAME")
    parser.add_argument("--pose-format", default="rotvec", metavar="VENDOR",
                        help="convention of --board-in-base: rotvec (x y z mm, rx ry rz rad; "
                             f"default) or {', '.join(VENDORS)}")
    parser.add_argument("--rig", action="append", default=[], metavar="NAME=CAM,CAM[,...]",
                        help="a group of cameras for per-rig residuals (written as "
                             "[[calibration.rigs]])")
    add_model_arguments(parser)
    parser.add_argument("--subpix-window", type=int, default=None, metavar="N",
                        help="cornerSubPix half-window in px (default: from the corner spacing)")
    add_output_arguments(parser, "cameras.toml")


def _split(text: str, option: str, what: str) -> tuple[str, str]:
    name, sep, value = text.partition("=")
    if not sep or not name or not value:
        raise CalibrationError(f"{option} {text!r}: expected {what}")
    return name.strip(), value.strip()


def _camera_name(name: str, option: str) -> str:
    if not NAME.fullmatch(name):
        raise CalibrationError(f"{option}: camera name {name!r} must be [a-z0-9_]+")
    return name


def set_key(path: str) -> str:
    """The image set of a file: the last number in its file name, without leading zeros."""
    m = _LAST_NUMBER.search(Path(path).name)
    if m is None:
        raise CalibrationError(f"{path}: no number in the file name; image sets are matched "
                               "across cameras by the last number in the name")
    return str(int(m.group(1)))


def _images(name: str, pattern: str) -> dict[str, str]:
    paths = sorted(glob.glob(os.path.expanduser(pattern), recursive=True), key=natural_key)
    if not paths:
        raise CalibrationError(f"--camera {name}={pattern!r}: no file matches (relative to "
                               f"{os.getcwd()})")
    out: dict[str, str] = {}
    for p in paths:
        key = set_key(p)
        if key in out:
            raise CalibrationError(f"--camera {name}: {out[key]} and {p} are both image set "
                                   f"{key} (the last number in the name)")
        out[key] = p
    return out


def read_intrinsics(spec: str) -> dict[str, Any]:
    """``FILE`` or ``FILE:left|right``: ``[calibration.<side>]`` (default: left, or the only
    one) of a result file or config, validated as ``IntrinsicsConfig``."""
    path, side = spec, None
    if spec.endswith((":left", ":right")):
        path, _, side = spec.rpartition(":")
    try:
        calib = read_config_data(path).get("calibration", {})
    except ConfigError as err:
        raise CalibrationError(f"--intrinsics: {err}") from None
    sides = [s for s in ("left", "right") if s in calib]
    if side is None:
        side = "left" if "left" in sides else (sides[0] if sides else "left")
    if side not in calib:
        raise CalibrationError(f"{path}: no [calibration.{side}] intrinsics")
    try:
        return IntrinsicsConfig.model_validate(calib[side]).model_dump(mode="json")
    except ValueError as err:  # pydantic's ValidationError
        raise CalibrationError(f"{path}: calibration.{side}: {err}") from None


def _board_pose(text: str, pose_format: str) -> tuple[str, np.ndarray]:
    key, values = _split(text, "--board-in-base", "SET=POSE")
    numbers = values.replace(",", " ").split()
    if pose_format == "rotvec":
        try:
            v = [float(x) for x in numbers]
        except ValueError:
            raise CalibrationError(f"--board-in-base {text!r}: not numbers") from None
        if len(v) != 6 or not np.all(np.isfinite(v)):
            raise CalibrationError(f"--board-in-base {text!r}: rotvec needs 6 finite numbers "
                                   "(x y z mm, rx ry rz rad)")
        return str(int(key)) if key.isdigit() else key, make_transform(
            matrix_from_rotvec(v[3:]), v[:3])
    try:
        return (str(int(key)) if key.isdigit() else key,
                transform_from_vendor(pose_format, numbers))
    except ConversionError as err:
        raise CalibrationError(f"--board-in-base: {err}") from None


def _hand_eye(text: str) -> tuple[str, str, np.ndarray]:
    name, path = _split(text, "--hand-eye", "NAME=FILE")
    try:
        data = read_config_data(path).get("calibration", {}).get("hand_eye")
    except ConfigError as err:
        raise CalibrationError(f"--hand-eye: {err}") from None
    if data is None:
        raise CalibrationError(f"{path}: no [calibration.hand_eye]")
    try:
        he = HandEyeConfig.model_validate(data)
    except ValueError as err:
        raise CalibrationError(f"{path}: calibration.hand_eye: {err}") from None
    pose = he.T_base_camera if he.mounting == "fixed" else he.T_flange_camera
    assert pose is not None
    if pose.matrix is not None:
        T = np.asarray(pose.matrix, dtype=np.float64)
    else:
        T = make_transform(matrix_from_rotvec(pose.rotvec_rad or (0.0, 0.0, 0.0)),
                           pose.translation_mm)
    return name, he.mounting, T


def run(args: argparse.Namespace) -> int:
    board = Board.parse(args.board)
    if args.subpix_window is not None and args.subpix_window < 1:
        raise CalibrationError(f"--subpix-window {args.subpix_window}: must be at least 1 px")
    cameras: dict[str, dict[str, str]] = {}
    for text in args.camera:
        name, pattern = _split(text, "--camera", "NAME=GLOB")
        if _camera_name(name, "--camera") in cameras:
            raise CalibrationError(f"--camera {name}: given twice")
        cameras[name] = _images(name, pattern)
    names = list(cameras)
    if not 2 <= len(names) <= MAX_CAMERAS:
        raise CalibrationError(f"{len(names)} --camera given: need 2 to {MAX_CAMERAS}")
    known: dict[str, dict[str, Any]] = {}
    known_prior: dict[str, dict[str, Any] | None] = {}
    for text in args.intrinsics:
        name, spec = _split(text, "--intrinsics", "NAME=FILE")
        if name not in cameras:
            raise CalibrationError(f"--intrinsics {name}: no --camera {name}")
        known[name] = read_intrinsics(spec)
        known_prior[name] = read_intrinsics_prior(spec)
    rigs = _rigs(args.rig, names)
    if args.reference is not None and args.reference not in cameras:
        raise CalibrationError(f"--reference {args.reference}: no --camera of that name")
    placement = _placement(args, names)

    observations: list[Observation] = []
    intrinsics: list[dict[str, Any]] = []
    priors: list[dict[str, Any] | None] = []
    rejected: list[dict[str, str]] = []
    intrinsics_source: dict[str, str] = {}
    covariance_source: dict[str, str] = {}  # where the intrinsics' covariance came from
    warnings: list[str] = [w for w in [board.symmetry_warning()] if w]
    obj = board.object_points()
    for c, name in enumerate(names):
        paths = cameras[name]
        found, failed = detect_files(board, list(paths.values()), args.subpix_window)
        rejected += [{"camera": name, "image": p, "reason": why} for p, why in failed]
        if name in known:
            cam = known[name]
            for d in found:
                if d.size != (cam["width"], cam["height"]):
                    raise CalibrationError(f"{d.image}: image is {d.size[0]}x{d.size[1]} but "
                                           f"the intrinsics of {name} are for {cam['width']}x"
                                           f"{cam['height']}")
            intrinsics_source[name] = "given"
            prior = known_prior[name]
            covariance_source[name] = (
                "the given file's [about.richest]" if prior is not None else
                "none (the given file has no [about.richest]): the pose sigma takes the "
                "intrinsics as exact")
        else:
            cam, why, prior = _own_intrinsics(board, name, found, args)
            intrinsics_source[name] = why
            covariance_source[name] = "its own calibration here (richest model)"
        intrinsics.append(cam)
        priors.append(prior)
        key_of = {p: k for k, p in paths.items()}
        for d in found:
            if len(d.ids) < MIN_POINTS:  # a ChArUco board seen in part
                rejected.append({"camera": name, "image": d.image, "reason": f"only "
                                 f"{len(d.ids)} board points (need at least {MIN_POINTS})"})
            else:
                observations.append(Observation(c, key_of[d.image], obj[d.ids], d.px, d.image))
    free = None
    if args.refine_intrinsics:
        free = [("fx", "fy", "cx", "cy", *[n for n, v in zip(DIST_NAMES, cam["dist"],
                                                             strict=True) if v != 0.0])
                for cam in intrinsics]
    result = calibrate_cameras(names, intrinsics, observations, reference=args.reference,
                               free=free, intrinsics_prior=priors)
    rejected += result.rejected
    warnings += result.warnings
    T_base = None
    mounting = "fixed"
    base_words = "none: poses relative to the reference camera only (no base frame given)"
    if placement is not None:
        kind, key, value = placement
        if kind == "board":
            T_base = base_from_board(result, key, value)
            base_words = f"board pose in the base frame in image set {key}"
        else:
            mounting = kind
            T_base = base_from_camera(result, key, value)
            base_words = (f"hand-eye of camera {key} (mounting {kind}"
                          + (": poses on the flange)" if kind == "robot" else ")"))
    rig_rows = _rig_residuals(result, rigs)
    for row in result.cameras:
        row["intrinsics_covariance"] = covariance_source[row["name"]]
    summary = _summary(result, T_base, mounting, base_words, rig_rows, intrinsics_source,
                       rejected, warnings, args)
    sections: dict[str, Any] = {}
    if T_base is not None:
        key_pose = "T_base_camera" if mounting == "fixed" else "T_flange_camera"
        sections["calibration"] = {"cameras": [
            {"name": n, "intrinsics": _intrinsics_table(cam), "mounting": mounting,
             key_pose: pose_table(T)}
            for n, cam, T in zip(names, result.intrinsics, place(result, T_base), strict=True)]}
        if rigs:
            sections["calibration"]["rigs"] = [{"name": r, "cameras": cams}
                                               for r, cams in rigs.items()]
    else:
        warnings.append("no --board-in-base or --hand-eye: the cameras are not placed in the "
                        f"robot base frame; {args.output} holds only [about] (poses relative "
                        f"to {result.reference})")
    about = {"command": _command(args), "board": board.spec, "opencv": cv2.__version__,
             "reference": result.reference, "base_frame": base_words,
             "rms_px": result.rms_px, "cameras": summary["cameras"], "pairs": result.pairs,
             "rigs": rig_rows, "view_graph": summary["view_graph"], "sets": result.sets,
             "rejected": rejected, "warnings": warnings}
    write_result(args.output, sections, about,
                 header="N cameras ([[calibration.cameras]]): include this file from a config."
                        "\n[about] (provenance, residuals) is ignored by the loader.")
    lines = _human(result, summary, args)
    if args.report:
        from vgripd.calib.report import ImageResiduals, write_report

        images = [ImageResiduals(o.image, o.px, r)
                  for o, r in zip(result.observations, result.residuals, strict=True)]
        first = result.intrinsics[0]
        write_report(args.report, f"vgripd calibrate cameras  {board.spec}",
                     (first["width"], first["height"]), images,
                     lines=[line for line in lines if not line.startswith("written")][:40])
        summary["report"] = str(args.report)
        lines.append(f"report: {args.report}")
    emit(args, summary, lines)
    return 0


def read_intrinsics_prior(spec: str) -> dict[str, Any] | None:
    """``[about.richest]`` of a ``calibrate intrinsics`` result (the richest model's values
    and 9x9 covariance), or None when the file has none (a config, a stereo result)."""
    path = spec.rpartition(":")[0] if spec.endswith((":left", ":right")) else spec
    try:
        rich = read_config_data(path).get("about", {}).get("richest")
    except ConfigError as err:
        raise CalibrationError(f"--intrinsics: {err}") from None
    if not isinstance(rich, dict):
        return None
    values = np.asarray(rich.get("values", []), dtype=np.float64)
    cov = np.asarray(rich.get("covariance", []), dtype=np.float64)
    if values.shape != (9,) or cov.shape != (9, 9) or not (
            np.all(np.isfinite(values)) and np.all(np.isfinite(cov))):
        raise CalibrationError(f"{path}: about.richest: need 9 finite values and a finite 9x9 "
                               f"covariance, have {values.shape} and {cov.shape}")
    return {"values": values, "covariance": cov}


def _own_intrinsics(board: Board, name: str, found: list[Detection], args: argparse.Namespace,
                    ) -> tuple[dict[str, Any], str, dict[str, Any] | None]:
    if not found:
        raise CalibrationError(f"camera {name}: the board {board.spec} was not found in any "
                               "of its images, and no --intrinsics given")
    try:
        r = calibrate_intrinsics(board, found, found[0].size, fix_k3=args.fix_k3,
                                 fix_tangential=args.fix_tangential)
    except CalibrationError as err:
        raise CalibrationError(f"camera {name}: its own intrinsics calibration failed ({err});"
                               f" give --intrinsics {name}=FILE") from None
    return dict(r.camera), (f"calibrated from its {len(r.per_image)} images, RMS "
                            f"{r.rms_px:.3f} px, model {r.model.model.name}"), r.richest


def _rigs(texts: list[str], names: list[str]) -> dict[str, list[str]]:
    rigs: dict[str, list[str]] = {}
    for text in texts:
        rig, members = _split(text, "--rig", "NAME=CAM,CAM")
        _camera_name(rig, "--rig")
        cams = [m.strip() for m in members.split(",") if m.strip()]
        unknown = [m for m in cams if m not in names]
        if unknown:
            raise CalibrationError(f"--rig {rig}: no --camera {', '.join(unknown)}")
        if rig in rigs:
            raise CalibrationError(f"--rig {rig}: given twice")
        if rig in names:
            raise CalibrationError(f"--rig {rig}: also a camera's name (the config's "
                                   "residuals are keyed by both)")
        taken = [f"{m} (in rig {r})" for r, members in rigs.items() for m in cams
                 if m in members]
        if taken:
            raise CalibrationError(f"--rig {rig}: a camera is in one rig at most: "
                                   + ", ".join(taken))
        rigs[rig] = cams
    return rigs


def _placement(args: argparse.Namespace, names: list[str],
               ) -> tuple[str, str, np.ndarray] | None:
    if args.board_in_base is not None:
        key, T = _board_pose(args.board_in_base, args.pose_format)
        return "board", key, T
    if args.hand_eye is not None:
        name, mounting, T = _hand_eye(args.hand_eye)
        if name not in names:
            raise CalibrationError(f"--hand-eye {name}: no --camera {name}")
        return mounting, name, T
    return None


def _rig_residuals(r: MultiResult, rigs: dict[str, list[str]]) -> list[dict[str, Any]]:
    """Per rig: its cameras' RMS over all their points."""
    out = []
    for rig, cams in rigs.items():
        idx = [r.names.index(c) for c in cams]
        sq = [np.sum(res**2, axis=1) for o, res in zip(r.observations, r.residuals, strict=True)
              if o.camera in idx]
        out.append({"name": rig, "cameras": cams,
                    "rms_px": float(np.sqrt(np.mean(np.concatenate(sq)))) if sq else 0.0})
    return out


def _intrinsics_table(cam: dict[str, Any]) -> dict[str, Any]:
    keys = ("fx", "fy", "cx", "cy", "skew", "dist", "width", "height")
    return {k: cam[k] for k in keys}


def _command(args: argparse.Namespace) -> str:
    words = ["vgripd", "calibrate", "cameras"]
    for text in args.camera:
        words += ["--camera", text]
    words += ["--board", args.board, *model_words(args)]
    for text in args.intrinsics:
        words += ["--intrinsics", text]
    if args.refine_intrinsics:
        words.append("--refine-intrinsics")
    if args.reference:
        words += ["--reference", args.reference]
    if args.board_in_base:
        words += ["--board-in-base", args.board_in_base, "--pose-format", args.pose_format]
    if args.hand_eye:
        words += ["--hand-eye", args.hand_eye]
    for text in args.rig:
        words += ["--rig", text]
    if args.subpix_window is not None:
        words += ["--subpix-window", str(args.subpix_window)]
    return shlex.join([*words, "-o", args.output])


def _summary(r: MultiResult, T_base: np.ndarray | None, mounting: str, base_words: str,
             rigs: list[dict[str, Any]], sources: dict[str, str], rejected: list[dict[str, str]],
             warnings: list[str], args: argparse.Namespace) -> dict[str, Any]:
    cams = []
    placed = place(r, T_base) if T_base is not None else [None] * len(r.names)
    for row, T_ref, cam, T in zip(r.cameras, r.T_ref_camera, r.intrinsics, placed, strict=True):
        entry = {**row, "intrinsics": _intrinsics_table(cam),
                 "intrinsics_source": sources[row["name"]],
                 "T_reference_camera": pose_table(T_ref)}
        if T is not None:
            entry["T_base_camera" if mounting == "fixed" else "T_flange_camera"] = pose_table(T)
        cams.append(entry)
    graph = {"edges": [{"a": a, "b": b, "shared_sets": n} for a, b, n in r.graph["edges"]],
             "tree": [list(e) for e in r.graph["tree"]]}
    return {"reference": r.reference, "base_frame": base_words, "mounting": mounting,
            "rms_px": r.rms_px, "cameras": cams, "pairs": r.pairs, "rigs": rigs,
            "view_graph": graph, "sets": r.sets, "rejected": rejected, "warnings": warnings,
            "output": str(args.output)}


def _human(r: MultiResult, s: dict[str, Any], args: argparse.Namespace) -> list[str]:
    w = max(len(n) for n in r.names)
    lines = [f"{'camera':{w}s}  sets  points  RMS px  pose in {r.reference} (mm, rotvec rad)"
             "   +- position mm, rotation deg (1 sigma)"]
    for cam in s["cameras"]:
        p = cam["T_reference_camera"]
        lines.append(f"{cam['name']:{w}s}  {cam['sets']:4d}  {cam['points']:6d}  "
                     f"{cam['rms_px']:6.3f}  " + " ".join(f"{v:9.2f}" for v in p["translation_mm"])
                     + "  " + " ".join(f"{v:8.5f}" for v in p["rotvec_rad"]) + "   +- "
                     + " ".join(f"{v:.2f}" for v in cam["position_std_mm"])
                     + f", {cam['rotation_std_deg']:.3f}")
    lines.append("")
    lines.append("pairs (shared sets; RMS px; spread of the per-set estimates around the joint "
                 "solution, RMS / max):")
    for p in r.pairs:
        lines.append(f"  {p['a']} / {p['b']}: {p['shared_sets']} sets, {p['rms_px']:.3f} px, "
                     f"{p['rotation_deg']['rms']:.3f} / {p['rotation_deg']['max']:.3f} deg, "
                     f"{p['translation_mm']['rms']:.2f} / {p['translation_mm']['max']:.2f} mm")
    lines.append("view graph tree: " + ", ".join(f"{a} -> {b}" for a, b in r.graph["tree"]))
    for rig in s["rigs"]:
        lines.append(f"rig {rig['name']} ({', '.join(rig['cameras'])}): RMS {rig['rms_px']:.3f}"
                     " px")
    lines.append(f"RMS {r.rms_px:.3f} px over {len(r.observations)} images in "
                 f"{len(r.sets)} sets; base frame: {s['base_frame']}")
    if s["rejected"]:
        lines.append(f"left out {len(s['rejected'])} image(s):")
        lines += [f"  {x['image']}: {x['reason']}" for x in s["rejected"]]
    lines.append(f"written: {args.output}")
    return lines

