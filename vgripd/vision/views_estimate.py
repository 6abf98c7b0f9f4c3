"""What the multi-camera path measured for one job (``ViewsEstimate``): made by
:mod:`vgripd.vision.views_locator`, judged by :mod:`vgripd.vision.rigcheck`, so it sits below
both."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from vgripd.geometry.pose_from_views import GroupCheck, MultiViewPose
from vgripd.types import FloatArray


@dataclass
class ViewsEstimate:
    """What the multi-camera path measured: the pose, which features it used, the residuals
    (``rig.<name>.*``, ``camera.<name>.*`` and the checked figures) and the groups the consistency
    check found odd (names). ``pose`` is None when fewer than 3 features were identified."""

    used: npt.NDArray[np.bool_]
    camera_names: tuple[str, ...] = ()
    pose: MultiViewPose | None = None
    ambiguous: bool = False
    residuals: dict[str, float] = field(default_factory=dict)
    points_base: dict[str, FloatArray] = field(default_factory=dict)
    checks: tuple[GroupCheck, ...] = ()
    odd: tuple[str, ...] = ()
    excluded: str = ""
    lost: tuple[str, ...] = ()
