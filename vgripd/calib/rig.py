"""Stereo rig calibration: both cameras and the left -> right transform (Bouguet's "global
stereo optimisation").

Model: each camera is a pinhole with fx, fy, cx, cy, skew 0 and Brown distortion
``[k1, k2, p1, p2, k3]`` (OpenCV order = Bouguet ``kc``). Whether p1 p2 and k3 are estimated
or held at 0 is chosen from the data as for one camera (``calib.intrinsics``: BIC over the four
candidates, Bouguet's k1 k2 p1 p2 kept unless beaten by more than 2), here on the joint stereo
fit, one model for both cameras (OpenCV's stereo flags apply to both); ``fix_k3`` /
``fix_tangential`` override it. A held term is 0, also when ``initial`` intrinsics had it.
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

Pair consistency, before any joint fit: each camera alone gives the board pose of every view
(``cv2.calibrateCamera`` on its own images, or ``solvePnP`` with ``initial``), so every pair
gives its own left -> right pose. A rigid rig makes them agree (a few tenths of a degree, a few
mm); a pair off the others' consensus by more than ``PAIR_ROTATION_TOL_DEG`` or by more than
``PAIR_TRANSLATION_TOL`` x the baseline (and ``PAIR_DEPTH_TOL`` x the board distance) is not a
pair of this rig: the images were not taken at the same time, or are not partners (a right
list shifted by one because a file is missing, globs that sort differently). Any such pair is
refused with a CalibrationError naming it; when pairing left i with right i+s (s = +-1, +-2)
makes the poses agree, the message says so. Without this check such input ends in a joint fit
that diverges or distorts beyond its fold.

Outliers: a pair whose RMS (both images) is above ``outlier_factor`` x the median and above
``outlier_floor_px`` is dropped and the rig refitted, worst first, one pair at a time (as
``calib.intrinsics`` does for single images), with every candidate distortion term free.

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

from vgripd.calib.intrinsics import (
    PLAUSIBLE_BIC,
    DistortionModel,
    ModelChoice,
    bic,
    candidate_models,
    choose_model,
    k3_note,
    widen,
    with_model_bias,
)
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
PAIR_ROTATION_TOL_DEG = 5.0  # a pair's left->right rotation this far from the consensus: no pair
PAIR_TRANSLATION_TOL = 0.3  # ... or its translation this far, relative to the baseline
PAIR_DEPTH_TOL = 0.05  # ... and relative to the board distance (single-view depth is loose)

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
    ``model``: the distortion model (both cameras) and the candidates it was chosen from; their
    ``dist``/``dist_std`` are the left camera's, ``right_dist``/``right_dist_std`` the right's.
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
    model: ModelChoice
    rejected: list[dict[str, str]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    #: The chosen model's own sigmas (``left``, ``right``, ``rotvec_rad``, ``translation_mm``;
    #: what OpenCV and Bouguet's toolbox report); the ``*_std`` fields add the model's possible
    #: bias when the choice left terms out (``intrinsics.with_model_bias``).
    std_model: dict[str, Any] = field(default_factory=dict)

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
                  names: Sequence[tuple[str, str]] | None = None,
                  fix_k3: bool | None = None, fix_tangential: bool | None = None,
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
    fix_k3, fix_tangential : True holds k3 / p1 p2 at 0 in both cameras, False estimates them,
        None (default) chooses from the data (module docstring).
    baseline_hint_mm : expected |T|; a result off by more than 5 % is warned about.
    outlier_factor, outlier_floor_px : the pair outlier rule (module docstring).

    Raises CalibrationError for inconsistent input (naming the view), pairs whose left and
    right board poses disagree with the rig (naming them and the likely cause), fewer than 3
    usable pairs, or a fit that fails.
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
    models, reference = candidate_models(fix_k3, fix_tangential)
    richest = models[-1]
    if len(views.names) >= MIN_PAIRS:
        _check_pairs(views, sizes, initial, reference)
    rejected: list[dict[str, str]] = []
    while True:
        if len(views.names) < MIN_PAIRS:
            raise CalibrationError(
                f"need at least {MIN_PAIRS} pairs with the board in both images, have "
                f"{len(views.names)}" + (f" ({len(rejected)} rejected)" if rejected else ""))
        fit = _fit(views, sizes, initial, richest)
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
    fits = {mdl: fit if mdl == richest else _fit(views, sizes, initial, mdl) for mdl in models}
    m = 4 * sum(len(o) for o in views.obj)
    scores, rows = {}, {}
    for mdl, f in fits.items():
        ssr = float(sum(np.sum(r**2) for r in f["res_l"] + f["res_r"]))
        scores[mdl] = bic(ssr, m, 2 * (4 + len(mdl.free)) + 6 + 6 * len(views.obj))
        cams = [[float(v) for v in d] for _, d in f["cams"]]
        std_l, std_r, f["std_all"] = _stds(views, f, mdl)
        rows[mdl] = {"rms_px": float(np.sqrt(2 * ssr / m)), "dist": cams[0],
                     "dist_std": _dist_std(std_l, mdl), "right_dist": cams[1],
                     "right_dist_std": _dist_std(std_r, mdl)}
    choice = choose_model(scores, reference, rows)
    choice.notes = (k3_note(choice, "left camera: ", "dist")
                    + k3_note(choice, "right camera: ", "right_dist"))
    rich = None
    if choice.model != richest:
        rich = dict(fits[richest], model=richest)
    others = [dict(fits[mdl], model=mdl) for mdl in models
              if mdl not in (choice.model, richest)
              and scores[mdl] - scores[choice.model] < PLAUSIBLE_BIC]
    return _result(views, sizes, fits[choice.model], choice, rejected, baseline_hint_mm, rich,
                   others)


def _with_model_bias(own: tuple[list[dict[str, Any]], FloatArray, FloatArray],
                     cams: list[dict[str, Any]], fit: dict[str, Any], alt: dict[str, Any],
                     model: DistortionModel,
                     ) -> tuple[list[dict[str, Any]], FloatArray, FloatArray, dict[str, Any]]:
    """The chosen fit's sigmas (``own``: per camera std dicts, rotvec and translation std)
    widened by another candidate's (``alt``, a ``_fit`` with ``model`` and ``std_all``):
    per parameter ``sqrt(max(own, alt's)^2 + (chosen - alt)^2)``. Returns the widened
    (stds, rotvec_std, translation_std) and the shifts."""
    alt_model: DistortionModel = alt["model"]
    alt_std = alt["std_all"]
    n_alt = 4 + len(alt_model.free)
    bias: dict[str, Any] = {}
    stds = []
    for k, (K, dist) in enumerate(alt["cams"]):
        s_k = alt_std[k * n_alt:(k + 1) * n_alt]
        alt_fit = {"K": K, "dist": dist,
                   "std": np.concatenate([s_k[:4], _dist_std(s_k, alt_model)])}
        std_k, bias[("left", "right")[k]] = with_model_bias(own[0][k], cams[k], alt_fit, model)
        stds.append(std_k)
    d_om = np.asarray(fit["om"], dtype=float) - np.asarray(alt["om"], dtype=float)
    d_t = np.asarray(fit["T"], dtype=float) - np.asarray(alt["T"], dtype=float)
    rotvec_std = np.hypot(np.maximum(own[1], alt_std[2 * n_alt:2 * n_alt + 3]), d_om)
    translation_std = np.hypot(np.maximum(own[2], alt_std[2 * n_alt + 3:2 * n_alt + 6]), d_t)
    bias["rotvec_rad"] = d_om.tolist()
    bias["translation_mm"] = d_t.tolist()
    return stds, rotvec_std, translation_std, bias


def _dist_std(s: FloatArray, model: DistortionModel) -> list[float]:
    """One camera's std slice (fx fy cx cy, then the free dist terms) as a 5-entry dist std."""
    free = iter(s[4:])
    return [float(next(free)) if f else 0.0 for f in model.mask]


def _stds(views: _Views, fit: dict[str, Any], model: DistortionModel,
          ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """One-sigma std of each camera's free intrinsics (fx fy cx cy + free dist terms), and
    of every parameter (``parameter_names`` order)."""
    n_int = 4 + len(model.free)
    ssr = float(sum(np.sum(r**2) for r in fit["res_l"] + fit["res_r"]))
    std = np.sqrt(np.diag(_covariance(_jacobian(views, fit, model), ssr)))
    return std[:n_int], std[n_int:2 * n_int], std


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
                    model: DistortionModel) -> tuple[FloatArray, FloatArray, list[FloatArray]]:
    """One camera calibrated on its own images of the views (the stereo fit's start): K, dist
    and the board pose of every view (4x4, mm)."""
    px = views.left if side == "left" else views.right
    try:
        _rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
            [o.astype(np.float32) for o in views.obj], [p.astype(np.float32) for p in px],
            (int(size[0]), int(size[1])), np.eye(3), np.zeros(5), flags=model.flags,
            criteria=CRITERIA)
    except cv2.error as err:
        raise CalibrationError(f"initial calibration of the {side} camera failed: "
                               f"{err.msg}") from None
    poses = [_pose(r, t) for r, t in zip(rvecs, tvecs, strict=True)]
    return (np.asarray(K, dtype=np.float64), np.asarray(dist, dtype=np.float64).ravel()[:5],
            poses)


def _pose(rvec: ArrayLike, tvec: ArrayLike) -> FloatArray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3))[0]
    T[:3, 3] = np.asarray(tvec, dtype=np.float64).ravel()
    return T


