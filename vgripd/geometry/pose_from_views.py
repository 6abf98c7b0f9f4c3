"""The pose of one object seen by N calibrated cameras, and which camera group disagrees.

:func:`fit_pose`: Horn's closed form (``geometry/orientation.py``) over the marks triangulated
from 2+ cameras (the union of what every rig sees, in the base frame), then one joint
refinement of the 6-DOF object pose over the reprojection errors of every observation in every
camera (marks seen by a single camera count too), with residuals per camera group (rig).

:func:`rig_consistency`: a linearised leave-one-group-out analysis around the joint fit that
names the group (rig) that disagrees with the others: a camera knocked out of its calibration.

Pixels are (n, N, 2) tables as in :mod:`vgripd.geometry.points_from_views` (NaN = not seen);
millimetres, radians, pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from vgripd.errors import ConvergenceError, DegenerateInputError
from vgripd.geometry.camera_model import project_with_jacobian
from vgripd.geometry.orientation import horn, pnp
from vgripd.geometry.points_from_views import MIN_DEPTH_MM, MultiView, pixel_table
from vgripd.geometry.transforms import (
    check_transform,
    left_jacobians,
    make_transform,
    matrix_from_rotvec,
    skew,
)
from vgripd.types import FloatArray

__all__ = ["GroupCheck", "GroupResidual", "MultiViewPose", "fit_pose", "rig_consistency"]

#: Stopping tolerances of the joint pose refinement (relative cost decrease, step, gradient).
TOLERANCE = 1e-12
MAX_EVALUATIONS = 100
#: A group counts as odd only when the other groups agree about as well without it as they
#: do without the best candidate: their RMS within this factor of the best rest's, or within
#: this share of the limit above it (noise-free data has rests near 0).
AGREE_FACTOR = 2.0
AGREE_SLACK = 0.1
#: Condition number of a 6x6 normal matrix above which a group (or the rest of the cameras)
#: does not determine the pose on its own.
MAX_CONDITION = 1e10
#: How many standard deviations of the poses' noise a rig's disagreement must exceed, on top of
#: the pose checks, before the rig is blamed. A rig far away, with a short baseline or a low
#: resolution fixes the object's pose loosely; a near high-resolution rig then sees that
#: pose's noise as pixels beyond the limit although no camera moved. The noise comes from the
#: same Jacobian (covariance s^2 H^-1, s^2 from the residuals), so it costs nothing extra. A
#: knocked camera leaves the residuals of the others at the finder's noise: its allowance
#: stays a small fraction of a pixel.
UNCERTAINTY_SIGMAS = 3.0


@dataclass(frozen=True)
class GroupResidual:
    """Reprojection residuals of one camera group (rig) under the joint pose.

    ``rms_px``: root mean square of the pixel error lengths of the group's observations (NaN
    if it has none); ``max_px``; ``observations``: how many (mark, camera) pairs it has.
    """

    name: str
    cameras: tuple[int, ...]
    observations: int
    rms_px: float
    max_px: float


@dataclass(frozen=True, eq=False)
class MultiViewPose:
    """Result of :func:`fit_pose`.

    Attributes
    ----------
    T_base_obj : (4, 4) float64
        Object pose in the base frame after the joint refinement.
    T_base_obj_horn : (4, 4) float64
        The closed-form start: Horn over the triangulated marks (or one camera's PnP when fewer
        than 3 marks are seen by two cameras).
    horn_rms_mm : float
        Horn's fit residual over the triangulated marks (NaN when PnP started it).
    rms_px, max_px : float
        Over every observation under the joint pose.
    errors_px : (n, N) float64
        Reprojection error of each model point in each camera (px), NaN where not observed.
    groups : tuple of GroupResidual
        Per camera group (rig), in the order of ``MultiView.groups``.
    triangulated : int
        Marks seen by 2+ cameras (Horn's points).
    converged : bool
        The refinement met its tolerances (otherwise it stopped at its evaluation limit).
    """

    T_base_obj: FloatArray
    T_base_obj_horn: FloatArray
    horn_rms_mm: float
    rms_px: float
    max_px: float
    errors_px: FloatArray
    groups: tuple[GroupResidual, ...]
    triangulated: int
    converged: bool


@dataclass(frozen=True)
class GroupCheck:
    """One group's part of :func:`rig_consistency` (linearised around the joint fit).

    ``rest_rms_px``: the other groups' RMS when the pose is fitted without this group (NaN when
    they cannot determine a pose alone); ``predicted_rms_px``: this group's RMS under that pose
    (how badly the others' pose explains this group); ``alone_rms_px``: this group's RMS fitted
    alone (NaN when it cannot: too few marks); ``deviation_mm`` / ``deviation_deg``: how far
    the pose from this group alone is from the pose from the rest, at this group's marks (mm:
    the largest displacement of its marks) and in rotation (deg); NaN when either cannot be
    fitted. ``odd``: the rest agree among themselves (``rest_rms_px`` within the limit) and this
    group does not (predicted RMS beyond the limit, or deviation beyond its limits).
    """

    name: str
    rest_rms_px: float
    predicted_rms_px: float
    alone_rms_px: float
    deviation_mm: float
    deviation_deg: float
    odd: bool


@dataclass
class _Observations:
    """The observed (point, camera) pairs, grouped by camera for batched projection."""

    per_camera: list[tuple[int, npt.NDArray[np.intp], FloatArray]]  # (camera, points, px)
    count: int


# ------------------------------------------------------------------ the object pose
def _observations(mv: MultiView, px: FloatArray) -> _Observations:
    per_camera = []
    count = 0
    for j in range(len(mv.cameras)):
        idx = np.flatnonzero(~np.isnan(px[:, j, 0]))
        if idx.size:
            per_camera.append((j, idx, px[idx, j]))
            count += idx.size
    return _Observations(per_camera, count)

def _residuals(mv: MultiView, obs: _Observations, X_base: FloatArray, dX: FloatArray | None
               ) -> tuple[FloatArray, FloatArray | None, FloatArray]:
    """Stacked residuals (2K,) of all observations for base-frame model points X_base
    (n, 3), their Jacobian (2K, 6) when ``dX`` (n, 3, 6) = d X_base / d params is given,
    and the smallest depth of each observation (K,)."""
    r = np.empty(2 * obs.count)
    J = np.empty((2 * obs.count, 6)) if dX is not None else None
    depth = np.empty(obs.count)
    k = 0
    for j, idx, px in obs.per_camera:
        R = mv.T_cameras_base[j, :3, :3]
        Pc = X_base[idx] @ R.T + mv.T_cameras_base[j, :3, 3]
        depth[k:k + idx.size] = Pc[:, 2]
        Pc[:, 2] = np.maximum(Pc[:, 2], MIN_DEPTH_MM)
        proj, Jp = project_with_jacobian(mv.cameras[j], Pc)
        r[2 * k:2 * (k + idx.size)] = (proj - px).ravel()
        if J is not None and dX is not None:
            J[2 * k:2 * (k + idx.size)] = ((Jp @ R) @ dX[idx]).reshape(-1, 6)
        k += idx.size
    return r, J, depth

def _start(mv: MultiView, model: FloatArray, px: FloatArray) -> tuple[FloatArray, float, int]:
    """Closed-form start: Horn over the marks seen by 2+ cameras, else PnP in the camera
    that sees the most marks (4 or more)."""
    tri = mv.triangulate(px, strict=False)
    ok = np.isfinite(tri.points_mm).all(axis=1)
    why = f"{int(ok.sum())} marks seen by two or more cameras (Horn needs 3)"
    if ok.sum() >= 3:
        try:
            h = horn(model[ok], tri.points_mm[ok])
            return h.T_to_from, h.rms_mm, int(ok.sum())
        except DegenerateInputError as err:
            why = f"Horn over the {int(ok.sum())} triangulated marks: {err}"
    counts = (~np.isnan(px[..., 0])).sum(axis=0)
    j = int(np.argmax(counts))
    if counts[j] < 4:
        raise DegenerateInputError(
            f"too few marks for a pose: {why}; at most {int(counts[j])} in one camera "
            "(PnP needs 4)")
    sel = ~np.isnan(px[:, j, 0])
    fit = pnp(model[sel], px[sel, j], mv.cameras[j])
    if fit.ambiguous:
        raise DegenerateInputError(
            f"too few marks seen by two cameras and camera {mv.names[j]}'s marks alone "
            "allow two poses")
    return mv.T_base_cameras[j] @ fit.T_cam_obj, math.nan, int(ok.sum())

def fit_pose(mv: MultiView, model_points: object, pixels: object,
             T_base_obj_start: object = None) -> MultiViewPose:
    """Object pose in the base frame from its model points and their pixels in N cameras.

    Horn's closed form over the triangulated marks (the union of what all cameras see)
    gives the start; then scipy's Levenberg-Marquardt minimises the sum of squared
    reprojection errors of every observation in every camera over the six pose
    parameters. The pose moves as ``X' = exp(w) (X - c) + c + v`` about the centroid c of
    the model points in the base frame, with the exact (analytic) Jacobian.

    Parameters
    ----------
    model_points : (n, 3) array_like
        Points in the object frame (mm).
    pixels : (n, N, 2) array_like
        Their pixels, NaN where a camera does not see them.
    T_base_obj_start : (4, 4) array_like, optional
        Start pose instead of the closed form (``T_base_obj_horn`` then repeats it).

    Raises
    ------
    DegenerateInputError
        Shapes, fewer marks than a pose needs, degenerate geometry, or a model point the
        fitted pose puts behind a camera that observes it (naming both).
    ConvergenceError
        A pixel cannot be undistorted.
    """
    model = np.asarray(model_points, dtype=np.float64)
    if model.ndim != 2 or model.shape[1] != 3 or not np.isfinite(model).all():
        raise DegenerateInputError(
            f"model_points: expected finite (n, 3), got shape {model.shape}")
    px = pixel_table(pixels, model.shape[0], len(mv.cameras), "pixels")
    if T_base_obj_start is None:
        T0, horn_rms, n_tri = _start(mv, model, px)
    else:
        T0 = check_transform(T_base_obj_start, "T_base_obj_start")
        horn_rms, n_tri = math.nan, int(((~np.isnan(px[..., 0])).sum(axis=1) >= 2).sum())
    obs = _observations(mv, px)
    if obs.count < 3:
        raise DegenerateInputError(f"{obs.count} observations cannot fix a 6-DOF pose")
    X0 = model @ T0[:3, :3].T + T0[:3, 3]
    c = X0.mean(axis=0)
    Y = X0 - c

    def points(x: FloatArray) -> FloatArray:
        return Y @ matrix_from_rotvec(x[:3]).T + c + x[3:]

    def fun(x: FloatArray) -> FloatArray:
        return _residuals(mv, obs, points(x), None)[0]

    def jac(x: FloatArray) -> FloatArray:
        RY = Y @ matrix_from_rotvec(x[:3]).T
        dX = np.empty((model.shape[0], 3, 6))
        dX[:, :, :3] = -skew(RY) @ left_jacobians(x[:3])
        dX[:, :, 3:] = np.eye(3)
        J = _residuals(mv, obs, points(x), dX)[1]
        assert J is not None
        return J

    from scipy.optimize import least_squares  # on first use: a daemon that never solves
    # here starts without it (scipy.optimize is the largest import of a start)
    sol = least_squares(fun, np.zeros(6), jac=jac, method="lm", x_scale="jac",
                        ftol=TOLERANCE, xtol=TOLERANCE, gtol=TOLERANCE,
                        max_nfev=MAX_EVALUATIONS)
    x, converged = sol.x, bool(sol.status > 0)
    R = matrix_from_rotvec(x[:3])
    T = make_transform(R, c + x[3:] - R @ c) @ T0
    r, _, depth = _residuals(mv, obs, points(x), None)
    if not (depth > 0).all():
        k = int(np.argmin(depth))
        j, i = _which(mv, obs, k)
        raise DegenerateInputError(f"model point {i} lies behind camera {mv.names[j]} "
                                   f"in the fitted pose (depth {depth[k]:.4g} mm)")
    if not np.isfinite(r).all():
        raise ConvergenceError("pose refinement ended with non-finite residuals")
    errors = _errors_table(mv, obs, r, model.shape[0])
    return MultiViewPose(
        T_base_obj=T, T_base_obj_horn=T0, horn_rms_mm=horn_rms,
        rms_px=_rms(errors), max_px=float(np.nanmax(errors)), errors_px=errors,
        groups=_group_residuals(mv, errors), triangulated=n_tri, converged=converged)

def _which(mv: MultiView, obs: _Observations, k: int) -> tuple[int, int]:
    """(camera, point) of observation number k."""
    for j, idx, _ in obs.per_camera:
        if k < idx.size:
            return j, int(idx[k])
        k -= idx.size
    raise IndexError(k)

def _errors_table(mv: MultiView, obs: _Observations, r: FloatArray, n: int) -> FloatArray:
    out = np.full((n, len(mv.cameras)), np.nan)
    e = np.linalg.norm(r.reshape(-1, 2), axis=1)
    k = 0
    for j, idx, _ in obs.per_camera:
        out[idx, j] = e[k:k + idx.size]
        k += idx.size
    return out

def _group_residuals(mv: MultiView, errors: FloatArray) -> tuple[GroupResidual, ...]:
    out = []
    for name, members in mv.groups:
        e = errors[:, list(members)]
        e = e[~np.isnan(e)]
        out.append(GroupResidual(name=name, cameras=members, observations=int(e.size),
                                 rms_px=_rms(e), max_px=float(e.max()) if e.size else math.nan))
    return tuple(out)

# ------------------------------------------------------------------ consistency
def rig_consistency(mv: MultiView, model_points: object, pixels: object, T_base_obj: object, *,
                limit_px: float, max_deviation_mm: float, max_deviation_deg: float
                ) -> tuple[GroupCheck, ...]:
    """Which group (rig) disagrees with the others, around the joint pose ``T_base_obj``.

    With the stacked residuals r and Jacobian J of all observations at the joint optimum,
    each group g owns some rows (r_g, J_g) and its normal equations (H_g = J_g^T J_g,
    b_g = J_g^T r_g). One Gauss-Newton step from the joint pose gives, in closed form:

    * the pose from the other groups alone: ``d_rest = -(H - H_g)^-1 (b - b_g)``, their
      RMS under it (do they agree among themselves?) and g's RMS under it (does g agree
      with them?);
    * the pose from g alone: ``d_g = -H_g^-1 b_g`` (when g determines a pose), its RMS
      (is g consistent in itself? a moved camera of a stereo rig is not) and the
      difference between the two poses at g's marks (mm) and in rotation (deg).

    Every figure comes from the one Jacobian of the joint fit, so the whole check costs
    about as much as one iteration of it: linear in the number of observations. The
    linearisation holds while the poses differ by small motions (well beyond the
    millimetres and tenths of a degree a knocked camera causes).

    A group is ``odd`` when the rest agree (``rest_rms_px <= limit_px``, and about as well as
    the rest of the best candidate: ``AGREE_FACTOR``, ``AGREE_SLACK``) and g does not
    (``predicted_rms_px > limit_px``, or the deviation beyond ``max_deviation_mm`` /
    ``max_deviation_deg``). With three or more groups, a group moved as a whole is named
    alone. With two groups both can be odd (a rig moved as a whole is
    self-consistent: nothing tells which of two moved); with one camera of a stereo rig
    moved, only that rig is.
    """
    model = np.asarray(model_points, dtype=np.float64)
    px = pixel_table(pixels, model.shape[0], len(mv.cameras), "pixels")
    T = check_transform(T_base_obj, "T_base_obj")
    obs = _observations(mv, px)
    X = model @ T[:3, :3].T + T[:3, 3]
    c = X.mean(axis=0)
    dX = np.empty((model.shape[0], 3, 6))
    dX[:, :, :3] = -skew(X - c)
    dX[:, :, 3:] = np.eye(3)
    r, J, _ = _residuals(mv, obs, X, dX)
    assert J is not None
    cam_of_obs = np.concatenate([np.full(idx.size, j) for j, idx, _ in obs.per_camera])
    point_of_obs = np.concatenate([idx for _, idx, _ in obs.per_camera])
    H = J.T @ J
    b = J.T @ r
    out = []
    for name, members in mv.groups:
        in_g = np.isin(cam_of_obs, members)
        rows = np.repeat(in_g, 2)
        Jg, rg = J[rows], r[rows]
        Hg, bg = Jg.T @ Jg, Jg.T @ rg
        d_rest = _solve(H - Hg, -(b - bg))
        d_alone = _solve(Hg, -bg)
        rest_rms = pred_rms = alone_rms = dev_mm = dev_deg = math.nan
        # What the noise alone explains (0 when a pose is missing): see _noise_allowance.
        slack_px = slack_mm = slack_deg = 0.0
        if d_rest is not None:
            res_rest = r[~rows] + J[~rows] @ d_rest
            rest_rms = _rms_rows(res_rest)
            pred_rms = _rms_rows(rg + Jg @ d_rest)
            var = _coordinate_variance(res_rest)
            cov_rest = var * np.linalg.inv(H - Hg)
            slack_px = UNCERTAINTY_SIGMAS * math.sqrt(
                max(float(np.trace(Jg @ cov_rest @ Jg.T)), 0.0) / max(rg.size // 2, 1))
        if d_alone is not None:
            alone_rms = _rms_rows(rg + Jg @ d_alone)
        if d_rest is not None and d_alone is not None:
            diff = d_alone - d_rest
            marks = np.unique(point_of_obs[in_g])
            dev_mm = float(np.linalg.norm(dX[marks] @ diff, axis=1).max())
            dev_deg = math.degrees(float(np.linalg.norm(diff[:3])))
            cov = cov_rest + _coordinate_variance(rg + Jg @ d_alone) * np.linalg.inv(Hg)
            slack_mm = UNCERTAINTY_SIGMAS * math.sqrt(max(float(np.max(
                np.einsum("kij,jl,kil->k", dX[marks], cov, dX[marks]))), 0.0))
            slack_deg = UNCERTAINTY_SIGMAS * math.degrees(math.sqrt(max(float(np.trace(
                cov[:3, :3])), 0.0)))
        off = (pred_rms > limit_px + slack_px or dev_mm > max_deviation_mm + slack_mm
               or dev_deg > max_deviation_deg + slack_deg)
        out.append(GroupCheck(name=name, rest_rms_px=rest_rms, predicted_rms_px=pred_rms,
                              alone_rms_px=alone_rms, deviation_mm=dev_mm,
                              deviation_deg=dev_deg,
                              odd=bool(rest_rms <= limit_px and off)))
    # Of the candidates, only those whose rest agrees about as well as the best one's: with
    # three rigs and one knocked, leaving out a good rig leaves the knocked one in its rest,
    # whose RMS, though within the limit, is then far above the noise the best rest shows.
    rests = [c.rest_rms_px for c in out if c.odd]
    if rests:
        best = min(rests)
        agree = max(AGREE_FACTOR * best, best + AGREE_SLACK * limit_px)
        out = [c if not c.odd or c.rest_rms_px <= agree else replace(c, odd=False)
               for c in out]
    return tuple(out)


def _coordinate_variance(residuals: FloatArray) -> float:
    """Per-coordinate pixel noise variance of stacked (u, v) residuals after a 6-DOF fit
    (the sum of squares over the degrees of freedom left; 0 when none are)."""
    dof = residuals.size - 6
    return float(residuals @ residuals) / dof if dof > 0 else 0.0


def _solve(H: FloatArray, g: FloatArray) -> FloatArray | None:
    """``H^-1 g`` for a 6x6 normal matrix, or None when H does not determine a pose."""
    if not np.isfinite(H).all() or np.linalg.cond(H) > MAX_CONDITION:
        return None
    out: FloatArray = np.asarray(np.linalg.solve(H, g), dtype=np.float64)
    return out


def _rms(errors: FloatArray) -> float:
    """Root mean square of the finite entries of an error table (NaN if none)."""
    e = errors[np.isfinite(errors)]
    return float(np.sqrt(np.mean(e * e))) if e.size else math.nan


def _rms_rows(r: FloatArray) -> float:
    """RMS of the pixel error lengths of stacked (u, v) residuals (NaN if empty)."""
    return float(np.sqrt(np.sum(r * r) / (r.size // 2))) if r.size else math.nan
