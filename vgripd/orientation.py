"""Absolute orientation (3D-3D, Horn 1987) and exterior orientation (2D-3D, PnP).

Both answer "where is frame *from* (the object, or the camera at its taught position) in frame
*to*", given point correspondences:

* :func:`horn` and :func:`horn_robust` take the same points measured in two frames (e.g. model
  points from CAD and the same points triangulated by the stereo rig) and return ``T_to_from``
  with ``p_to = T_to_from @ p_from``. The closed-form unit-quaternion solution of Horn (1987)
  is exact for any n >= 3 non-collinear points (the chapter, section "Relative orientation").
* :func:`pnp` takes model points in the object frame and their pixels in one calibrated image
  and returns ``T_cam_obj`` (the chapter, section "Exterior orientation").

Units: millimetres, radians, pixels (OpenCV pixel origin: centre of the top-left pixel is 0, 0).
Every degenerate input raises :class:`~vgripd.errors.DegenerateInputError` naming the point
index or the condition; nothing returns a pose it cannot vouch for.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vgripd.camera_model import CameraModel
from vgripd.errors import ConvergenceError, DegenerateInputError, GeometryError
from vgripd.transforms import make_transform, matrix_from_quat, matrix_from_rotvec
from vgripd.types import FloatArray

__all__ = [
    "HornResult",
    "PnPResult",
    "RobustHornResult",
    "horn",
    "horn_robust",
    "pnp",
]

#: Smallest ratio of the second to the first singular value of a centred point set (the
#: "width" of the set relative to its length). Below it the rotation about the set's long axis
#: is not determined by the data: a 100 mm long set would need to be at least 0.1 mm wide.
MIN_SPREAD_RATIO = 1e-3

#: Point sets whose largest singular value (root of summed squared distances to the centroid)
#: is below this many millimetres are treated as a single point.
MIN_SPREAD_MM = 1e-9


@dataclass(frozen=True, eq=False)
class HornResult:
    """Least-squares rigid transform between two corresponding point sets.

    Attributes
    ----------
    T_to_from : (4, 4) float64
        ``p_to = T_to_from @ p_from`` (mm).
    rms_mm : float
        Root mean square of ``residuals_mm`` (unweighted, over the points used).
    residuals_mm : (n,) float64
        ``|| R p_from_i + t - p_to_i ||`` per input point (mm), for every input point, also
        for points a robust fit dropped.
    """

    T_to_from: FloatArray
    rms_mm: float
    residuals_mm: FloatArray


@dataclass(frozen=True, eq=False)
class RobustHornResult(HornResult):
    """:class:`HornResult` of the inliers plus the indices of the dropped correspondences.

    ``rms_mm`` is over the inliers only; ``residuals_mm`` covers every input point, so a dropped
    point's residual shows how far off it was.
    """

    dropped: tuple[int, ...] = ()

    @property
    def inliers(self) -> FloatArray:
        """Boolean mask (n,) of the correspondences used for ``T_to_from``."""
        mask = np.ones(self.residuals_mm.shape[0], dtype=bool)
        mask[list(self.dropped)] = False
        return mask


def _as_points(points: object, name: str, dim: int) -> FloatArray:
    """Return ``points`` as a float64 (n, dim) array; shapes and NaN are checked by index."""
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise DegenerateInputError(f"{name}: expected shape (n, {dim}), got {arr.shape}")
    finite = np.isfinite(arr).all(axis=1)
    if not finite.all():
        bad = int(np.flatnonzero(~finite)[0])
        raise DegenerateInputError(f"{name}: point {bad} is not finite: {arr[bad].tolist()}")
    return arr


def _check_spread(centred: FloatArray, name: str) -> None:
    """Refuse coincident or collinear point sets (from singular values of the centred set)."""
    s = np.linalg.svd(centred, compute_uv=False)
    if s[0] < MIN_SPREAD_MM:
        raise DegenerateInputError(f"{name}: all points coincide")
    if s[1] < MIN_SPREAD_RATIO * s[0]:
        raise DegenerateInputError(
            f"{name}: points are (nearly) collinear: singular values {s.tolist()}, the second "
            f"must be at least {MIN_SPREAD_RATIO:g} of the first"
        )


def _horn_matrix(M: FloatArray) -> FloatArray:
    """Horn's symmetric 4x4 matrix N from cross-covariances ``M[.., i, j] = sum a_i b_j``.

    The unit quaternion (w, x, y, z) rotating the *a* points onto the *b* points is N's
    eigenvector of the largest eigenvalue. Works on stacks (..., 3, 3) -> (..., 4, 4).
    """
    sxx, sxy, sxz = M[..., 0, 0], M[..., 0, 1], M[..., 0, 2]
    syx, syy, syz = M[..., 1, 0], M[..., 1, 1], M[..., 1, 2]
    szx, szy, szz = M[..., 2, 0], M[..., 2, 1], M[..., 2, 2]
    rows = [
        [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
        [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
        [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
        [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
    ]
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def _normalised_weights(weights: object, n: int) -> FloatArray:
    w = np.asarray(weights, dtype=np.float64)
    if w.shape != (n,):
        raise DegenerateInputError(f"weights: expected shape ({n},), got {w.shape}")
    bad = np.flatnonzero(~np.isfinite(w) | (w < 0))
    if bad.size:
        raise DegenerateInputError(f"weights: weight {int(bad[0])} is negative or not finite")
    if np.count_nonzero(w) < 3:
        raise DegenerateInputError("weights: fewer than 3 points have a positive weight")
    return w / w.sum()


def horn(points_from: object, points_to: object, weights: object = None) -> HornResult:
    """Closed-form least-squares rigid transform (Horn 1987, unit quaternions).

    Minimises ``sum_i w_i || R a_i + t - b_i ||^2`` over rotations R and translations t, with
    ``a = points_from`` and ``b = points_to``.

    Parameters
    ----------
    points_from, points_to : (n, 3) array_like, mm
        Corresponding points, n >= 3, neither set coincident nor collinear.
    weights : (n,) array_like, optional
        Non-negative relative weights (e.g. inverse variances); at least 3 must be positive.

    Raises
    ------
    DegenerateInputError
        Mismatched shapes, fewer than 3 points, NaN/inf (naming the point index), coincident
        or collinear points in either set, or a rotation the data do not determine uniquely.
    """
    a = _as_points(points_from, "points_from", 3)
    b = _as_points(points_to, "points_to", 3)
    if a.shape != b.shape:
        raise DegenerateInputError(
            f"points_from has {a.shape[0]} points but points_to has {b.shape[0]}"
        )
    n = a.shape[0]
    if n < 3:
        raise DegenerateInputError(f"need at least 3 point pairs, got {n}")
    w = np.full(n, 1.0 / n) if weights is None else _normalised_weights(weights, n)
    ca = w @ a
    cb = w @ b
    a0 = a - ca
    b0 = b - cb
    sw = np.sqrt(w)[:, None]
    _check_spread(sw * a0, "points_from")
    _check_spread(sw * b0, "points_to")
    evals, evecs = np.linalg.eigh(_horn_matrix((w[:, None] * a0).T @ b0))
    # eigh sorts ascending; a repeated top eigenvalue means two rotations fit equally well.
    if evals[3] - evals[2] <= 1e-12 * max(abs(evals[3]), 1e-300):
        raise DegenerateInputError("the point sets do not determine a unique rotation")
    R = matrix_from_quat(evecs[:, 3])
    t = cb - R @ ca
    residuals = np.linalg.norm(a @ R.T + t - b, axis=1)
    return HornResult(
        T_to_from=make_transform(R, t),
        rms_mm=float(np.sqrt(np.mean(residuals**2))),
        residuals_mm=residuals,
    )


def _leave_one_out_sse(a: FloatArray, b: FloatArray, w: FloatArray) -> FloatArray:
    """Weighted mean squared residual of Horn fits that each leave out one point, (n,).

    Uses Horn's identity: the minimum of ``sum w |R a + t - b|^2`` equals
    ``sum w (|a - ca|^2 + |b - cb|^2) - 2 lambda_max``, so the n fits need only the largest
    eigenvalues of n 4x4 matrices, computed as one stack.
    """
    a = a - a.mean(axis=0)
    b = b - b.mean(axis=0)
    wa = w[:, None] * a
    wb = w[:, None] * b
    W = w.sum() - w  # total weight of each leave-one-out subset
    sum_a = wa.sum(axis=0) - wa  # (n, 3)
    sum_b = wb.sum(axis=0) - wb
    ca = sum_a / W[:, None]
    cb = sum_b / W[:, None]
    outer = wa[:, :, None] * b[:, None, :]  # (n, 3, 3) per-point contribution
    M = outer.sum(axis=0) - outer - W[:, None, None] * ca[:, :, None] * cb[:, None, :]
    sq_a = (wa * a).sum(axis=1)
    sq_b = (wb * b).sum(axis=1)
    spread = (sq_a.sum() - sq_a - W * (ca**2).sum(axis=1)) + (
        sq_b.sum() - sq_b - W * (cb**2).sum(axis=1)
    )
    lam = np.linalg.eigvalsh(_horn_matrix(M))[:, 3]
    return np.maximum(spread - 2.0 * lam, 0.0) / W


def horn_robust(
    points_from: object,
    points_to: object,
    weights: object = None,
    *,
    threshold_mm: float = 1.0,
) -> RobustHornResult:
    """:func:`horn` that finds and drops wrong correspondences.

    While some used point's residual exceeds ``threshold_mm``, drop the point whose removal
    leaves the best fit of the others (leave-one-out over all remaining points). This is more
    reliable than dropping the largest residual: with few points one wrong pair pulls the fit
    so that a correct point can show the largest residual.

    Parameters
    ----------
    threshold_mm : float
        Largest residual (mm) an inlier may have; set it to a few times the expected 3D
        measurement noise.

    Raises
    ------
    DegenerateInputError
        As :func:`horn` for the input as a whole.
    GeometryError
        No subset of at least 3 points fits within ``threshold_mm``.
    """
    if not threshold_mm > 0:
        raise DegenerateInputError(f"threshold_mm must be positive, got {threshold_mm}")
    a = _as_points(points_from, "points_from", 3)
    b = _as_points(points_to, "points_to", 3)
    fit = horn(a, b, weights)  # validates shapes, count, weights and spread once
    n = a.shape[0]
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)
    keep = np.flatnonzero(w > 0)
    dropped: list[int] = []
    while fit.residuals_mm[keep].max() > threshold_mm:
        if keep.size <= 3:
            raise GeometryError(
                f"no 3 or more correspondences agree within {threshold_mm} mm; dropped "
                f"{dropped}, residuals of the rest {fit.residuals_mm[keep].round(3).tolist()} mm"
            )
        worst = int(np.argmin(_leave_one_out_sse(a[keep], b[keep], w[keep])))
        dropped.append(int(keep[worst]))
        keep = np.delete(keep, worst)
        sub = horn(a[keep], b[keep], w[keep])
        T = sub.T_to_from
        fit = HornResult(T, sub.rms_mm, np.linalg.norm(a @ T[:3, :3].T + T[:3, 3] - b, axis=1))
    return RobustHornResult(
        T_to_from=fit.T_to_from,
        rms_mm=float(np.sqrt(np.mean(fit.residuals_mm[keep] ** 2))),
        residuals_mm=fit.residuals_mm,
        dropped=tuple(sorted(dropped)),
    )


@dataclass(frozen=True, eq=False)
class PnPResult:
    """Pose of an object in one calibrated camera, refined on the reprojection error.

    Attributes
    ----------
    T_cam_obj : (4, 4) float64
        ``p_cam = T_cam_obj @ p_obj`` (mm).
    rms_px : float
        Root mean square reprojection error (pixels, distorted image).
    errors_px : (n,) float64
        Reprojection error per point (pixels).
    ambiguous : bool
        True when a second pose explains the pixels nearly as well (planar targets seen small
        or nearly fronto-parallel); the pose must then not be trusted.
    T_cam_obj_alt : (4, 4) float64 or None
        The other local minimum for planar targets (None for non-planar targets, or when
        refining it converged onto the first pose).
    rms_px_alt : float or None
        Its reprojection RMS (pixels).
    """

    T_cam_obj: FloatArray
    rms_px: float
    errors_px: FloatArray
    ambiguous: bool
    T_cam_obj_alt: FloatArray | None
    rms_px_alt: float | None


#: Smallest ratio of the third to the first singular value of the centred model points for
#: which the target counts as non-planar; flatter targets are solved as planar (IPPE).
PLANAR_RATIO = 1e-6


def _project_errors(
    camera: CameraModel, R: FloatArray, t: FloatArray, obj: FloatArray, px: FloatArray
) -> FloatArray:
    """Reprojection residuals (n, 2) in pixels."""
    return camera.project(obj @ R.T + t) - px


def _refine_lm(
    camera: CameraModel,
    R: FloatArray,
    t: FloatArray,
    obj: FloatArray,
    px: FloatArray,
    max_iter: int = 50,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Levenberg-Marquardt on the pixel reprojection error with our own camera model.

    The pose is updated by a small motion of the camera-frame points, ``X' = exp(w) X + v``,
    so ``dX/dw = -[X]x`` and ``dX/dv = I``; the camera's own Jacobian ``d pixel / d X`` is taken
    by central differences in one batched ``project`` call, so any distortion model the
    camera implements is honoured (OpenCV's LM would ignore skew).

    Returns
    -------
    R (3, 3), t (3,), residuals (n, 2) px.
    """
    n = obj.shape[0]
    eye3 = np.eye(3)
    res = _project_errors(camera, R, t, obj, px)
    cost = float((res**2).sum())
    mu = 1e-3
    for _ in range(max_iter):
        X = obj @ R.T + t
        h = 1e-6 * np.abs(X[:, 2])[:, None, None] * eye3  # (n, 3, 3) per-point steps
        shifted = np.concatenate([(X[:, None, :] + h), (X[:, None, :] - h)], axis=1)
        proj = camera.project(shifted.reshape(-1, 3)).reshape(n, 6, 2)
        J_x = (proj[:, :3, :] - proj[:, 3:, :]).transpose(0, 2, 1) / (2.0 * h[:, 0, 0])[
            :, None, None
        ]  # (n, 2, 3): d pixel / d X
        skew = np.zeros((n, 3, 3))
        skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -X[:, 2], X[:, 1], -X[:, 0]
        skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = X[:, 2], -X[:, 1], X[:, 0]
        J = np.concatenate([J_x @ -skew, J_x], axis=2).reshape(2 * n, 6)
        g = J.T @ res.reshape(-1)
        H = J.T @ J
        while True:
            step = np.linalg.solve(H + mu * np.diag(np.diag(H)), -g)
            dR = matrix_from_rotvec(step[:3])
            R_new, t_new = dR @ R, dR @ t + step[3:]
            res_new = _project_errors(camera, R_new, t_new, obj, px)
            cost_new = float((res_new**2).sum())
            if cost_new <= cost:
                break
            mu *= 10.0
            if mu > 1e12:  # no descent direction left: we are at the minimum
                return R, t, res
        converged = cost - cost_new <= 1e-14 * cost + 1e-24 or np.abs(step).max() < 1e-13
        R, t, res, cost = R_new, t_new, res_new, cost_new
        mu = max(mu / 10.0, 1e-9)
        if converged:
            return R, t, res
    raise ConvergenceError(
        f"PnP refinement did not converge in {max_iter} iterations "
        f"(reprojection RMS {np.sqrt(cost / n):.4g} px)"
    )