def _board_poses(views: _Views, sizes: tuple[tuple[int, ...], tuple[int, ...]],
                 initial: tuple[CameraModel, CameraModel] | None,
                 model: DistortionModel) -> tuple[list[FloatArray], list[FloatArray]]:
    """Each camera's own board pose of every view: from its own calibration, or solvePnP with
    the given intrinsics."""
    out = []
    for k, side in enumerate(("left", "right")):
        if initial is None:
            out.append(_initial_camera(views, side, sizes[k], model)[2])
            continue
        K, dist = initial[k].to_opencv()
        px = views.left if side == "left" else views.right
        poses = []
        for obj, p, names in zip(views.obj, px, views.names, strict=True):
            ok, rvec, tvec = cv2.solvePnP(obj, p, K, dist)
            if not ok:
                raise CalibrationError(f"{names[k]}: no board pose with the initial {side} "
                                       "intrinsics")
            poses.append(_pose(rvec, tvec))
        out.append(poses)
    return out[0], out[1]


def _angle_deg(R: FloatArray) -> float:
    return float(np.degrees(np.linalg.norm(cv2.Rodrigues(R)[0])))


def _agreement(left: list[FloatArray], right: list[FloatArray], pairs: list[tuple[int, int]],
               reference: FloatArray | None = None,
               ) -> tuple[FloatArray, list[float], list[float], list[bool]]:
    """Left -> right poses of the view pairs (i, j) = (left view i, right view j): their
    consensus (rotation: the medoid; translation: the median), or ``reference``, and each
    pair's rotation (deg) and translation (mm) off it, and whether that is within tolerance."""
    rel = [right[j] @ np.linalg.inv(left[i]) for i, j in pairs]
    if reference is None:
        spread = [sum(_angle_deg(a[:3, :3] @ b[:3, :3].T) for b in rel) for a in rel]
        reference = rel[int(np.argmin(spread))].copy()
        reference[:3, 3] = np.median([r[:3, 3] for r in rel], axis=0)
    baseline = float(np.linalg.norm(reference[:3, 3]))
    angles = [_angle_deg(r[:3, :3] @ reference[:3, :3].T) for r in rel]
    shifts = [float(np.linalg.norm(r[:3, 3] - reference[:3, 3])) for r in rel]
    ok = [a <= PAIR_ROTATION_TOL_DEG
          and d <= max(PAIR_TRANSLATION_TOL * baseline, PAIR_DEPTH_TOL * float(
              np.linalg.norm(left[i][:3, 3])))
          for a, d, (i, _) in zip(angles, shifts, pairs, strict=True)]
    return reference, angles, shifts, ok


