"""ImagePair -> features -> pose -> offset -> RobotTarget, with the pose checks in between.

The chain (docs/pipeline.md has the whole story and the status table):

1. image checks: 8-bit, the calibrated size, not black/flat (else CAMERA_ERROR);
2. features in both images (``vgripd.vision.features``);
3. stereo: left/right pairs on the epipolar line, triangulated in the left camera frame;
   mono: identified features (ArUco/template) only, PnP;
4. model correspondence by rigid distances, robust Horn fit of the model onto the points:
   ``T_cam_obj``;
5. ``T_base_obj = T_base_camera @ T_cam_obj`` (fixed camera, or ``T_base_flange @
   T_flange_camera`` for a robot-mounted one), offset ``T_base_obj @ inv(T_base_obj_ref)``;
6. pose checks (:func:`check_pose`), then the vendor convention of ``output.vendor`` for the offset
   (``output.mode = "offset"``) or for the grip ``T_offset @ reference.grip`` (``"grip"``).

The model is the features' ``xyz_mm``, or for ``object.definition = "reference"`` the taught
``reference.points_mm`` when set (base-frame points measured by ``vgripd teach``).

``Pipeline.process`` never raises for bad images: every job ends with one status, and a pose
that failed a check is never carried as a target. It is pure CPU and keeps no state between jobs,
so the daemon may run it in an executor.
"""

from __future__ import annotations

import time
import traceback
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from vgripd.config import MIN_PNP_FEATURES, Config
from vgripd.errors import GeometryError, NotCalibratedError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.orientation import horn, horn_robust, pnp
from vgripd.geometry.stereo import StereoRig
from vgripd.geometry.transforms import invert_transform
from vgripd.geometry.vendors import target_from_transform
from vgripd.types import FloatArray, ImagePair, JobResult, Status
from vgripd.vision import diagnosis as dg
from vgripd.vision import features as ft
from vgripd.vision import picklist, scene
from vgripd.vision.found import Found, _Finder
from vgripd.vision.jobstate import PoseEstimate, StereoPoints, _Job
from vgripd.vision.pose_checks import Measurement, check_pose
from vgripd.vision.readiness import ready
from vgripd.vision.rigcheck import rig_verdict
from vgripd.vision.views_locator import ViewsLocator

# --------------------------------------------------------------------------- pipeline


class _Reject(Exception):
    """A job ends early with this status (internal control flow of ``process``)."""

    def __init__(self, status: Status, message: str) -> None:
        super().__init__(message)
        self.status = status
        self.message = message


