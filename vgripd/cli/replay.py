"""Run every frame (image pair) of a folder through the pipeline: one JSON line per frame, then a
summary.

Which files: the config's own replay layout when its ``[camera]`` is ``type = "replay"``
(``left_glob`` + ``right_glob``, or ``glob``, plus ``grayscale`` and ``flange_poses``), with
``DIR`` in place of its ``folder``. Any other camera type: ``left*`` + ``right*`` when the config
calibrates a stereo rig, else ``left*`` (or every image when there is no ``left*``). A folder
written by the job recorder (``pair.json`` beside ``left.png``) is replayed as recorded:
``left.png`` (+ ``right.png``). Only image files count; others a pattern matches (``truth.json``)
are skipped and named on stderr. Frames are listed and paired by
``vgripd.imagefiles.list_frames``, the function the replay camera driver opens with, so
this command and a daemon replaying the same folder see the same pairs.

Refused before any job runs (one line naming the folder and the patterns, exit 1): no image
matches; a stereo layout or a stereo config with no right image; a file without its partner;
a stereo config whose ``[camera]`` replays single images.

The last line is ``{"summary": {...}}``: frames, pairs processed, unreadable frames, found rate,
counts per status, residual statistics (median, max over the found poses), the total job time
percentiles p50/p95/p99 (ms) and the skipped non-image files.

Recipes (docs/recipes.md): the frames run through the pipeline of ``--recipe N``; without it,
through the recipe a recorded job ran (its ``result.json``), else recipe 0.

``--annotate OUTDIR`` writes ``<name>_left.png`` (and ``_right.png``) per pair: the model
features at the found pose, labelled, green used / red missing, the object axes, epipolar lines.
A multi-camera cell: ``frame<NNNN>_<camera>.png`` for every camera of every frame (job number
from 1), each with the marks that camera can see at the found pose.

Exit codes: 0 every frame was read and processed (whatever its status); 1 a frame could not be
read (corrupt or vanished file: its line has status ``CAMERA_ERROR``, the rest still run) or the
folder was refused; 78 configuration error.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from vgripd.config import Config, DriverSection, load_config
from vgripd.errors import CameraError
from vgripd.imagefiles import Frames, list_frames, list_images, list_views
from vgripd.registry import CAMERAS, load_class, validate_options
from vgripd.service.worker.recorder import dict_from_result
from vgripd.types import ImagePair, JobResult
from vgripd.vision.annotate import annotate
from vgripd.vision.checked import CheckedPipeline

GRAB_TIMEOUT_S = 30.0
LAYOUT_KEYS = ("glob", "left_glob", "right_glob")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-c", "--config", required=True, help="TOML configuration file")
    parser.add_argument("folder", help="folder with the images (replaces the config's "
                                       "[camera] folder; its left_glob/right_glob apply)")
    parser.add_argument("--annotate", metavar="OUTDIR", help="write annotated images here")
    parser.add_argument("--recipe", type=int, default=None, metavar="N",
                        help="run recipe N's pipeline (default: the recorded job's recipe, "
                             "else 0)")


def recorded_recipe(folder: Path) -> int:
    """The recipe a job folder written by the recorder ran (0 when not recorded or older)."""
    try:
        recipe = json.loads((folder / "result.json").read_text(encoding="utf-8")).get("recipe", 0)
    except (OSError, ValueError, AttributeError):
        return 0
    return recipe if isinstance(recipe, int) else 0


def is_stereo_config(config: Config) -> bool:
    """True when the config calibrates a stereo rig (right camera and T_right_left)."""
    cal = config.calibration
    return cal is not None and cal.right is not None and cal.stereo is not None


def replay_section(config: Config, folder: Path) -> DriverSection:
    """The replay camera options for ``folder`` under ``config`` (module docstring)."""
    cameras = config.calibration.cameras if config.calibration is not None else None
    if cameras is not None:  # a multi-camera cell: one glob per camera
        if (folder / "pair.json").is_file() and (folder / "view0.png").is_file():
            globs = [f"view{j}.png" for j in range(len(cameras))]  # a recorded job
        elif config.camera.type == "replay" and config.camera.options().get("globs"):
            globs = list(config.camera.options()["globs"])
        else:
            globs = [f"{cam.name}*" for cam in cameras]
        return DriverSection.model_validate({"type": "replay", "folder": str(folder),
                                             "globs": globs})
    if (folder / "pair.json").is_file() and (folder / "left.png").is_file():
        layout: dict[str, Any] = (
            {"left_glob": "left.png", "right_glob": "right.png"}
            if (folder / "right.png").is_file() or is_stereo_config(config)
            else {"glob": "left.png"})
        return DriverSection.model_validate({"type": "replay", "folder": str(folder), **layout})
    camera = config.camera
    if camera.type == "replay":
        options = camera.options()
        options.update(folder=str(folder), loop=False)
        if options.get("glob") is not None and is_stereo_config(config):
            raise CameraError(
                f"replay: the config calibrates a stereo rig but its [camera] replays single "
                f"images (glob = {options['glob']!r}); set left_glob and right_glob to replay "
                f"the pairs in {folder}")
        return DriverSection.model_validate({"type": "replay", **options})
    if is_stereo_config(config):
        layout = {"left_glob": "left*", "right_glob": "right*"}
    else:
        layout = {"glob": "left*" if list_images(folder, "left*")[0] else "*"}
    return DriverSection.model_validate({"type": "replay", "folder": str(folder), **layout})


def frames_of(section: DriverSection) -> Frames:
    """The frames the replay camera built from ``section`` will deliver (same function)."""
    o = section.options()
    if o.get("globs"):
        views = list_views(Path(o["folder"]), o["globs"])
        return Frames(Path(o["folder"]), views[0], None, "name")
    return list_frames(Path(o["folder"]), **{k: o.get(k) for k in LAYOUT_KEYS})


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


async def _grab_all(camera: Any, frames: Frames,
                    handle: Callable[[int, ImagePair], None]) -> list[dict[str, Any]]:
    """Grab every frame from the replay camera and hand each to ``handle``; frames that could
    not be read are printed as ``CAMERA_ERROR`` lines and returned."""
    unreadable = []
    await camera.open()
    try:
        for job_id in range(1, len(frames) + 1):
            try:
                pair = await camera.grab(GRAB_TIMEOUT_S)
            except CameraError as err:  # a corrupt or vanished file: report it and go on
                line = {"job_id": job_id, "source": f"replay:{frames.left[job_id - 1].name}",
                        "status": "CAMERA_ERROR", "message": str(err)}
                print(json.dumps(line), flush=True)
                unreadable.append(line)
                continue
            handle(job_id, pair)
    finally:
        await camera.close()
    return unreadable


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    folder = Path(args.folder)
    if not folder.is_dir():
        raise CameraError(f"replay: {folder} is not a folder")
    section = replay_section(config, folder)
    frames = frames_of(section)  # refuses an empty or unpaired folder before any job
    if frames.skipped:
        print(f"replay: skipped {len(frames.skipped)} non-image file(s) in {folder}: "
              + ", ".join(p.name for p in frames.skipped), file=sys.stderr)
    recipe = recorded_recipe(folder) if args.recipe is None else args.recipe
    pipeline = CheckedPipeline(config.for_recipe(recipe))  # as the daemon diagnoses
    cls = load_class(CAMERAS, "camera", "replay")
    camera = cls(validate_options(cls, section, "camera"), config)
    out = Path(args.annotate) if args.annotate else None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    results: list[JobResult] = []

    def handle(job_id: int, pair: ImagePair) -> None:
        result = dataclasses.replace(pipeline.process(pair, job_id), recipe=recipe)
        results.append(result)
        print(json.dumps({"source": pair.source, **dict_from_result(result)}), flush=True)
        if out is None:
            return
        images = annotate(pipeline, pair, result)
        if pipeline.multi is not None:  # <frame>_<camera>.png, one per camera
            for name, image in zip(pipeline.multi.names, images, strict=False):
                cv2.imwrite(str(out / f"frame{job_id:04d}_{name}.png"), image)
            return
        stem = Path(str(pair.meta.get("left_path", f"pair{job_id}"))).stem
        for side, image in zip(("left", "right"), images, strict=False):
            cv2.imwrite(str(out / f"{stem}_{side}.png"), image)

    unreadable = asyncio.run(_grab_all(camera, frames, handle))
    print(json.dumps({"summary": {
        "frames": len(frames), "unreadable": len(unreadable), **summary(results),
        "skipped": [p.name for p in frames.skipped]}}))
    if unreadable:
        print(f"replay: {len(unreadable)} of {len(frames)} frame(s) in {folder} could not be "
              "read (CAMERA_ERROR lines above)", file=sys.stderr)
        return 1
    return 0