def _check_pairs(views: _Views, sizes: tuple[tuple[int, ...], tuple[int, ...]],
                 initial: tuple[CameraModel, CameraModel] | None,
                 model: DistortionModel) -> None:
    """Refuse pairs whose left -> right pose disagrees with the others' (module docstring)."""
    left, right = _board_poses(views, sizes, initial, model)
    n = len(left)
    consensus, angles, shifts, ok = _agreement(left, right, [(i, i) for i in range(n)])
    reference: FloatArray | None = consensus
    bad = [i for i in range(n) if not ok[i]]
    if not bad:
        return
    majority = len(bad) < n / 2
    if not majority:  # no consensus: look for a shift under which one appears
        reference = None
        for s in (1, -1, 2, -2):
            pairs = [(i, i + s) for i in range(n) if 0 <= i + s < n]
            if len(pairs) >= MIN_PAIRS:
                ref, _a, _d, fine = _agreement(left, right, pairs)
                if sum(fine) >= 0.8 * len(pairs):
                    reference = ref
                    break
    hint = ""
    if reference is not None:  # which partner would fit the rig for the bad pairs
        moves = {}
        for i in bad:
            for s in (1, -1, 2, -2):
                if 0 <= i + s < n and _agreement(left, right, [(i, i + s)], reference)[3][0]:
                    moves[i] = s
                    break
        if moves and len(set(moves.values())) == 1:
            s = next(iter(moves.values()))
            first = min(moves)
            hint = (f" {len(moves)} of them fit the rig when left i goes with right i{s:+d} "
                    f"(from {views.names[first][0]} with {views.names[first + s][1]}): the "
                    f"right images are shifted by {abs(s)} (a missing or extra file, or names "
                    "that sort differently)")
    worst = sorted(bad, key=lambda i: -angles[i])[:3]
    named = ", ".join(f"{views.names[i][0]} / {views.names[i][1]} ({angles[i]:.1f} deg, "
                      f"{shifts[i]:.0f} mm)" for i in worst)
    more = f" and {len(bad) - len(worst)} more" if len(bad) > len(worst) else ""
    what = (f"{len(bad)} of {n} pairs disagree with the rig of the other {n - len(bad)}"
            if majority else
            f"{len(bad)} of {n} pairs disagree with each other: no rig fits them")
    cause = hint or (" Likely: pairs shifted (left i with right i+1), images not taken at "
                     "the same time, or left and right globs that sort in different orders.")
    raise CalibrationError(
        f"left and right images are not consistent pairs: {what} (each pair's left->right "
        f"pose, from each camera alone, is off by more than {PAIR_ROTATION_TOL_DEG:g} deg or "
        f"{PAIR_TRANSLATION_TOL:.0%} of the baseline; a rigid rig gives < 1 deg): {named}{more}."
        + (cause if not hint else hint + "."))


