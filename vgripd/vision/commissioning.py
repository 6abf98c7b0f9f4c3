"""Commissioning checks of the scene: does the taught reference object show up where the finder
can find it? (``vgripd check``, docs/daemon.md "vgripd check").

The reference object (``reference.T_base_obj`` and the model points) is carried through the
hand-eye pose into each camera and projected. For every mark: in front of the camera, inside
the image (with its own radius of margin), within ``vision.working_distance_mm`` of the left
camera, and imaged at a size the finder searches for; then whether enough marks land in both
images for a pose at all. When the marks land behind a camera or outside the images, the same
projection is tried with ``calibration.hand_eye`` inverted and with ``reference.T_base_obj``
inverted (a transform written in the opposite direction is the usual mistake): when one of those
puts every mark inside both images, the finding names it.

Each finding has a level (ERROR: the config cannot give a pose; WARNING: it can, with a
weakness), the config key to fix and a one-line message with the numbers. Pure CPU, no I/O.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

from vgripd.config import MIN_PNP_FEATURES
from vgripd.errors import VgripError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.transforms import invert_transform
from vgripd.types import FloatArray
from vgripd.vision.pipeline import Pipeline
from vgripd.vision.views_locator import ViewsLocator

Level = Literal["ERROR", "WARNING", "NOTE"]

#: OpenCV's ArUco detector (default ``minMarkerPerimeterRate``) ignores a marker whose outline
#: is shorter than this share of the larger image side.
ARUCO_MIN_PERIMETER_RATE = 0.03

#: A circle seen this far off its normal is a thin ellipse the circularity test may refuse.
MAX_VIEW_ANGLE_DEG = 60.0

_RIM = np.stack([np.cos(np.linspace(0, 2 * np.pi, 36, endpoint=False)),
                 np.sin(np.linspace(0, 2 * np.pi, 36, endpoint=False))], axis=1)


@dataclass(frozen=True)
class Finding:
    """One result of a commissioning check: ``key`` is the config key to look at."""

    level: Level
    key: str
    message: str

    def __str__(self) -> str:
        return f"{self.key}: {self.message}"


@dataclass(frozen=True)
class View:
    """The reference object as one camera sees it (one entry per model point)."""

    side: str  # "left" | "right"
    camera: CameraModel
    depth_mm: FloatArray  # (n,) along the optical axis; <= 0 is behind the camera
    px: FloatArray  # (n, 2) projected centres (nan behind the camera)
    size_px: FloatArray  # (n,) imaged diameter (circles) or side (ArUco); nan otherwise
    view_deg: FloatArray  # (n,) angle between the mark's normal (object z) and the camera ray
    inside: npt.NDArray[np.bool_]  # (n,): in front and inside the image, margin included

    @property
    def image(self) -> str:
        return f"the {self.side} image ({self.camera.width}x{self.camera.height})"


def _normalized_bounds(camera: CameraModel) -> tuple[float, float]:
    """Largest |X/Z| and |Y/Z| that land in the image (corners and edge midpoints undistorted):
    beyond them a distortion polynomial can fold a far-off point back into the picture."""
    w, h = camera.width - 1.0, camera.height - 1.0
    px = np.array([(0, 0), (w, 0), (0, h), (w, h), (w / 2, 0), (w / 2, h), (0, h / 2),
                   (w, h / 2)], dtype=np.float64)
    try:
        xy = camera.undistort(px)
    except VgripError:
        return np.inf, np.inf
    return float(np.abs(xy[:, 0]).max() * 1.05), float(np.abs(xy[:, 1]).max() * 1.05)


def _view(side: str, camera: CameraModel, T_cam_obj: FloatArray, pipeline: Pipeline) -> View:
    model = pipeline.model
    n = model.shape[0]
    R, t = T_cam_obj[:3, :3], T_cam_obj[:3, 3]
    cam = model @ R.T + t
    depth = cam[:, 2].copy()
    px = np.full((n, 2), np.nan)
    size = np.full(n, np.nan)
    inside = np.zeros(n, dtype=bool)
    normal = R[:, 2]
    ray = -cam / np.maximum(np.linalg.norm(cam, axis=1, keepdims=True), 1e-9)
    view_deg = np.degrees(np.arccos(np.clip(ray @ normal, -1.0, 1.0)))
    bound_x, bound_y = _normalized_bounds(camera)
    features = pipeline.config.object.features
    for i in range(n):
        if depth[i] <= 1.0:
            continue
        px[i] = camera.project(cam[i : i + 1])[0]
        f = features[i]
        outline: FloatArray | None = None
        if f.kind == "circle":
            outline = 0.5 * f.diameter_mm * _RIM
        elif f.kind == "aruco":
            outline = 0.5 * f.size_mm * np.array([(-1, -1), (1, -1), (1, 1), (-1, 1)], float)
        margin = 0.0
        if outline is not None:
            rim = np.zeros((outline.shape[0], 3))
            rim[:, :2] = outline
            rim = (rim + model[i]) @ R.T + t
            if (rim[:, 2] > 1.0).all():
                q = camera.project(rim)
                x, y = q[:, 0], q[:, 1]
                area = abs(float((x * np.roll(y, -1) - np.roll(x, -1) * y).sum())) / 2.0
                if f.kind == "circle":
                    size[i] = 2.0 * np.sqrt(area / np.pi)  # the finder's equivalent diameter
                    margin = size[i] / 2.0
                else:
                    size[i] = np.sqrt(area)
                    margin = size[i] / np.sqrt(2.0)
        u, v = px[i]
        inside[i] = bool(
            margin <= u <= camera.width - 1 - margin and margin <= v <= camera.height - 1 - margin
            and abs(cam[i, 0] / depth[i]) <= bound_x and abs(cam[i, 1] / depth[i]) <= bound_y)
    return View(side, camera, depth, px, size, view_deg, inside)


def _views(pipeline: Pipeline, T_base_camera: FloatArray, T_base_obj_ref: FloatArray
           ) -> list[View]:
    T_cam_obj = invert_transform(T_base_camera) @ T_base_obj_ref
    views = [_view("left", pipeline.left, T_cam_obj, pipeline)]
    if pipeline.rig is not None:
        views.append(_view("right", pipeline.rig.right, pipeline.rig.T_right_left @ T_cam_obj,
                           pipeline))
    return views


def _all_placed(views: Sequence[View]) -> bool:
    return all(bool(v.inside.all()) for v in views)


def _names(names: Sequence[str], most: int = 4) -> str:
    text = ", ".join(names[:most])
    return text + (f" and {len(names) - most} more" if len(names) > most else "")


def _placement_summary(views: Sequence[View], names: Sequence[str]) -> str:
    """What is wrong with where the marks land, in one clause."""
    for v in views:
        behind = v.depth_mm <= 1.0
        if behind.all():
            return (f"the object is {-float(np.median(v.depth_mm)):.0f} mm BEHIND the {v.side} "
                    "camera")
        if behind.any():
            return (f"marks {_names([names[int(i)] for i in np.flatnonzero(behind)])} are behind "
                    f"the {v.side} camera")
    for v in views:
        out = np.flatnonzero(~v.inside)
        if out.size:
            i = int(out[0])
            return (f"{out.size} of {len(names)} marks project outside {v.image}, "
                    f"{names[i]} to ({v.px[i, 0]:.0f}, {v.px[i, 1]:.0f}) px")
    return "every mark lands inside the images"


def _inversions(pipeline: Pipeline, T_bc: FloatArray, T_ref: FloatArray) -> list[str]:
    """The keys whose transform, inverted, puts every mark inside every image."""
    trials = [("calibration.hand_eye", invert_transform(T_bc), T_ref)]
    if pipeline.config.object.definition == "cad":
        trials.append(("reference.T_base_obj", T_bc, invert_transform(T_ref)))
    hits = []
    for key, bc, ref in trials:
        try:
            if _all_placed(_views(pipeline, bc, ref)):
                hits.append(key)
        except VgripError:
            continue
    return hits


_INVERTED_HINT = {
    "calibration.hand_eye": "T_base_camera is the camera's pose in the robot base frame, not the "
                            "base's pose in the camera frame",
    "reference.T_base_obj": "T_base_obj is the object's pose in the robot base frame, not the "
                            "base's pose in the object frame",
}


def check_scene(pipeline: Pipeline) -> list[Finding]:
    """Where the taught reference object lands in each camera (module docstring)."""
    config = pipeline.config
    assert config.calibration is not None  # Pipeline() raised otherwise
    if pipeline.multi is not None:
        return check_cameras(pipeline, pipeline.multi)
    if pipeline.fixed_T_base_camera is None:
        return [Finding("NOTE", "calibration.hand_eye",
                        "robot-mounted camera: where the object lands in the images depends on "
                        "the flange pose at capture, so the projection checks are skipped")]
    names = list(pipeline.names)
    n = len(names)
    T_bc, T_ref = pipeline.fixed_T_base_camera, pipeline.T_base_obj_ref
    views = _views(pipeline, T_bc, T_ref)
    stereo = len(views) == 2
    needed = config.vision.min_features if stereo else max(config.vision.min_features,
                                                          MIN_PNP_FEATURES)
    findings: list[Finding] = []
    usable = np.ones(n, dtype=bool)
    for v in views:
        behind = np.flatnonzero(v.depth_mm <= 1.0)
        if behind.size:
            usable[behind] = False
            worst = int(behind[np.argmin(v.depth_mm[behind])])
            findings.append(Finding(
                "ERROR", "calibration.hand_eye",
                f"{behind.size} of {n} marks are behind the {v.side} camera ({names[worst]} "
                f"{-v.depth_mm[worst]:.0f} mm behind it): check calibration.hand_eye and "
                "reference.T_base_obj"))
        outside = [int(i) for i in np.flatnonzero(~v.inside) if v.depth_mm[i] > 1.0]
        usable[outside] = False
        if outside:
            where = [f"{names[i]} to ({v.px[i, 0]:.0f}, {v.px[i, 1]:.0f}) px" for i in outside]
            which = (f"mark {where[0].replace(' to ', ' projects to ')}, outside {v.image}"
                     if len(outside) == 1 else
                     f"{len(outside)} of {n} marks project outside {v.image}: "
                     f"{_names(where, 3)}")
            findings.append(Finding(
                "ERROR", "reference.T_base_obj",
                f"{which}; check calibration.hand_eye and reference.T_base_obj"))
    findings += _distance_and_size(pipeline, views, names, usable)
    # A mark the finder cannot see is an ERROR only when too few remain for a pose.
    left_over = int(usable.sum())
    if left_over >= needed:
        return [Finding("WARNING" if f.level == "ERROR" else f.level, f.key, f.message)
                for f in findings]
    if not _all_placed(views):
        summary = _placement_summary(views, names)
        inside = "both images" if stereo else "the image"
        findings[:0] = [Finding(
            "ERROR", key,
            f"looks inverted: {summary}; with the transform inverted all {n} marks would be in "
            f"front of the camera{'s' if stereo else ''}, inside {inside} "
            f"({_INVERTED_HINT[key]})") for key in _inversions(pipeline, T_bc, T_ref)]
    overlap = "both images" if stereo else "the image"
    findings.append(Finding(
        "ERROR", "vision.min_features" if left_over >= 3 else findings[0].key,
        f"only {left_over} of {n} marks can be found in {overlap}, a pose needs {needed} "
        f"(vision.min_features = {config.vision.min_features})"))
    return findings


def _marks(names: Sequence[str], rows: Sequence[int], values: Sequence[float], unit: str,
           verb: str) -> str:
    """``mark m2 is 35.0 px`` or ``3 marks (m1, m2, m3) are 25.4-26.8 px``."""
    digits = 1 if unit == "px" else 0
    if len(rows) == 1:
        return f"mark {names[rows[0]]} {verb} {values[0]:.{digits}f} {unit}"
    listed = _names([names[i] for i in rows])
    verb = verb.replace("is", "are", 1)
    return (f"{len(rows)} marks ({listed}) {verb} {min(values):.{digits}f}-"
            f"{max(values):.{digits}f} {unit}")


def _distance_and_size(pipeline: Pipeline, views: Sequence[View], names: Sequence[str],
                       usable: npt.NDArray[np.bool_]) -> list[Finding]:
    """Depth against the working distance, imaged size against the finder's range, and the
    viewing angle, for marks that land inside the images (one finding per check and camera)."""
    config = pipeline.config
    near, far = config.vision.working_distance_mm
    findings: list[Finding] = []
    left = views[0]
    if len(views) == 2:  # the stereo points outside the working distance are discarded
        rows = [int(i) for i in np.flatnonzero(left.inside)
                if not near <= left.depth_mm[i] <= far]
        if rows:
            usable[rows] = False
            findings.append(Finding(
                "ERROR", "vision.working_distance_mm",
                f"{_marks(names, rows, [float(left.depth_mm[i]) for i in rows], 'mm', 'is')} "
                f"from the left camera, outside vision.working_distance_mm [{near:g}, {far:g}]"
                ": the pipeline discards stereo points there"))
    features = config.object.features
    for v, finder in zip(views, [pipeline.find_left, pipeline.find_right], strict=False):
        if finder is None:
            continue
        wrong: dict[tuple[float, float], list[int]] = {}
        small: list[int] = []
        aruco_min = ARUCO_MIN_PERIMETER_RATE * max(v.camera.width, v.camera.height) / 4.0
        for i in (int(k) for k in np.flatnonzero(v.inside)):
            f = features[i]
            size = float(v.size_px[i])
            if not np.isfinite(size):
                continue
            if f.kind == "circle":
                spec = next(s for s in finder.specs if s.polarity == f.polarity)
                if not spec.min_diameter_px <= size <= spec.max_diameter_px:
                    wrong.setdefault((spec.min_diameter_px, spec.max_diameter_px), []).append(i)
            elif f.kind == "aruco" and size < aruco_min:
                small.append(i)
        for (lo, hi), rows in wrong.items():
            usable[rows] = False
            sizes = [float(v.size_px[i]) for i in rows]
            findings.append(Finding(
                "ERROR", "vision.working_distance_mm",
                f"{_marks(names, rows, sizes, 'px', 'is')} across in the {v.side} image, the "
                f"finder searches {lo:.1f}-{hi:.1f} px (the marks' diameter_mm over "
                f"vision.working_distance_mm [{near:g}, {far:g}])"))
        if small:
            usable[small] = False
            sizes = [float(v.size_px[i]) for i in small]
            findings.append(Finding(
                "ERROR", f"object.features[{small[0]}].size_mm",
                f"ArUco {_marks(names, small, sizes, 'px', 'is')} a side in the {v.side} image, "
                f"the detector needs at least {aruco_min:.1f} px"))
        slanted = [int(i) for i in np.flatnonzero(v.inside)
                   if features[i].kind != "template" and v.view_deg[i] > MAX_VIEW_ANGLE_DEG]
        if slanted:
            angles = [float(v.view_deg[i]) for i in slanted]
            face = ("from behind (they face away from it)" if min(angles) > 90
                    else "at a grazing angle")
            findings.append(Finding(
                "WARNING", "reference.T_base_obj",
                f"{_marks(names, slanted, angles, 'deg', 'is seen at')} off its normal "
                f"(object z) by the {v.side} camera: seen {face}"))
    return findings


def check_cameras(pipeline: Pipeline, multi: ViewsLocator) -> list[Finding]:
    """A multi-camera cell (docs/multicamera.md): which marks of the reference object each
    camera sees (in front, facing it, inside its image), their imaged size against the finder's
    range, and whether enough marks are seen by two or more cameras for a pose."""
    config = pipeline.config
    flanges = None
    if not multi.fixed:
        if not pipeline.view_poses:
            return [Finding("NOTE", "calibration.cameras",
                            "a robot-mounted camera: where the object lands in its image "
                            "depends on the flange pose at capture, so the projection checks "
                            "are skipped")]
        flanges = np.stack(pipeline.view_poses)  # several views: each at its taught pose
    names = list(pipeline.names)
    view = multi.view(flanges)
    T_ref = pipeline.T_base_obj_ref
    seen = multi.visible(view, T_ref)  # (n, N)
    X = pipeline.model @ T_ref[:3, :3].T + T_ref[:3, 3]
    findings: list[Finding] = []
    usable = seen.copy()
    for j, (cam, cam_name) in enumerate(zip(multi.cameras, multi.names, strict=True)):
        pose_key = (f"calibration.cameras.{j}.T_base_camera" if flanges is None
                    else f"vision.view_poses.{j}")
        if not seen[:, j].any():
            findings.append(Finding(
                "WARNING", pose_key,
                f"camera {cam_name} sees none of the marks of the object at its taught place "
                f"(reference.T_base_obj): check {pose_key}"))
            continue
        finder = pipeline.finders[j]
        depth = np.linalg.norm(X - view.centres_mm[j], axis=1)
        wrong = []
        for i in np.flatnonzero(seen[:, j]):
            f = config.object.features[i]
            if f.kind != "circle":
                continue
            size = cam.fx * f.diameter_mm / depth[i]
            spec = next(s for s in finder.specs if s.polarity == f.polarity)
            if not spec.min_diameter_px <= size <= spec.max_diameter_px:
                wrong.append((int(i), size, spec))
        if wrong:
            usable[[i for i, _, _ in wrong], j] = False
            near, far = config.vision.working_distance_mm
            rows = [i for i, _, _ in wrong]
            spec = wrong[0][2]
            findings.append(Finding(
                "ERROR", "vision.working_distance_mm",
                f"{_marks(names, rows, [s for _, s, _ in wrong], 'px', 'is')} across in camera "
                f"{cam_name}'s image, the finder searches {spec.min_diameter_px:.1f}-"
                f"{spec.max_diameter_px:.1f} px (the marks' diameter_mm over "
                f"vision.working_distance_mm [{near:g}, {far:g}])"))
    twice = int((usable.sum(axis=1) >= 2).sum())
    needed = config.vision.min_features
    if twice < needed:
        findings.append(Finding(
            "ERROR", "calibration.cameras",
            f"only {twice} of {len(names)} marks are seen by two or more cameras at the taught "
            f"place, a pose needs {needed} (vision.min_features = {needed})"))
    else:
        findings = [Finding("WARNING" if f.level == "ERROR" else f.level, f.key, f.message)
                    for f in findings]
    for g_name, members in multi.groups:
        if len(members) >= 2 and not (usable[:, list(members)].sum(axis=1) >= 2).any():
            findings.append(Finding(
                "WARNING", "calibration.rigs",
                f"rig {g_name} triangulates none of the marks at the taught place: its "
                "residuals and the rig check have nothing to go on"))
    return findings
