"""Pictures of a job for an operator: where the model landed, what was missing, the pose axes.

Drawn from the JobResult and the calibration only (no second pass of the finders): every model
feature is projected at the found pose and labelled by name, green when it was used for the
pose, red when it was missing; the object axes (x red, y green, z blue) are drawn from its
origin; in the right image, the epipolar line of each used left feature is drawn as a straight
line in ideal pixels (exact without lens distortion, within a pixel or so with the usual
distortion near the image centre). Without a pose only the status line is written. A pick list
draws every instance, labelled with its place in the list, status, pick id and score.

A failed job (``result.diagnosis``) also shows every candidate blob the finders saw, circled in
the colour of what became of it and labelled with the reason it was dropped (``CANDIDATE_COLOURS``:
size, contrast, circularity, border, of the other polarity, no epipolar partner, outside the
working distance, not matched to the model), and the top likely cause under the status line.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from vgripd.errors import VgripError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.transforms import invert_transform
from vgripd.types import FloatArray, ImagePair, JobResult
from vgripd.vision.pipeline import Pipeline

GREEN, RED, BLUE, YELLOW, WHITE = (0, 200, 0), (0, 0, 255), (255, 80, 0), (0, 220, 255), (255,) * 3

#: BGR colour per candidate fate (``vgripd.vision.diagnosis.CANDIDATE_REASONS``).
CANDIDATE_COLOURS: dict[str, tuple[int, int, int]] = {
    "used": GREEN,
    "kept": GREEN,
    "model": (0, 140, 255),  # orange: paired and triangulated, not matched to the model
    "depth": (255, 0, 255),  # magenta: triangulated outside vision.working_distance_mm
    "epipolar": (255, 255, 0),  # cyan: no partner on the epipolar line
    "size": RED,
    "contrast": (160, 0, 200),  # purple
    "circularity": (0, 128, 255),
    "border": (150, 150, 150),
    "polarity": BLUE,  # a blob of the other polarity that would have passed
}


def _bgr(image: Any) -> np.ndarray:
    arr = np.asarray(image)
    return cv2.cvtColor(arr, cv2.COLOR_GRAY2BGR) if arr.ndim == 2 else arr.copy()


def _pt(p: FloatArray) -> tuple[int, int]:
    return int(round(float(p[0]))), int(round(float(p[1])))


def _draw_model(img: np.ndarray, cam: CameraModel, T_cam_obj: FloatArray, pipeline: Pipeline,
                used: set[str], scale: int, shown: Any = None) -> None:
    """The model at a pose in one camera: each feature circled and named (green used, red
    missing), and the object's axes. ``shown``: (n,) which features to draw (a multi-camera
    cell: those this camera can see), default all; a feature behind the camera draws none."""
    keep = np.ones(len(pipeline.names), dtype=bool) if shown is None else np.asarray(shown)
    pts = pipeline.model @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
    if (pts[keep, 2] <= 0).any():
        return
    px = np.full((len(pts), 2), np.nan)
    if keep.any():
        px[keep] = cam.project(pts[keep])
    for name, p, k in zip(pipeline.names, px, keep, strict=True):
        if not k:
            continue
        colour = GREEN if name in used else RED
        cv2.circle(img, _pt(p), 6 * scale, colour, scale)
        cv2.putText(img, name, _pt(p + 8 * scale), cv2.FONT_HERSHEY_SIMPLEX, 0.5 * scale, colour,
                    scale)
    if shown is not None and T_cam_obj[2, 3] <= 0:
        return  # a multi-camera view with the object's origin behind it: no axes
    size = float(np.ptp(pipeline.model, axis=0).max()) / 2.0 or 10.0
    axes = np.array([[0, 0, 0], [size, 0, 0], [0, size, 0], [0, 0, size]], dtype=np.float64)
    ends = cam.project(axes @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3])
    for k, colour in ((1, RED), (2, GREEN), (3, BLUE)):
        cv2.arrowedLine(img, _pt(ends[0]), _pt(ends[k]), colour, 2 * scale, tipLength=0.1)


def annotate(pipeline: Pipeline, pair: ImagePair, result: JobResult) -> list[np.ndarray]:
    """BGR images (left, and right for a stereo pair; every camera's in camera order for a
    multi-camera cell) with the job drawn on them."""
    if pipeline.multi is not None:
        return _annotate_views(pipeline, pair, result)
    images = [_bgr(pair.left)] + ([_bgr(pair.right)] if pair.right is not None else [])
    scale = max(1, images[0].shape[1] // 1200)
    text = f"{result.status.name} {result.message}"[:120]
    for img in images:
        cv2.putText(img, text, (10, 30 * scale), cv2.FONT_HERSHEY_SIMPLEX, 0.8 * scale, YELLOW,
                    2 * scale)
    if result.diagnosis is not None:
        _draw_diagnosis(images, result.diagnosis, scale)
    if result.T_base_obj is None:
        return images
    T_camera_base = invert_transform(pipeline.T_base_camera(pair))
    T_cam_obj = T_camera_base @ result.T_base_obj
    used = set(result.features_used)
    _draw_model(images[0], pipeline.left, T_cam_obj, pipeline, used, scale)
    rig = pipeline.rig
    # A pick list: every other instance too, each labelled with its place in the list, its
    # status and pick id (docs/picklists.md).
    for k, inst in enumerate(result.instances):
        if inst.T_base_obj is None:
            continue
        T_k = T_camera_base @ inst.T_base_obj
        if k:
            _draw_model(images[0], pipeline.left, T_k, pipeline, set(inst.features_used), scale)
            if len(images) == 2 and rig is not None:
                _draw_model(images[1], rig.right, rig.T_right_left @ T_k, pipeline,
                            set(inst.features_used), scale)
        if T_k[2, 3] > 0:
            label = f"#{k} {inst.status.name} pick {inst.pick_id} score {inst.score:.2f}"
            colour = GREEN if inst.status.pose_valid else RED
            at = pipeline.left.project(T_k[None, :3, 3])[0] + (-40 * scale, 24 * scale)
            cv2.putText(images[0], label, _pt(at), cv2.FONT_HERSHEY_SIMPLEX, 0.6 * scale,
                        colour, 2 * scale)
    if len(images) == 2 and rig is not None:
        T_right_obj = rig.T_right_left @ T_cam_obj
        _draw_model(images[1], rig.right, T_right_obj, pipeline, used, scale)
        sel = [i for i, n in enumerate(pipeline.names) if n in used]
        pts = pipeline.model[sel] @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
        if len(sel) and (pts[:, 2] > 0).all():
            w = images[1].shape[1]
            for a, b, c in rig.epipolar_lines_right(pipeline.left.project(pts)):
                if abs(b) > 1e-9:
                    cv2.line(images[1], (0, int(round(-c / b))), (w, int(round(-(c + a * w) / b))),
                             WHITE, scale)
    return images


def _annotate_views(pipeline: Pipeline, pair: ImagePair, result: JobResult
                    ) -> list[np.ndarray]:
    """A multi-camera job: every camera's image with its name and the status; with a pose,
    the model in each camera where that camera can see it (a mark facing away, or outside
    the image, is left out rather than drawn through the object)."""
    multi = pipeline.multi
    assert multi is not None
    images = [_bgr(v) for v in pair.views]
    scale = max(1, max(img.shape[1] for img in images) // 1200)
    text = f"{result.status.name} {result.message}"[:120]
    names = list(multi.names) + [f"image {j}" for j in range(len(multi.names), len(images))]
    for img, name in zip(images, names, strict=False):
        cv2.putText(img, text, (10, 30 * scale), cv2.FONT_HERSHEY_SIMPLEX, 0.8 * scale, YELLOW,
                    2 * scale)
        cv2.putText(img, f"camera {name}", (10, img.shape[0] - 12 * scale),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.7 * scale, YELLOW, 2 * scale)
    if result.diagnosis is not None:
        _draw_diagnosis(images, result.diagnosis, scale)
    if result.T_base_obj is None or len(images) != len(multi.cameras):
        return images
    try:
        view = multi.view(pair.T_base_flange)
    except VgripError:  # robot-mounted without the flange pose: the status says why
        return images
    seen = multi.visible(view, result.T_base_obj)
    used = set(result.features_used)
    for j, (img, cam) in enumerate(zip(images, multi.cameras, strict=True)):
        T_cam_obj = view.T_cameras_base[j] @ result.T_base_obj
        _draw_model(img, cam, T_cam_obj, pipeline, used, scale, shown=seen[:, j])
    return images


def _draw_diagnosis(images: list[np.ndarray], diagnosis: Any, scale: int) -> None:
    """Every candidate blob of each image with its fate, and the top cause under the status."""
    for img, stage in zip(images, diagnosis.images, strict=False):
        for c in stage.candidates:
            colour = CANDIDATE_COLOURS.get(c.reason, WHITE)
            centre = (int(round(c.x)), int(round(c.y)))
            radius = max(4, int(round(0.5 * c.diameter_px)) + 3)
            cv2.circle(img, centre, radius, colour, scale)
            if c.label:
                cv2.putText(img, c.label, (centre[0] + radius + 2, centre[1] + 4),
                            cv2.FONT_HERSHEY_SIMPLEX, 0.45 * scale, colour, scale)
    top = diagnosis.top
    if top is not None:
        text = f"likely: {top.key}: {top.reason}"
        for img in images:
            for k in range(0, min(len(text), 360), 120):  # up to three lines
                cv2.putText(img, text[k:k + 120], (10, (60 + 25 * (k // 120)) * scale),
                            cv2.FONT_HERSHEY_SIMPLEX, 0.55 * scale, YELLOW, scale)