def _fit(views: _Views, sizes: tuple[tuple[int, ...], tuple[int, ...]],
         initial: tuple[CameraModel, CameraModel] | None,
         model: DistortionModel) -> dict[str, Any]:
    if initial is None:
        K1, d1, _ = _initial_camera(views, "left", sizes[0], model)
        K2, d2, _ = _initial_camera(views, "right", sizes[1], model)
    else:
        (K1, d1), (K2, d2) = initial[0].to_opencv(), initial[1].to_opencv()
        held = ~np.array(model.mask)
        d1, d2 = np.where(held, 0.0, d1), np.where(held, 0.0, d2)
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | model.flags
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


def _jacobian(views: _Views, fit: dict[str, Any], model: DistortionModel) -> FloatArray:
    """d(residual)/d(parameter), rows: per view the left then the right points (u, v
    interleaved); columns: see ``_parameter_names``. Sign: of the projection (the residual's
    sign does not matter for the covariance)."""
    # projectPoints' Jacobian columns: rvec(3), tvec(3), fx, fy, cx, cy, k1, k2, p1, p2, k3
    cols = [6, 7, 8, 9] + [10 + k for k, free in enumerate(model.mask) if free]
    n_int = len(cols)
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
        J[r0:r0 + m, :n_int] = Jl[:, cols]
        J[r0:r0 + m, pose_cols] = Jl[:, :6]
        r0 += m
        # right image: board pose composed with the rig, chain rule through composeRT
        (rv3, tv3, dr3dr1, dr3dt1, dr3dr2, dr3dt2,
         dt3dr1, dt3dt1, dt3dr2, dt3dt2) = cv2.composeRT(rv, tv, om, T)
        Jr = _projection_jacobian(obj, rv3.ravel(), tv3.ravel(), fit["cams"][1])
        d_r3, d_t3 = Jr[:, :3], Jr[:, 3:6]
        J[r0:r0 + m, n_int:2 * n_int] = Jr[:, cols]
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