class Pipeline:
    """The configured vision chain; construct once, call :meth:`process` per image pair.

    Raises what ``vgripd.vision.readiness.ready`` raises for a config that cannot run jobs
    (``NotCalibratedError``, ``ConfigError``).
    """

    def __init__(self, config: Config) -> None:
        # Several views of one robot-mounted camera are a multi-camera cell of N views; their
        # taught flange poses (if any) let `vgripd check` place the object in each view.
        self.view_poses = tuple(scene.matrix_from_pose(p) for p in config.vision.view_poses)
        judged = ready(config)  # every rule a config must meet to run jobs (its docstring)
        config = judged.config
        self.config = config
        self.left, self.right = judged.left, judged.right
        self.rig: StereoRig | None = judged.rig
        self.names = scene.feature_names(config)
        self.model = judged.model
        self.T_base_obj_ref = judged.T_base_obj_ref
        # Pick lists (docs/picklists.md): with pick points, "the grip" is each pick point.
        self.many = config.picking.max_objects > 1
        self.limit_point, self.limit_point_name = judged.limit_point, judged.limit_point_name
        self.T_base_grip_ref: FloatArray | None = judged.T_base_grip_ref
        assert config.calibration is not None  # ready() raised otherwise
        self.fixed_T_base_camera = (
            scene.T_base_camera(config)
            if config.calibration.hand_eye.mounting == "fixed"
            else None
        )
        self.kinds = tuple(f.kind for f in config.object.features)
        self.is_circle = np.array([k == "circle" for k in self.kinds])
        self.diameters = np.array(
            [f.diameter_mm if f.kind == "circle" else 0.0 for f in config.object.features]
        )
        # A multi-camera cell (calibration.cameras): its own path, one finder per camera. The
        # kinds of marks a pick list needs and unique ArUco ids the config judged at load.
        self.multi: ViewsLocator | None = None
        self.finders: list[_Finder] = []
        templates = judged.templates
        if scene.is_multi_camera(config):
            self.multi = ViewsLocator(config, self.model, self.T_base_obj_ref)
            self.finders = [_Finder(config, cam.fx, templates) for cam in self.multi.cameras]
        self.find_left = _Finder(config, self.left.fx, templates)
        self.find_left.keep_all = self.many and self.rig is None
        self.find_right = (_Finder(config, self.right.fx, templates)
                           if self.right is not None else None)

    def T_base_camera(self, pair: ImagePair) -> FloatArray:
        """Pose of the left camera in the base frame when ``pair`` was taken (mm)."""
        if self.fixed_T_base_camera is not None:
            return self.fixed_T_base_camera
        return scene.T_base_camera(self.config, pair.T_base_flange)

    # ------------------------------------------------------------------ entry point
    def process(self, pair: ImagePair, job_id: int) -> JobResult:
        """Run one job. Never raises: failures become a status with a message."""
        return self.process_with_points(pair, job_id)[0]

    def process_with_points(
        self, pair: ImagePair, job_id: int, *, diagnose: bool = False
    ) -> tuple[JobResult, dict[str, FloatArray]]:
        """:meth:`process`, plus the measured feature points (3,) mm in the base frame by name
        (empty without a pose). ``vgripd teach`` stores them for the ``reference`` definition.

        A job that found the images usable but no valid pose carries ``JobResult.diagnosis``
        (``vgripd.vision.diagnosis``: what each stage saw, the likely causes with the config
        key to check); ``diagnose=True`` attaches one to a successful job too."""
        job = _Job()
        try:
            status, message, target = self._run(pair, job)
        except _Reject as rej:
            status, message, target = rej.status, rej.message, None
        except NotCalibratedError as err:
            status, message, target = Status.NOT_CALIBRATED, str(err), None
        except Exception as err:  # noqa: BLE001 - a job must end with a status, never crash
            last = traceback.extract_tb(err.__traceback__)[-1]
            status, target = Status.INTERNAL, None
            message = f"{type(err).__name__}: {err} ({Path(last.filename).name}:{last.lineno})"
        job.timings_ms["total"] = sum(job.timings_ms.values())
        diagnosis = None
        if job.trace.found and (diagnose or status in dg.DIAGNOSED):
            try:
                diagnosis = dg.explain(self, job, status, message)
            except Exception:  # noqa: BLE001 - explaining a failure must never fail the job
                diagnosis = None
        return JobResult(
            job_id=job_id,
            status=status,
            message=message,
            target=target,
            T_base_obj=job.T_base_obj,
            offset=job.offset,
            residuals=dict(job.residuals),
            timings_ms=dict(job.timings_ms),
            features_used=job.used,
            features_missing=job.missing,
            t_capture_mono_ns=pair.t_mono_ns,
            t_done_mono_ns=time.monotonic_ns(),
            diagnosis=diagnosis,
            instances=job.instances,
        ), job.points_base

    def _run(self, pair: ImagePair, job: _Job) -> tuple[Status, str, Any]:
        if self.multi is not None:
            return self._run_multi(self.multi, pair, job)
        vision, limits = self.config.vision, self.config.limits
        gray_l = _checked_gray(pair.left, self.left, "left")
        stereo = pair.right is not None and self.rig is not None
        gray_r = _checked_gray(pair.right, self.right, "right") if stereo else None
        T_base_camera = self.T_base_camera(pair)
        job.lap("checks")

        found_l = self.find_left(gray_l)
        found_r = None
        if gray_r is not None and self.find_right is not None:
            found_r = self.find_right(gray_r)
        job.lap("features")
        job.trace.grays = (gray_l, gray_r) if found_r is not None else (gray_l,)
        job.trace.found = (found_l, found_r) if found_r is not None else (found_l,)

        if self.many and found_r is not None:
            paired = self._stereo_points(found_l, found_r, job)
            return picklist.locate_all(self, paired, job, T_base_camera, vision.min_features)
        if self.many and self.find_left.keep_all:
            return picklist.locate_all_mono(self, found_l, job, T_base_camera,
                                            max(vision.min_features, MIN_PNP_FEATURES))
        if found_r is not None:
            estimate = self._stereo_pose(found_l, found_r, job)
            needed = vision.min_features
        else:
            estimate = self._mono_pose(found_l, job)
            needed = max(vision.min_features, MIN_PNP_FEATURES)
        job.lap("pose")
        if estimate is None:
            return (*check_pose(Measurement(len(job.used), needed), vision, limits), None)

        T_base_obj = T_base_camera @ estimate.T_cam_obj
        points_base = estimate.points_cam @ T_base_camera[:3, :3].T + T_base_camera[:3, 3]
        job.points_base = dict(zip((self.names[i] for i in np.flatnonzero(estimate.used)),
                                   points_base, strict=True))
        measurement = self._measurement(job, T_base_obj, int(estimate.used.sum()), needed,
                                        estimate.ambiguous, estimate.residuals)
        status, message = check_pose(measurement, vision, limits)
        return self._output(job, status, message)

    def _measurement(self, job: _Job, T_base_obj: FloatArray, found: int, needed: int,
                     ambiguous: bool, residuals: dict[str, float]) -> Measurement:
        """The pose checks' view of a pose (and the job's record of it)."""
        offset = T_base_obj @ invert_transform(self.T_base_obj_ref)
        job.T_base_obj, job.offset = T_base_obj, offset
        job.residuals.update(residuals)
        return Measurement(
            found=found,
            needed=needed,
            ambiguous=ambiguous,
            T_base_obj=T_base_obj,
            offset=offset,
            model_base=self.model @ T_base_obj[:3, :3].T + T_base_obj[:3, 3],
            limit_point=self.limit_point,
            limit_point_name=self.limit_point_name,
            residuals=residuals,
        )

    def _output(self, job: _Job, status: Status, message: str) -> tuple[Status, str, Any]:
        """The vendor target of a job's offset (or grip), only for a publishable status."""
        offset = job.offset
        assert offset is not None
        sent = offset if self.T_base_grip_ref is None else offset @ self.T_base_grip_ref
        target = target_from_transform(self.config.output.vendor, sent) if (
            status.pose_valid
        ) else None
        job.lap("output")
        return status, message, target

    # ------------------------------------------------------------------ multi-camera
    def _run_multi(self, multi: ViewsLocator, pair: ImagePair, job: _Job
                   ) -> tuple[Status, str, Any]:
        """A multi-camera cell (docs/multicamera.md): marks in every image, one joint fit."""
        vision, limits = self.config.vision, self.config.limits
        n_cams = len(multi.cameras)
        if len(pair.views) != n_cams:
            raise _Reject(Status.CAMERA_ERROR, f"{len(pair.views)} image(s) for the {n_cams} "
                          "cameras of calibration.cameras")
        grays = [_checked_gray(image, cam, f"camera {name}",
                               f"calibration.cameras.{j}.intrinsics")
                 for j, (image, cam, name) in enumerate(zip(pair.views, multi.cameras,
                                                             multi.names, strict=True))]
        job.lap("checks")
        found = [finder(gray) for finder, gray in zip(self.finders, grays, strict=True)]
        job.lap("features")
        job.trace.grays, job.trace.found = tuple(grays), tuple(found)
        job.trace.T_base_flange = pair.T_base_flange
        est = multi.locate([f.circles for f in found], [f.identified for f in found],
                           pair.T_base_flange)
        job.lap("pose")
        job.trace.odd = est.odd
        job.trace.camera_marks = tuple(int(est.residuals.get(f"camera.{name}.marks", 0))
                                       for name in multi.names)
        job.used = tuple(self.names[i] for i in np.flatnonzero(est.used))
        job.missing = tuple(self.names[i] for i in np.flatnonzero(~est.used))
        needed = vision.min_features
        if est.pose is None:
            return (*check_pose(Measurement(found=len(job.used), needed=needed,
                                      ambiguous=est.ambiguous), vision, limits), None)
        job.points_base = est.points_base
        measurement = self._measurement(job, est.pose.T_base_obj, len(job.used), needed,
                                        est.ambiguous, est.residuals)
        status, message = rig_verdict(*check_pose(measurement, vision, limits), est, vision)
        return self._output(job, status, message)

    # ------------------------------------------------------------------ stereo
    def _stereo_pose(self, left: Found, right: Found, job: _Job) -> PoseEstimate | None:
        """Pair, triangulate, match to the model and fit; None when fewer than 3 features."""
        paired = self._stereo_points(left, right, job)
        if paired is None:
            return None
        return self._stereo_match(paired, job)

    def _stereo_points(self, left: Found, right: Found, job: _Job) -> StereoPoints | None:
        """Pair the two images' features (identity, epipolar line) and triangulate them; None
        (every feature missing) under three pairs."""
        assert self.rig is not None
        vision = self.config.vision
        px_l: list[FloatArray] = []
        px_r: list[FloatArray] = []
        # Identified features pair by identity (and must still satisfy the epipolar constraint).
        fixed: dict[int, int] = {}  # feature index -> row in px_l/px_r
        for index, p in left.identified.items():
            q = right.identified.get(index)
            if q is None:
                continue
            fixed[index] = len(px_l)
            px_l.append(p)
            px_r.append(q)
        # Circles: every right candidate near the left candidate's epipolar line.
        keys: list[tuple[int, ...]] = [(-1 - i,) for i in range(len(px_l))]
        circle_rows: list[int] = []
        if len(left.circles) and len(right.circles):
            lines = self.rig.epipolar_lines_right(left.circles)
            ideal_r = self.rig.ideal_pixels(self.rig.right, right.circles)
            dist = np.abs(lines[:, :2] @ ideal_r.T + lines[:, 2:3])
            pairs = ft.match_epipolar(dist, vision.epipolar_tolerance_px)
            job.trace.pairs, job.trace.first_circle_row = pairs, len(px_l)
            for i, j in pairs:
                circle_rows.append(len(px_l))
                keys.append((2 * int(i), 2 * int(j) + 1))  # left blob i, right blob j
                px_l.append(left.circles[i])
                px_r.append(right.circles[j])
        if len(px_l) < 3:
            job.missing = self.names
            return None
        points, gap, valid = self._triangulate(np.array(px_l), np.array(px_r))
        job.trace.depth_mm, job.trace.in_front = points[:, 2], valid.copy()
        near, far = vision.working_distance_mm
        valid &= (points[:, 2] >= near) & (points[:, 2] <= far)
        return StereoPoints(np.array(px_l), np.array(px_r), points, gap, valid, keys, fixed,
                            circle_rows)

    def _stereo_match(self, paired: StereoPoints, job: _Job) -> PoseEstimate | None:
        """One object among the paired points: correspondence to the model, then the fit."""
        vision = self.config.vision
        n = len(self.names)
        points, gap, valid = paired.points, paired.gap, paired.valid
        keys, fixed, circle_rows = paired.keys, paired.fixed, paired.circle_rows
        px_l, px_r = paired.px_l, paired.px_r
        assignment = np.full(n, -1, dtype=np.intp)
        for index, row in fixed.items():
            if valid[row]:
                assignment[index] = row
        rows = np.array([r for r in circle_rows if valid[r]], dtype=np.intp)
        circle_model = np.flatnonzero(self.is_circle)
        ambiguous = False
        if rows.size and circle_model.size:
            sub = None
            if (assignment >= 0).sum() >= 3:
                sel = np.flatnonzero(assignment >= 0)
                T0 = ft.kabsch(self.model[sel], points[assignment[sel]])
                sub, _ = ft.assign_nearest(
                    self.model[circle_model], points[rows], T0, vision.model_tolerance_mm,
                    [keys[r] for r in rows],
                )
            elif circle_model.size >= 3:
                # Hypothesise and verify over every model triple (features.match_model): a
                # rival pose scoring about as well, or a match that the spurious points could
                # have made by chance, makes the job AMBIGUOUS (docs/pipeline.md).
                match = ft.match_model(
                    self.model[circle_model], points[rows], vision.model_tolerance_mm,
                    [keys[r] for r in rows], max_rms_mm=vision.max_fit_rms_mm,
                )
                if match is not None:
                    sub, ambiguous = match.assignment, match.ambiguous
                    job.trace.hypotheses = match.hypotheses
            if sub is not None:
                hit = sub >= 0
                assignment[circle_model[hit]] = rows[sub[hit]]
        job.trace.assignment = assignment
        return self._fit_stereo(assignment, points, gap, px_l, px_r, ambiguous, job)

    def _triangulate(
        self, px_l: FloatArray, px_r: FloatArray
    ) -> tuple[FloatArray, FloatArray, npt.NDArray[np.bool_]]:
        """Points (k, 3) mm in the left frame, ray gaps (k,) mm and a validity mask.

        ``StereoRig.triangulate`` refuses a whole batch when one pair meets behind a camera
        (a wrong pairing); then the pairs are triangulated one by one to keep the good ones.
        """
        assert self.rig is not None
        k = px_l.shape[0]
        try:
            tri = self.rig.triangulate(px_l, px_r)
            return tri.points_mm, tri.gap_mm, np.ones(k, dtype=bool)
        except GeometryError:
            pass
        points = np.full((k, 3), np.nan)
        gap = np.full(k, np.nan)
        valid = np.zeros(k, dtype=bool)
        for i in range(k):
            try:
                tri = self.rig.triangulate(px_l[i : i + 1], px_r[i : i + 1])
            except GeometryError:
                continue
            points[i], gap[i], valid[i] = tri.points_mm[0], tri.gap_mm[0], True
        return points, gap, valid

    def _fit_stereo(
        self,
        assignment: npt.NDArray[np.intp],
        points: FloatArray,
        gap: FloatArray,
        px_l: FloatArray,
        px_r: FloatArray,
        ambiguous: bool,
        job: _Job,
    ) -> PoseEstimate | None:
        assert self.rig is not None
        vision = self.config.vision
        sel = np.flatnonzero(assignment >= 0)
        if sel.size < 3:
            job.used = tuple(self.names[i] for i in sel)
            job.missing = tuple(self.names[i] for i in range(len(self.names)) if i not in sel)
            return None
        rows = assignment[sel]
        try:
            fit = horn_robust(self.model[sel], points[rows], threshold_mm=vision.model_tolerance_mm)
        except GeometryError:
            job.used = ()
            job.missing = self.names
            return None
        keep = sel[fit.inliers]
        used = np.zeros(len(self.names), dtype=bool)
        used[keep] = True
        job.used = tuple(self.names[i] for i in keep)
        job.missing = tuple(self.names[i] for i in np.flatnonzero(~used))
        kept_rows = assignment[keep]
        T, fit_rms = fit.T_to_from, fit.rms_mm
        measured = points[kept_rows]
        circles = keep[self.is_circle[keep]]
        if circles.size:
            # Second pass with the perspective bias of circle centres removed (see
            # _circle_centre_bias); the pose of the first pass is good enough to predict it.
            px_l, px_r = px_l.copy(), px_r.copy()
            px_l[assignment[circles]] -= _circle_centre_bias(
                self.rig.left, T, self.model[circles], self.diameters[circles])
            px_r[assignment[circles]] -= _circle_centre_bias(
                self.rig.right, self.rig.T_right_left @ T, self.model[circles],
                self.diameters[circles])
            try:
                tri = self.rig.triangulate(px_l[kept_rows], px_r[kept_rows])
                refit = horn(self.model[keep], tri.points_mm)
            except GeometryError:
                pass  # keep the first pass
            else:
                T, fit_rms = refit.T_to_from, refit.rms_mm
                measured = tri.points_mm
                gap = gap.copy()
                gap[kept_rows] = tri.gap_mm
        model_cam = self.model[keep] @ T[:3, :3].T + T[:3, 3]
        T_right_left = self.rig.T_right_left
        model_right = model_cam @ T_right_left[:3, :3].T + T_right_left[:3, 3]
        err_l = self.rig.left.project(model_cam) - px_l[kept_rows]
        err_r = self.rig.right.project(model_right) - px_r[kept_rows]
        err = np.concatenate([np.linalg.norm(err_l, axis=1), np.linalg.norm(err_r, axis=1)])
        epi = self.rig.epipolar_residuals_px(px_l[kept_rows], px_r[kept_rows]).max(axis=1)
        residuals = {
            "fit_rms_mm": fit_rms,
            "reprojection_px": float(np.sqrt(np.mean(err**2))),
            "epipolar_px": float(np.median(epi)),
            "ray_gap_mm": float(np.max(gap[kept_rows])),
        }
        return PoseEstimate(T, used, ambiguous, residuals, measured)

    # ------------------------------------------------------------------ mono
    def _mono_pose(self, left: Found, job: _Job) -> PoseEstimate | None:
        """PnP on the identified features (ArUco ids, templates); circles carry no identity."""
        index = np.array(sorted(left.identified), dtype=np.intp)
        used = np.zeros(len(self.names), dtype=bool)
        used[index] = True
        job.used = tuple(self.names[i] for i in index)
        job.missing = tuple(self.names[i] for i in np.flatnonzero(~used))
        if index.size < MIN_PNP_FEATURES:
            return None
        px = np.array([left.identified[i] for i in index])
        try:
            result = pnp(self.model[index], px, self.left)
        except GeometryError:
            return None
        residuals = {"reprojection_px": result.rms_px}
        T = result.T_cam_obj
        return PoseEstimate(T, used, result.ambiguous, residuals,
                            self.model[index] @ T[:3, :3].T + T[:3, 3])


