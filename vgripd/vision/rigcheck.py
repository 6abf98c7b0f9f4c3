"""The verdict of a multi-camera job on its rigs: which rig is inconsistent in itself, and
the status and message a job ends with when a rig disagrees (docs/multicamera.md, "Which rig
disagrees").

Apart from :mod:`vgripd.vision.views_locator` (which measures) so that the rules that turn the
measurements into a status read in one place.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from vgripd.config import VisionConfig
from vgripd.geometry.pose_from_views import GroupCheck
from vgripd.types import Status
from vgripd.vision.views_estimate import ViewsEstimate

#: A rig fitted alone leaving this many times the residuals of the best other rig is
#: inconsistent in itself (:func:`self_inconsistent`) ...
SELF_FACTOR = 10.0
#: ... provided its RMS is also above this fraction of ``vision.max_reprojection_px``.
SELF_FLOOR = 0.1
#: ... and the best other rig has at least this many residual degrees of freedom.
MIN_DOF = 6


def self_inconsistent(checks: Sequence[GroupCheck], observations: dict[str, int],
                      limit_px: float) -> set[str]:
    """Groups whose own fit is far worse than every other group's (names).

    The absolute limits judge a rig by pixels, but a pixel means little at one rig and much
    at another: a low-resolution rig far away whose camera moved 2 mm sees it as half a
    pixel, under every limit, yet its wrong rays pull the joint pose by half a millimetre. The
    finder's noise is about the same in every camera, so a rig fitted alone leaving
    ``SELF_FACTOR`` times the residuals of the most consistent other rig (and more than
    ``SELF_FLOOR`` of the limit, so that noise among good rigs never counts) is inconsistent in
    itself: one of its cameras moved. RMS values are compared per degree of freedom
    (``observations``: pixel observations per group), and only groups with ``MIN_DOF`` of them
    serve as the reference.
    """
    alone: dict[str, float] = {}
    for c in checks:
        n = observations.get(c.name, 0)
        dof = 2 * n - 6  # residual degrees of freedom of a 6-DOF fit of n pixel observations
        if np.isfinite(c.alone_rms_px) and dof > 0:
            # Per degree of freedom: a camera alone with 3-4 marks fits them almost exactly,
            # which says nothing about its noise (and would make every other rig look bad).
            alone[c.name] = c.alone_rms_px * float(np.sqrt(2 * n / dof))
    reference = {name: v for name, v in alone.items() if 2 * observations[name] - 6 >= MIN_DOF}
    out = set()
    for name, rms in alone.items():
        others = [v for other, v in reference.items() if other != name]
        if others and rms > max(SELF_FACTOR * min(others), SELF_FLOOR * limit_px):
            out.add(name)
    return out


def rig_verdict(status: Status, message: str, est: ViewsEstimate,
                vision: VisionConfig) -> tuple[Status, str]:
    """The status of a multi-camera job after the common checks: every rig's own reprojection
    RMS is checked too, and a rig that disagrees with the others is named; a pose that passed
    every check is still published then, but as OK_RECALIBRATE (docs/multicamera.md)."""
    groups = est.pose.groups if est.pose is not None else ()
    over = [(g.rms_px, g.name) for g in groups if g.rms_px > vision.max_reprojection_px]
    if status.pose_valid and over:
        rms, name = max(over)
        status, message = Status.RESIDUAL_TOO_HIGH, (
            f"rig {name}: reprojection RMS {rms:.3f} px > vision.max_reprojection_px "
            f"{vision.max_reprojection_px}")
    blame = _blame(est)
    if est.lost:
        lost = (f"camera{'s' if len(est.lost) > 1 else ''} {', '.join(est.lost)}: mark-like "
                "blobs, but none where the calibration puts the marks it should see: is each "
                "image the one of its camera (calibration.cameras order), or did it move far?")
        blame = f"{blame}; {lost}" if blame else lost
    if not blame:
        return status, message
    if status.pose_valid:
        return Status.OK_RECALIBRATE, blame
    return status, f"{message}; {blame}"


def _blame(est: ViewsEstimate) -> str:
    """The sentence naming the rig(s) the consistency check found odd ('' for none)."""
    if not est.odd or est.pose is None:
        return ""
    if len(est.odd) > 1:
        return (f"rigs {', '.join(est.odd)} disagree with each other (two rigs alone cannot "
                "tell which one moved): check their cameras and calibration.cameras")
    check = next(c for c in est.checks if c.name == est.odd[0])
    group = next(g for g in est.pose.groups if g.name == check.name)
    errors = est.pose.errors_px
    cams = [(float(np.sqrt(np.nanmean(errors[:, j] ** 2))), est.camera_names[j])
            for j in group.cameras if np.isfinite(errors[:, j]).any()]
    rest = [(est.residuals[f"camera.{est.camera_names[j]}.rest_px"], est.camera_names[j])
            for j in group.cameras if f"camera.{est.camera_names[j]}.rest_px" in est.residuals]
    if rest:  # under the other rigs' pose: the camera that moved stands out
        cams = rest
    worst = f" (worst camera {max(cams)[1]}, {max(cams)[0]:.2f} px)" if cams else ""
    return (f"rig {check.name} disagrees with the other rigs: {check.predicted_rms_px:.2f} px "
            f"under their pose, its own pose {check.deviation_mm:.2f} mm / "
            f"{check.deviation_deg:.3f} deg from theirs{worst}: a camera moved? recalibrate "
            "it (calibration.cameras)"
            + ("; the pose is the other rigs' alone" if est.excluded == check.name else ""))
