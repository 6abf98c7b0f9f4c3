"""What one job of the pipeline carries from stage to stage, shared by the pipeline
(``vgripd.vision.pipeline``), the pick lists (``vgripd.vision.picklist``) and the diagnosis
(``vgripd.vision.diagnosis``), which sit apart so that each reads in one place:

- ``Trace``: what each stage saw (the diagnosis reads it);
- ``_Job``: what a job has learnt so far (becomes the ``JobResult``);
- ``PoseEstimate``, ``StereoPoints``: a fitted pose, the triangulated pairs;
- ``PipelineView``: what the pick lists and the diagnosis read of the configured ``Pipeline``
  that calls them (they are handed the pipeline, never import it).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import numpy.typing as npt

from vgripd.config import Config
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.stereo import StereoRig
from vgripd.types import FloatArray, PickInstance
from vgripd.vision import features as ft
from vgripd.vision.found import Found, _Finder
from vgripd.vision.views_locator import ViewsLocator


@dataclass
class Trace:
    """What the pipeline's stages saw in one job (filled as it goes; cheap references only)."""

    grays: tuple[ft.UInt8Image | None, ...] = ()
    found: tuple[Found, ...] = ()  # left[, right]
    pairs: npt.NDArray[np.intp] | None = None  # (k, 2) left/right circle indices
    first_circle_row: int = 0  # row of the first circle pair among the triangulated rows
    depth_mm: FloatArray | None = None  # (rows,) z in the left camera frame
    in_front: npt.NDArray[np.bool_] | None = None  # (rows,) triangulated in front of both
    hypotheses: int = 0
    assignment: npt.NDArray[np.intp] | None = None  # (n_model,) row per feature, -1 missing
    odd: tuple[str, ...] = ()  # multi-camera: the rigs the consistency check named
    camera_marks: tuple[int, ...] = ()  # multi-camera: observations in the fit, per camera
    T_base_flange: FloatArray | None = None  # multi-camera: the flange pose at capture


@dataclass
class _Job:
    """What a job has learnt so far; becomes the JobResult."""

    timings_ms: dict[str, float] = field(default_factory=dict)
    residuals: dict[str, float] = field(default_factory=dict)
    points_base: dict[str, FloatArray] = field(default_factory=dict)
    used: tuple[str, ...] = ()
    missing: tuple[str, ...] = ()
    T_base_obj: FloatArray | None = None
    offset: FloatArray | None = None
    instances: tuple[PickInstance, ...] = ()  # the pick list (picking.max_objects > 1)
    trace: Trace = field(default_factory=Trace)  # what each stage saw (diagnosis)
    _t: float = field(default_factory=time.perf_counter)

    def lap(self, stage: str) -> None:
        now = time.perf_counter()
        self.timings_ms[stage] = (now - self._t) * 1e3
        self._t = now


@dataclass(frozen=True)
class PoseEstimate:
    """Object pose in the left camera frame and the features behind it."""

    T_cam_obj: FloatArray
    used: npt.NDArray[np.bool_]  # (n_model,) features that entered the fit
    ambiguous: bool
    residuals: dict[str, float]
    # (n_used, 3) mm, left camera frame, rows in feature order of ``used``: triangulated points
    # (stereo) or the model at the fitted pose (mono, which measures no 3D point of its own).
    points_cam: FloatArray


@dataclass(frozen=True)
class StereoPoints:
    """The paired features of a stereo job, triangulated (rows: identified pairs first, then
    circle pairs; a circle blob may sit in several rows, ``keys`` tell which)."""

    px_l: FloatArray  # (k, 2) px
    px_r: FloatArray  # (k, 2) px
    points: FloatArray  # (k, 3) mm, left camera frame
    gap: FloatArray  # (k,) mm between the two rays
    valid: npt.NDArray[np.bool_]  # in front of both cameras and within the working distance
    keys: list[tuple[int, ...]]  # per row: the image blobs it uses (exclusive)
    fixed: dict[int, int]  # identified feature index -> row
    circle_rows: list[int]


class PipelineView(Protocol):
    """What ``vgripd.vision.picklist`` and ``vgripd.vision.diagnosis`` use of a
    ``vgripd.vision.pipeline.Pipeline`` (set up once from the config; see there)."""

    config: Config
    left: CameraModel
    right: CameraModel | None
    rig: StereoRig | None
    multi: ViewsLocator | None
    names: tuple[str, ...]
    model: FloatArray
    T_base_obj_ref: FloatArray
    T_base_grip_ref: FloatArray | None
    limit_point: FloatArray | None
    limit_point_name: str
    finders: list[_Finder]
    find_left: _Finder
    find_right: _Finder | None

    def _fit_stereo(
        self,
        assignment: npt.NDArray[np.intp],
        points: FloatArray,
        gap: FloatArray,
        px_l: FloatArray,
        px_r: FloatArray,
        ambiguous: bool,
        job: _Job,
    ) -> PoseEstimate | None: ...
