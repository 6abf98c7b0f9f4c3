"""Frozen value types that flow one way through vgripd.

camera driver -> ImagePair -> (features, geometry) -> JobResult (with RobotTarget) -> link driver.

Every value carries its capture time on the monotonic clock (``t_mono_ns``, from
``time.monotonic_ns()``) and transforms are named ``T_a_b`` (pose of frame b in frame a, mm).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from types import MappingProxyType
from typing import Any

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

_EMPTY: Mapping[str, Any] = MappingProxyType({})


class Status(IntEnum):
    """Every job ends with exactly one of these codes (also the value of the status register).

    Grouped by range, so a PLC can test ``status < 10`` for "a pose was published":

    ====  ==================  ==================================================================
    code  name                meaning / what the robot should do
    ====  ==================  ==================================================================
       0  IDLE                no job has run since start (register value only)
       1  OK                  pose published; all checks passed
       2  OK_RECALIBRATE      pose published, but epipolar residuals exceed the warning level:
                              the stereo calibration has drifted, plan a recalibration
      10  NOT_FOUND           too few features found; no pose
      11  PARTIAL             some model features missing and the rest is not enough to trust
      12  AMBIGUOUS           two poses explain the image equally well (planar PnP); no pose
      13  RESIDUAL_TOO_HIGH   a pose was computed but its residuals exceed the thresholds
      20  OUT_OF_LIMITS       offset exceeds the configured translation/rotation limits
      21  OUT_OF_WORKSPACE    object pose outside the configured workspace box
      30  CAMERA_ERROR        acquisition failed (timeout, missing/corrupt image, device)
      31  NOT_CALIBRATED      calibration missing or invalid for this job
      32  BAD_REQUEST         the trigger/command was malformed (unknown command, bad recipe)
      40  BUSY                trigger refused: a job is already running
      41  ABORTED             job aborted by shutdown
      99  INTERNAL            unexpected error (logged with a traceback); no pose
    ====  ==================  ==================================================================
    """

    IDLE = 0
    OK = 1
    OK_RECALIBRATE = 2
    NOT_FOUND = 10
    PARTIAL = 11
    AMBIGUOUS = 12
    RESIDUAL_TOO_HIGH = 13
    OUT_OF_LIMITS = 20
    OUT_OF_WORKSPACE = 21
    CAMERA_ERROR = 30
    NOT_CALIBRATED = 31
    BAD_REQUEST = 32
    BUSY = 40
    ABORTED = 41
    INTERNAL = 99

    @property
    def pose_valid(self) -> bool:
        """True only for codes under which a pose is published to the robot."""
        return self in (Status.OK, Status.OK_RECALIBRATE)


@dataclass(frozen=True)
class CaptureView:
    """Which view of a several-view job an acquisition is (``vision.views``; the daemon hands
    it to the camera driver's ``grab``). ``index`` is 1-based of ``count``; ``T_base_flange``
    is the flange pose of the view (mm; the robot's own, or the taught ``vision.view_poses``),
    None when neither is known. Real cameras ignore it (the robot has moved them there); the
    synthetic camera renders from it and keeps the object still over the views of a job."""

    index: int
    count: int
    T_base_flange: FloatArray | None = None


@dataclass(frozen=True)
class ImagePair:
    """One acquisition: a stereo pair, a single image (``right is None``), or the images of
    all N cameras of a multi-camera cell (``views``).

    Images are 8-bit grey (H, W) or BGR (H, W, 3) arrays as the driver delivered them.
    ``views`` holds every image in camera order (``calibration.cameras``); it defaults to
    ``(left,)`` or ``(left, right)``, and ``left`` / ``right`` are always ``views[0]`` /
    ``views[1]``, so code written for one or two cameras keeps working. Build an N-camera
    acquisition with :meth:`of_views`.
    ``T_base_flange`` is the robot flange pose at capture (mm) for robot-mounted cameras;
    for the N views of one robot-mounted camera (``vision.views``) a (N, 4, 4) stack, one
    flange pose per image.
    ``truth`` carries ground truth from the synthetic driver (e.g. ``{"T_cam_obj": 4x4}``).
    """

    left: npt.NDArray[Any]
    right: npt.NDArray[Any] | None
    t_mono_ns: int
    source: str = ""
    meta: Mapping[str, Any] = field(default_factory=lambda: _EMPTY)
    T_base_flange: FloatArray | None = None
    truth: Mapping[str, Any] = field(default_factory=lambda: _EMPTY)
    views: tuple[npt.NDArray[Any], ...] = ()

    def __post_init__(self) -> None:
        if not self.views:
            views = (self.left,) if self.right is None else (self.left, self.right)
            object.__setattr__(self, "views", views)
            return
        second = self.views[1] if len(self.views) > 1 else None
        if self.views[0] is not self.left or second is not self.right:
            raise ValueError("ImagePair: left and right must be views[0] and views[1] "
                             "(build N images with ImagePair.of_views)")

    @classmethod
    def of_views(cls, views: Sequence[npt.NDArray[Any]], t_mono_ns: int,
                 **fields: Any) -> ImagePair:
        """An acquisition of ``len(views)`` >= 1 images in camera order."""
        if not views:
            raise ValueError("ImagePair.of_views: no images")
        v = tuple(views)
        return cls(left=v[0], right=v[1] if len(v) > 1 else None, t_mono_ns=t_mono_ns,
                   views=v, **fields)

    @property
    def is_stereo(self) -> bool:
        return self.right is not None


@dataclass(frozen=True)
class RobotTarget:
    """A pose in one robot vendor's convention: field names, values in that vendor's units."""

    vendor: str
    fields: tuple[str, ...]
    values: tuple[float, ...]


@dataclass(frozen=True)
class BeltPose:
    """Where a result stands on a conveyor (docs/conveyor.md): the encoder ``count`` its pose
    belongs to, where that count came from (``source``: the LATCH_SOURCE value, 1 link,
    2 frame id, 3 timestamp), the one-sigma position error along the belt it leaves
    (``error_mm``), and the pose in belt terms at that count: ``along_mm`` from the belt's
    origin in its direction, ``across_mm`` in the belt plane to the left, ``theta_deg`` the
    rotation about the belt's normal. ``queued``: parts waiting in the queue after this answer.
    """

    count: int
    source: int
    error_mm: float
    along_mm: float = 0.0
    across_mm: float = 0.0
    theta_deg: float = 0.0
    queued: int = 0


@dataclass(frozen=True)
class PickInstance:
    """One object instance of a pick list (several identical objects in one job's images).

    The same meaning as the ``JobResult`` fields of the same names, for this instance alone:
    ``status`` is this instance's own gate (one instance out of limits does not hide the
    others) and ``target`` is set only when ``status.pose_valid``. ``pick_id`` is the id of the
    chosen pick point (``picking.pick_points``; 0 = the object's single grip/offset), ``score``
    the detection score in 0..1 (1 = every model mark found with residuals at zero).
    """

    status: Status
    message: str = ""
    target: RobotTarget | None = None
    T_base_obj: FloatArray | None = None
    offset: FloatArray | None = None
    pick_id: int = 0
    score: float = 0.0
    residuals: Mapping[str, float] = field(default_factory=lambda: _EMPTY)
    features_used: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.target is not None and not self.status.pose_valid:
            raise ValueError(f"PickInstance with status {self.status.name} must not carry a "
                             "target")


@dataclass(frozen=True)
class JobResult:
    """The outcome of one job. ``target`` is set only when ``status.pose_valid``.

    ``T_base_obj``: object pose in the robot base frame (mm). ``offset``: the gripping offset
    against the taught reference as a 4x4 transform (mm), before vendor conversion.
    ``residuals``: named figures (px for reprojection/epipolar, mm for fit RMS).
    ``timings_ms``: per-stage wall time.
    ``diagnosis``: see the field's comment.
    """

    job_id: int
    status: Status
    message: str = ""
    target: RobotTarget | None = None
    T_base_obj: FloatArray | None = None
    offset: FloatArray | None = None
    residuals: Mapping[str, float] = field(default_factory=lambda: _EMPTY)
    timings_ms: Mapping[str, float] = field(default_factory=lambda: _EMPTY)
    features_used: tuple[str, ...] = ()
    features_missing: tuple[str, ...] = ()
    t_capture_mono_ns: int | None = None
    t_done_mono_ns: int = 0
    # A failed job's ``vgripd.vision.diagnosis.Diagnosis`` (what each stage saw, the likely
    # causes with the config key to check); None for a successful job or a camera error.
    diagnosis: Any = field(default=None, compare=False)
    # Pick list (``picking.max_objects`` > 1): every instance found, in pick order (the
    # pickable ones first, in the configured order; then the rejected ones). The top-level
    # fields above describe ``instances[0]``; () for a single-object job.
    instances: tuple[PickInstance, ...] = ()
    # The recipe the job ran (``Trigger.recipe``; 0 = the top-level config), set by the daemon.
    recipe: int = 0
    # A conveyor recipe's answer: the count the pose belongs to and the pose in belt terms.
    belt: BeltPose | None = None

    def __post_init__(self) -> None:
        if self.target is not None and not self.status.pose_valid:
            raise ValueError(f"JobResult with status {self.status.name} must not carry a target")
