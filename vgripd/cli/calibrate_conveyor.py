"""The belt's direction and encoder scale (``[conveyor]``, docs/conveyor.md).

From observations: a board or a taught object on the belt, its position in the robot base frame
at two or more encoder counts (``--points FILE``: lines ``count, x, y, z`` in mm, as written
down from ``vgripd locate`` or a robot touch-up at each count; ``--observe COUNT=LEFT[,RIGHT]``:
the taught object located in these images with the config's calibration). The fit gives the
direction, the counts per mm and a point on the belt with their sigmas.

Or imported from the robot's own conveyor frame (``--import-direction X Y Z`` and
``--counts-per-mm K``; UR's ``track_conveyor_linear(direction, ticks_per_meter)`` gives
``K = ticks_per_meter / 1000``, FANUC's tracking schedule its scale in counts/mm).

Writes a result file with the ``[conveyor]`` fields it determines (``-o``, default
``conveyor.toml``); a config includes it and adds the window, trigger distance and speed.
"""

from __future__ import annotations

import argparse
import csv
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from vgripd.calib.files import write_result
from vgripd.calib.output import emit
from vgripd.errors import CalibrationError, DegenerateInputError

#: Belt travel (mm) over which ``sigma_mm`` states a carried part's position sigma.
SIGMA_TRAVEL_MM = 1000.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-c", "--config", default=None,
                        help="config with the calibration and the taught object (--observe)")
    parser.add_argument("--points", metavar="FILE",
                        help="CSV lines 'count, x, y, z' (base frame, mm)")
    parser.add_argument("--observe", action="append", default=[], metavar="COUNT=LEFT[,RIGHT]",
                        help="images of the object on the belt at encoder count COUNT")
    parser.add_argument("--import-direction", nargs=3, type=float, metavar=("X", "Y", "Z"),
                        help="the robot's conveyor direction in the base frame")
    parser.add_argument("--counts-per-mm", type=float,
                        help="with --import-direction: the robot's encoder scale")
    parser.add_argument("--normal", nargs=3, type=float, default=[0.0, 0.0, 1.0],
                        metavar=("X", "Y", "Z"), help="the belt plane's normal (default 0 0 1)")
    parser.add_argument("--point-sigma-mm", type=float, default=0.1,
                        help="sigma of one measured position (default 0.1 mm)")
    parser.add_argument("--bits", type=int, choices=(16, 32), default=32,
                        help="encoder count width (default 32)")
    parser.add_argument("-o", "--output", default="conveyor.toml", help="result file")
    parser.add_argument("--json", action="store_true", help="JSON summary on stdout")


def read_points(path: str) -> tuple[list[int], list[list[float]]]:
    """``count, x, y, z`` lines of ``path`` (``#`` comments and blank lines skipped);
    ``CalibrationError`` naming the file and line of a bad one."""
    counts: list[int] = []
    points: list[list[float]] = []
    try:
        with open(path, newline="") as f:
            for n, row in enumerate(csv.reader(f), start=1):
                if not row or row[0].strip().startswith("#"):
                    continue
                try:
                    if len(row) != 4:
                        raise ValueError(f"{len(row)} fields, 4 expected")
                    counts.append(int(row[0]))
                    xyz = [float(v) for v in row[1:]]
                    if not all(math.isfinite(v) for v in xyz):
                        raise ValueError("not a finite position")
                    points.append(xyz)
                except ValueError as err:
                    raise CalibrationError(f"{path}:{n}: 'count, x, y, z' expected: {err}") \
                        from None
    except OSError as err:
        raise CalibrationError(f"{path}: {err.strerror}") from None
    return counts, points


def locate(config_path: str | None, observe: list[str]) -> tuple[list[int], list[list[float]]]:
    """The taught object's origin in the base frame in each ``COUNT=LEFT[,RIGHT]`` image set."""
    if config_path is None:
        raise CalibrationError("--observe needs -c CONFIG (the calibration and taught object)")
    from vgripd.cli.locate import read_image
    from vgripd.config import load_config
    from vgripd.types import ImagePair
    from vgripd.vision.checked import CheckedPipeline

    pipeline = CheckedPipeline(load_config(config_path))
    counts: list[int] = []
    points: list[list[float]] = []
    for i, item in enumerate(observe, start=1):
        count, sep, files = item.partition("=")
        if not sep or not count.strip().isdigit():
            raise CalibrationError(f"--observe {item!r}: COUNT=LEFT[,RIGHT] expected")
        paths = files.split(",")
        pair = ImagePair.of_views([read_image(p) for p in paths], time.monotonic_ns(),
                                  source=paths[0])
        result = pipeline.process(pair, job_id=i)
        if result.T_base_obj is None or not result.status.pose_valid:
            raise CalibrationError(f"--observe {item}: object not located "
                                   f"({result.status.name}: {result.message})")
        counts.append(int(count))
        points.append([float(v) for v in result.T_base_obj[:3, 3]])
    return counts, points