def _pose_from_cv(rvec: object, tvec: object) -> tuple[FloatArray, FloatArray]:
    return matrix_from_rotvec(np.asarray(rvec, dtype=np.float64).reshape(3)), np.asarray(
        tvec, dtype=np.float64
    ).reshape(3)


def pnp(
    model_points: object,
    pixels: object,
    camera: CameraModel,
    *,
    ambiguity_ratio: float = 2.0,
    noise_floor_px: float = 0.1,
) -> PnPResult:
    """Pose of an object from n >= 4 model points and their pixels in one image.

    An initial pose comes from OpenCV on the undistorted normalised coordinates (IPPE for
    planar targets, which yields both poses of the two-fold planar ambiguity; SQPnP otherwise)
    and is refined by Levenberg-Marquardt on the reprojection error in pixels
    (:func:`_refine_lm`). Three points are refused: P3P has up to four exact solutions, so
    three points cannot tell the right one.

    A planar target is flagged ``ambiguous`` when the second IPPE pose, refined too, fits
    almost as well: ``rms_alt < ambiguity_ratio * max(rms_best, noise_floor_px)``.
    ``noise_floor_px`` (about the corner-detection noise) keeps noise-free data from calling
    any second pose distinguishable only because the best fit is exact.

    Parameters
    ----------
    model_points : (n, 3) array_like
        Points in the object frame (mm).
    pixels : (n, 2) array_like
        Their measured (distorted) pixel coordinates.
    camera : CameraModel
        Intrinsics and distortion of the image.

    Raises
    ------
    DegenerateInputError
        Fewer than 4 points, mismatched counts, NaN (naming the index), collinear model
        points, collinear image points (plane seen edge-on), or a model point behind the camera.
    ConvergenceError
        The refinement did not converge.
    """
    obj = _as_points(model_points, "model_points", 3)
    px = _as_points(pixels, "pixels", 2)
    n = obj.shape[0]
    if px.shape[0] != n:
        raise DegenerateInputError(f"model_points has {n} points but pixels has {px.shape[0]}")
    if n < 4:
        raise DegenerateInputError(f"PnP needs at least 4 points, got {n}")
    centred = obj - obj.mean(axis=0)
    s = np.linalg.svd(centred, compute_uv=False)
    _check_spread(centred, "model_points")
    norm = camera.undistort(px)
    _check_spread(norm - norm.mean(axis=0), "pixels (undistorted)")
    obj_cv = np.ascontiguousarray(obj).reshape(-1, 1, 3)
    norm_cv = np.ascontiguousarray(norm).reshape(-1, 1, 2)
    planar = s[2] < PLANAR_RATIO * s[0]
    if planar:
        _, rvecs, tvecs, _ = cv2.solvePnPGeneric(
            obj_cv, norm_cv, np.eye(3), None, flags=cv2.SOLVEPNP_IPPE
        )
        starts = [_pose_from_cv(r, t) for r, t in zip(rvecs, tvecs, strict=True)]
    else:
        ok, rvec, tvec = cv2.solvePnP(obj_cv, norm_cv, np.eye(3), None, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            raise ConvergenceError("SQPnP found no initial pose")
        starts = [_pose_from_cv(rvec, tvec)]
    fits = []
    for R0, t0 in starts:
        z = (obj @ R0.T + t0)[:, 2]
        if (z <= 0).any():
            continue  # not a physical solution; the other one may be
        R, t, res = _refine_lm(camera, R0, t0, obj, px)
        err = np.linalg.norm(res, axis=1)
        fits.append((float(np.sqrt(np.mean(err**2))), R, t, err))
    if not fits:
        raise DegenerateInputError("no pose puts all model points in front of the camera")
    fits.sort(key=lambda f: f[0])
    rms, R, t, err = fits[0]
    behind = np.flatnonzero((obj @ R.T + t)[:, 2] <= 0)
    if behind.size:
        raise DegenerateInputError(f"model point {int(behind[0])} lies behind the camera")
    alt = None
    if len(fits) > 1:
        rms_alt, R_alt, t_alt, _ = fits[1]
        # Refining the second start can slide into the first minimum: then there is only one.
        if np.linalg.norm(R_alt - R) > 1e-6 or np.linalg.norm(t_alt - t) > 1e-6 * np.linalg.norm(t):
            alt = (rms_alt, make_transform(R_alt, t_alt))
    ambiguous = alt is not None and alt[0] < ambiguity_ratio * max(rms, noise_floor_px)
    return PnPResult(
        T_cam_obj=make_transform(R, t),
        rms_px=rms,
        errors_px=err,
        ambiguous=bool(ambiguous),
        T_cam_obj_alt=None if alt is None else alt[1],
        rms_px_alt=None if alt is None else alt[0],
    )
