"""Run every image pair of a folder through the pipeline: one JSON line per pair, then a summary.

Pairs are ``left*``/``right*`` files matched by natural sort order, read by the replay camera
driver (a folder without ``right*`` files is single-camera: every ``left*`` file, or every file
when there is no ``left*`` either). The last line is ``{"summary": {...}}``: pairs, found rate,
counts per status, residual statistics (median, max over the found poses) and the total job
time percentiles p50/p95/p99 (ms).

``--annotate OUTDIR`` writes ``<name>_left.png`` (and ``_right.png``) per pair: the model
features at the found pose, labelled, green used / red missing, the object axes, epipolar lines.

Exit codes: 0 every pair was processed (whatever its status); 1 the folder has no images;
78 configuration error.
"""

from __future__ import annotations

import argparse
import asyncio
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from vgripd.config import DriverSection, load_config
from vgripd.errors import CameraError
from vgripd.registry import CAMERAS, load_class, validate_options
from vgripd.service.recorder import dict_from_result
from vgripd.types import ImagePair, JobResult
from vgripd.vision.annotate import annotate
from vgripd.vision.pipeline import Pipeline

GRAB_TIMEOUT_S = 30.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-c", "--config", required=True, help="TOML configuration file")
    parser.add_argument("folder", help="folder with left*/right* image files")
    parser.add_argument("--annotate", metavar="OUTDIR", help="write annotated images here")


def replay_section(folder: Path) -> DriverSection:
    """The replay camera options for a folder (stereo when it has ``right*`` files)."""
    if any(folder.glob("right*")):
        return DriverSection.model_validate(
            {"type": "replay", "folder": str(folder), "left_glob": "left*", "right_glob": "right*"}
        )
    pattern = "left*" if any(folder.glob("left*")) else "*"
    return DriverSection.model_validate({"type": "replay", "folder": str(folder), "glob": pattern})


def summary(results: list[JobResult]) -> dict[str, Any]:
    """Found rate, status counts, residual and timing statistics over a run."""
    found = [r for r in results if r.status.pose_valid]
    counts: dict[str, int] = {}
    for r in results:
        counts[r.status.name] = counts.get(r.status.name, 0) + 1
    residuals: dict[str, dict[str, float]] = {}
    for key in sorted({k for r in found for k in r.residuals}):
        values = np.array([r.residuals[key] for r in found if key in r.residuals])
        residuals[key] = {"median": float(np.median(values)), "max": float(values.max())}
    totals = np.array([r.timings_ms.get("total", 0.0) for r in results])
    timing = (
        {f"p{q}": float(np.percentile(totals, q)) for q in (50, 95, 99)} if totals.size else {}
    )
    return {
        "pairs": len(results),
        "found": len(found),
        "found_rate": len(found) / len(results) if results else 0.0,
        "status_counts": counts,
        "residuals": residuals,
        "total_ms": timing,
    }


async def _grab_all(camera: Any, count: int, handle: Callable[[int, ImagePair], None]) -> None:
    """Grab ``count`` frames from the open-able replay camera and hand each to ``handle``."""
    await camera.open()
    try:
        for job_id in range(1, count + 1):
            try:
                pair = await camera.grab(GRAB_TIMEOUT_S)
            except CameraError as err:  # a corrupt file: report it and go on
                print(json.dumps({"job_id": job_id, "status": "CAMERA_ERROR",
                                  "message": str(err)}), flush=True)
                continue
            handle(job_id, pair)
    finally:
        await camera.close()


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    pipeline = Pipeline(config)
    folder = Path(args.folder)
    if not folder.is_dir():
        raise CameraError(f"replay: {folder} is not a folder")
    section = replay_section(folder)
    cls = load_class(CAMERAS, "camera", "replay")
    camera = cls(validate_options(cls, section, "replay"), config)
    out = Path(args.annotate) if args.annotate else None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    pattern = section.options().get("left_glob") or section.options()["glob"]
    count = sum(1 for p in folder.glob(pattern) if p.is_file())
    results: list[JobResult] = []

    def handle(job_id: int, pair: ImagePair) -> None:
        result = pipeline.process(pair, job_id)
        results.append(result)
        print(json.dumps({"source": pair.source, **dict_from_result(result)}), flush=True)
        if out is not None:
            stem = Path(str(pair.meta.get("left_path", f"pair{job_id}"))).stem
            images = annotate(pipeline, pair, result)
            for side, image in zip(("left", "right"), images, strict=False):
                cv2.imwrite(str(out / f"{stem}_{side}.png"), image)

    asyncio.run(_grab_all(camera, count, handle))
    print(json.dumps({"summary": summary(results)}))
    return 0
