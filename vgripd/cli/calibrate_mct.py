"""Read and write Camera Calibration Toolbox for Matlab (Bouguet) result scripts.

import-mct: ``Calib_Results.m`` (or ``.mat``) -> ``camera.toml`` ([calibration.left], or
.right with ``--camera right``); ``Calib_Results_stereo.mat`` or a stereo script (fc_left, ...,
om, T) -> ``rig.toml``.
export-mct: a camera/rig result file or a config -> ``Calib_Results.m`` /
``Calib_Results_stereo.m``. See docs/calibration-mct.md for the conventions (kc order, alpha_c,
pixel origin, om/T direction, *_error = 3 sigma).
"""

from __future__ import annotations

import argparse
from typing import Any

from vgripd.calib.files import write_result
from vgripd.calib.mct import (
    MctCamera,
    MctStereo,
    from_result_file,
    read_mct,
    result_tables,
    write_mct,
)
from vgripd.calib.output import emit
from vgripd.errors import CalibrationError


def add_arguments(parser: argparse.ArgumentParser, name: str) -> None:
    if name == "import-mct":
        parser.add_argument("file", help="the toolbox's Calib_Results.m/.mat or "
                                         "Calib_Results_stereo.mat/.m")
        parser.add_argument("-o", "--output", default=None,
                            help="result file (default camera.toml, rig.toml for a stereo rig)")
        parser.add_argument("--camera", choices=("left", "right"), default=None,
                            help="which camera a single-camera result is (default left)")
    else:
        parser.add_argument("file", help="camera.toml, rig.toml or a config (with includes)")
        parser.add_argument("-o", "--output", default=None,
                            help="script to write (default Calib_Results.m, "
                                 "Calib_Results_stereo.m for a rig)")
        parser.add_argument("--camera", choices=("left", "right"), default=None,
                            help="export only this camera of a rig")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")


def run(args: argparse.Namespace) -> int:
    if args.calibrate_command == "import-mct":
        return _import(args)
    return _export(args)


def summary_of(result: MctCamera | MctStereo) -> dict[str, Any]:
    """The JSON summary (CALIB contract keys) of a camera or rig."""
    if isinstance(result, MctCamera):
        return {"camera": result.camera, "std": result.std}
    return {"left": result.left.camera, "right": result.right.camera,
            "left_std": result.left.std, "right_std": result.right.std,
            "rotvec_rad": list(result.rotvec_rad), "translation_mm": list(result.translation_mm),
            "rotvec_std": result.rotvec_std, "translation_std": result.translation_std}


def _lines(result: MctCamera | MctStereo, verb: str, src: str, out: str) -> list[str]:
    lines = [f"{verb} {src} -> {out}"]
    cams = ([("camera", result)] if isinstance(result, MctCamera)
            else [("left", result.left), ("right", result.right)])
    for name, c in cams:
        k = c.camera
        lines.append(f"{name}: fx {k['fx']:.5f} fy {k['fy']:.5f} cx {k['cx']:.5f} "
                     f"cy {k['cy']:.5f} skew {k['skew']:.5g} dist "
                     + " ".join(f"{d:.5f}" for d in k["dist"]))
    if isinstance(result, MctStereo):
        lines.append("T_right_left: rotvec_rad " + " ".join(f"{v:.5f}" for v in result.rotvec_rad)
                     + ", translation_mm " + " ".join(f"{v:.5f}" for v in result.translation_mm))
    return lines


def _import(args: argparse.Namespace) -> int:
    result = read_mct(args.file)
    if isinstance(result, MctStereo) and args.camera is not None:
        raise CalibrationError(
            f"{args.file}: a stereo result holds both cameras; --camera is for single-camera "
            "files")
    out = args.output or ("rig.toml" if isinstance(result, MctStereo) else "camera.toml")
    sections, about = result_tables(result, str(args.file), args.camera or "left")
    write_result(out, sections, about,
                 header=f"imported from the Camera Calibration Toolbox result {args.file}")
    summary = summary_of(result)
    summary.update(source=str(args.file), output=out,
                   warnings=result.warnings if isinstance(result, MctStereo) else [])
    emit(args, summary, _lines(result, "imported", str(args.file), out))
    return 0


def _export(args: argparse.Namespace) -> int:
    result = from_result_file(args.file, args.camera)
    default = "Calib_Results_stereo.m" if isinstance(result, MctStereo) else "Calib_Results.m"
    out = args.output or default
    write_mct(out, result)
    warnings = []
    cams = [result] if isinstance(result, MctCamera) else [result.left, result.right]
    if any(c.std is None for c in cams):
        warnings.append(f"{args.file}: no standard deviations in [about]; *_error not written")
    summary = summary_of(result)
    summary.update(source=str(args.file), output=out, warnings=warnings)
    emit(args, summary, _lines(result, "exported", str(args.file), out))
    return 0