#: Rim vertices for predicting the imaged centre of a circle (bias error < 1e-4 px).
_RIM = np.stack([np.cos(np.linspace(0, 2 * np.pi, 48, endpoint=False)),
                 np.sin(np.linspace(0, 2 * np.pi, 48, endpoint=False))], axis=1)


def _circle_centre_bias(
    camera: CameraModel, T_cam_obj: FloatArray, centres: FloatArray, diameters: FloatArray
) -> FloatArray:
    """Imaged area centroid minus projected centre (n, 2) px of circular marks at a pose.

    Under perspective the image of a circle's centre is not the centre of its image: the
    nearer half of the disc looks bigger. The finder measures the area centroid, so this
    difference (0.01-0.05 px in the demo cell, about 0.04 mm of depth) is subtracted before the
    second fit. Marks are assumed to lie in planes normal to the object's z axis.
    """
    R, t = T_cam_obj[:3, :3], T_cam_obj[:3, 3]
    n, k = centres.shape[0], _RIM.shape[0]
    rim = np.zeros((n, k, 3))
    rim[:, :, :2] = 0.5 * diameters[:, None, None] * _RIM[None]
    rim += centres[:, None, :]
    px = camera.project(rim.reshape(-1, 3) @ R.T + t).reshape(n, k, 2)
    x, y = px[..., 0], px[..., 1]
    x1, y1 = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    cross = x * y1 - x1 * y
    area = cross.sum(axis=1) / 2.0
    centroid = np.stack([((x + x1) * cross).sum(axis=1), ((y + y1) * cross).sum(axis=1)], axis=1)
    centroid /= 6.0 * area[:, None]
    return np.asarray(centroid - camera.project(centres @ R.T + t), dtype=np.float64)


