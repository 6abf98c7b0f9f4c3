"""Pick lists: every instance of the object in one stereo job, each checked on its own, with its
chosen pick point, in the configured pick order (docs/picklists.md).

The pipeline calls :func:`locate_all` instead of its single-object match when
``picking.max_objects > 1``. The points it gets are the job's paired and triangulated marks;
``instances.find_instances`` groups them into objects, and each object then goes through the
same fit (``Pipeline._fit_stereo``: robust Horn, circle-centre bias removed) and the same
checks (``pose_checks.check_pose``) as a single object, so that one rule decides what the robot may
receive whether the image holds one plate or six.

Pick points (``picking.pick_points``) are tried per instance in priority order (then by id);
the first one whose target passes the pose checks is chosen (see :func:`choose`). The ordering
(:func:`ordered`) puts the pickable instances first, in the configured order, then the rejected
ones by score, and keeps ``max_objects`` of them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from vgripd.config import Config, PickingConfig
from vgripd.geometry.transforms import invert_transform
from vgripd.geometry.vendors import target_from_transform
from vgripd.types import FloatArray, PickInstance, RobotTarget, Status
from vgripd.vision import scene
from vgripd.vision.correspondence import kabsch, score_scale
from vgripd.vision.found import Found
from vgripd.vision.instances import InstanceMatch, find_instances, find_instances_mono
from vgripd.vision.jobstate import PipelineView as Pipeline
from vgripd.vision.jobstate import PoseEstimate, StereoPoints, _Job
from vgripd.vision.pose_checks import Measurement, check_pose

#: Gate failures that one pick point may pass and another not (where the grip is): the
#: others (counts, ambiguity, residuals) belong to the instance and end the search at once.
PICK_DEPENDENT = (Status.OUT_OF_LIMITS, Status.OUT_OF_WORKSPACE)


@dataclass(frozen=True)
class PickPoint:
    """A grip point: ``T_obj_pick`` its pose in the object frame."""

    id: int
    priority: int
    T_obj_pick: FloatArray


def pick_points(config: Config) -> tuple[PickPoint, ...]:
    """The configured pick points in the order they are tried: priority, then id."""
    points = [PickPoint(p.id, p.priority, scene.matrix_from_pose(p.pose))
              for p in config.picking.pick_points]
    return tuple(sorted(points, key=lambda p: (p.priority, p.id)))


@dataclass(frozen=True)
class Located:
    """An instance before ordering, with the point the order rules look at (base frame, mm):
    its chosen pick point, or the centroid of its model points."""

    instance: PickInstance
    position: FloatArray
    # Stereo: the feature -> paired-row assignment behind it (what a failed job's diagnosis
    # reads for the first instance); None for one camera.
    assignment: npt.NDArray[np.intp] | None = field(default=None, compare=False)
    # The measured feature points (base frame, mm) by name, as ``process_with_points`` gives
    # them for one object (``vgripd teach`` averages them).
    points_base: dict[str, FloatArray] = field(default_factory=dict, compare=False)


def order_key(picking: PickingConfig, position: FloatArray, score: float
              ) -> tuple[float, ...]:
    """Sort key of a pickable instance (ascending = picked first); ties go to the better score,
    then to the smaller x, y (a fixed order for equal keys)."""
    if picking.order == "z":
        first = -float(position[2])
    elif picking.order == "nearest":
        assert picking.point_mm is not None  # the config refuses "nearest" without it
        first = float(np.linalg.norm(position - np.asarray(picking.point_mm)))
    elif picking.order == "axis":
        assert picking.axis is not None
        axis = np.asarray(picking.axis, dtype=np.float64)
        first = float(position @ axis / np.linalg.norm(axis))
    else:  # "score"
        first = -score
    return (first, -score, float(position[0]), float(position[1]))


def ordered(picking: PickingConfig, located: list[Located]) -> tuple[PickInstance, ...]:
    """The pick list: pickable instances in the configured order, then the rejected ones (best
    score first), ``picking.max_objects`` at most."""
    good = [x for x in located if x.instance.status.pose_valid]
    bad = [x for x in located if not x.instance.status.pose_valid]
    good.sort(key=lambda x: order_key(picking, x.position, x.instance.score))
    bad.sort(key=lambda x: (-x.instance.score, float(x.position[0]), float(x.position[1])))
    return tuple(x.instance for x in (good + bad)[: picking.max_objects])


def detection_score(model: FloatArray, estimate: PoseEstimate, scale_mm: float) -> float:
    """0..1: the MSAC support of the fitted pose over the model's marks (a mark found exactly
    where the pose puts it counts 1, one ``scale_mm`` or more off counts 0, a missing one 0),
    divided by the number of marks."""
    T = estimate.T_cam_obj
    used = np.flatnonzero(estimate.used)
    moved = model[used] @ T[:3, :3].T + T[:3, 3]
    d2 = np.sum((moved - estimate.points_cam) ** 2, axis=1)
    support = float(np.clip(1.0 - d2 / scale_mm**2, 0.0, None).sum())
    return support / model.shape[0]


def choose(pipe: Pipeline, T_base_obj: FloatArray, offset: FloatArray, estimate: PoseEstimate,
           needed: int, points: tuple[PickPoint, ...]
           ) -> tuple[Status, str, PickPoint | None]:
    """The pose check of one instance and its pick point.

    Without pick points: ``pose_checks.check_pose`` as for a single object (pick point None). With
    them: each in turn (priority, then id) is checked with its own position as the limit point
    when ``limits.point = "grip"``, and its position must also lie in the workspace box; the
    first that passes is chosen. A failure no pick point can change (counts, ambiguity,
    residuals) ends the search; if none passes, the status is the highest-priority pick point's
    failure."""
    config = pipe.config
    limits = config.limits
    model_base = pipe.model @ T_base_obj[:3, :3].T + T_base_obj[:3, 3]
    first: tuple[Status, str, PickPoint | None] | None = None
    for point in points or (None,):
        lp, lp_name = pipe.limit_point, pipe.limit_point_name
        if point is not None and limits.point == "grip" and limits.point_mm is None:
            lp, lp_name = point.T_obj_pick[:3, 3], f"pick point {point.id}"
        status, message = check_pose(Measurement(
            found=int(estimate.used.sum()), needed=needed, ambiguous=estimate.ambiguous,
            T_base_obj=T_base_obj, offset=offset, model_base=model_base,
            residuals=estimate.residuals, limit_point=lp, limit_point_name=lp_name,
        ), config.vision, limits)
        if status.pose_valid and point is not None and limits.workspace_min_mm is not None:
            assert limits.workspace_max_mm is not None
            at = T_base_obj[:3, :3] @ point.T_obj_pick[:3, 3] + T_base_obj[:3, 3]
            lo, hi = np.asarray(limits.workspace_min_mm), np.asarray(limits.workspace_max_mm)
            if ((at < lo) | (at > hi)).any():
                status, message = Status.OUT_OF_WORKSPACE, (
                    f"pick point {point.id} at {np.round(at, 1).tolist()} mm (base) is outside "
                    "the limits.workspace box")
        if status.pose_valid:
            return status, message, point
        if first is None:
            first = (status, message, point)
        if status not in PICK_DEPENDENT:
            break
    assert first is not None
    status, message, point = first
    if len(points) > 1 and status in PICK_DEPENDENT:
        message = f"no pick point passes the gates; {message}"
    return status, message, None


def _sent(pipe: Pipeline, T_base_obj: FloatArray, offset: FloatArray,
          point: PickPoint | None) -> FloatArray:
    """What the robot gets (``output.mode``): the offset, which is the same for every point of
    a rigid object (the robot program picks its taught grip by the pick id), or the absolute
    grip: the pick point on the found object, else ``offset @ reference.grip``."""
    if pipe.config.output.mode == "offset":
        return offset
    if point is not None:
        return T_base_obj @ point.T_obj_pick
    assert pipe.T_base_grip_ref is not None  # the Pipeline refused grip mode without it
    return offset @ pipe.T_base_grip_ref


def _instance(pipe: Pipeline, match: InstanceMatch, paired: StereoPoints,
              T_base_camera: FloatArray, needed: int, points: tuple[PickPoint, ...]
              ) -> Located:
    """One grouped stereo instance fitted, checked and given its pick point."""
    config = pipe.config
    scratch = _Job()
    estimate = pipe._fit_stereo(match.assignment, paired.points, paired.gap, paired.px_l,
                                paired.px_r, match.ambiguous, scratch)
    lone = _lone_outlier(pipe.model, estimate, needed)
    if lone is not None:
        # One mark far off a fit the others agree on (a mark partly covered by a mark of a
        # neighbouring plate in one image: its centre is pulled by half a pixel): fit again
        # without it (docs/picklists.md, "Pose checks per instance").
        assignment = match.assignment.copy()
        assignment[lone] = -1
        again = _Job()
        refit = pipe._fit_stereo(assignment, paired.points, paired.gap, paired.px_l,
                                 paired.px_r, match.ambiguous, again)
        if refit is not None and int(refit.used.sum()) >= needed:
            estimate, scratch = refit, again
    if estimate is None:
        status, message = check_pose(Measurement(found=len(scratch.used), needed=needed),
                               config.vision, config.limits)
        T = T_base_camera @ match.T_points_model
        centre = (pipe.model @ T[:3, :3].T + T[:3, 3]).mean(axis=0)
        return Located(PickInstance(status=status, message=message,
                                    features_used=scratch.used), centre)
    scale = score_scale(config.vision.model_tolerance_mm, config.vision.max_fit_rms_mm)
    return _judged(pipe, estimate, scratch.used, T_base_camera, needed, points,
                   detection_score(pipe.model, estimate, scale))


#: An instance whose fit RMS (mm) exceeds ``LONE_FLOOR_MM`` and falls to at most
#: ``LONE_RATIO`` of it without one mark leaves that mark out (``_lone_outlier``).
LONE_RATIO = 0.3
LONE_FLOOR_MM = 0.1


def _lone_outlier(model: FloatArray, estimate: PoseEstimate | None, needed: int) -> int | None:
    """The feature index of the one mark to leave out of an instance's fit, or None.

    A mark partly covered by another plate's mark in one image keeps a centre biased by half a
    pixel: its triangulated point lies some tenths of a millimetre off, well inside the fit
    check and the robust fit's threshold (the model tolerance), yet it turns a whole plate by a
    few tenths of a degree (measured 0.18-0.26 mm, 0.28-0.32 deg). The fit spreads that error
    over every mark, so the residuals do not show which one it is; leaving each out in turn
    does: when the fit's RMS is over ``LONE_FLOOR_MM`` and the others fit to ``LONE_RATIO`` of
    it without one mark, and the instance keeps ``needed`` marks (and four) without it, that
    mark goes. A plate measured evenly off (a drifted calibration: no single mark explains
    it) keeps every mark; a single-object job never gets here.
    """
    if estimate is None:
        return None
    used = np.flatnonzero(estimate.used)
    if used.size - 1 < max(needed, 4):
        return None
    T = estimate.T_cam_obj
    full = float(np.sqrt(np.mean(np.sum(
        (model[used] @ T[:3, :3].T + T[:3, 3] - estimate.points_cam) ** 2, axis=1))))
    if full <= LONE_FLOOR_MM:
        return None
    rms = []
    for k in range(used.size):
        keep = np.delete(np.arange(used.size), k)
        Tk = kabsch(model[used[keep]], estimate.points_cam[keep])
        moved = model[used[keep]] @ Tk[:3, :3].T + Tk[:3, 3]
        rms.append(float(np.sqrt(np.mean(np.sum((moved - estimate.points_cam[keep]) ** 2,
                                                axis=1)))))
    best = int(np.argmin(rms))
    return int(used[best]) if rms[best] <= LONE_RATIO * full else None


def _judged(pipe: Pipeline, estimate: PoseEstimate, used: tuple[str, ...],
            T_base_camera: FloatArray, needed: int, points: tuple[PickPoint, ...],
            score: float) -> Located:
    """An instance's pose through the pose checks and the pick point choice."""
    config = pipe.config
    T_base_obj = T_base_camera @ estimate.T_cam_obj
    offset = T_base_obj @ invert_transform(pipe.T_base_obj_ref)  # as the single path does
    status, message, point = choose(pipe, T_base_obj, offset, estimate, needed, points)
    target: RobotTarget | None = None
    if status.pose_valid:
        target = target_from_transform(config.output.vendor,
                                       _sent(pipe, T_base_obj, offset, point))
    where = point if point is not None else (points[0] if points else None)
    if where is not None:
        position = T_base_obj[:3, :3] @ where.T_obj_pick[:3, 3] + T_base_obj[:3, 3]
    else:
        position = (pipe.model @ T_base_obj[:3, :3].T + T_base_obj[:3, 3]).mean(axis=0)
    instance = PickInstance(
        status=status, message=message, target=target, T_base_obj=T_base_obj, offset=offset,
        pick_id=point.id if point is not None else 0, score=score,
        residuals=dict(estimate.residuals), features_used=used,
    )
    measured = estimate.points_cam @ T_base_camera[:3, :3].T + T_base_camera[:3, 3]
    names = (pipe.names[i] for i in np.flatnonzero(estimate.used))
    return Located(instance, position, points_base=dict(zip(names, measured, strict=True)))


