"""The worker's warm-up of a pipeline (``vgripd.vision.pipeline.Pipeline``, typed ``Any`` here:
the pipeline imports this module) before it reports ready (vgripd.service.worker.process): one job
on made-up images, so the first real job does not pay for first calls."""

from __future__ import annotations

import time
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from vgripd.geometry.transforms import invert_transform
from vgripd.types import ImagePair, JobResult


def warm_up(pipeline: Any) -> JobResult:
    """One job on a made-up acquisition, run before the first real one (the worker does
    this for each recipe before it reports ready), so that the first real job does not pay
    for first calls: OpenCV's buffers and thread pool, the finders, the stereo rig's tables,
    matching, the pose fit. Mid-grey images of each camera's calibrated size; a fixed stereo
    rig whose object is all circle marks sees them drawn where the taught reference puts
    them (the whole chain runs); any other cell gets a dark and a bright disc per size the
    finders look for. Its result is for the log only, never published. Never raises."""
    models = pipeline.multi.cameras if pipeline.multi is not None else (
        (pipeline.left,) if pipeline.right is None else (pipeline.left, pipeline.right))
    views = [np.full((m.height or 1024, m.width or 1280), 128, np.uint8) for m in models]
    try:
        _draw_reference(pipeline, views)
    except Exception:  # noqa: BLE001 - a cell it cannot draw gets the plain discs
        for image in views:
            h, w = image.shape
            for k, spec in enumerate(pipeline.find_left.specs):
                r = max(2, int(0.25 * (spec.min_diameter_px + spec.max_diameter_px)))
                y = min(h - r - 1, (k + 1) * (4 * r + 4))
                cv2.circle(image, (w // 3, y), r, 40, -1)
                cv2.circle(image, (2 * w // 3, y), r, 220, -1)
    return pipeline.process(ImagePair.of_views(views, t_mono_ns=time.monotonic_ns(),
                                           source="warm-up"), 0)

def _draw_reference(pipeline: Any, views: list[npt.NDArray[np.uint8]]) -> None:
    """The circle marks at the taught reference pose, drawn into a stereo pair (ValueError
    for any other cell)."""
    if (pipeline.rig is None or pipeline.multi is not None or pipeline.fixed_T_base_camera is None
            or not pipeline.is_circle.all() or len(views) != 2):
        raise ValueError("not a fixed stereo rig of circle marks")
    T_left_obj = invert_transform(pipeline.fixed_T_base_camera) @ pipeline.T_base_obj_ref
    polarity = [getattr(f, "polarity", "dark") for f in pipeline.config.object.features]
    for image, T in zip(views, (T_left_obj, pipeline.rig.T_right_left @ T_left_obj),
                        strict=True):
        model = pipeline.left if image is views[0] else pipeline.right
        assert model is not None
        points = pipeline.model @ T[:3, :3].T + T[:3, 3]
        for (u, v), z, d, pol in zip(model.project(points), points[:, 2], pipeline.diameters,
                                     polarity, strict=True):
            r = max(2, round(0.5 * model.fx * d / z))
            cv2.circle(image, (round(u), round(v)), r, 40 if pol == "dark" else 220, -1)
