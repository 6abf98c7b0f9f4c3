"""The multi-camera path of the pipeline: marks from N images -> one object pose in the base frame.

Given the marks found in every camera's image (``vgripd.vision.found``), for a cell configured
with ``calibration.cameras`` (docs/multicamera.md):

1. candidates: for every two cameras whose views overlap, each mark of one and each mark of the
   other within ``vision.epipolar_tolerance_px`` of its epipolar line, triangulated (base
   frame) and kept when in front of both within ``vision.working_distance_mm``;
2. tracks: candidates that share a mark and agree in 3D (within ``vision.model_tolerance_mm``)
   are grouped into one track (a mark seen by 2+ cameras, at most one image mark per camera),
   then triangulated from all its rays (:class:`~vgripd.geometry.points_from_views.MultiView`);
3. identification against the model by rigid distances (``features.match_model``, as the
   stereo path does; identified features, ArUco/templates, pair by identity);
4. joint fit (:func:`~vgripd.geometry.pose_from_views.fit_pose`): Horn over the tracks, then the
   6-DOF pose refined over every observation of every camera. Marks the tracks missed (seen
   by one camera only, or a view a candidate pair did not contain) are then added where the
   fitted pose predicts them, within the epipolar tolerance, and the fit repeated once more
   with the perspective bias of the circle centres removed;
5. per-rig residuals and the linearised leave-one-rig-out check
   (:func:`~vgripd.geometry.pose_from_views.rig_consistency`) that names a rig that disagrees.

Pure CPU, no state between jobs. The images come from the ``multi`` camera driver
(``drivers/cameras/multi.py``), which grabs every camera of the cell.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from itertools import combinations

import numpy as np
import numpy.typing as npt

from vgripd.config import Config
from vgripd.errors import GeometryError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.orientation import horn
from vgripd.geometry.points_from_views import MultiView
from vgripd.geometry.pose_from_views import MultiViewPose, fit_pose, rig_consistency
from vgripd.geometry.stereo import StereoRig
from vgripd.geometry.transforms import invert_transform
from vgripd.types import FloatArray
from vgripd.vision import features as ft
from vgripd.vision import scene
from vgripd.vision.rigcheck import self_inconsistent
from vgripd.vision.views_estimate import ViewsEstimate

#: Pixels a mark's predicted centre must be inside the image to count as visible there.
EDGE_MARGIN_PX = 4.0
#: Completing the observations from the fitted pose: an image mark counts as the predicted
#: one within this many epipolar tolerances (wider than the pairing, so that the marks of a
#: camera knocked a few pixels off still enter the fit and the rig check can name it).
COMPLETE_FACTOR = 4.0
#: An observation this many times the RMS of its camera's other observations (and above
#: ``OUTLIER_FLOOR`` of ``vision.max_reprojection_px``) is an outlier of its own camera
#: (:meth:`ViewsLocator._without_outliers`); at most ``MAX_OUTLIERS`` are dropped per job.
OUTLIER_FACTOR = 8.0
OUTLIER_FLOOR = 0.2
MAX_OUTLIERS = 8
#: A match over all tracks that identifies fewer than this share of them (or of the model's
#: marks) is checked against each rig's own match: a rig whose camera moved triangulates its
#: marks several mm off, which can leave the correct pose over all tracks beyond
#: ``vision.max_fit_rms_mm`` and let a small chance match of a few tracks win.
FALLBACK_SHARE = 0.5


def visible(camera: CameraModel, T_camera_base: FloatArray, points_base: FloatArray,
            normals_base: FloatArray) -> npt.NDArray[np.bool_]:
    """(n,) which base-frame points a camera sees: in front of it, facing it (rows of
    ``normals_base`` that are NaN face every way) and inside its image."""
    P = points_base @ T_camera_base[:3, :3].T + T_camera_base[:3, 3]
    front = P[:, 2] > 0
    eye = invert_transform(T_camera_base)[:3, 3]
    with np.errstate(invalid="ignore"):
        faces = ~(((eye - points_base) * normals_base).sum(axis=1) <= 0)
    ok = front & faces
    inside = np.zeros_like(ok)
    if ok.any():
        px = camera.project(P[ok])
        m = EDGE_MARGIN_PX
        inside[ok] = ((px[:, 0] >= m) & (px[:, 0] < camera.width - m)
                      & (px[:, 1] >= m) & (px[:, 1] < camera.height - m))
    return inside


class ViewsLocator:
    """The multi-camera geometry of one configured cell, prepared once; :meth:`locate` per job.

    Parameters
    ----------
    config : the validated config with ``calibration.cameras``.
    model : (n, 3) model points in feature order (``pipeline.model_points``).
    T_base_obj_ref : (4, 4) the taught reference pose: which cameras' views overlap is judged
        from what they see of the object there (all pairs when a camera is robot-mounted).
    """

    def __init__(self, config: Config, model: FloatArray, T_base_obj_ref: FloatArray) -> None:
        self.config = config
        self.names = scene.camera_names(config)
        self.cameras = scene.multi_camera_models(config)
        self.groups = scene.camera_groups(config)
        self.model = model
        self.normals = scene.feature_normals(config)
        self.is_circle = np.array([f.kind == "circle" for f in config.object.features])
        self.diameters = np.array([f.diameter_mm if f.kind == "circle" else 0.0
                                   for f in config.object.features])
        assert config.calibration is not None
        assert config.calibration.cameras is not None
        self.fixed = all(c.mounting == "fixed" for c in config.calibration.cameras)
        self._view: MultiView | None = None
        self._rigs: dict[tuple[int, int], StereoRig] = {}
        all_pairs = list(combinations(range(len(self.cameras)), 2))
        self.pairs = all_pairs
        if self.fixed:
            view = self._view = self.view(None)
            seen = self.visible(view, T_base_obj_ref)
            self.pairs = [(a, b) for a, b in all_pairs if (seen[:, a] & seen[:, b]).any()]
            self._rigs = self._stereo_rigs(view)

    # ------------------------------------------------------------------ geometry per job
    def view(self, T_base_flange: FloatArray | None) -> MultiView:
        """The cameras at capture (fixed cells: prepared once)."""
        if self._view is not None:
            return self._view
        return MultiView(self.cameras, scene.T_base_cameras(self.config, T_base_flange),
                         self.names, self.groups)

    def _stereo_rigs(self, view: MultiView) -> dict[tuple[int, int], StereoRig]:
        if self._view is view and self._rigs:
            return self._rigs
        return {(a, b): StereoRig(self.cameras[a], self.cameras[b],
                                  view.T_cameras_base[b] @ view.T_base_cameras[a])
                for a, b in self.pairs}

    def visible(self, view: MultiView, T_base_obj: FloatArray) -> npt.NDArray[np.bool_]:
        """(n, N) which model points each camera sees at the object pose ``T_base_obj``."""
        X = self.model @ T_base_obj[:3, :3].T + T_base_obj[:3, 3]
        normals = self.normals @ T_base_obj[:3, :3].T
        return np.stack([visible(cam, view.T_cameras_base[j], X, normals)
                         for j, cam in enumerate(self.cameras)], axis=1)

    # ------------------------------------------------------------------ the job
    def locate(self, circles: Sequence[FloatArray], identified: Sequence[dict[int, FloatArray]],
               T_base_flange: FloatArray | None) -> ViewsEstimate:
        """The object pose from the marks of every camera (``circles[j]`` (k_j, 2) px,
        ``identified[j]`` feature index -> px)."""
        vision = self.config.vision
        view = self.view(T_base_flange)
        rigs = self._stereo_rigs(view)
        n = self.model.shape[0]
        tracks = self._tracks(view, rigs, circles)
        # Identified features: one track per feature seen (with identity) by 2+ cameras.
        fixed: dict[int, dict[int, int]] = {}
        for j, ids in enumerate(identified):
            for index in ids:
                fixed.setdefault(index, {})[j] = -1 - index
        fixed = {i: cams for i, cams in fixed.items() if len(cams) >= 2}

        def pixel(cam: int, blob: int) -> FloatArray:
            return identified[cam][-1 - blob] if blob < 0 else circles[cam][blob]

        all_tracks = [cams for cams in fixed.values()] + [t for t, _ in tracks]
        table = np.full((len(all_tracks), len(self.cameras), 2), np.nan)
        for k, cams in enumerate(all_tracks):
            for cam, blob in cams.items():
                table[k, cam] = pixel(cam, blob)
        points = view.triangulate(table, strict=False).points_mm if all_tracks else np.zeros(
            (0, 3))
        assignment = np.full(n, -1, dtype=np.intp)
        for k, index in enumerate(fixed):
            if np.isfinite(points[k]).all():
                assignment[index] = k
        est = ViewsEstimate(used=np.zeros(n, dtype=bool), camera_names=self.names)
        rows = np.array([k for k in range(len(fixed), len(all_tracks))
                         if np.isfinite(points[k]).all()], dtype=np.intp)
        circle_model = np.flatnonzero(self.is_circle)
        keys = [tuple(cam * 100_000 + blob for cam, blob in cams.items()) for cams in all_tracks]
        if rows.size and circle_model.size:
            sub = None
            if (assignment >= 0).sum() >= 3:
                sel = np.flatnonzero(assignment >= 0)
                T0 = ft.kabsch(self.model[sel], points[assignment[sel]])
                sub, _ = ft.assign_nearest(self.model[circle_model], points[rows], T0,
                                           vision.model_tolerance_mm, [keys[r] for r in rows])
            elif circle_model.size >= 3:
                sub, est.ambiguous = self._identify(points[rows], [keys[r] for r in rows],
                                                    [all_tracks[r] for r in rows])
            if sub is not None:
                hit = sub >= 0
                assignment[circle_model[hit]] = rows[sub[hit]]
        if (assignment >= 0).sum() < 3:
            est.used = assignment >= 0
            return est
        px = np.full((n, len(self.cameras), 2), np.nan)
        taken: set[tuple[int, int]] = set()
        for i in np.flatnonzero(assignment >= 0):
            for cam, blob in all_tracks[assignment[i]].items():
                px[i, cam] = pixel(cam, blob)
                taken.add((cam, blob))
        for j, ids in enumerate(identified):  # identity known: every view counts, even alone
            for index, p in ids.items():
                px[index, j] = p
        try:
            pose = fit_pose(view, self.model, px)
            px = self._complete(view, pose.T_base_obj, px, circles, taken)
            px = self._unbiased(view, pose.T_base_obj, px)
            pose = fit_pose(view, self.model, px, pose.T_base_obj)
            pose, px, dropped = self._without_outliers(view, pose, px)
        except GeometryError:
            est.used = assignment >= 0
            return est
        est = self._measure(view, rigs, est, pose, px)
        est.residuals["outliers"] = float(dropped)
        self._without_odd_rig(view, est, px)
        est.lost = self._lost(view, est, px, [len(c) + len(i) for c, i in
                                              zip(circles, identified, strict=True)])
        return est

    def _lost(self, view: MultiView, est: ViewsEstimate, px: FloatArray, blobs: list[int]
              ) -> tuple[str, ...]:
        """Cameras that found mark-like blobs (3 or more) and should see 3 or more marks at
        the found pose, yet contribute no observation: their image is not what their
        calibration predicts (images given in the wrong order, or a camera turned far away).
        The others' pose can be right; the job must not look healthy."""
        assert est.pose is not None
        seen = self.visible(view, est.pose.T_base_obj).sum(axis=0)
        return tuple(name for j, name in enumerate(self.names)
                     if seen[j] >= 3 and blobs[j] >= 3 and np.isnan(px[:, j, 0]).all())

    def _without_odd_rig(self, view: MultiView, est: ViewsEstimate, px: FloatArray) -> None:
        """When one rig is named and the others agree among themselves, the pose the job
        gives is theirs: the named rig's calibration is wrong, so its rays only pull the
        joint pose off (by up to a millimetre, measured). Residuals, pose checks and the verdict
        stay those of the joint fit: a job refused for its residuals is still refused; one
        published with OK_RECALIBRATE gets the better pose. ``est.excluded`` names the rig."""
        if len(est.odd) != 1 or est.pose is None:
            return
        check = next(c for c in est.checks if c.name == est.odd[0])
        if not check.rest_rms_px <= self.config.vision.max_reprojection_px:
            return  # NaN (the others cannot fix a pose alone) or they do not agree
        members = next(m for name, m in self.groups if name == check.name)
        rest = px.copy()
        rest[:, list(members)] = np.nan
        try:
            pose = fit_pose(view, self.model, rest, est.pose.T_base_obj)
        except GeometryError:
            return
        joint, T = est.pose.T_base_obj, pose.T_base_obj
        est.pose = replace(est.pose, T_base_obj=T)
        est.excluded = check.name
        # Which of its cameras moved: under the others' pose the knocked camera's marks are
        # off, its partner's are not (under the joint pose both share the error).
        X = self.model @ T[:3, :3].T + T[:3, 3]
        for j in members:
            rows = np.flatnonzero(~np.isnan(px[:, j, 0]))
            if rows.size:
                Tc = view.T_cameras_base[j]
                e = np.linalg.norm(self.cameras[j].project(X[rows] @ Tc[:3, :3].T + Tc[:3, 3])
                                   - px[rows, j], axis=1)
                est.residuals[f"camera.{self.names[j]}.rest_px"] = float(
                    np.sqrt(np.mean(e * e)))
        # How far leaving the rig out moved the marks: what its calibration error cost.
        est.residuals["excluded_shift_mm"] = float(np.max(np.linalg.norm(
            (self.model @ T[:3, :3].T + T[:3, 3]) - (self.model @ joint[:3, :3].T + joint[:3, 3]),
            axis=1)))

    def _without_outliers(self, view: MultiView, pose: MultiViewPose, px: FloatArray
                          ) -> tuple[MultiViewPose, FloatArray, int]:
        """The fit again without observations that stand out in their own camera.

        One image mark can be wrong while its camera is right: a blob touching a mark or a
        glint on its rim shifts its centroid by pixels. Such an observation is far off while
        the other marks of the same camera fit to the finder's noise. A knocked camera is
        different: all its marks are off alike, none stands out, so the rig check still sees
        it. Dropped, worst first and refitting each time: an observation whose error is
        above ``OUTLIER_FACTOR`` times the RMS of its camera's other observations and above
        ``OUTLIER_FLOOR`` of the limit; at most a quarter of a camera's observations, and
        never below 3 marks per camera."""
        limit_px = self.config.vision.max_reprojection_px
        dropped = 0
        out = px
        for _ in range(MAX_OUTLIERS):
            worst: tuple[float, int, int] | None = None
            for j in range(len(self.cameras)):
                e = pose.errors_px[:, j]
                rows = np.flatnonzero(np.isfinite(e))
                if rows.size < 4 or rows.size <= 3 * dropped_in(out, px, j):
                    continue
                k = rows[int(np.argmax(e[rows]))]
                rest = e[rows[rows != k]]
                limit = max(OUTLIER_FACTOR * float(np.sqrt(np.mean(rest * rest))),
                            OUTLIER_FLOOR * limit_px)
                if e[k] > limit and (worst is None or e[k] / limit > worst[0]):
                    worst = (float(e[k] / limit), int(k), j)
            if worst is None:
                break
            _, k, j = worst
            trial = out.copy()
            trial[k, j] = np.nan
            try:
                pose = fit_pose(view, self.model, trial, pose.T_base_obj)
            except GeometryError:
                break
            out = trial
            dropped += 1
        return pose, out, dropped

    def _identify(self, points: FloatArray, keys: list[tuple[int, ...]],
                  tracks: list[dict[int, int]]
                  ) -> tuple[npt.NDArray[np.intp] | None, bool]:
        """Which track is which circle mark: the rigid-distance match over all tracks; when
        that is ambiguous, fails or explains few of the tracks, the best unambiguous match of
        one rig's own tracks (or of all tracks but one rig's), whose pose then assigns the
        other tracks (a rig whose camera moved triangulates its marks a few mm off, which can
        spoil the match of the whole set but not of the others), unless the match over all
        tracks still explains more."""
        vision = self.config.vision
        model = self.model[self.is_circle]
        match = ft.match_model(model, points, vision.model_tolerance_mm, keys,
                               max_rms_mm=vision.max_fit_rms_mm)
        if (match is not None and not match.ambiguous
                and match.count >= FALLBACK_SHARE * min(len(points), len(model))):
            return match.assignment, False
        best: ft.ModelMatch | None = None
        # Each rig's own tracks, and every rig's tracks but one rig's (a cell of single
        # cameras has no own tracks: leaving the knocked camera out is what helps there).
        subsets: dict[bytes, npt.NDArray[np.bool_]] = {}
        for _, members in self.groups:
            cams = set(members)
            for mask in (np.array([set(t) <= cams for t in tracks]),
                         np.array([not set(t) & cams for t in tracks])):
                subsets.setdefault(mask.tobytes(), mask)
        for own in subsets.values():
            if own.sum() < 3 or own.all():
                continue
            rig_match = ft.match_model(model, points[own], vision.model_tolerance_mm,
                                       [k for k, o in zip(keys, own, strict=True) if o],
                                       max_rms_mm=vision.max_fit_rms_mm)
            if rig_match is not None and not rig_match.ambiguous and rig_match.count >= 4 and (
                    best is None or rig_match.score > best.score):
                best = rig_match
        if best is None:
            return (None, False) if match is None else (match.assignment, match.ambiguous)
        sub, _ = ft.assign_nearest(model, points, best.T_points_model,
                                   2 * vision.model_tolerance_mm, keys)
        # A valid match over all tracks that explains more of them than the rig's pose does
        # stands (the rigs were asked only because it explained few).
        if (match is not None and not match.ambiguous
                and match.count >= int((sub >= 0).sum())):
            return match.assignment, False
        return sub, False

    def _tracks(self, view: MultiView, rigs: dict[tuple[int, int], StereoRig],
                circles: Sequence[FloatArray]) -> list[tuple[dict[int, int], FloatArray]]:
        """Marks seen by 2+ cameras: epipolar candidates of every overlapping pair, grouped
        where they share an image mark and agree in 3D. Each track maps camera -> mark index."""
        vision = self.config.vision
        near, far = vision.working_distance_mm
        cands: list[tuple[float, int, int, int, int]] = []  # (distance, a, i, b, j)
        for (a, b), rig in rigs.items():
            if not (len(circles[a]) and len(circles[b])):
                continue
            lines = rig.epipolar_lines_right(circles[a])
            ideal_b = rig.ideal_pixels(rig.right, circles[b])
            dist = np.abs(lines[:, :2] @ ideal_b.T + lines[:, 2:3])
            for i, j in ft.match_epipolar(dist, vision.epipolar_tolerance_px):
                cands.append((float(dist[i, j]), a, int(i), b, int(j)))
        if not cands:
            return []
        table = np.full((len(cands), len(self.cameras), 2), np.nan)
        for k, (_, a, i, b, j) in enumerate(cands):
            table[k, a], table[k, b] = circles[a][i], circles[b][j]
        X = view.triangulate(table, strict=False).points_mm
        centres = view.centres_mm
        tracks: list[tuple[dict[int, int], FloatArray]] = []
        member: dict[tuple[int, int], list[int]] = {}
        tol = vision.model_tolerance_mm
        for k in np.argsort([c[0] for c in cands], kind="stable"):
            _, a, i, b, j = cands[k]
            x = X[k]
            if not np.isfinite(x).all():
                continue
            depth_a = np.linalg.norm(x - centres[a])
            depth_b = np.linalg.norm(x - centres[b])
            if not (near <= depth_a <= far and near <= depth_b <= far):
                continue
            joined = False
            for t in member.get((a, i), []) + member.get((b, j), []):
                cams, point = tracks[t]
                if (cams.get(a, i) != i or cams.get(b, j) != j
                        or np.linalg.norm(point - x) > tol):
                    continue
                for cam, blob in ((a, i), (b, j)):
                    if cam not in cams:
                        cams[cam] = blob
                        member.setdefault((cam, blob), []).append(t)
                joined = True
                break
            if not joined:
                tracks.append(({a: i, b: j}, x))
                member.setdefault((a, i), []).append(len(tracks) - 1)
                member.setdefault((b, j), []).append(len(tracks) - 1)
        return tracks

    def _complete(self, view: MultiView, T_base_obj: FloatArray, px: FloatArray,
                  circles: Sequence[FloatArray], taken: set[tuple[int, int]]) -> FloatArray:
        """Add the observations the tracks missed: each circle mark the pose predicts in a
        camera that has no pixel for it yet takes the nearest free image mark within
        ``COMPLETE_FACTOR`` epipolar tolerances, when no other mark is nearly as near (a mark
        seen by one camera only, or a third view)."""
        tol = COMPLETE_FACTOR * self.config.vision.epipolar_tolerance_px
        seen = self.visible(view, T_base_obj)
        X = self.model @ T_base_obj[:3, :3].T + T_base_obj[:3, 3]
        out = px.copy()
        for j, cam in enumerate(self.cameras):
            want = np.flatnonzero(seen[:, j] & np.isnan(px[:, j, 0]) & self.is_circle)
            if not want.size or not len(circles[j]):
                continue
            T = view.T_cameras_base[j]
            pred = cam.project(X[want] @ T[:3, :3].T + T[:3, 3])
            d = np.linalg.norm(pred[:, None, :] - circles[j][None], axis=2)
            # Unambiguous only: the nearest mark at most half as far as the next one.
            second = np.partition(d, 1, axis=1)[:, 1] if d.shape[1] > 1 else np.full(
                d.shape[0], np.inf)
            for o in np.argsort(d, axis=None, kind="stable"):
                r, blob = divmod(int(o), d.shape[1])
                if d[r, blob] > tol:
                    break
                if ((j, blob) in taken or not np.isnan(out[want[r], j, 0])
                        or 2 * d[r, blob] > second[r]):
                    continue
                out[want[r], j] = circles[j][blob]
                taken.add((j, blob))
        return out

    def _unbiased(self, view: MultiView, T_base_obj: FloatArray, px: FloatArray) -> FloatArray:
        """Circle pixels with the perspective bias of their centres removed (the finder
        measures the area centroid of the imaged disc, not the image of its centre)."""
        out = px.copy()
        circles = np.flatnonzero(self.is_circle)
        for j, cam in enumerate(self.cameras):
            rows = circles[~np.isnan(px[circles, j, 0])]
            if rows.size:
                out[rows, j] -= circle_centre_bias(
                    cam, view.T_cameras_base[j] @ T_base_obj, self.model[rows],
                    self.diameters[rows], self.normals[rows])
        return out

    def _measure(self, view: MultiView, rigs: dict[tuple[int, int], StereoRig],
                 est: ViewsEstimate, pose: MultiViewPose, px: FloatArray) -> ViewsEstimate:
        vision = self.config.vision
        seen: npt.NDArray[np.bool_] = ~np.isnan(px[..., 0])
        est.used = np.asarray(seen.any(axis=1), dtype=bool)
        est.pose = pose
        T = pose.T_base_obj
        model_base = self.model @ T[:3, :3].T + T[:3, 3]
        tri = view.triangulate(px, strict=False)
        ok = np.asarray(np.isfinite(tri.points_mm).all(axis=1), dtype=bool)
        names = scene.feature_names(self.config)
        est.points_base = {names[i]: (tri.points_mm[i] if ok[i] else model_base[i])
                           for i in np.flatnonzero(est.used)}
        r = est.residuals
        r["reprojection_px"] = pose.rms_px
        if ok.any():
            d = np.linalg.norm(tri.points_mm[ok] - model_base[ok], axis=1)
            r["fit_rms_mm"] = float(np.sqrt(np.mean(d * d)))
            r["ray_distance_mm"] = float(np.nanmax(tri.ray_distance_mm[ok]))
        epi: dict[tuple[int, int], FloatArray] = {}  # camera pair -> its marks' residuals
        for (a, b), rig in rigs.items():
            both = seen[:, a] & seen[:, b]
            if both.any():
                epi[a, b] = rig.epipolar_residuals_px(px[both, a], px[both, b]).max(axis=1)
        if epi:
            r["epipolar_px"] = float(np.median(np.concatenate(list(epi.values()))))
        # A rig's own epipolar residual: the pairs of its own cameras only. A pair across two
        # groups says nothing about either alone (a knocked camera would make every camera
        # it overlaps with look inconsistent, and single cameras have no pair of their own).
        rig_epi = {}
        for name, members in self.groups:
            mine = [e for (a, b), e in epi.items() if a in members and b in members]
            if mine:
                rig_epi[name] = r[f"rig.{name}.epipolar_px"] = float(
                    np.median(np.concatenate(mine)))
        for j, name in enumerate(self.names):
            e = pose.errors_px[:, j]
            e = e[np.isfinite(e)]
            r[f"camera.{name}.marks"] = float(e.size)
            if e.size:
                r[f"camera.{name}.reprojection_px"] = float(np.sqrt(np.mean(e * e)))
        for g in pose.groups:
            r[f"rig.{g.name}.marks"] = float(g.observations)
            if g.observations:
                r[f"rig.{g.name}.reprojection_px"] = g.rms_px
        own_fit, joint_fit = self._rig_fits(view, px, model_base)
        for name, rms in own_fit.items():
            r[f"rig.{name}.own_fit_mm"] = rms
            r[f"rig.{name}.fit_rms_mm"] = joint_fit[name]
        if len(self.groups) >= 2:
            est.checks = rig_consistency(
                view, self.model, px, T, limit_px=vision.max_reprojection_px,
                max_deviation_mm=vision.rig_deviation_mm,
                max_deviation_deg=vision.rig_deviation_deg)
            for c in est.checks:
                for key, value in (("deviation_mm", c.deviation_mm),
                                   ("deviation_deg", c.deviation_deg),
                                   ("alone_px", c.alone_rms_px)):
                    if np.isfinite(value):
                        r[f"rig.{c.name}.{key}"] = value
            # A rig that is not consistent in itself (its own marks do not fit the model in
            # 3D, its cameras break their epipolar geometry, or its own pose fit leaves
            # pixel residuals beyond the limit) while every other rig is: one of its
            # cameras moved. (The leave-one-out check alone misses a camera moved along its
            # rig's baseline: that scales the rig's depths, which a pose fitted on pixels
            # mostly absorbs.)
            inconsistent = {c.name for c in est.checks
                            if own_fit.get(c.name, 0.0) > vision.max_fit_rms_mm
                            or rig_epi.get(c.name, 0.0) > vision.epipolar_warn_px
                            or c.alone_rms_px > vision.max_reprojection_px}
            inconsistent |= self_inconsistent(
                est.checks, {g.name: g.observations for g in pose.groups},
                vision.max_reprojection_px)
            # Or, failing that, the one rig whose residuals under the joint pose break a limit
            # while the others' do not (its residuals dominate the job's).
            dominant = {g.name for g in pose.groups
                        if joint_fit.get(g.name, 0.0) > vision.max_fit_rms_mm
                        or g.rms_px > vision.max_reprojection_px}
            alone = inconsistent if len(inconsistent) < len(est.checks) else set()
            if alone:
                # A rig inconsistent in itself is in the rest of every other rig, so their
                # leave-one-out verdicts are judged against a pose it spoiled: it alone is
                # named (a knocked camera of three rigs made the wrong rig look odd too).
                est.odd = tuple(c.name for c in est.checks if c.name in alone)
                return est
            if not any(c.odd for c in est.checks) and len(dominant) == 1:
                alone = dominant
            est.odd = tuple(c.name for c in est.checks if c.odd or c.name in alone)
        return est

    def _rig_fits(self, view: MultiView, px: FloatArray, model_base: FloatArray
                  ) -> tuple[dict[str, float], dict[str, float]]:
        """Per group, from the marks the group alone triangulates (groups that triangulate
        fewer than 3 are left out): the RMS (mm) of Horn's fit of the model onto them (is the
        rig consistent in itself?) and their RMS distance from the model at the joint pose
        ``model_base`` (does it agree with the others?)."""
        out, joint = {}, {}
        for name, members in self.groups:
            if len(members) < 2:
                continue
            sub = np.full_like(px, np.nan)
            sub[:, list(members)] = px[:, list(members)]
            tri = view.triangulate(sub, strict=False).points_mm
            ok = np.isfinite(tri).all(axis=1)
            if ok.sum() >= 3:
                try:
                    out[name] = horn(self.model[ok], tri[ok]).rms_mm
                except GeometryError:
                    continue
                d = np.linalg.norm(tri[ok] - model_base[ok], axis=1)
                joint[name] = float(np.sqrt(np.mean(d * d)))
        return out, joint