def _finish(pipe: Pipeline, job: _Job, located: list[Located], found_what: str
            ) -> tuple[Status, str, RobotTarget | None]:
    """Order the list into ``job`` and return the first instance's status, message, target."""
    config = pipe.config
    job.instances = ordered(config.picking, located)
    job.lap("output")
    if not job.instances:
        return Status.NOT_FOUND, (
            f"no instance of {config.object.name!r} found among {found_what}"), None
    first = job.instances[0]
    behind = next(x for x in located if x.instance is first)
    if behind.assignment is not None:
        job.trace.assignment = behind.assignment
    job.points_base = dict(behind.points_base)
    job.T_base_obj, job.offset = first.T_base_obj, first.offset
    job.residuals.update(first.residuals)
    job.used = first.features_used
    job.missing = tuple(n for n in pipe.names if n not in first.features_used)
    return first.status, first.message, first.target


def locate_all_mono(pipe: Pipeline, found: Found, job: _Job, T_base_camera: FloatArray,
                    needed: int) -> tuple[Status, str, RobotTarget | None]:
    """The pick list of a single-camera job on ArUco markers repeated per object
    (``instances.find_instances_mono``); as :func:`locate_all` otherwise."""
    config = pipe.config
    marks = found.markers
    feature = np.array([f for f, _ in marks], dtype=np.intp)
    px = np.array([m.centre for _, m in marks], dtype=np.float64).reshape(-1, 2)
    side = np.array([np.mean(np.linalg.norm(m.corners - np.roll(m.corners, 1, axis=0),
                                            axis=1)) for _, m in marks]).reshape(-1)
    size = np.array([getattr(f, "size_mm", 1.0) for f in config.object.features])
    tolerance_px = 3.0 * config.vision.max_reprojection_px
    groups = find_instances_mono(pipe.model, feature, px, side, size, pipe.left,
                                 tolerance_px, min_count=needed)
    job.lap("pose")
    points = pick_points(config)
    n = len(pipe.names)
    scale_px = 2.0 * config.vision.max_reprojection_px
    located = []
    for g in groups:
        sel = np.flatnonzero(g.assignment >= 0)
        used = np.zeros(n, dtype=bool)
        used[sel] = True
        T = g.T_cam_obj
        cam_pts = pipe.model[sel] @ T[:3, :3].T + T[:3, 3]
        err = np.linalg.norm(pipe.left.project(cam_pts) - px[g.assignment[sel]], axis=1)
        score = float(np.clip(1.0 - (err / scale_px) ** 2, 0.0, None).sum()) / n
        estimate = PoseEstimate(T, used, g.ambiguous, {"reprojection_px": g.rms_px}, cam_pts)
        located.append(_judged(pipe, estimate, tuple(pipe.names[i] for i in sel),
                               T_base_camera, needed, points, score))
    return _finish(pipe, job, located, f"{len(marks)} marker detection(s)")


