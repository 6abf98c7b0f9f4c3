"""The pose checks of a job: what they look at (``Measurement``) and the status they give it
(``check_pose``), shared by the single-object pipeline (``vgripd.vision.pipeline``) and pick lists
(``vgripd.vision.picklist``) so that one rule decides what the robot may receive."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from vgripd.config import Config, LimitsConfig, VisionConfig
from vgripd.errors import NotCalibratedError
from vgripd.geometry.transforms import invert_transform, rotation_angle
from vgripd.types import FloatArray, Status
from vgripd.vision import scene


@dataclass(frozen=True)
class Measurement:
    """What the pose checks look at: counts, pose and residuals of one job (mm, rad, px)."""

    found: int
    needed: int
    ambiguous: bool = False
    T_base_obj: FloatArray | None = None
    offset: FloatArray | None = None
    model_base: FloatArray | None = None  # (n, 3) model points in the base frame at the pose
    residuals: Mapping[str, float] = field(default_factory=dict)
    # The point whose displacement ``limits.max_translation_mm`` limits, in the object frame
    # (None: the object origin), and its name for messages (``limit_point``).
    limit_point: FloatArray | None = None
    limit_point_name: str = "object origin"


def displacement_mm(T_base_obj: FloatArray, offset: FloatArray,
                    point_obj: FloatArray | None = None) -> float:
    """How far the object point ``point_obj`` (object frame, default its origin) moved between
    the taught reference and ``T_base_obj``, in mm: ``|T_base_obj @ P - T_base_obj_ref @ P|``
    with ``T_base_obj_ref = inv(offset) @ T_base_obj``.

    Unlike ``|offset[:3, 3]|`` this holds no lever arm: a rotation of the offset about the
    robot base moves a far-away object's origin by much less than the offset's translation.
    """
    p = np.zeros(3) if point_obj is None else np.asarray(point_obj, dtype=np.float64)
    found = T_base_obj[:3, :3] @ p + T_base_obj[:3, 3]
    T_ref = invert_transform(offset) @ T_base_obj
    return float(np.linalg.norm(found - (T_ref[:3, :3] @ p + T_ref[:3, 3])))


def limit_point(config: Config, model: FloatArray,
                T_base_obj_ref: FloatArray) -> tuple[FloatArray | None, str]:
    """The point P of ``limits.point``/``limits.point_mm`` in the object frame and its name
    (docs/pipeline.md, "Limits"). Raises NotCalibratedError for ``point = "grip"`` without a
    taught ``reference.grip``."""
    limits = config.limits
    if limits.point_mm is not None:
        xyz = np.asarray(limits.point_mm, dtype=np.float64)
        return xyz, f"limits.point_mm {(np.round(xyz, 1) + 0.0).tolist()}"  # no -0.0
    point = limits.point
    if point is None:
        point = "centroid" if config.object.definition == "reference" else "origin"
    if point == "centroid":
        return model.mean(axis=0), "mark centroid"
    if point == "grip":
        if config.reference.grip is None:
            raise NotCalibratedError(
                'reference.grip: limits.point = "grip" needs the grip pose taught on the '
                "reference object (vgripd teach --grip)")
        grip = scene.matrix_from_pose(config.reference.grip)
        T_obj_base = invert_transform(T_base_obj_ref)
        return T_obj_base[:3, :3] @ grip[:3, 3] + T_obj_base[:3, 3], "grip point"
    return None, "object origin"


def check_pose(m: Measurement, vision: VisionConfig, limits: LimitsConfig) -> tuple[Status, str]:
    """The status of a job from its measurement, checked in a fixed order (first failure wins).

    Counts (NOT_FOUND under 3 matched, PARTIAL under ``needed``), ambiguity, residuals (fit RMS
    mm and reprojection px), offset limits, workspace box, then the epipolar warning that still
    publishes the pose (OK_RECALIBRATE).
    """
    if m.found < 3:
        return Status.NOT_FOUND, f"{m.found} feature(s) matched, need at least 3"
    if m.found < m.needed:
        return Status.PARTIAL, f"{m.found} feature(s) matched, need {m.needed}"
    if m.ambiguous:
        return Status.AMBIGUOUS, "two poses explain the features equally well"
    if m.offset is None or m.T_base_obj is None:
        return Status.NOT_FOUND, "no pose"
    r = m.residuals
    # A NaN compares False against every limit below: refuse it here, never let it through.
    if not (np.isfinite(m.offset).all() and np.isfinite(m.T_base_obj).all()
            and all(np.isfinite(v) for v in r.values())):
        bad = [k for k, v in r.items() if not np.isfinite(v)]
        return Status.INTERNAL, f"non-finite pose or residuals {bad} (numerical failure)"
    fit = r.get("fit_rms_mm", 0.0)
    if fit > vision.max_fit_rms_mm:
        return Status.RESIDUAL_TOO_HIGH, (
            f"fit RMS {fit:.3f} mm > vision.max_fit_rms_mm {vision.max_fit_rms_mm}"
        )
    reproj = r.get("reprojection_px", 0.0)
    if reproj > vision.max_reprojection_px:
        return Status.RESIDUAL_TOO_HIGH, (
            f"reprojection RMS {reproj:.3f} px > vision.max_reprojection_px "
            f"{vision.max_reprojection_px}"
        )
    # Limits (docs/pipeline.md, "Limits"): the displacement of one point of the object and the
    # angle of its rotation, both between the taught reference and the found pose.
    moved = displacement_mm(m.T_base_obj, m.offset, m.limit_point)
    if not moved <= limits.max_translation_mm:
        return Status.OUT_OF_LIMITS, (
            f"offset translation: {m.limit_point_name} moved {moved:.2f} mm > "
            f"limits.max_translation_mm {limits.max_translation_mm:g}"
        )
    turn = float(np.degrees(rotation_angle(m.offset[:3, :3])))
    if not turn <= limits.max_rotation_deg:
        return Status.OUT_OF_LIMITS, (
            f"offset rotation: object turned {turn:.2f} deg > limits.max_rotation_deg "
            f"{limits.max_rotation_deg:g}"
        )
    if limits.workspace_min_mm is not None and limits.workspace_max_mm is not None:
        pts = m.model_base if m.model_base is not None else m.T_base_obj[None, :3, 3]
        lo, hi = np.asarray(limits.workspace_min_mm), np.asarray(limits.workspace_max_mm)
        outside = np.flatnonzero(((pts < lo) | (pts > hi)).any(axis=1))
        if outside.size:
            p = pts[outside[0]]
            return Status.OUT_OF_WORKSPACE, (
                f"object point {int(outside[0])} at {np.round(p, 1).tolist()} mm (base) is "
                "outside the limits.workspace box"
            )
    epi = r.get("epipolar_px", 0.0)
    if epi > vision.epipolar_warn_px:
        return Status.OK_RECALIBRATE, (
            f"median epipolar residual {epi:.2f} px > vision.epipolar_warn_px "
            f"{vision.epipolar_warn_px}: plan a recalibration"
        )
    return Status.OK, ""