def dropped_in(now: FloatArray, before: FloatArray, camera: int) -> int:
    """How many observations of ``camera`` the outlier check has dropped so far."""
    return int((np.isnan(now[:, camera, 0]) & ~np.isnan(before[:, camera, 0])).sum())


#: Rim vertices for predicting the imaged centre of a circle (bias error < 1e-4 px).
_THETA = np.linspace(0, 2 * np.pi, 48, endpoint=False)


def circle_centre_bias(camera: CameraModel, T_cam_obj: FloatArray, centres: FloatArray,
                       diameters: FloatArray, normals: FloatArray) -> FloatArray:
    """Imaged area centroid minus projected centre (n, 2) px of circular marks at a pose.

    As ``pipeline._circle_centre_bias``, for marks whose plane is normal to their feature's
    ``normal`` (object frame; NaN rows: the object's z axis).
    """
    R, t = T_cam_obj[:3, :3], T_cam_obj[:3, 3]
    n = centres.shape[0]
    rim = np.empty((n, _THETA.size, 3))
    for i in range(n):
        nz = normals[i] if np.isfinite(normals[i]).all() else np.array([0.0, 0.0, 1.0])
        u = np.cross([0.0, 0.0, 1.0], nz) if abs(nz[2]) < 0.9 else np.cross(nz, [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(nz, u)
        rim[i] = centres[i] + 0.5 * diameters[i] * (np.cos(_THETA)[:, None] * u
                                                     + np.sin(_THETA)[:, None] * v)
    px = camera.project(rim.reshape(-1, 3) @ R.T + t).reshape(n, _THETA.size, 2)
    x, y = px[..., 0], px[..., 1]
    x1, y1 = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    cross = x * y1 - x1 * y
    area = cross.sum(axis=1) / 2.0
    centroid = np.stack([((x + x1) * cross).sum(axis=1), ((y + y1) * cross).sum(axis=1)], axis=1)
    centroid /= 6.0 * area[:, None]
    return np.asarray(centroid - camera.project(centres @ R.T + t), dtype=np.float64)
