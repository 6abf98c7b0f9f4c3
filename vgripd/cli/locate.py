"""Locate the object in one stereo pair (LEFT RIGHT) or one image (LEFT) and print the result.

Prints the status, the object pose in the robot base frame, the offset against the taught
reference, the values the robot would receive (with the vendor's field names), residuals and
per-stage timings; ``--json`` prints the same as one JSON object. A job without a valid pose
adds a "why" block (``diagnosis`` in JSON): what each stage saw and the likely causes, each
naming the config key to check (``vgripd.vision.diagnosis``). ``--recipe N`` runs the
pipeline of recipe N (docs/recipes.md; an unknown number is a configuration error).

Exit codes: 0 a pose was found (status OK or OK_RECALIBRATE); 1 no valid pose (any other
status); 2 an image file is missing or unreadable; 78 configuration error.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from vgripd.config import load_config
from vgripd.service.worker.recorder import dict_from_result
from vgripd.types import ImagePair, JobResult
from vgripd.vision.checked import CheckedPipeline


class ImageFileError(Exception):
    """An image file given on the command line cannot be read."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-c", "--config", required=True, help="TOML configuration file")
    parser.add_argument("left", help="left image (or the only image in single-camera mode)")
    parser.add_argument("right", nargs="?", help="right image of the stereo pair")
    parser.add_argument("more", nargs="*", metavar="IMAGE",
                        help="a multi-camera cell (calibration.cameras): the images of the "
                             "third and further cameras, all in camera order")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--recipe", type=int, default=0, metavar="N",
                        help="the pipeline of recipe N ([recipes.N]; default 0, the top level)")


def read_image(path: str | Path) -> np.ndarray:
    """An 8-bit grey image from a file; ``ImageFileError`` naming the file otherwise."""
    p = Path(path)
    if not p.is_file():
        raise ImageFileError(f"{p}: no such image file")
    image = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
    if image is None or image.size == 0:
        raise ImageFileError(f"{p}: cannot decode image (corrupt or unsupported format)")
    return np.asarray(image)


def format_result(result: JobResult) -> str:
    """The human-readable report of one job."""
    lines = [f"status:    {result.status.name} ({int(result.status)})"]
    if result.message:
        lines.append(f"message:   {result.message}")
    lines.append(f"features:  used {' '.join(result.features_used) or '-'}; "
                 f"missing {' '.join(result.features_missing) or '-'}")

    def matrix(name: str, T: Any) -> None:
        if T is None:
            return
        lines.append(f"{name}:")
        lines.extend("  " + " ".join(f"{v:12.4f}" for v in row) for row in np.asarray(T))

    matrix("T_base_obj (mm)", result.T_base_obj)
    matrix("offset (mm)", result.offset)
    if result.target is not None:
        values = "  ".join(
            f"{f}={v:.4f}" for f, v in zip(result.target.fields, result.target.values, strict=True)
        )
        lines.append(f"robot ({result.target.vendor}): {values}")
    else:
        lines.append("robot:     nothing sent (no valid pose)")
    if result.residuals:
        lines.append("residuals: " + "  ".join(f"{k}={v:.4f}" for k, v in result.residuals.items()))
    lines.append("timings:   " + "  ".join(f"{k}={v:.1f}ms" for k, v in result.timings_ms.items()))
    if result.instances:
        pickable = sum(i.status.pose_valid for i in result.instances)
        lines.append(f"pick list: {pickable} pickable of {len(result.instances)} "
                     "(index status pick score x y z; message)")
        for k, inst in enumerate(result.instances):
            xyz = ("-" if inst.T_base_obj is None else
                   " ".join(f"{v:.2f}" for v in np.asarray(inst.T_base_obj)[:3, 3]))
            lines.append(f"  {k:2d} {inst.status.name:<17} {inst.pick_id:3d} {inst.score:5.3f} "
                         f"{xyz}{'; ' + inst.message if inst.message else ''}")
    if result.diagnosis is not None:
        lines.append("why:")
        lines.extend(result.diagnosis.lines())
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config).for_recipe(args.recipe)
    try:
        paths = [args.left] + ([args.right] if args.right is not None else []) + list(
            getattr(args, "more", None) or [])
        images = [read_image(path) for path in paths]
    except ImageFileError as err:
        print(f"vgripd locate: {err}", file=sys.stderr)
        return 2
    pipeline = CheckedPipeline(config)  # the daemon's: the check's findings first
    pair = ImagePair.of_views(images, time.monotonic_ns(), source=args.left)
    result = dataclasses.replace(pipeline.process(pair, job_id=1), recipe=args.recipe)
    if args.json:
        print(json.dumps(dict_from_result(result)))
    else:
        print(format_result(result))
    return 0 if result.status.pose_valid else 1