def run(args: argparse.Namespace) -> int:
    from vgripd.geometry.belt import fit_belt

    normal = np.asarray(args.normal, dtype=np.float64)
    if not np.linalg.norm(normal) > 0:
        raise CalibrationError("--normal: a zero vector")
    normal = normal / np.linalg.norm(normal)
    about: dict[str, Any] = {"tool": "vgripd calibrate conveyor"}
    section: dict[str, Any] = {"normal": [round(float(v), 9) for v in normal]}
    if args.import_direction is not None:
        if args.points or args.observe:
            raise CalibrationError("--import-direction replaces the observations: give one")
        if args.counts_per_mm is None or not args.counts_per_mm > 0:
            raise CalibrationError("--import-direction needs --counts-per-mm > 0")
        d = np.asarray(args.import_direction, dtype=np.float64)
        if not np.linalg.norm(d) > 0:
            raise CalibrationError("--import-direction: a zero vector")
        d = d / np.linalg.norm(d)
        section |= {"direction": [round(float(v), 9) for v in d],
                    "counts_per_mm": args.counts_per_mm}
        about |= {"source": "imported from the robot's conveyor frame"}
        lines = [f"imported: direction {section['direction']}, {args.counts_per_mm:g} counts/mm"]
    else:
        counts: list[int] = []
        points: list[list[float]] = []
        if args.points:
            counts, points = read_points(args.points)
        if args.observe:
            more = locate(args.config, args.observe)
            counts, points = counts + more[0], points + more[1]
        try:
            fit = fit_belt(counts, points, args.point_sigma_mm, args.bits)
        except DegenerateInputError as err:
            raise CalibrationError(str(err)) from None
        d = np.asarray(fit.direction)
        d = d - normal * float(d @ normal)  # the belt runs in its plane: drop the rest
        tilt = math.degrees(math.asin(min(1.0, abs(float(np.dot(fit.direction, normal))))))
        d = d / np.linalg.norm(d)
        scale_rel = fit.sigma_counts_per_mm / fit.counts_per_mm
        sigma = math.hypot(max(fit.rms_mm, args.point_sigma_mm),
                           SIGMA_TRAVEL_MM * scale_rel,
                           SIGMA_TRAVEL_MM * math.radians(fit.sigma_direction_deg))
        section |= {"direction": [round(float(v), 9) for v in d],
                    "counts_per_mm": round(fit.counts_per_mm, 9),
                    "origin_mm": [round(v, 4) for v in fit.origin_mm],
                    "sigma_mm": round(sigma, 4)}
        about |= {"observations": fit.observations, "rms_mm": fit.rms_mm,
                  "sigma_counts_per_mm": fit.sigma_counts_per_mm,
                  "sigma_direction_deg": fit.sigma_direction_deg,
                  "out_of_plane_deg": tilt,
                  "sigma_mm_over": f"{SIGMA_TRAVEL_MM:g} mm of travel"}
        lines = [f"belt from {fit.observations} observations: direction "
                 f"{section['direction']} +- {fit.sigma_direction_deg:.3g} deg, "
                 f"{fit.counts_per_mm:.6g} +- {fit.sigma_counts_per_mm:.2g} counts/mm, "
                 f"rms {fit.rms_mm:.3g} mm, out of the belt plane {tilt:.2f} deg"]
        if tilt > 0.5:
            lines.append(f"warning: the board moved {tilt:.2f} deg out of the plane with "
                         "normal --normal: check the normal, or the board slipped")
    path = write_result(Path(args.output), {"conveyor": section}, about,
                        "The belt (vgripd calibrate conveyor): include it and add window_mm, "
                        "trigger_distance_mm, speed_mm_s")
    emit(args, {"conveyor": section, "about": about, "output": str(path)},
         [*lines, f"wrote {path}"])
    return 0
