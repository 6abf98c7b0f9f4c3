"""``[vision]`` (finding, matching, the residual gates, several views) and ``[picking]``
(pick lists, docs/picklists.md)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from vgripd.config.common import Model, PoseConfig, Vec3


class VisionConfig(Model):
    """Feature finding, matching and the residual gates of the pipeline (see docs/pipeline.md).

    Pixel figures are at full image resolution; mm figures in the left camera frame.
    """

    working_distance_mm: tuple[float, float] = (300.0, 2000.0)
    downscale: int = Field(default=2, ge=1, le=8)
    min_contrast: float = Field(default=25.0, gt=0, le=255)
    min_circularity: float = Field(default=0.6, gt=0, le=1)
    template_min_score: float = Field(default=0.7, gt=0, le=1)
    epipolar_tolerance_px: float = Field(default=3.0, gt=0)
    model_tolerance_mm: float = Field(default=3.0, gt=0)
    min_features: int = Field(default=4, ge=3)
    max_fit_rms_mm: float = Field(default=1.0, gt=0)
    max_reprojection_px: float = Field(default=1.5, gt=0)
    epipolar_warn_px: float = Field(default=1.0, gt=0)
    # Multi-camera cells (docs/multicamera.md): a rig whose own pose differs from the pose of
    # the other rigs by more than this at its marks (mm) or in rotation (deg) is named as
    # disagreeing (a camera moved since calibration).
    rig_deviation_mm: float = Field(default=3.0, gt=0)
    rig_deviation_deg: float = Field(default=0.5, gt=0)
    # Several views per job for one robot-mounted camera (docs/multicamera.md, "Several
    # views per job"): the robot takes ``views`` images from as many poses (CAPTURE 1..N),
    # the last one runs one fit over all. ``view_poses``: the taught flange pose of each view,
    # for links that cannot report the robot's pose (Modbus); ``view_timeout_s``: the longest
    # wait for the next view before the job ends CAMERA_ERROR.
    views: int = Field(default=1, ge=1, le=8)
    view_poses: tuple[PoseConfig, ...] = ()
    view_timeout_s: float = Field(default=30.0, gt=0, le=3600)

    @model_validator(mode="after")
    def _ranges(self) -> VisionConfig:
        near, far = self.working_distance_mm
        if not 0 < near < far:
            raise ValueError(
                f"working_distance_mm must be [near, far] with 0 < near < far, got {[near, far]}"
            )
        if self.epipolar_warn_px > self.epipolar_tolerance_px:
            raise ValueError("epipolar_warn_px must not exceed epipolar_tolerance_px")
        if self.view_poses and len(self.view_poses) != self.views:
            raise ValueError(f"view_poses has {len(self.view_poses)} poses for views = "
                             f"{self.views}: give one flange pose per view, or none")
        return self


class PickPointConfig(Model):
    """One grip point of the object (``[[picking.pick_points]]``): ``pose`` is the gripper's
    pose in the object frame (for ``object.definition = "reference"``: in the base frame with
    the object at its reference). ``id`` goes to the robot with the result; ``priority``: a
    smaller number is tried first (1 = first choice). See docs/picklists.md."""

    id: int = Field(ge=1, le=32767)
    priority: int = Field(default=1, ge=0, le=32767)
    pose: PoseConfig


class PickingConfig(Model):
    """Pick lists: several identical objects in one job's images (docs/picklists.md).

    ``max_objects = 1`` (the default) is the single-object job of before: one pose, no
    instance list. Above 1 every instance found is located, gated and ordered, and up to
    ``max_objects`` of them are returned, the pickable ones first in the order ``order``:

    - ``"z"``: highest first (base-frame z of the instance's pick point, or its mark centroid
      without pick points);
    - ``"nearest"``: nearest first to ``point_mm`` (base frame);
    - ``"axis"``: ascending along the direction ``axis`` (base frame; its length is ignored);
    - ``"score"``: best detection score first.

    ``pick_points``: grip points with ids and priorities; for each instance the first one in
    priority order whose target passes the gates is chosen. Empty: the object's own grip
    (``pick_id`` 0).
    """

    max_objects: int = Field(default=1, ge=1, le=64)
    order: Literal["z", "nearest", "axis", "score"] = "z"
    point_mm: Vec3 | None = None
    axis: Vec3 | None = None
    pick_points: tuple[PickPointConfig, ...] = ()

    @model_validator(mode="after")
    def _order_parameters(self) -> PickingConfig:
        if self.order == "nearest" and self.point_mm is None:
            raise ValueError('order = "nearest" needs point_mm (base frame, mm)')
        if self.order == "axis":
            if self.axis is None:
                raise ValueError('order = "axis" needs axis (a direction in the base frame)')
            if sum(a * a for a in self.axis) < 1e-12:
                raise ValueError(f"axis {list(self.axis)} has no direction (zero length)")
        if self.point_mm is not None and self.order != "nearest":
            raise ValueError(f'point_mm is the parameter of order = "nearest", not of '
                             f'order = "{self.order}"')
        if self.axis is not None and self.order != "axis":
            raise ValueError(f'axis is the parameter of order = "axis", not of '
                             f'order = "{self.order}"')
        if self.pick_points and self.max_objects == 1:
            raise ValueError("pick_points need max_objects > 1 (a single-object job has no "
                             "pick list to carry the pick id)")
        ids = [p.id for p in self.pick_points]
        twice = sorted({i for i in ids if ids.count(i) > 1})
        if twice:
            raise ValueError(f"pick_points: id {twice[0]} is used twice")
        return self