def _checked_gray(image: Any, camera: CameraModel | None, side: str,
                  where: str | None = None) -> ft.UInt8Image:
    """The 8-bit grey image of one side, or a CAMERA_ERROR naming what is wrong with it
    (``where``: the calibration section of its size, default ``calibration.<side>``)."""
    if image is None or camera is None:
        raise _Reject(Status.CAMERA_ERROR, f"{side} image missing")
    arr = np.asarray(image)
    try:
        gray = ft.gray_from_image(arr)
    except ValueError as err:
        raise _Reject(Status.CAMERA_ERROR, f"{side} image: {err}") from None
    h, w = gray.shape
    if (w, h) != (camera.width, camera.height):
        raise _Reject(
            Status.CAMERA_ERROR,
            f"{side} image is {w}x{h} but {where or f'calibration.{side}'} is "
            f"{camera.width}x{camera.height}",
        )
    lo, hi = cv2.minMaxLoc(gray)[:2]
    if hi < 16:
        raise _Reject(Status.CAMERA_ERROR, f"{side} image is black (max grey {hi:.0f})")
    if hi - lo < 8:
        raise _Reject(Status.CAMERA_ERROR, f"{side} image is flat (grey {lo:.0f}..{hi:.0f})")
    return gray


def diagnose(config: Config, pair: ImagePair) -> dg.Diagnosis:
    """Run the configured pipeline on one pair (the commissioning API; ``vgripd.vision.diagnosis``
    holds the rules) and say what each stage saw and, when the job
    fails, the likely causes with the config key to check (none for a successful job).

    Raises what ``Pipeline(config)`` raises (``NotCalibratedError``, ``ConfigError``: those
    name their key already). A job that ends before the finders (CAMERA_ERROR: black, flat or
    wrongly sized images; NOT_CALIBRATED) gets a diagnosis with no image stages and its
    message as the one cause (key ``camera`` or ``calibration``).
    """
    result, _ = Pipeline(config).process_with_points(pair, 0, diagnose=True)
    if result.diagnosis is not None:
        return result.diagnosis
    key = "camera" if result.status is Status.CAMERA_ERROR else "calibration"
    causes = () if result.status.pose_valid else (dg.Cause(key, result.message),)
    return dg.Diagnosis(status=result.status.name, images=(), causes=causes)