def _parameter_names(n_views: int, model: DistortionModel) -> list[str]:
    intr = (*INTRINSIC_NAMES[:4], *model.free)
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
            choice: ModelChoice, rejected: list[dict[str, str]],
            baseline_hint_mm: float | None, rich: dict[str, Any] | None = None,
            others: Sequence[dict[str, Any]] = ()) -> RigResult:
    model = choice.model
    n_int = 4 + len(model.free)
    res_l, res_r = fit["res_l"], fit["res_r"]
    all_res = np.concatenate(res_l + res_r)
    ssr = float(np.sum(all_res**2))
    cov = _covariance(_jacobian(views, fit, model), ssr)
    std = np.sqrt(np.diag(cov))
    cams, stds = [], []
    for k, ((K, dist), size) in enumerate(zip(fit["cams"], sizes, strict=True)):
        cams.append({"fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]),
                     "cy": float(K[1, 2]), "skew": 0.0, "dist": [float(v) for v in dist],
                     "width": int(size[0]), "height": int(size[1])})
        s = std[k * n_int:(k + 1) * n_int]
        stds.append({"fx": float(s[0]), "fy": float(s[1]), "cx": float(s[2]), "cy": float(s[3]),
                     "skew": 0.0, "dist": _dist_std(s, model)})
    rotvec_std = std[2 * n_int:2 * n_int + 3]
    translation_std = std[2 * n_int + 3:2 * n_int + 6]
    std_model = {"left": stds[0], "right": stds[1], "rotvec_rad": rotvec_std,
                 "translation_mm": translation_std}
    own = ([dict(x) for x in stds], rotvec_std, translation_std)
    if rich is not None:
        # widened by what leaving terms out may have done (intrinsics.with_model_bias): each
        # sigma is the larger of the chosen and the richest model's, with the shift between
        # the two models' estimates in quadrature
        stds, rotvec_std, translation_std, bias = _with_model_bias(own, cams, fit, rich, model)
        for side in ("left", "right"):  # held terms: the richest value, no sigma here
            bias[side]["held"] = {n: v[:1] for n, v in bias[side].get("held", {}).items()}
        choice.model_bias = bias
    for other in others:  # the candidates the data did not rule out (intrinsics.widen)
        o_stds, o_rot, o_t, _ = _with_model_bias(own, cams, fit, other, model)
        stds = [widen(a, b) for a, b in zip(stds, o_stds, strict=True)]
        rotvec_std = np.maximum(rotvec_std, o_rot)
        translation_std = np.maximum(translation_std, o_t)
    poses = []
    for rv, tv in fit["poses"]:
        poses.append(make_transform(matrix_from_rotvec(rv), tv))
    per_pair = [{"left": a, "right": b, "rms_px": float(rms), "points": len(o)}
                for (a, b), rms, o in zip(views.names, fit["per_pair_rms"], views.obj,
                                          strict=True)]
    result = RigResult(
        left=cams[0], right=cams[1], left_std=stds[0], right_std=stds[1],
        rotvec_rad=fit["om"], translation_mm=fit["T"],
        rotvec_std=rotvec_std, translation_std=translation_std,
        rms_px=float(np.sqrt(2 * np.mean(all_res**2))), names=list(views.names),
        per_pair=per_pair, residuals_left_px=res_l, residuals_right_px=res_r,
        px_left=list(views.left), px_right=list(views.right), T_left_board=poses,
        epipolar_residuals_px=[], epipolar_px={}, covariance=cov,
        parameter_names=_parameter_names(len(views.obj), model), model=choice,
        rejected=rejected, std_model=std_model)
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
