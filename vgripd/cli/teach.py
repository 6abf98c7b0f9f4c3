"""Teach the reference: measure the object at its reference place and write reference.toml.

Grabs ``--shots`` images from the configured camera with the object where the robot's grip was
taught, runs the pipeline on each, refuses if any shot is not clean (status OK with every
feature) or if the shots disagree by more than ``--max-spread-mm/--max-spread-deg``, and
otherwise writes the averaged reference (``[reference]``) for the config to ``include``:
``T_base_obj`` for a CAD object, the measured base-frame feature points (``points_mm``) for
``object.definition = "reference"``; with ``--grip`` also the taught grip pose.

``--recipe N`` teaches recipe N's object (its effective config, docs/recipes.md) and writes
``[recipes.N.reference]`` to ``reference-recipe-N.toml`` (default), where that recipe's
reference lives; recipe 0 (the default) is the top-level ``[reference]``.

Examples::

    vgripd teach -c cell.toml
    vgripd teach -c cell.toml --shots 10 --grip="612.5 98.1 55.0 180 0 180" --pose-format kuka
    vgripd teach -c cell.toml --recipe 2

Exit codes: 0 written; 1 refused (a bad shot, too much spread, the file exists without
``--force``, camera failure); 2 bad ``--grip`` or ``--shots``; 78 configuration error.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from vgripd.calib import teach
from vgripd.calib.files import pose_table, write_result
from vgripd.calib.output import emit
from vgripd.config import load_config
from vgripd.errors import ConfigError, ConversionError
from vgripd.geometry.fingerprint import camera_about, hand_eye_fingerprint
from vgripd.geometry.vendors import VENDORS, transform_from_vendor


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("-c", "--config", required=True, help="TOML configuration file")
    parser.add_argument("--shots", type=int, default=teach.DEFAULT_SHOTS,
                        help=f"images to average (default {teach.DEFAULT_SHOTS})")
    parser.add_argument("--grip", metavar="VALUES",
                        help="the grip pose taught on the reference object (robot base frame), "
                             "values separated by spaces or commas in --pose-format; quote it "
                             'and use "=" when it starts with a minus: --grip="-10 20 ..."')
    parser.add_argument("--pose-format", default="kuka", metavar="VENDOR",
                        help=f"convention of --grip, one of {', '.join(VENDORS)} (default kuka)")
    parser.add_argument("--recipe", type=int, default=0, metavar="N",
                        help="teach recipe N ([recipes.N]); 0 = the top-level object (default)")
    parser.add_argument("-o", "--output", default=None,
                        help="result file (default reference.toml beside the config, "
                             "reference-recipe-N.toml with --recipe N)")
    parser.add_argument("--force", action="store_true", help="overwrite an existing file")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument("--max-spread-mm", type=float, default=teach.DEFAULT_MAX_SPREAD_MM,
                        help="refuse when a shot's pose (or a feature point) is further than "
                             f"this from the mean (default {teach.DEFAULT_MAX_SPREAD_MM})")
    parser.add_argument("--max-spread-deg", type=float, default=teach.DEFAULT_MAX_SPREAD_DEG,
                        help="refuse when a shot's rotation is further than this from the mean "
                             f"(default {teach.DEFAULT_MAX_SPREAD_DEG})")


def _fail(message: str, code: int = 1) -> int:
    print(f"vgripd teach: {message}", file=sys.stderr)
    return code


def _include_name(config_path: Path, output: Path) -> str:
    """How the config names ``output`` in its ``include`` (relative to the config's folder)."""
    try:
        return os.path.relpath(output.resolve(), config_path.resolve().parent)
    except ValueError:  # another drive (Windows)
        return str(output.resolve())


def _included(config_path: Path, output: Path) -> bool:
    data = tomllib.loads(config_path.read_text(encoding="utf-8"))
    base = config_path.resolve().parent
    return any((base / str(i)).resolve() == output.resolve() for i in data.get("include", []))


def _summary_lines(summary: dict[str, Any]) -> list[str]:
    lines = [f"{len(summary['shots'])} shot(s) of object {summary['object']!r} "
             f"(definition {summary['definition']!r}):"]
    for s in summary["shots"]:
        lines.append(f"  shot {s['shot']}: {s['deviation_mm']:.4f} mm  "
                     f"{s['deviation_deg']:.4f} deg from the mean, "
                     f"points {s['points_deviation_mm']:.4f} mm, "
                     f"fit {s['residuals'].get('fit_rms_mm', float('nan')):.4f} mm")
    sp = summary["spread"]
    lines.append(f"spread (max deviation from the mean): {sp['mm']:.4f} mm, {sp['deg']:.4f} deg, "
                 f"feature points {sp['points_mm']:.4f} mm")
    t, r = summary["T_base_obj"]["translation_mm"], summary["T_base_obj"]["rotvec_rad"]
    lines.append("T_base_obj: translation_mm " + " ".join(f"{v:.4f}" for v in t)
                 + ", rotvec_rad " + " ".join(f"{v:.6f}" for v in r))
    return lines


def run(args: argparse.Namespace) -> int:
    config_path = Path(args.config)
    cell = load_config(config_path, redo="reference")
    for warning in cell.load_warnings:  # what this command measures again
        print(f"warning: {warning}", file=sys.stderr)
    try:
        config = cell.for_recipe(args.recipe)
    except ConfigError as err:
        return _fail(f"--recipe: {err}", 2)
    if args.shots < 1:
        return _fail(f"--shots must be at least 1, got {args.shots}", 2)
    T_base_grip = None
    if args.grip is not None:
        try:
            T_base_grip = transform_from_vendor(args.pose_format,
                                                args.grip.replace(",", " ").split())
        except ConversionError as err:
            return _fail(f"--grip: {err}", 2)
    default_name = f"reference-recipe-{args.recipe}.toml" if args.recipe else "reference.toml"
    output = Path(args.output) if args.output else config_path.parent / default_name
    if output.exists() and not args.force:
        return _fail(f"{output} exists; nothing measured (--force overwrites it)")

    # The camera sees the measuring config too: a driver that needs a reference (the synthetic
    # one's random poses) must not stop the teaching of a new object.
    # The camera is the cell's (the top-level config with its recipes: a synthetic camera
    # renders the plate of its own ``recipe`` option, the one lying in the cell).
    pairs = asyncio.run(teach.acquire(teach.measuring_config(cell), args.shots))
    taught = teach.measure(config, pairs)
    problems = taught.problems(args.max_spread_mm, args.max_spread_deg,
                               check_points=config.object.definition == "reference")
    summary: dict[str, Any] = {
        "recipe": args.recipe,
        "object": config.object.name,
        "definition": config.object.definition,
        "shots": [
            {"shot": s.index, "deviation_mm": d[0], "deviation_deg": d[1],
             "points_deviation_mm": pd, "T_base_obj": s.T_base_obj,
             "residuals": dict(s.residuals)}
            for s, d, pd in zip(taught.shots, taught.deviations, taught.point_deviations_mm,
                                strict=True)
        ],
        "T_base_obj": {"matrix_mm": taught.T_base_obj, **pose_table(taught.T_base_obj)},
        "points_mm": {n: p for n, p in taught.points_base.items()},
        "spread": {"mm": taught.spread_mm, "deg": taught.spread_deg,
                   "points_mm": taught.points_spread_mm},
        "limits": {"max_spread_mm": args.max_spread_mm, "max_spread_deg": args.max_spread_deg},
        "grip": None if T_base_grip is None else pose_table(T_base_grip),
        "refused": problems,
        "output": None,
        "warnings": [],
    }
    if problems:
        emit(args, summary, _summary_lines(summary))
        return _fail("refused, nothing written: " + "; ".join(problems))

    sections = teach.reference_sections(config, taught, T_base_grip)
    section_name = "[reference]"
    if args.recipe:
        sections = {"recipes": {str(args.recipe): sections}}
        section_name = f"[recipes.{args.recipe}.reference]"
    about = {
        "command": "vgripd teach",
        "config": str(config_path),
        "recipe": args.recipe,
        "object": config.object.name,
        "definition": config.object.definition,
        "camera": config.camera.type,
        "shots": len(taught.shots),
        "spread_mm": taught.spread_mm,
        "spread_deg": taught.spread_deg,
        "points_spread_mm": taught.points_spread_mm,
        "fit_rms_mm_max": max(s.residuals.get("fit_rms_mm", 0.0) for s in taught.shots),
        "T_base_obj": np.round(taught.T_base_obj, 9),
    }
    if config.calibration is not None:  # what it was measured with (vgripd.geometry.fingerprint)
        calibration = config.calibration.model_dump(mode="json")
        about.update(camera_about(calibration))
        about["hand_eye"] = hand_eye_fingerprint(calibration)
    write_result(output, sections, about,
                 header=f"vgripd teach: the taught reference of object {config.object.name!r}.\n"
                        "Include it from the config; re-teach after moving the reference.")
    name = _include_name(config_path, output)
    summary["output"] = str(output)
    summary["include"] = name
    lines = [*_summary_lines(summary), f"wrote {output}"]
    if _included(config_path, output):
        lines.append(f"{config_path} already includes it")
    else:
        lines.append(f'add to {config_path}: include = ["{name}"]  (with any other includes; '
                     f"remove the {section_name} section it may still have)")
    emit(args, summary, lines)
    return 0