def locate_all(pipe: Pipeline, paired: StereoPoints | None, job: _Job,
               T_base_camera: FloatArray, needed: int
               ) -> tuple[Status, str, RobotTarget | None]:
    """The pick list of a stereo job (module docstring); fills ``job`` with the first
    instance's pose, residuals and features and ``job.instances`` with the list. Returns the
    first instance's status, message and target (NOT_FOUND without any instance)."""
    config = pipe.config
    vision = config.vision
    if paired is None:
        return Status.NOT_FOUND, "fewer than 3 feature pairs in the two images", None
    rows = np.array([r for r in paired.circle_rows if paired.valid[r]], dtype=np.intp)
    grouping = find_instances(
        pipe.model, paired.points[rows], vision.model_tolerance_mm,
        [paired.keys[r] for r in rows], max_rms_mm=vision.max_fit_rms_mm)
    job.trace.hypotheses = grouping.verified
    job.lap("pose")
    points = pick_points(config)
    located = []
    for match in grouping.instances:
        assignment = np.where(match.assignment >= 0, rows[np.maximum(match.assignment, 0)], -1)
        remapped = InstanceMatch(assignment, match.T_points_model, match.rms_mm, match.score,
                                 match.ambiguous or not grouping.complete, match.rival)
        item = _instance(pipe, remapped, paired, T_base_camera, needed, points)
        located.append(dataclasses.replace(item, assignment=assignment))
    return _finish(pipe, job, located, f"{rows.size} triangulated point(s)")
