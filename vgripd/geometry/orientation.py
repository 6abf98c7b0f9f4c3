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

import math
from dataclasses import dataclass, field
from itertools import combinations

import cv2
import numpy as np
import numpy.typing as npt

from vgripd.errors import ConvergenceError, DegenerateInputError, GeometryError
from vgripd.geometry.camera_model import CameraModel
from vgripd.geometry.transforms import (
    make_transform,
    matrices_from_quats,
    matrix_from_rotvec,
    skew,
)
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
        Root mean square of ``residuals_mm`` (unweighted; all points for :func:`horn`, the
        inliers for :func:`horn_robust`).
    residuals_mm : (n,) float64
        ``|| R p_from_i + t - p_to_i ||`` per input point (mm), for every input point, also
        for points a robust fit dropped.
    """

    T_to_from: FloatArray
    rms_mm: float
    residuals_mm: FloatArray


@dataclass(frozen=True, eq=False)
class RobustHornResult(HornResult):
    """:class:`HornResult` of the inliers, and which correspondences were dropped.

    ``rms_mm`` is over the inliers only; ``residuals_mm`` covers every input point, so a dropped
    point's residual shows how far off it was.

    Attributes
    ----------
    inliers : (n,) bool
        Correspondences used for ``T_to_from`` (points with weight 0 are never inliers).
    dropped : tuple of int
        Indices of positive-weight correspondences rejected as wrong, ascending.
    """

    inliers: npt.NDArray[np.bool_] = field(default_factory=lambda: np.ones(0, dtype=bool))
    dropped: tuple[int, ...] = ()


def _as_array(points: object, name: str, dim: int) -> FloatArray:
    """Return ``points`` as a float64 (n, dim) array (shape checked, values not)."""
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise DegenerateInputError(f"{name}: expected shape (n, {dim}), got {arr.shape}")
    return arr


def _check_finite(arr: FloatArray, name: str) -> None:
    """Raise naming the first point with a NaN or inf coordinate."""
    if not np.isfinite(arr).all():
        bad = int(np.argmin(np.isfinite(arr).all(axis=1)))
        raise DegenerateInputError(f"{name}: point {bad} is not finite: {arr[bad].tolist()}")


def _as_points(points: object, name: str, dim: int) -> FloatArray:
    """Return ``points`` as a float64 (n, dim) array; shape and NaN are checked by index."""
    arr = _as_array(points, name, dim)
    _check_finite(arr, name)
    return arr


def _check_spread(scatter: list[list[float]], name: str) -> None:
    """Refuse coincident or collinear point sets.

    Parameters
    ----------
    scatter : (d, d) nested list of float
        Scatter matrix ``sum w (p - c)(p - c)^T`` of a centred point set (d = 2 or 3); its
        eigenvalues l1 >= l2 >= l3 are the squared singular values of the set.
    name : str
        Names the set in the message.

    Notes
    -----
    The trace is ``l1 + l2 + l3`` and the second invariant (sum of the 2x2 principal minors)
    ``I2 = l1 l2 + l1 l3 + l2 l3`` lies between ``l1 l2`` and ``3 l1 l2``, so ``I2 / trace^2``
    tracks ``(s2 / s1)^2``. Plain float arithmetic on a 3x3 is far cheaper than an
    eigen-decomposition in the hot path; the exact singular values go into the message.
    A NaN in the points makes the trace NaN, which is also refused (callers then name the point).
    """
    m = scatter
    if len(m) == 3:
        (s00, s01, s02), (s10, s11, s12), (s20, s21, s22) = m
        tr = s00 + s11 + s22
        i2 = s00 * s11 - s01 * s10 + s00 * s22 - s02 * s20 + s11 * s22 - s12 * s21
    else:
        (s00, s01), (s10, s11) = m
        tr = s00 + s11
        i2 = s00 * s11 - s01 * s10
    if not tr >= MIN_SPREAD_MM**2:
        raise DegenerateInputError(f"{name}: all points coincide (or are not finite)")
    if i2 < MIN_SPREAD_RATIO**2 * tr * tr:
        sv = np.sqrt(np.maximum(np.linalg.eigvalsh(np.array(scatter)), 0.0))[::-1]
        raise DegenerateInputError(
            f"{name}: points are (nearly) collinear: singular values {sv.round(6).tolist()}, "
            f"the second must be at least about {MIN_SPREAD_RATIO:g} of the first"
        )


def _horn_n(M: FloatArray | list[list[float]]) -> FloatArray:
    """Horn's 4x4 matrix N for one 3x3 ``M`` (written out as in Horn 1987, section 4)."""
    (sxx, sxy, sxz), (syx, syy, syz), (szx, szy, szz) = M
    return np.array(
        [
            [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
            [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
            [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
            [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
        ]
    )


# N is linear in M: tabulate the map once (row k = N of the k-th unit matrix, flattened), so
# that a stack of N costs one matrix product.
_HORN_MAP_T = np.stack([_horn_n(E.reshape(3, 3)).ravel() for E in np.eye(9)])


def _horn_matrix(M: FloatArray) -> FloatArray:
    """Horn's symmetric 4x4 matrix N from cross-covariances ``M[.., i, j] = sum a_i b_j``.

    The unit quaternion (w, x, y, z) rotating the *a* points onto the *b* points is N's
    eigenvector of the largest eigenvalue. Works on stacks (..., 3, 3) -> (..., 4, 4).
    """
    return (M.reshape(-1, 9) @ _HORN_MAP_T).reshape(*M.shape[:-2], 4, 4)


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


def _rotation_quadratic(q: list[float]) -> list[list[float]]:
    """Rows of R(q) for one unit quaternion (w, x, y, z), written homogeneous (quadratic in q)."""
    w, x, y, z = q
    return [
        [w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z],
    ]


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
    a = _as_array(points_from, "points_from", 3)
    b = _as_array(points_to, "points_to", 3)
    if a.shape != b.shape:
        raise DegenerateInputError(
            f"points_from has {a.shape[0]} points but points_to has {b.shape[0]}"
        )
    n = a.shape[0]
    if n < 3:
        raise DegenerateInputError(f"need at least 3 point pairs, got {n}")
    ab = np.concatenate([a, b], axis=1)  # (n, 6): both sets in one pass
    # ufunc.reduce: what .sum() runs, without its Python wrapper (this is a hot path).
    if weights is None:
        c = np.add.reduce(ab) / n
        ab0 = ab - c
        S = (ab0.T @ ab0) / n
    else:
        w = _normalised_weights(weights, n)
        c = w @ ab
        ab0 = ab - c
        S = (w[:, None] * ab0).T @ ab0
    # One product gave both sets' scatter matrices (diagonal blocks) and Horn's M (off-diagonal
    # block); the small matrices are handled as Python floats, cheaper than numpy calls.
    m = S.tolist()
    if not math.isfinite(m[0][0] + m[1][1] + m[2][2] + m[3][3] + m[4][4] + m[5][5]):
        # NaN/inf anywhere ends up on the diagonal
        _check_finite(a, "points_from")
        _check_finite(b, "points_to")
    _check_spread([row[:3] for row in m[:3]], "points_from")
    _check_spread([row[3:] for row in m[3:]], "points_to")
    # OpenCV's Jacobi solver for symmetric matrices: as exact as LAPACK's, with a fraction of
    # np.linalg.eigh's call overhead on a 4x4; eigenvalues descending, eigenvectors as rows.
    _, evals, evecs = cv2.eigen(_horn_n([row[3:] for row in m[:3]]))
    (l0,), (l1,), _, _ = evals.tolist()
    # A repeated top eigenvalue means two rotations fit equally well.
    if l0 - l1 <= 1e-12 * max(abs(l0), 1e-300):
        raise DegenerateInputError("the point sets do not determine a unique rotation")
    # R is orthonormal by construction: no make_transform check needed.
    R = _rotation_quadratic(evecs[0].tolist())
    ca0, ca1, ca2, *cb = c.tolist()
    t = [cb_i - (r0 * ca0 + r1 * ca1 + r2 * ca2) for cb_i, (r0, r1, r2) in zip(cb, R, strict=True)]
    T = np.array([[*R[0], t[0]], [*R[1], t[1]], [*R[2], t[2]], [0.0, 0.0, 0.0, 1.0]])
    diff = ab0[:, :3] @ T[:3, :3].T - ab0[:, 3:]  # R a + t - b, as t = c_b - R c_a
    sq = np.add.reduce(diff * diff, axis=1)
    return HornResult(
        T_to_from=T, rms_mm=math.sqrt(float(np.add.reduce(sq)) / n), residuals_mm=np.sqrt(sq)
    )


def _triple_hypotheses(a: FloatArray, b: FloatArray, triples: npt.NDArray[np.intp]) -> FloatArray:
    """Residuals (m, n) of every point under the Horn fit of each triple of points (m, 3)."""
    ta, tb = a[triples], b[triples]  # (m, 3, 3): triple, point, coordinate
    ca, cb = ta.mean(axis=1), tb.mean(axis=1)
    M = (ta - ca[:, None]).transpose(0, 2, 1) @ (tb - cb[:, None])
    R = matrices_from_quats(np.linalg.eigh(_horn_matrix(M))[1][:, :, 3])
    t = cb - np.einsum("mij,mj->mi", R, ca)
    return np.linalg.norm(np.einsum("mij,nj->mni", R, a) + t[:, None] - b[None], axis=2)


#: Above this many point triples, :func:`horn_robust` tries a fixed pseudo-random sample of
#: this many instead of all (C(23, 3) = 1771 is still exhaustive).
MAX_TRIPLES = 2000


def horn_robust(
    points_from: object,
    points_to: object,
    weights: object = None,
    *,
    threshold_mm: float = 1.0,
) -> RobustHornResult:
    """:func:`horn` that finds and drops wrong correspondences.

    Every triple of points (or :data:`MAX_TRIPLES` of them) gives an exact-fit hypothesis; the
    one under which most points lie within ``threshold_mm`` wins (ties: smaller summed squared
    residual), then the fit is redone on its inliers until the inlier set is stable. Unlike
    dropping the worst residual of a fit over all points, this is not fooled when a wrong pair
    pulls the fit so that a correct point shows the largest residual, and it finds a swapped
    pair (two wrong correspondences) among 5 or more points.

    Parameters
    ----------
    threshold_mm : float
        Largest residual (mm) an inlier may have; a few times the expected 3D noise.

    Raises
    ------
    DegenerateInputError
        As :func:`horn` for the input as a whole.
    GeometryError
        Fewer than 3 correspondences agree within ``threshold_mm``, or those that agree are
        collinear.
    """
    if not threshold_mm > 0:
        raise DegenerateInputError(f"threshold_mm must be positive, got {threshold_mm}")
    a = _as_points(points_from, "points_from", 3)
    b = _as_points(points_to, "points_to", 3)
    fit = horn(a, b, weights)  # validates shapes, count, weights and spread once
    w = np.ones(a.shape[0]) if weights is None else np.asarray(weights, dtype=np.float64)
    usable = w > 0
    inliers = usable & (fit.residuals_mm <= threshold_mm)
    if inliers.sum() < usable.sum():
        candidates = np.flatnonzero(usable)
        triples = np.array(list(combinations(candidates, 3)), dtype=np.intp)
        if len(triples) > MAX_TRIPLES:
            triples = np.random.default_rng(0).choice(triples, MAX_TRIPLES, replace=False)
        res = _triple_hypotheses(a, b, triples)
        ok = (res <= threshold_mm) & usable
        sse = np.where(ok, res**2, 0.0).sum(axis=1)
        best = np.lexsort((sse, -ok.sum(axis=1)))[0]
        inliers = ok[best]
        for _ in range(10):
            if inliers.sum() < 3:
                raise GeometryError(
                    f"fewer than 3 correspondences agree within {threshold_mm} mm "
                    f"(best set: {np.flatnonzero(inliers).tolist()})"
                )
            try:
                sub = horn(a[inliers], b[inliers], w[inliers])
            except DegenerateInputError as err:
                raise GeometryError(
                    f"the correspondences that agree, {np.flatnonzero(inliers).tolist()}, "
                    f"are degenerate: {err}"
                ) from None
            T = sub.T_to_from
            residuals = np.linalg.norm(a @ T[:3, :3].T + T[:3, 3] - b, axis=1)
            fit = HornResult(T, sub.rms_mm, residuals)
            refined = usable & (residuals <= threshold_mm)
            if np.array_equal(refined, inliers):
                break
            inliers = refined
        else:
            raise GeometryError("the inlier set of the robust Horn fit did not settle")
    return RobustHornResult(
        T_to_from=fit.T_to_from,
        rms_mm=float(np.sqrt(np.mean(fit.residuals_mm[inliers] ** 2))),
        residuals_mm=fit.residuals_mm,
        inliers=inliers,
        dropped=tuple(int(i) for i in np.flatnonzero(usable & ~inliers)),
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
        The other pose of a planar target (see :func:`pnp`); None for non-planar targets and
        when both IPPE poses coincide.
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
        J = np.concatenate([J_x @ -skew(X), J_x], axis=2).reshape(2 * n, 6)
        g = J.T @ res.reshape(-1)
        H = J.T @ J
        while True:
            step = np.linalg.solve(H + mu * np.diag(np.diag(H)), -g)
            dR = matrix_from_rotvec(step[:3])
            R_new, t_new = dR @ R, dR @ t + step[3:]
            try:
                res_new = _project_errors(camera, R_new, t_new, obj, px)
            except DegenerateInputError:  # the trial step put a point behind the camera
                res_new = np.full_like(res, np.inf)
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


def _rms(res: FloatArray) -> float:
    """Root mean square of the per-point error lengths of residuals (n, 2)."""
    return float(np.sqrt((res**2).sum() / res.shape[0]))


def _same_pose(R1: FloatArray, t1: FloatArray, R2: FloatArray, t2: FloatArray) -> bool:
    """Equal to about 1e-6 (rad, relative translation): two solvers found the same pose."""
    return bool(
        np.abs(R1 - R2).max() < 1e-6 and np.linalg.norm(t1 - t2) < 1e-6 * np.linalg.norm(t1)
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
    almost as well: ``rms_alt < ambiguity_ratio * max(rms_best, noise_floor_px)``. When its
    refinement slides into the first minimum (a flat valley between the two), the unrefined
    IPPE pose stands for the alternative.
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
        Undistorting a pixel or the refinement did not converge.

    Notes
    -----
    Only planar targets are checked for a second pose. Non-planar targets of 6 or more points
    in general position have a unique pose; for 4-5 points a rare second one goes undetected.
    """
    obj = _as_points(model_points, "model_points", 3)
    px = _as_points(pixels, "pixels", 2)
    n = obj.shape[0]
    if px.shape[0] != n:
        raise DegenerateInputError(f"model_points has {n} points but pixels has {px.shape[0]}")
    if n < 4:
        raise DegenerateInputError(f"PnP needs at least 4 points, got {n}")
    centred = obj - obj.mean(axis=0)
    _check_spread((centred.T @ centred).tolist(), "model_points")
    norm = camera.undistort(px)
    norm0 = norm - norm.mean(axis=0)
    _check_spread((norm0.T @ norm0).tolist(), "pixels (undistorted)")
    obj_cv = np.ascontiguousarray(obj).reshape(-1, 1, 3)
    norm_cv = np.ascontiguousarray(norm).reshape(-1, 1, 2)
    s = np.linalg.svd(centred, compute_uv=False)
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
    behind_start = -1
    for R0, t0 in starts:
        in_front = (obj @ R0.T + t0)[:, 2] > 0
        if not in_front.all():  # not a physical solution; the other one may be
            behind_start = int(np.argmin(in_front))
            continue
        R, t, res = _refine_lm(camera, R0, t0, obj, px)
        fits.append((_rms(res), R, t, res, R0, t0))
    if not fits:
        raise DegenerateInputError(
            f"model point {behind_start} lies behind the camera in every candidate pose"
        )
    fits.sort(key=lambda f: f[0])
    rms, R, t, res = fits[0][:4]
    behind = np.flatnonzero((obj @ R.T + t)[:, 2] <= 0)
    if behind.size:
        raise DegenerateInputError(f"model point {int(behind[0])} lies behind the camera")
    alt = None
    if len(fits) > 1:
        rms_alt, R_alt, t_alt = fits[1][:3]
        if _same_pose(R_alt, t_alt, R, t):
            # Both starts slid into one minimum (a flat valley between them): the start that
            # fits worse stands for the alternative explanation.
            rms_alt, R_alt, t_alt = max(
                ((_rms(_project_errors(camera, f[4], f[5], obj, px)), f[4], f[5]) for f in fits),
                key=lambda f: f[0],
            )
        if not _same_pose(R_alt, t_alt, R, t):
            alt = (rms_alt, make_transform(R_alt, t_alt))
    ambiguous = alt is not None and alt[0] < ambiguity_ratio * max(rms, noise_floor_px)
    return PnPResult(
        T_cam_obj=make_transform(R, t),
        rms_px=rms,
        errors_px=np.linalg.norm(res, axis=1),
        ambiguous=bool(ambiguous),
        T_cam_obj_alt=None if alt is None else alt[1],
        rms_px_alt=None if alt is None else alt[0],
    )
