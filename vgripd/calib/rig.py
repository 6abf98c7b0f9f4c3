"""Stereo rig calibration: both cameras and the left -> right transform (Bouguet's "global
stereo optimisation").

Model: each camera is a pinhole with fx, fy, cx, cy, skew 0 and Brown distortion
``[k1, k2, p1, p2, k3]`` (OpenCV order = Bouguet ``kc``; k3 fixed at 0 unless ``fix_k3=False``).
The rig is ``X_R = R(om) X_L + T`` (mm): the pose of the left camera in the right camera,
config ``T_right_left``, Bouguet's ``om``/``T``, OpenCV ``stereoCalibrate``'s ``R``/``T``.
Board view ``i`` has one pose in the left camera, ``X_L = R_i X_board + t_i``; the right camera
sees it through the rig.

Fit: starting from each camera's own calibration (``cv2.calibrateCamera`` on the same views, or
given intrinsics), ``cv2.stereoCalibrateExtended`` with ``CALIB_USE_INTRINSIC_GUESS`` minimises
the reprojection error of all points in both images over both cameras' intrinsics, om, T and the
board poses together, as Bouguet's toolbox does. On his stereo example it reproduces the
published result to every printed decimal.

Uncertainty: OpenCV's stereo fit gives no standard deviations, so they are computed here the
way the toolbox does: at the solution, the Jacobian ``J`` of all reprojection residuals (both
images, all views; 2 per point) with respect to all parameters (both intrinsics, om, T, the
left board pose of every view), ``cov = s^2 (J^T J)^-1`` with ``s^2 = SSR / (m - p)`` (m
residuals, p parameters). The projection Jacobians come from ``cv2.projectPoints``; the right
camera's through ``cv2.composeRT`` (board pose composed with the rig). ``std`` = one sigma;
Bouguet's printed ``+-`` is three sigma.

Outliers: a pair whose RMS (both images) is above ``outlier_factor`` x the median and above
``outlier_floor_px`` is dropped and the rig refitted, worst first, one pair at a time (as
``calib.intrinsics`` does for single images).

Epipolar residuals: the distance (ideal px) of every calibration point from the epipolar line
of its partner, in both images, with ``vgripd.geometry.stereo.StereoRig``; a good rig gives a few
tenths of a pixel. Large values mean corresponding points disagree with the geometry: a
mismatched pair, a rig that moved between views, unsynchronised images.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from vgripd.errors import CalibrationError, GeometryError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.stereo import StereoRig
from vgripd.geometry.transforms import make_transform, matrix_from_rotvec

MIN_PAIRS = 3
FEW_PAIRS = 10  # below this, warn (as for a single camera)
EPIPOLAR_WARN_MEDIAN_PX = 0.5
EPIPOLAR_WARN_P95_PX = 1.5
BASELINE_TOLERANCE = 0.05  # relative deviation from the hint that triggers a warning
BASELINE_SIGMA_WARN = 0.005  # relative one-sigma uncertainty of |T| that triggers a warning
CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")

FloatArray = NDArray[np.float64]


@dataclass
class RigResult:
    """A calibrated stereo rig and the evidence for it.

    ``left``/``right`` have the keys of ``config.IntrinsicsConfig`` (px); ``left_std`` /
    ``right_std`` one-sigma standard deviations of the same keys (0 for what was fixed).
    ``rotvec_rad``/``translation_mm`` (3,) are om and T of ``X_R = R(om) X_L + T``, with their
    one-sigma ``rotvec_std``/``translation_std``. Per used pair ``i``: ``names[i]`` = (left,
    right), ``per_pair[i]`` = {left, right, rms_px, points}, residuals (observed - projected,
    (N_i, 2) px) in each image, the board pose ``T_left_board[i]`` (4x4, mm) and the epipolar
    residuals ``epipolar_residuals_px[i]`` (N_i, 2) (left image, right image).
    ``covariance`` is the full parameter covariance in the order of ``parameter_names``.
    """

    left: dict[str, Any]
    right: dict[str, Any]
    left_std: dict[str, Any]
    right_std: dict[str, Any]
    rotvec_rad: FloatArray
    translation_mm: FloatArray
    rotvec_std: FloatArray
    translation_std: FloatArray
    rms_px: float
    names: list[tuple[str, str]]
    per_pair: list[dict[str, Any]]
    residuals_left_px: list[FloatArray]
    residuals_right_px: list[FloatArray]
    px_left: list[FloatArray]
    px_right: list[FloatArray]
    T_left_board: list[FloatArray]
    epipolar_residuals_px: list[FloatArray]
    epipolar_px: dict[str, float]
    covariance: FloatArray
    parameter_names: list[str]
    rejected: list[dict[str, str]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def T_right_left(self) -> FloatArray:
        """4x4 pose of the left camera in the right camera (mm): ``X_R = R X_L + T``."""
        return make_transform(matrix_from_rotvec(self.rotvec_rad), self.translation_mm)

    @property
    def rig(self) -> StereoRig:
        """The result as a :class:`vgripd.geometry.stereo.StereoRig` (triangulation, epipolar
        lines)."""
        return StereoRig(camera_model(self.left), camera_model(self.right), self.T_right_left)


def camera_model(camera: dict[str, Any]) -> CameraModel:
    """A camera dict (IntrinsicsConfig keys) as a :class:`CameraModel`."""
    d = camera["dist"]
    return CameraModel(camera["fx"], camera["fy"], camera["cx"], camera["cy"], camera["skew"],
                       (d[0], d[1], d[2], d[3], d[4]), camera["width"], camera["height"])


@dataclass
class _Views:
    """The pairs still in the fit (same order everywhere)."""

    names: list[tuple[str, str]]
    obj: list[FloatArray]
    left: list[FloatArray]
    right: list[FloatArray]

    def drop(self, i: int) -> None:
        for seq in (self.names, self.obj, self.left, self.right):
            del seq[i]


def calibrate_rig(object_points: Sequence[ArrayLike], px_left: Sequence[ArrayLike],
                  px_right: Sequence[ArrayLike], size_left: tuple[int, int],
                  size_right: tuple[int, int] | None = None, *,
                  initial: tuple[CameraModel, CameraModel] | None = None,
                  names: Sequence[tuple[str, str]] | None = None, fix_k3: bool = True,
                  baseline_hint_mm: float | None = None, outlier_factor: float = 3.0,
                  outlier_floor_px: float = 0.5) -> RigResult:
    """Calibrate a stereo rig from board points seen by both cameras.

    Parameters
    ----------
    object_points : per view (N_i, 3) board points, mm (planar or not).
    px_left, px_right : per view (N_i, 2) observed pixels of the same points, in the same order,
        OpenCV convention (centre of the top-left pixel = (0, 0)).
    size_left, size_right : image sizes (w, h) px; ``size_right`` defaults to ``size_left``.
    initial : intrinsics to start from (e.g. separate calibrations, skew 0); None = calibrate
        each camera on these views first.
    names : per view (left image, right image) for messages; default "pair 1", ...
    fix_k3 : keep k3 at 0 in both cameras (Bouguet's default).
    baseline_hint_mm : expected |T|; a result off by more than 5 % is warned about.
    outlier_factor, outlier_floor_px : the pair outlier rule (module docstring).

    Raises CalibrationError for inconsistent input (naming the view), fewer than 3 usable
    pairs, or a fit that fails.
    """
    n = len(object_points)
    if len(px_left) != n or len(px_right) != n:
        raise CalibrationError(f"object_points has {n} views but px_left {len(px_left)} and "
                               f"px_right {len(px_right)}")
    pair_names = ([(str(a), str(b)) for a, b in names] if names is not None
                  else [(f"pair {i + 1} left", f"pair {i + 1} right") for i in range(n)])
    if len(pair_names) != n:
        raise CalibrationError(f"names has {len(pair_names)} entries for {n} views")
    views = _Views(pair_names, [], [], [])
    for i in range(n):
        obj, pl, pr = _view_arrays(object_points[i], px_left[i], px_right[i], pair_names[i])
        views.obj.append(obj)
        views.left.append(pl)
        views.right.append(pr)
    sizes = (tuple(size_left), tuple(size_right or size_left))
    if initial is not None:
        for cam, side in zip(initial, ("left", "right"), strict=True):
            if cam.skew != 0.0:
                raise CalibrationError(f"initial {side} intrinsics: skew {cam.skew} px is not "
                                       "supported (the stereo fit keeps skew at 0)")
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | (cv2.CALIB_FIX_K3 if fix_k3 else 0)
    rejected: list[dict[str, str]] = []
    while True:
        if len(views.names) < MIN_PAIRS:
            raise CalibrationError(
                f"need at least {MIN_PAIRS} pairs with the board in both images, have "
                f"{len(views.names)}" + (f" ({len(rejected)} rejected)" if rejected else ""))
        fit = _fit(views, sizes, initial, flags, fix_k3)
        rms = fit["per_pair_rms"]
        median = float(np.median(rms))
        worst = int(np.argmax(rms))
        if (len(views.names) == MIN_PAIRS or rms[worst] <= outlier_factor * median
                or rms[worst] <= outlier_floor_px):
            break
        left_name, right_name = views.names[worst]
        rejected.append({"left": left_name, "right": right_name,
                         "reason": f"pair RMS {rms[worst]:.2f} px vs median {median:.2f} px "
                                   f"(outlier: > {outlier_factor:g}x median)"})
        views.drop(worst)
    return _result(views, sizes, fit, fix_k3, rejected, baseline_hint_mm)


def _view_arrays(obj: ArrayLike, pl: ArrayLike, pr: ArrayLike,
                 names: tuple[str, str]) -> tuple[FloatArray, FloatArray, FloatArray]:
    o = np.asarray(obj, dtype=np.float64)
    a = np.asarray(pl, dtype=np.float64)
    b = np.asarray(pr, dtype=np.float64)
    where = f"{names[0]} / {names[1]}"
    if o.ndim != 2 or o.shape[1] != 3:
        raise CalibrationError(f"{where}: object points must be (N, 3), got {o.shape}")
    for arr, side in ((a, "left"), (b, "right")):
        if arr.shape != (len(o), 2):
            raise CalibrationError(f"{where}: {side} pixels must be ({len(o)}, 2) like the "
                                   f"object points, got {arr.shape}")
    for arr, what in ((o, "object point"), (a, "left pixel"), (b, "right pixel")):
        bad = ~np.isfinite(arr).all(axis=1)
        if bad.any():
            raise CalibrationError(f"{where}: {what} {int(np.argmax(bad))} is not finite")
    if len(o) < 6:
        raise CalibrationError(f"{where}: only {len(o)} points (need at least 6 per view)")
    return o, a, b


def _initial_camera(views: _Views, side: str, size: tuple[int, ...],
                    fix_k3: bool) -> tuple[FloatArray, FloatArray]:
    """One camera calibrated on its own images of the views (the stereo fit's start)."""
    px = views.left if side == "left" else views.right
    try:
        _rms, K, dist, _r, _t = cv2.calibrateCamera(
            [o.astype(np.float32) for o in views.obj], [p.astype(np.float32) for p in px],
            (int(size[0]), int(size[1])), np.eye(3), np.zeros(5),
            flags=cv2.CALIB_FIX_K3 if fix_k3 else 0, criteria=CRITERIA)
    except cv2.error as err:
        raise CalibrationError(f"initial calibration of the {side} camera failed: "
                               f"{err.msg}") from None
    return np.asarray(K, dtype=np.float64), np.asarray(dist, dtype=np.float64).ravel()[:5]


def _fit(views: _Views, sizes: tuple[tuple[int, ...], tuple[int, ...]],
         initial: tuple[CameraModel, CameraModel] | None, flags: int,
         fix_k3: bool) -> dict[str, Any]:
    if initial is None:
        (K1, d1), (K2, d2) = (_initial_camera(views, "left", sizes[0], fix_k3),
                              _initial_camera(views, "right", sizes[1], fix_k3))
    else:
        (K1, d1), (K2, d2) = initial[0].to_opencv(), initial[1].to_opencv()
    try:
        (_rms, K1_out, d1_out, K2_out, d2_out, R, T, _E, _F, rvecs, tvecs,
         _per_view) = cv2.stereoCalibrateExtended(
            [o.astype(np.float32) for o in views.obj],
            [p.astype(np.float32) for p in views.left],
            [p.astype(np.float32) for p in views.right],
            K1.copy(), d1.copy(), K2.copy(), d2.copy(), (int(sizes[0][0]), int(sizes[0][1])),
            np.eye(3), np.zeros(3), flags=flags, criteria=CRITERIA)
    except cv2.error as err:
        raise CalibrationError(f"stereo calibration failed: {err.msg}") from None
    cams = [(np.asarray(K, dtype=np.float64), np.asarray(d, dtype=np.float64).ravel()[:5])
            for K, d in ((K1_out, d1_out), (K2_out, d2_out))]
    om = cv2.Rodrigues(np.asarray(R, dtype=np.float64))[0].ravel()
    t = np.asarray(T, dtype=np.float64).ravel()
    poses = [(np.asarray(r, dtype=np.float64).ravel(), np.asarray(v, dtype=np.float64).ravel())
             for r, v in zip(rvecs, tvecs, strict=True)]
    if not all(np.all(np.isfinite(x)) for x in (*cams[0], *cams[1], om, t)):
        raise CalibrationError("stereo calibration diverged (non-finite parameters); check "
                               "the board spec and that left and right images are pairs")
    res_l, res_r = [], []
    for obj, pl, pr, (rv, tv) in zip(views.obj, views.left, views.right, poses, strict=True):
        res_l.append(pl - _project(obj, rv, tv, cams[0]))
        rv_r, tv_r = cv2.composeRT(rv, tv, om, t)[:2]
        res_r.append(pr - _project(obj, np.asarray(rv_r, dtype=np.float64).ravel(),
                                   np.asarray(tv_r, dtype=np.float64).ravel(), cams[1]))
    per_pair = np.array([np.sqrt(np.mean(np.concatenate([a, b]) ** 2) * 2)
                         for a, b in zip(res_l, res_r, strict=True)])
    return {"cams": cams, "om": om, "T": t, "poses": poses, "res_l": res_l, "res_r": res_r,
            "per_pair_rms": per_pair}


def _project(obj: FloatArray, rvec: FloatArray, tvec: FloatArray,
             cam: tuple[FloatArray, FloatArray]) -> FloatArray:
    px, _ = cv2.projectPoints(obj, rvec, tvec, cam[0], cam[1])
    return np.asarray(px, dtype=np.float64).reshape(-1, 2)


def _jacobian(views: _Views, fit: dict[str, Any], fix_k3: bool) -> FloatArray:
    """d(residual)/d(parameter), rows: per view the left then the right points (u, v
    interleaved); columns: see ``_parameter_names``. Sign: of the projection (the residual's
    sign does not matter for the covariance)."""
    n_int = 9 if not fix_k3 else 8
    n_views = len(views.obj)
    p = 2 * n_int + 6 + 6 * n_views
    rows = 2 * sum(2 * len(o) for o in views.obj)
    J = np.zeros((rows, p))
    om, T = fit["om"], fit["T"]
    r0 = 0
    for i, (obj, (rv, tv)) in enumerate(zip(views.obj, fit["poses"], strict=True)):
        m = 2 * len(obj)
        pose_cols = slice(2 * n_int + 6 + 6 * i, 2 * n_int + 12 + 6 * i)
        # left image: direct
        Jl = _projection_jacobian(obj, rv, tv, fit["cams"][0])
        J[r0:r0 + m, :n_int] = Jl[:, 6:6 + n_int]
        J[r0:r0 + m, pose_cols] = Jl[:, :6]
        r0 += m
        # right image: board pose composed with the rig, chain rule through composeRT
        (rv3, tv3, dr3dr1, dr3dt1, dr3dr2, dr3dt2,
         dt3dr1, dt3dt1, dt3dr2, dt3dt2) = cv2.composeRT(rv, tv, om, T)
        Jr = _projection_jacobian(obj, rv3.ravel(), tv3.ravel(), fit["cams"][1])
        d_r3, d_t3 = Jr[:, :3], Jr[:, 3:6]
        J[r0:r0 + m, n_int:2 * n_int] = Jr[:, 6:6 + n_int]
        J[r0:r0 + m, 2 * n_int:2 * n_int + 3] = d_r3 @ dr3dr2 + d_t3 @ dt3dr2
        J[r0:r0 + m, 2 * n_int + 3:2 * n_int + 6] = d_r3 @ dr3dt2 + d_t3 @ dt3dt2
        J[r0:r0 + m, pose_cols] = np.hstack([d_r3 @ dr3dr1 + d_t3 @ dt3dr1,
                                             d_r3 @ dr3dt1 + d_t3 @ dt3dt1])
        r0 += m
    return J


def _projection_jacobian(obj: FloatArray, rvec: FloatArray, tvec: FloatArray,
                         cam: tuple[FloatArray, FloatArray]) -> FloatArray:
    """(2N, 15) columns rvec(3), tvec(3), fx, fy, cx, cy, k1, k2, p1, p2, k3."""
    _, jac = cv2.projectPoints(obj, rvec, tvec, cam[0], cam[1])
    return np.asarray(jac, dtype=np.float64)[:, :15]


def _parameter_names(n_views: int, fix_k3: bool) -> list[str]:
    intr = INTRINSIC_NAMES[:8] if fix_k3 else INTRINSIC_NAMES
    names = [f"left.{k}" for k in intr] + [f"right.{k}" for k in intr]
    names += [f"om[{k}]" for k in range(3)] + [f"T[{k}]" for k in range(3)]
    for i in range(n_views):
        names += [f"view{i}.rvec[{k}]" for k in range(3)]
        names += [f"view{i}.tvec[{k}]" for k in range(3)]
    return names


def _covariance(J: FloatArray, ssr: float) -> FloatArray:
    m, p = J.shape
    if m <= p:
        raise CalibrationError(f"{m} residuals for {p} parameters: too few points")
    scale = np.linalg.norm(J, axis=0)
    if np.any(scale == 0):
        raise CalibrationError("a parameter does not affect any residual (degenerate views)")
    Jn = J / scale
    try:
        inv = np.linalg.inv(Jn.T @ Jn)
    except np.linalg.LinAlgError:
        raise CalibrationError("the views do not determine the parameters (singular normal "
                               "matrix); add views at varied tilts") from None
    return ssr / (m - p) * inv / np.outer(scale, scale)


def _result(views: _Views, sizes: tuple[tuple[int, ...], tuple[int, ...]], fit: dict[str, Any],
            fix_k3: bool, rejected: list[dict[str, str]],
            baseline_hint_mm: float | None) -> RigResult:
    n_int = 8 if fix_k3 else 9
    res_l, res_r = fit["res_l"], fit["res_r"]
    all_res = np.concatenate(res_l + res_r)
    ssr = float(np.sum(all_res**2))
    cov = _covariance(_jacobian(views, fit, fix_k3), ssr)
    std = np.sqrt(np.diag(cov))
    cams, stds = [], []
    for k, ((K, dist), size) in enumerate(zip(fit["cams"], sizes, strict=True)):
        cams.append({"fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]),
                     "cy": float(K[1, 2]), "skew": 0.0, "dist": [float(v) for v in dist],
                     "width": int(size[0]), "height": int(size[1])})
        s = std[k * n_int:(k + 1) * n_int]
        stds.append({"fx": float(s[0]), "fy": float(s[1]), "cx": float(s[2]), "cy": float(s[3]),
                     "skew": 0.0, "dist": [float(v) for v in s[4:]] + ([0.0] if fix_k3 else [])})
    poses = []
    for rv, tv in fit["poses"]:
        poses.append(make_transform(matrix_from_rotvec(rv), tv))
    per_pair = [{"left": a, "right": b, "rms_px": float(rms), "points": len(o)}
                for (a, b), rms, o in zip(views.names, fit["per_pair_rms"], views.obj,
                                          strict=True)]
    result = RigResult(
        left=cams[0], right=cams[1], left_std=stds[0], right_std=stds[1],
        rotvec_rad=fit["om"], translation_mm=fit["T"],
        rotvec_std=std[2 * n_int:2 * n_int + 3], translation_std=std[2 * n_int + 3:2 * n_int + 6],
        rms_px=float(np.sqrt(2 * np.mean(all_res**2))), names=list(views.names),
        per_pair=per_pair, residuals_left_px=res_l, residuals_right_px=res_r,
        px_left=list(views.left), px_right=list(views.right), T_left_board=poses,
        epipolar_residuals_px=[], epipolar_px={}, covariance=cov,
        parameter_names=_parameter_names(len(views.obj), fix_k3), rejected=rejected)
    try:
        rig = result.rig
        result.epipolar_residuals_px = [rig.epipolar_residuals_px(a, b)
                                        for a, b in zip(views.left, views.right, strict=True)]
    except GeometryError as err:
        raise CalibrationError(f"calibrated rig is unusable: {err}") from None
    e = np.concatenate(result.epipolar_residuals_px).ravel()
    result.epipolar_px = {"median": float(np.median(e)), "p95": float(np.percentile(e, 95)),
                          "max": float(np.max(e))}
    result.warnings = _warnings(result, baseline_hint_mm)
    return result


def _warnings(r: RigResult, baseline_hint_mm: float | None) -> list[str]:
    out = []
    n = len(r.names)
    if n < FEW_PAIRS:
        out.append(f"only {n} pairs used; {FEW_PAIRS}-20 pairs at varied tilts and distances "
                   "determine the rig better")
    e = r.epipolar_px
    if e["median"] > EPIPOLAR_WARN_MEDIAN_PX or e["p95"] > EPIPOLAR_WARN_P95_PX:
        out.append(f"large epipolar residuals on the calibration images (median "
                   f"{e['median']:.2f} px, 95 % {e['p95']:.2f} px): are the images true pairs, "
                   "taken at the same time, with a rig that did not move?")
    baseline = float(np.linalg.norm(r.translation_mm))
    if baseline_hint_mm is not None and abs(baseline - baseline_hint_mm) > (
            BASELINE_TOLERANCE * baseline_hint_mm):
        out.append(f"baseline {baseline:.2f} mm differs from the expected {baseline_hint_mm:g} "
                   f"mm by more than {BASELINE_TOLERANCE:.0%}: wrong board pitch or rig?")
    # the baseline length sets the depth scale: its sigma along T, from the covariance block
    i_t = r.parameter_names.index("T[0]")
    direction = r.translation_mm / baseline
    sigma_b = float(np.sqrt(direction @ r.covariance[i_t:i_t + 3, i_t:i_t + 3] @ direction))
    if sigma_b > BASELINE_SIGMA_WARN * baseline:
        out.append(f"the baseline is uncertain: {baseline:.2f} +- {sigma_b:.2f} mm (1 sigma, "
                   f"> {BASELINE_SIGMA_WARN:.1%}; depth scale errors of that size); add pairs "
                   "at varied tilts and distances")
    return out
